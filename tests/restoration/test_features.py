"""Tests of spot detection and grid correspondence on synthetic camera-s images.

Every image is drawn here from known dot positions, so the expected answers (centres, grid
indices) are facts of the drawing, not of the code under test.
"""

from __future__ import annotations

import dataclasses
import pickle

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from restoration import features
from restoration.features import (
    ReferenceGrid,
    SpotScales,
    detect_spots,
    find_features,
    match_distorted,
    match_reference,
    order_violations,
    predict_flat_spots,
)
from restoration.features._lattice import _LatticeTables
from restoration.features._segments import _segment, _split_joined
from restoration.features.detect import _background, _minimum_bias, _noise_sigma
from restoration.features.match import _choose_seed
from restoration.features.ordering import _anchor_shift, _braced_piece, _SpotLookup
from wai_core.config import SystemConfig, load_config
from wai_core.errors import RestorationFailed, WaiInputError

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


@pytest.mark.parametrize("read_noise, found", [(0.03, 1.0), (0.1, 0.99)])
def test_read_noise_does_not_swallow_the_dots(read_noise, found):
    # Gaussian read noise (a fraction of the peak) on a sparse background: a local-minimum
    # background sits ~3 sigma below the noise's mean, and uncorrected it lifts every pixel
    # above the detection floor (the image became one blob). Every dot must still be found.
    rng = np.random.default_rng(3)
    c = jittered_grid(16.0, rng)
    cov = np.broadcast_to(np.diag([2.0**2, 1.5**2]), (len(c), 2, 2))
    img = draw_dots(c, np.full(len(c), 1000.0), cov)
    img = img + rng.normal(0.0, read_noise * img.max(), img.shape)
    spots = detect_spots(img.astype(np.float32))
    on_a_dot = nearest(c, spots.centres_px) < 0.5  # per detection
    assert len(spots) <= len(c)
    assert on_a_dot.sum() >= found * len(c)


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


def test_spots_on_a_shared_pedestal_are_split_at_their_saddles():
    """A rough surface spreads part of each spot's light over a halo; on a dense lattice the
    halos join spots into segments of many. Split at their saddles, the spots come back, each
    centre near its dot (the halo is centred on it)."""
    rng = np.random.default_rng(21)
    c = jittered_grid(9.0, rng, margin=40)
    sharp = draw_dots(c, 1000.0, 2.0 * np.eye(2))
    halo = draw_dots(c, 1000.0, 16.0 * np.eye(2))  # half the light in a 4 px halo
    img = (sharp + halo + rng.normal(0.0, 0.05, sharp.shape)).astype(np.float32)
    plain = SpotScales.of(features.detect._TUNED_SIGMA_PX)
    near_plain = np.mean(nearest(detect_spots(img, scales=plain).centres_px, c) < 0.5)
    split = detect_spots(img, scales=plain.joined())
    near_split = np.mean(nearest(split.centres_px, c) < 0.5)
    assert split.joined > 5
    assert near_plain < 0.95 < 0.97 < near_split
    assert len(split) <= 1.01 * len(c)  # no spot cut in two


def test_a_joined_segment_splits_into_its_two_spots():
    """Two spots whose saddle stays above the threshold make one segment; the split gives each
    its own label, the watershed line between them."""
    c = np.array([[40.0, 40.0], [47.0, 40.0]])
    img = draw_dots(c, 1000.0, 4.0 * np.eye(2), shape=(80, 90)).astype(np.float32)
    labels = (img > 0.02 * img.max()).astype(np.int32)
    n, split = _split_joined(img, labels, 2, area_px=20)
    assert (n, split) == (3, 1)
    cols = np.arange(90)[None, :]
    for lab, col in ((1, 40.0), (2, 47.0)):
        w = np.where(labels == lab, img, 0.0)
        assert abs((w * cols).sum() / w.sum() - col) < 1.0  # each part around its own dot
    assert np.array_equal(np.unique(labels), [0, 1, 2])


