"""The true surface a frame renders, sampled on the mesh grid: the wave model's or a file's.

The grid covers the modelled extent (:func:`~wai_core.layout.surface_extent`, or a given one),
its spacing set by the shortest wave (:func:`wave_surface`) or by the file's own grid
(:func:`file_surface`), and never more than :data:`MAX_MESH_VERTICES` vertices.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

import numpy as np
from numpy.typing import NDArray

from mitsuba_wai.waves import mesh_spacing_mm, sea_surface
from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError
from wai_core.heightfield import Heightfield
from wai_core.layout import observed_patch, surface_extent

__all__ = ["MAX_MESH_VERTICES", "file_surface", "labelled", "moving_surface", "wave_grid_axes",
           "wave_surface"]

# Largest mesh the renderer builds: ~1 M vertices keeps a frame's memory and time bounded.
MAX_MESH_VERTICES = 1_000_000


def _axis_size(lo: float, hi: float, spacing: float) -> int:
    return max(int(np.ceil((hi - lo) / spacing)) + 1, 5) if spacing > 0 else 5


def _axis(lo: float, hi: float, spacing: float) -> NDArray:
    return np.linspace(lo, hi, _axis_size(lo, hi, spacing))


def wave_surface(cfg: SystemConfig, extent: NDArray | None = None) -> Heightfield:
    """The true surface of ``cfg.waves`` at ``time_s`` on the mesh grid: the modelled extent
    (``[[x0, x1], [y0, y1]]`` mm; default :func:`~wai_core.layout.surface_extent`) sampled at
    the shortest wavelength / ``mesh_points_per_wavelength`` (:func:`wave_grid_axes`)."""
    x, y = wave_grid_axes(cfg, extent)
    return sea_surface(cfg.waves).grid(x, y, cfg.waves.time_s, mean_level_mm=cfg.water.h0_mm)


def wave_grid_axes(cfg: SystemConfig, extent: NDArray | None = None) -> tuple[NDArray, NDArray]:
    """The axes ``x`` (n,), ``y`` (m,), mm, of :func:`wave_surface`'s grid, without its heights.

    Raises :class:`~wai_core.errors.WaiInputError` where the grid would exceed
    ``MAX_MESH_VERTICES``."""
    ext = surface_extent(cfg) if extent is None else np.asarray(extent, dtype=float)
    sea = sea_surface(cfg.waves)
    spacing = mesh_spacing_mm(
        sea, cfg.waves.mesh_points_per_wavelength, float(np.max(ext[:, 1] - ext[:, 0]))
    )
    # Count before allocating: a light wind's millimetre waves would ask for billions.
    nx, ny = _axis_size(*ext[0], spacing), _axis_size(*ext[1], spacing)
    if nx * ny > MAX_MESH_VERTICES:
        raise WaiInputError(
            f"[waves]: wind {cfg.waves.wind_speed_m_s:g} m/s makes waves as short as "
            f"{sea.shortest_wavelength_mm:.3g} mm, a mesh of {nx}x{ny} vertices (at most "
            f"{MAX_MESH_VERTICES}): raise the wind, lower [waves].omega_max_rel or "
            "mesh_points_per_wavelength"
        )
    return _axis(*ext[0], spacing), _axis(*ext[1], spacing)


def file_surface(
    cfg: SystemConfig, given: Heightfield, extent: NDArray | None = None
) -> Heightfield:
    """A surface given as a file, resampled on the modelled extent (default
    :func:`~wai_core.layout.surface_extent`) at the file's own spacing.

    The file must cover the observed patch (what either system looks at). Beyond the file's grid
    (e.g. camera v's TIR band) the water is flat at ``h0``.
    """
    patch = observed_patch(cfg)
    if (
        given.x[0] > patch[0, 0]
        or given.x[-1] < patch[0, 1]
        or given.y[0] > patch[1, 0]
        or given.y[-1] < patch[1, 1]
    ):
        raise WaiInputError(
            "heightfield: does not cover the observed patch "
            f"x {patch[0, 0]:.0f}..{patch[0, 1]:.0f} mm, y {patch[1, 0]:.0f}..{patch[1, 1]:.0f} mm"
        )
    ext = surface_extent(cfg) if extent is None else np.asarray(extent, dtype=float)
    spacing = float(min(np.diff(given.x).min(), np.diff(given.y).min()))
    spacing = max(spacing, float(np.sqrt(np.prod(ext[:, 1] - ext[:, 0]) / MAX_MESH_VERTICES)))
    x, y = _axis(*ext[0], spacing), _axis(*ext[1], spacing)
    xx, yy = np.meshgrid(x, y)
    z = given.height(xx, yy)
    return Heightfield(x, y, np.where(np.isfinite(z), z, cfg.water.h0_mm))


def moving_surface(cfg: SystemConfig) -> Callable[[float], Heightfield]:
    """The wave model's surface as a function of time, s, on the mesh grid of ``cfg`` (what
    motion blur's sub-frames render)."""
    return lambda t: wave_surface(cfg.replace("waves", time_s=float(t)))


@contextlib.contextmanager
def labelled(label: str) -> Iterator[None]:
    """Errors about the surface inside the block start with ``label`` (the user's option or
    file) instead of the generic ``[waves]`` / ``heightfield``."""
    try:
        yield
    except WaiInputError as exc:
        why = str(exc)
        for generic in ("[waves]: ", "heightfield: "):
            why = why.removeprefix(generic)
        raise WaiInputError(f"{label}: {why}") from None
