"""Shared fixtures: the paper's configuration and small variants of it for fast renders."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from wai_core.config import SystemConfig, load_config

ROOT = Path(__file__).resolve().parents[1]
PAPER_TOML = ROOT / "scenes" / "paper.toml"


@pytest.fixture(scope="package")
def paper_cfg() -> SystemConfig:
    return load_config(PAPER_TOML)


def shrink(cfg: SystemConfig, factor: int = 4, spp: int = 4) -> SystemConfig:
    """The same optics with images ``factor`` times smaller (same fields of view) and few spp."""

    def small(dev):
        return dataclasses.replace(
            dev, width_px=dev.width_px // factor, height_px=dev.height_px // factor
        )

    cfg = dataclasses.replace(cfg, camera_s=small(cfg.camera_s), camera_v=small(cfg.camera_v))
    return cfg.replace("render", spp_pattern=spp, spp_view=spp)


@pytest.fixture(scope="package")
def small_cfg(paper_cfg) -> SystemConfig:
    return shrink(paper_cfg)