def test_dim_spots_on_a_bright_spots_ridge_are_split_by_their_own_saddles():
    """Rough water smears a row of spots into one ridge whose brightness falls along it: each
    spot's saddle to the next is a share of its own peak, not of the ridge's brightest (a
    saddle 0.1 of the brightest spot's peak below a dim spot is most of that spot's)."""
    c = np.array([[20.0 + 9.0 * k, 30.0] for k in range(6)])
    flux = 1000.0 * 0.45 ** np.arange(6)  # each spot under half its brighter neighbour
    img = draw_dots(c, flux, np.diag([5.0, 3.0]), shape=(60, 90)).astype(np.float32)
    labels = (img > 1e-4 * img.max()).astype(np.int32)
    assert labels.sum() > 20 and np.unique(labels).size == 2  # one segment holds them all
    n, split = _split_joined(img, labels, 2, area_px=20)
    assert (n, split) == (7, 1)
    cols = np.arange(90)[None, :]
    means = sorted((np.where(labels == lab, img, 0.0) * cols).sum()
                   / np.where(labels == lab, img, 0.0).sum() for lab in range(1, 7))
    assert np.abs(np.array(means) - c[:, 0]).max() < 2.0  # each part around its own dot


def reference_detect(image: np.ndarray) -> dict[str, np.ndarray]:
    """:func:`detect_spots` (default parameters) written plainly: a loop over segments, float64,
    each spot's centroid window evaluated pixel by pixel over its box. Only the image-level
    segmentation (noise, background, labelling) is shared with the module."""
    lum = np.asarray(image, np.float64)
    lum = (lum[..., :3].sum(axis=2) if lum.ndim == 3 else lum).astype(np.float32)
    smooth = cv2.GaussianBlur(lum, (0, 0), 1.0, borderType=cv2.BORDER_REFLECT)
    noise = _noise_sigma(lum, smooth, 1.0)
    bg = _background(smooth, 25)
    lifted = float(np.percentile(smooth[::4, ::4] - bg[::4, ::4], 25.0))
    bg += min(noise * _minimum_bias(1.0, 25), max(lifted, 0.0))
    smooth, raw = smooth - bg, (lum - bg).astype(np.float64)
    tiny = 1e-6 * max(float(smooth.max()), 1e-30)
    n, _, labels, _ = _segment(smooth, 3, 0.25, max(2.0 * noise, tiny), np.empty_like(smooth))
    h, w = labels.shape
    seg = []
    for k in range(1, n):
        r, c = np.nonzero(labels == k)
        s = smooth[r, c].astype(np.float64)
        wt = np.clip(s, 0.0, None)
        mean = np.array([wt @ c, wt @ r]) / wt.sum() if wt.sum() > 0 else np.zeros(2)
        d = np.stack([c - mean[0], r - mean[1]])
        cov = (wt * d) @ d.T / max(wt.sum(), 1e-300)
        # Kurtosis along the major axis of the part above 0.2 x peak.
        w2 = np.clip(s - 0.2 * s.max(), 0.0, None)
        m2c = np.array([w2 @ c, w2 @ r]) / w2.sum()
        d2 = np.stack([c - m2c[0], r - m2c[1]])
        c2 = (w2 * d2) @ d2.T / w2.sum()
        angle = 0.5 * np.arctan2(2 * c2[0, 1], c2[0, 0] - c2[1, 1])
        t = np.cos(angle) * d2[0] + np.sin(angle) * d2[1]
        with np.errstate(divide="ignore", invalid="ignore"):
            kurt = (w2 @ t**4) * w2.sum() / (w2 @ t**2) ** 2
        seg.append(dict(
            label=k, tot=wt.sum(), mean=mean, cov=cov, peak=s.max(), flux=raw[r, c].sum(),
            area=len(r), kurt=kurt if np.isfinite(kurt) else 3.0,
            border=bool(r.min() == 0 or c.min() == 0 or r.max() == h - 1 or c.max() == w - 1),
        ))
    good = [g for g in seg if g["peak"] > max(6.0 * noise, tiny) and g["area"] >= 3
            and g["tot"] > 0]
    flux = np.sort([g["flux"] for g in good])
    typical = flux[np.searchsorted(np.cumsum(flux), 0.5 * flux.sum())]
    kept = [g for g in good if g["flux"] > 5e-3 * typical]
    own = np.zeros(n, np.int64)  # label -> itself if kept, else 0 (background)
    own[[g["label"] for g in kept]] = [g["label"] for g in kept]
    owner = own[labels]
    out = {k: [] for k in ("centres_px", "cov_px2", "merged", "border", "flux", "area_px")}
    for g in kept:
        evals, evecs = np.linalg.eigh(g["cov"])
        cov = evecs @ np.diag(np.clip(evals, 0.09, None)) @ evecs.T
        half = np.clip(np.ceil(3.5 * np.sqrt(np.diag(cov)) + 1.0), 3, 48)
        hx, hy = (3 * np.ceil(half / 3)).astype(int)
        bx, by = np.rint(g["mean"]).astype(int)
        rr, cc = np.mgrid[by - hy : by + hy + 1, bx - hx : bx + hx + 1]
        inside = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
        rr, cc = rr[inside], cc[inside]
        vals = np.where(np.isin(owner[rr, cc], [0, g["label"]]), raw[rr, cc], 0.0)
        inv = np.linalg.inv(2.5 * cov)
        x = g["mean"].copy()
        for _ in range(2):
            d = np.stack([cc - x[0], rr - x[1]])
            wv = vals * np.exp(-0.5 * np.einsum("ip,ij,jp->p", d, inv, d))
            if wv.sum() > 0:
                step = (1.0 + 1.0 / (0.7 * 2.5)) * (d @ wv) / wv.sum()
                x += np.clip(step, -1.0, 1.0)
        out["centres_px"].append(x)
        out["cov_px2"].append(cov)
        out["merged"].append(g["kurt"] < 2.15 and np.linalg.eigvalsh(g["cov"])[1] >= 1.3**2)
        out["border"].append(g["border"])
        out["flux"].append(g["flux"])
        out["area_px"].append(g["area"])
    return {k: np.array(v) for k, v in out.items()}


