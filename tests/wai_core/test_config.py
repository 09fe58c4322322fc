"""Configuration loading: the paper's file parses; mistakes name the key."""

import dataclasses
from pathlib import Path

import pytest

from wai_core.config import config_from_dict, load_config
from wai_core.errors import WaiInputError


def test_paper_config_values(paper_cfg):
    assert paper_cfg.water.h0_mm == 150 and paper_cfg.diffuser.z_mm == 60
    assert paper_cfg.object_z_mm == 1150
    assert paper_cfg.rig.projector.fov_x_deg == pytest.approx(52.0, abs=0.1)


def test_unknown_key_is_named(paper_cfg):
    data = paper_cfg.to_dict()
    data["water"]["depth"] = 3
    with pytest.raises(WaiInputError, match=r"\[water\]\.depth"):
        config_from_dict(data)


def test_wrong_kind_and_missing(paper_cfg):
    data = paper_cfg.to_dict()
    data["waves"]["seed"] = "one"
    with pytest.raises(WaiInputError, match="seed"):
        config_from_dict(data)
    data = paper_cfg.to_dict()
    del data["camera_v"]["focal_mm"]
    with pytest.raises(WaiInputError, match="focal_mm"):
        config_from_dict(data)


def test_impossible_geometry(paper_cfg):
    data = paper_cfg.to_dict()
    data["diffuser"]["z_mm"] = 200.0
    with pytest.raises(WaiInputError, match="diffuser"):
        config_from_dict(data)


def test_unknown_sampling_is_named(paper_cfg):
    data = paper_cfg.to_dict()
    data["render"]["sampling"] = "sobol"
    with pytest.raises(WaiInputError, match=r"\[render\]\.sampling.*'sobol'"):
        config_from_dict(data)


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(WaiInputError, match="not found"):
        load_config(tmp_path / "none.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[water\nh0 = ")
    with pytest.raises(WaiInputError, match="TOML"):
        load_config(bad)


@pytest.mark.parametrize(
    "section, key, value, needle",
    [
        ("waves", "n_frequencies", 10**9, "harmonics would need about"),
        ("sensor", "reference_frames", 10**6, "reference_frames = 1000000"),
        ("camera_v", "rotation", [[0.0] * 3] * 3, r"\[camera_v\]\.rotation is not a rotation"),
        ("camera_s", "rotation", [[2.0, 0, 0], [0, 2.0, 0], [0, 0, 2.0]], "not a rotation"),
        # A reflection is orthonormal but not a rotation (det -1).
        ("projector", "rotation", [[1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]], "det -1"),
    ],
)
def test_values_that_cannot_be_right_or_cannot_fit_are_refused(paper_cfg, section, key, value,
                                                                needle):
    data = paper_cfg.to_dict()
    data[section][key] = value
    with pytest.raises(WaiInputError, match=needle):
        config_from_dict(data)


SIMULATION_SECTIONS = ("waves", "render", "sensor", "motion", "water_optics", "ambient",
                       "crosstalk")


def test_the_rig_is_required_and_only_the_simulation_defaults(paper_cfg):
    # Every section the restoration reads describes the rig: leaving one out is refused, the
    # others (what only the renderer reads) take their defaults.
    import restoration

    data = paper_cfg.to_dict()
    for optional in SIMULATION_SECTIONS:
        del data[optional]
    cfg = config_from_dict(data)
    assert cfg.waves == type(paper_cfg.waves)() and cfg.water == paper_cfg.water
    for section in set(paper_cfg.to_dict()) - set(SIMULATION_SECTIONS):
        partial = {k: v for k, v in data.items() if k != section}
        with pytest.raises(WaiInputError, match=rf"missing section \[{section}\].*required"):
            config_from_dict(partial)
    # The restoration reads none of the sections left to default (checked on its source).
    source = " ".join(p.read_text() for p in Path(restoration.__file__).parent.rglob("*.py"))
    for section in SIMULATION_SECTIONS:
        assert f"cfg.{section}." not in source, section


def test_every_accepted_skimage_texture_is_an_image_that_ships_with_scikit_image(paper_cfg):
    from mitsuba_wai.textures import object_texture
    from wai_core.config import SKIMAGE_TEXTURES

    for name in SKIMAGE_TEXTURES:
        obj = dataclasses.replace(paper_cfg.object, texture=f"skimage:{name}")
        img = object_texture(obj)
        assert img.ndim == 3 and img.shape[2] == 3 and 0 <= img.min() <= img.max() <= 1, name


def test_a_scene_extends_another_with_only_what_differs(tmp_path):
    from wai_core.config import load_config
    from wai_core.errors import WaiInputError
    from wai_core.scenes import scene_path

    paper = load_config(scene_path("paper"))
    (tmp_path / "base.toml").write_text(scene_path("paper").read_text())
    (tmp_path / "tank.toml").write_text('extends = "base.toml"\n[object]\ntexture = "speckle"\n'
                                        '[waves]\nseed = 7\n')
    tank = load_config(tmp_path / "tank.toml")
    assert tank.object.texture == "speckle" and tank.waves.seed == 7
    assert tank.replace("object", texture="checkerboard").replace("waves", seed=0) == paper
    (tmp_path / "bad.toml").write_text('extends = "base.toml"\n[objekt]\ntexture = "speckle"\n')
    with pytest.raises(WaiInputError, match=r"unknown section \[objekt\]"):
        load_config(tmp_path / "bad.toml")
    (tmp_path / "loop.toml").write_text('extends = "loop.toml"\n')
    with pytest.raises(WaiInputError, match="more than 8 files deep"):
        load_config(tmp_path / "loop.toml")
    assert load_config(scene_path("schlieren")).replace("object", texture="checkerboard") \
        == paper
