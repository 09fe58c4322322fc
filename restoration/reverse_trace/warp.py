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

import contextlib
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np
from numpy.typing import NDArray

from restoration._threads import restore_threads, run_beside
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
from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera
from wai_core.heightfield import Heightfield
from wai_core.optics import RayStatus, _check_system, trace_to_object
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


@dataclass(frozen=True)
class _WarpScratch:
    """The full-size intermediate arrays of :func:`_pixel_warp`: sampling columns and rows
    (H, W) float32, and each row's valid pixels and first and last valid column (H,)."""

    map_x: NDArray[np.float32]
    map_y: NDArray[np.float32]
    per_row: NDArray[np.int64]
    first: NDArray[np.int64]
    last: NDArray[np.int64]

    @classmethod
    def new(cls, h: int, w: int) -> _WarpScratch:
        """Uninitialised arrays for an image ``h`` x ``w`` (every entry is written)."""
        return cls(np.empty((h, w), np.float32), np.empty((h, w), np.float32),
                   *(np.empty(h, np.int64) for _ in range(3)))


class _Workspace:
    """A :class:`ViewPlan`'s :class:`_WarpScratch`, kept from frame to frame.

    Fresh image-sized arrays cost more in page faults than the pass that fills them, so the
    plan keeps one set; nothing of them reaches a :class:`Restoration`. One frame at a time
    uses them: a thread that finds them taken works in fresh ones. Pickled, it starts empty.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._scratch: _WarpScratch | None = None

    @contextlib.contextmanager
    def borrow(self, h: int, w: int) -> Iterator[_WarpScratch]:
        """The scratch for an image ``h`` x ``w`` (fresh while another thread has it)."""
        if not self._lock.acquire(blocking=False):
            yield _WarpScratch.new(h, w)
            return
        try:
            if self._scratch is None or self._scratch.map_x.shape != (h, w):
                self._scratch = _WarpScratch.new(h, w)
            yield self._scratch
        finally:
            self._lock.release()

    def __reduce__(self) -> tuple:
        return (_Workspace, ())


@dataclass(frozen=True, eq=False)
class ViewPlan:
    """The flat-water (truth) view of camera v on the coarse warp grid: all of
    :func:`restore_view` that does not depend on the surface.

    Build it with :meth:`build` once per camera, water and warp step (a rig's calibration keeps
    one) and pass it to each :func:`restore_view`, which checks that it was built for the
    camera, water and step it is given.

    Attributes
    ----------
    camera : PinholeCamera
        Camera v.
    h0_mm, n_water, z_object_mm : float
        Mean water level (mm), refractive index, object-plane height (mm).
    step_px : int
        Spacing of the coarse nodes, pixels.
    grid_shape : (int, int)
        Coarse nodes (rows, cols): every ``step_px`` pixels from 0 up to, or just past, the
        last pixel.
    node_px : (K, 2) ndarray
        Truth pixel ``(col, row)`` of each node whose flat-water ray reaches the object plane.
    node_index : (K,) ndarray of int
        Their flat indices in the coarse grid.
    targets : (K, 3) ndarray
        Their object points, mm.
    node_q0 : (K, 2) ndarray
        Where their rays cross flat water, mm (Newton's start).
    truth_status : (rows, cols) ndarray of int8
        :class:`RayStatus` of every node in the truth view.
    image_shape : (int, int)
        ``(H, W)`` pixels.
    pixel_cells : tuple of four ndarrays
        Coarse cell (int) and fraction across it (float32) of every pixel column, then row:
        (W,), (W,), (H,), (H,).
    cell_area : (rows - 1, cols - 1) ndarray
        Pixels in each coarse cell.
    workspace
        Full-size scratch arrays that every frame's :func:`restore_view` reuses (one frame
        at a time; another thread meanwhile works in fresh ones); not part of the result.

    Examples
    --------
    >>> from wai_core import load_rig
    >>> cfg = load_rig("paper")
    >>> plan = ViewPlan.build(cfg.rig.camera_v, cfg.water.h0_mm, cfg.water.n_water,
    ...                       cfg.object_z_mm, 8)
    >>> plan.grid_shape, plan.image_shape
    ((76, 101), (600, 800))
    """

    camera: PinholeCamera = field(repr=False)
    h0_mm: float
    n_water: float
    z_object_mm: float
    step_px: int
    grid_shape: tuple[int, int]
    node_px: Array = field(repr=False)
    node_index: NDArray[np.intp] = field(repr=False)
    targets: Array = field(repr=False)
    node_q0: Array = field(repr=False)
    truth_status: NDArray[np.int8] = field(repr=False)
    image_shape: tuple[int, int]
    pixel_cells: tuple[
        NDArray[np.intp], NDArray[np.float32], NDArray[np.intp], NDArray[np.float32]
    ] = field(repr=False)
    cell_area: NDArray[np.float64] = field(repr=False)
    workspace: _Workspace = field(default_factory=_Workspace, init=False, repr=False,
                                  compare=False)

    @classmethod
    def build(
        cls,
        camera: PinholeCamera,
        h0_mm: float,
        n_water: float,
        z_object_mm: float,
        step_px: int = 8,
    ) -> ViewPlan:
        """Trace the truth view of ``camera`` through flat water at the coarse nodes.

        Parameters
        ----------
        camera : PinholeCamera
            Camera v.
        h0_mm, n_water, z_object_mm : float
            Mean water level (mm), refractive index, object-plane height (mm).
        step_px : int
            Spacing of the coarse warp grid, pixels (``warp_step_px`` of :func:`restore_view`).

        Returns
        -------
        ViewPlan
        """
        step = _check_step(step_px, "ViewPlan.build")
        _check_system(h0_mm, n_water, z_object_mm)
        w, h = camera.width_px, camera.height_px
        # Nodes every `step` pixels from 0 up to (or just past) the last pixel: every pixel then
        # lies in a cell of four nodes and bilinear interpolation never extrapolates.
        ncol = -(-(w - 1) // step) + 1
        nrow = -(-(h - 1) // step) + 1
        cols, rows = np.meshgrid(np.arange(ncol) * float(step), np.arange(nrow) * float(step))
        truth = trace_to_object(camera, None, h0_mm, n_water, z_object_mm, cols, rows)
        ok = truth.ok.ravel()
        targets = truth.object_mm.reshape(-1, 3)[ok]
        q0 = truth.surface_mm.reshape(-1, 3)[ok, :2]
        return cls(
            camera,
            float(h0_mm),
            float(n_water),
            float(z_object_mm),
            step,
            (nrow, ncol),
            np.column_stack([cols.ravel(), rows.ravel()])[ok],
            np.flatnonzero(ok),
            targets,
            q0,
            truth.status,
            (h, w),
            _pixel_cells(w, ncol, step) + _pixel_cells(h, nrow, step),
            np.outer(_cell_sizes(h, nrow, step), _cell_sizes(w, ncol, step)),
        )

    def check_fits(
        self, camera: PinholeCamera, h0_mm: float, n_water: float, z_object_mm: float,
        step_px: int, caller: str = "restore_view",
    ) -> None:
        """Raise :class:`~wai_core.errors.WaiInputError` unless the plan was built for this
        camera (size, optics and pose), water and step."""
        if _plan_key(camera, h0_mm, n_water, z_object_mm, step_px) != _plan_key(
            self.camera, self.h0_mm, self.n_water, self.z_object_mm, self.step_px
        ):
            raise WaiInputError(
                f"{caller}: plan was built for camera {self.camera.width_px}x"
                f"{self.camera.height_px}, step {self.step_px} px and other water or pose than "
                f"given (camera {camera.width_px}x{camera.height_px}, step {step_px} px)"
            )


@dataclass(eq=False)
class ViewState:
    """A sequence's warp between frames: where each frame's warp solve starts.

    A video's surface moves little between frames, so each node's Newton iteration starts
    where the previous frame's converged (nodes that did not start at their flat-water
    crossing, as without a state; a warm start that fails is solved again from there). The
    view then differs from a cold start's by less than the solver's tolerance
    (``_WARP_TOL_PX``) where both converge. Per sequence, never per rig (one calibration may
    serve several sequences at once): create one per sequence and pass it to every frame's
    :func:`restore_view`, in order. A state of another plan (camera, water or step) is
    started afresh.

    Attributes
    ----------
    surface_mm : (K, 2) ndarray or None
        The last frame's surface point of each node of the plan, mm (NaN where unsolved).
    plan_key : tuple or None
        What that plan was built for.

    Examples
    --------
    >>> ViewState().surface_mm is None
    True
    """

    surface_mm: Array | None = field(default=None, repr=False)
    plan_key: tuple | None = field(default=None, repr=False)

    def start(self, plan: ViewPlan) -> tuple[Array, BoolArray]:
        """Start points (K, 2) mm of ``plan``'s nodes, and which of them are warm."""
        key = _plan_key(plan.camera, plan.h0_mm, plan.n_water, plan.z_object_mm, plan.step_px)
        if self.surface_mm is None or self.plan_key != key:
            return plan.node_q0, np.zeros(len(plan.node_q0), bool)
        warm = np.isfinite(self.surface_mm[:, 0])
        return np.where(warm[:, None], self.surface_mm, plan.node_q0), warm

    def update(self, plan: ViewPlan, surface_mm: Array, status: NDArray[np.int8]) -> None:
        """Keep a frame's solved surface points (K, 3) mm and statuses (K,)."""
        q = surface_mm[:, :2].copy()
        q[status != RayStatus.OK] = np.nan
        self.surface_mm = q
        self.plan_key = _plan_key(plan.camera, plan.h0_mm, plan.n_water, plan.z_object_mm,
                                  plan.step_px)


