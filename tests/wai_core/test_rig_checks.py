"""A surface must lie between the rig's parts over the observed patch, or be refused in one line."""

import numpy as np
import pytest

from wai_core.errors import WaiInputError
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
