"""Tests of the coded pattern's decoding on synthetic camera-s images.

The images are drawn here: each lit dot's spot where the geometric model puts it
(:func:`wai_core.forward.predict_spots`) in its code colour, so every spot's true label is
known without the renderer.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from restoration.features import (
    decode_distorted,
    detect_spots,
    features_from_code,
    flag_diffuser_edge,
    node_symbols,
    prepare_reference,
    spot_sigma_px,
    spot_symbols,
)
from restoration.features._outline import _edge_distances, _outline_px, _visible_outline
from restoration.features.match import match_distorted
from wai_core.config import load_config
from wai_core.errors import WaiInputError
from wai_core.forward import predict_spots
from wai_core.heightfield import Heightfield
from wai_core.layout import surface_extent
from wai_core.limits import correspondence_limit
from wai_core.pattern import CODE_LEVELS, dot_codes

SCENE = "scenes/paper.toml"


@pytest.fixture(scope="module")
def cfg():
    return load_config(SCENE).replace("pattern", code="colour")


def draw(cfg, surface, symbols_of=None, keep=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RGB image (H, W, 3) of the lit dots' spots through ``surface`` (None: flat), with the
    grid indices (K, 2) and centres (K, 2) of all (``keep``: a mask of those drawn)."""
    ij, px = predict_spots(cfg, surface)
    sym = true_symbols(cfg, ij) if symbols_of is None else symbols_of
    h, w = cfg.camera_s.height_px, cfg.camera_s.width_px
    img = np.zeros((h, w, 3), np.float32)
    drawn = np.ones(len(ij), bool) if keep is None else keep
    for c, k in zip(px[drawn], sym[drawn], strict=True):  # drawing only: a few hundred spots
        add_spot(img, c, k, spot_sigma_px(cfg))
    return img, ij, px


def true_symbols(cfg, ij) -> np.ndarray:
    """The code's symbol (K,) of the dots ``ij`` (K, 2)."""
    all_ij, _ = cfg.rig.dot_grid
    codes = dot_codes(cfg.pattern, cfg.rig.projector)
    lut = {tuple(k): int(c) for k, c in zip(all_ij.tolist(), codes, strict=True)}
    return np.array([lut[tuple(k)] for k in ij.tolist()])


def add_spot(img, centre, symbol, sigma, amplitude=1.0) -> None:
    """Add a Gaussian spot of ``symbol``'s colour at ``centre`` (col, row) to ``img``."""
    h, w = img.shape[:2]
    c, r = centre
    r0, r1 = max(int(r) - 8, 0), min(int(r) + 9, h)
    c0, c1 = max(int(c) - 8, 0), min(int(c) + 9, w)
    rows, cols = np.mgrid[r0:r1, c0:c1]
    blob = amplitude * np.exp(-((cols - c) ** 2 + (rows - r) ** 2) / (2 * sigma**2))
    g = CODE_LEVELS[symbol]
    img[r0:r1, c0:c1, 1] += g * blob
    img[r0:r1, c0:c1, 2] += (1 - g) * blob


def wavy(cfg, phi_ratio: float, wavelength_mm: float = 80.0) -> Heightfield:
    """A sinusoid along x whose slope amplitude is ``phi_ratio`` times eq. 35's limit."""
    ext = surface_extent(cfg)
    x = np.linspace(ext[0, 0], ext[0, 1], 801)
    y = np.linspace(ext[1, 0], ext[1, 1], 401)
    phi = phi_ratio * correspondence_limit(cfg)["phi_max_rad"]
    amp = phi * wavelength_mm / (2 * np.pi)
    z = cfg.water.h0_mm + amp * np.sin(2 * np.pi * x / wavelength_mm)[None, :] + 0 * y[:, None]
    return Heightfield(x, y, z)


def precision(matches, ij_true, px_true) -> tuple[float, int]:
    index = {tuple(k): n for n, k in enumerate(ij_true.tolist())}
    ok = [
        tuple(k) in index and np.linalg.norm(s - px_true[index[tuple(k)]]) < 1.0
        for k, s in zip(matches.ij.tolist(), matches.spot_px, strict=True)
    ]
    return float(np.mean(ok)) if ok else 0.0, int(np.sum(ok))


@pytest.fixture(scope="module")
def reference(cfg):
    flat, _, _ = draw(cfg, None)
    return prepare_reference(flat, cfg)


def test_symbols_read_from_colour(cfg):
    img, _, px = draw(cfg, None)
    sym, conf, green, levels = spot_symbols(img, px, spot_sigma_px(cfg))
    ij, _ = predict_spots(cfg, None)
    all_ij, _ = cfg.rig.dot_grid
    codes = dot_codes(cfg.pattern, cfg.rig.projector)
    lut = {tuple(k): int(c) for k, c in zip(all_ij.tolist(), codes, strict=True)}
    truth = np.array([lut[tuple(k)] for k in ij.tolist()])
    clear = sym >= 0
    assert clear.mean() > 0.95
    assert np.all(sym[clear] == truth[clear])
    np.testing.assert_allclose(levels, CODE_LEVELS, atol=0.05)


