"""Forward ray optics of the observation camera through the water (eq. 14-20 of Jian et al. 2022).

Camera v sits under the water and looks up at a horizontal object plane ``z = z_object`` (z_a).
The *forward map* of a pixel is: back-project the pixel, hit the water surface, refract into the
air (Snell, eq. 20), hit the object plane; :func:`trace_to_object` computes it, for the
restoration's reverse tracing and for the renderer-side geometric model alike. Statuses of a ray
or target are :class:`RayStatus` codes. Pixel coordinates are continuous ``(col, row)`` with
integer values at pixel centres (see :mod:`wai_core.geometry`).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera, intersect_plane_z, refract
from wai_core.heightfield import Heightfield

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


class RayStatus(IntEnum):
    """Outcome of one ray or one target."""

    OK = 0
    MISSED_SURFACE = 1  # outside the known surface (its extent or its NaN holes)
    TIR = 2  # totally reflected at the surface: no view of the air there
    MISSED_OBJECT = 3  # the air ray never reaches the object plane
    NOT_CONVERGED = 4  # Newton did not settle within its iterations
    OUT_OF_VIEW = 5  # the solved pixel lies outside the image


def status_counts(status: ArrayLike) -> dict[str, int]:
    """Number of entries with each :class:`RayStatus`, keyed by lower-case name."""
    hist = np.bincount(np.asarray(status, dtype=np.int64).ravel(), minlength=len(RayStatus))
    return {s.name.lower(): int(hist[s]) for s in RayStatus}


@dataclass(frozen=True)
class TraceResult:
    """Forward map of a set of pixels (eq. 17-20).

    Attributes
    ----------
    object_mm : (..., 3) ndarray
        Hit points on the object plane, mm, ``lab``; NaN unless status is OK.
    surface_mm : (..., 3) ndarray
        Hit points on the water surface, mm; NaN where the surface was missed.
    status : (...,) ndarray of int8
        :class:`RayStatus` code of each ray.
    """

    object_mm: Array
    surface_mm: Array
    status: NDArray[np.int8]

    @property
    def ok(self) -> BoolArray:
        """True where the ray reached the object plane."""
        return self.status == RayStatus.OK

    @property
    def counts(self) -> dict[str, int]:
        """Rays per status (see :func:`status_counts`)."""
        return status_counts(self.status)


def _check_system(h0_mm: float, n_water: float, z_object_mm: float) -> None:
    if not (np.isfinite(h0_mm) and np.isfinite(n_water) and np.isfinite(z_object_mm)):
        raise WaiInputError("reverse trace: h0, n_water and z_object must be finite")
    if n_water <= 1.0:
        raise WaiInputError(f"reverse trace: n_water must exceed 1, got {n_water}")
    if z_object_mm <= h0_mm:
        raise WaiInputError("reverse trace: the object plane must lie above the water (z > h0)")


def trace_to_object(
    camera: PinholeCamera,
    surface: Heightfield | None,
    h0_mm: float,
    n_water: float,
    z_object_mm: float,
    cols: ArrayLike,
    rows: ArrayLike,
) -> TraceResult:
    """Trace pixels of ``camera`` through the water surface to the object plane (eq. 17-20).

    Parameters
    ----------
    camera : PinholeCamera
        The submerged camera (camera v).
    surface : Heightfield or None
        The water surface; None means flat water at ``h0_mm``.
    h0_mm : float
        Mean water level, mm (used when ``surface`` is None).
    n_water : float
        Refractive index of water (4/3).
    z_object_mm : float
        Height of the object plane, mm (z_a).
    cols, rows : array_like
        Continuous pixel coordinates, broadcast to a common shape (...).

    Returns
    -------
    TraceResult
        Object-plane points (..., 3) mm, surface hits (..., 3) mm and a status per ray.
    """
    _check_system(h0_mm, n_water, z_object_mm)
    origin, dirs = camera.pixel_rays(cols, rows)
    if surface is None:
        hit, _ = intersect_plane_z(origin, dirs, h0_mm)
        normals = np.broadcast_to(np.array([0.0, 0.0, 1.0]), hit.shape)
    else:
        hit, _, normals = surface.intersect_normals(origin, dirs)
    missed = ~np.all(np.isfinite(hit), axis=-1)
    # Water to air: eta = n_water / 1 (eq. 20).
    air, tir = refract(dirs, normals, n_water)
    points, _ = intersect_plane_z(hit, air, z_object_mm)
    status = np.full(missed.shape, RayStatus.OK, dtype=np.int8)
    status[~np.all(np.isfinite(points), axis=-1)] = RayStatus.MISSED_OBJECT
    status[tir] = RayStatus.TIR
    status[missed] = RayStatus.MISSED_SURFACE
    points[status != RayStatus.OK] = np.nan
    return TraceResult(points, hit, status)


def radiance_gain(n_water: float) -> float:
    """The factor radiance gains crossing from air into water of index ``n_water``: the
    n²-law of radiance (basic radiance L/n² is conserved along a ray), so a rendered underwater
    view carries ``n_water**2`` times the object's radiance.

    Examples
    --------
    >>> round(radiance_gain(4 / 3), 4)
    1.7778
    """
    return float(n_water) ** 2


CHANNEL_WAVELENGTHS_NM = (600.0, 530.0, 460.0)
"""Wavelengths (nm) the renders' colour channels R, G, B stand for (as ``[water_optics]``)."""

