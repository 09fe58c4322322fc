"""Calibrating a rig's cameras from checkerboard images, as the field does (OpenCV).

Each camera's intrinsics (focal length with square pixels, principal point, distortion k1, k2,
p1, p2) come from ``cv2.findChessboardCornersSB`` and ``cv2.calibrateCameraExtended`` over a
dozen views of a planar board. A rig file (JSON) records the fits with their standard
deviations and reprojection RMS, what they could not determine, and the configuration keys
that ``wai restore --rig`` applies (:func:`read_rig`).
"""

from __future__ import annotations

import json
import platform
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from restoration.video.checkerboard import DETECT_SEED
from wai_core.config import DeviceConfig
from wai_core.errors import WaiInputError
from wai_core.io import write_json

__all__ = [
    "PORT_TILT_UNDETERMINED", "PORT_UNDETERMINED", "PROJECTOR_PORT_UNDETERMINED",
    "PROJECTOR_TILT_UNDETERMINED", "RIG_FORMAT", "SIGNIFICANT_SIGMAS", "UNDETERMINED", "BoardSpec",
    "DeviceFit", "FlatFit", "board_views", "calibrate_device", "find_corners", "is_written_rig",
    "read_rig", "refine_on_flat_water", "rig_keys", "rig_undetermined", "write_rig",
]

RIG_FORMAT = "wai-rig/1"
"""The ``format`` of a rig file :func:`write_rig` wrote: what tells it from a hand-written one
(which ``wai restore --rig`` reads alike, and ``wai calibrate --out`` never replaces)."""

UNDETERMINED = (
    "poses (rotation, translation_mm): measure them in the lab frame (`wai guide rig`)",
    "the projector's intrinsics",
    "the diffuser's height and extent, the water level and index",
)
"""What checkerboards seen by the cameras cannot give."""

PROJECTOR_PORT_UNDETERMINED = ("the projector's port (its images are not a camera's; "
                               "calibrate --flat fits its gap on the flat-water spots)")
"""What board views cannot give of the projector (``wai calibrate --flat`` can)."""
PORT_UNDETERMINED = (
    "the port's thickness and index (its maker's: taken from --config)",
    PROJECTOR_PORT_UNDETERMINED,
)
"""What a port's board views are not asked to give."""
PORT_TILT_UNDETERMINED = ("a camera port's tilt, where its fit held the port square to the "
                          "optical axis")
"""Left undetermined by a port fit that did not fit the tilt (``fit_tilt=False``)."""
PROJECTOR_TILT_UNDETERMINED = ("the projector port's tilt (the flat-water fit takes it from "
                               "--config)")
"""Left undetermined by ``calibrate --flat``, which fits the projector port's gap alone."""


@dataclass(frozen=True)
class BoardSpec:
    """A checkerboard's inner corners (``cols`` x ``rows``) and square size, mm.

    Examples
    --------
    >>> BoardSpec(3, 3, 10.0).corners_mm()[[0, 1, 3]].tolist()
    [[10.0, 10.0, 0.0], [20.0, 10.0, 0.0], [10.0, 20.0, 0.0]]
    """

    cols: int
    rows: int
    square_mm: float

    def corners_mm(self) -> NDArray[np.float32]:
        """The inner corners (cols * rows, 3) on the board, row by row, mm."""
        j, i = np.mgrid[1:self.rows + 1, 1:self.cols + 1]
        pts = np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=1) * self.square_mm
        return pts.astype(np.float32)


