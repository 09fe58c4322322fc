"""Shared fixtures: the paper's configuration and small variants of it for fast renders."""

from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from wai_core.config import SystemConfig, load_config

ROOT = Path(__file__).resolve().parents[1]
PAPER_TOML = ROOT / "scenes" / "paper.toml"


def paper_toml_with(**sections: dict) -> str:
    """The paper's scene file with sections it leaves at their defaults given, e.g.
    ``paper_toml_with(render={"spp_pattern": 1, "spp_view": 1})``."""
    text = PAPER_TOML.read_text()
    for name, keys in sections.items():
        assert f"\n[{name}]\n" not in text, name
        text += f"\n[{name}]\n" + "".join(f"{k} = {v!r}\n" for k, v in keys.items())
    return text


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


def render_paper_frame(folder: Path, *, seed: int, texture: str = "checkerboard",
                       wind: float = 1.0, **sections: dict) -> Path:
    """Render the paper's rig at wind ``wind`` m/s, sea ``seed``, its object's ``texture``,
    and sections changed as given (e.g. ``water={"roughness": 0.01}``), into ``folder``."""
    from mitsuba_wai import render_folder
    from wai_core.system import load_rig

    cfg = load_rig("paper").replace("object", texture=texture).replace(
        "waves", wind_speed_m_s=wind, seed=seed)
    for name, keys in sections.items():
        cfg = cfg.replace(name, **keys)
    render_folder(cfg, folder, progress=False)
    return folder


@pytest.fixture(scope="package")
def small_cfg(paper_cfg) -> SystemConfig:
    return shrink(paper_cfg)


@dataclasses.dataclass(frozen=True)
class Installed:
    """The package as ``pip install`` puts it: built into a wheel from the checkout's files,
    installed into a folder of its own (``site``; its dependencies are this environment's),
    and run from another folder (``elsewhere``), as a user runs it."""

    site: Path
    elsewhere: Path
    numba_cache: Path

    def run(self, *args: str, timeout: float = 600, cwd: Path | None = None
            ) -> subprocess.CompletedProcess:
        """``python -m wai ARGS`` from :attr:`elsewhere` (or ``cwd``), the installed copy
        first on the path."""
        env = {**os.environ, "PYTHONPATH": str(self.site),
               "NUMBA_CACHE_DIR": str(self.numba_cache)}
        return subprocess.run([sys.executable, "-m", "wai", *args], cwd=cwd or self.elsewhere,
                              env=env, capture_output=True, text=True, timeout=timeout)


def _checkout_files() -> list[str]:
    """The checkout's files a wheel is built from: tracked and untracked, git's ignores left
    out (the virtual environment, renders, caches)."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others",
                             "--exclude-standard"], cwd=ROOT, capture_output=True, check=True)
    return [name for name in listed.stdout.decode().split("\0")
            if name and (ROOT / name).is_file()]


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Installed:
    """A plain install of the package (see :class:`Installed`), once per test module."""
    root = tmp_path_factory.mktemp("install")
    src, wheels, site = root / "src", root / "wheels", root / "site"
    for name in _checkout_files():
        (src / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, src / name)
    pip = [sys.executable, "-m", "pip", "-q", "--disable-pip-version-check"]
    subprocess.run([*pip, "wheel", "--no-deps", str(src), "-w", str(wheels)], check=True,
                   capture_output=True, timeout=600)
    wheel = next(wheels.glob("*.whl"))
    subprocess.run([*pip, "install", "--no-deps", "--target", str(site), str(wheel)],
                   check=True, capture_output=True, timeout=600)
    elsewhere = root / "elsewhere"
    elsewhere.mkdir()
    return Installed(site, elsewhere, root / "numba-cache")
