"""What the view's restoration keeps from frame to frame: the flat-water (truth) view of camera v
on the coarse warp grid (:class:`ViewPlan`, all of :func:`restoration.reverse_trace.restore_view`
that does not depend on the surface), its scratch arrays, and a sequence's warp so far
(:class:`ViewState`)."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera
from wai_core.optics import RayStatus, _check_system, trace_to_object
from wai_core.port import pack_port

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


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
        pack_port(camera).tobytes(),
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