@dataclass
class DeviceFit:
    """One camera's calibration.

    Attributes
    ----------
    fx_px, fy_px, cx_px, cy_px : float
        Focal lengths (equal: square pixels) and principal point, px.
    distortion : (5,) ndarray
        OpenCV's ``(k1, k2, p1, p2, k3)`` (k3 held at 0).
    sigma : dict of str to float
        Standard deviations of ``fx_px``, ``cx_px``, ``cy_px``, ``k1``, ``k2``, ``p1``, ``p2``.
    rms_px : float
        Reprojection RMS over every corner of the views used, px.
    view_rms_px : list of float
        Each used view's RMS, px.
    n_used, n_rejected : int
        Views whose board was found, and views without one (never silently dropped).
    corners_px, reprojected_px : list of (K, 2) ndarray
        Each used view's corners as found and as the fit reprojects them, px (for the
        figures: :func:`restoration.figures.calibration_figure`).
    views : list of int
        Each used view's index among the images given.
    held_zero : dict of str to float
        Distortion terms held at zero, the views not determining them
        (:data:`SIGNIFICANT_SIGMAS`; their ``sigma`` is 0), each with its standard deviation
        where it was last free: how far the views would let it move.
    """

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion: NDArray[np.float64]
    sigma: dict[str, float]
    rms_px: float
    view_rms_px: list[float] = field(default_factory=list)
    n_used: int = 0
    n_rejected: int = 0
    corners_px: list[NDArray[np.float32]] = field(default_factory=list, repr=False)
    reprojected_px: list[NDArray[np.float64]] = field(default_factory=list, repr=False)
    views: list[int] = field(default_factory=list, repr=False)
    held_zero: dict[str, float] = field(default_factory=dict)

    def to_config_keys(self, device: str, dev: DeviceConfig) -> dict[str, Any]:
        """The configuration keys of ``device`` (its section ``dev`` gives the image size
        and sensor width) that this fit replaces."""
        cx0, cy0 = (dev.width_px - 1) / 2.0, (dev.height_px - 1) / 2.0
        return {
            f"{device}.focal_mm": self.fx_px * dev.sensor_width_mm / dev.width_px,
            f"{device}.principal_offset_px": [self.cx_px - cx0, self.cy_px - cy0],
            f"{device}.distortion": [float(v) for v in self.distortion],
        }

    def summary(self) -> dict[str, Any]:
        return {
            "fx_px": self.fx_px, "fy_px": self.fy_px, "cx_px": self.cx_px, "cy_px": self.cy_px,
            "distortion": [float(v) for v in self.distortion], "sigma": self.sigma,
            "rms_px": self.rms_px, "view_rms_px": self.view_rms_px, "views_used": self.n_used,
            "views_rejected": self.n_rejected, "held_at_zero": dict(self.held_zero),
        }


def _as_uint8(image: NDArray) -> NDArray[np.uint8]:
    img = np.asarray(image)
    if img.ndim == 3:
        img = img.mean(axis=2)
    if np.issubdtype(img.dtype, np.floating):
        hi = float(np.nanpercentile(img, 99.5)) or 1.0
        img = np.clip(img / hi * 255.0, 0, 255)
    return np.ascontiguousarray(img, dtype=np.uint8)


def find_corners(image: NDArray, board: BoardSpec) -> NDArray[np.float32] | None:
    """The board's inner corners (cols * rows, 2) px in ``image``, or None when not found."""
    flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
    cv2.setRNGSeed(DETECT_SEED)  # the detector draws from OpenCV's generator
    found, corners = cv2.findChessboardCornersSB(_as_uint8(image), (board.cols, board.rows),
                                                 flags=flags)
    return corners.reshape(-1, 2) if found else None


def board_views(images: Sequence[NDArray], board: BoardSpec, image_size: tuple[int, int],
                min_views: int, what: str = "images") -> tuple[list[NDArray], list[int], int]:
    """The board's corners in each image that shows it: ``(corners (cols * rows, 2) px per
    such image, their indices among ``images``, how many images do not show it)``.

    Raises
    ------
    WaiInputError
        When an image is not ``image_size`` (H, W), or fewer than ``min_views`` show the board
        (``what``: how the message names the images).
    """
    h, w = image_size
    corners_px, used = [], []
    for k, image in enumerate(images):
        if np.shape(image)[:2] != (h, w):
            raise WaiInputError(f"checkerboard image is {np.shape(image)[:2]}, not {(h, w)}")
        corners = find_corners(image, board)
        if corners is not None:
            corners_px.append(corners.astype(np.float32))
            used.append(k)
    if len(used) < min_views:
        raise WaiInputError(
            f"the board ({board.cols}x{board.rows} inner corners) was found in {len(used)} of "
            f"{len(images)} {what}: at least {min_views} are needed"
        )
    return corners_px, used, len(images) - len(used)


