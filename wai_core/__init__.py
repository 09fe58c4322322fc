"""Shared core: ray geometry and optics, the system configuration, heightfields and file I/O.

Everything else depends on this package; it depends on nothing of the project. What a script
needs first::

    from wai_core import load_system, Heightfield
    cfg = load_system("paper")            # a packaged scene, or a path to a TOML file
"""

from wai_core.alterman import AltermanSystem
from wai_core.config import (
    SystemConfig,
    config_from_dict,
    load_config,
    renderer_effects,
    with_keys,
)
from wai_core.errors import WaiInputError
from wai_core.heightfield import Heightfield, load_heightfield
from wai_core.lens import DeviceOptics
from wai_core.scenes import scene_names, scene_path
from wai_core.system import load_rig, load_system

__all__ = [
    "AltermanSystem",
    "DeviceOptics",
    "Heightfield",
    "SystemConfig",
    "WaiInputError",
    "config_from_dict",
    "load_config",
    "load_heightfield",
    "load_rig",
    "load_system",
    "renderer_effects",
    "scene_names",
    "scene_path",
    "with_keys",
]
