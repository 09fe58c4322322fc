"""Mitsuba scene descriptions of the paper's two optical systems, built from the configuration.

Each scene carries only what its measurement needs:

System S (structured light): the projector with the dot pattern (only the dots whose spots can
reach the diffuser are lit, each as bright as its Fresnel loss needs), the water surface, the
diffuser and camera s. The pattern reaches camera s only after a specular bounce, which a
camera-side path tracer can never connect to a delta-position projector, so it is rendered
with ``ptracer`` (light tracing), ``max_depth = 4`` (6 with a reflecting screen,
:func:`pattern_depth`): projector -> (through the one-way diffuser)
-> water -> diffuser -> camera; the pass-through counts as a bounce.

System V (observation): camera v, the water surface and the object plane as an area emitter that
carries the texture, so every path is camera -> water -> object: the ``path`` integrator with
``max_depth = 2`` (one specular bounce, nothing more).

Water is a smooth interface (n = 4/3 below, air above; default) that follows the one branch its
system needs with the exact Fresnel weight (``water_interface`` in :mod:`mitsuba_wai.bsdfs`: the
expectation of Mitsuba's ``dielectric`` without its random branch choice), or, for system S's
idealised variant, a ``mirror`` (a perfect ``conductor``, two-sided because Mitsuba's
conductors reflect on the front side only and the light arrives from below).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mitsuba_wai.diffuser import diffuser_bsdf
from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera
from wai_core.optics import channel_indices

SCENE_S_DEPTH = 4
SCENE_V_DEPTH = 2
VIEW_SAMPLERS = {"stratified": "multijitter", "independent": "independent"}
"""Camera v's Mitsuba sampler for each ``[render].sampling``."""


def _transform(matrix: NDArray) -> object:
    import mitsuba as mi

    return mi.ScalarTransform4f(np.asarray(matrix, dtype=float).tolist())


def device_to_world(camera: PinholeCamera) -> object:
    """Mitsuba ``to_world`` of a device: looks along its +z_cam with image +y_cam down (the
    ``cam`` frame of :mod:`wai_core.geometry`)."""
    import mitsuba as mi

    c = camera.pose.center_lab_mm
    R = camera.pose.R
    return mi.ScalarTransform4f().look_at(
        origin=c.tolist(), target=(c + R[2]).tolist(), up=(-R[1]).tolist()
    )


def sensor_dict(camera: PinholeCamera, rfilter: str = "box", sampler: str = "independent") -> dict:
    """Perspective sensor matching a :class:`PinholeCamera` (square pixels, centred), with
    Mitsuba's ``sampler`` (its sample count is set at render time)."""
    return {
        "type": "perspective",
        "sampler": {"type": sampler},
        "fov": camera.fov_x_deg,
        "fov_axis": "x",
        "near_clip": 1.0,
        "far_clip": 1.0e5,
        "to_world": device_to_world(camera),
        "film": {
            "type": "hdrfilm",
            "width": camera.width_px,
            "height": camera.height_px,
            "pixel_format": "rgb",
            "rfilter": {"type": rfilter},
        },
    }


