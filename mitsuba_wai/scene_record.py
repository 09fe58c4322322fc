"""What a render folder's ``scene.json`` holds (the configuration, the derived rig, the
versions and the degradations: enough for the restoration to run from the folder alone), and
the renders' sampler seed."""

from __future__ import annotations

import platform

import numpy as np

from mitsuba_wai.degrade import degradation_record
from mitsuba_wai.scenes import (
    SCENE_V_DEPTH,
    VIEW_SAMPLERS,
    pattern_depth,
)
from wai_core.config import SystemConfig
from wai_core.heightfield import Heightfield
from wai_core.layout import observed_patch, surface_extent


def scene_record(
    cfg: SystemConfig, variant: str, surface: Heightfield, source: str
) -> dict:
    """What ``scene.json`` holds: enough for the restoration to run from the folder alone
    (and, when enabled, the degradations' derived values under ``degradations``)."""
    import drjit
    import mitsuba as mi

    devices = {}
    for name in ("projector", "camera_s", "camera_v"):
        cam = cfg.rig.device(name)
        devices[name] = {
            "center_lab_mm": cam.pose.center_lab_mm,
            "axis_lab": cam.pose.axis_lab,
            "R": cam.pose.R,
            "t_mm": cam.pose.t_mm,
            "pixel_pitch_mm": cam.pixel_pitch_mm,
            "focal_px": cam.focal_px,
            "fov_x_deg": cam.fov_x_deg,
            "sensor_size_mm": cam.sensor_size_mm,
        }
    record = {
        "format": "wai-render/1",
        "config": cfg.to_dict(),
        "derived": {
            "devices": devices,
            "diffuser_rect_mm": cfg.rig.diffuser_rect,
            "surface_extent_mm": surface_extent(cfg),
            "observed_patch_mm": observed_patch(cfg),
            "object_center_mm": cfg.rig.object_center_mm,
            "object_z_mm": cfg.object_z_mm,
            "mesh_vertices": [int(surface.y.size), int(surface.x.size)],
            "mesh_spacing_mm": float(np.diff(surface.x).mean()),
            "vertex_normals": "exact surface normals (smooth shading)",
            "view_radiance_gain": cfg.water.n_water**2,
        },
        "surface_source": source,
        "seed": cfg.waves.seed,
        "render_seed": render_seed(cfg),
        "variant": variant,
        "integrators": {
            "pattern": {"type": "ptracer", "max_depth": pattern_depth(cfg),
                        "emitter_samples": cfg.render.sampling},
            "view": {"type": "path", "max_depth": SCENE_V_DEPTH,
                     "sampler": VIEW_SAMPLERS[cfg.render.sampling]},
        },
        "versions": {
            "mitsuba": mi.__version__,
            "drjit": drjit.__version__,
            "numpy": np.__version__,
            "python": platform.python_version(),
        },
    }
    degradations = degradation_record(cfg)
    if degradations:
        record["degradations"] = degradations
    return record


def render_seed(cfg: SystemConfig) -> int:
    """Mitsuba's sampler seed, derived from the scene seed so reruns are identical
    (0 .. 2^32 - 1, Mitsuba's range)."""
    return (int(cfg.waves.seed) * 7919 + 17) % 2**32