def test_detection_matches_a_plain_per_spot_implementation():
    # Round, elongated, dim, merged, border-cut and noise-only spots on a small noisy image.
    rng = np.random.default_rng(7)
    shape = (180, 260)
    c = np.stack(np.meshgrid(np.arange(8, 260, 17.0), np.arange(6, 180, 15.0)), -1).reshape(-1, 2)
    c += rng.uniform(-0.5, 0.5, c.shape)
    angle = rng.uniform(0, np.pi, len(c))
    rot = np.stack([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]).T
    sd = np.where(rng.random((len(c), 1)) < 0.25, [3.5, 1.2], [1.6, 1.4])
    cov = rot @ (sd[:, :, None] * np.eye(2) * sd[:, None, :]) @ rot.transpose(0, 2, 1)
    flux = np.where(rng.random(len(c)) < 0.3, 40.0, 2000.0)
    pair = np.array([[100.2, 91.4], [107.3, 91.9]])  # two dots 3.5 sigma apart: one blob
    img = draw_dots(np.vstack([c, pair]), np.r_[flux, 2000.0, 2000.0],
                    np.vstack([cov, np.broadcast_to(4.0 * np.eye(2), (2, 2, 2))]), shape)
    img = rng.poisson(img + 0.5).astype(np.float32)
    spots = detect_spots(img)
    ref = reference_detect(img)
    assert len(spots) == len(ref["centres_px"]) > 100
    assert np.abs(spots.centres_px - ref["centres_px"]).max() < 1e-4
    assert np.abs(spots.cov_px2 - ref["cov_px2"]).max() < 1e-8
    assert np.allclose(spots.flux, ref["flux"], rtol=1e-9, atol=1e-6)
    assert (spots.area_px == ref["area_px"]).all()
    assert (spots.border == ref["border"]).all() and spots.border.any()
    assert (spots.merged == ref["merged"]).all() and spots.merged.any()


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


