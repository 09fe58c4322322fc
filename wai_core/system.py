"""Loading a system configuration by packaged name or by path."""

from __future__ import annotations

from pathlib import Path

from wai_core.alterman import AltermanSystem, is_alterman_file, load_alterman
from wai_core.config import SystemConfig, load_config
from wai_core.errors import WaiInputError
from wai_core.scenes import resolve_scene

__all__ = ["load_rig", "load_system"]


def load_system(scene: str | Path) -> SystemConfig | AltermanSystem:
    """The system configuration of a packaged scene (``"paper"``, ``"alterman"``) or a TOML
    file.

    Parameters
    ----------
    scene : str or Path
        A packaged scene's name (see :func:`wai_core.scenes.scene_names`) or a path to a scene
        TOML file. A file with a ``[base]`` table describes Alterman's sun sensor over a base
        scene.

    Returns
    -------
    SystemConfig or AltermanSystem

    Raises
    ------
    WaiInputError
        Unknown scene, missing or invalid file; the message names it.

    Examples
    --------
    >>> from wai_core import load_system
    >>> cfg = load_system("paper")
    >>> cfg.water.h0_mm, cfg.camera_v.width_px
    (150.0, 800)
    >>> type(load_system("alterman")).__name__
    'AltermanSystem'
    """
    path = resolve_scene(scene)
    if path.is_file() and is_alterman_file(path):
        return load_alterman(path)
    return load_config(path)


def load_rig(scene: str | Path) -> SystemConfig:
    """The structured light's system configuration of a scene name or file (as
    :func:`load_system`), refusing a sun-sensor file.

    Examples
    --------
    >>> load_rig("paper").pattern.spacing_px
    28.0
    """
    system = load_system(scene)
    if isinstance(system, AltermanSystem):
        raise WaiInputError(
            f"scene {str(scene)!r} describes the sun sensor; this needs a structured-light "
            "scene such as 'paper'"
        )
    return system
