"""Wrong inputs that restore without an error must not say ``ok``: a swapped pair of patterns,
two differing files of one image, a view of another moment or turned (seen against a
flat-water view). Renders of the paper's rig at two moments of the same sea."""

import shutil

import numpy as np
import pytest

from mitsuba_wai.render import render_folder
from restoration import restore_folder
from restoration.view_check import VIEW_MATCH_MIN_NCC, match_sequence, ncc
from wai_core.io import read_exr, write_exr, write_png

FILES = ("scene.json", "pattern.exr", "pattern_flat.exr", "view.exr", "view_truth.exr")


@pytest.fixture(scope="module")
def quick_cfg(paper_cfg):
    return paper_cfg.replace("render", spp_pattern=4, spp_view=4)


@pytest.fixture(scope="module")
def frames(quick_cfg, tmp_path_factory):
    """Two render folders of one sea 0.5 s apart."""
    out = []
    for t in (10.0, 10.5):
        folder = tmp_path_factory.mktemp("moment") / "frame"
        render_folder(quick_cfg.replace("waves", time_s=t), folder, progress=False)
        out.append(folder)
    return out


def _case(frames, tmp_path, flat_view=True):
    """A folder of one's own images (no truth), from the first render."""
    folder = tmp_path / "case"
    folder.mkdir()
    for name in FILES[:-1]:
        shutil.copy(frames[0] / name, folder / name)
    if flat_view:  # what the rig sees through flat water, captured once
        shutil.copy(frames[0] / "view_truth.exr", folder / "view_flat.exr")
    return folder


def test_the_right_images_are_ok_and_match_the_flat_view(frames, tmp_path):
    done = restore_folder(_case(frames, tmp_path), write=False)
    assert done.result.status == "ok"
    match = done.result.view_match
    assert match.ncc_restored > VIEW_MATCH_MIN_NCC > match.ncc_distorted


def test_swapped_patterns_are_a_bad_reference(frames, tmp_path):
    folder = _case(frames, tmp_path, flat_view=False)
    (folder / "pattern.exr").rename(folder / "wavy.exr")
    (folder / "pattern_flat.exr").rename(folder / "pattern.exr")
    (folder / "wavy.exr").rename(folder / "pattern_flat.exr")
    result = restore_folder(folder, write=False).result
    assert result.status == "bad_reference"
    assert "swapped" in result.message and "\n" not in result.message


def test_a_png_that_differs_from_the_exr_is_ambiguous(frames, tmp_path):
    folder = _case(frames, tmp_path, flat_view=False)
    write_png(folder / "pattern.png", read_exr(frames[1] / "pattern.exr"))
    result = restore_folder(folder, write=False).result
    assert result.status == "ambiguous_input"
    assert "pattern.exr" in result.message and "pattern.png" in result.message


def test_a_png_preview_of_the_same_exr_is_not_ambiguous(frames, tmp_path):
    folder = _case(frames, tmp_path, flat_view=False)
    shutil.copy(frames[0] / "pattern.png", folder / "pattern.png")  # the render's preview
    assert restore_folder(folder, write=False).result.status == "ok"


def test_the_tools_own_preview_never_makes_its_frame_ambiguous(frames, tmp_path):
    """A preview the render recorded as its own is never a second image, however little it
    correlates with the EXR (a coded pattern's colour preview, a clipped exposure); once the
    EXR beside it is another frame's, the stale preview is a differing file again."""
    from wai_core.images import PREVIEWS_FILE, record_previews

    folder = _case(frames, tmp_path, flat_view=False)
    assert (frames[0] / PREVIEWS_FILE).is_file()  # the render recorded its previews
    pattern = read_exr(folder / "pattern.exr")
    glare = np.clip(pattern * 50.0 / pattern.max(), 0, 1)  # a preview that clips every spot
    write_png(folder / "pattern.png", glare, exposure=1.0)
    assert restore_folder(folder, write=False).result.status == "ambiguous_input"  # unrecorded
    record_previews(folder, {"pattern.png": ("pattern.exr", pattern)})
    result = restore_folder(folder, write=False).result
    assert result.status == "ok" and not result.warnings
    write_exr(folder / "pattern.exr", read_exr(frames[1] / "pattern.exr"))
    result = restore_folder(folder, write=False).result
    assert result.status == "ambiguous_input" and "pattern.png" in result.message


def test_a_coded_pattern_render_restores_ok(quick_cfg, tmp_path):
    """``[pattern] code = "colour"``: the render's colour previews leave its status alone."""
    folder = tmp_path / "coded"
    render_folder(quick_cfg.replace("pattern", code="colour"), folder, progress=False)
    done = restore_folder(folder, write=False)
    assert done.result.status == "ok", done.result.message
    assert "decoded" in done.result.features.counts
    assert done.metrics["wai_rmse_mm"] < 0.1  # 0.016-0.042 mm on unseen surfaces


@pytest.mark.parametrize("wrong", ["turned", "other moment"])
def test_a_wrong_view_is_a_view_mismatch_against_the_flat_view(frames, tmp_path, wrong):
    folder = _case(frames, tmp_path)
    view = read_exr(frames[0] / "view.exr")
    write_exr(folder / "view.exr",
              view[::-1, ::-1] if wrong == "turned" else read_exr(frames[1] / "view.exr"))
    result = restore_folder(folder, write=False).result
    assert result.status == "view_mismatch"
    assert result.view_match.ncc_restored < VIEW_MATCH_MIN_NCC


def test_a_sequence_median_singles_out_the_turned_frame():
    # A still random texture seen in five frames; frame 3's view is turned.
    rng = np.random.default_rng(3)
    still = rng.random((60, 80, 3))
    views = [still + 0.02 * rng.standard_normal(still.shape) for _ in range(5)]
    views[3] = views[3][::-1, ::-1]
    masks = [np.ones((60, 80), bool)] * 5
    matches = match_sequence(views, masks, views, step=1)
    assert [m.consistent for m in matches] == [True, True, True, False, True]
    assert ncc(views[0], still, masks[0]) > 0.99


def test_every_integrator_wai_restore_offers_restores_the_paper_frame_ok(frames, tmp_path):
    from restoration import StructuredLightOptions
    from wai.cli import build_parser

    parser = build_parser()
    restore = parser._subparsers._group_actions[0].choices["restore"]
    offered = next(a.choices for a in restore._actions if a.dest == "integrator")
    folder = _case(frames, tmp_path, flat_view=False)
    for name in offered:
        options = StructuredLightOptions(integrator=name)
        result = restore_folder(folder, options=options, write=False)
        assert result.result.status == "ok", (name, result.result.message)
