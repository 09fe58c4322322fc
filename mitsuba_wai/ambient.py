"""Daylight above the water (``[ambient]``): a uniform sky and the sun, in both systems.

System S (camera s sees the diffuser, lit from above through the wavy surface):

- **Sun**: a ``directionalarea`` emitter (as Alterman's sun sensor, :mod:`mitsuba_wai.alterman`)
  on a rectangle perpendicular to the sun above the highest crest, covering every sun ray that
  can reach the diffuser (:func:`sun_footprint`; none passes the mesh's edge), in its own scene,
  ``[ambient].sun_spp`` particles per pixel (~14 % Monte Carlo noise per pixel at 64), which
  ``sun_smooth_px`` can smooth (off by default: the caustics of the paper's waves, >= 130 mm
  long, are tens of px wide, but noise correlated at the spots' scale misleads the detector):
  sun -> water (``water_interface``, ``refract``) -> diffuser -> camera s, rendered with the
  same deterministic particle tracer as the pattern (``max_depth = 3``). The wavy surface
  focuses it into caustics on the diffuser; through flat water it is uniform.
- **Sky**: a uniform sky of radiance ``L`` puts ``E = pi L (1 - F_h)`` on any horizontal plane
  under flat water (``F_h``: the cosine-weighted hemispherical Fresnel reflectance of air to
  water, 0.066 at n = 4/3; the radiance gain ``n^2`` and the Snell window's solid angle cancel),
  so the Lambertian diffuser (albedo 1) shows camera s the radiance ``L (1 - F_h)`` everywhere:
  a constant image, computed, not rendered (waves tilt the window by a few degrees and change
  ``E`` by well under a per cent; a particle tracer would spend most of its light on sky that
  never reaches the screen, a camera-side one cannot see through the one-way screen).

System V: the sky as a ``constant`` emitter and the sun as a far disk of the sun's angular
radius (0.267 deg, radiance ``E / Omega``), both seen by the ``path`` integrator where camera
v's refracted rays reach them past the object plane (which hides whatever lies behind it): the
Snell window's sky and the sun's glints.

Not modelled: the object plane's shadow on the rig and its own lighting (it is a luminous
target), skylight reflected by the water or the rig, the sun's limb darkening, polarisation.
With ``[water_optics]`` on, the ambient light is attenuated from the surface down (the sky's
path by its mean secant under the window, 1.205, times ``h0 - z_h``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from wai_core.config import AmbientConfig, SystemConfig
from wai_core.heightfield import Heightfield

__all__ = [
    "SUN_RADIUS_DEG",
    "SCENE_SUN_DEPTH",
    "hemispherical_reflectance",
    "sky_image",
    "sky_on_diffuser",
    "smooth",
    "sun_direction",
    "sun_footprint",
    "skirt_mesh",
    "sun_s_scene",
    "view_emitters",
]

SUN_RADIUS_DEG = 0.267
"""Angular radius of the sun's disk, deg."""
SCENE_SUN_DEPTH = 3
"""Sun -> water -> diffuser -> camera s."""
SKY_MEAN_SECANT = 1.205
"""Cosine-weighted mean of 1 / cos(theta) over the Snell window (critical angle 48.6 deg):
2 (1 - cos theta_c) / sin^2 theta_c."""
# Vertical clearance of the sun beam above (and its reach below) the mean level, mm: the
# crests stay within it for the seas the rig is laid out for.
_BEAM_CLEARANCE_MM = 50.0
# The far disk of system V's sun, mm from the observed patch (parallax under 0.02 deg).
_SUN_DISTANCE_MM = 1.0e6


def sun_direction(a: AmbientConfig) -> NDArray:
    """Unit direction of the sunlight's travel (downwards), lab (3,)."""
    th, ph = np.radians(a.sun_zenith_deg), np.radians(a.sun_azimuth_deg)
    return -np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])


def hemispherical_reflectance(n: float, steps: int = 2000) -> float:
    """Cosine-weighted hemispherical Fresnel reflectance of unpolarised light from air into a
    medium of index ``n``: ``2 int F(theta) cos(theta) sin(theta) dtheta`` (midpoint rule)."""
    th = (np.arange(steps) + 0.5) * (np.pi / 2) / steps
    ci = np.cos(th)
    ct = np.sqrt(1.0 - (np.sin(th) / n) ** 2)
    rs = ((ci - n * ct) / (ci + n * ct)) ** 2
    rp = ((ct - n * ci) / (ct + n * ci)) ** 2
    return float(np.sum(0.5 * (rs + rp) * 2 * ci * np.sin(th)) * (np.pi / 2) / steps)


def sky_on_diffuser(cfg: SystemConfig) -> NDArray:
    """Radiance of the diffuser under the sky, as camera s sees it, per channel (3,), before
    the water's attenuation (module notes)."""
    a = cfg.ambient
    f_h = hemispherical_reflectance(cfg.water.n_water)
    return a.sky_radiance * np.asarray(a.sky_color, dtype=float) * (1.0 - f_h)