def water_bsdf(cfg: SystemConfig, system: str) -> dict:
    """The water surface's BSDF in system ``"S"`` (reflection), ``"V"`` or ``"A"`` (refraction;
    A is Alterman's sun sensor, :mod:`mitsuba_wai.alterman`).

    Normals point into the air (exterior). A water surface follows the one branch its system
    needs with the exact Fresnel weight (``water_interface``, :mod:`mitsuba_wai.bsdfs`); the
    ``mirror`` surface of system S reflects everything. The renderer-only ``[water]`` and
    ``[pattern]`` keys add, each when on:

    - ``index_model = "quan_fry"``: the index per colour channel (:func:`water_channel_indices`);
    - ``polarisation = "linear"`` (system S): the projector's field direction
      (:func:`projector_field_axis`), so the reflectance weighs R_s and R_p by it;
    - ``roughness > 0``: Mitsuba's ``roughdielectric`` (GGX, ``alpha = roughness``, index
      ``n_water``). It chooses reflection or refraction at random by the Fresnel weight, so
      each system keeps only its share of the paths (noisier at the same spp); it has one
      scalar index (:class:`~mitsuba_wai.render.FrameRenderer` renders sea water's one
      channel at a time with it) and no polarisation: with polarised projector light, system
      S's rough surface is ``rough_water_reflection`` (:mod:`mitsuba_wai.bsdfs`: the same
      microfacets, reflected only, each facet's Fresnel weighed by the field).
    """
    from mitsuba_wai.bsdfs import register

    register()
    if system not in ("S", "V", "A"):
        raise ValueError(f"system must be 'S', 'V' or 'A', not {system!r}")
    if system == "S" and cfg.water.surface == "mirror":
        return {"type": "twosided", "bsdf": {"type": "conductor", "material": "none"}}
    w = cfg.water
    polarised = system == "S" and cfg.pattern.polarisation == "linear"
    if w.roughness > 0:
        if w.index_model != "constant":
            raise WaiInputError(
                "config: [water].roughness > 0 with [water].index_model = 'quan_fry' is "
                "rendered one colour channel at a time (mitsuba_wai.FrameRenderer)"
            )
        if polarised:
            return {"type": "rough_water_reflection", "alpha": float(w.roughness),
                    "int_ior": w.n_water, "ext_ior": 1.0,
                    "polarisation_axis": projector_field_axis(cfg).tolist()}
        return {"type": "roughdielectric", "distribution": "ggx", "alpha": float(w.roughness),
                "int_ior": w.n_water, "ext_ior": 1.0}
    mode = "reflect" if system == "S" else "refract"
    bsdf = {"type": "water_interface", "int_ior": w.n_water, "ext_ior": 1.0, "mode": mode}
    if w.index_model == "quan_fry":
        bsdf["int_ior_rgb"] = list(water_channel_indices(cfg))
    if polarised:
        bsdf["polarisation_axis"] = projector_field_axis(cfg).tolist()
    return bsdf


def water_channel_indices(cfg: SystemConfig) -> tuple[float, float, float]:
    """The water's index in the renders' R, G, B channels: ``[water].n_water`` in each
    (``index_model = "constant"``) or sea water's at ``salinity_psu`` and ``temperature_c``
    (``"quan_fry"``, :func:`wai_core.optics.channel_indices`)."""
    w = cfg.water
    if w.index_model == "quan_fry":
        return channel_indices(w.salinity_psu, w.temperature_c)
    return (w.n_water,) * 3


def projector_field_axis(cfg: SystemConfig) -> NDArray:
    """Unit vector (3,) ``lab``: the projector's electric field, ``cos(psi) x_cam +
    sin(psi) y_cam`` of its pose (psi = ``[pattern].polarisation_deg``, from the panel's x axis
    towards y). A ray's field is this axis made transverse to the ray."""
    psi = np.radians(cfg.pattern.polarisation_deg)
    R = cfg.rig.projector.pose.R
    axis = np.cos(psi) * R[0] + np.sin(psi) * R[1]
    return axis / np.linalg.norm(axis)


