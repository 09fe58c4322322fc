"""The structured light's level pinned by camera v's view (``--method structured-light-view``).

One spot per projector ray fixes the surface only together with its level: raise the surface
and bend it back, and every spot stays within microns (:mod:`restoration.anchor`). The
integrability of the slopes pins the level where the spots are sharp (0.005 mm standard error
on smooth water), but a spot error of 0.06 px already leaves it 0.09 mm uncertain, and
micro-roughness (GGX alpha 0.01) blurs the spots to that (docs/results.md, "Rough water").

Camera v sees the same surface from below. Where the object carries texture at the waves'
scale (a lab tank's speckle, ``[object] texture = "speckle"``), the dense flow from its view
to its flat-water view gives, for each of its sample pixels, the object point its line of
sight reaches through the waves (:func:`restoration.schlieren.flow_samples`). A surface at the
wrong level has the wrong slopes (the depth-normal ambiguity tilts them), and those slopes
send camera v's lines of sight elsewhere on the object: the view's residual, each sample's
line traced through the structured light's surface to the object against where the flow put
it (flat-water pixels), is least at the right level. :func:`find_view_level` probes it around
the integrability level, takes the vertex of a parabola through the probes, and its standard
error from the spread of four interleaved sample sets' own vertices.

The method is the structured light with that level (every other stage as it is), and a frame
whose level's standard error exceeds the structured light's bound is ``uncertain_level`` as
before. The view checks the surface too: where its lines of sight miss the flow's object points
by more than :data:`~restoration.frame_status.VIEW_MAX_RESIDUAL_PX` (median), the surface is
wrong (labels shifted by whole dots leave 4 px) and the frame ``inconsistent``. It needs the
rig's flat-water view of the object (``view_flat``; a render's ``view_truth`` is that view) and
an object with texture: the paper's 200 mm checkerboard gives the flow too little to follow
(docs/results.md). Whether it has is judged first on the flat-water view alone
(:func:`textured_share`, a few milliseconds): where too few samples lie on texture for the
flow to serve, the flow (0.3-0.6 s) is not computed and the frame is the structured light's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np
from numpy.typing import NDArray

from restoration.calibration import Calibration
from restoration.features import Matches, ReferenceGrid
from restoration.frame_status import VIEW_MAX_RESIDUAL_PX, unpinned_patch
from restoration.observations import Observations
from restoration.options import SchlierenOptions, StructuredLightOptions, checked_options
from restoration.schlieren import (
    LastFlow,
    SightLines,
    cached_lattice,
    flat_view_file,
    flow_samples,
)
from restoration.structured_light import StructuredLight, reconstruct_at, shifted_surface
from restoration.surface import SurfaceEstimate
from wai_core.errors import RestorationFailed
from wai_core.images import find_image
from wai_core.optics import trace_to_object
from wai_core.timings import Timings

__all__ = [
    "ViewLevel", "ViewLevelCalibration", "ViewSamples", "StructuredLightView", "find_view_level",
    "textured_share", "view_samples",
]

Array = NDArray[np.float64]

CLIP_PX = 2.0
"""A sample's view residual counts up to this (flat-water px) while the level is searched: a
line of sight that meets the object far from its flow point (a flow error, a patch edge)
weighs no more than one this far."""
FINE_CLIP_TIMES = 3.0
"""Once found, the level is found again with each residual clipped at this many times the
samples' median residual at it (within :data:`FINE_CLIP_MIN_PX` and :data:`CLIP_PX`): the
frame's own flow noise sets what an outlier is. A few flow errors within 2 px weigh as much
as hundreds of samples at the noise's 0.1-0.3 px and pull the level with them; on rough
water, where the blurred view keeps flows the smooth one rejects, they moved it 0.03-0.1 mm
(docs/results.md, "The level's outliers")."""
FINE_CLIP_MIN_PX = 0.5
"""The fine clip's floor (px): on smooth water a right surface's samples miss by 0.03-0.07 px
(median), and a clip at a few times that weighs the noise's own tail as outliers (at 0.35 px
a smooth frame's level went 0.011 → 0.033 mm off; at 0.5, as at 0.75, none lost)."""
PROBE_MM = 0.3
"""First probes' distance either side of the integrability level, mm."""
MAX_PROBES = 9
"""Most levels probed (each one surface and one trace of the samples)."""
VERTEX_TOL_MM = 0.02
"""The search stops once the parabola's vertex lies this close to a level already probed."""
N_SETS = 4
"""Interleaved sample sets (by the lattice's parity) whose own vertices give the standard
error."""
SERVED_SHARE = 0.6
"""The share of camera v's samples in view the flow must serve (its round trip within
Schlieren's check) for the view to weigh the level or check the surface. A speckle object,
smooth or rough water, a real rig: 0.82-0.91; the paper's 200 mm checkerboard: 0.31, where the
flow's errors inside the squares pull the level (0.086 mm against the spots' 0.029 mm on the
compare cases) and miss 1.2-1.7 px at the 90th percentile through a right surface."""
TEXTURE_PRESMOOTH_PX = 1.0
"""Gaussian blur of the flat-water view before its gradients (:func:`textured_share`), px: the
render's or the sensor's pixel noise is no texture the flow can follow."""
TEXTURE_SIGMA_PX = 4.0
"""Scale of the flat-water view's structure tensor, px: about the flow's patch."""
TEXTURE_MIN_EIGEN = 3e-4
"""Smaller eigenvalue of the structure tensor (grey levels in [0, 1], per px squared) above
which a sample lies on texture that fixes both directions of the flow."""
TEXTURE_MIN_SHARE = 0.45
"""The share of camera v's samples on texture below which the flow is not computed. The
flat view predicts the flow's share from above: the paper's checkerboard 0.22-0.26 on texture
(smooth water, the sensor's noise, rough water's noisier view), 0.17-0.41 served; a speckle
0.76-0.88 on texture, 0.59-0.95 served (alpha 0.02 the least). Below this, no frame has reached
:data:`SERVED_SHARE`."""


