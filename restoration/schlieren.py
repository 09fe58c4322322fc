"""Free-surface synthetic Schlieren on camera v: the surface from how the waves displace the
object in view (Moisy, Rabaud & Salsac, Exp. Fluids 2009), with no projector.

Camera v looks up through the water at a known object; a flat-water view of it is taken once
(``view_flat``; a render's flat-water view is its ``view_truth``). Per frame:

1. the dense optical flow from the view to the flat-water view (OpenCV's DIS; checked by the
   flow back): the flat-water pixel ``q`` showing what pixel ``p`` shows. Through flat water,
   ``q``'s line of sight reaches the object point ``X`` exactly (Snell at ``h0``), so ``p``'s
   line of sight, refracted by the wave, reaches ``X`` too;
2. on a lattice of pixels every ``sample_step_px``: where ``p``'s line of sight crosses the
   surface at height ``h`` (the point ``S``), the refracted direction is ``(X - S) / |X - S|``
   and Snell's law gives the normal, ``N ~ n d - a`` (``d`` the sight line in the water, ``a``
   the ray in the air): each pixel's slope, from the exact rig geometry (tilted camera, the
   object's distance, Snell at every pixel), not the linearised method's one paraxial
   constant;
3. the slopes are integrated with the restoration's integrators at the gauge's level and the
   samples moved along their sight lines to the integrated heights until they settle
   (:func:`~restoration.ray_surface.integrate_along_rays`); the slopes do not pin the level,
   so it is the gauge's ``h0`` (the field's methods give heights up to a constant: scores
   that compare shapes are the de-meaned ones); a wrong level bends the slopes, so the shape
   too is only as right as the level;
4. the truth-free check: each sample's line of sight traced through the surface to the
   object, against the flow's ``X`` (in flat-water pixels); a median residual above
   ``max_residual_px`` makes the frame ``inconsistent`` (a flow that follows no surface: an
   object without texture at the waves' scale, a checkerboard's plain squares); a frame it
   passes is ``gauge_level``, not ``ok``: nothing in the view tells the level; samples whose
   line of sight the check cannot trace through the surface are dropped and their part of
   the surface left unknown (:func:`verified_support`);
5. the view is restored by the same reverse ray tracing as the other methods'.

The object must carry texture at the scale of the waves: ``[object] texture = "speckle"`` is
a lab tank's random pattern; the paper's 200 mm checkerboard squares leave the flow
undetermined inside them (docs/results.md, "Methods compared").
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from restoration.calibration import RigCalibration
from restoration.consistency import Consistency
from restoration.integrate import MIN_SAMPLES, to_heightfield
from restoration.level import Anchor
from restoration.options import SchlierenOptions
from restoration.ray_surface import RaySurface, integrate_along_rays
from restoration.result import SPARSE_FRACTION, RestoreResult, Status
from wai_core.errors import RestorationFailed, WaiInputError
from wai_core.heightfield import Heightfield
from wai_core.images import find_image, locate_image
from wai_core.optics import trace_to_object
from wai_core.timings import Timings

__all__ = [
    "COARSE_PASSES", "GAUGE_LEVEL_MESSAGE", "FlowSamples", "LastFlow", "LevelRule", "Rebuild",
    "SchlierenCalibration", "SightLines",
    "cached_lattice", "flat_view_file", "flat_view_flow", "flow_samples",
    "reconstruct_schlieren", "restore_schlieren", "slopes_on_sight_lines",
]

Array = NDArray[np.float64]

METHOD = "schlieren"


class LastFlow:
    """A calibration's last frame's flow (:func:`flat_view_flow`) per quality, given again
    while the frame's ``view`` and ``view_flat`` are the same arrays: a method that asks twice
    for one frame (``schlieren-sl``'s level and its surface) computes it once.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> images = {"view": rng.random((60, 80)), "view_flat": rng.random((60, 80))}
    >>> flows, radiance = LastFlow(), (lambda image: image)
    >>> flows.of(images, radiance, "medium")[0] is flows.of(images, radiance, "medium")[0]
    True
    """

    def __init__(self) -> None:
        self._last: dict[str, tuple[Any, Any, tuple[NDArray, NDArray]]] = {}

    def __getstate__(self) -> dict:
        return {}  # a calibration sent to another process starts with no flow kept

    def __setstate__(self, state: dict) -> None:
        self._last = {}

    def of(self, images: dict[str, NDArray], radiance: Callable[[NDArray], NDArray],
           quality: str) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """:func:`flat_view_flow` of ``images``' view and flat view, each through
        ``radiance`` (the calibration's), at ``quality``."""
        view, flat = images["view"], images["view_flat"]
        last = self._last.get(quality)
        if last is not None and last[0]() is view and last[1]() is flat:
            return last[2]
        flow = flat_view_flow(radiance(view), radiance(flat), quality)
        try:
            self._last[quality] = (weakref.ref(view), weakref.ref(flat), flow)
        except TypeError:  # an image that takes no weak reference is not kept
            pass
        return flow


@dataclass
class SchlierenCalibration(RigCalibration):
    """What synthetic Schlieren knows: the rig (camera v, the water's level and index, the
    object's height) and, derived once, the lattice of sample pixels with their lines of sight.

    Examples
    --------
    >>> from wai_core import load_system
    >>> cal = SchlierenCalibration(load_system("paper"))
    >>> cal.image_size("view_flat")
    (600, 800)
    """

    _lattices: dict[int, SightLines] = field(default_factory=dict, init=False, repr=False,
                                             compare=False)
    flows: LastFlow = field(default_factory=LastFlow, init=False, repr=False, compare=False)

    IMAGES: ClassVar[tuple[str, ...]] = ("view", "view_flat")

    def image_files(self, folder: str | Path) -> dict[str, Path]:
        """The view and the rig's flat-water view in ``folder`` (:func:`flat_view_file`)."""
        return {"view": find_image(folder, "view"), "view_flat": flat_view_file(folder)}

    def lattice(self, step_px: int) -> SightLines:
        """The sample pixels every ``step_px`` and their lines of sight (kept per step)."""
        return cached_lattice(self, self._lattices, step_px)


def flat_view_file(folder: str | Path) -> Path:
    """The rig's flat-water view of the object in ``folder``: ``view_flat.*``, or where a
    render has none its ``view_truth.*`` (the flat-water view it renders for every frame, the
    reference a rig takes once).

    Raises
    ------
    WaiInputError
        When ``folder`` holds neither (naming ``view_flat``).
    """
    flat = locate_image(folder, "view_flat") or locate_image(folder, "view_truth")
    return flat if flat is not None else find_image(folder, "view_flat")


def cached_lattice(cal: RigCalibration, cache: dict[int, SightLines], step_px: int
                   ) -> SightLines:
    """``cal``'s camera-v lattice every ``step_px`` (:meth:`SightLines.build`), from ``cache``
    (a calibration's own, filled here)."""
    cached = cache.get(int(step_px))
    if cached is None:
        cached = SightLines.build(cal, int(step_px))
        cache[int(step_px)] = cached
    return cached


@dataclass(frozen=True)
class SightLines:
    """Camera v's sample pixels on a square lattice and their lines of sight in the water.

    Attributes
    ----------
    ij : (K, 2) ndarray of int
        Lattice indices (row, column).
    px : (K, 2) ndarray
        The pixels, ``(col, row)``.
    origins_mm, dirs : (K, 3) ndarray
        The lines of sight in the water (behind a port: from the port's outer face), mm.
    reach : (K,) ndarray of bool
        Whether the pixel sees the object through flat water: the samples a frame serves.
    """

    ij: NDArray[np.int64]
    px: Array
    origins_mm: Array
    dirs: Array
    reach: NDArray[np.bool_]

    @cached_property
    def beyond(self) -> cKDTree | None:
        """A tree of the pixels that do not see the object (None where every one does),
        built once per lattice: where the flow's samples must keep away from
        (:func:`_inside_view`)."""
        unseen = self.px[~self.reach]
        return cKDTree(unseen) if len(unseen) else None

    @classmethod
    def build(cls, cal: RigCalibration, step_px: int) -> SightLines:
        """The lattice of ``cal``'s camera v every ``step_px`` pixels (centred in the image)."""
        h, w = cal.image_size("view")
        rows, cols = np.mgrid[step_px // 2:h:step_px, step_px // 2:w:step_px]
        px = np.column_stack([cols.ravel(), rows.ravel()]).astype(float)
        origins, dirs = cal.camera_v_grey.pixel_rays(px[:, 0], px[:, 1])
        dirs = np.asarray(dirs, dtype=float).reshape(-1, 3)
        origins = np.broadcast_to(np.asarray(origins, dtype=float), dirs.shape).copy()
        ij = np.column_stack([rows.ravel() // step_px, cols.ravel() // step_px])
        cfg = cal.cfg
        reach = trace_to_object(cal.camera_v_grey, None, cfg.water.h0_mm, cal.view_index,
                                cfg.object_z_mm, px[:, 0], px[:, 1]).ok
        return cls(ij.astype(np.int64), px, origins, dirs, reach)


def _grey_u8(image: NDArray, scale: float) -> NDArray[np.uint8]:
    img = np.asarray(image, dtype=np.float32) / np.float32(scale)
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
    return np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)


def _dis(quality: str) -> cv2.DISOpticalFlow:
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    if quality == "fine":  # full resolution, small overlapping patches, more refinement
        flow.setFinestScale(0)
        flow.setPatchSize(8)
        flow.setPatchStride(3)
        flow.setVariationalRefinementIterations(10)
    return flow


def flat_view_flow(view: NDArray, view_flat: NDArray, quality: str = "fine"
                   ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Where each pixel's content lies in the flat-water view, and how well the flow says so.

    Parameters
    ----------
    view, view_flat : (H, W[, 3]) ndarray
        The view through the waves and the flat-water view (one radiance scale: both are
        divided by the flat view's 99.5th percentile).
    quality : str
        :data:`~restoration.options.FLOW_QUALITIES`.

    Returns
    -------
    flow_px : (H, W, 2) ndarray of float32
        ``(dcol, drow)``: ``view(p) ~ view_flat(p + flow_px(p))``.
    round_trip_px : (H, W) ndarray of float32
        How far the flow back from the flat-water view misses ``p``, px (NaN where it leaves
        the image).

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> from scipy.ndimage import gaussian_filter, shift
    >>> flat = gaussian_filter(rng.random((120, 160)), 2.0)
    >>> moved = shift(flat, (0.0, -1.5), order=3, mode="nearest")  # content 1.5 px left
    >>> flow, trip = flat_view_flow(moved, flat)
    >>> round(float(np.median(flow[20:100, 20:140, 0])), 1)
    1.5
    """
    scale = float(np.percentile(view_flat, 99.5)) or 1.0
    a, b = _grey_u8(view, scale), _grey_u8(view_flat, scale)
    dis = _dis(quality)
    forward = dis.calc(a, b, None)
    backward = dis.calc(b, a, None)
    h, w = a.shape
    cols, rows = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    back = cv2.remap(backward, cols + forward[..., 0], rows + forward[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=(np.nan, np.nan))
    return forward, np.linalg.norm(forward + back, axis=-1)


def slopes_on_sight_lines(points_mm: Array, dirs: Array, object_mm: Array, n_water: float
                          ) -> tuple[Array, Array]:
    """The unit normals (K, 3, up) and slopes ``(dz/dx, dz/dy)`` (K, 2) that refract each
    line of sight ``dirs`` (K, 3, unit, in the water) at ``points_mm`` (K, 3) towards its
    object point ``object_mm`` (K, 3): Snell's law ``n d x N = a x N`` makes ``N`` parallel
    to ``n d - a``.

    Examples
    --------
    >>> import numpy as np
    >>> d = np.array([[0.0, 0.0, 1.0]])
    >>> n, s = slopes_on_sight_lines(np.zeros((1, 3)), d, np.array([[0.0, 0.0, 9.0]]), 1.33)
    >>> n.tolist(), s.tolist()
    ([[0.0, 0.0, 1.0]], [[-0.0, -0.0]])
    """
    air = object_mm - points_mm
    air /= np.linalg.norm(air, axis=1, keepdims=True)
    normals = n_water * dirs - air
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals *= np.sign(normals[:, 2:3])
    return normals, -normals[:, :2] / normals[:, 2:3]


@dataclass(frozen=True)
class FlowSamples:
    """:func:`flow_samples`'s result: the lattice's samples the flow serves.

    Attributes
    ----------
    lines : SightLines
        The lattice.
    kept : (K,) ndarray of bool
        The samples the flow serves, on the object, ``edge_margin_px`` inside the flat view's
        textured part.
    object_mm : (K, 3) ndarray
        The object point each sample's flow points at, mm.
    mm_per_px : (K,) ndarray
        The object plane's size of one flat-water pixel at each, mm.
    counts : dict
        Samples in reach and those rejected by the flow's round trip, the object and the edge.
    inner : (K,) ndarray of bool
        Those of ``kept`` that lie :class:`~restoration.options.SchlierenOptions`' default edge
        margin inside (``kept`` itself where the options' margin is as large): where the flow
        is trusted whatever the margin asked.
    """

    lines: SightLines
    kept: NDArray[np.bool_]
    object_mm: Array
    mm_per_px: Array
    counts: dict[str, int]
    inner: NDArray[np.bool_]


def flow_samples(images: dict[str, NDArray], cal: Any,
                 options: SchlierenOptions) -> FlowSamples:
    """The lattice's samples the flow serves, their object points and the counts
    (:class:`FlowSamples`). ``cal``: a calibration with camera v's lattice and its
    :class:`LastFlow` (:class:`SchlierenCalibration`,
    :class:`~restoration.view_level.ViewLevelCalibration`); ``images``: ``view`` and
    ``view_flat``."""
    cfg = cal.cfg
    flow, trip = cal.flows.of(images, cal.radiance, options.flow)
    lines = cal.lattice(options.sample_step_px)
    cols, rows = lines.px[:, 0].astype(int), lines.px[:, 1].astype(int)
    q = lines.px + flow[rows, cols]
    camera, h0, n, z_obj = cal.camera_v_grey, cfg.water.h0_mm, cal.view_index, cfg.object_z_mm
    seen = trace_to_object(camera, None, h0, n, z_obj, q[:, 0], q[:, 1])
    step = trace_to_object(camera, None, h0, n, z_obj, q[:, 0] + 1.0, q[:, 1])
    reach = lines.reach
    flowed = reach & (np.nan_to_num(trip[rows, cols], nan=np.inf) < options.flow_check_px)
    on_object = flowed & seen.ok & step.ok
    kept = on_object & _inside_view(lines, q, options.edge_margin_px, flow.shape[:2])
    trusted_px = SchlierenOptions.edge_margin_px
    inner = (kept if options.edge_margin_px >= trusted_px
             else kept & _inside_view(lines, q, trusted_px, flow.shape[:2]))
    mm_per_px = np.linalg.norm(step.object_mm - seen.object_mm, axis=1)
    counts = {"samples": int(reach.sum()), "rejected_flow": int((reach & ~flowed).sum()),
              "rejected_object": int((flowed & ~on_object).sum()),
              "rejected_edge": int((on_object & ~kept).sum()), "matched": int(kept.sum())}
    return FlowSamples(lines, kept, seen.object_mm, mm_per_px, counts, inner)


def _inside_view(lines: SightLines, q: Array, margin_px: float, size: tuple[int, int]
                 ) -> NDArray[np.bool_]:
    """Whether each flat-water pixel ``q`` (K, 2) lies ``margin_px`` or more inside the flat
    view's textured part: from the image's border and from the lattice's samples that do not
    see the object (``lines.reach`` false: beyond its edge, or outside Snell's window). Near
    there the flow matches the object's texture to what lies past it."""
    h, w = size
    inside = ((q[:, 0] >= margin_px) & (q[:, 0] <= w - 1 - margin_px)
              & (q[:, 1] >= margin_px) & (q[:, 1] <= h - 1 - margin_px))
    if margin_px > 0 and lines.beyond is not None:
        distance, _ = lines.beyond.query(np.nan_to_num(q, nan=-1e9))
        inside &= distance > margin_px
    return inside


def reconstruct_schlieren(lines: SightLines, index: NDArray, object_mm: Array,
                          cal: RigCalibration, options: SchlierenOptions,
                          level_mm: float | None = None) -> RaySurface:
    """The surface from the object points ``object_mm`` (K, 3) that the lines of sight
    ``lines``' samples ``index`` (K,) reach through it: each sample's slope by Snell's law
    (:func:`slopes_on_sight_lines`) where its line crosses the surface, integrated with the
    samples' mean height at ``level_mm`` (None: the gauge's h0) and refined along the lines
    (:func:`~restoration.ray_surface.integrate_along_rays`).

    Raises
    ------
    RestorationFailed
        When the samples fix no surface.
    """
    n_water = cal.view_index
    dirs = lines.dirs[index]

    def slopes_at(points: Array, which: NDArray) -> tuple[Array, Array]:
        return slopes_on_sight_lines(points, dirs[which], object_mm[which], n_water)

    level = cal.cfg.water.h0_mm if level_mm is None else float(level_mm)
    return integrate_along_rays(lines.ij[index], lines.origins_mm[index], dirs, slopes_at,
                                level, options, options.refine_tol_mm)


def _consistency(surface: RaySurface, lines: SightLines, index: NDArray, object_mm: Array,
                 mm_per_px: Array, cal: SchlierenCalibration, threshold_px: float
                 ) -> Consistency:
    """Each kept sample's line of sight through the surface to the object, against its flow
    object point, in flat-water pixels."""
    cfg, hf = cal.cfg, surface.heightfield
    traced = trace_to_object(cal.camera_v_grey, hf, cfg.water.h0_mm, cal.view_index,
                             cfg.object_z_mm, lines.px[index, 0], lines.px[index, 1])
    residual = np.linalg.norm(traced.object_mm - object_mm[index], axis=1) / mm_per_px[index]
    finite = residual[np.isfinite(residual)]
    median, p95 = ((float(np.median(finite)), float(np.percentile(finite, 95)))
                   if finite.size else (np.nan, np.nan))
    return Consistency(residual, median, p95, float(threshold_px), int(finite.size), hf,
                       surface.points_mm[:, :2])


def verified_support(surface: RaySurface, check: Consistency, options: SchlierenOptions
                     ) -> tuple[RaySurface, Consistency, int]:
    """``surface`` and its ``check`` without what the forward check could not verify: the
    samples whose line of sight finds no object point through the surface (their residual
    NaN) are dropped, the rest gridded again, and the cells nearest to a dropped sample
    stay unknown. Also returns how many samples were dropped.

    They lie along the surface's border (7-13 % of the grid's cells on the frames measured)
    and where the flow, near the view's edge, bent the integrated surface too far to trace:
    an edge 4 mm off on one unseen frame whose traced samples all lay within 0.03 mm
    (docs/results.md, "Synthetic Schlieren").
    """
    points = surface.points_mm
    unverified = ~np.isfinite(check.residual_px)
    if not unverified.any():
        return surface, check, 0
    keep = ~unverified
    if keep.sum() < MIN_SAMPLES:
        raise RestorationFailed("the forward check verifies too few samples of the surface")
    grid = to_heightfield(points[keep, :2], points[keep, 2], surface.slopes[keep],
                          options.grid_spacing_mm, method=options.gridder)
    gx, gy = np.meshgrid(grid.x, grid.y)
    _, nearest = cKDTree(points[:, :2]).query(np.column_stack([gx.ravel(), gy.ravel()]))
    z = np.where(unverified[nearest].reshape(grid.z.shape), np.nan, grid.z)
    if not np.isfinite(z).any():
        raise RestorationFailed("the forward check verifies no part of the surface")
    hf = Heightfield(grid.x, grid.y, z)
    trimmed = replace(surface, heightfield=hf, ij=surface.ij[keep], points_mm=points[keep],
                      normals=surface.normals[keep], slopes=surface.slopes[keep],
                      kept=surface.kept[keep])
    checked = Consistency(check.residual_px[keep], check.median_px, check.p95_px,
                          check.threshold_px, check.n_predicted, hf, points[keep, :2])
    return trimmed, checked, int(unverified.sum())


def _sparse_message(used: int, counts: dict[str, int]) -> str:
    return (f"the flow serves {used} of {counts['samples']} samples in view in one surface "
            "(the object's texture does not follow the waves elsewhere)")


GAUGE_LEVEL_MESSAGE = (
    "the slopes do not pin the level: the gauge's h0 was used, and the shape bends with the "
    "patch's offset from it (--method schlieren-sl takes the structured light's level)")
"""Plain Schlieren's verdict on a frame no check flags: its level is always the gauge's, which
long waves move the patch away from, and its shape bends with that offset (docs/results.md,
"Synthetic Schlieren"), so it is never ``ok``."""

LEVEL_PASSES = 4
"""Most reconstructions at a :data:`LevelRule`'s level (each bends the slopes a little, and
the rule is asked again)."""

COARSE_PASSES = 3
"""Most refinement passes of a rebuild a level search asks for as coarse."""

Rebuild = Callable[[float, bool], RaySurface]
"""The frame's surface rebuilt with its samples' mean height at a level, mm (``True``: a coarse
rebuild, at most :data:`COARSE_PASSES` refinement passes), for a rule that searches."""

LevelRule = Callable[[RaySurface, Rebuild], tuple[Anchor, tuple[Status, str] | None]]
"""Where a surface at the gauge's level should lie instead: given it (and how to rebuild it at
another level), the anchor of the level to rebuild it at (its ``anchor_mm`` the samples' mean
height) and the verdict on that level (None: it holds; else the status and message it gives
the frame)."""


def restore_schlieren(
    images: dict[str, NDArray],
    cal: SchlierenCalibration,
    options: SchlierenOptions | None = None,
    level: LevelRule | None = None,
) -> RestoreResult:
    """Run the method on loaded images (``view``, ``view_flat``).

    Returns a :class:`~restoration.result.RestoreResult` with the surface (its level the
    gauge's, or ``level``'s), the restored view, the forward check and the timings. Its
    status: ``sparse`` when the flow serves fewer than
    :data:`~restoration.result.SPARSE_FRACTION` of the samples in view; ``inconsistent`` when
    the surface does not send the lines of sight where the flow does (module notes);
    ``failed`` when the samples fix no surface; else ``level``'s verdict on its level
    (``ok`` where it holds), and without a ``level``, ``gauge_level``
    (:data:`GAUGE_LEVEL_MESSAGE`).

    Examples
    --------
    >>> from restoration import SchlierenCalibration, restore_schlieren   # doctest: +SKIP
    >>> cal = SchlierenCalibration.from_folder("renders/schlieren")       # doctest: +SKIP
    >>> restore_schlieren(cal.load_images("renders/schlieren"), cal).status  # doctest: +SKIP
    <Status.GAUGE_LEVEL: 'gauge_level'>
    """
    options = SchlierenOptions() if options is None else options
    for name in cal.IMAGES:
        if name not in images:
            raise WaiInputError(f"schlieren: the frame needs a {name!r} image")
    timings = Timings()
    with timings("features"):
        served = flow_samples(images, cal, options)
    lines, kept, counts = served.lines, served.kept, served.counts
    object_mm, mm_per_px = served.object_mm, served.mm_per_px
    index = np.flatnonzero(kept)
    if index.size < max(MIN_SAMPLES, SPARSE_FRACTION * counts["samples"]):
        return RestoreResult(METHOD, Status.SPARSE, _sparse_message(index.size, counts),
                             counts=counts)
    try:
        coarse = replace(options, n_refine=min(options.n_refine, COARSE_PASSES))

        def rebuild(level_mm: float, rough: bool) -> RaySurface:
            return reconstruct_schlieren(lines, index, object_mm[index], cal,
                                         coarse if rough else options, level_mm)

        with timings("surface"):
            surface = reconstruct_schlieren(lines, index, object_mm[index], cal, options)
            at_mm = float(cal.cfg.water.h0_mm)
            anchor, verdict = Anchor("gauge", at_mm), None
            # A new level bends the slopes a little: the rule is asked again until it holds.
            for _ in range(LEVEL_PASSES if level is not None else 0):
                anchor, verdict = level(surface, rebuild)
                if anchor.anchor_mm is None or abs(anchor.anchor_mm - at_mm) <= (
                        options.refine_tol_mm):
                    break
                at_mm = float(anchor.anchor_mm)
                surface = reconstruct_schlieren(lines, index, object_mm[index], cal, options,
                                                at_mm)
            surface = replace(surface, anchor=replace(anchor, anchor_mm=at_mm))
    except RestorationFailed as exc:
        return RestoreResult(METHOD, Status.FAILED, str(exc), counts=counts)
    with timings("consistency"):
        check = _consistency(surface, lines, index[surface.kept], object_mm, mm_per_px, cal,
                             options.max_residual_px)
        try:
            surface, check, counts["unverified"] = verified_support(surface, check, options)
        except RestorationFailed as exc:
            return RestoreResult(METHOD, Status.FAILED, str(exc), counts=counts)
    with timings("reverse_trace"):
        view = cal.restore_view(images["view"], surface.heightfield, options.warp_step_px,
                                gain=cal.view_gain)
    timings.add("end_to_end", timings.total())
    counts["used"] = len(surface.ij)
    status, message = Status.OK, ""
    if counts["used"] < SPARSE_FRACTION * counts["samples"]:
        status, message = Status.SPARSE, _sparse_message(counts["used"], counts)
    elif not check.consistent:
        status = Status.INCONSISTENT
        message = (f"the surface sends the lines of sight {check.median_px:.2f} px (median) "
                   f"from where the flow puts them (threshold {check.threshold_px:g} px)")
    elif verdict is not None:
        status, message = verdict
    elif level is None:
        status, message = Status.GAUGE_LEVEL, GAUGE_LEVEL_MESSAGE
    return RestoreResult(METHOD, status, message, None, surface, view, timings.to_dict(), counts,
                         consistency=check)