def _plan_key(camera: PinholeCamera, h0: float, n: float, z: float, step: int) -> tuple:
    """What a :class:`ViewPlan` depends on, comparable by value."""
    pose = camera.pose
    return (
        camera.width_px,
        camera.height_px,
        camera.focal_mm,
        camera.pixel_pitch_mm,
        pose.R.tobytes(),
        pose.t_mm.tobytes(),
        float(h0),
        float(n),
        float(z),
        int(step),
    )


def _check_step(step_px: int, caller: str) -> int:
    """``step_px`` as an int after checking that it is a positive integer."""
    if isinstance(step_px, bool) or int(step_px) != step_px or step_px < 1:
        raise WaiInputError(f"{caller}: warp_step_px must be a positive integer, got {step_px!r}")
    return int(step_px)


def _pixel_cells(
    n_px: int, n_nodes: int, step: int
) -> tuple[NDArray[np.intp], NDArray[np.float32]]:
    """Cell (n_px,) of each pixel along an axis and its fraction of the way across it; a last
    pixel lying exactly on the last node belongs to the cell before it."""
    i = np.minimum(np.arange(n_px) // step, n_nodes - 2)
    return i, ((np.arange(n_px) - i * step) / step).astype(np.float32)


def _cell_sizes(n_px: int, n_nodes: int, step: int) -> NDArray[np.float64]:
    """Pixels in each of the ``n_nodes - 1`` cells along an axis of ``n_px`` pixels: ``step``
    each, the rest in the last (it also holds a last pixel lying exactly on the last node)."""
    sizes = np.full(n_nodes - 1, float(step))
    sizes[-1] = n_px - step * (n_nodes - 2)
    return sizes


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