def marked_lattice(sp: float, nj: int, ni: int, holes: list[list[int]]):
    """A square lattice of spacing ``sp`` px, nodes i in -ni..ni and j in -nj..nj, centred in
    the image, its dots lit but at ``holes`` (marker dots left dark), and its flat-water
    reference: ``(ij, px, lit, cov, ref)``."""
    jj, ii = np.mgrid[-nj:nj + 1, -ni:ni + 1]
    ij = np.stack([ii.ravel(), jj.ravel()], 1)
    px = np.stack([399.5 + ij[:, 0] * sp, 299.5 + ij[:, 1] * sp], 1)
    in_view = ((px > 10) & (px < np.array(SHAPE[::-1]) - 10)).all(axis=1)
    lit = ~(ij[:, None, :] == np.array(holes)[None]).all(axis=2).any(axis=1)
    cov = (sp / 9.3) ** 2 * np.eye(2)
    ref = match_reference(detect_spots(draw_dots(px[lit], 3000.0, cov)), (ij, px, px, in_view),
                          lit=lit)
    return ij, px, lit, cov, ref


def test_a_lattice_stretched_far_past_flat_waters_spacing_is_grown_across_its_lines():
    # Waves that magnify the pattern 1.8x along x (or a port's denser dots) put each column's
    # neighbour 0.8 spacings from where one flat-water step predicts it: growing stalls on one
    # column. The first spot along each step from a matched neighbour carries it across, and
    # the unlit marker dots still pin the labels.
    rng = np.random.default_rng(11)
    sp = 16.0
    holes = [[0, 0], [1, 0], [0, 1], [4, -3], [5, -3], [4, -2], [-6, 4], [-6, 5]]
    ij, px, lit, cov, ref = marked_lattice(sp, 10, 22, holes)
    pos = px.copy()
    pos[:, 0] = 399.5 + 1.8 * sp * (ij[:, 0] + 0.3) + 2.0 * np.sin(ij[:, 1] / 4.0)
    pos[:, 1] += 0.2 * sp * np.cos(ij[:, 0] / 5.0)
    spots = detect_spots(rng.poisson(draw_dots(pos[lit], 3000.0, cov)).astype(np.float32))
    seen = lit & ((pos > 15) & (pos < np.array(SHAPE[::-1]) - 15)).all(axis=1)
    m = match_distorted(ref, spots)
    assert m.counts["regrown"] == 2  # the lines' steps, after two growings that stalled
    assert m.counts["anchor_candidates"] == 1 and m.counts["labels_ambiguous"] == 0
    assert labels_correct(m, ij, pos).all()
    assert len(m) > 0.9 * seen.sum()


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
    ij, px, lit, cov, ref = marked_lattice(sp, 12, 17, [[0, 0], [1, 0], [0, 1], [5, -4],
                                                        [6, -4], [5, -3]])
    assert isinstance(ref, ReferenceGrid)
    u = 0.25 * sp * np.stack([np.sin(ij[:, 1] / 5.0), np.cos(ij[:, 0] / 6.0)], 1)
    pos = px + np.array([2, 1]) * sp + u
    spots = detect_spots(rng.poisson(draw_dots(pos[lit], 3000.0, cov)).astype(np.float32))
    m = match_distorted(ref, spots)
    assert (m.counts["anchor_di"], m.counts["anchor_dj"]) == (-2, -1)
    assert m.counts["anchor_candidates"] == 1 and m.counts["labels_ambiguous"] == 0
    assert labels_correct(m, ij, pos).all()
    seen = lit & ((pos > 15) & (pos < np.array(SHAPE[::-1]) - 15)).all(axis=1)
    assert len(m) > 0.9 * seen.sum()


