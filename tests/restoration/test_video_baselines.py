"""The image-only video baselines and the truth-free checkerboard score.

Facts from outside the code: a regular grid and any homography of it fit a homography exactly;
a still scene warped by zero-mean water distortions is recovered better by registration than
by averaging; a frame source names the file it cannot read.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from restoration.video import (
    checkerboard_score,
    grid_residual_px,
    lucky_fusion,
    read_frames,
    register_frames,
    stability_px,
    temporal_mean,
    track_corners,
)
from wai_core.errors import WaiInputError

CMU = Path(__file__).resolve().parents[3] / "shared" / "data" / "cmu-water" / "checkboard.avi"
CMU_PATTERN = (8, 6)  # 9 x 7 squares on the printed board

SQUARE = 20
PATTERN = (7, 5)  # inner corners of an 8 x 6 board


def board_image(h: int = 180, w: int = 220) -> np.ndarray:
    """A light page holding an 8 x 6 checkerboard of 20 px squares, slightly blurred (a
    camera's optics): grey (H, W) float32 in [0.1, 0.9]. Inner corners at x = 50.5 + 20 i,
    y = 50.5 + 20 j in pixel-centre coordinates."""
    y, x = np.mgrid[0:h, 0:w]
    x0, y0 = 31, 31
    inside = (x >= x0) & (x < x0 + 8 * SQUARE) & (y >= y0) & (y < y0 + 6 * SQUARE)
    dark = ((x - x0) // SQUARE + (y - y0) // SQUARE) % 2 == 0
    img = np.where(inside & dark, 0.1, 0.9).astype(np.float32)
    return gaussian_filter(img, 1.0).astype(np.float32)


def smooth_field(rng: np.random.Generator, shape: tuple[int, int], amp_px: float) -> np.ndarray:
    """A smooth random displacement field (H, W, 2) with peak magnitude ``amp_px``."""
    field = np.stack([gaussian_filter(rng.standard_normal(shape), 12.0) for _ in range(2)], -1)
    return (field * (amp_px / np.abs(field).max())).astype(np.float32)


def warp(img: np.ndarray, field: np.ndarray) -> np.ndarray:
    """``img`` sampled at x + field(x): what a camera sees through a wavy surface."""
    h, w = img.shape[:2]
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(
        img,
        gx + field[..., 0],
        gy + field[..., 1],
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )


@pytest.fixture(scope="module")
def sequence() -> tuple[np.ndarray, np.ndarray]:
    """The still board and 12 frames of it through water (zero-mean displacements, 4 px)."""
    rng = np.random.default_rng(7)
    still = board_image()
    fields = np.stack([smooth_field(rng, still.shape, 4.0) for _ in range(12)])
    fields -= fields.mean(axis=0)  # the water's mean surface is flat
    return still, np.stack([warp(still, f) for f in fields])


def mse(a: np.ndarray, b: np.ndarray, margin: int = 12) -> float:
    m = (slice(margin, -margin), slice(margin, -margin))
    return float(np.mean((a[m] - b[m]) ** 2))


# ------------------------------------------------------------------------------------------
# The score
# ------------------------------------------------------------------------------------------


def test_grid_and_its_homography_have_zero_residual():
    j, i = np.mgrid[0:5, 0:7]
    grid = np.c_[i.ravel(), j.ravel()].astype(float)
    hom = np.array([[30.0, 4.0, 50.0], [-3.0, 25.0, 40.0], [1e-3, 2e-3, 1.0]])
    mapped = cv2.perspectiveTransform(grid[None], hom)[0]
    assert grid_residual_px(grid * 20 + 5, (7, 5)) < 1e-9
    assert grid_residual_px(mapped, (7, 5)) < 1e-4
    bent = mapped + np.c_[np.sin(grid[:, 0]), np.cos(grid[:, 1])] * 2.0
    assert grid_residual_px(bent, (7, 5)) > 0.5


def test_score_zero_on_a_flat_board_larger_when_distorted():
    still = board_image()
    flat = checkerboard_score(still, PATTERN)
    assert flat.found and flat.fraction == 1.0 and flat.corners.shape == (35, 2)
    assert flat.rms_px < 0.15  # the detector's own sub-pixel noise
    # The detector's corners are the drawn ones (up to its order).
    j, i = np.mgrid[0:5, 0:7]
    drawn = np.c_[50.5 + SQUARE * i.ravel(), 50.5 + SQUARE * j.ravel()]
    dist = np.linalg.norm(flat.corners[:, None] - drawn[None], axis=2).min(axis=1)
    assert dist.max() < 0.5  # the right corners, to the detector's sub-pixel accuracy

    hom = np.array([[0.9, 0.12, 15.0], [-0.05, 0.85, 20.0], [2e-4, 4e-4, 1.0]])
    tilted = cv2.warpPerspective(still, hom, still.shape[::-1], borderValue=0.9)
    assert checkerboard_score(tilted, PATTERN).rms_px < 0.15

    wavy = warp(still, smooth_field(np.random.default_rng(3), still.shape, 2.5))
    bent = checkerboard_score(wavy, PATTERN)
    assert bent.found and bent.rms_px > 0.4 and bent.rms_px > 4 * flat.rms_px


def test_score_not_found_and_bad_input():
    s = checkerboard_score(np.full((60, 80), 0.5, np.float32), PATTERN)
    assert not s.found and s.fraction == 0.0 and np.isnan(s.rms_px) and s.corners.shape == (0, 2)
    with pytest.raises(WaiInputError, match="pattern"):
        checkerboard_score(board_image(), (1, 5))
    with pytest.raises(WaiInputError, match="image must be"):
        checkerboard_score(np.zeros((4, 60, 80)), PATTERN)


def test_stability_and_tracking_follow_a_known_motion():
    still = board_image()
    corners = checkerboard_score(still, PATTERN).corners
    shifted = np.float32([[1, 0, 1.5], [0, 1, -2.0]])  # moves the board by (1.5, -2) px
    moved = cv2.warpAffine(still, shifted, still.shape[::-1], borderValue=0.9)
    tracked = track_corners(np.stack([still, moved, still]), corners, PATTERN)
    assert np.all(np.isfinite(tracked))
    assert np.allclose(tracked[1] - tracked[0], [1.5, -2.0], atol=0.1)
    assert stability_px(list(tracked)) == pytest.approx(2.5, abs=0.1)
    assert stability_px([corners, None, corners[::-1]]) != stability_px([corners])  # NaN: no pair
    # A blank frame holds no corner: all lost.
    assert np.all(np.isnan(track_corners(np.full((1, *still.shape), 0.9), corners, PATTERN)))


# ------------------------------------------------------------------------------------------
# The baselines
# ------------------------------------------------------------------------------------------


def test_registration_undoes_the_water_better_than_the_mean(sequence):
    still, frames = sequence
    mean = temporal_mean(frames)
    reg = register_frames(frames, iterations=3, keep_frames=True)
    assert reg.image.shape == still.shape and reg.iterations == 3 and reg.frames_used == 12
    assert reg.registered is not None and reg.registered.shape == frames.shape
    assert reg.valid.mean() > 0.9 and reg.ms_per_frame > 0
    assert mse(reg.image, still) < 0.5 * mse(mean.image, still)
    # The registered corners lie on a grid; the raw frames' do not. (The mean's geometry is
    # the frames' mean geometry, the registration's too: the score does not tell them apart
    # here, only the blur does.)
    s_reg = checkerboard_score(reg.image, PATTERN)
    raw = [checkerboard_score(f, PATTERN) for f in frames]
    raw_rms = np.median([s.rms_px if s.found else np.inf for s in raw])
    assert s_reg.found and s_reg.rms_px < 0.5 * raw_rms


def test_lucky_fusion_beats_the_mean_and_keeps_colour(sequence):
    still, frames = sequence
    mean = temporal_mean(frames)
    lucky = lucky_fusion(frames, reference="mean", keep=0.25)
    assert lucky.method == "lucky" and lucky.image.shape == still.shape
    assert lucky.frame_share is not None and lucky.frame_share.sum() == pytest.approx(1.0)
    assert mse(lucky.image, still) < 0.7 * mse(mean.image, still)
    raw = [checkerboard_score(f, PATTERN) for f in frames]
    raw_rms = np.median([s.rms_px if s.found else np.inf for s in raw])
    for criterion in ("flow", "ncc"):
        r = lucky_fusion(frames, reference=register_frames(frames).image, criterion=criterion)
        assert mse(r.image, still) < 0.7 * mse(mean.image, still)
        s = checkerboard_score(r.image, PATTERN)
        assert s.found and s.rms_px < 0.5 * raw_rms
    colour = lucky_fusion(np.repeat(frames[:4, ..., None], 3, axis=3), reference="mean")
    assert colour.image.shape == (*still.shape, 3)
    assert np.allclose(colour.image[..., 0], colour.image[..., 2], atol=1e-5)


def test_baselines_reject_bad_input(sequence):
    _, frames = sequence
    with pytest.raises(WaiInputError, match="at least 2 frames"):
        register_frames(frames[:1])
    with pytest.raises(WaiInputError, match="iterations"):
        register_frames(frames, iterations=0)
    with pytest.raises(WaiInputError, match="preset"):
        register_frames(frames, preset="slowest")
    with pytest.raises(WaiInputError, match="keep"):
        lucky_fusion(frames, reference="mean", keep=0.0)
    with pytest.raises(WaiInputError, match="reference"):
        lucky_fusion(frames, reference=np.zeros((3, 3)))
    with pytest.raises(WaiInputError, match="NaN"):
        temporal_mean(np.full((2, 16, 16), np.nan))


# ------------------------------------------------------------------------------------------
# The frame source
# ------------------------------------------------------------------------------------------


def test_read_frames_video_and_folder(tmp_path):
    values = [40, 120, 200]
    video = tmp_path / "clip.avi"
    out = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (32, 24))
    for v in values:
        out.write(np.full((24, 32, 3), v, np.uint8))
    out.release()
    clip = read_frames(video)
    assert clip.shape == (3, 24, 32, 3) and clip.dtype == np.float32
    assert np.allclose(clip.mean(axis=(1, 2, 3)) * 255, values, atol=3)
    assert read_frames(video, max_frames=2).shape[0] == 2

    folder = tmp_path / "frames"
    folder.mkdir()
    for i, v in zip((10, 2, 1), values, strict=True):  # natural order: 1, 2, 10
        cv2.imwrite(str(folder / f"frame_{i}.png"), np.full((8, 12), v, np.uint8))
    stack = read_frames(folder)
    assert stack.shape == (3, 8, 12)
    assert np.allclose(stack[:, 0, 0] * 255, values[::-1])


def test_read_frames_errors_name_the_path(tmp_path):
    missing = tmp_path / "nowhere.avi"
    with pytest.raises(WaiInputError, match="nowhere.avi"):
        read_frames(missing)
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"not a video at all")
    with pytest.raises(WaiInputError, match="broken.mp4"):
        read_frames(broken)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(WaiInputError, match="empty"):
        read_frames(empty)
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    cv2.imwrite(str(mixed / "a1.png"), np.zeros((8, 12), np.uint8))
    cv2.imwrite(str(mixed / "a2.png"), np.zeros((9, 12), np.uint8))
    with pytest.raises(WaiInputError, match="a2.png"):
        read_frames(mixed)
    text = tmp_path / "notes.txt"
    text.write_text("x")
    with pytest.raises(WaiInputError, match="notes.txt"):
        read_frames(text)


# ------------------------------------------------------------------------------------------
# The real capture (Tian & Narasimhan's checkerboard under a water tank)
# ------------------------------------------------------------------------------------------


@pytest.mark.skipif(not CMU.is_file(), reason="the CMU capture is not on this machine")
def test_cmu_capture_baselines_beat_raw_frames_and_the_mean():
    frames = read_frames(CMU)
    assert frames.shape == (61, 238, 285, 3)
    mean = temporal_mean(frames)
    reg = register_frames(frames)
    lucky = lucky_fusion(frames, reference=reg.image)
    s_reg = checkerboard_score(reg.image, CMU_PATTERN)
    s_lucky = checkerboard_score(lucky.image, CMU_PATTERN)
    assert s_reg.found and s_lucky.found
    # The raw frames and the mean do not show the full board; where the mean shows part of
    # it, the baselines' same corners lie closer to a grid.
    assert not any(checkerboard_score(f, CMU_PATTERN).found for f in frames[::10])
    s_mean = checkerboard_score(mean.image, CMU_PATTERN)
    assert not s_mean.found or s_mean.rms_px > max(s_reg.rms_px, s_lucky.rms_px)
    part = checkerboard_score(mean.image, (CMU_PATTERN[0], CMU_PATTERN[1] - 1))
    if part.found:
        for s in (s_reg, s_lucky):
            d = np.linalg.norm(s.corners[:, None] - part.corners[None], axis=2)
            same = d.min(axis=1) < 8.0
            assert same.sum() == len(part.corners)
            assert grid_residual_px(s.corners, CMU_PATTERN, same) < part.rms_px
    # Raw corners, followed from the restored ones, lie further from a grid than those.
    tracked = track_corners(frames, s_reg.corners, CMU_PATTERN)
    raw_rms = [grid_residual_px(c, CMU_PATTERN) for c in tracked]
    assert np.nanmedian(raw_rms) > 2 * max(s_reg.rms_px, s_lucky.rms_px)
