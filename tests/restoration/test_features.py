"""Tests of spot detection and grid correspondence on synthetic camera-s images.

Every image is drawn here from known dot positions, so the expected answers (centres, grid
indices) are facts of the drawing, not of the code under test.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from restoration.features import (
    ReferenceGrid,
    detect_spots,
    find_features,
    match_distorted,
    match_reference,
    order_violations,
    predict_flat_spots,
)
from wai_core.config import SystemConfig, load_config
from wai_core.errors import WaiInputError

SCENE = "scenes/paper.toml"
SHAPE = (600, 800)


def draw_dots(
    centres: np.ndarray, flux: np.ndarray | float, cov: np.ndarray, shape=SHAPE
) -> np.ndarray:
    """Image (h, w) of Gaussian dots of total ``flux`` and covariance ``cov`` (px^2) centred at
    ``centres`` (N, 2) ``(col, row)``; pixel integration is modelled by adding 1/12 px^2."""
    centres = np.asarray(centres, float)
    n = len(centres)
    flux = np.broadcast_to(np.asarray(flux, float), (n,))
    cov = np.broadcast_to(np.asarray(cov, float), (n, 2, 2)) + np.eye(2) / 12.0
    half = int(np.ceil(5.0 * np.sqrt(np.linalg.eigvalsh(cov)[:, 1].max()))) + 1
    off = np.arange(-half, half + 1)
    base = np.rint(centres).astype(int)
    cols = np.broadcast_to(base[:, 0, None, None] + off[None, None, :], (n, off.size, off.size))
    rows = np.broadcast_to(base[:, 1, None, None] + off[None, :, None], (n, off.size, off.size))
    inv = np.linalg.inv(cov)
    dx = cols - centres[:, 0, None, None]
    dy = rows - centres[:, 1, None, None]
    q = inv[:, 0, 0, None, None] * dx**2 + 2 * inv[:, 0, 1, None, None] * dx * dy
    q += inv[:, 1, 1, None, None] * dy**2
    norm = flux / (2 * np.pi * np.sqrt(np.linalg.det(cov)))
    val = norm[:, None, None] * np.exp(-0.5 * q)
    h, w = shape
    ok = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    return np.bincount(rows[ok] * w + cols[ok], val[ok], h * w).reshape(h, w)


def jittered_grid(spacing: float, rng: np.random.Generator, margin: float = 30.0) -> np.ndarray:
    """Dot centres (N, 2) on a square grid with uniform sub-pixel jitter."""
    g = np.mgrid[margin : SHAPE[0] - margin : spacing, margin : SHAPE[1] - margin : spacing]
    c = g.reshape(2, -1).T[:, ::-1].astype(float)
    return c + rng.uniform(-0.5, 0.5, c.shape)


def nearest(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Distance from each true centre to the nearest found one, px."""
    return cKDTree(found).query(truth)[0]


@pytest.fixture(scope="module")
def cfg() -> SystemConfig:
    return load_config(SCENE)


@pytest.fixture(scope="module")
def flat_scene(cfg):
    """Predicted flat-water spots and each dot's spot covariance (from the local Jacobian of the
    panel -> camera map and the panel sigma), for drawing realistic camera-s images."""
    ij, panel, spot, in_view = predict_flat_spots(cfg)
    side = int(round(np.sqrt(len(ij))))
    grid = spot.reshape(side, side, 2)  # dot_grid is laid out row by row
    d = cfg.pattern.spacing_px
    jac = np.stack([np.gradient(grid, axis=1), np.gradient(grid, axis=0)], axis=-1) / d
    jac = jac.reshape(-1, 2, 2)
    cov = cfg.pattern.sigma_px**2 * jac @ jac.transpose(0, 2, 1)
    drawable = np.isfinite(spot).all(axis=1) & (np.abs(spot) < 3000).all(axis=1)
    return ij, panel, spot, in_view, cov, drawable


def pattern_image(flat_scene, pos: np.ndarray, flux: np.ndarray, rng=None) -> np.ndarray:
    """Camera-s image (h, w, 3) of the dots at ``pos``, drawn only where the flat-water spot is
    on the diffuser, in the pattern's blue-green."""
    ij, _, _, in_view, cov, drawable = flat_scene
    sel = drawable & in_view
    img = draw_dots(pos[sel], flux[sel], cov[sel])
    if rng is not None:
        img = rng.poisson(img * 4.0) / 4.0
    return (img[..., None] * np.array([0.0, 0.75, 1.0])).astype(np.float32)