def test_faint_light_in_the_marker_dots_places_does_not_hide_them():
    # Rough water scatters a few per cent of the neighbours' light into an unlit marker dot's
    # place (1-4 % at GGX alpha 0.01), where the detector, which keeps spots 200x dimmer than
    # the bright ones, finds a faint spot. The pattern is wider than the view, so only the
    # markers can pin the lattice shift: counted as lit dots, the faint spots hide them and
    # every shift ties (the labels are then all wrong); counted as the dark they are, the
    # markers pin it.
    rng = np.random.default_rng(6)
    sp = 22.0
    ij, px, lit, cov, ref = marked_lattice(sp, 20, 25, [[0, 0], [1, 0], [0, 1], [5, -4],
                                                        [6, -4], [5, -3]])
    u = 0.25 * sp * np.stack([np.sin(ij[:, 1] / 5.0), np.cos(ij[:, 0] / 6.0)], 1)
    pos = px + np.array([2, 1]) * sp + u
    image = draw_dots(pos[lit], 3000.0, cov) + draw_dots(pos[~lit], 0.03 * 3000.0, cov)
    spots = detect_spots(rng.poisson(image).astype(np.float32))
    assert (cKDTree(spots.centres_px).query(pos[~lit])[0] < 1.0).sum() == (~lit).sum()
    m = match_distorted(ref, spots)
    assert (m.counts["anchor_di"], m.counts["anchor_dj"]) == (-2, -1)
    assert m.counts["anchor_candidates"] == 1
    assert labels_correct(m, ij, pos).all()
    assert len(m) > 900


def test_behind_a_projector_port_the_lattice_runs_on_past_the_grid_without_a_kink(cfg):
    """A flat port bends each dot's ray smoothly, so a lattice line's spacing changes smoothly
    past the grid's last dot too. A homography fitted to the grid cannot follow the port's
    bending at the edge: its first virtual node sits out of line (the kink that sent the
    labelling of wavy frames one column astray). Placed through the rig's own path
    (``node_flat_px``), the virtual nodes continue each line: the second difference across
    the edge is as small as inside the grid."""
    import functools

    from restoration.features import node_flat_px
    from wai_core.config import with_keys

    ported = with_keys(cfg, {"projector.port_thickness_mm": 5.0, "projector.port_gap_mm": 5.0})
    predicted = predict_flat_spots(ported)
    ij, _, px, in_view = predicted
    assert np.allclose(node_flat_px(ported, ij)[in_view], px[in_view], atol=1e-9)
    flat = draw_dots(px[in_view], 3000.0, 1.5**2 * np.eye(2))
    spots = detect_spots(flat)
    edge = int(ij[:, 0].min())

    def bend(ref, i):  # |second difference| about column i, per row in view at the edge, px
        at = {tuple(k): p for k, p in zip(ref.ij.tolist(), ref.ref_px, strict=True)}
        rows = np.unique(ij[in_view & (ij[:, 0] == edge), 1])
        return np.array([np.linalg.norm(at[i - 1, j] - 2 * at[i, j] + at[i + 1, j])
                         for j in rows])

    def kink(ref):  # across the grid's left edge
        return bend(ref, edge)

    def inside(ref):  # the same one column in, within the grid
        return bend(ref, edge + 1)

    fitted = match_reference(spots, predicted)
    placed = match_reference(spots, predicted, node_px=functools.partial(node_flat_px, ported))
    assert len(kink(placed)) > 10
    assert np.median(kink(fitted)) > 1.0  # the homography's kink
    assert np.max(kink(placed)) < np.max(inside(placed)) + 0.1


def test_anchor_shift_counts_equal_a_lookup_per_shift():
    # The correlation that scores all lattice shifts at once against the plain count.
    rng = np.random.default_rng(8)
    jj, ii = np.mgrid[-9:10, -12:13]
    ij = np.stack([ii.ravel(), jj.ravel()], 1)
    lit = rng.random(len(ij)) < 0.9
    tab = _LatticeTables.of(ij, lit)
    matched = rng.random(len(ij)) < 0.5
    absent = ~matched & (rng.random(len(ij)) < 0.3)
    shift, tied = _anchor_shift(tab, matched, absent, 4)
    r = np.arange(-4, 5)
    shifts = np.stack(np.meshgrid(r, r, indexing="ij"), -1).reshape(-1, 2)
    lookup = {tuple(k): bool(v) for k, v in zip(ij.tolist(), lit, strict=True)}

    def lit_count(nodes, d):
        return sum(lookup.get((i + d[0], j + d[1]), False) for i, j in ij[nodes].tolist())

    cost = np.array([3 * (matched.sum() - lit_count(matched, d)) + lit_count(absent, d)
                     for d in shifts])
    best = cost.min()
    ties = cost <= best + 3 + best // 4
    assert len(tied) == ties.sum()
    assert {tuple(t) for t in tied.tolist()} == {tuple(t) for t in shifts[ties].tolist()}
    if ties[(shifts == 0).all(1)].any():
        assert (shift == 0).all()
    else:
        cand = np.flatnonzero(ties)
        assert (shift == shifts[cand[np.argmin(np.abs(shifts[cand]).sum(1))]]).all()


