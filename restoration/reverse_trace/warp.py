"""The restored image: resample the distorted view of camera v into its flat-water view.

The ground-truth view is camera v through *flat* water. For each truth pixel ``p`` the target
``P`` is the flat-water forward map of ``p``; the distorted image shows ``P`` at ``u =
find_pixels(surface_est, P)``; so ``restored(p) = distorted(u)``. :func:`restore_view` solves the
warp ``u(p)`` on a coarse grid, upsamples it bilinearly (the surface is smooth) and samples the
image through it in one compiled pass, and reports the :class:`Restoration` with its validity
mask and the cause of every unrestored pixel. The truth view's part, which no surface changes,
is a :class:`ViewPlan`: a rig builds it once and passes it to every frame's view.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np
from numpy.typing import NDArray

from restoration.reverse_trace._kernels import (
    finish_rows,
    node_warp,
    valid_box,
    warp_node_rows,
    warp_rows,
)
from restoration.reverse_trace._surface import (
    SplinePatches,
    _FlatWater,
    _surface_model,
    check_patches,
)
from restoration.reverse_trace.inverse import _newton, _Optics
from restoration.reverse_trace.plan import ViewPlan, ViewState, _check_step, _WarpScratch
from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera
from wai_core.heightfield import Heightfield
from wai_core.optics import RayStatus, _check_system
from wai_core.parallel import restore_threads, run_beside
from wai_core.timings import Timings

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Tolerance and iterations of the warp solve in restore_view. Convergence is tested on the
#: last Newton step, which is then taken: the error left is second order (below 3e-3 px for
#: 0.05 px on the paper's rig), far below what bilinear interpolation of the warp adds.
_WARP_TOL_PX, _WARP_ITER = 0.05, 12


@dataclass(frozen=True)
class _CoarseWarp:
    """The warp on the coarse grid, all a :class:`Restoration` needs to give its full-size
    maps when they are read: displacement ``u - p`` in columns and rows (rows, cols) px,
    cells whose four nodes were solved (rows - 1, cols - 1), and the plan's pixel cells."""

    disp_x: NDArray[np.float32]
    disp_y: NDArray[np.float32]
    cell_ok: BoolArray
    pixel_cells: tuple[NDArray[np.intp], NDArray[np.float32], NDArray[np.intp],
                       NDArray[np.float32]]

    def along_x(self) -> tuple[NDArray[np.float32], NDArray[np.float32], BoolArray]:
        """The warp interpolated along x at every pixel column of each node row, and each
        column's cell validity (:func:`~restoration.reverse_trace._kernels.warp_node_rows`)."""
        col_i, col_t = self.pixel_cells[:2]
        return warp_node_rows(self.disp_x, self.disp_y, self.cell_ok, col_i, col_t)

    def maps(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Sampling columns and rows (H, W): the very values the restored image sampled."""
        h, w = self.pixel_cells[2].size, self.pixel_cells[0].size
        scratch = _WarpScratch.new(h, w)
        warp_rows(0, h, *self.along_x(), *self.pixel_cells[2:], scratch.map_x, scratch.map_y,
                  np.empty((h, w), bool), scratch.per_row, scratch.first, scratch.last)
        return scratch.map_x, scratch.map_y


@dataclass(frozen=True)
class Restoration:
    """Restored image in the geometry of the flat-water (ground-truth) view.

    Attributes
    ----------
    image : (H, W[, C]) ndarray
        Restored image, float32 or float64 like the input; 0 where not valid.
    valid : (H, W) ndarray of bool
        True where the pixel was restored.
    counts : dict of str to int
        Pixels per :class:`RayStatus` name (they sum to H W): ``ok``; ``tir`` (totally
        reflected in the truth view, or no ray through the estimated surface reaches the
        target); ``missed_surface`` (the estimated surface is unknown there); ``out_of_view``
        (the target is seen outside the distorted image); ``not_converged``; ``missed_object``.
        A pixel takes the cause of the worst of the four warp nodes around it.
    timings_ms : dict of str to float
        Wall times of the stages, ms: ``plan`` (geometry of the truth view: the
        :class:`ViewPlan`, ~0 when one is passed), ``surface`` (spline tables, ~0 when passed),
        ``solve`` (warp on the coarse grid), ``upsample``
        (the warp at the nodes and their status), ``remap`` (upsampled to pixels and the image
        sampled, one pass) and ``total``.
    step_px : int
        Spacing of the coarse warp grid, pixels.
    """

    image: NDArray
    valid: BoolArray
    counts: dict[str, int]
    timings_ms: dict[str, float]
    step_px: int
    coarse: _CoarseWarp = field(repr=False)

    @cached_property
    def _maps(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        return self.coarse.maps()

    @property
    def map_cols(self) -> NDArray[np.float32]:
        """(H, W) float32: the warp's columns (see :attr:`map_px`); upsampled from the coarse
        warp on first read (the restoration samples the image without keeping them)."""
        return self._maps[0]

    @property
    def map_rows(self) -> NDArray[np.float32]:
        """(H, W) float32: the warp's rows (see :attr:`map_px`), as :attr:`map_cols`."""
        return self._maps[1]

    @property
    def map_px(self) -> NDArray[np.float32]:
        """(H, W, 2) pixel ``(col, row)`` of the distorted image sampled for each truth pixel
        (the warp); meaningless where not valid (see :attr:`warp_px`). Assembled on each read
        from :attr:`map_cols` and :attr:`map_rows`."""
        return cv2.merge([self.map_cols, self.map_rows])

    def restrict(self, sampled_ok: NDArray[np.bool_]) -> None:
        """Take back the restored pixels whose sample of the distorted image is not data:
        ``sampled_ok`` (H, W) False where the warp's sample falls on pixels the camera did not
        record (a real lens's image resampled into its pinhole: past the sensor's edge). They
        become 0, not valid, and are counted as ``out_of_view``."""
        lost = self.valid & ~sampled_ok
        n = int(lost.sum())
        if n == 0:
            return
        self.valid[lost] = False
        self.image[lost] = 0
        self.counts["ok"] = self.counts.get("ok", 0) - n
        self.counts["out_of_view"] = self.counts.get("out_of_view", 0) + n

    @property
    def warp_px(self) -> NDArray[np.float32]:
        """The warp as (H, W, 2) ``(col, row)`` pixels of the distorted image; NaN where not
        valid."""
        warp = self.map_px
        warp[~self.valid] = np.nan
        return warp


def _check_image(distorted: NDArray, camera: PinholeCamera) -> NDArray:
    """The image as float32 or float64, after checking its shape and values."""
    img = np.asarray(distorted)
    if img.ndim not in (2, 3) or img.shape[:2] != (camera.height_px, camera.width_px):
        raise WaiInputError(
            f"restore_view: image shape {img.shape} does not match the camera "
            f"({camera.height_px}, {camera.width_px}[, C])"
        )
    if not np.issubdtype(img.dtype, np.floating):
        raise WaiInputError(f"restore_view: image must be floating point, got {img.dtype}")
    if img.ndim == 3 and not 1 <= img.shape[2] <= 4:
        raise WaiInputError(f"restore_view: image must have 1 to 4 channels, got {img.shape[2]}")
    if img.dtype not in (np.float32, np.float64):
        img = img.astype(np.float32)
    img = np.ascontiguousarray(img)
    # NaN or inf propagate into the sum (float64 accumulators: finite float32 cannot overflow);
    # several times faster than cv2.checkRange and without a full-size temporary.
    if not np.all(np.isfinite(cv2.sumElems(img))):
        raise WaiInputError("restore_view: image holds NaN or inf")
    return img


# Which status a cell of four nodes reports when some are invalid (most fundamental first).
_PRIORITY = np.array([0, 4, 5, 3, 2, 1], dtype=np.int8)  # rank of each RayStatus code
_BY_RANK = np.array(
    [
        RayStatus.OK,
        RayStatus.OUT_OF_VIEW,
        RayStatus.NOT_CONVERGED,
        RayStatus.MISSED_OBJECT,
        RayStatus.MISSED_SURFACE,
        RayStatus.TIR,
    ],
    dtype=np.int8,
)


def _cell_status(node_status: NDArray[np.int8]) -> NDArray[np.int8]:
    """Status of each coarse cell: OK if its four nodes are, else its worst node's status."""
    r = _PRIORITY[node_status]
    worst = np.maximum(np.maximum(r[:-1, :-1], r[1:, :-1]), np.maximum(r[:-1, 1:], r[1:, 1:]))
    return _BY_RANK[worst]


def _node_warp(
    plan: ViewPlan, px: Array, status: NDArray[np.int8]
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.int8]]:
    """Displacement ``u - p`` in columns and in rows (rows, cols) px at the coarse nodes (0 where
    unsolved) and the status of every node (the truth view's where it sees no object)."""
    n = plan.grid_shape[0] * plan.grid_shape[1]
    disp_x, disp_y = np.empty(n, np.float32), np.empty(n, np.float32)
    node_status = np.empty(n, np.int8)
    node_warp(plan.truth_status.ravel(), plan.node_index, plan.node_px, px, status, disp_x,
              disp_y, node_status)
    return (disp_x.reshape(plan.grid_shape), disp_y.reshape(plan.grid_shape),
            node_status.reshape(plan.grid_shape))


