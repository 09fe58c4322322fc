"""Calibrating a flat housing port from checkerboards seen through it in the water.

A camera in a housing is calibrated in two steps, as the field does (Treibitz, Schechner, Kunz
& Singh, PAMI 2012; Agrawal, Ramalingam, Taguchi & Chari, CVPR 2012): its lens in air
(:func:`~restoration.rig_calibration.calibrate_device`), then the port from a dozen views of a
board in the water. The port's glass (thickness, index) comes from its maker and the water's
index from the scene; what the housing hides is where the lens sits behind the port, the
*gap*, and how far the window's normal is off the lens's axis, its *tilt*. :func:`calibrate_port`
fits both, with every board's pose, by least squares on the corners' pixels through the exact
two-refraction model (:func:`wai_core.lens.port_pinhole_xy`): the non-central camera's rays,
not a pinhole's.

A pinhole fitted to the same views (the focal length free, the port ignored) is reported beside
it: its residual is what the port's non-centrality costs a model that ignores it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from restoration.rig_calibration import (
    PORT_TILT_UNDETERMINED,
    PORT_UNDETERMINED,
    BoardSpec,
    DeviceFit,
    board_views,
    fit_covariance,
)
from wai_core.config import MAX_PORT_TILT_DEG
from wai_core.distortion import undistort
from wai_core.errors import WaiInputError
from wai_core.lens import port_pinhole_xy

__all__ = ["PortFit", "calibrate_port"]



@dataclass
class PortFit:
    """One camera's port, fitted in the water.

    Attributes
    ----------
    gap_mm, sigma_gap_mm : float
        Air between the lens's pinhole and the port's inner face (along its normal), and its
        standard deviation (from the fit's Jacobian and residual), mm.
    tilt_deg, sigma_tilt_deg : (2,) tuple of float
        The port's normal off the optical axis (``port_tilt_deg``: towards ``+x``, ``+y``)
        and its standard deviations, deg; zeros where the fit held it square
        (``fit_tilt=False``, ``tilt_fitted`` False).
    thickness_mm, port_n, n_water : float
        The port's thickness and index and the water's, as given (held fixed).
    rms_px : float
        Reprojection RMS through the fitted port over every corner, px.
    pinhole_rms_px : float
        The same for a pinhole fitted to the same views (focal length and poses free, no
        port): what ignoring the port costs, px.
    view_rms_px : list of float
        Each used view's RMS through the port, px.
    n_used, n_rejected, n_outliers : int
        Views fitted, views without the board, and views set aside as outliers (a view
        whose RMS exceeds :data:`OUTLIER_FACTOR` x the median's and
        :data:`OUTLIER_FLOOR_PX`).
    """

    gap_mm: float
    sigma_gap_mm: float
    thickness_mm: float
    port_n: float
    n_water: float
    rms_px: float
    pinhole_rms_px: float
    view_rms_px: list[float] = field(default_factory=list)
    tilt_deg: tuple[float, float] = (0.0, 0.0)
    sigma_tilt_deg: tuple[float, float] = (0.0, 0.0)
    tilt_fitted: bool = False
    n_used: int = 0
    n_rejected: int = 0
    n_outliers: int = 0

    @property
    def undetermined(self) -> tuple[str, ...]:
        """What the fit does not give (:data:`PORT_UNDETERMINED`, and the tilt where it was
        held square)."""
        if self.tilt_fitted:
            return PORT_UNDETERMINED
        return (*PORT_UNDETERMINED, PORT_TILT_UNDETERMINED)

    def to_config_keys(self, device: str) -> dict[str, Any]:
        """The ``[device]`` port keys this fit sets."""
        return {f"{device}.port_gap_mm": self.gap_mm,
                f"{device}.port_thickness_mm": self.thickness_mm,
                f"{device}.port_n": self.port_n,
                f"{device}.port_tilt_deg": list(self.tilt_deg)}

    def summary(self) -> dict[str, Any]:
        return {"gap_mm": self.gap_mm, "sigma_gap_mm": self.sigma_gap_mm,
                "tilt_deg": list(self.tilt_deg), "sigma_tilt_deg": list(self.sigma_tilt_deg),
                "thickness_mm": self.thickness_mm, "port_n": self.port_n,
                "n_water": self.n_water, "rms_px": self.rms_px,
                "pinhole_rms_px": self.pinhole_rms_px, "view_rms_px": self.view_rms_px,
                "views_used": self.n_used, "views_rejected": self.n_rejected,
                "views_outliers": self.n_outliers}


def _normalised(corners_px: NDArray, lens: DeviceFit) -> NDArray:
    """Corner pixels (K, 2) to the lens's ideal normalised coordinates x/z, y/z (K, 2)."""
    px = np.asarray(corners_px, np.float64)
    xd, yd = (px[:, 0] - lens.cx_px) / lens.fx_px, (px[:, 1] - lens.cy_px) / lens.fy_px
    x, y = undistort(xd, yd, tuple(float(v) for v in lens.distortion))
    return np.stack([x, y], axis=1)


def _poses_to_cam(params: NDArray, board_mm: NDArray) -> NDArray:
    """The board's corners (V, K, 3) in the camera for the views' poses ``params`` (V, 6):
    rotation vector, translation mm."""
    rot = Rotation.from_rotvec(params[:, :3]).as_matrix()
    return np.einsum("vij,kj->vki", rot, board_mm) + params[:, None, 3:]


def _sparsity(views: int, corners: int, shared: int) -> lil_matrix:
    """Which parameters each residual depends on: the shared ones, and its view's pose."""
    rows, cols = 2 * views * corners, shared + 6 * views
    s = lil_matrix((rows, cols), dtype=int)
    s[:, :shared] = 1
    for v in range(views):
        s[2 * corners * v:2 * corners * (v + 1), shared + 6 * v:shared + 6 * (v + 1)] = 1
    return s


def calibrate_port(images: Sequence[NDArray], board: BoardSpec | Any, lens: DeviceFit,
                   thickness_mm: float, port_n: float, n_water: float,
                   image_size: tuple[int, int], gap_start_mm: float = 5.0,
                   min_views: int = 5, fit_tilt: bool = True) -> PortFit:
    """Fit the gap behind a flat port, and its tilt, from ``images`` (H, W each,
    ``image_size``) of ``board`` taken through the port in water, the lens calibrated in air
    (``lens``).

    Parameters
    ----------
    images : sequence of (H, W) or (H, W, 3) arrays
        The board in 10-20 poses, seen through the port from the water.
    board : BoardSpec
    lens : DeviceFit
        The camera's lens, calibrated in air (:func:`~restoration.calibrate_device`).
    thickness_mm, port_n : float
        The port's thickness, mm, and index (held fixed: the maker's).
    n_water : float
        The water's index during the views.
    image_size : (int, int)
        ``(H, W)``, px.
    gap_start_mm : float
        Where the fit starts, mm.
    min_views : int
    fit_tilt : bool
        Fit the port's tilt too (from square); False holds it square to the axis.

    Returns
    -------
    PortFit

    Raises
    ------
    WaiInputError
        Fewer than ``min_views`` images show the board, an image has another size, or the
        port's thickness or indices are not physical.

    Examples
    --------
    >>> from mitsuba_wai.checkerboards import Board, render_checkerboards
    >>> from restoration import calibrate_device
    >>> from wai_core import load_system, with_keys
    >>> cfg = with_keys(load_system("paper"), {"camera_v.port_thickness_mm": 5.0,
    ...                                        "camera_v.port_gap_mm": 3.0})
    >>> size = (600, 800)
    >>> boards = render_checkerboards(cfg, "camera_v", 10)                 # doctest: +SKIP
    >>> lens = calibrate_device(boards, Board(), size)                     # doctest: +SKIP
    >>> wet = render_checkerboards(cfg, "camera_v", 10, seed=4, medium="water")  # doctest: +SKIP
    >>> fit = calibrate_port(wet, Board(), lens, 5.0, 1.49, 4 / 3, size)  # doctest: +SKIP
    >>> round(fit.gap_mm, 1)                                               # doctest: +SKIP
    2.9
    """
    if not (thickness_mm > 0 and port_n >= 1 and n_water >= 1):
        raise WaiInputError(f"port: needs thickness > 0 mm and indices >= 1, not thickness "
                            f"{thickness_mm} mm, port index {port_n}, water {n_water}")
    board = BoardSpec(int(board.cols), int(board.rows), float(board.square_mm))
    found, _, rejected = board_views(images, board, image_size, min_views,
                                     "images through the port")
    seen = [_normalised(corners, lens) for corners in found]
    first = _fit(np.stack(seen), board, lens, thickness_mm, port_n, n_water, gap_start_mm,
                 fit_tilt)
    # A view the port model cannot fit (a corner found off its square) would pull the gap:
    # it is set aside, counted, and the rest fitted again.
    rms = np.asarray(first.view_rms_px)
    bad = rms > max(OUTLIER_FACTOR * float(np.median(rms)), OUTLIER_FLOOR_PX)
    fit = first
    if bad.any() and (~bad).sum() >= min_views:
        fit = _fit(np.stack(seen)[~bad], board, lens, thickness_mm, port_n, n_water,
                   first.gap_mm, fit_tilt)
        fit.n_outliers = int(bad.sum())
    fit.n_rejected = rejected
    return fit


OUTLIER_FACTOR = 3.0
OUTLIER_FLOOR_PX = 0.5
"""A view whose RMS exceeds both this factor times the median view's and this floor (px) is
set aside as an outlier."""


def _fit(obs: NDArray, board: BoardSpec, lens: DeviceFit, thickness_mm: float, port_n: float,
         n_water: float, gap_start_mm: float, fit_tilt: bool = True) -> PortFit:
    """The gap (and the tilt) and the poses fitted to the views' normalised corners ``obs``
    (V, K, 2)."""
    obj = board.corners_mm().astype(np.float64)
    views, corners = obs.shape[:2]
    f_px = lens.fy_px

    # Each pose starts from a pinhole in the water (slopes n_water times the water ray's).
    poses = []
    for o in obs:
        _, rvec, tvec = cv2.solvePnP(obj, o * n_water, np.eye(3), None,
                                     flags=cv2.SOLVEPNP_ITERATIVE)
        poses.append(np.concatenate([rvec.ravel(), tvec.ravel()]))
    pose0 = np.asarray(poses)

    shared = 3 if fit_tilt else 1  # gap, then the tilt's two angles (deg)

    def port_residual(p: NDArray) -> NDArray:
        pts = _poses_to_cam(p[shared:].reshape(views, 6), obj)
        tilt = (p[1], p[2]) if fit_tilt else (0.0, 0.0)
        x, y, ok = port_pinhole_xy(pts, p[0], thickness_mm, port_n, n_water, tilt)
        xy = np.where(ok[..., None], np.stack([x, y], axis=-1), np.nan)
        r = (xy - obs) * f_px
        return np.nan_to_num(r, nan=1e3).ravel()

    def pinhole_residual(p: NDArray) -> NDArray:
        pts = _poses_to_cam(p[1:].reshape(views, 6), obj)
        return ((pts[..., :2] / pts[..., 2:] * p[0] - obs) * f_px).ravel()

    start = [gap_start_mm, 0.0, 0.0][:shared]
    x0 = np.concatenate([start, pose0.ravel()])
    limit = np.full(shared - 1, MAX_PORT_TILT_DEG)
    fit = least_squares(port_residual, x0, jac_sparsity=_sparsity(views, corners, shared),
                        bounds=(np.r_[0.0, -limit, np.full(6 * views, -np.inf)],
                                np.r_[np.inf, limit, np.full(6 * views, np.inf)]),
                        x_scale="jac", method="trf")
    pinhole = least_squares(pinhole_residual, np.concatenate([[n_water], pose0.ravel()]),
                            jac_sparsity=_sparsity(views, corners, 1), x_scale="jac",
                            method="trf")
    res = fit.fun.reshape(views, corners, 2)
    cov = fit_covariance(fit)
    sd = np.sqrt(np.clip(np.diag(cov)[:shared], 0.0, None))
    tilt = (float(fit.x[1]), float(fit.x[2])) if fit_tilt else (0.0, 0.0)
    sigma_tilt = (float(sd[1]), float(sd[2])) if fit_tilt else (0.0, 0.0)
    return PortFit(
        gap_mm=float(fit.x[0]), sigma_gap_mm=float(sd[0]),
        tilt_deg=tilt, sigma_tilt_deg=sigma_tilt, tilt_fitted=bool(fit_tilt),
        thickness_mm=float(thickness_mm), port_n=float(port_n), n_water=float(n_water),
        rms_px=float(np.sqrt(np.mean(np.sum(res**2, axis=-1)))),
        pinhole_rms_px=float(np.sqrt(np.mean(pinhole.fun**2) * 2)),
        view_rms_px=[float(v) for v in np.sqrt(np.mean(np.sum(res**2, axis=-1), axis=1))],
        n_used=views,
    )
