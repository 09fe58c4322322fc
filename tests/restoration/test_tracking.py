"""Sequences: labels tracked from the previous frames agree with full matching, and tracking
that cannot hold (a jump in time, a wrong state) falls back to full matching."""

import dataclasses

import numpy as np
import pytest

from mitsuba_wai.sequence import render_sequence
from restoration import StructuredLight
from restoration.features.track import TrackedSpots
from restoration.scoring import Truth, score
from restoration.sequence import load_sequence
from restoration.tracking import SequenceState
from wai_core.sequence import read_sequence
from wai_core.system import load_rig

pytestmark = pytest.mark.slow  # a rendered sequence restored twice; tracking is opt-in

# Spots move well under half a lattice spacing between frames this close in time.
FPS, FRAMES = 240.0, 4


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    """Four frames 1/240 s apart, and one frame a second later (two renders, 2 spp)."""
    cfg = load_rig("paper")
    cfg = dataclasses.replace(cfg, render=dataclasses.replace(cfg.render, spp_pattern=2,
                                                              spp_view=2))
    root = tmp_path_factory.mktemp("track")
    render_sequence(cfg, root / "near", FRAMES, FPS, progress=False)
    later = dataclasses.replace(cfg, waves=dataclasses.replace(cfg.waves,
                                                               time_s=cfg.waves.time_s + 1.0))
    render_sequence(later, root / "far", 1, FPS, progress=False)
    cal, near = load_sequence(root / "near")
    _, far = load_sequence(root / "far")
    dirs = [*read_sequence(root / "near").frame_dirs, *read_sequence(root / "far").frame_dirs]
    truths = [Truth.from_folder(d, cal) for d in dirs]
    return cal, [*near, *far], truths


def _rmse(result, images, cal, truth):
    return score(result, cal.radiance(images["view"]), cal, truth).rmse_mm


def _labels(result):
    """Spot centre -> grid index of a result's features."""
    return {tuple(np.round(p, 6)): tuple(ij)
            for ij, p in zip(result.features.ij, result.features.spot_px, strict=True)}


def _run(cal, frames, track, order):
    method, state = StructuredLight(), SequenceState(track=track)
    return [method(frames[k], cal, state) for k in order], state


def test_tracked_frames_agree_with_full_matching(clips):
    cal, frames, truths = clips
    order = list(range(FRAMES))
    tracked, state = _run(cal, frames, True, order)
    plain, plain_state = _run(cal, frames, False, order)
    assert state.tracked == FRAMES - 1 and state.fallbacks == 0  # all but the first
    assert plain_state.tracked == 0 and plain_state.view_state is None
    assert [r.features.counts["tracked"] for r in tracked] == [0] + [1] * (FRAMES - 1)
    assert [r.status for r in tracked] == [r.status for r in plain]
    rmse_on, rmse_off = [], []
    for k, (on, off) in enumerate(zip(tracked, plain, strict=True)):
        a, b = _labels(on), _labels(off)
        common = set(a) & set(b)
        # The same spot has the same label; nearly every spot either labels, both label.
        assert all(a[s] == b[s] for s in common)
        assert len(common) >= 0.95 * max(len(a), len(b))
        rmse_on.append(_rmse(on, frames[k], cal, truths[k]))
        rmse_off.append(_rmse(off, frames[k], cal, truths[k]))
    assert abs(np.mean(rmse_on) - np.mean(rmse_off)) < 0.005
    assert max(rmse_on) < 0.1  # the paper's rig restores these frames to well under 0.1 mm


def test_a_jump_in_time_falls_back_to_full_matching(clips):
    cal, frames, truths = clips
    order = [0, 1, 2, FRAMES]  # the last a second after the others
    tracked, state = _run(cal, frames, True, order)
    plain, _ = _run(cal, frames, False, order)
    jumped = tracked[-1]
    assert jumped.features.counts["tracked"] == 0
    assert jumped.features.counts["track_fallback"] == 1 and state.fallbacks == 1
    # After a refused attempt the next frame is matched without trying, the one after tried.
    assert state.next_history() == () and state.skipped == 1
    assert len(state.next_history()) == 1
    # Matched in full: the labels of a frame restored on its own.
    np.testing.assert_array_equal(jumped.features.ij, plain[-1].features.ij)
    assert jumped.status == plain[-1].status
    assert abs(_rmse(jumped, frames[FRAMES], cal, truths[FRAMES])
               - _rmse(plain[-1], frames[FRAMES], cal, truths[FRAMES])) < 0.005


@pytest.mark.parametrize("shift", [(1, 0), (0, -1)])
def test_labels_shifted_by_one_dot_are_caught_not_followed(clips, shift):
    cal, frames, truths = clips
    method, state = StructuredLight(), SequenceState()
    for k in (0, 1):
        method(frames[k], cal, state)
    # The state's labels all moved by one lattice node: the pattern's boundary and marker dots
    # (or the surface's miss of its spots) must refuse them.
    state.spots = tuple(TrackedSpots(s.ij + shift, s.spot_px) for s in state.spots)
    res = method(frames[2], cal, state)
    alone = method(frames[2], cal)
    assert res.features.counts["tracked"] == 0 and res.features.counts["track_fallback"] == 1
    assert _labels(res) == _labels(alone)
    assert res.status == alone.status
    assert _rmse(res, frames[2], cal, truths[2]) < 0.1