def test_shift_without_markers_or_visible_edge_is_flagged_ambiguous():
    # All dots lit and the pattern wider than the view: nothing pins a whole-spacing shift.
    sp = 22.0
    jj, ii = np.mgrid[-20:21, -25:26]
    ij = np.stack([ii.ravel(), jj.ravel()], 1)
    px = np.stack([399.5 + ij[:, 0] * sp, 299.5 + ij[:, 1] * sp], 1)
    in_view = ((px > 10) & (px < np.array(SHAPE[::-1]) - 10)).all(axis=1)
    cov = (sp / 9.3) ** 2 * np.eye(2)
    ref = match_reference(detect_spots(draw_dots(px, 3000.0, cov)), (ij, px, px, in_view))
    spots = detect_spots(draw_dots(px + np.array([2, 1]) * sp, 3000.0, cov))
    m = match_distorted(ref, spots)
    assert m.counts["anchor_candidates"] > 1 and m.counts["labels_ambiguous"] == 1


def test_too_few_features_raise(cfg, flat_scene):
    ij, _, spot, in_view, _, _ = flat_scene
    flux = np.zeros(len(ij))
    flux[np.flatnonzero(in_view)[:5]] = 3000.0
    img = pattern_image(flat_scene, spot, flux)
    with pytest.raises(RestorationFailed, match="too few"):
        find_features(img, img, cfg)
    with pytest.raises(WaiInputError, match="NaN"):
        bad = img.copy()
        bad[0, 0, 0] = np.nan
        find_features(bad, img, cfg)
    with pytest.raises(WaiInputError, match="camera s"):
        find_features(img[:100], img, cfg)


def test_a_second_seed_avoids_the_first_piece(flat_scene, reference):
    # After a growth stops at a fold, the retry must start elsewhere: the seed chooser honours
    # an exclusion mask (the first piece and its neighbours).
    ij, _, spot, _, _, _ = flat_scene
    spots = detect_spots(pattern_image(flat_scene, spot, np.full(len(ij), 3000.0)))
    tab, lookup = reference.tables, _SpotLookup(spots.centres_px)
    args = (tab, reference.ref_px, reference, spots, lookup, 0.35, 0.6)
    first = _choose_seed(*args)
    assert first >= 0
    exclude = np.zeros(len(reference.ij), bool)
    exclude[reference.ij[:, 0] >= reference.ij[first, 0] - 2] = True  # a half-plane around it
    second = _choose_seed(*args, exclude)
    assert second >= 0 and not exclude[second]
    assert _choose_seed(*args, np.ones(len(reference.ij), bool)) == -1


def test_spot_lookup_finds_the_nearest_two_within_each_bound():
    # Against brute force: nearest and second-nearest distance and the nearest's index, only
    # spots closer than each query's own bound counted (inf, and index P - 1, where none).
    rng = np.random.default_rng(5)
    xy = rng.uniform(0.0, 200.0, (300, 2))
    pts = np.vstack([rng.uniform(-20.0, 220.0, (200, 2)), [[np.nan, 1.0]]])
    bound = rng.uniform(0.5, 30.0, len(pts))
    d1, i1, d2 = _SpotLookup(xy).nearest(pts, bound)
    dist = np.hypot(*(pts[:, None, :] - xy[None]).transpose(2, 0, 1))
    dist = np.where(dist < bound[:, None], dist, np.inf)
    order = np.sort(dist, axis=1)
    np.testing.assert_allclose(d1, order[:, 0], rtol=1e-12)
    np.testing.assert_allclose(d2, order[:, 1], rtol=1e-12)
    found = np.isfinite(order[:, 0])
    np.testing.assert_array_equal(i1[found], np.argmin(dist, axis=1)[found])
    assert (i1[~found] == len(xy) - 1).all() and not found[-1]