def calibrate_device(images: Sequence[NDArray], board: BoardSpec | Any,
                     image_size: tuple[int, int], min_views: int = 5,
                     select_terms: bool = True) -> DeviceFit:
    """Calibrate one camera from ``images`` of ``board``, each ``image_size`` (H, W).

    The lens model is the least the views call for: k1 always, k2 and the tangential pair
    (p1, p2) only past :data:`SIGNIFICANT_SIGMAS` standard deviations; each term that fails,
    the least significant first, is held at zero and the rest fitted again. A term the views
    do not determine, traded against k1 where the boards are, bends the lens where they seldom
    reach (the image's corners: docs/rig.md).

    Parameters
    ----------
    images : sequence of (H, W) or (H, W, 3) ndarray
        The board's views.
    board : BoardSpec
    image_size : (int, int)
        (H, W), px.
    min_views : int
        Views that must show the board.
    select_terms : bool
        Hold insignificant terms at zero (default); False fits k1, k2, p1 and p2 whatever the
        views say.

    Raises
    ------
    WaiInputError
        When fewer than ``min_views`` images show the board, or an image has another size.

    Examples
    --------
    >>> import numpy as np
    >>> blank = [np.zeros((60, 80), np.float32)] * 5
    >>> calibrate_device(blank, BoardSpec(9, 6, 20.0), (60, 80))  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    wai_core.errors.WaiInputError: the board (9x6 inner corners) was found in 0 of 5 images: ...
    """
    board = BoardSpec(int(board.cols), int(board.rows), float(board.square_mm))
    img_pts, used, rejected = board_views(images, board, image_size, min_views)
    obj = [board.corners_mm()] * len(img_pts)
    held: dict[str, float] = {}
    fit = _fit_lens(obj, img_pts, image_size, held)
    while select_terms:
        weakest = min(((terms, _significance(fit, terms)) for terms in _OPTIONAL_TERMS
                       if terms[0] not in held), key=lambda c: c[1], default=None)
        if weakest is None or not weakest[1] < SIGNIFICANT_SIGMAS:
            break
        held.update({t: fit.sigma[t] for t in weakest[0]})
        fit = _fit_lens(obj, img_pts, image_size, held)
    return replace(fit, n_rejected=rejected, corners_px=[c.reshape(-1, 2) for c in img_pts],
                   views=used)


SIGNIFICANT_SIGMAS = 3.0
"""A distortion term beyond k1 is fitted only where the free fit puts it this many standard
deviations from zero (:func:`calibrate_device`). Three, not two: OpenCV's deviations take the
corners' errors as independent, and they are not quite (a lens without tangential terms,
rendered on three seeds of 12 views, came out with p1 and p2 at 2.0-2.1 deviations on two)."""

_OPTIONAL_TERMS = (("k2",), ("p1", "p2"))  # the tangential pair is tested and held together
_DIST_INDEX = {"k1": 0, "k2": 1, "p1": 2, "p2": 3}


