"""Rendering a dataset's frames, with the scenes loaded once per mesh level (:class:`FrameMaker`).

Each frame is rendered by :mod:`mitsuba_wai` on a mesh as fine as its shortest wave needs, and
its truth is sampled on one grid shared by the whole dataset (the finest the wind range needs).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from wai.dataset.records import FrameRecord
from wai.dataset.spec import DatasetSpec, flat_seed, frame_config, sample_params
from wai.dataset.truth import NEWTON_STEPS, true_view_warp
from wai_core.config import SystemConfig
from wai_core.heightfield import Heightfield

__all__ = ["FrameMaker", "grid_axes"]


def grid_axes(spec: DatasetSpec, base: SystemConfig) -> tuple[NDArray, NDArray]:
    """The dataset's storage grid: the wave model's mesh grid at the lowest wind of the range,
    whose waves are the shortest (as fine as any frame's mesh)."""
    from mitsuba_wai import wave_grid_axes

    return wave_grid_axes(base.replace("waves", wind_speed_m_s=spec.ranges.wind_speed_m_s[0]))


def _coarser(axis: NDArray, level: int) -> NDArray:
    """``axis`` over the same span with its spacing times ``2**level`` (>= 5 samples)."""
    n = max(int(np.ceil((axis.size - 1) / 2**level)) + 1, 5)
    return np.linspace(axis[0], axis[-1], n)


class FrameMaker:
    """Renders frames of a dataset, with its scenes loaded once per mesh level.

    A frame's mesh is the storage grid (:func:`grid_axes`) with its spacing doubled as often
    as the frame's shortest wave allows (at most its own ``mesh_points_per_wavelength``
    spacing): a few mesh levels cover the wind range, each with its renderer loaded on first
    use, so calm and windy frames both render on meshes their own size.

    Flat water is the same for every frame of the rig: its two renders are made once, with the
    dataset's :func:`~wai.dataset.spec.flat_seed`, and every frame's ``pattern_flat`` and
    ``view_truth`` are them (read by the frame's own sensor when degraded).

    The waves are summed where the frame renders: on a GPU (``cuda_ad_rgb``) on the device
    (:class:`mitsuba_wai.JitWaveGrid`, one grid of points per mesh level), on a CPU by the
    host's matrix product (:meth:`mitsuba_wai.waves.SeaSurface.grid`, faster there); the two
    agree to float64 rounding.

    Parameters
    ----------
    spec : DatasetSpec
    waves_on_device : bool, optional
        Sum the waves on the renders' device (default: where that is a GPU).

    Examples
    --------
    >>> maker = FrameMaker(DatasetSpec(size_px=(80, 60), spp=1))     # doctest: +SKIP
    >>> maker.make(0).view.shape                                        # doctest: +SKIP
    (60, 80, 3)
    """

    def __init__(self, spec: DatasetSpec, waves_on_device: bool | None = None) -> None:
        self.spec = spec
        self._waves_on_device = waves_on_device
        self._wave_grids: dict[int, Any] = {}  # mesh level -> JitWaveGrid
        self.base = spec.base_config()
        self.x_mm, self.y_mm = grid_axes(spec, self.base)
        self._renderers: dict[int, Any] = {}
        self._flat: dict[str, NDArray] | None = None
        self._flat_kept: tuple | None = None  # the flat renders last converted, and the result
        # The warp's tracer on the renders' device, made on first use: the same rig every
        # frame, so it keeps camera v's pixel rays there.
        self._tracer: Any = None

    def surface(
        self, cfg: SystemConfig, time_s: float | None = None, level: int = 0
    ) -> Heightfield:
        """The sea state of ``cfg`` at ``time_s`` (default its own) on the storage grid, or
        on mesh ``level`` (spacing times ``2**level``)."""
        from mitsuba_wai import JitWaveGrid, sea_surface, select_variant

        t = cfg.waves.time_s if time_s is None else time_s
        sea = sea_surface(cfg.waves)
        if self._waves_on_device is None:
            self._waves_on_device = select_variant().startswith("cuda")
        if self._waves_on_device and level in self._wave_grids:
            return self._wave_grids[level].heightfield(sea, t, mean_level_mm=cfg.water.h0_mm)
        x, y = _coarser(self.x_mm, level), _coarser(self.y_mm, level)
        if self._waves_on_device:
            self._wave_grids[level] = JitWaveGrid(x, y)
            return self._wave_grids[level].heightfield(sea, t, mean_level_mm=cfg.water.h0_mm)
        return sea.grid(x, y, t, mean_level_mm=cfg.water.h0_mm)

    def level(self, cfg: SystemConfig) -> int:
        """The coarsest mesh level whose spacing resolves ``cfg``'s shortest wave."""
        from mitsuba_wai import mesh_spacing_mm, sea_surface

        span = float(max(self.x_mm[-1] - self.x_mm[0], self.y_mm[-1] - self.y_mm[0]))
        own = mesh_spacing_mm(sea_surface(cfg.waves), cfg.waves.mesh_points_per_wavelength, span)
        fine = float(max(np.diff(self.x_mm).max(), np.diff(self.y_mm).max()))
        level = 0
        while (2 ** (level + 1) * fine <= own and _coarser(self.x_mm, level + 1).size > 5
               and _coarser(self.y_mm, level + 1).size > 5):
            level += 1
        return level

    def _renderer(self, level: int, surface: Heightfield) -> Any:
        from mitsuba_wai import FrameRenderer

        if level not in self._renderers:
            # Flat water is the same plane at every mesh level: one renderer of it serves all.
            flat = next((r.flat for r in self._renderers.values() if r.flat is not None), None)
            self._renderers[level] = FrameRenderer(self.base, surface, flat=flat)
        return self._renderers[level]

    def render(self, index: int, truth: Heightfield | None = None
               ) -> tuple[SystemConfig, Heightfield, dict[str, NDArray], float]:
        """Frame ``index``'s configuration, true surface (on the storage grid; ``truth`` when
        given), images and the views' gain: the renders of :func:`mitsuba_wai.render_frame`
        on the frame's mesh."""
        from mitsuba_wai import render_flat_water, render_frame_images, render_seed
        from wai_core.optics import radiance_gain

        p = sample_params(self.spec.seed, index, self.spec.ranges, self.spec.degrade)
        cfg = frame_config(self.base, p)
        level = self.level(cfg)
        mesh = truth if truth is not None and level == 0 else self.surface(cfg, level=level)

        def surface_at(t: float) -> Heightfield:
            return self.surface(cfg, t, level)

        renderer = self._renderer(level, mesh)
        if self._flat is None:  # any level's renderer: they share one of flat water
            self._flat = render_flat_water(renderer, self.base, mesh, flat_seed(self.spec.seed),
                                           self.spec.spp)
        cfg, images = render_frame_images(
            renderer, cfg, mesh, render_seed(cfg), spp=self.spec.spp,
            surface_at=surface_at if cfg.motion.exposure_s > 0 else None, flat=self._flat,
        )
        # With the sensor on, the views are its reading, already scaled by the exposure.
        gain = 1.0 if cfg.sensor.enabled else radiance_gain(cfg.water.n_water)
        # Level 0's mesh is the storage grid: the same heights, not synthesised twice.
        storage = mesh if level == 0 else truth if truth is not None else self.surface(cfg)
        return cfg, storage, images, gain

    def make(self, index: int) -> FrameRecord:
        """Frame ``index``, rendered and reduced to what the store holds, with BLAS on one
        thread: idle ones would spin beside Dr.Jit's, and the sums are the same in any process.

        The truth (the exact warp and the normals, from the storage grid's surface) is worked
        out on a second thread while the frame renders: the warp is traced by Dr.Jit on the
        renderer's device (:class:`mitsuba_wai.ViewWarpTracer`), the normals on the host."""
        from concurrent.futures import ThreadPoolExecutor

        from threadpoolctl import threadpool_limits

        p = sample_params(self.spec.seed, index, self.spec.ranges, self.spec.degrade)
        geometry = frame_config(self.base, p)  # the warp needs the rig and the sea, no more
        with threadpool_limits(1, user_api="blas"), ThreadPoolExecutor(1) as pool:
            surf = self.surface(geometry)
            if self._tracer is None:  # here: it sets the renders' variant when none is
                from mitsuba_wai import ViewWarpTracer

                self._tracer = ViewWarpTracer(self.base.rig)
            truth = pool.submit(self._truth, geometry, surf)
            _, _, images, gain = self.render(index, surf)
            normals, warp = truth.result()
            view_truth, pattern_flat = self._flat_record(images, gain)
            return FrameRecord(
                params=p,
                view=(images["view"] / gain).astype(np.float16),
                view_truth=view_truth,
                pattern=_grey16(images["pattern"]),
                pattern_flat=pattern_flat,
                height_mm=surf.z.astype(np.float32),
                normals=normals,
                warp_px=warp,
            )

    def _truth(self, cfg: SystemConfig, surface: Heightfield) -> tuple[NDArray, NDArray]:
        """The storage grid's unit normals (float32) and camera v's exact warp through
        ``surface``: traced on the renderer's device (the CPU's compiled kernels, which give
        the same warp to float32 rounding, where the surface has holes)."""
        normals = surface.grid_normals().astype(np.float32)
        if surface.has_holes:
            return normals, true_view_warp(cfg, surface)
        return normals, self._tracer(cfg.rig, surface, n_iter=NEWTON_STEPS)

    def _flat_record(self, images: dict[str, NDArray], gain: float) -> tuple[NDArray, NDArray]:
        """The frame's flat-water pair as the store holds it: without a sensor, the shared
        render's, converted once for every frame."""
        flat = images["view_truth"], images["pattern_flat"]
        kept = self._flat_kept
        if kept is not None and kept[0] is flat[0] and kept[1] is flat[1] and kept[2] == gain:
            return kept[3]
        out = (flat[0] / gain).astype(np.float16), _grey16(flat[1])
        self._flat_kept = (*flat, gain, out)
        return out


def _grey16(image: NDArray[np.float32]) -> NDArray[np.float16]:
    """The channels' mean of an (H, W, 3) float32 image as float16 (``image.mean(axis=-1)``'s
    float32 values, summed in the same order, in a fifth of its time)."""
    return ((image[..., 0] + image[..., 1] + image[..., 2]) / 3).astype(np.float16)