def test_detection_at_twice_the_resolution_sees_the_same_spots():
    """Spots drawn twice as large on a twice finer grid, detected at twice the calibrated spot
    size: the same spots, the same flags, centres at twice the coordinates."""
    rng = np.random.default_rng(11)
    c = jittered_grid(12.0, rng)
    flux = rng.uniform(300.0, 3000.0, len(c))
    cov = np.array([[1.2, 0.4], [0.4, 2.0]])  # elongated, as on the diffuser, px^2
    rng_noise = np.random.default_rng(12)
    coarse_img = draw_dots(c, flux, cov)
    fine_img = draw_dots(2.0 * c + 0.5, flux, 4.0 * cov, shape=(2 * SHAPE[0], 2 * SHAPE[1]))
    coarse_img += rng_noise.normal(0.0, 0.2, coarse_img.shape)
    fine_img += rng_noise.normal(0.0, 0.1, fine_img.shape)  # the same noise per coarse pixel
    sigma = features.detect._TUNED_SIGMA_PX
    coarse = detect_spots(coarse_img.astype(np.float32), spot_sigma_px=sigma)
    fine = detect_spots(fine_img.astype(np.float32), spot_sigma_px=2.0 * sigma)
    assert len(fine) == len(coarse) == len(c)
    assert fine.merged.sum() == coarse.merged.sum() == 0
    err_coarse = nearest(coarse.centres_px, c)
    err_fine = nearest((fine.centres_px - 0.5) / 2.0, c)  # in coarse pixels
    assert np.median(err_fine) <= 1.1 * np.median(err_coarse)
    # Without the scale the fine image is cut into the tuned (coarse) windows.
    assert SpotScales.of(2.0 * sigma).local_radius_px == 6


def test_pixel_scales_default_to_the_tuned_values():
    tuned = SpotScales.of(None)
    same = SpotScales.of(features.detect._TUNED_SIGMA_PX)
    assert (tuned.smooth_px, tuned.local_radius_px, tuned.min_area_px) == (1.0, 3, 3)
    assert (tuned.background_px, tuned.wide_px, tuned.box_max_px) == (25, 40, 48)
    assert same.smooth_px == pytest.approx(1.0) and same.local_radius_px == 3
    double = SpotScales.of(2.0 * features.detect._TUNED_SIGMA_PX)
    assert (double.min_area_px, double.background_px, double.box_max_px) == (12, 50, 96)
    # The background's noise bias is measured at each scale's own smoothing and window.
    assert tuned.minimum_bias == _minimum_bias(1.0, 25)
    assert double.minimum_bias == _minimum_bias(double.smooth_px, 50)
    with pytest.raises(WaiInputError):
        SpotScales.of(-1.0)


def test_reference_carries_the_calibrated_spot_scale(cfg):
    """The paper's rig at 800 x 600 is the tuning: scale 1; a grid at twice the spot size
    scales the per-frame constants (detection, order margin) by 2."""
    sigma = features.spot_sigma_px(cfg)
    assert sigma == pytest.approx(1.5178, abs=1e-3)
    grid = ReferenceGrid(
        np.zeros((1, 2), np.int64), np.zeros((1, 2)), np.ones(1, bool), np.ones(1, bool),
        np.ones(1), np.full((1, 2, 2), np.nan), np.zeros((0, 2), np.int64), {}, 0.0,
        spot_sigma_px=2.0 * sigma,
    )
    assert grid.pixel_scale == pytest.approx(2.0, rel=1e-4)
    assert grid.detect_sigma_px == pytest.approx(2.0 * sigma)
    assert grid.spot_scales.local_radius_px == 6  # the tuned 3 px, doubled
    assert ReferenceGrid(*[getattr(grid, f) for f in (
        "ij", "ref_px", "observed", "lit", "spacing_px", "cov_px2", "unmatched_ij", "counts",
        "rms_px")]).pixel_scale == 1.0  # not calibrated: the tuned constants