@dataclass
class ViewLevelCalibration(Calibration):
    """The structured light's calibration with camera v's flat-water view of the object
    (``view_flat``, or a render's ``view_truth``) among the frame's images, and camera v's
    sample lattice.

    Examples
    --------
    >>> from wai_core import load_system
    >>> ViewLevelCalibration(load_system("paper")).IMAGES[-1]
    'view_flat'
    """

    _lattices: dict[int, SightLines] = field(default_factory=dict, init=False, repr=False,
                                             compare=False)
    flows: LastFlow = field(default_factory=LastFlow, init=False, repr=False, compare=False)

    IMAGES: ClassVar[tuple[str, ...]] = ("pattern", "pattern_flat", "view", "view_flat")

    def image_files(self, folder: str | Path) -> dict[str, Path]:
        """The structured light's images and the flat-water view
        (:func:`~restoration.schlieren.flat_view_file`)."""
        return {**{name: find_image(folder, name) for name in Calibration.IMAGES},
                "view_flat": flat_view_file(folder)}

    def lattice(self, step_px: int) -> SightLines:
        """Camera v's sample pixels every ``step_px`` and their lines of sight."""
        return cached_lattice(self, self._lattices, step_px)


@dataclass(frozen=True)
class ViewSamples:
    """The frame's view samples: camera v's sample pixels whose object point the flow gives.

    Attributes
    ----------
    px : (K, 2) ndarray
        The sample pixels ``(col, row)`` (camera v's ideal pinhole).
    object_mm : (K, 3) ndarray
        The object point each one's line of sight reaches through the waves, mm.
    mm_per_px : (K,) ndarray
        The object's extent of one flat-water pixel there, mm.
    sets : (K,) ndarray of int
        Each sample's interleaved set (0 .. N_SETS - 1).
    counts : dict
        :func:`~restoration.schlieren.flow_samples`'s counts.
    textured_share : float or None
        Where the flow was not run: the share of the samples in view on the flat view's
        texture (:func:`textured_share`, below :data:`TEXTURE_MIN_SHARE`); None where it ran.
    inner : (K,) ndarray of bool or None
        The samples synthetic Schlieren's edge margin inside the flat view's textured part
        (:class:`~restoration.schlieren.FlowSamples`), where the flow is trusted to check a
        part of the surface; None: every sample.
    """

    px: Array
    object_mm: Array
    mm_per_px: Array
    sets: NDArray[np.int64]
    counts: dict[str, int]
    textured_share: float | None = None
    inner: NDArray[np.bool_] | None = None

    @property
    def served(self) -> bool:
        """Whether the flow serves enough of the samples in view (:data:`SERVED_SHARE`) to
        weigh the level."""
        return len(self.px) >= max(N_SETS * 8, SERVED_SHARE * self.counts["samples"])


