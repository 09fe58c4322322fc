"""Reverse ray tracing through a known water surface and the image restoration it gives (sec. 3.3).

Given an estimate of the water surface, the stage finds, for every pixel of the flat-water
(ground-truth) view of camera v, the pixel of the distorted view that sees the same point of the
object plane, and resamples the distorted image there (eq. 14-20 of Jian et al. 2022).

Modules
-------
:mod:`wai_core.optics`
    The forward map, pixel -> water surface -> refraction -> object plane
    (:func:`trace_to_object`), and the :class:`RayStatus` codes; shared with the renderer side.
:mod:`restoration.reverse_trace._surface`
    Surface models (flat water, bicubic spline patches: :class:`SplinePatches`) with the
    derivatives the solver needs.
:mod:`restoration.reverse_trace.inverse`
    The inverse map, object point -> pixel, by Newton over surface points (:func:`solve_pixels`,
    :func:`find_pixels`).
:mod:`restoration.reverse_trace.warp`
    The restored image (:func:`restore_view`, :class:`Restoration`) and the truth view it
    resamples into (:class:`ViewPlan`).

A caller that restores many frames keeps one :class:`ViewPlan` per camera and passes it to
every :func:`restore_view` (a sequence may also pass one :class:`ViewState`, which starts each
frame's solve from the previous frame's); one frame that both restores its view and checks its
surface (:func:`restoration.consistency.spot_consistency`) builds one :class:`SplinePatches`
and passes it to both.
"""

from restoration.reverse_trace._surface import SplinePatches
from restoration.reverse_trace.inverse import (
    DEFAULT_TOL_PX,
    PixelSolution,
    find_pixels,
    solve_pixels,
)
from restoration.reverse_trace.plan import ViewPlan, ViewState
from restoration.reverse_trace.warp import Restoration, restore_view
from wai_core.optics import RayStatus, TraceResult, status_counts, trace_to_object

__all__ = [
    "DEFAULT_TOL_PX",
    "PixelSolution",
    "RayStatus",
    "Restoration",
    "SplinePatches",
    "TraceResult",
    "ViewPlan",
    "ViewState",
    "find_pixels",
    "restore_view",
    "solve_pixels",
    "status_counts",
    "trace_to_object",
]
