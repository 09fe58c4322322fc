"""The restored image: resample the distorted view of camera v into its flat-water view.

The ground-truth view is camera v through *flat* water. For each truth pixel ``p`` the target
``P`` is the flat-water forward map of ``p``; the distorted image shows ``P`` at ``u =
find_pixels(surface_est, P)``; so ``restored(p) = distorted(u)``. :func:`restore_view` solves the
warp ``u(p)`` on a coarse grid (plans of the truth view are cached between calls), upsamples it
bilinearly (the surface is smooth), applies it with one ``cv2.remap`` and reports the
:class:`Restoration` with its validity mask and the cause of every unrestored pixel.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from restoration.reverse_trace._surface import _surface_model
from restoration.reverse_trace.inverse import _newton, _Optics
from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera
from wai_core.heightfield import Heightfield
from wai_core.optics import RayStatus, _check_system, trace_to_object

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Tolerance and iterations of the warp solve in restore_view. Convergence is tested on the
#: last Newton step, which is then taken: the error left is second order (below 3e-3 px for
#: 0.05 px on the paper's rig), far below what bilinear interpolation of the warp adds.
_WARP_TOL_PX, _WARP_ITER = 0.05, 12


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
        Wall times of the stages, ms: ``plan`` (geometry of the truth view, cached between
        calls), ``surface`` (spline tables), ``solve`` (warp on the coarse grid), ``upsample``,
        ``remap`` and ``total``.
    step_px : int
        Spacing of the coarse warp grid, pixels.
    map_cols, map_rows : (H, W) ndarray of float32
        The warp's columns and rows (see :attr:`map_px`).
    """

    image: NDArray
    valid: BoolArray
    counts: dict[str, int]
    timings_ms: dict[str, float]
    step_px: int
    map_cols: NDArray[np.float32] = field(repr=False)
    map_rows: NDArray[np.float32] = field(repr=False)

    @property
    def map_px(self) -> NDArray[np.float32]:
        """(H, W, 2) pixel ``(col, row)`` of the distorted image sampled for each truth pixel
        (the warp); meaningless where not valid (see :attr:`warp_px`). Assembled on each read
        from :attr:`map_cols` and :attr:`map_rows`."""
        return cv2.merge([self.map_cols, self.map_rows])

    @property
    def warp_px(self) -> NDArray[np.float32]:
        """The warp as (H, W, 2) ``(col, row)`` pixels of the distorted image; NaN where not
        valid."""
        warp = self.map_px
        warp[~self.valid] = np.nan
        return warp


@dataclass(frozen=True)
class _Plan:
    """Everything about the truth view that does not depend on the surface."""

    grid_shape: tuple[int, int]  # coarse nodes (rows, cols)
    node_px: Array  # (K, 2) truth pixel of each node that sees the object plane
    node_index: NDArray[np.intp]  # (K,) flat index of those nodes in the coarse grid
    targets: Array  # (K, 3) their object points, mm
    node_q0: Array  # (K, 2) where their rays cross flat water, mm: Newton's start
    truth_status: NDArray[np.int8]  # (rows, cols) status of every node in the truth view
    base_x: NDArray[np.float32]  # (H, W) column of every pixel
    base_y: NDArray[np.float32]  # (H, W) row of every pixel
    cell_area: NDArray[np.float64]  # (rows - 1, cols - 1) pixels in each coarse cell


_PLANS: dict[tuple, _Plan] = {}


def _plan_key(camera: PinholeCamera, h0: float, n: float, z: float, step: int) -> tuple:
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


def _make_plan(camera: PinholeCamera, h0: float, n: float, z: float, step: int) -> _Plan:
    w, h = camera.width_px, camera.height_px
    # Nodes every `step` pixels from 0 up to (or just past) the last pixel: every pixel then lies
    # in a cell of four nodes and bilinear interpolation never extrapolates.
    ncol = -(-(w - 1) // step) + 1
    nrow = -(-(h - 1) // step) + 1
    cols, rows = np.meshgrid(np.arange(ncol) * float(step), np.arange(nrow) * float(step))
    truth = trace_to_object(camera, None, h0, n, z, cols, rows)
    ok = truth.ok.ravel()
    targets = truth.object_mm.reshape(-1, 3)[ok]
    q0 = truth.surface_mm.reshape(-1, 3)[ok, :2]
    base_x, base_y = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return _Plan(
        (nrow, ncol),
        np.column_stack([cols.ravel(), rows.ravel()])[ok],
        np.flatnonzero(ok),
        targets,
        q0,
        truth.status,
        base_x,
        base_y,
        np.outer(_cell_sizes(h, nrow, step), _cell_sizes(w, ncol, step)),
    )


def _cell_sizes(n_px: int, n_nodes: int, step: int) -> NDArray[np.float64]:
    """Pixels in each of the ``n_nodes - 1`` cells along an axis of ``n_px`` pixels: ``step``
    each, the rest in the last (it also holds a last pixel lying exactly on the last node)."""
    sizes = np.full(n_nodes - 1, float(step))
    sizes[-1] = n_px - step * (n_nodes - 2)
    return sizes


def _plan(camera: PinholeCamera, h0: float, n: float, z: float, step: int) -> _Plan:
    key = _plan_key(camera, h0, n, z, step)
    if key not in _PLANS:
        if len(_PLANS) >= 4:
            _PLANS.clear()
        _PLANS[key] = _make_plan(camera, h0, n, z, step)
    return _PLANS[key]


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
    plan: _Plan, px: Array, status: NDArray[np.int8]
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.int8]]:
    """Displacement ``u - p`` in columns and in rows (rows, cols) px at the coarse nodes (0 where
    unsolved) and the status of every node (the truth view's where it sees no object)."""
    node_status = plan.truth_status.copy().ravel()
    node_status[plan.node_index] = status
    disp = np.zeros((2, plan.grid_shape[0] * plan.grid_shape[1]), dtype=np.float32)
    solved = status == RayStatus.OK
    disp[:, plan.node_index[solved]] = (px[solved] - plan.node_px[solved]).T
    dx, dy = disp.reshape((2,) + plan.grid_shape)
    return dx, dy, node_status.reshape(plan.grid_shape)


