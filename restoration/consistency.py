"""Does the restored surface explain what was seen? A truth-free forward check of each frame.

From the reconstructed surface, the exact geometric model predicts where every matched dot's
spot must be: the dot's projector ray meets the surface, reflects about its normal, meets the
diffuser and is imaged by camera s. The distance between that prediction and the detected
spot is the dot's *residual* (px). A surface that is right reproduces the spots to about the
detector's noise; one that is wrong in level or shape (an unconverged refinement, wrong
labels, a surface the method cannot follow) does not, because the reflected rays magnify
slope errors on the way to the diffuser (a 1 mrad slope error moves a spot by ~2 mrad times
the 50-100 mm path).

Threshold
---------
A frame is ``inconsistent`` when its median residual exceeds :data:`INCONSISTENT_FRACTION`
of the median dot spacing in camera s (in px, from the flat-water reference: the scale that
every pixel constant of the pattern follows, so a finer camera gets a proportionally larger
threshold in px). On the paper's rig (13 px median spacing) that is 0.33 px. It was set
between two measured populations, not tuned to one frame: frames restored to under 0.3 mm
RMSE give median residuals of 0.03-0.12 px (0.002-0.009 spacings; the detector's own error
on rendered spots is 0.05-0.07 px), while frames whose surface is wrong by 0.6-3 mm give
0.6-1.1 px (0.05-0.08 spacings); ``wai experiment stability`` records both rates on every
sweep frame (docs/results.md). A frame right in most of its area and wrong in a part (a patch
of labels shifted by whole dots, outvoted in the median) is caught by its tail: where the
spots' residuals are large together, not one by one. Each sample's *local residual* is the
median of its own and its :data:`TAIL_NEIGHBOURS` nearest samples' residuals, and the frame is
``inconsistent`` when the 95th percentile of the local residuals passes :data:`TAIL_FACTOR`
times the threshold (:attr:`Consistency.tail_consistent`). Rough water scatters single spots
far (a noisy centroid beside neighbours that fit): a wrong part moves its spots together.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from restoration.normals import ray_origins
from restoration.reverse_trace._kernels import spline_jet
from restoration.reverse_trace._surface import SplinePatches, check_patches
from wai_core.geometry import PinholeCamera
from wai_core.heightfield import Heightfield
from wai_core.light_paths import pack_camera, reflected_spot_px

__all__ = ["GROSS_FRACTION", "INCONSISTENT_FRACTION", "TAIL_FACTOR", "TAIL_NEIGHBOURS",
           "UNCHECKED_REACH",
           "Consistency", "spot_consistency", "unchecked_beside"]

Array = NDArray[np.float64]

INCONSISTENT_FRACTION = 0.025
"""Median spot residual, as a fraction of the median dot spacing in px, above which a frame's
surface cannot be right (see the module notes)."""
GROSS_FRACTION = 0.2
"""A sample whose residual exceeds this fraction of the median dot spacing is not reproduced at
all: a spot given the wrong dot's label, or a detection that is no single spot. The surface
around it follows that sample, not the water. On the paper's rig (13 px spacing) that is 2.6
px, 20-80 times the detector's own error; of 120 frames restored right, six hold one such
sample (a merged or cut spot) and none two, while the frames wrong over a region hold 3-6 of
them, side by side (docs/results.md, "Knowing when a frame is wrong")."""
TAIL_FACTOR = 1.75
"""A frame whose samples' local residuals (:data:`TAIL_NEIGHBOURS`) pass this many times the
threshold at their 95th percentile is wrong in a part, even with its median within it: a patch
of labels shifted by whole dots that the rest of the frame outvotes. Set between measured
populations (docs/results.md, "A part missed together"): over 543 frames of the error budget
and of ``wai experiment compare``'s stored cases, the 398 that no other check flags and that
are right (RMSE within 0.05 mm) reach at most 1.52; a steep sea's frame with a strip astray
(0.064 mm RMSE) reaches 3.7. On each sample's own residual (the 95th percentile at twice the
threshold) the rule flagged three right rough or rippled frames whose noisy spots stood apart
(2.1-2.8 times the threshold)."""
TAIL_NEIGHBOURS = 8
"""Nearest samples (besides itself) whose residuals' median is a sample's local residual."""
_NEWTON_STEPS = 3  # ray-surface hit, started at the sample: it moves by well under a cell


@dataclass
class Consistency:
    """How well the surface predicts the detected spots.

    Attributes
    ----------
    residual_px : (K,) ndarray
        Predicted minus detected spot distance per sample, px (NaN where the ray misses the
        known surface).
    median_px, p95_px : float
        Median and 95th percentile of the finite residuals, px.
    threshold_px : float
        The frame's threshold on the median (see :data:`INCONSISTENT_FRACTION`).
    n_predicted : int
        Samples whose ray met the surface.
    surface : Heightfield
        The surface checked.
    xy_mm : (K, 2) ndarray
        The samples' positions, mm.
    """

    residual_px: Array
    median_px: float
    p95_px: float
    threshold_px: float
    n_predicted: int
    surface: Heightfield = field(repr=False)
    xy_mm: Array = field(repr=False)

    @cached_property
    def residual_map_px(self) -> Array:
        """(m, n): the nearest sample's residual at each known node of the surface's grid, px
        (NaN off the surface): where the surface is trusted. Made on first read (it costs a
        nearest-neighbour query per node; the per-frame check needs only the figures)."""
        out = np.full(self.surface.z.shape, np.nan)
        known = np.isfinite(self.surface.z)
        finite = np.isfinite(self.residual_px)
        if finite.any() and known.any():
            xx, yy = np.meshgrid(self.surface.x, self.surface.y)
            _, nearest = cKDTree(self.xy_mm[finite]).query(np.column_stack([xx[known], yy[known]]))
            out[known] = self.residual_px[finite][nearest]
        return out

    @cached_property
    def confidence(self) -> Array:
        """(m, n): ``2 ** -(residual / threshold) ** 2``, 1 where the spots are reproduced,
        0.5 at the threshold, towards 0 beyond; NaN off the surface."""
        return np.exp2(-((self.residual_map_px / self.threshold_px) ** 2))

    @property
    def consistent(self) -> bool:
        """Whether the median residual is within the threshold."""
        return bool(self.median_px <= self.threshold_px)

    @cached_property
    def local_p95_px(self) -> float:
        """The 95th percentile of the samples' local residuals (each the median of its own
        and its :data:`TAIL_NEIGHBOURS` nearest samples' residuals in ``xy_mm``), px. NaN
        (not worked out) where fewer samples than a neighbourhood's majority pass
        :data:`TAIL_FACTOR` times the threshold, so that no local residual can, and with fewer
        samples than a neighbourhood.

        Examples
        --------
        >>> import numpy as np
        >>> xy = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0)), -1).reshape(-1, 2)
        >>> far = np.random.default_rng(0).permutation(400)[:20]  # a spot in 20, anywhere
        >>> scattered = np.where(np.isin(np.arange(400), far), 1.0, 0.1)
        >>> patch = np.where((xy[:, 0] < 5) & (xy[:, 1] < 5), 1.0, 0.1)  # 25 spots together
        >>> def check(r):
        ...     return Consistency(r, 0.1, float(np.percentile(r, 95)), 0.3, 400, None, xy)
        >>> check(scattered).local_p95_px, check(patch).local_p95_px
        (0.1, 1.0)
        """
        finite = np.isfinite(self.residual_px)
        k = TAIL_NEIGHBOURS + 1
        if finite.sum() < k:
            return float("nan")
        residual = self.residual_px[finite]
        if np.count_nonzero(residual > TAIL_FACTOR * self.threshold_px) < k // 2 + 1:
            return float("nan")
        xy = self.xy_mm[finite]
        _, nearest = cKDTree(xy).query(xy, k=k)
        return float(np.percentile(np.median(residual[nearest], axis=1), 95))

    @property
    def tail_consistent(self) -> bool:
        """Whether the 95th percentile of the samples' local residuals
        (:attr:`local_p95_px`) is within :data:`TAIL_FACTOR` times the threshold."""
        return bool(not self.local_p95_px > TAIL_FACTOR * self.threshold_px)

    @property
    def gross_px(self) -> float:
        """The residual beyond which a sample is not reproduced at all (see
        :data:`GROSS_FRACTION`), px."""
        return self.threshold_px * GROSS_FRACTION / INCONSISTENT_FRACTION

    @property
    def gross(self) -> NDArray[np.bool_]:
        """(K,) bool: the samples the surface does not reproduce at all (residual above
        :attr:`gross_px`)."""
        return np.nan_to_num(self.residual_px, nan=0.0) > self.gross_px

    def where_gross(self) -> str:
        """Where the :attr:`gross` samples lie, in words (their count and the middle of them,
        lab mm)."""
        g = self.gross
        if not g.any():
            return "nowhere"
        x, y = np.median(self.xy_mm[g], axis=0)
        return f"{int(g.sum())} spots around x = {x:.0f}, y = {y:.0f} mm"

    def summary(self) -> dict[str, Any]:
        """Plain values for ``metrics.json`` (``residual_local_p95_px``: the tail rule's figure,
        :attr:`local_p95_px`, None where not worked out; ``confident_fraction``: of the
        samples, those whose residual is within the threshold)."""
        finite = np.isfinite(self.residual_px)
        return {
            "residual_median_px": self.median_px,
            "residual_p95_px": self.p95_px,
            "residual_local_p95_px": (self.local_p95_px if np.isfinite(self.local_p95_px)
                                      else None),
            "threshold_px": self.threshold_px,
            "consistent": self.consistent,
            "n_predicted": self.n_predicted,
            "n_gross": int(self.gross.sum()),
            "confident_fraction": float(np.mean(self.residual_px[finite] <= self.threshold_px))
            if finite.any() else 0.0,
        }


def predict_spots_px(
    surface: Heightfield,
    origin_mm: Array,
    dirs: Array,
    start_mm: Array,
    camera_s: PinholeCamera,
    z_h_mm: float,
    patches: SplinePatches | None = None,
) -> Array:
    """Camera-s pixels (K, 2) of rays ``origin + t dirs`` reflected by ``surface``.

    Parameters
    ----------
    surface : Heightfield
        Absolute heights, mm.
    origin_mm : (3,) or (K, 3) ndarray
        The projector centre, or each ray's origin (a projector behind a port), mm.
    dirs : (K, 3) ndarray
        Ray directions (upwards).
    start_mm : (K, 3) ndarray
        A point on each ray near its hit (the reconstruction's sample), mm.
    camera_s : PinholeCamera
    z_h_mm : float
        Height of the diffuser plane, mm.
    patches : SplinePatches, optional
        The spline table of ``surface`` (that very object, else
        :class:`~wai_core.errors.WaiInputError`), e.g. the one the frame's view uses; built
        for this call when omitted.

    Returns
    -------
    (K, 2) ndarray
        ``(col, row)`` px; NaN where the ray leaves the known surface.
    """
    # The same spline as Heightfield.height, and the table the view's solver evaluates.
    if patches is None:
        patches = SplinePatches(surface)
    else:
        check_patches(patches, surface, "predict_spots_px")
    camera = pack_camera(camera_s)
    px = np.empty((len(dirs), 2))
    _predict_kernel(
        patches.table, patches.cell_ok, patches.x, patches.y,
        ray_origins(origin_mm, len(dirs)), np.ascontiguousarray(dirs, dtype=float),
        np.ascontiguousarray(start_mm, dtype=float), camera, float(z_h_mm), _NEWTON_STEPS, px,
    )
    return px


@njit(cache=True, nogil=True, error_model="numpy")
def _predict_kernel(
    table, cell_ok, gx, gy, origin, dirs, start, camera, z_h, n_steps, px
):  # pragma: no cover
    """:func:`predict_spots_px` one ray at a time into ``px`` (K, 2): the ray-surface Newton on
    the spline table, then system S's reflection to camera s
    (:func:`wai_core.light_paths.reflected_spot_px`). ``camera`` (15,): camera s packed
    (:func:`wai_core.light_paths.pack_camera`)."""
    for k in range(dirs.shape[0]):
        ox, oy, oz = origin[k, 0], origin[k, 1], origin[k, 2]
        norm = math.sqrt(dirs[k, 0] * dirs[k, 0] + dirs[k, 1] * dirs[k, 1]
                         + dirs[k, 2] * dirs[k, 2])
        dx, dy, dz = dirs[k, 0] / norm, dirs[k, 1] / norm, dirs[k, 2] / norm
        t = (start[k, 2] - oz) / dz
        for _ in range(n_steps):
            h, hx, hy = spline_jet(table, cell_ok, gx, gy, ox + t * dx, oy + t * dy)[:3]
            t = t - ((oz + t * dz) - h) / (dz - hx * dx - hy * dy)
        x, y, z = ox + t * dx, oy + t * dy, oz + t * dz
        hx, hy = spline_jet(table, cell_ok, gx, gy, x, y)[1:3]
        px[k, 0], px[k, 1] = reflected_spot_px(x, y, z, dx, dy, dz, hx, hy, z_h, camera)


def spot_consistency(
    surface: Heightfield,
    points_mm: Array,
    origin_mm: Array,
    dirs: Array,
    spot_px: Array,
    camera_s: PinholeCamera,
    z_h_mm: float,
    spacing_px: float,
    patches: SplinePatches | None = None,
) -> Consistency:
    """The forward check of a reconstructed surface against its spots.

    Parameters
    ----------
    surface : Heightfield
        The reconstruction (absolute heights, mm).
    points_mm : (K, 3) ndarray
        Its samples (where each dot's ray met it), mm.
    origin_mm : (3,) or (K, 3) ndarray
        The projector centre, or each ray's origin (a projector behind a port), mm.
    dirs : (K, 3) ndarray
        The samples' projector rays.
    spot_px : (K, 2) ndarray
        The samples' detected spots in camera s, px.
    camera_s : PinholeCamera
    z_h_mm : float
    spacing_px : float
        Median dot spacing in camera s, px (sets the threshold).
    patches : SplinePatches, optional
        The spline table of ``surface`` (that very object), e.g. shared with the frame's
        :func:`~restoration.reverse_trace.restore_view`; built for this call when omitted.

    Returns
    -------
    Consistency

    Examples
    --------
    A flat mirror predicts its own spots exactly:

    >>> import numpy as np
    >>> from wai_core import Heightfield, load_rig
    >>> cfg = load_rig("paper")
    >>> from restoration.normals import projector_rays
    >>> from restoration import Calibration
    >>> from wai_core.light_paths import spots_through
    >>> ij = np.array([[i, j] for i in range(-3, 4) for j in range(-3, 4)])
    >>> panel = Calibration(cfg).panel_px(ij)
    >>> o, d = projector_rays(panel, cfg.rig.projector)
    >>> x, y = np.linspace(-200, 800, 101), np.linspace(-400, 400, 81)
    >>> flat = Heightfield(x, y, np.full((81, 101), cfg.water.h0_mm))
    >>> spots = spots_through(cfg.rig, flat, panel)
    >>> q = o + ((cfg.water.h0_mm - o[2]) / d[:, 2])[:, None] * d
    >>> c = spot_consistency(flat, q, o, d, spots, cfg.rig.camera_s, cfg.diffuser.z_mm, 13.0)
    >>> c.median_px < 1e-6, c.consistent
    (True, True)
    """
    pred = predict_spots_px(surface, origin_mm, dirs, points_mm, camera_s, z_h_mm, patches)
    residual = np.linalg.norm(pred - spot_px, axis=1)
    finite = np.isfinite(residual)
    median = float(np.median(residual[finite])) if finite.any() else float("inf")
    p95 = float(np.percentile(residual[finite], 95)) if finite.any() else float("inf")
    threshold = INCONSISTENT_FRACTION * float(spacing_px)
    return Consistency(
        residual, median, p95, threshold, int(finite.sum()), surface, points_mm[:, :2]
    )


UNCHECKED_REACH = 2
"""Lattice steps from a sample the surface did not reproduce within which the samples the
check could not reach (at the surface's edge) are left out with it."""


def unchecked_beside(ij: NDArray, check: Consistency) -> NDArray[np.bool_]:
    """(K,) bool: the samples (grid indices ``ij`` (K, 2)) whose residual the check could not
    compute, within :data:`UNCHECKED_REACH` dots of one it found wrong
    (:attr:`~restoration.consistency.Consistency.gross`): a wrong label seldom comes alone,
    and these could not say whether they share it."""
    gross = check.gross
    unchecked = np.isnan(check.residual_px)
    if not (gross.any() and unchecked.any()):
        return np.zeros(len(ij), bool)
    steps = np.abs(ij[unchecked][:, None, :] - ij[gross][None, :, :]).max(axis=2)
    out = np.zeros(len(ij), bool)
    out[np.flatnonzero(unchecked)[steps.min(axis=1) <= UNCHECKED_REACH]] = True
    return out