def smooth(image: NDArray, sigma_px: float) -> NDArray[np.float32]:
    """``image`` (H, W, 3) Gaussian-smoothed by ``sigma_px`` in each channel (0: unchanged)."""
    from scipy.ndimage import gaussian_filter

    if sigma_px <= 0:
        return image
    return gaussian_filter(image.astype(np.float64), sigma=(sigma_px, sigma_px, 0),
                           mode="reflect", truncate=3.0).astype(np.float32)


def sky_image(cfg: SystemConfig) -> NDArray[np.float32]:
    """Camera s's image of the sky-lit diffuser (H, W, 3): :func:`sky_on_diffuser` (times a
    port's :meth:`~wai_core.lens.DeviceOptics.radiance_factor`), through the water when
    ``[water_optics]`` is on (surface -> diffuser by the window's mean secant,
    diffuser -> camera s along each pixel's ray; the glow of a uniform field is uniform)."""
    from mitsuba_wai.seawater import coefficients_per_mm

    cam = cfg.rig.camera_s
    value = sky_on_diffuser(cfg)
    image = np.broadcast_to(value, (cam.height_px, cam.width_px, 3)).astype(np.float64)
    optics = cfg.rig.optics("camera_s")
    if optics.has_port:  # uniform radiance stays uniform through a lens, but not a port's
        rows, cols = np.mgrid[0 : cam.height_px, 0 : cam.width_px]
        _, _, pinhole = optics.rays_cam(cols.astype(float), rows.astype(float),
                                        cfg.water.n_water)
        factor = optics.radiance_factor(pinhole, cfg.water.n_water)
        image = image * np.nan_to_num(factor, nan=0.0)[..., None]
    w = cfg.water_optics
    if w.enabled:
        rows, cols = np.mgrid[0 : cam.height_px, 0 : cam.width_px]
        o, d = cam.pixel_rays(cols.astype(float), rows.astype(float))
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        to_screen = (cfg.diffuser.z_mm - o[2]) / d[..., 2]
        length = (to_screen + SKY_MEAN_SECANT * (cfg.water.h0_mm - cfg.diffuser.z_mm))[..., None]
        a, b = coefficients_per_mm(w)
        direct = np.exp(-b * length)
        image = image * np.exp(-a * length) * (direct + w.forward_fraction * (1 - direct))
    return image.astype(np.float32)


def sun_footprint(cfg: SystemConfig, grid: Heightfield) -> NDArray:
    """Where the sun beam meets the mean level, ``[[x0, x1], [y0, y1]]`` mm: the diffuser's
    flat-water pre-image (shifted towards the sun by ``(h0 - z_h) tan(theta_w)``), widened by
    ``0.3 (h0 - z_h)`` for the waves' deflection (~17 deg of refracted direction, four times
    the paper's). Beyond the wave mesh the water is a flat skirt (:func:`skirt_mesh`)."""

    a = cfg.ambient
    th = np.radians(a.sun_zenith_deg)
    th_w = np.arcsin(np.sin(th) / cfg.water.n_water)
    lever = cfg.water.h0_mm - cfg.diffuser.z_mm
    towards_sun = -sun_direction(a)[:2]
    shift = lever * np.tan(th_w) * (towards_sun / max(np.linalg.norm(towards_sun), 1e-12))
    return cfg.rig.diffuser_rect + shift[:, None] + np.array([-1.0, 1.0]) * 0.3 * lever


def skirt_mesh(cfg: SystemConfig, grid: Heightfield) -> object:
    """Flat water at ``h0`` around the wave mesh, out to where the sun beam can reach
    (a ``trimesh`` frame of four rectangles, normals up): the diffuser is wider than the
    modelled waves, and its outer part is lit through flat water. Where a crest meets the
    skirt's edge a sliver of sunlight (height x tan(theta_sun) wide) passes unrefracted."""
    import trimesh

    reach = _BEAM_CLEARANCE_MM * np.tan(np.radians(cfg.ambient.sun_zenith_deg)) + 1.0
    out = sun_footprint(cfg, grid) + np.array([-1.0, 1.0]) * (reach + 1.0)
    inner = np.array([[grid.x[0], grid.x[-1]], [grid.y[0], grid.y[-1]]])
    out = np.stack([np.minimum(out[:, 0], inner[:, 0] - 1), np.maximum(out[:, 1],
                                                                        inner[:, 1] + 1)], 1)
    (X0, X1), (Y0, Y1) = out
    (x0, x1), (y0, y1) = inner
    rects = [(X0, X1, Y0, y0), (X0, X1, y1, Y1), (X0, x0, y0, y1), (x1, X1, y0, y1)]
    h0 = cfg.water.h0_mm
    verts, faces = [], []
    for k, (a0, a1, b0, b1) in enumerate(rects):
        verts += [[a0, b0, h0], [a1, b0, h0], [a1, b1, h0], [a0, b1, h0]]
        faces += [[4 * k, 4 * k + 1, 4 * k + 2], [4 * k, 4 * k + 2, 4 * k + 3]]
    mesh = trimesh.Trimesh(np.array(verts), np.array(faces), process=False)
    mesh.vertex_normals = np.tile([0.0, 0.0, 1.0], (len(verts), 1))
    return mesh