def _fit_lens(obj: list[NDArray], img_pts: list[NDArray], image_size: tuple[int, int],
              held: dict[str, float]) -> DeviceFit:
    """OpenCV's calibration of the views with the terms ``held`` at zero (k3 always)."""
    h, w = image_size
    flags = cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_FIX_K3
    if "k2" in held:
        flags |= cv2.CALIB_FIX_K2
    if "p1" in held:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    k0 = np.array([[1.0, 0.0, (w - 1) / 2.0], [0.0, 1.0, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    rms, k, dist, rvecs, tvecs, std_in, _, per_view = cv2.calibrateCameraExtended(
        obj, img_pts, (w, h), k0, np.zeros(5), flags=flags,
    )
    std = std_in.ravel()
    return DeviceFit(
        float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]),
        np.asarray(dist, float).ravel()[:5],
        # fx follows fy (square pixels): fy is the free parameter, with fy's deviation; a
        # term held at zero has none.
        {name: 0.0 if name in held else float(std[i]) for i, name in
         ((1, "fx_px"), (2, "cx_px"), (3, "cy_px"), (4, "k1"), (5, "k2"), (6, "p1"),
          (7, "p2"))},
        float(rms), [float(v) for v in np.ravel(per_view)], len(obj),
        reprojected_px=[cv2.projectPoints(o, r, t, k, dist)[0].reshape(-1, 2)
                        for o, r, t in zip(obj, rvecs, tvecs, strict=True)],
        held_zero=dict(held))


def _significance(fit: DeviceFit, terms: tuple[str, ...]) -> float:
    """How many standard deviations the most significant of ``terms`` lies from zero (inf
    where the fit gives no deviation: kept)."""
    return max(abs(float(fit.distortion[_DIST_INDEX[t]])) / fit.sigma[t]
               if fit.sigma[t] > 0 else np.inf for t in terms)


def rig_keys(fits: dict[str, DeviceFit], devices: dict[str, DeviceConfig]) -> dict[str, Any]:
    """The configuration keys of every fit."""
    keys: dict[str, Any] = {}
    for name, fit in fits.items():
        keys.update(fit.to_config_keys(name, devices[name]))
    return keys


def write_rig(path: str | Path, fits: dict[str, DeviceFit], devices: dict[str, DeviceConfig],
              board: BoardSpec | Any, flat: FlatFit | None = None,
              ports: dict[str, Any] | None = None) -> None:
    """Write the rig file: each device's fit, its configuration keys (camera s's refined on
    flat water when ``flat`` is given; each port of ``ports``, name to
    :class:`~restoration.port_calibration.PortFit`), what is undetermined."""
    ports = ports or {}
    undetermined = rig_undetermined(ports, flat)
    keys = rig_keys(fits, devices)
    for name, port in ports.items():
        keys.update(port.to_config_keys(name))
    if flat is not None:
        keys.update(flat.config_keys)
    write_json(path, {
        "format": RIG_FORMAT,
        "written_by": "wai calibrate",
        "flat_water": None if flat is None else {
            "config_keys": flat.config_keys, "sigma": flat.sigma,
            "rms_before_px": flat.rms_before_px, "rms_after_px": flat.rms_after_px,
            "spots": flat.n_spots},
        "devices": {name: fit.summary() for name, fit in fits.items()},
        "ports": {name: port.summary() for name, port in ports.items()},
        "config_keys": keys,
        "undetermined": undetermined,
        "board": {"cols": int(board.cols), "rows": int(board.rows),
                  "square_mm": float(board.square_mm)},
        "versions": {"opencv": cv2.__version__, "numpy": np.__version__,
                     "python": platform.python_version()},
    })


def rig_undetermined(ports: dict[str, Any] | None = None,
                     flat: FlatFit | None = None) -> list[str]:
    """What a calibration leaves undetermined: :data:`UNDETERMINED`, each fitted port's
    (:attr:`~restoration.port_calibration.PortFit.undetermined`), and for a projector port
    fitted on flat water the same but its gap.

    Examples
    --------
    >>> rig_undetermined() == list(UNDETERMINED)
    True
    """
    out = list(UNDETERMINED)
    told = [port.undetermined for port in (ports or {}).values()]
    if flat is not None and flat.fits_projector_port:
        tilt = () if flat.fits_projector_tilt else (PROJECTOR_TILT_UNDETERMINED,)
        told.append((*PORT_UNDETERMINED, *tilt))
    for items in told:
        out += [u for u in items if u not in out]
    if flat is not None and flat.fits_projector_port:
        out = [u for u in out if u != PROJECTOR_PORT_UNDETERMINED]
    return out


def is_written_rig(path: str | Path) -> bool:
    """Whether ``path`` is a rig file :func:`write_rig` wrote (its ``format`` is
    :data:`RIG_FORMAT`); any other file, a hand-written rig included, is the user's."""
    try:
        record = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(record, dict) and record.get("format") == RIG_FORMAT


def read_rig(path: str | Path) -> dict[str, Any]:
    """The configuration keys of a rig file (``config_keys``), to apply with
    :func:`wai_core.config.with_keys`.

    Raises
    ------
    WaiInputError
        Naming the file when it is missing, not JSON, or holds no ``config_keys`` table.
    """
    path = Path(path)
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        raise WaiInputError(f"{path}: rig file not found") from None
    except IsADirectoryError:
        raise WaiInputError(f"{path}: is a folder, not a rig file") from None
    except OSError as exc:
        raise WaiInputError(f"{path}: cannot read the rig file ({exc.strerror})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise WaiInputError(f"{path}: not a rig file (JSON): {exc}") from None
    keys = record.get("config_keys") if isinstance(record, dict) else None
    if not isinstance(keys, dict) or not keys:
        raise WaiInputError(f"{path}: needs a 'config_keys' table (written by wai calibrate)")
    return keys


PROJECTOR_GAP = "projector.port_gap_mm"
"""The configuration key of the projector port's gap (fitted on flat water)."""
PROJECTOR_TILT = "projector.port_tilt_deg"
"""The configuration key of the projector port's tilt (fitted on flat water when asked)."""


@dataclass
class FlatFit:
    """Camera s's intrinsics (and the projector's port) refined on the flat-water reference
    (:func:`refine_on_flat_water`).

    Attributes
    ----------
    config_keys : dict
        ``camera_s.focal_mm`` and ``camera_s.principal_offset_px``, refined; with a projector
        port, ``projector.port_gap_mm`` too, and ``projector.port_tilt_deg`` where its tilt
        was fitted.
    rms_before_px, rms_after_px : float
        The flat-water residual (detected against predicted spots, RMS px) before and after.
    n_spots : int
        Spots the fit used.
    sigma : dict of str to float
        Standard deviation of each fitted number (``camera_s.focal_mm``, mm;
        ``camera_s.principal_offset_px``, its larger axis, px; ``projector.port_gap_mm``,
        mm; ``projector.port_tilt_deg``, its larger axis, deg), from the fit's Jacobian and
        residual.
    """

    config_keys: dict[str, Any]
    rms_before_px: float
    rms_after_px: float
    n_spots: int
    sigma: dict[str, float] = field(default_factory=dict)

    @property
    def fits_projector_port(self) -> bool:
        """Whether the projector port's gap was fitted."""
        return PROJECTOR_GAP in self.config_keys

    @property
    def fits_projector_tilt(self) -> bool:
        """Whether the projector port's tilt was fitted."""
        return PROJECTOR_TILT in self.config_keys


def fit_covariance(fit: Any) -> NDArray:
    """The covariance (n, n) of a ``scipy.optimize.least_squares`` result's n parameters: the
    residual's variance (its sum of squares over the degrees of freedom) times
    ``(J^T J)^-1``, a dense or sparse Jacobian alike."""
    jac = fit.jac.toarray() if hasattr(fit.jac, "toarray") else np.asarray(fit.jac)
    dof = max(fit.fun.size - fit.x.size, 1)
    return np.linalg.pinv(jac.T @ jac) * float(np.sum(fit.fun**2)) / dof


def refine_on_flat_water(cfg: Any, pattern_flat: NDArray, max_px: float = 3.0,
                         projector_port: bool | None = None,
                         held: Sequence[dict[str, Any]] = (),
                         projector_tilt: bool = False) -> FlatFit:
    """Refine camera s's focal length and principal point so that the flat-water pattern's
    spots land where the rig predicts them (its poses, diffuser and water level taken as
    known; the lens's distortion as calibrated: freeing k1, k2 too trades them against the
    focal length). Behind a projector port (``[projector].port_thickness_mm > 0``) the gap
    between the projector's lens and its port is fitted too, the port's thickness and index
    taken as given: the projector shows no checkerboard, but its dots through the port bend
    as no pinhole's rays do, and the flat reference's ~1000 spots see it.

    The structured light's level rests on camera s's intrinsics far more finely than a
    checkerboard pins them (docs/results.md, "Calibrating a real rig"); the ~1000 spots of the
    flat reference pin them again, in the rig's own geometry.

    Parameters
    ----------
    cfg : SystemConfig
        The rig: its poses, diffuser, water level, camera s's lens as calibrated.
    pattern_flat : (H, W) or (H, W, 3) ndarray
        The flat-water pattern.
    max_px : float
        Farthest a spot may lie from its prediction to be paired with it, px.
    projector_port : bool, optional
        Fit the projector port's gap (default: when ``cfg``'s projector has a port).
    held : sequence of dict
        Configuration keys the fit holds, each moved by its standard deviation (e.g. camera
        s's distortion with k1 one sigma up, as its checkerboards left it): the fit is
        repeated with each, and the change of every fitted number joins its ``sigma`` in
        quadrature. The spots alone leave the port's gap correlated with camera s's lens, so
        without these the gap's sigma is the spots' noise only.
    projector_tilt : bool
        Fit the projector port's tilt too (with its gap), from the configuration's tilt.

    Raises
    ------
    WaiInputError
        When fewer than 50 spots lie within ``max_px`` of their prediction.
    """
    from scipy.optimize import least_squares
    from scipy.spatial import cKDTree

    from restoration.features import detect_spots, predict_flat_spots, spot_sigma_px
    from restoration.undistort import diffuser_pinhole_px
    from wai_core.config import with_keys

    sigma = spot_sigma_px(cfg)
    raw = detect_spots(pattern_flat, spot_sigma_px=float(sigma) if sigma > 0 else None)
    raw_px = raw.centres_px[~raw.border]
    dev = cfg.camera_s

    port = cfg.projector.port_thickness_mm > 0 if projector_port is None else projector_port
    if port and not cfg.projector.port_thickness_mm > 0:
        raise WaiInputError("refine_on_flat_water: the projector has no port to fit "
                            "([projector].port_thickness_mm is 0)")
    tilt = bool(projector_tilt)
    if tilt and not port:
        raise WaiInputError("refine_on_flat_water: the projector port's tilt is fitted with "
                            "its gap (projector_port)")

    def rig(p: NDArray, base: Any = cfg) -> Any:
        keys = {"camera_s.focal_mm": float(p[0]),
                "camera_s.principal_offset_px": [float(p[1]), float(p[2])]}
        if port:  # a gap must stay positive: fitted as its logarithm (kept to 1 um .. 1 m)
            keys[PROJECTOR_GAP] = float(np.exp(np.clip(p[3], -7.0, 7.0)))
        if tilt:
            keys[PROJECTOR_TILT] = [float(p[4]), float(p[5])]
        return with_keys(base, keys)

    def predicted(p: NDArray, base: Any = cfg) -> tuple[NDArray, NDArray]:
        c = rig(p, base)
        _, _, pred, in_view = predict_flat_spots(c)
        detected = diffuser_pinhole_px(c, raw_px)
        return detected, np.where(in_view[:, None], pred, np.nan)

    start = np.array([dev.focal_mm, *dev.principal_offset_px], float)
    scale = np.array([dev.focal_mm * 1e-3, 1.0, 1.0])
    if port:
        start = np.append(start, np.log(cfg.projector.port_gap_mm))
        scale = np.append(scale, 0.1)
    if tilt:
        start = np.append(start, [float(v) for v in cfg.projector.port_tilt_deg])
        scale = np.append(scale, [0.1, 0.1])

    def pairs_at(p: NDArray) -> tuple[NDArray, NDArray]:
        seen, pred = predicted(p)
        dots = np.flatnonzero(np.isfinite(pred).all(axis=1))  # indices stay the grid's
        dist, nearest = cKDTree(pred[dots]).query(seen)
        index = dots[np.minimum(nearest, len(dots) - 1)]
        keep = np.isfinite(dist) & (dist < max_px)
        if keep.sum() < 50:
            raise WaiInputError(f"pattern_flat: only {int(keep.sum())} spots lie within "
                                f"{max_px} px of the rig's prediction: check the poses and "
                                "the diffuser")
        return np.flatnonzero(keep), index[keep]

    def residual_of(pairs: tuple[NDArray, NDArray], base: Any = cfg) -> Any:
        def residual(p: NDArray) -> NDArray:
            s, q = predicted(p, base)
            return np.nan_to_num((s[pairs[0]] - q[pairs[1]]).ravel(), nan=max_px)
        return residual

    def settle(x: NDArray, pairs: tuple[NDArray, NDArray],
               free: NDArray) -> tuple[NDArray, tuple[NDArray, NDArray]]:
        """The parameters ``free`` fitted (the others held), the spots paired again with the
        nearest prediction, which moves as the fit does, until the pairs hold."""
        for _ in range(4):
            held = x.copy()

            def residual(q: NDArray, held: NDArray = held,
                         pairs: tuple[NDArray, NDArray] = pairs) -> NDArray:
                full = held.copy()
                full[free] = q
                return residual_of(pairs)(full)

            x = held.copy()
            x[free] = least_squares(residual, held[free], x_scale=scale[free], method="lm").x
            again = pairs_at(x)
            if len(again[0]) == len(pairs[0]) and all(map(np.array_equal, again, pairs)):
                break
            pairs = again
        return x, pairs

    # A tilt moves every spot (a degree: ~4 px), the gap bends the outer ones: the tilt is
    # found first with the gap held, so that a gap fitted against pairs the tilt has not yet
    # put right cannot run off.
    pairs, x = pairs_at(start), start
    if tilt:
        x, pairs = settle(x, pairs, np.array([0, 1, 2, 4, 5]))
    x, pairs = settle(x, pairs, np.arange(start.size))
    residual = residual_of(pairs)
    fit = least_squares(residual, x, x_scale=scale, method="lm")
    keep = pairs[0]
    before = float(np.sqrt(np.mean(residual_of(pairs_at(start))(start) ** 2) * 2))
    after = float(np.sqrt(np.mean(fit.fun**2) * 2))
    best = rig(fit.x)
    keys = {"camera_s.focal_mm": best.camera_s.focal_mm,
            "camera_s.principal_offset_px": list(best.camera_s.principal_offset_px)}
    # Standard deviations: the fit's own, the gap's by its logarithm's (d gap = gap d log gap).
    var = np.clip(np.diag(fit_covariance(fit)), 0.0, None)
    for shifted in held:  # the held values' own uncertainty, one refit each
        moved = least_squares(residual_of(pairs, with_keys(cfg, shifted)), fit.x,
                              x_scale=scale, method="lm").x
        var = var + (moved - fit.x) ** 2
    sd = np.sqrt(var)
    sigma = {"camera_s.focal_mm": float(sd[0]),
             "camera_s.principal_offset_px": float(max(sd[1], sd[2]))}
    if port:
        keys[PROJECTOR_GAP] = best.projector.port_gap_mm
        sigma[PROJECTOR_GAP] = float(best.projector.port_gap_mm * sd[3])
    if tilt:
        keys[PROJECTOR_TILT] = [float(v) for v in best.projector.port_tilt_deg]
        sigma[PROJECTOR_TILT] = float(max(sd[4], sd[5]))
    return FlatFit(keys, before, after, int(keep.size), sigma)