def rectangle_to_world(center: NDArray, size_mm: NDArray, facing_down: bool) -> object:
    """``to_world`` of Mitsuba's [-1, 1]^2 rectangle: centred, sized, normal up or down.

    Facing down is a mirror of local y (``diag(1, -1, -1)``), a proper rotation that also keeps
    texture v growing with lab -y; callers account for that in their uv mapping.
    """
    sx, sy = np.asarray(size_mm, dtype=float) / 2.0
    flip = -1.0 if facing_down else 1.0
    m = np.array(
        [
            [sx, 0.0, 0.0, center[0]],
            [0.0, flip * sy, 0.0, center[1]],
            [0.0, 0.0, flip, center[2]],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    return _transform(m)


def pattern_depth(cfg: SystemConfig) -> int:
    """System S's particle-tracer ``max_depth``: :data:`SCENE_S_DEPTH` (4), or 6 when the
    diffuser reflects (``[diffuser].reflectance > 0``), whose glow takes two more vertices:
    diffuser -> water (reflected back down) -> diffuser -> camera."""
    return SCENE_S_DEPTH + 2 if cfg.diffuser.reflectance > 0 else SCENE_S_DEPTH


def pattern_scene(cfg: SystemConfig, water_mesh: object) -> dict:
    """System S: projector, water, diffuser, camera s (see module notes)."""
    import mitsuba as mi

    from mitsuba_wai.bsdfs import register

    register()
    projector = cfg.rig.projector
    rect = cfg.rig.diffuser_rect
    center = np.array([rect[0].mean(), rect[1].mean(), cfg.diffuser.z_mm])
    panel = cfg.rig.panel_image  # the rig's, made once (read-only)

    def projector_dict(image: NDArray) -> dict:
        return {
            "type": "projector",
            "irradiance": {"type": "bitmap", "bitmap": mi.Bitmap(image), "raw": True},
            "fov": projector.fov_x_deg,
            "scale": cfg.pattern.power,
            "to_world": device_to_world(projector),
        }

    if cfg.pattern.code != "none":
        # The coded pattern as two projectors in one place, its green and its blue channel:
        # Mitsuba draws a projector's particles by the image's luminance (Y weighs blue 0.07,
        # green 0.72), so one RGB panel would give a blue dot a tenth of a green dot's
        # particles and a noisier centre; per channel, every dot gets its share of its own
        # channel's particles. Same irradiance (the two add up to the RGB panel).
        lights = {}
        for name, channel in (("projector", 1), ("projector_blue", 2)):
            image = np.zeros_like(panel)
            image[..., channel] = panel[..., channel]
            lights[name] = projector_dict(image)
    else:
        lights = {"projector": projector_dict(np.array(panel))}  # Mitsuba takes a writable one
    return {
        "type": "scene",
        "integrator": {"type": "ptracer", "max_depth": pattern_depth(cfg), "hide_emitters": True},
        # Box filter: splats land in one pixel, so centroids stay unbiased and splatting is cheap.
        "sensor": sensor_dict(cfg.rig.camera_s, rfilter="box"),
        **lights,
        "water": water_mesh,
        # Diffuse transmission from above, pass-through from below (see mitsuba_wai.bsdfs);
        # a real screen's profile and back-reflection when [diffuser] asks (mitsuba_wai.diffuser).
        "diffuser": {
            "type": "rectangle",
            "to_world": rectangle_to_world(center, rect[:, 1] - rect[:, 0], facing_down=False),
            "bsdf": diffuser_bsdf(cfg),
        },
    }


def view_scene(cfg: SystemConfig, water_mesh: object, texture: NDArray) -> dict:
    """System V: camera v, water, the textured object plane as an emitter facing down."""
    import mitsuba as mi

    center = cfg.rig.object_center_mm
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": SCENE_V_DEPTH, "hide_emitters": False},
        # Multi-jittered pixel samples: stratified and well spread for any count, so edges of
        # the board converge far faster than with independent samples (docs/results.md).
        "sensor": sensor_dict(cfg.rig.camera_v, rfilter="box", sampler=VIEW_SAMPLERS[
            cfg.render.sampling]),
        "water": water_mesh,
        "object": {
            "type": "rectangle",
            "to_world": rectangle_to_world(center, np.array(cfg.object.size_mm), facing_down=True),
            "emitter": {
                "type": "area",
                # The down-facing rectangle runs texture v along lab -y: flip the rows so that
                # row r grows with lab +y (mitsuba_wai.textures) and camera v sees it upright.
                "radiance": {
                    "type": "bitmap",
                    "bitmap": mi.Bitmap(np.ascontiguousarray(texture[::-1])),
                    "raw": True,
                },
            },
        },
    }


def sun_frame(sun_dir: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Right-handed orthonormal frame ``(a, b, w)`` of the sun: ``w`` points towards the sun,
    ``b`` is horizontal, ``a = b x w`` (it has ``a_z = -sin(theta_sun)``)."""
    w = -np.asarray(sun_dir, dtype=float)
    horiz = np.hypot(w[0], w[1])
    b = np.array([-w[1], w[0], 0.0]) / horiz if horiz > 1e-12 else np.array([0.0, 1.0, 0.0])
    return np.cross(b, w), b, w
