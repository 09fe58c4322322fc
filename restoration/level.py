"""How a surface's absolute level was set (:class:`Anchor`, recorded in ``metrics.json``), and
the standard error of a level searched on separate, interleaved sets of the samples' edges
(:func:`anchor_sigma_mm`: the integrability search's and the fit's)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray


@dataclass
class Anchor:
    """How a surface's absolute level was set (``metrics.json``'s ``anchor``).

    Attributes
    ----------
    method : str
        ``gauge`` (the gauge's h0), ``integrability`` (searched from the slopes,
        :mod:`restoration.anchor`), ``gauge_fallback`` (searched, but the slopes did not pin
        it: the gauge's h0), ``view`` (camera v's view, :mod:`restoration.view_level`),
        ``structured_light`` (another method's surface) or ``pattern``
        (camera s's spots, :mod:`restoration.pattern_level`); empty until the level is set.
    anchor_mm : float or None
        The level the samples' mean height was pinned at, mm.
    searched_mm, sigma_mm : float or None
        After a search: the level it found and its standard error, mm.
    evaluations : int or None
        After a search: the reconstructions it ran.
    refine_passes : int or None
        Most refinement passes each reconstruction allowed.
    fit_rms_mm, fit_iterations, fit_level_offset_mm, fit_level_sigma_mm, fit_level_probes,
    fit_level_probes_converged, fit_level_kept_start, fit_level_reason
        After a fit to the spots (:func:`restoration.fit_level.fit_level`): its RMS spot miss as a
        height (mm), Gauss-Newton iterations, the level's offset from the reconstruction and
        its standard error (mm), the levels probed and how many converged, whether the
        reconstruction's level was kept, and why.
    image_fit_explained, image_fit_loss, image_fit_evaluations, image_fit_curve,
    image_fit_ms_per_evaluation, image_fit_backend, image_fit_start
        After a fit to the pattern image (:mod:`restoration.inverse_rendering`): the median
        dot's share of its light the fit explains, the loss after each pass, the loss
        evaluations, the loss after each iteration (from the start's), the descents' time
        per evaluation (each one the model's image and its gradient), ms, where the fit ran
        (``"numpy"``, or Dr.Jit's ``"llvm"`` or ``"cuda"``), and the method whose surface it
        started from.
    view_residual_px, view_residual_p90_px
        Where camera v's view weighed the level (:mod:`restoration.view_level`): the median
        of the misses of its lines of sight through the surface against the flow's object
        points, flat-water px, and their 90th percentile over the samples synthetic
        Schlieren's edge margin inside the object's texture (where the flow is trusted).
    view_served_share, view_textured_share
        Where the view was asked (:mod:`restoration.view_level`): the share of camera v's
        samples in view that the flow served, or, where the flat view showed too little
        texture for the flow to be run, the share of them on texture (the view weighs the
        level from a served share of 0.6).
    source_difference_mm
        Where another method's surface set the level (:mod:`restoration.schlieren_level`):
        the RMS difference between this surface's samples and it, once levelled, mm.
    pattern_alias_ratio, pattern_matched_share, pattern_residual_px
        Where camera s's spots set the level without labels (``pattern``,
        :mod:`restoration.pattern_level`): the best level's score over the runner-up's, the
        share of the dots' predicted spots that land on a detected spot, and their median
        miss, px.

    Examples
    --------
    >>> from restoration.surface import Anchor
    >>> a = Anchor("gauge", 150.0)
    >>> a.update(refine_passes=8)
    >>> a.to_dict()
    {'method': 'gauge', 'anchor_mm': 150.0, 'refine_passes': 8}
    """

    method: str = ""
    anchor_mm: float | None = None
    searched_mm: float | None = None
    sigma_mm: float | None = None
    evaluations: int | None = None
    refine_passes: int | None = None
    fit_rms_mm: float | None = None
    fit_iterations: int | None = None
    fit_level_offset_mm: float | None = None
    fit_level_sigma_mm: float | None = None
    fit_level_probes: int | None = None
    fit_level_probes_converged: int | None = None
    fit_level_kept_start: bool | None = None
    fit_level_reason: str | None = None
    image_fit_explained: float | None = None
    image_fit_loss: list[float] | None = None
    image_fit_evaluations: int | None = None
    image_fit_curve: list[float] | None = None
    image_fit_ms_per_evaluation: float | None = None
    image_fit_backend: str | None = None
    image_fit_start: str | None = None
    view_residual_px: float | None = None
    view_residual_p90_px: float | None = None
    view_served_share: float | None = None
    view_textured_share: float | None = None
    source_difference_mm: float | None = None
    pattern_alias_ratio: float | None = None
    pattern_matched_share: float | None = None
    pattern_residual_px: float | None = None

    def update(self, **values: Any) -> None:
        """Set the named fields.

        Raises
        ------
        TypeError
            For a name that is not a field.
        """
        for name, value in values.items():
            if not hasattr(self, name) or name.startswith("_"):
                raise TypeError(f"Anchor has no field {name!r}")
            setattr(self, name, value)

    def to_dict(self) -> dict[str, Any]:
        """The fields that are set, as plain values."""
        return {f.name: getattr(self, f.name) for f in fields(self)
                if getattr(self, f.name) is not None}


N_SETS = 4
"""Interleaved edge sets whose separate minima measure the anchor's standard error."""


def anchor_sigma_mm(anchors_mm: NDArray, set_ms: NDArray, reach_mm: float) -> float:
    """Standard error of the anchor from the spread of the edge sets' own minima, mm.

    Parameters
    ----------
    anchors_mm : (A,) ndarray
        Anchors evaluated, mm.
    set_ms : (A, N_SETS) ndarray
        Mean squared residual of each edge set at each anchor, mm^2.
    reach_mm : float
        A set's minimum further than this outside the evaluated anchors counts as not found.

    Returns
    -------
    float
        ``std(minima) / sqrt(N_SETS)``, mm; infinite when any set has no minimum in reach (the
        data do not pin the anchor).
    """
    vertices = np.array([parabola_vertex(anchors_mm, set_ms[:, k]) for k in range(N_SETS)])
    lo, hi = anchors_mm.min() - reach_mm, anchors_mm.max() + reach_mm
    if not (np.isfinite(vertices).all() and np.all((vertices >= lo) & (vertices <= hi))):
        return float("inf")
    return float(np.std(vertices, ddof=1) / np.sqrt(N_SETS))


def parabola_vertex(x: NDArray, y: NDArray) -> float:
    """Abscissa of the minimum of the least-squares parabola through ``(x, y)``; NaN when the
    parabola opens downwards or the fit is undetermined."""
    if x.size < 3 or not np.isfinite(y).all():
        return float("nan")
    a, b, _ = np.polyfit(x - x.mean(), y, 2)
    return float(x.mean() - b / (2 * a)) if a > 0 else float("nan")