# Quan & Fry (1995), eq. (1)'s ten coefficients (n0 .. n9), lambda in nm, T in deg C, S in PSU.
_QUAN_FRY = (1.31405, 1.779e-4, -1.05e-6, 1.6e-8, -2.02e-6, 15.868, 0.01155, -0.00423, -4382.0,
             1.1455e6)


def quan_fry_index(
    salinity_psu: ArrayLike, temperature_c: ArrayLike, wavelength_nm: ArrayLike
) -> Array:
    """Refractive index of sea water (relative to air) by Quan & Fry's empirical equation.

    Parameters
    ----------
    salinity_psu : array_like
        Salinity S, PSU (parts per thousand; the fit covers 0 .. 35).
    temperature_c : array_like
        Temperature T, deg C (the fit covers 0 .. 30).
    wavelength_nm : array_like
        Wavelength in vacuum, nm (the fit covers 400 .. 700).

    Returns
    -------
    ndarray
        Index n(S, T, lambda), the inputs' broadcast shape.

    Notes
    -----
    .. math::

        n = n_0 + (n_1 + n_2 T + n_3 T^2) S + n_4 T^2 + \\frac{n_5 + n_6 S + n_7 T}{\\lambda}
            + \\frac{n_8}{\\lambda^2} + \\frac{n_9}{\\lambda^3}

    a fit to the data that Austin & Halikas (1976) selected, at atmospheric pressure.

    References
    ----------
    X. Quan and E. S. Fry, "Empirical equation for the index of refraction of seawater",
    Appl. Opt. 34(18), 3477-3480 (1995).

    Examples
    --------
    >>> round(float(quan_fry_index(0.0, 20.0, 589.3)), 4)
    1.333
    """
    n0, n1, n2, n3, n4, n5, n6, n7, n8, n9 = _QUAN_FRY
    s = np.asarray(salinity_psu, dtype=float)
    t = np.asarray(temperature_c, dtype=float)
    lam = np.asarray(wavelength_nm, dtype=float)
    return (
        n0 + (n1 + n2 * t + n3 * t**2) * s + n4 * t**2
        + (n5 + n6 * s + n7 * t) / lam + n8 / lam**2 + n9 / lam**3
    )


def channel_indices(salinity_psu: float, temperature_c: float) -> tuple[float, float, float]:
    """Sea water's index at the renders' R, G, B wavelengths (:data:`CHANNEL_WAVELENGTHS_NM`),
    by :func:`quan_fry_index`.

    Examples
    --------
    >>> [round(n, 4) for n in channel_indices(35.0, 20.0)]
    [1.3391, 1.3416, 1.3452]
    """
    n = quan_fry_index(salinity_psu, temperature_c, np.array(CHANNEL_WAVELENGTHS_NM))
    return float(n[0]), float(n[1]), float(n[2])


def pattern_index(cfg: Any) -> float:
    """The water's index for the pattern's light, where it meets a housing port (camera s's,
    the projector's): ``[water] n_water``, or for sea water (``index_model = "quan_fry"``) the
    channels' indices (:func:`channel_indices`) weighted by the pattern's colour, as the
    detector sums the channels (blue-green: 1.3441 at 35 PSU and 15 degrees C, where a port
    modelled at 4/3 moved the level by 0.13 mm; docs/results.md, "The whole real rig").

    Examples
    --------
    >>> from wai_core import load_system, with_keys
    >>> cfg = load_system("paper")
    >>> pattern_index(cfg) == cfg.water.n_water
    True
    >>> sea = with_keys(cfg, {"water.index_model": "quan_fry", "water.salinity_psu": 35.0,
    ...                       "water.temperature_c": 15.0})
    >>> round(pattern_index(sea), 4)
    1.3441
    """
    w = cfg.water
    if w.index_model != "quan_fry":
        return float(w.n_water)
    colour = np.asarray(cfg.pattern.color, dtype=float)
    n = np.asarray(channel_indices(w.salinity_psu, w.temperature_c))
    return float(np.dot(colour, n) / colour.sum())