def textured_share(view_flat: NDArray, px: Array) -> float:
    """The share of the pixels ``px`` (K, 2: col, row) at which the flat-water view
    ``view_flat`` (H, W[, 3], linear) has texture in both directions: the smaller eigenvalue of
    its structure tensor (grey from its 0.5th to its 99.5th percentile as 0 to 1, blurred by
    :data:`TEXTURE_PRESMOOTH_PX`; the gradients' products smoothed over
    :data:`TEXTURE_SIGMA_PX`) above :data:`TEXTURE_MIN_EIGEN`.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> px = rng.uniform(20, 140, (200, 2))
    >>> round(textured_share(np.full((160, 160), 0.5), px), 2)
    0.0
    >>> import cv2
    >>> speckle = cv2.GaussianBlur(rng.random((160, 160)).astype(np.float32), (0, 0), 2.0)
    >>> textured_share(speckle, px) > 0.9
    True
    """
    grey = np.asarray(view_flat, dtype=np.float32)
    if grey.ndim == 3:  # the channels' sum: the grey's scale goes with the percentiles below
        grey = sum(grey[..., c] for c in range(grey.shape[-1]))
    lo, hi = np.percentile(grey, [0.5, 99.5])
    grey = (grey - lo) / (hi - lo if hi > lo else 1.0)
    grey = cv2.GaussianBlur(np.clip(grey, 0.0, 1.0).astype(np.float32), (0, 0),
                            TEXTURE_PRESMOOTH_PX)
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    jxx, jyy, jxy = (cv2.GaussianBlur(a, (0, 0), TEXTURE_SIGMA_PX)
                     for a in (gx * gx, gy * gy, gx * gy))
    smaller = 0.5 * (jxx + jyy - np.sqrt((jxx - jyy) ** 2 + 4.0 * jxy**2))
    if not len(px):
        return 0.0
    h, w = grey.shape
    cols = np.clip(np.rint(px[:, 0]).astype(int), 0, w - 1)
    rows = np.clip(np.rint(px[:, 1]).astype(int), 0, h - 1)
    return float(np.mean(smaller[rows, cols] > TEXTURE_MIN_EIGEN))


def view_samples(images: dict[str, NDArray], cal: ViewLevelCalibration) -> ViewSamples:
    """The view samples of one frame (``images``: ``view`` and ``view_flat``), on synthetic
    Schlieren's lattice and flow (:class:`~restoration.options.SchlierenOptions`' defaults,
    but every sample up to the object's edge: the level's residual is clipped at
    :data:`CLIP_PX`, so a sample the flow gets wrong there weighs little, and the level
    search keeps more of the structured light's patch); none, and no flow computed, where too
    few of the samples lie on the flat view's texture (:data:`TEXTURE_MIN_SHARE`; their share
    in ``textured_share``)."""
    options = SchlierenOptions(edge_margin_px=0.0)
    lines = cal.lattice(options.sample_step_px)
    reach = lines.px[lines.reach]
    textured = textured_share(cal.radiance(images["view_flat"]), reach)
    if textured < TEXTURE_MIN_SHARE:
        n = int(len(reach))
        return ViewSamples(np.empty((0, 2)), np.empty((0, 3)), np.empty(0),
                           np.empty(0, dtype=np.int64), {"samples": n, "matched": 0}, textured)
    served = flow_samples(images, cal, options)
    index = np.flatnonzero(served.kept)
    ij = served.lines.ij[index]
    return ViewSamples(served.lines.px[index], served.object_mm[index],
                       served.mm_per_px[index], (ij[:, 0] % 2) * 2 + ij[:, 1] % 2,
                       served.counts, inner=served.inner[index])


def view_residual_px(surface: SurfaceEstimate, samples: ViewSamples,
                     cal: Calibration) -> Array:
    """Each sample's line of sight traced through ``surface`` to the object, against its flow
    point, in flat-water pixels (K,); NaN where the line misses the surface's patch."""
    cfg = cal.cfg
    traced = trace_to_object(cal.camera_v_grey, surface.heightfield, cfg.water.h0_mm,
                             cal.view_index, cfg.object_z_mm, samples.px[:, 0],
                             samples.px[:, 1])
    return np.linalg.norm(traced.object_mm - samples.object_mm, axis=1) / samples.mm_per_px


@dataclass
class ViewLevel:
    """:func:`find_view_level`'s result.

    Attributes
    ----------
    anchor_mm, sigma_mm : float
        The level (the reconstruction's anchor) and its standard error, mm.
    probes_mm, cost_px2 : (P,) ndarray
        The levels probed, sorted, and the mean clipped squared view residual at each, px^2.
    estimate : SurfaceEstimate
        The surface at ``anchor_mm``.
    samples : int
        Samples that weighed (inside the surface's patch at every probe).
    """

    anchor_mm: float
    sigma_mm: float
    probes_mm: Array
    cost_px2: Array
    estimate: SurfaceEstimate
    samples: int


