"""Scene configurations shipped with the package, addressed by name.

``paper`` is the configuration of Jian et al. 2022 (Table 1 and section 5.1); ``alterman`` is
Alterman et al.'s sun-and-pinhole sensor over the same water; ``schlieren`` is the paper's rig
looking at a speckle object (synthetic Schlieren's texture). In a checkout, ``scenes/`` at the
top of the repository points here.

Examples
--------
>>> from wai_core.scenes import scene_names, scene_path
>>> scene_names()
['alterman', 'paper', 'schlieren']
>>> scene_path("paper").name
'paper.toml'
"""

from __future__ import annotations

from pathlib import Path

from wai_core.errors import WaiInputError

__all__ = ["SCENES_DIR", "resolve_scene", "scene_names", "scene_path"]

SCENES_DIR = Path(__file__).resolve().parent
"""Folder of the packaged scene TOML files."""


def scene_names() -> list[str]:
    """Names of the packaged scenes, sorted (``"paper"``, ``"alterman"``, ...)."""
    return sorted(p.stem for p in SCENES_DIR.glob("*.toml"))


def scene_path(name: str) -> Path:
    """The TOML file of the packaged scene ``name``.

    Raises
    ------
    WaiInputError
        When no packaged scene has that name.
    """
    path = SCENES_DIR / f"{name}.toml"
    if not path.is_file():
        raise WaiInputError(f"no packaged scene {name!r} (known: {', '.join(scene_names())})")
    return path


def resolve_scene(name_or_path: str | Path) -> Path:
    """A scene given by packaged name (``"paper"``) or by path (``my_rig.toml``).

    An existing file wins over a packaged name; a bare name without suffix that is no file is
    looked up among the packaged scenes; anything else is returned as a path (so the loader
    reports it as not found, naming the user's path).
    """
    path = Path(name_or_path)
    if path.is_file():
        return path
    if path.suffix == "" and path.parent == Path(".") and (SCENES_DIR / f"{path}.toml").is_file():
        return SCENES_DIR / f"{path}.toml"
    if path.suffix == "" and path.parent == Path("."):
        raise WaiInputError(
            f"scene {str(name_or_path)!r}: neither a file nor a packaged scene "
            f"(known: {', '.join(scene_names())})"
        )
    return path