def _sun_beam_to_world(cfg: SystemConfig, grid: Heightfield) -> NDArray:
    """4x4 ``to_world`` of the sun's rectangle: perpendicular to the sun, normal along the
    light's travel, its rays meeting the mean level on :func:`sun_footprint` (and the mesh
    inside its extent at any height within ``h0 +- _BEAM_CLEARANCE_MM``)."""
    from mitsuba_wai.scenes import sun_frame

    d = sun_direction(cfg.ambient)
    a, b, w = sun_frame(d)
    h0 = cfg.water.h0_mm
    (x0, x1), (y0, y1) = sun_footprint(cfg, grid)
    corners = np.array([[x, y, h0] for x in (x0, x1) for y in (y0, y1)])
    ua, ub, uw = corners @ a, corners @ b, corners @ w
    bounds = np.array([[ua.min(), ua.max()], [ub.min(), ub.max()]])
    top = h0 + _BEAM_CLEARANCE_MM
    z_min_a = min(bounds[0, 0] * a[2], bounds[0, 1] * a[2])
    w_e = max((top - z_min_a) / w[2], uw.max() + 1.0)
    centre = bounds[0].mean() * a + bounds[1].mean() * b + w_e * w
    half = (bounds[:, 1] - bounds[:, 0]) / 2
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = half[1] * b, half[0] * a, -w, centre
    return m


def sun_s_scene(cfg: SystemConfig, water_mesh: object, grid: Heightfield) -> dict:
    """System S's sunlit diffuser: sun, water (refracting), diffuser, camera s (module notes).

    Parameters
    ----------
    cfg : SystemConfig
    water_mesh : mitsuba.Mesh
        The water with the ``refract`` interface (:func:`mitsuba_wai.scenes.water_bsdf` "A").
    grid : Heightfield
        The renderer's mesh grid: the beam covers its extent.
    """
    import mitsuba as mi

    from mitsuba_wai import mesh as meshes
    from mitsuba_wai.bsdfs import register
    from mitsuba_wai.scenes import rectangle_to_world, sensor_dict, water_bsdf

    register()
    a = cfg.ambient
    rect = cfg.rig.diffuser_rect
    centre = np.array([rect[0].mean(), rect[1].mean(), cfg.diffuser.z_mm])
    radiance = (a.sun_irradiance * np.asarray(a.sun_color, dtype=float)).tolist()
    return {
        "type": "scene",
        "integrator": {"type": "ptracer", "max_depth": SCENE_SUN_DEPTH, "hide_emitters": True},
        "sensor": sensor_dict(cfg.rig.camera_s, rfilter="box"),
        "water": water_mesh,
        "skirt": meshes.to_mitsuba(skirt_mesh(cfg, grid), "skirt", water_bsdf(cfg, "A")),
        "diffuser": {
            "type": "rectangle",
            "to_world": rectangle_to_world(centre, rect[:, 1] - rect[:, 0], facing_down=False),
            "bsdf": {"type": "oneway_diffuser"},
        },
        "sun": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f(_sun_beam_to_world(cfg, grid).tolist()),
            "emitter": {"type": "directionalarea", "radiance": {"type": "rgb", "value": radiance}},
        },
    }


def view_emitters(cfg: SystemConfig) -> dict:
    """System V's sky (``constant``) and sun (a far disk), as scene entries; none that is 0."""
    import mitsuba as mi

    from wai_core.layout import observed_patch

    a = cfg.ambient
    out: dict = {}
    if a.sky_radiance > 0:
        sky = (a.sky_radiance * np.asarray(a.sky_color, dtype=float)).tolist()
        out["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": sky}}
    if a.sun_irradiance > 0:
        r = np.radians(SUN_RADIUS_DEG)
        solid_angle = 2 * np.pi * (1 - np.cos(r))
        value = (a.sun_irradiance / solid_angle * np.asarray(a.sun_color, dtype=float)).tolist()
        patch = observed_patch(cfg)
        target = np.array([patch[0].mean(), patch[1].mean(), cfg.water.h0_mm])
        d = sun_direction(a)
        centre = target - _SUN_DISTANCE_MM * d
        up = [0.0, 1.0, 0.0] if abs(d[1]) < 0.9 else [1.0, 0.0, 0.0]
        radius = _SUN_DISTANCE_MM * np.tan(r)
        to_world = mi.ScalarTransform4f().look_at(
            origin=centre.tolist(), target=(centre + d).tolist(), up=up
        ) @ mi.ScalarTransform4f().scale([radius, radius, 1.0])
        out["sun"] = {
            "type": "disk",
            "to_world": to_world,
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": value}},
        }
    return out