def test_reference_keeps_the_rig_outlines(cfg, reference):
    """The prepared grid holds the diffuser's outline in camera s and the part of it that the
    image shows: inside the image frame and inside the outline, neither writable."""
    vis, outline = reference.visible_px, reference.outline_px
    cam = cfg.camera_s
    assert np.all(vis >= -0.5 - 1e-6)
    assert np.all(vis <= np.array([cam.width_px, cam.height_px]) - 0.5 + 1e-6)
    assert np.all(_edge_distances(outline, vis)[0] >= -1e-3)
    for arr in (vis, outline):
        with pytest.raises(ValueError):
            arr[0, 0] = 0.0


def test_node_symbols_match_the_panel(cfg, reference):
    codes = node_symbols(reference, cfg)
    assert np.all(codes[~reference.lit] == -1)
    assert set(np.unique(codes[reference.lit])) <= {0, 1, 2, 3}


@pytest.mark.parametrize("phi_ratio", [0.5, 2.0])
def test_decodes_past_the_ordering_limit(cfg, reference, phi_ratio):
    img, ij, px = draw(cfg, wavy(cfg, phi_ratio))
    spots = flag_diffuser_edge(detect_spots(img, spot_sigma_px=reference.detect_sigma_px),
                               _outline_px(cfg))
    dec = decode_distorted(reference, spots, img, cfg)
    frac, n_ok = precision(dec.matches, ij, px)
    assert frac >= 0.99
    assert n_ok > (0.5 if phi_ratio < 1 else 0.1) * len(ij)  # recall falls; precision not
    assert np.all((dec.confidence >= 0) & (dec.confidence <= 1))
    assert dec.matches.counts["matched"] == len(dec.matches)


def test_specks_take_no_label(cfg, reference):
    """A speck (Monte Carlo firefly, stray light) in a dot's colour, 5 px from where the dot's
    spot would be, takes no label, also where the dot's own spot is missing: the window votes
    would give it one (5 px is within their tolerance), 5 px off the dot."""
    surface = wavy(cfg, 0.5)
    ij, px = predict_spots(cfg, surface)
    h, w = cfg.camera_s.height_px, cfg.camera_s.width_px
    gone = np.zeros(len(ij), bool)
    gone[np.flatnonzero(np.linalg.norm(px - [w / 2, h / 2], axis=1) < 0.35 * h)[::7]] = True
    img, _, _ = draw(cfg, surface, keep=~gone)
    s = spot_sigma_px(cfg)
    for c, k in zip(px[gone] + [5.0, 0.0], true_symbols(cfg, ij[gone]), strict=True):
        add_spot(img, c, k, 1.0, amplitude=0.015 * s**2)  # 1.5 % of a spot's flux
    spots = flag_diffuser_edge(detect_spots(img, spot_sigma_px=reference.detect_sigma_px),
                               _outline_px(cfg))
    specks = np.linalg.norm(spots.centres_px[:, None] - (px[gone] + [5.0, 0.0]), axis=2) < 1.0
    assert specks.any(axis=0).mean() > 0.5  # the detector keeps them
    dec = decode_distorted(reference, spots, img, cfg)
    frac, n_ok = precision(dec.matches, ij, px)
    assert frac == 1.0
    assert not {tuple(k) for k in dec.matches.ij.tolist()} & {tuple(k) for k in ij[gone].tolist()}
    assert n_ok > 0.7 * len(ij)
    assert dec.matches.counts["rejected_faint"] > 0


def test_fold_is_not_decoded_one_dot_off(cfg, reference):
    """Past eq. 35's bound a fold squeezes columns of spots together, where a column labelled
    one dot over varies more smoothly than the right labels and passes the lattice check (8
    labels at 1.5x the bound here, with the ordering labels); the symbols of the spots next
    to it, where its window was not decoded, drop it."""
    img, ij, px = draw(cfg, wavy(cfg, 1.5))
    m = features_from_code(img, reference, cfg)
    frac, n_ok = precision(m, ij, px)
    assert frac == 1.0
    assert n_ok > 0.5 * len(ij)
    assert m.counts["rejected_window"] > 0


def test_wrong_symbols_are_dropped_not_used(cfg, reference):
    """Misprinted dots (their symbol changed) must not come back with a wrong label."""
    surface = wavy(cfg, 1.0)
    ij, _ = predict_spots(cfg, surface)
    all_ij, _ = cfg.rig.dot_grid
    codes = dot_codes(cfg.pattern, cfg.rig.projector)
    lut = {tuple(k): int(c) for k, c in zip(all_ij.tolist(), codes, strict=True)}
    sym = np.array([lut[tuple(k)] for k in ij.tolist()])
    rng = np.random.default_rng(0)
    bad = rng.random(len(sym)) < 0.05
    sym = np.where(bad, (sym + 1 + rng.integers(0, 3, len(sym))) % 4, sym)
    img, ij, px = draw(cfg, surface, sym)
    m = features_from_code(img, reference, cfg)
    frac, _ = precision(m, ij, px)
    assert frac >= 0.99
    kept = {tuple(k) for k in m.ij.tolist()}
    misprinted = {tuple(k) for k in ij[bad].tolist()}
    assert len(kept & misprinted) <= 0.1 * len(misprinted)