# ------------------------------------------------------------------------------------------
# Detection
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "sigma, elong, dim", [(0.8, 1.0, 0.05), (1.5, 1.0, 0.01), (3.0, 1.0, 0.01), (2.0, 2.5, 0.02)]
)
def test_centroids_without_noise_within_0p05_px(sigma, elong, dim):
    rng = np.random.default_rng(1)
    c = jittered_grid(9.5 * sigma * elong, rng)
    angle = rng.uniform(0, np.pi, len(c))  # elongated spots at any orientation
    rot = np.stack([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]).T
    cov = rot @ np.diag([(sigma * elong) ** 2, sigma**2]) @ rot.transpose(0, 2, 1)
    flux = np.where(rng.random(len(c)) < 0.3, dim, 1.0) * 1000.0  # 20-100x dimmer dots mixed in
    spots = detect_spots(draw_dots(c, flux, cov))
    assert len(spots) == len(c)
    assert nearest(spots.centres_px, c).max() < 0.05
    assert not spots.merged.any()


def test_centroids_with_poisson_noise_near_the_photon_limit():
    # N photons of a Gaussian spot of standard deviation s: no unbiased estimator beats
    # s / sqrt(N) per axis (Cramer-Rao, Poisson noise, no background). The windowed centroid's
    # theory is ~1.1x that; allow 1.35x (the sample rms over ~700 spots is good to ~4 %).
    rng = np.random.default_rng(2)
    sigma, photons = 1.5, 2000.0
    c = jittered_grid(14.0, rng)
    img = rng.poisson(draw_dots(c, photons, sigma**2 * np.eye(2))).astype(np.float32)
    spots = detect_spots(img)
    err = nearest(spots.centres_px, c)
    limit_2d = np.sqrt(2.0) * np.sqrt(sigma**2 + 1 / 12) / np.sqrt(photons)
    assert len(spots) == len(c)
    assert np.sqrt(np.mean(err**2)) < 1.35 * limit_2d


def test_dim_dots_beside_100x_brighter_ones_are_found():
    rng = np.random.default_rng(3)
    c = jittered_grid(10.0, rng)
    checker = ((np.rint(c[:, 0] / 10) + np.rint(c[:, 1] / 10)) % 2).astype(bool)
    flux = np.where(checker, 10.0, 1000.0)
    spots = detect_spots(draw_dots(c, flux, 1.0 * np.eye(2)))
    err = nearest(spots.centres_px, c)
    assert len(spots) == len(c)
    assert err[checker].max() < 0.05


def test_two_dots_run_together_are_flagged_merged():
    rng = np.random.default_rng(4)
    singles = jittered_grid(60.0, rng, margin=60)
    sigma = 2.0
    pair = singles[:10] + np.array([[3.5 * sigma, 0.0]])  # 3.5 sigma from the first ten
    spots = detect_spots(draw_dots(np.vstack([singles, pair]), 1000.0, sigma**2 * np.eye(2)))
    mid = singles[:10] + np.array([[1.75 * sigma, 0.0]])
    merged_at = spots.centres_px[spots.merged]
    assert len(merged_at) == 10
    assert nearest(merged_at, mid).max() < 0.5


def test_bad_images_raise():
    img = np.zeros(SHAPE, np.float32)
    img[10, 10] = np.nan
    with pytest.raises(WaiInputError, match="NaN"):
        detect_spots(img)
    with pytest.raises(WaiInputError, match="shape"):
        detect_spots(np.zeros((4, 5, 6, 7)))
    assert len(detect_spots(np.zeros(SHAPE))) == 0  # nothing there is not an error


# ------------------------------------------------------------------------------------------
# Flat-water prediction
# ------------------------------------------------------------------------------------------


def test_flat_prediction_is_a_plane_projective_map(cfg):
    # Panel -> water plane -> mirror -> diffuser plane -> camera s: a homography, so grid lines
    # stay straight and a single 3x3 matrix reproduces every spot.
    ij, panel, spot, in_view = predict_flat_spots(cfg)
    assert in_view.sum() > 300
    p, s = panel[in_view], spot[in_view]
    hom, _ = cv2.findHomography(p, s, 0)
    back = cv2.perspectiveTransform(p[None], hom)[0]
    assert np.abs(back - s).max() < 1e-4  # float rounding of the fit; spots err by ~0.1 px
    for j in np.unique(ij[in_view, 1]):
        row = spot[in_view & (ij[:, 1] == j)]
        if len(row) >= 3:  # collinear: the smallest singular value of the centred points is 0
            assert np.linalg.svd(row - row.mean(axis=0), compute_uv=False)[-1] < 1e-6


