"""Sea water's absorption and scattering (``[water_optics]``) along the renders' water paths.

Everything below the surface is water: system S's projector, diffuser and camera s, and
camera v. Per colour channel (R, G, B = 600 / 530 / 460 nm) the water has an absorption
coefficient ``a`` and a scattering coefficient ``b`` (``[water_optics]``, 1/m; the defaults are
Smith & Baker's clear ocean, :data:`wai_core.sections.SMITH_BAKER_ABSORPTION_PER_M`), ``b``
scaled by ``turbidity``, ``a`` by ``absorption_scale``.

What is modelled
----------------
- **Direct light, Beer-Lambert** ``exp(-(a + b) L)`` with ``L`` each light path's length in the
  water (the seed paper's eq. 6-7: scattered light leaves the beam).

  System S (particle tracer, no Mitsuba medium): per traced path, exactly
  (:func:`mitsuba_wai.particles.render_particles_water`): projector -> surface -> diffuser ->
  camera s, every leg. Ambient light on the diffuser is weighted from the surface down.

  System V (``path``): per pixel, ``L`` the distance from camera v to the surface along the
  pixel's centre ray (:func:`view_path_lengths`, one ray cast per frame; the surface ~200 mm
  away moves ``L`` by far under a millimetre across a pixel). Checked against Mitsuba's own
  ``volpath`` with a ``homogeneous`` medium inside the water (``tests/mitsuba_wai``).
- **Veiling glow** (optional, ``forward_fraction > 0``): of the scattered, unabsorbed light
  ``exp(-a L)(1 - exp(-b L))`` the share ``forward_fraction`` still arrives, blurred by a
  Gaussian whose width follows the forward scattering angle ``glow_sigma_deg`` (sea water
  scatters strongly forward): in camera v's image ``f tan(sigma) / pitch`` pixels; on the
  diffuser ``tan(sigma)`` times half the mean path length before the diffuser (light scattered
  uniformly along the path), in camera s's pixels on the diffuser.

What is not
-----------
Multiple scattering, back-scatter from the projector's beam into camera s (the screen is
between them), the scattered light's own spectrum change, the wavelength spread within a
channel, and water below the rig (no bottom). A wavy surface's effect on the sky's path length
is ignored (:mod:`mitsuba_wai.ambient`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from wai_core.config import SystemConfig, WaterOpticsConfig
from wai_core.layout import flat_pattern_hits

__all__ = [
    "coefficients_per_mm",
    "glow",
    "glow_sigma_px",
    "pattern_path_lengths_mm",
    "view_path_lengths",
    "water_view",
]

MM_PER_M = 1000.0


def coefficients_per_mm(w: WaterOpticsConfig) -> tuple[NDArray, NDArray]:
    """The effective ``(a, b)`` per channel, (3,) each, 1/mm (scales applied)."""
    a = np.asarray(w.absorption_per_m, dtype=float) * w.absorption_scale / MM_PER_M
    b = np.asarray(w.scattering_per_m, dtype=float) * w.turbidity / MM_PER_M
    return a, b


def pattern_path_lengths_mm(cfg: SystemConfig) -> NDArray:
    """Flat-water water path of each dot in camera s's view, mm (K,): projector -> surface ->
    diffuser -> camera s."""
    q, s, seen = flat_pattern_hits(cfg)
    p0 = cfg.rig.projector.pose.center_lab_mm
    c = cfg.rig.camera_s.pose.center_lab_mm
    q, s = q[seen], s[seen]
    return (np.linalg.norm(q - p0, axis=1) + np.linalg.norm(s - q, axis=1)
            + np.linalg.norm(c - s, axis=1))


def glow_sigma_px(cfg: SystemConfig, system: str) -> float:
    """Standard deviation of the veiling glow's blur in camera s's (``"S"``) or camera v's
    (``"V"``) image, px (see the module notes)."""
    tan = np.tan(np.radians(cfg.water_optics.glow_sigma_deg))
    if system == "V":
        cam = cfg.rig.camera_v
        return float(tan * cam.focal_px)
    q, s, seen = flat_pattern_hits(cfg)
    p0 = cfg.rig.projector.pose.center_lab_mm
    lead = np.linalg.norm(q - p0, axis=1) + np.linalg.norm(s - q, axis=1)
    lead_mm = float(np.mean(lead[seen])) if seen.any() else 2 * cfg.water.h0_mm
    cam = cfg.rig.camera_s
    depth = abs(float(cam.pose.points_to_cam(np.array([[*cam.pose.center_lab_mm[:2],
                                                        cfg.diffuser.z_mm]]))[0, 2]))
    footprint_mm = depth / cam.focal_px
    return float(tan * lead_mm / 2 / footprint_mm)


def glow(scattered: NDArray, fraction: float, sigma_px: float) -> NDArray[np.float32]:
    """The veiling glow: ``fraction`` of the scattered light (H, W, 3), Gaussian-blurred by
    ``sigma_px`` (reflecting borders), float32."""
    from scipy.ndimage import gaussian_filter

    if fraction <= 0:
        return np.zeros_like(scattered, dtype=np.float32)
    out = gaussian_filter(scattered.astype(np.float64), sigma=(sigma_px, sigma_px, 0),
                          mode="reflect", truncate=3.0)
    return (fraction * out).astype(np.float32)


def view_path_lengths(scene: object, cfg: SystemConfig) -> NDArray[np.float64]:
    """Distance from camera v to the surface along each pixel's centre ray, mm (H, W), in the
    loaded scene (its current surface); rays that miss it: to the plane ``h0``."""
    import drjit as dr

    from mitsuba_wai.variant import mitsuba

    mi = mitsuba()
    cam = cfg.rig.camera_v
    rows, cols = np.mgrid[0 : cam.height_px, 0 : cam.width_px]
    o, d = cam.pixel_rays(cols.ravel().astype(float), rows.ravel().astype(float))
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    n = d.shape[0]
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(np.full(n, v, dtype=np.float32)) for v in o]),
                   mi.Vector3f(*[mi.Float(np.ascontiguousarray(d[:, k], dtype=np.float32))
                                 for k in range(3)]))
    si = scene.ray_intersect(ray)
    dr.eval(si.t)
    t = np.asarray(si.t, dtype=np.float64)
    up = np.where(d[:, 2] > 1e-9, d[:, 2], 1e-9)
    fallback = (cfg.water.h0_mm - o[2]) / up
    # Only the water hit counts (the object plane lies far beyond it).
    t = np.where(np.isfinite(t) & (t < 2 * fallback), t, fallback)
    return t.reshape(cam.height_px, cam.width_px)


def water_view(image: NDArray, lengths_mm: NDArray, cfg: SystemConfig) -> NDArray[np.float32]:
    """Camera v's image (H, W, 3) through the water: Beer-Lambert per pixel along
    ``lengths_mm`` (H, W) plus the veiling glow."""
    a, b = coefficients_per_mm(cfg.water_optics)
    L = lengths_mm[..., None]
    kept = np.exp(-a * L) * image
    direct = kept * np.exp(-b * L)
    out = direct + glow(kept - direct, cfg.water_optics.forward_fraction,
                        glow_sigma_px(cfg, "V"))
    return out.astype(np.float32)


def medium_view_scene(cfg: SystemConfig, surface: object, texture: NDArray,
                      max_depth: int = 2) -> dict:
    """System V with Mitsuba's own medium, for checking :func:`water_view`: ``volpath`` with a
    ``homogeneous`` medium (``sigma_t = a + b``, albedo ``b / (a + b)``, 1/mm) inside the water
    and around camera v. At ``max_depth = 2`` a path that scatters in the medium cannot reach
    the object (two more vertices), so the image is Beer-Lambert's direct light.

    Parameters
    ----------
    cfg : SystemConfig
    surface : Heightfield
        The surface to render through.
    texture : (H, W, 3) ndarray
        The object plane's radiance.
    max_depth : int
        ``volpath``'s depth (2: direct light only; more: in-scattering too).
    """
    from mitsuba_wai import mesh as meshes
    from mitsuba_wai.scenes import view_scene, water_bsdf
    from mitsuba_wai.variant import mitsuba

    mi = mitsuba()
    a, b = coefficients_per_mm(cfg.water_optics)
    c = a + b
    albedo = np.where(c > 0, b / np.where(c > 0, c, 1.0), 0.0)
    medium = mi.load_dict({
        "type": "homogeneous",
        "sigma_t": {"type": "rgb", "value": c.tolist()},
        "albedo": {"type": "rgb", "value": albedo.tolist()},
        "phase": {"type": "hg", "g": 0.9},
    })
    tm = meshes.heightfield_mesh(surface)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(water_bsdf(cfg, "V"))
    props["interior"] = medium
    water = mi.Mesh("water", vertex_count=len(tm.vertices), face_count=len(tm.faces),
                    props=props, has_vertex_normals=True)
    meshes.set_mesh_geometry(water, tm)
    scene = view_scene(cfg, water, texture)
    scene["integrator"] = {"type": "volpath", "max_depth": max_depth, "hide_emitters": False}
    scene["sensor"]["medium"] = medium
    return scene