def _pixel_warp(
    plan: ViewPlan,
    img: NDArray,
    disp_x: NDArray[np.float32],
    disp_y: NDArray[np.float32],
    node_status: NDArray[np.int8],
    gain: float,
) -> tuple[NDArray, BoolArray, dict[str, int], _CoarseWarp]:
    """The restored image (H, W[, C]) over ``gain``, validity (H, W), counts per cause and
    the coarse warp (the full-size maps on demand).

    A pixel is valid when the four nodes of its cell were solved and its sampling position
    lies inside the distorted image. The rows are done in two bands, one on each of the
    restoration's threads when it has two (one hand-off for a band's few milliseconds of
    work: warp, remap and finish together). In each band a compiled pass upsamples the
    warp into the plan's scratch maps and tests it
    (:func:`~restoration.reverse_trace._kernels.warp_rows`); ``cv2.remap`` samples the image
    in the band's valid pixels' bounding box (exact bilinear weights on float maps since
    OpenCV 5; the fixed-point maps of ``cv2.convertMaps`` would round the position to 1/32 px
    and measured no faster); the box is then divided by the gain, and its invalid pixels and
    the band's rows outside it zeroed (:func:`~restoration.reverse_trace._kernels.finish_rows`).
    The image and validity are new arrays (the caller keeps them); the maps are not kept.
    Displacements are interpolated, not positions: they vary slowly, so float32 costs nothing.
    """
    h, w = plan.image_shape
    cell = _cell_status(node_status)
    cell_ok = cell == RayStatus.OK
    coarse = _CoarseWarp(disp_x, disp_y, cell_ok, plan.pixel_cells)
    along = coarse.along_x()
    valid = np.empty((h, w), bool)
    out = np.empty(img.shape, dtype=img.dtype)
    gain = img.dtype.type(gain)
    with plan.workspace.borrow(h, w) as scratch:

        def band(r0: int, r1: int) -> int:
            """Rows r0 to r1 - 1 sampled and finished; their valid pixels."""
            warp_rows(r0, r1, *along, *plan.pixel_cells[2:], scratch.map_x, scratch.map_y,
                      valid, scratch.per_row, scratch.first, scratch.last)
            n, box = valid_box(scratch.per_row[r0:r1], scratch.first[r0:r1],
                               scratch.last[r0:r1], w)
            if n:  # only the box is sampled (views: cv2 writes into the result)
                box[:2] += r0
                b0, b1, c0, c1 = (int(v) for v in box)
                # Half-pixel border: replicate rather than blend with black.
                cv2.remap(img, scratch.map_x[b0:b1, c0:c1], scratch.map_y[b0:b1, c0:c1],
                          cv2.INTER_LINEAR, dst=out[b0:b1, c0:c1],
                          borderMode=cv2.BORDER_REPLICATE)
            finish_rows(r0, r1, out.reshape(h, w, -1), valid, box, gain)
            return int(n)

        mid = h // 2 if restore_threads() > 1 else h
        lower = run_beside(lambda: band(mid, h))
        n_valid = band(0, mid) + lower()
    return out, valid, _counts(cell, plan, n_valid), coarse


