"""Crosstalk (``[crosstalk]``): systems S and V in one scene, the projector's light on the object.

The water reflects 2-3 % of the projector's light down onto the diffuser (the pattern); it
transmits the rest up into the air, where it lights the object that camera v looks at. Camera v
then sees the projector's dots on the object, moved by the waves a second time on their way
down. The path (projector -> refraction -> the object's diffuse reflection -> refraction ->
camera v) holds a point light behind a specular interface, which neither a path tracer nor a
light tracer can connect; it is rendered in two passes instead:

1. the projector's particles (:class:`mitsuba_wai.dots.DotEmitter`, the pattern's own) are
   traced through the wavy surface (Snell's law and the Fresnel transmittance at the shading
   normal, the particles' power kept: importance transport) to the object plane, where their
   power per texel is the projector's irradiance ``E`` (per colour channel);
2. the object, a Lambertian of albedo its texture ``rho``, adds the radiance ``rho E / pi``:
   the texture camera v's render reads this frame (:meth:`Crosstalk.texture`).

A red-pass filter in front of camera v (``camera_v_filter = "red"``) keeps only the red channel
(the pattern is blue-green), as a rig would; it applies to the view and its truth whether the
crosstalk is on or not. The truth view stays the object's own (rendered without crosstalk): the
dots are what the restoration should not restore.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from mitsuba_wai.dots import DotEmitter
from mitsuba_wai.variant import mitsuba
from wai_core.config import SystemConfig
from wai_core.forward import texture_coords

__all__ = ["CAMERA_V_FILTER", "Crosstalk", "camera_v_filter"]

CAMERA_V_FILTER = {"none": (1.0, 1.0, 1.0), "red": (1.0, 0.0, 0.0)}
"""Each ``[crosstalk].camera_v_filter``'s transmission per colour channel."""


def camera_v_filter(cfg: SystemConfig, view: NDArray) -> NDArray:
    """``view`` (H, W, 3) through camera v's filter; the same array without one."""
    name = cfg.crosstalk.camera_v_filter
    if name == "none":
        return view
    return (view * np.asarray(CAMERA_V_FILTER[name], np.float32)).astype(np.float32)


class Crosstalk:
    """The projector's light on the object, frame by frame.

    Parameters
    ----------
    cfg : SystemConfig
    view_scene : mitsuba.Scene
        System V's scene (its ``water`` mesh, updated per frame, and its ``object`` plane).
    texture : (H, W, 3) ndarray
        The object's texture (:func:`wai_core.forward.texture_coords`: columns along lab +x,
        rows along lab +y): its albedo.

    Examples
    --------
    >>> from mitsuba_wai import FrameRenderer, wave_surface
    >>> from wai_core import load_system
    >>> cfg = load_system("paper").replace("crosstalk", enabled=True)
    >>> renderer = FrameRenderer(cfg, wave_surface(cfg), systems=("view",))
    >>> view = renderer.render(wave_surface(cfg), 1, which=("view",))["view"]  # doctest: +SKIP
    """

    def __init__(self, cfg: SystemConfig, view_scene: Any, texture: NDArray) -> None:
        self._emitter = DotEmitter(cfg)
        shapes = {shape.id(): shape for shape in view_scene.shapes()}
        self._scene, self._water, self._plane = view_scene, shapes["water"], shapes["object"]
        self._albedo = np.asarray(texture, np.float32)
        self._cfg = cfg
        self._n = int(cfg.crosstalk.particles)
        self._scale = float(cfg.crosstalk.scale)
        self._n_water = float(cfg.water.n_water)
        self._size = np.array(cfg.object.size_mm, float)

    @property
    def albedo(self) -> NDArray[np.float32]:
        """The object's own texture (H, W, 3)."""
        return self._albedo

    def irradiance(self, seed: int) -> NDArray[np.float32]:
        """The projector's irradiance on the object (H, W, 3) on the texture's grid (power per
        mm^2 in the renders' units) through the water surface the scene holds now."""
        import drjit as dr

        mi = mitsuba()
        ray, weight, _ = self._emitter(0.0, self._n, int(seed) % 2**32)
        si = self._scene.ray_intersect(ray)  # from below the water, the water is the first
        hit = si.is_valid() & (si.shape == mi.ShapePtr(self._water))
        # Snell and Fresnel at the shading normal (it points into the air; the ray comes from
        # the water, so the incident cosine is negative: mi.fresnel treats it as leaving).
        wi = si.to_local(-ray.d)
        f, cos_t, _, eta_ti = mi.fresnel(mi.Frame3f.cos_theta(wi), self._n_water)
        up = si.spawn_ray(si.to_world(mi.refract(wi, cos_t, eta_ti)))
        on = self._plane.ray_intersect(up, mi.RayFlags.Minimal, hit)
        reached = hit & on.is_valid() & (f < 1.0)
        p = up.o + up.d * on.t
        # A particle's weight is the projector's whole flux over its sampling density (as
        # Mitsuba's Scene.sample_emitter_ray gives it): each carries 1/n of it.
        power = weight * (1.0 - f) / self._n
        dr.eval(p, power, reached)
        keep = np.asarray(reached, bool)
        xy = np.stack([np.asarray(p.x), np.asarray(p.y)], axis=1)[keep]
        rgb = np.stack([np.asarray(power[c]) for c in range(3)], axis=1)[keep]
        rows_n, cols_n = self._albedo.shape[:2]
        # The texture's layout as the view's scene shows it (wai_core.forward.texture_coords:
        # column along lab +x, row along lab +y; tests/mitsuba_wai/test_crosstalk.py renders it).
        uv = texture_coords(np.concatenate([xy, np.zeros((len(xy), 1))], axis=1), self._cfg,
                            self._albedo.shape)
        col = np.floor(uv[:, 0] + 0.5).astype(np.int64)
        row = np.floor(uv[:, 1] + 0.5).astype(np.int64)
        inside = (col >= 0) & (col < cols_n) & (row >= 0) & (row < rows_n)
        index = row[inside] * cols_n + col[inside]
        texel_mm2 = float(np.prod(self._size)) / (rows_n * cols_n)
        out = np.stack([np.bincount(index, rgb[inside, c], rows_n * cols_n)
                        for c in range(3)], axis=1)
        return (out.reshape(rows_n, cols_n, 3) / texel_mm2).astype(np.float32)

    def texture(self, seed: int) -> NDArray[np.float32]:
        """The object's radiance this frame (H, W, 3): its own plus ``rho E / pi`` (times
        ``[crosstalk].scale``)."""
        lit = self.irradiance(seed) * (self._scale / np.pi)
        return (self._albedo * (1.0 + lit)).astype(np.float32)
