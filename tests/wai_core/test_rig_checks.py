"""A surface must lie between the rig's parts over the observed patch, or be refused in one line."""

import numpy as np
import pytest

from wai_core.errors import WaiInputError
from wai_core.geometry import pinhole_of
from wai_core.heightfield import Heightfield
from wai_core.rig_checks import check_surface_in_rig, rig_levels


def _flat(z, bump=None):
    x, y = np.linspace(-400.0, 900.0, 66), np.linspace(-500.0, 500.0, 51)
    zz = np.full((y.size, x.size), float(z))
    if bump is not None:
        zz[25, 30] = bump  # one sample (x = 200, y = 0), inside the observed patch
    return Heightfield(x, y, zz)


def test_levels_of_the_paper_rig(paper_cfg):
    levels = dict(rig_levels(paper_cfg))
    assert levels["the diffuser"] == 60.0 and levels["the object plane"] == 1150.0
    assert levels["camera s"] == pytest.approx(-190.0)
    assert levels["the projector"] == pytest.approx(0.0) and abs(levels["camera v"]) < 0.1


@pytest.mark.parametrize(
    "z, needle",
    [
        (5000.0, "reaches z = 5000.0 mm .*above the object plane at 1150.0 mm"),
        (-50.0, "dips to z = -50.0 mm .*below the diffuser at 60.0 mm, the projector"),
        (30.0, "dips to z = 30.0 mm .*below the diffuser at 60.0 mm;"),
        (1e11, r"reaches z = 1e\+11 mm"),
    ],
)
def test_surface_outside_the_rig_is_refused(paper_cfg, z, needle):
    with pytest.raises(WaiInputError, match=f"^heightfield F.npz: the surface {needle}"):
        check_surface_in_rig(paper_cfg, _flat(z), "heightfield F.npz")


def test_one_bad_sample_is_found_and_located(paper_cfg):
    surface = _flat(150.0, bump=40.0)
    with pytest.raises(WaiInputError, match=r"z = 40.0 mm \(at x = 200, y = 0 mm\)"):
        check_surface_in_rig(paper_cfg, surface, "--wind 3")


def test_surfaces_inside_the_rig_pass(paper_cfg):
    for z in (61.0, 150.0, 1100.0):
        check_surface_in_rig(paper_cfg, _flat(z))


def _moved(cfg, device, shift_mm):
    """``cfg`` with ``device``'s centre moved by ``shift_mm`` in the lab frame (t = -R c)."""
    import dataclasses

    dev = getattr(cfg, device)
    rot = np.asarray(dev.rotation)
    centre = pinhole_of(dev).pose.center_lab_mm + np.asarray(shift_mm, float)
    return dataclasses.replace(cfg, **{device: dataclasses.replace(
        dev, translation_mm=tuple(-rot @ centre))})


@pytest.mark.parametrize(
    "device, shift, needle",
    [
        ("camera_s", (5000.0, 0.0, 0.0), "camera s sees none of the projector's dots on the "
         "diffuser through flat water"),
        ("camera_s", (0.0, 0.0, 300.0), "camera s is at z = 110.0 mm, not below the diffuser"),
        ("camera_v", (0.0, 0.0, 2000.0), "camera v is at z = 2000.0 mm, not below the water"),
        ("projector", (0.0, 0.0, 200.0), "the projector is at z = 200.0 mm, not below the water"),
    ],
)
def test_a_rig_that_sees_nothing_through_flat_water_is_refused(paper_cfg, device, shift,
                                                               needle):
    from wai_core.rig_checks import check_rig

    check_rig(paper_cfg)  # the paper's rig works
    check_rig(_moved(paper_cfg, device, (20.0, 0.0, 0.0)))  # 2 cm off: a rig to check, not refuse
    with pytest.raises(WaiInputError, match=f"^scene.json: {needle}"):
        check_rig(_moved(paper_cfg, device, shift), "scene.json")


def test_the_dots_and_camera_s_view_are_named_where_they_miss(paper_cfg):
    # Camera s 5 m along x: its view of the diffuser is 5 m from where flat water sends the
    # dots (which it does not move); both spans in the message.
    from wai_core.layout import diffuser_rect, flat_pattern_hits
    from wai_core.rig_checks import check_rig

    moved = _moved(paper_cfg, "camera_s", (5000.0, 0.0, 0.0))
    spots = flat_pattern_hits(paper_cfg)[1]
    spots = spots[np.isfinite(spots[:, 0])]
    view = diffuser_rect(moved)
    assert view[0, 0] > spots[:, 0].max()  # disjoint, independently of the check
    with pytest.raises(WaiInputError) as err:
        check_rig(moved)
    assert f"camera s sees x from {view[0, 0]:.0f} to {view[0, 1]:.0f}" in str(err.value)
