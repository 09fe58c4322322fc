"""Analytic test surfaces with known heights: steep, sharp-crested and smooth shapes that the
wave model does not make, to test a method outside the surfaces it was tuned on.

Each function returns a :class:`~wai_core.heightfield.Heightfield` about the mean level
``h0_mm`` over a grid that covers the paper's rig; write one with
:meth:`~wai_core.heightfield.Heightfield.save` to use it as ``wai render --heightfield``.

Examples
--------
>>> s = trochoidal(150.0, wavelength_mm=120.0, steepness=0.5)
>>> crest, trough = float(s.z.max() - 150.0), float(150.0 - s.z.min())
>>> crest > 1.5 * trough          # a sharp crest above flat troughs
True
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from wai_core.heightfield import Heightfield

__all__ = ["SURFACES", "bump", "crossing_swells", "scaled", "stokes", "trochoidal"]

Array = NDArray[np.float64]
_X = (-200.0, 800.0)
_Y = (-400.0, 400.0)


def _grid(spacing_mm: float) -> tuple[Array, Array, Array, Array]:
    x = np.arange(_X[0], _X[1] + spacing_mm / 2, spacing_mm)
    y = np.arange(_Y[0], _Y[1] + spacing_mm / 2, spacing_mm)
    xx, yy = np.meshgrid(x, y)
    return x, y, xx, yy


def _along(xx: Array, yy: Array, direction_deg: float) -> Array:
    th = np.radians(direction_deg)
    return xx * np.cos(th) + yy * np.sin(th)


def trochoidal(
    h0_mm: float, wavelength_mm: float = 120.0, steepness: float = 0.5,
    direction_deg: float = 20.0, spacing_mm: float = 1.0,
) -> Heightfield:
    """A Gerstner (trochoidal) wave: sharp crests and flat troughs, the shape of steep waves.

    The free surface is ``x = a - A sin(k a)``, ``z = A cos(k a)`` over the parameter ``a``
    with ``k A = steepness`` (< 1; the crest is a cusp at 1), inverted for ``z(x)`` by Newton
    steps. The mean height of the trochoid lies ``k A^2 / 2`` above its still level; it is
    removed so the surface averages ``h0_mm``.

    Parameters
    ----------
    h0_mm : float
        Mean level, mm.
    wavelength_mm : float
        Wavelength ``2 pi / k``, mm.
    steepness : float
        ``k A`` in (0, 1).
    direction_deg : float
        Direction of travel from +x towards +y, degrees.
    spacing_mm : float
        Grid spacing, mm.
    """
    x, y, xx, yy = _grid(spacing_mm)
    k = 2 * np.pi / wavelength_mm
    amp = steepness / k
    s = _along(xx, yy, direction_deg)
    a = s.copy()
    for _ in range(40):  # solve a - A sin(k a) = s (monotone for k A < 1)
        a -= (a - amp * np.sin(k * a) - s) / (1 - steepness * np.cos(k * a))
    z = amp * np.cos(k * a)
    return Heightfield(x, y, h0_mm + z - np.mean(z))


def stokes(
    h0_mm: float, wavelength_mm: float = 150.0, steepness: float = 0.3,
    direction_deg: float = -30.0, spacing_mm: float = 1.0,
) -> Heightfield:
    """A third-order Stokes wave: ``eta = A [cos t + (kA/2) cos 2t + (3/8)(kA)^2 cos 3t]``
    with ``t = k s``, ``k A = steepness``: peaked crests, the classical nonlinear wave."""
    x, y, xx, yy = _grid(spacing_mm)
    k = 2 * np.pi / wavelength_mm
    amp = steepness / k
    t = k * _along(xx, yy, direction_deg)
    eta = amp * (np.cos(t) + 0.5 * steepness * np.cos(2 * t)
                 + 0.375 * steepness**2 * np.cos(3 * t))
    return Heightfield(x, y, h0_mm + eta - np.mean(eta))


def crossing_swells(
    h0_mm: float, amplitude_mm: float = 2.0, spacing_mm: float = 1.0
) -> Heightfield:
    """Two sinusoidal swells of 140 and 190 mm wavelength crossing at 45 degrees."""
    x, y, xx, yy = _grid(spacing_mm)
    z = amplitude_mm * (0.6 * np.sin(2 * np.pi * xx / 140.0)
                        + 0.4 * np.cos(2 * np.pi * (xx + yy) / (190.0 * np.sqrt(2.0))))
    return Heightfield(x, y, h0_mm + z)


def bump(h0_mm: float, amplitude_mm: float = 3.0, sigma_mm: float = 40.0,
         center_mm: tuple[float, float] = (230.0, 20.0), spacing_mm: float = 1.0) -> Heightfield:
    """A Gaussian bump on flat water (a smooth, isolated feature)."""
    x, y, xx, yy = _grid(spacing_mm)
    r2 = (xx - center_mm[0]) ** 2 + (yy - center_mm[1]) ** 2
    return Heightfield(x, y, h0_mm + amplitude_mm * np.exp(-r2 / (2 * sigma_mm**2)))


def scaled(surface: Heightfield, h0_mm: float, factor: float) -> Heightfield:
    """``surface`` with its heights about ``h0_mm`` multiplied by ``factor``: the same shape
    (a sharp crest stays sharp) with proportionally smaller slopes."""
    return Heightfield(surface.x, surface.y, h0_mm + factor * (surface.z - h0_mm))


SURFACES = {
    "trochoidal_0.3": lambda h0: trochoidal(h0, wavelength_mm=160.0, steepness=0.3),
    "trochoidal_0.6": lambda h0: trochoidal(h0, wavelength_mm=160.0, steepness=0.6),
    "trochoidal_0.9": lambda h0: trochoidal(h0, wavelength_mm=160.0, steepness=0.9),
    "stokes_0.3": lambda h0: stokes(h0, steepness=0.3),
    "crossing_swells": crossing_swells,
    "bump": bump,
}
"""The analytic surfaces by name (each a function of the mean level h0, mm); at full height
the steep ones exceed what the paper's pattern can follow (eq. 35): :func:`scaled` brings a
shape within reach."""