def swell(cfg, slope: float, wavelength_mm: float = 600.0) -> Heightfield:
    """A long sinusoid along x of slope amplitude ``slope``: it moves whole patches of spots
    far from flat water (up to about 10 spacings at 0.1) while keeping their order."""
    ext = surface_extent(cfg)
    x = np.linspace(ext[0, 0], ext[0, 1], 801)
    y = np.linspace(ext[1, 0], ext[1, 1], 401)
    amp = slope * wavelength_mm / (2 * np.pi)
    z = cfg.water.h0_mm + amp * np.sin(2 * np.pi * x / wavelength_mm)[None, :] + 0 * y[:, None]
    return Heightfield(x, y, z)


@pytest.fixture(scope="module")
def swell_frame(cfg, reference):
    img, ij, px = draw(cfg, swell(cfg, 0.1))
    spots = flag_diffuser_edge(detect_spots(img, spot_sigma_px=reference.detect_sigma_px),
                               _outline_px(cfg))
    ordering = match_distorted(reference, spots, visible_px=_visible_outline(cfg))
    return img, ij, px, spots, ordering


def test_keeps_the_ordering_labels_beyond_the_reach(cfg, reference, swell_frame):
    """Where ordering holds, the coded pattern keeps at least the ordering matcher's right
    labels, also those of spots moved farther than the windows' reach from flat water."""
    img, ij, px, spots, ordering = swell_frame
    spacing = float(np.nanmedian(reference.spacing_px))
    ij0, px0 = predict_spots(cfg, None)
    flat_at = {tuple(k): c for k, c in zip(ij0.tolist(), px0, strict=True)}
    far = [np.linalg.norm(c - flat_at[tuple(k)]) > 6.0 * spacing
           for k, c in zip(ij.tolist(), px, strict=True) if tuple(k) in flat_at]
    assert np.sum(far) > 50  # the frame does test the reach
    frac_o, n_ordering = precision(ordering, ij, px)
    dec = decode_distorted(reference, spots, img, cfg, ordering=ordering)
    frac, n_ok = precision(dec.matches, ij, px)
    assert frac >= 0.99
    assert n_ok >= n_ordering
    assert n_ok > n_ok_windows(reference, spots, img, cfg, ij, px)  # the join is what adds them


def n_ok_windows(reference, spots, img, cfg, ij, px) -> int:
    """Right labels decoded from the windows alone (no ordering labels)."""
    return precision(decode_distorted(reference, spots, img, cfg).matches, ij, px)[1]


def test_symbols_settle_the_ordering_shift(cfg, reference, swell_frame):
    """Ordering labels shifted by whole grid steps, with the shift among the ones the plain
    grid could not rule out, are put back by the symbols: the same labels as unshifted."""
    img, ij, px, spots, ordering = swell_frame
    shifted = replace(ordering, ij=ordering.ij + np.array([4, 0]),
                      alt_shifts=np.array([[0, 0], [-1, 0], [-4, 0]]))
    right = decode_distorted(reference, spots, img, cfg, ordering=ordering).matches
    fixed = decode_distorted(reference, spots, img, cfg, ordering=shifted).matches
    assert {tuple(k) for k in fixed.ij.tolist()} == {tuple(k) for k in right.ij.tolist()}
    # Without the alternative, the shifted labels show the wrong symbols and stay out.
    alone = replace(shifted, alt_shifts=np.zeros((1, 2), np.int64))
    frac, _ = precision(decode_distorted(reference, spots, img, cfg, ordering=alone).matches,
                        ij, px)
    assert frac >= 0.99


def test_grey_image_is_refused(cfg, reference):
    img, _, _ = draw(cfg, None)
    with pytest.raises(WaiInputError, match="RGB"):
        features_from_code(img.sum(axis=2), reference, cfg)


def test_structured_light_decodes_by_config(cfg):
    """``[pattern] code = "colour"`` makes the pipeline decode (its counts say so) and the
    surface follow; the plain pattern keeps the ordering matcher."""
    from restoration import Calibration, StructuredLight
    from wai_core.optics import radiance_gain

    surface = wavy(cfg, 0.5)
    flat, _, _ = draw(cfg, None)
    img, _, _ = draw(cfg, surface)
    view = np.random.default_rng(0).random((cfg.camera_v.height_px, cfg.camera_v.width_px, 3))
    images = {"pattern": img, "pattern_flat": flat, "view": view.astype(np.float32)}
    result = StructuredLight()(images, Calibration(cfg, radiance_gain(cfg.water.n_water)))
    assert result.status != "failed", result.message
    assert "decoded" in result.features.counts
    ok = np.isfinite(result.surface.heightfield.z)
    xx, yy = np.meshgrid(result.surface.heightfield.x, result.surface.heightfield.y)
    err = result.surface.heightfield.z[ok] - surface.height(xx[ok], yy[ok])
    assert np.sqrt(np.mean(err**2)) < 1.0