def _counts(cell: NDArray[np.int8], plan: ViewPlan, n_valid: int) -> dict[str, int]:
    """Restored pixels (``ok``: the ``n_valid`` valid ones) and the others by cause: the
    coarse cells' statuses weighed by their pixel areas, solved cells' pixels sampling
    outside the image counted ``out_of_view``."""
    hist = np.bincount(cell.ravel(), weights=plan.cell_area.ravel(), minlength=len(RayStatus))
    counts = {s.name.lower(): int(round(hist[s])) for s in RayStatus}
    counts["out_of_view"] += counts["ok"] - n_valid
    counts["ok"] = n_valid
    return counts


def _solve_nodes(
    camera: PinholeCamera, model: _FlatWater | SplinePatches, optics: _Optics, plan: ViewPlan,
    state: ViewState | None,
) -> tuple[Array, NDArray[np.int8]]:
    """Pixels (K, 2) and statuses (K,) of the plan's nodes: started at their flat-water
    crossings, or where ``state`` says (warm starts that fail solved again from there);
    ``state`` then takes this frame's solution."""
    targets = plan.targets[:, :2]
    if state is None:
        px, st, _, _ = _newton(camera, model, optics, targets, plan.node_q0, _WARP_TOL_PX,
                               _WARP_ITER)
        return px, st
    if not isinstance(state, ViewState):
        raise WaiInputError(f"restore_view: state must be a ViewState, got {type(state)}")
    start, warm = state.start(plan)
    px, st, q, _ = _newton(camera, model, optics, targets, start, _WARP_TOL_PX, _WARP_ITER)
    redo = np.flatnonzero(warm & (st != RayStatus.OK))
    if redo.size:
        px[redo], st[redo], q[redo], _ = _newton(
            camera, model, optics, targets[redo], plan.node_q0[redo], _WARP_TOL_PX, _WARP_ITER
        )
    state.update(plan, q, st)
    return px, st