def test_flat_image_matches_every_seen_dot_with_no_rejection(cfg, flat_scene):
    ij, _, spot, in_view, _, _ = flat_scene
    flux = np.full(len(ij), 3000.0)
    img = pattern_image(flat_scene, spot, flux)
    m = find_features(img, img, cfg)
    c = m.counts
    assert c["reference"] > 300
    assert c["matched"] >= c["reference"]
    assert c["rejected_order"] == c["rejected_merged"] == c["rejected_ambiguous"] == 0
    assert c["unmatched_reference"] == 0
    # Labels are right: each matched spot sits at its own dot's predicted position.
    look = {tuple(k): p for k, p in zip(ij.tolist(), spot, strict=True)}
    truth = np.array([look[tuple(k)] for k in m.ij.tolist()])
    assert np.abs(m.spot_px - truth).max() < 0.05
    assert set(m.timings_ms) >= {"reference", "detect", "match", "total"}


# ------------------------------------------------------------------------------------------
# Wavy-water correspondence
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def reference(cfg, flat_scene):
    ij, panel, spot, in_view, _, _ = flat_scene
    img = pattern_image(flat_scene, spot, np.full(len(ij), 3000.0))
    return match_reference(detect_spots(img), (ij, panel, spot, in_view))


def spacing_of(flat_scene) -> np.ndarray:
    """Local flat spot spacing (K,): distance to the nearest grid neighbour, px."""
    ij, _, spot, _, _, _ = flat_scene
    side = int(round(np.sqrt(len(ij))))
    g = spot.reshape(side, side, 2)
    dist = np.full((side, side, 4), np.inf)
    dist[:, :-1, 0] = np.linalg.norm(np.diff(g, axis=1), axis=2)
    dist[:, 1:, 1] = dist[:, :-1, 0]
    dist[:-1, :, 2] = np.linalg.norm(np.diff(g, axis=0), axis=2)
    dist[1:, :, 3] = dist[:-1, :, 2]
    return dist.min(axis=2).ravel()


def labels_correct(m, ij, pos) -> np.ndarray:
    """For each kept match: is its spot the true spot of its labelled dot?"""
    look = {tuple(k): p for k, p in zip(ij.tolist(), pos, strict=True)}
    truth = np.array([look[tuple(k)] for k in m.ij.tolist()])
    return np.linalg.norm(m.spot_px - truth, axis=1) < 1.0


def test_smooth_displacement_is_matched_without_error(flat_scene, reference):
    ij, _, spot, _, _, _ = flat_scene
    rng = np.random.default_rng(5)
    # A 0.4-spacing sinusoid, 10 grid spacings long, oblique to both grid axes.
    phase = 2 * np.pi * (ij[:, 0] / 10.0 + ij[:, 1] / 13.0)
    u = 0.4 * spacing_of(flat_scene)[:, None] * np.stack([np.sin(phase), np.cos(0.7 * phase)], 1)
    pos = spot + u
    flux = np.where(rng.random(len(ij)) < 0.3, 0.05, 1.0) * 3000.0  # 20x dimmer dots too
    spots = detect_spots(pattern_image(flat_scene, pos, flux, rng))
    m = match_distorted(reference, spots)
    assert labels_correct(m, ij, pos).all()
    assert m.counts["matched"] >= 0.97 * m.counts["reference"]


def test_merged_blob_is_dropped_and_counted(flat_scene, reference):
    ij, _, spot, _, cov, _ = flat_scene
    # Dot a moves onto its i-neighbour b, stopping 3.5 sigma short: one blob.
    a = int(np.flatnonzero((ij == [0, 0]).all(1))[0])
    b = int(np.flatnonzero((ij == [1, 0]).all(1))[0])
    pos = spot.copy()
    step = (spot[b] - spot[a]) / np.linalg.norm(spot[b] - spot[a])
    sigma_along = np.sqrt(step @ cov[a] @ step)
    pos[a] = spot[b] - 3.5 * sigma_along * step
    spots = detect_spots(pattern_image(flat_scene, pos, np.full(len(ij), 3000.0)))
    assert spots.merged.sum() == 1
    m = match_distorted(reference, spots)
    kept = {tuple(k) for k in m.ij.tolist()}
    assert (0, 0) not in kept and (1, 0) not in kept
    assert m.counts["rejected_merged"] >= 1
    assert labels_correct(m, ij, pos).all()