def _pixel_warp(
    plan: _Plan,
    disp_x: NDArray[np.float32],
    disp_y: NDArray[np.float32],
    node_status: NDArray[np.int8],
    step: int,
) -> tuple[NDArray[np.float32], NDArray[np.float32], BoolArray, dict[str, int]]:
    """Full-resolution sampling columns and rows (H, W), validity (H, W) and counts per cause.

    A pixel is valid when the four nodes of its cell were solved and its sampling position
    lies inside the distorted image.
    """
    h, w = plan.base_x.shape
    # The node grid is a scaled copy of the pixel grid, so an affine warp reads it, one channel
    # at a time: OpenCV's two-channel path is several times slower and rounds the read position
    # to 1/32 of a cell (up to ~0.1 px of warp for steps that do not divide 32); this one is
    # bilinear to ~1e-5 px for any step. Displacements are interpolated, not positions: they
    # vary slowly, so float32 costs nothing.
    scale = np.array([[1.0 / step, 0.0, 0.0], [0.0, 1.0 / step, 0.0]])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP

    def positions(disp: NDArray[np.float32], base: NDArray[np.float32]) -> NDArray[np.float32]:
        full = cv2.warpAffine(disp, scale, (w, h), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        return cv2.add(full, base, dst=full)

    map_x, map_y = positions(disp_x, plan.base_x), positions(disp_y, plan.base_y)
    cell = _cell_status(node_status)
    # Each cell's flag over its step x step pixels; a last pixel lying exactly on the last node
    # belongs to the cell before it.
    cell_ok = (cell == RayStatus.OK).view(np.uint8) * np.uint8(255)
    cell_ok = cv2.resize(
        cell_ok, (cell.shape[1] * step, cell.shape[0] * step), interpolation=cv2.INTER_NEAREST
    )
    pad = (max(0, h - cell_ok.shape[0]), max(0, w - cell_ok.shape[1]))
    if any(pad):
        cell_ok = cv2.copyMakeBorder(cell_ok, 0, pad[0], 0, pad[1], cv2.BORDER_REPLICATE)
    cell_ok = cell_ok[:h, :w]
    # 255 inside the image (as PinholeCamera.in_image) and in a solved cell.
    valid = cv2.inRange(map_x, -0.5, w - 0.5)
    cv2.bitwise_and(valid, cv2.inRange(map_y, -0.5, h - 0.5), dst=valid)
    cv2.bitwise_and(valid, cell_ok, dst=valid)
    hist = np.bincount(cell.ravel(), weights=plan.cell_area.ravel(), minlength=len(RayStatus))
    counts = {s.name.lower(): int(round(hist[s])) for s in RayStatus}
    n_valid = cv2.countNonZero(valid)
    counts["out_of_view"] += counts["ok"] - n_valid
    counts["ok"] = n_valid
    return map_x, map_y, valid.view(bool), counts


def restore_view(
    distorted: NDArray,
    camera: PinholeCamera,
    surface_est: Heightfield | None,
    h0_mm: float,
    n_water: float,
    z_object_mm: float,
    warp_step_px: int = 8,
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

    Returns
    -------
    Restoration
    """
    t_start = time.perf_counter()
    img = _check_image(distorted, camera)
    if isinstance(warp_step_px, bool) or int(warp_step_px) != warp_step_px or warp_step_px < 1:
        raise WaiInputError(
            f"restore_view: warp_step_px must be a positive integer, got {warp_step_px!r}"
        )
    step = int(warp_step_px)
    _check_system(h0_mm, n_water, z_object_mm)
    t = {"plan": time.perf_counter()}
    plan = _plan(camera, h0_mm, n_water, z_object_mm, step)
    t["surface"] = time.perf_counter()
    model = _surface_model(surface_est, h0_mm)
    optics = _Optics(camera.pose.center_lab_mm, float(n_water), float(z_object_mm))
    t["solve"] = time.perf_counter()
    px, st, _, _ = _newton(
        camera, model, optics, plan.targets[:, :2], plan.node_q0, _WARP_TOL_PX, _WARP_ITER
    )
    t["upsample"] = time.perf_counter()
    map_x, map_y, valid, counts = _pixel_warp(plan, *_node_warp(plan, px, st), step)
    t["remap"] = time.perf_counter()
    # Half-pixel border: replicate rather than blend with black. Sampled straight into the
    # result, whose invalid pixels are then zeroed (x - x under the mask; the image is finite):
    # one full-size array less to allocate and fault in.
    out = np.empty(img.shape, dtype=img.dtype)
    cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, dst=out, borderMode=cv2.BORDER_REPLICATE)
    cv2.subtract(out, out, dst=out, mask=cv2.bitwise_not(valid.view(np.uint8)))
    t["end"] = time.perf_counter()
    names = list(t)
    timings = {a: 1e3 * (t[b] - t[a]) for a, b in zip(names[:-1], names[1:], strict=True)}
    timings["total"] = 1e3 * (t["end"] - t_start)
    return Restoration(out, valid, counts, timings, step, map_x, map_y)