def restore_view(
    distorted: NDArray,
    camera: PinholeCamera,
    surface_est: Heightfield | None,
    h0_mm: float,
    n_water: float,
    z_object_mm: float,
    warp_step_px: int = 8,
    gain: float = 1.0,
    *,
    plan: ViewPlan | None = None,
    patches: SplinePatches | None = None,
    state: ViewState | None = None,
) -> Restoration:
    """Undo the refraction of ``surface_est``: resample the distorted view into the flat-water view.

    For each truth pixel ``p``: ``P`` = flat-water forward map of ``p``; ``u`` = pixel that sees
    ``P`` through ``surface_est`` (:func:`find_pixels`, started at ``p``); ``restored(p) =
    distorted(u)``, sampled bilinearly. ``u`` is solved on nodes every ``warp_step_px`` pixels and
    its displacement ``u - p`` interpolated bilinearly in between. A pixel is restored only if the
    four nodes around it were solved and ``u`` falls inside the distorted image; all others are 0
    in the image, False in ``valid`` and counted by cause, never filled.

    Parameters
    ----------
    distorted : (H, W) or (H, W, C) ndarray of float
        Image of camera v through the wavy water, C <= 4.
    camera : PinholeCamera
        Camera v (H, W must match its size).
    surface_est : Heightfield or None
        The estimated water surface, mm; NaN holes and its limited extent are respected.
        None means flat water (restoration is then the identity).
    h0_mm, n_water, z_object_mm : float
        Mean water level (mm), refractive index, object-plane height (mm).
    warp_step_px : int
        Spacing of the coarse warp grid, pixels. On the paper's rig (800 x 600) 8 px is the
        sweet spot: 4 px solves 4x the nodes for no smaller corner spread, 16 px halves the
        solve but doubles the corner spread.
    gain : float
        The restored image is the sampled one divided by it (a camera's gain, e.g.
        :attr:`~restoration.calibration.RigCalibration.view_gain`): sampling is linear, so
        this is ``distorted / gain`` restored, to rounding, without a divided copy of it.
    plan : ViewPlan, optional
        The truth view, built by :meth:`ViewPlan.build` for this camera, water and
        ``warp_step_px`` (else :class:`~wai_core.errors.WaiInputError`); built for this call
        when omitted. The result does not depend on whether it is passed.
    patches : SplinePatches, optional
        The spline table of ``surface_est`` (that very object, else
        :class:`~wai_core.errors.WaiInputError`), e.g. shared with
        :func:`restoration.consistency.spot_consistency`; built for this call when omitted.
    state : ViewState, optional
        A sequence's warp so far: the solve starts from the previous frame's and the state
        takes this frame's (the view then agrees with a cold start's to the solver's
        tolerance, not to the bit). None: every node starts at its flat-water crossing.

    Returns
    -------
    Restoration
    """
    timings = Timings()
    with timings("total"):
        img = _check_image(distorted, camera)
        step = _check_step(warp_step_px, "restore_view")
        if not (np.isfinite(gain) and gain > 0):
            raise WaiInputError(f"restore_view: gain must be finite and positive, got {gain!r}")
        _check_system(h0_mm, n_water, z_object_mm)
        with timings("plan"):
            if plan is None:
                plan = ViewPlan.build(camera, h0_mm, n_water, z_object_mm, step)
            elif not isinstance(plan, ViewPlan):
                raise WaiInputError(f"restore_view: plan must be a ViewPlan, got {type(plan)}")
            else:
                plan.check_fits(camera, h0_mm, n_water, z_object_mm, step)
        with timings("surface"):
            if patches is not None:
                check_patches(patches, surface_est, "restore_view")
            model = _surface_model(surface_est, h0_mm, patches)
            optics = _Optics(camera.pose.center_lab_mm, float(n_water), float(z_object_mm))
        with timings("solve"):
            px, st = _solve_nodes(camera, model, optics, plan, state)
        with timings("upsample"):
            disp_x, disp_y, node_status = _node_warp(plan, px, st)
        with timings("remap"):
            out, valid, counts, coarse = _pixel_warp(
                plan, img, disp_x, disp_y, node_status, gain
            )
    return Restoration(out, valid, counts, timings.to_dict(), step, coarse)