def _vertex(x: Array, y: Array) -> float | None:
    """The vertex of the least-squares parabola through ``(x, y)`` (3 or more), or None
    where it opens downwards."""
    a, b, _ = np.polyfit(x - x.mean(), y, 2)
    return None if not a > 0 else float(x.mean() - b / (2 * a))


def find_view_level(rebuild: Callable[[float], SurfaceEstimate], start_mm: float,
                    samples: ViewSamples, cal: Calibration) -> ViewLevel | None:
    """The level at which the structured light's surface sends camera v's lines of sight
    where the flow does (module notes), searched from ``start_mm``; None where the probes
    find no minimum or the samples leave the surface's patch.

    ``rebuild(level_mm)`` is the structured light's surface anchored at that level.
    """
    residuals: dict[float, Array] = {}

    def probe(level: float) -> None:
        residuals[level] = view_residual_px(rebuild(level), samples, cal)

    for level in (start_mm - PROBE_MM, start_mm, start_mm + PROBE_MM):
        probe(level)
    clip, fine = CLIP_PX, False
    while True:
        levels = np.array(sorted(residuals))
        stack = np.array([residuals[a] for a in levels])
        inside = np.isfinite(stack).all(axis=0)
        if inside.sum() < N_SETS * 8:
            return None
        cost = np.mean(np.minimum(stack[:, inside], clip) ** 2, axis=1)
        best = int(np.argmin(cost))
        near = slice(max(best - 1, 0), min(best + 2, len(levels)))
        vertex = _vertex(levels[near], cost[near]) if cost[near].size == 3 else None
        if vertex is None:  # the minimum at the probes' edge: step out
            vertex = levels[best] + (PROBE_MM if best == len(levels) - 1 else -PROBE_MM)
        settled = np.abs(levels - vertex).min() < VERTEX_TOL_MM
        if settled and not fine:  # found: the frame's own noise now sets the clip
            noise = float(np.median(stack[best, inside]))
            clip, fine = float(np.clip(FINE_CLIP_TIMES * noise, FINE_CLIP_MIN_PX, CLIP_PX)), True
            continue
        if settled or len(levels) >= MAX_PROBES:
            break
        probe(float(np.clip(vertex, levels[0] - PROBE_MM, levels[-1] + PROBE_MM)))
    if best in (0, len(levels) - 1):
        return None
    level = _vertex(levels[near], cost[near])
    if level is None:
        return None
    # Each interleaved set's own vertex over the same three probes: their spread.
    clipped = np.minimum(stack[near][:, inside], clip) ** 2
    sets = samples.sets[inside]
    own = [_vertex(levels[near], clipped[:, sets == k].mean(axis=1)) for k in range(N_SETS)
           if np.any(sets == k)]
    if any(v is None for v in own) or len(own) < 2:
        return None
    sigma = float(np.std(own, ddof=1) / np.sqrt(len(own)))
    estimate = rebuild(level)
    return ViewLevel(level, sigma, levels, cost, estimate, int(inside.sum()))


PIN_FACTOR = 4.0
"""Camera v's view pins a small patch's labels when one labelling's lines of sight meet the
flow's object points (median miss within
:data:`~restoration.frame_status.VIEW_MAX_RESIDUAL_PX`) and every labelling a dot from it
misses by this many times as much, and past that bound too. On rough water (GGX alpha 0.01)
the right labels leave 0.25 px and the labels a dot off 6-15 px (docs/results.md)."""
_ONE_DOT = np.array([[di, dj] for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj])