def test_order_violations_flag_a_swapped_pair():
    jj, ii = np.mgrid[0:5, 0:6]
    ij = np.stack([ii.ravel(), jj.ravel()], 1)
    ref = ij * 20.0 + 100.0
    spot = ref.copy()
    assert not order_violations(ij, ref, spot).any()
    a, b = 14, 15  # (2, 2) and (3, 2): neighbours along a row
    spot[[a, b]] = spot[[b, a]] + np.array([[2.0, 1.0], [-2.0, 0.5]])
    bad = order_violations(ij, ref, spot)
    assert set(np.flatnonzero(bad)) == {a, b}
    # A spot skipped between two matched neighbours also breaks the ordering.
    extra = 0.5 * (spot[20] + spot[21])
    bad = order_violations(ij, ref, ref, all_spots_px=np.vstack([ref, extra]))
    assert set(np.flatnonzero(bad)) == {20, 21}


def test_crossed_pair_never_gives_a_wrong_label(flat_scene, reference):
    ij, _, spot, _, _, _ = flat_scene
    a = int(np.flatnonzero((ij == [0, 2]).all(1))[0])
    b = int(np.flatnonzero((ij == [1, 2]).all(1))[0])
    pos = spot.copy()
    pos[a] = spot[a] + 0.6 * (spot[b] - spot[a])  # the two dots cross over
    pos[b] = spot[a] + 0.4 * (spot[b] - spot[a])
    spots = detect_spots(pattern_image(flat_scene, pos, np.full(len(ij), 3000.0)))
    m = match_distorted(reference, spots)
    assert labels_correct(m, ij, pos).all()
    kept = {tuple(k) for k in m.ij.tolist()}
    assert (0, 2) not in kept and (1, 2) not in kept


def test_shifted_pattern_is_anchored_by_unlit_marker_dots():
    # Spots moved by whole spacings fool any proximity labelling; dots left dark in a known
    # asymmetric pattern pin the lattice shift.
    rng = np.random.default_rng(6)
    sp = 22.0
    jj, ii = np.mgrid[-12:13, -17:18]
    ij = np.stack([ii.ravel(), jj.ravel()], 1)
    px = np.stack([399.5 + ij[:, 0] * sp, 299.5 + ij[:, 1] * sp], 1)
    in_view = ((px > 10) & (px < np.array(SHAPE[::-1]) - 10)).all(axis=1)
    holes = np.array([[0, 0], [1, 0], [0, 1], [5, -4], [6, -4], [5, -3]])
    lit = ~(ij[:, None, :] == holes[None]).all(axis=2).any(axis=1)
    cov = (sp / 9.3) ** 2 * np.eye(2)
    flat = draw_dots(px[lit], 3000.0, cov)
    ref = match_reference(detect_spots(flat), (ij, px, px, in_view), lit=lit)
    assert isinstance(ref, ReferenceGrid)
    u = 0.25 * sp * np.stack([np.sin(ij[:, 1] / 5.0), np.cos(ij[:, 0] / 6.0)], 1)
    pos = px + np.array([2, 1]) * sp + u
    spots = detect_spots(rng.poisson(draw_dots(pos[lit], 3000.0, cov)).astype(np.float32))
    m = match_distorted(ref, spots)
    assert (m.counts["anchor_di"], m.counts["anchor_dj"]) == (-2, -1)
    assert m.counts["anchor_candidates"] == 1
    assert labels_correct(m, ij, pos).all()
    seen = lit & ((pos > 15) & (pos < np.array(SHAPE[::-1]) - 15)).all(axis=1)
    assert len(m) > 0.9 * seen.sum()


def test_too_few_features_raise(cfg, flat_scene):
    ij, _, spot, in_view, _, _ = flat_scene
    flux = np.zeros(len(ij))
    flux[np.flatnonzero(in_view)[:5]] = 3000.0
    img = pattern_image(flat_scene, spot, flux)
    with pytest.raises(WaiInputError, match="too few"):
        find_features(img, img, cfg)
    with pytest.raises(WaiInputError, match="NaN"):
        bad = img.copy()
        bad[0, 0, 0] = np.nan
        find_features(bad, img, cfg)
    with pytest.raises(WaiInputError, match="camera s"):
        find_features(img[:100], img, cfg)