def test_detection_takes_the_scales_or_the_spot_size():
    """Scales built once for a spot size detect exactly what that spot size does per call."""
    rng = np.random.default_rng(13)
    c = jittered_grid(12.0, rng)
    img = draw_dots(c, rng.uniform(300.0, 3000.0, len(c)), 2.0 * np.eye(2))
    img = (img + rng.normal(0.0, 0.2, img.shape)).astype(np.float32)
    sigma = 1.3 * features.detect._TUNED_SIGMA_PX
    per_call = detect_spots(img, spot_sigma_px=sigma)
    once = detect_spots(img, scales=SpotScales.of(sigma))
    assert len(once) == len(per_call) > 0
    for name in ("centres_px", "flux", "peak", "area_px", "cov_px2", "merged", "border"):
        assert np.array_equal(getattr(once, name), getattr(per_call, name)), name
    with pytest.raises(WaiInputError, match="not both"):
        detect_spots(img, spot_sigma_px=sigma, scales=SpotScales.of(sigma))


def test_scratch_arrays_kept_between_frames_change_no_spot():
    """The scales' reused scratch arrays (and fresh ones while another frame holds them, or
    after pickling) give exactly the spots of fresh arrays, frame after frame."""
    rng = np.random.default_rng(14)
    imgs = []
    for spacing in (12.0, 15.0):
        c = jittered_grid(spacing, rng)
        img = draw_dots(c, rng.uniform(300.0, 3000.0, len(c)), 2.0 * np.eye(2))
        imgs.append((img + rng.normal(0.0, 0.2, img.shape)).astype(np.float32))
    scales = SpotScales.of(features.detect._TUNED_SIGMA_PX)
    fresh = dataclasses.replace(scales, workspace=None)
    names = ("centres_px", "flux", "peak", "area_px", "cov_px2", "merged", "border")

    def same(a, b):
        return len(a) == len(b) > 0 and all(
            np.array_equal(getattr(a, k), getattr(b, k)) for k in names
        )

    want = [detect_spots(img, scales=fresh) for img in imgs]
    for img, w in zip(imgs + imgs, want + want, strict=True):  # each after the other one
        assert same(detect_spots(img, scales=scales), w)
    with scales.workspace.borrow():  # taken: this frame works in fresh arrays
        assert same(detect_spots(imgs[0], scales=scales), want[0])
    assert same(detect_spots(imgs[1], scales=pickle.loads(pickle.dumps(scales))), want[1])


def test_labels_are_kept_only_where_closed_loops_of_matches_check_them():
    # Ordering checks a label against its neighbours, so only a closed loop of matches can
    # contradict a label shifted by one dot. Matched here: a 6 x 6 block with a hole in it;
    # a patch beside it joined by two links, through which a loop runs; a chain hanging off
    # its corner, a column one dot wide on its top and a patch joined by one link. The block
    # (hole and all) and the patch of two links are checked, the rest is not.
    block = [(i, j) for i in range(6) for j in range(6) if (i, j) != (2, 3)]
    patch2 = ([(i, j) for i in (-3, -2) for j in range(-1, 7)]
              + [(-1, -1), (-1, 0), (-1, 5), (-1, 6)])  # links (-1, 0)-(0, 0), (-1, 5)-(0, 5)
    chain = [(6, 0), (7, 0), (8, 0), (9, 0)]
    column = [(1, j) for j in range(6, 12)]
    patch1 = [(i, j) for i in range(6, 9) for j in range(5, 8)]  # link (6, 5)-(5, 5)
    nodes_ij = np.array(block + patch2 + chain + column + patch1)
    lattice = np.array([(i, j) for i in range(-6, 17) for j in range(-4, 16)])
    lat = _LatticeTables.of(lattice, np.ones(len(lattice), bool)).lat
    kept = _braced_piece(lat, lat.lookup(nodes_ij))
    np.testing.assert_array_equal(kept, np.arange(len(nodes_ij)) < len(block) + len(patch2))
    # Without a single whole square, the largest 4-connected piece.
    line = np.array([(i, 0) for i in range(5)] + [(i, 3) for i in range(2)])
    assert _braced_piece(lat, lat.lookup(line)).tolist() == [True] * 5 + [False] * 2