class StructuredLightView(StructuredLight):
    """The structured light with its level pinned by camera v's view (module notes),
    configured once.

    Examples
    --------
    >>> from restoration import StructuredLightView
    >>> StructuredLightView().name
    'structured-light-view'
    """

    name = "structured-light-view"
    calibration_type = ViewLevelCalibration
    options_type = StructuredLightOptions

    def __init__(self, options: StructuredLightOptions | None = None) -> None:
        super().__init__(checked_options(self.name, StructuredLightOptions, options))

    def __repr__(self) -> str:
        return f"StructuredLightView({self.options!r})"

    def _pin_labels(self, features: Matches, obs: Observations, surface: SurfaceEstimate,
                    reference: ReferenceGrid, cal: Calibration, images: dict[str, NDArray],
                    memo: dict[str, Any], timings: Timings
                    ) -> tuple[Matches, Observations, SurfaceEstimate]:
        """A small patch whose labels the pattern leaves open (it would be ``sparse``:
        :func:`~restoration.frame_status.unpinned_patch`) pinned by the view where it can be.

        The labelling and each of its one-dot shifts are rebuilt at the level the view gives
        them, and their lines of sight traced to the object; where one of them meets the
        flow's object points and every other misses by :data:`PIN_FACTOR` times as much, that
        one is kept and its labels are pinned (``counts``: ``labels_ambiguous`` 0,
        ``labels_pinned_by_view`` 1; ``label_shift_di``/``dj`` add its shift). Otherwise
        everything is as it was (``labels_pinned_by_view`` 0). Up to nine view-level searches,
        on such frames only: 0.4-1.5 s more a frame on a loaded 2-core machine."""
        if not unpinned_patch(features, reference):
            return features, obs, surface

        def miss_of(o: Observations, est: SurfaceEstimate) -> float:
            try:
                miss = self._level(o, cal, est, images, memo, timings).anchor.view_residual_px
            except RestorationFailed:
                return np.inf
            return np.inf if miss is None else float(miss)

        features.counts["labels_pinned_by_view"] = 0
        misses = [miss_of(obs, surface)]
        if not np.isfinite(misses[0]):  # the view weighs nothing here (no texture, no flow)
            return features, obs, surface
        tried = [(np.zeros(2, np.int64), features, obs, surface)]
        for step in _ONE_DOT:
            with timings("surface"):
                built = shifted_surface(features, step, reference, cal, self.options)
            if built is None:
                continue
            tried.append((step, *built))
            misses.append(miss_of(built[1], built[2]))
        best = int(np.argmin(misses))
        rest = np.delete(np.asarray(misses), best)
        if not (len(rest) and misses[best] <= VIEW_MAX_RESIDUAL_PX
                and np.all(rest > max(VIEW_MAX_RESIDUAL_PX, PIN_FACTOR * misses[best]))):
            return features, obs, surface
        step, f, o, est = tried[best]
        base = features.counts
        f.counts.update(
            labels_ambiguous=0, labels_pinned_by_view=1,
            label_shift_di=int(base.get("label_shift_di", 0) + step[0]),
            label_shift_dj=int(base.get("label_shift_dj", 0) + step[1]),
        )
        return f, o, est

    def _level(self, obs: Observations, cal: Calibration, surface: SurfaceEstimate,
               images: dict[str, NDArray], memo: dict[str, Any],
               timings: Timings) -> SurfaceEstimate:
        """``surface`` rebuilt at the level the view pins, from its integrability level;
        as it is where the view cannot weigh the level (the anchor's ``method`` says which)."""
        options = self.options
        if options.anchor != "integrability" or surface.anchor.anchor_mm is None:
            return surface
        with timings("surface"):  # part of the surface's estimate, timed with it
            if "samples" not in memo:
                memo["samples"] = view_samples(images, cal)
            samples: ViewSamples = memo["samples"]
            in_view = max(samples.counts["samples"], 1)
            if samples.textured_share is not None:  # too little texture: no flow was run
                surface.anchor.update(view_textured_share=samples.textured_share)
                return surface
            served = len(samples.px) / in_view
            if not samples.served:
                surface.anchor.update(view_served_share=served)
                return surface

            passes = int(surface.anchor.refine_passes or options.n_refine)

            def rebuild(level: float) -> SurfaceEstimate:
                if not level > cal.diffuser_z_mm:
                    raise RestorationFailed(
                        "reconstruct_surface: the water level h0 must lie above the diffuser")
                return reconstruct_at(obs, level, options, passes)

            found = find_view_level(rebuild, float(surface.anchor.anchor_mm), samples, cal)
            if found is not None:
                est = found.estimate
                est.anchor.update(method="view", anchor_mm=found.anchor_mm,
                                  sigma_mm=found.sigma_mm, searched_mm=found.anchor_mm,
                                  evaluations=len(found.probes_mm) + 1,
                                  refine_passes=surface.anchor.refine_passes)
            else:  # no level of its own: the view still checks the surface
                est = surface
            est.anchor.update(view_served_share=served)
            miss = view_residual_px(est, samples, cal)
            finite = np.isfinite(miss)
            # The tail only where the flow is trusted: near the object's edge it matches the
            # texture to what lies past it (docs/results.md, "The view's tail is read where
            # the flow is trusted").
            inner = miss[finite if samples.inner is None else finite & samples.inner]
            miss = miss[finite]
            if miss.size:
                est.anchor.update(view_residual_px=float(np.median(miss)))
            if inner.size:
                est.anchor.update(view_residual_p90_px=float(np.percentile(inner, 90)))
        return est
