"""Scoring (reads the truth): surface errors (eq. 44), image quality (eq. 45-47) and the
checkerboard corner statistic of the paper's Fig. 15.

Nothing here feeds back into the restoration; it only compares its outputs with the truth.

Images are compared on the [0, 1] scale (values are clipped to it). The paper's Table 2 implies
the same scale: its PSNR of 8.6414 dB goes with an MSE of 0.1367 only if ``max(I) = 1`` in eq. 46.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import binary_erosion
from skimage.metrics import structural_similarity

from restoration.reverse_trace import find_pixels
from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera
from wai_core.heightfield import Heightfield
from wai_core.port import PortCamera

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

# --------------------------------------------------------------------------------------------
# Surface
# --------------------------------------------------------------------------------------------


def surface_errors(est: Heightfield, truth: Heightfield) -> dict:
    """Height errors of an estimated surface at its own grid points (eq. 44).

    Compared where both surfaces are known (finite ``est.z`` and ``truth.height``).

    Parameters
    ----------
    est, truth : Heightfield
        Estimated and true water surfaces, mm.

    Returns
    -------
    dict
        ``rmse_mm`` (root mean square of ``est - truth``), ``rmse_demeaned_mm`` (the same after
        removing the mean offset: the paper's "unrecoverable bias" taken out), ``mean_offset_mm``,
        ``max_abs_mm``, ``n_points``, and ``error_map_mm`` (m, n) on ``est``'s grid
        (``x_mm`` (n,), ``y_mm`` (m,)), NaN where not compared.

    Raises
    ------
    WaiInputError
        If the two surfaces share no known point.
    """
    xx, yy = np.meshgrid(est.x, est.y)
    err = est.z - truth.height(xx, yy)
    both = np.isfinite(err)
    if not both.any():
        raise WaiInputError("surface_errors: the estimate and the truth share no known point")
    e = err[both]
    mean = float(e.mean())
    return {
        "rmse_mm": float(np.sqrt(np.mean(e**2))),
        "rmse_demeaned_mm": float(np.sqrt(np.mean((e - mean) ** 2))),
        "mean_offset_mm": mean,
        "max_abs_mm": float(np.abs(e).max()),
        "n_points": int(both.sum()),
        "error_map_mm": np.where(both, err, np.nan),
        "x_mm": est.x.copy(),
        "y_mm": est.y.copy(),
    }


# --------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------


def _as_unit_pair(img: ArrayLike, truth: ArrayLike) -> tuple[Array, Array]:
    a = np.asarray(img, dtype=float)
    b = np.asarray(truth, dtype=float)
    if a.shape != b.shape or a.ndim not in (2, 3):
        raise WaiInputError(
            f"image_metrics: images must share a (H, W) or (H, W, C) shape, got {a.shape} and "
            f"{b.shape}"
        )
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise WaiInputError("image_metrics: an image holds NaN or inf")
    return np.clip(a, 0.0, 1.0), np.clip(b, 0.0, 1.0)


def psnr_db(mse: float) -> float:
    """Peak signal-to-noise ratio for [0, 1] images (eq. 46 with ``max(I) = 1``), dB."""
    return float("inf") if mse == 0 else float(10.0 * np.log10(1.0 / mse))


def image_metrics(
    img: ArrayLike, truth: ArrayLike, mask: ArrayLike | None = None, win_size: int = 7
) -> dict:
    """MSE, PSNR and SSIM (eq. 45-47) of an image against the truth, inside a mask.

    Both images are clipped to [0, 1]; MSE is on that scale (see the module docstring).
    SSIM is scikit-image's (uniform ``win_size`` window, K1 = 0.01, K2 = 0.03, ``data_range``
    1; the squares on ``c1``, ``c2`` that eq. 47 drops are restored), computed as a full map,
    averaged over channels, and then averaged over the mask eroded by the window, so that no
    window that touches a pixel outside the mask counts.

    Parameters
    ----------
    img, truth : (H, W) or (H, W, C) array_like
        Image and ground truth, nominally in [0, 1].
    mask : (H, W) array_like of bool, optional
        Pixels to score (e.g. ``Restoration.valid``); all by default.
    win_size : int
        Odd SSIM window side, pixels.

    Returns
    -------
    dict
        ``mse``, ``psnr_db``, ``ssim`` (NaN if the eroded mask is empty), ``n_pixels`` (in the
        mask) and ``n_ssim_pixels`` (in the eroded mask).
    """
    a, b = _as_unit_pair(img, truth)
    m = np.ones(a.shape[:2], dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if m.shape != a.shape[:2]:
        raise WaiInputError(f"image_metrics: mask shape {m.shape} is not the image's {a.shape[:2]}")
    if not m.any():
        raise WaiInputError("image_metrics: the mask selects no pixel")
    if win_size < 3 or win_size % 2 == 0 or win_size > min(a.shape[:2]):
        raise WaiInputError("image_metrics: win_size must be odd, >= 3 and fit the image")
    mse = float(np.mean((a[m] - b[m]) ** 2))
    smap = structural_similarity(
        a,
        b,
        win_size=win_size,
        data_range=1.0,
        full=True,
        channel_axis=-1 if a.ndim == 3 else None,
    )[1]
    if smap.ndim == 3:
        smap = smap.mean(axis=-1)
    inner = binary_erosion(m, np.ones((win_size, win_size), bool), border_value=0)
    ssim = float(smap[inner].mean()) if inner.any() else float("nan")
    return {
        "mse": mse,
        "psnr_db": psnr_db(mse),
        "ssim": ssim,
        "n_pixels": int(m.sum()),
        "n_ssim_pixels": int(inner.sum()),
    }


# --------------------------------------------------------------------------------------------
# Checkerboard corners (Fig. 15)
# --------------------------------------------------------------------------------------------


def _camera_v(cfg: SystemConfig) -> PinholeCamera | PortCamera:
    """Camera v as the restoration models it (:meth:`wai_core.rig.Rig.camera_model`)."""
    if cfg.camera_v is None:
        raise WaiInputError("config: missing section [camera_v]")
    return cfg.rig.camera_model("camera_v")


def object_plane_center(cfg: SystemConfig) -> Array:
    """Centre of the object plane, mm, ``lab``: where camera v's optical axis, refracted by flat
    water at ``h0``, meets the plane ``z = z_a``.

    The rule lives in :func:`wai_core.layout.object_plane_center`, which the renderer uses to
    place the textured rectangle; this wrapper only turns its failure into a WaiInputError.

    Returns
    -------
    (3,) ndarray
    """
    _camera_v(cfg)
    try:
        center = cfg.rig.object_center_mm
    except ValueError as exc:
        raise WaiInputError(f"config: {exc}") from None
    if not np.all(np.isfinite(center)):
        raise WaiInputError("config: camera v's optical axis does not reach the object plane")
    return center


def checkerboard_corners_lab(cfg: SystemConfig) -> Array:
    """Inner corners of the checkerboard on the object plane, mm, ``lab``.

    The board is ``cfg.object.size_mm`` (along x, y) with ``cfg.object.squares`` squares along
    x and y, edges parallel to the lab axes, centred at :func:`object_plane_center`.

    Returns
    -------
    (ny - 1, nx - 1, 3) ndarray
        Corner ``[j, i]`` lies ``i + 1`` squares from the board's low-x edge and ``j + 1`` from
        its low-y edge.
    """
    nx, ny = cfg.object.squares
    if nx < 2 or ny < 2:
        raise WaiInputError("config: [object].squares needs at least 2 squares along x and y")
    sx, sy = cfg.object.size_mm
    c = cfg.rig.object_center_mm
    xs = c[0] - sx / 2 + sx / nx * np.arange(1, nx)
    ys = c[1] - sy / 2 + sy / ny * np.arange(1, ny)
    xx, yy = np.meshgrid(xs, ys)
    return np.stack([xx, yy, np.full(xx.shape, c[2])], axis=-1)


def _gray(img: ArrayLike) -> NDArray[np.float32]:
    a = np.asarray(img, dtype=np.float32)
    if a.ndim == 3:
        a = a.mean(axis=-1)
    if a.ndim != 2:
        raise WaiInputError(f"refine_corners: image must be (H, W) or (H, W, C), got {a.shape}")
    return np.ascontiguousarray(np.nan_to_num(a))


def _ring_transitions(gray: NDArray[np.float32], px: Array, radius: float) -> tuple[Array, Array]:
    """Light/dark changes around circles at ``px`` (K, 2), and the contrast on each circle.

    A checkerboard corner (a saddle) has four: two light and two dark sectors. Samples within
    20 % of the contrast from the mid level are ignored so noise does not add changes.
    """
    ang = np.linspace(0.0, 2 * np.pi, 32, endpoint=False)
    mx = (px[:, :1] + radius * np.cos(ang)).astype(np.float32)
    my = (px[:, 1:] + radius * np.sin(ang)).astype(np.float32)
    ring = cv2.remap(gray, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    lo, hi = ring.min(axis=1, keepdims=True), ring.max(axis=1, keepdims=True)
    mid, band = 0.5 * (lo + hi), 0.2 * (hi - lo)
    label = np.where(ring > mid + band, 1, np.where(ring < mid - band, -1, 0))
    # Fill ignored samples with the previous label, around the circle.
    pos = np.where(label != 0, np.arange(ang.size), -1)
    last = pos.max(axis=1, keepdims=True)
    filled = np.maximum.accumulate(pos, axis=1)
    filled = np.where(filled < 0, last, filled)
    lab = np.take_along_axis(label, np.maximum(filled, 0), axis=1)
    changes = np.sum(lab != np.roll(lab, 1, axis=1), axis=1)
    return changes, (hi - lo)[:, 0]


def refine_corners(
    img: ArrayLike, init_px: ArrayLike, win: int = 5, min_contrast: float = 0.1
) -> tuple[Array, BoolArray]:
    """Sub-pixel checkerboard corners near initial guesses (``cv2.cornerSubPix``).

    Parameters
    ----------
    img : (H, W) or (H, W, C) array_like
        Image in [0, 1]; colour is averaged to gray.
    init_px : (K, 2) array_like
        Initial ``(col, row)`` guesses, pixels; NaN rows are skipped.
    win : int
        Half side of the search window, pixels (cornerSubPix's ``winSize``); keep it below
        half a square's side in the image.
    min_contrast : float
        Smallest light-dark difference around a corner, in image units.

    Returns
    -------
    px : (K, 2) ndarray
        Refined corners; NaN where rejected.
    ok : (K,) ndarray of bool
        False where the guess is NaN or within ``win + 1`` px of the border, the corner moved
        more than ``win``, or the refined point is not a saddle (four light/dark sectors of at
        least ``min_contrast`` on a circle of radius ``max(2, win / 2)`` around it: flat
        regions and straight edges fail).
    """
    if isinstance(win, bool) or int(win) != win or win < 1:
        raise WaiInputError(f"refine_corners: win must be a positive integer, got {win!r}")
    win = int(win)
    gray = _gray(img)
    init = np.asarray(init_px, dtype=float)
    if init.ndim != 2 or init.shape[1] != 2:
        raise WaiInputError(f"refine_corners: init_px must have shape (K, 2), got {init.shape}")
    h, w = gray.shape
    m = win + 1
    ok = np.all(np.isfinite(init), axis=1)
    ok &= (
        (init[:, 0] >= m)
        & (init[:, 1] >= m)
        & (init[:, 0] <= w - 1 - m)
        & (init[:, 1] <= h - 1 - m)
    )
    px = np.full(init.shape, np.nan)
    sel = np.flatnonzero(ok)
    if not sel.size:
        return px, ok
    pts = init[sel].astype(np.float32).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
    found = cv2.cornerSubPix(gray, pts, (win, win), (-1, -1), crit).reshape(-1, 2).astype(float)
    changes, contrast = _ring_transitions(gray, found, max(2.0, win / 2.0))
    good = (np.linalg.norm(found - init[sel], axis=1) <= win) & (changes == 4)
    good &= contrast >= min_contrast
    ok[sel] = good
    px[sel[good]] = found[good]
    return px, ok


def corner_offsets(
    px: ArrayLike, ok: ArrayLike, ref_px: ArrayLike, ref_ok: ArrayLike
) -> tuple[Array, BoolArray]:
    """Offsets of corners from reference corners, where both were found.

    Returns
    -------
    offsets : (K, 2) ndarray
        ``px - ref_px``, pixels; NaN where not used.
    used : (K,) ndarray of bool
    """
    p = np.asarray(px, dtype=float).reshape(-1, 2)
    r = np.asarray(ref_px, dtype=float).reshape(-1, 2)
    if p.shape != r.shape:
        raise WaiInputError(f"corner_offsets: {p.shape[0]} corners against {r.shape[0]} references")
    used = np.asarray(ok, bool).ravel() & np.asarray(ref_ok, bool).ravel()
    used &= np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(r), axis=1)
    return np.where(used[:, None], p - r, np.nan), used


def corner_spread(offsets: ArrayLike, used: ArrayLike) -> dict:
    """The paper's Fig. 15 statistic: spread of corner positions about their true positions.

    Returns
    -------
    dict
        ``std_px`` = sqrt(mean |d - mean d|^2) (the paper's "STD"; a common shift does not
        count), ``rms_px`` = sqrt(mean |d|^2) (it does), ``mean_px`` (2,), ``n_used`` and
        ``n_lost``; the statistics are NaN when fewer than two corners are used (one corner
        has no spread: its STD would read 0).
    """
    d = np.asarray(offsets, dtype=float).reshape(-1, 2)
    u = np.asarray(used, dtype=bool).ravel()
    n = int(u.sum())
    if n < 2:
        return {
            "std_px": np.nan,
            "rms_px": np.nan,
            "mean_px": [np.nan, np.nan],
            "n_used": n,
            "n_lost": int(u.size) - n,
        }
    du = d[u]
    mean = du.mean(axis=0)
    return {
        "std_px": float(np.sqrt(np.mean(np.sum((du - mean) ** 2, axis=1)))),
        "rms_px": float(np.sqrt(np.mean(np.sum(du**2, axis=1)))),
        "mean_px": [float(mean[0]), float(mean[1])],
        "n_used": n,
        "n_lost": int(u.size - n),
    }


def predict_corners(
    cfg: SystemConfig,
    surface: Heightfield | None,
    init_px: ArrayLike | None = None,
    camera: PinholeCamera | None = None,
    margin_px: float = 0.0,
) -> tuple[Array, BoolArray]:
    """Where the checkerboard's inner corners appear in camera v through ``surface``.

    Parameters
    ----------
    cfg : SystemConfig
        Scene (water, object plane, board, camera v).
    surface : Heightfield or None
        None for the ground-truth (flat water) view; the TRUE surface to predict the distorted
        view (scoring only).
    init_px : (K, 2) array_like, optional
        Newton starts; by default the pixel of the straight line from the camera to the corner
        where it crosses the mean water level.
    camera : PinholeCamera, optional
        Replaces camera v (e.g. a smaller render of the same view).
    margin_px : float
        Corners closer than this to the image border count as out of view.

    Returns
    -------
    px : (K, 2) ndarray
        Corner pixels ``(col, row)``, K = (nx - 1)(ny - 1) in the order of
        :func:`checkerboard_corners_lab` flattened; NaN where lost.
    ok : (K,) ndarray of bool
        False where no ray reaches the corner (beyond Snell's window, off the surface) or it
        falls outside the image.
    """
    cam = _camera_v(cfg) if camera is None else camera
    corners = checkerboard_corners_lab(cfg).reshape(-1, 3)
    if init_px is None:
        o = cam.pose.center_lab_mm
        frac = (cfg.water.h0_mm - o[2]) / (corners[:, 2] - o[2])
        cols, rows, _ = cam.project(o + frac[:, None] * (corners - o))
        init_px = np.stack([cols, rows], axis=-1)
    px, ok = find_pixels(
        cam, surface, cfg.water.h0_mm, cfg.water.n_water, cfg.object_z_mm, corners, init_px
    )
    ok &= cam.in_image(px[:, 0], px[:, 1], margin_px)
    px[~ok] = np.nan
    return px, ok


CORNER_REF_FOCAL_PX = 480.0
"""Focal length, px, of the camera v the corner statistics were tuned on (the paper's: 3 mm
over 6.25 um pixels, 800 x 600): corner windows scale with a camera's focal length over this,
and :func:`angular_px` expresses offsets in its pixels."""

_CORNER_WIN_REF_PX = 5
"""cornerSubPix half window at :data:`CORNER_REF_FOCAL_PX`, px (about 0.6 degrees)."""


def corner_window_px(camera: PinholeCamera) -> int:
    """Half window of the corner detector for ``camera``, px: 5 px at the paper's 800 x 600
    camera v (:data:`CORNER_REF_FOCAL_PX`), the same angle for any other, at least 2 px."""
    return max(int(round(_CORNER_WIN_REF_PX * camera.focal_px / CORNER_REF_FOCAL_PX)), 2)


def angular_px(value_px: float | None, camera: PinholeCamera) -> float | None:
    """A length in ``camera``'s pixels as pixels of the reference camera v (focal length
    :data:`CORNER_REF_FOCAL_PX`): the same angle, so that cameras of any resolution compare
    (at the paper's 5 mm sensor width, ``value_px x 800 / width_px``)."""
    if value_px is None:
        return None
    return float(value_px) * CORNER_REF_FOCAL_PX / float(camera.focal_px)


def _window_valid(valid: BoolArray, px: Array, win: int) -> BoolArray:
    """True where the (2 win + 1)^2 window around each corner is valid."""
    inner = binary_erosion(valid, np.ones((2 * win + 1, 2 * win + 1), bool), border_value=0)
    c = np.rint(np.nan_to_num(px, nan=-1.0)).astype(int)
    inside = (
        (c[:, 0] >= 0) & (c[:, 1] >= 0) & (c[:, 0] < valid.shape[1]) & (c[:, 1] < valid.shape[0])
    )
    out = np.zeros(px.shape[0], dtype=bool)
    out[inside] = inner[c[inside, 1], c[inside, 0]]
    return out


def score_corners(
    cfg: SystemConfig,
    truth_img: ArrayLike,
    distorted_img: ArrayLike,
    restored_img: ArrayLike,
    true_surface: Heightfield,
    restored_valid: ArrayLike | None = None,
    win: int | None = None,
    camera: PinholeCamera | None = None,
) -> dict:
    """Fig. 15: checkerboard corners in the truth, distorted and restored views.

    Corners are found with :func:`refine_corners` from predicted positions: truth view, the
    flat-water prediction; distorted view, the prediction through the TRUE surface (scoring may
    read the truth); restored view, the truth view's corners. Offsets are taken from the corners
    found in the truth image, so the detector's own bias cancels. Corners beyond Snell's window,
    out of view, not found, or (restored view) near an invalid pixel are lost, never averaged.

    ``win`` is :func:`refine_corners`'s half window, px; by default :func:`corner_window_px`
    of the camera (5 px at 800 x 600, 10 px at 1600 x 1200: the same angle, so a finer camera
    is measured over the same part of the board). Offsets stay in the camera's own pixels
    (:func:`angular_px` converts them).

    Returns
    -------
    dict
        ``truth``: ``n_predicted``, ``n_found`` and ``detector`` (the :func:`corner_spread` of
        found minus predicted truth corners); ``distorted`` and ``restored``:
        :func:`corner_spread` against the truth corners; ``points_px``: (K, 2) arrays per view
        (NaN where lost) for a scatter plot.
    """
    if win is None:
        win = corner_window_px(_camera_v(cfg) if camera is None else camera)
    margin = win + 1
    pred, pred_ok = predict_corners(cfg, None, camera=camera, margin_px=margin)
    truth_px, truth_ok = refine_corners(truth_img, pred, win)
    dist_pred, dist_pred_ok = predict_corners(
        cfg, true_surface, init_px=pred, camera=camera, margin_px=margin
    )
    dist_px, dist_ok = refine_corners(distorted_img, dist_pred, win)
    rest_px, rest_ok = refine_corners(restored_img, truth_px, win)
    if restored_valid is not None:
        rest_ok &= _window_valid(np.asarray(restored_valid, bool), rest_px, win)
        rest_px[~rest_ok] = np.nan
    k = pred.shape[0]
    return {
        "truth": {
            "n_corners": k,
            "n_predicted": int(pred_ok.sum()),
            "n_found": int(truth_ok.sum()),
            "detector": corner_spread(*corner_offsets(truth_px, truth_ok, pred, pred_ok)),
        },
        "distorted": corner_spread(
            *corner_offsets(dist_px, dist_ok & dist_pred_ok, truth_px, truth_ok)
        ),
        "restored": corner_spread(*corner_offsets(rest_px, rest_ok, truth_px, truth_ok)),
        "points_px": {"truth": truth_px, "distorted": dist_px, "restored": rest_px},
    }
