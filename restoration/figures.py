"""Figures of a restoration: the views side by side, surface error, profile, corners.

Matplotlib with the Agg backend (no display needed); each figure is written atomically.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from numpy.typing import NDArray  # noqa: E402

from wai_core.heightfield import Heightfield  # noqa: E402
from wai_core.io import to_srgb8  # noqa: E402

__all__ = [
    "ERROR_SCALE_PERCENTILE",
    "as_rgb8",
    "calibration_figure",
    "confidence_figure",
    "corner_scatter_figure",
    "crop_box",
    "draw_corners",
    "draw_error_map",
    "draw_profile",
    "flat_reference_figure",
    "error_map_figure",
    "mark_not_restored",
    "plt",
    "profile_figure",
    "robust_limit",
    "save_figure",
    "side_by_side",
    "views_figure",
    "zoom_box",
]


def save_figure(fig: plt.Figure, path: str | Path) -> None:
    """Write ``fig`` to ``path`` through a temporary file and a rename, and close it."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fig.savefig(tmp, dpi=120, bbox_inches="tight")
    plt.close(fig)
    os.replace(tmp, path)


def zoom_box(image: NDArray, fraction: float = 0.2) -> tuple[slice, slice]:
    """Rows and columns (a box ``fraction`` of the image's size) centred on the image's
    light: where a detail is worth a closer look."""
    lum = np.asarray(image, float)
    lum = lum.sum(axis=2) if lum.ndim == 3 else lum
    h, w = lum.shape
    total = lum.sum()
    if total > 0:
        cy = float((lum.sum(axis=1) * np.arange(h)).sum() / total)
        cx = float((lum.sum(axis=0) * np.arange(w)).sum() / total)
    else:
        cy, cx = h / 2.0, w / 2.0
    bh, bw = max(int(h * fraction), 8), max(int(w * fraction), 8)
    r0 = int(np.clip(cy - bh / 2, 0, h - bh))
    c0 = int(np.clip(cx - bw / 2, 0, w - bw))
    return slice(r0, r0 + bh), slice(c0, c0 + bw)


def side_by_side(
    images: list[NDArray], titles: list[str], path: str | Path, exposures: list[float | None],
    zoom: float | None = 0.2,
) -> None:
    """Linear images next to each other with titles, tone-mapped for display; with ``zoom``, a
    second row shows the same box of each (``zoom`` of the image's size, centred on the first
    image's light, :func:`zoom_box`), outlined in the first row."""
    from matplotlib.patches import Rectangle

    rows = 2 if zoom else 1
    fig, axes = plt.subplots(rows, len(images), figsize=(5 * len(images), 4 * rows),
                             squeeze=False)
    box = zoom_box(images[0], zoom) if zoom else None
    panels = zip(axes[0], images, titles, exposures, strict=True)
    for k, (ax, img, title, exposure) in enumerate(panels):
        shown = to_srgb8(img, exposure)
        ax.imshow(shown)
        ax.set_title(title)
        ax.set_axis_off()
        if box is not None:
            r, c = box
            ax.add_patch(Rectangle((c.start, r.start), c.stop - c.start, r.stop - r.start,
                                   fill=False, edgecolor="tab:orange", lw=1.5))
            axes[1, k].imshow(shown[r, c], interpolation="nearest")
            axes[1, k].set_title(f"the outlined box, {1 / zoom:.0f}x", fontsize=9)
            axes[1, k].set_axis_off()
    save_figure(fig, path)


ERROR_SCALE_PERCENTILE = 99.0
"""The error map's colour scale ends at this percentile of the errors (the few larger ones,
at the surface's edge, saturate) so that one outlier cannot darken the whole map."""


def robust_limit(values: NDArray, percentile: float = ERROR_SCALE_PERCENTILE) -> float:
    """The colour scale's end for ``values``: their ``percentile`` over the finite ones (1 when
    there are none or it is 0)."""
    v = np.abs(np.asarray(values, float))
    v = v[np.isfinite(v)]
    top = float(np.percentile(v, percentile)) if v.size else 0.0
    return top if top > 0 else 1.0


def draw_error_map(est: Heightfield, error_mm: NDArray) -> plt.Figure:
    """The error map's figure (:func:`error_map_figure`), not yet saved."""
    err = np.abs(np.asarray(error_mm, float))
    finite = err[np.isfinite(err)]
    rmse = float(np.sqrt(np.mean(finite**2))) if finite.size else float("nan")
    top = robust_limit(err)
    fig, ax = plt.subplots(figsize=(6.4, 5))
    im = ax.pcolormesh(est.x, est.y, err, cmap="magma", shading="auto", vmin=0.0, vmax=top)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    fig.colorbar(im, ax=ax, extend="max" if finite.size and finite.max() > top else "neither",
                 label=f"|z_est − z_true| (mm); scale ends at the {ERROR_SCALE_PERCENTILE:g}th "
                 "percentile")
    peak = f"{finite.max():.3f}" if finite.size else "nan"
    ax.set_title(f"Surface error: RMSE {rmse:.3f} mm, max {peak} mm", fontsize=10)
    return fig


def error_map_figure(est: Heightfield, error_mm: NDArray, path: str | Path) -> None:
    """Absolute height error over the reconstructed region (as the paper's Fig. 12), its RMSE
    and maximum in the title, the colour scale robust to outliers (:func:`robust_limit`)."""
    save_figure(draw_error_map(est, error_mm), path)


def draw_profile(x_mm: NDArray, est_mm: NDArray, true_mm: NDArray, y_mm: float) -> plt.Figure:
    """The profile's figure (:func:`profile_figure`), not yet saved."""
    fig, (ax, res) = plt.subplots(2, 1, figsize=(7.5, 5), sharex=True,
                                  gridspec_kw={"height_ratios": [2.2, 1]})
    ax.plot(x_mm, true_mm, "-", color="0.35", lw=2.2, label="ground truth")
    ax.plot(x_mm, est_mm, "--", color="tab:blue", lw=1.4, label="reconstructed")
    covered = np.isfinite(est_mm)
    if covered.any() and not covered.all():
        lo, hi = x_mm[covered].min(), x_mm[covered].max()
        for a in (ax, res):
            a.axvspan(x_mm.min(), lo, color="0.92", zorder=0)
            a.axvspan(hi, x_mm.max(), color="0.92", zorder=0)
        ax.text(0.99, 0.03, "grey: outside the estimate (beyond the spots camera s sees)",
                transform=ax.transAxes, ha="right", va="bottom", fontsize=8, color="0.3")
    ax.set_ylabel("z (mm)")
    ax.set_title(f"Surface profile at y = {y_mm:.0f} mm", fontsize=10)
    ax.legend(fontsize=8, loc="upper left")
    diff = est_mm - true_mm
    res.plot(x_mm, diff, "-", color="tab:red", lw=1.0)
    res.axhline(0.0, color="0.5", lw=0.8)
    known = diff[np.isfinite(diff)]
    if known.size:
        res.set_title(f"residual: RMS {np.sqrt(np.mean(known**2)):.3f} mm", fontsize=9)
    res.set_xlabel("x (mm)")
    res.set_ylabel("est − true (mm)")
    fig.tight_layout()
    return fig


def profile_figure(
    x_mm: NDArray, est_mm: NDArray, true_mm: NDArray, y_mm: float, path: str | Path
) -> None:
    """True and reconstructed heights along one line (as the paper's Fig. 11f) and their
    difference below, the part outside the estimate shaded."""
    save_figure(draw_profile(x_mm, est_mm, true_mm, y_mm), path)


CORNER_STYLE = {
    "truth": {"facecolors": "none", "edgecolors": "0.2", "marker": "o", "s": 70, "zorder": 1,
              "linewidths": 1.0},
    "distorted": {"c": "tab:orange", "marker": "x", "s": 22, "zorder": 2, "alpha": 0.8},
    "restored": {"c": "tab:blue", "marker": "+", "s": 60, "zorder": 3, "linewidths": 1.4},
}
"""Truth as hollow rings under the restored crosses (drawn last, on top), so a restored corner
on its true place shows as a cross in a ring."""


def draw_corners(points_px: dict[str, NDArray], stds: dict[str, float]) -> plt.Figure:
    """The corners' figure (:func:`corner_scatter_figure`), not yet saved."""
    fig, ax = plt.subplots(figsize=(7, 6.2))
    for name in ("truth", "distorted", "restored"):
        pts = points_px.get(name)
        if pts is None:
            continue
        label = name if name == "truth" else f"{name} (STD {stds[name]:.2f} px)"
        ax.scatter(pts[:, 0], pts[:, 1], label=label, **CORNER_STYLE[name])
    ax.invert_yaxis()
    ax.set_aspect("equal")
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=3, fontsize=8,
              frameon=False)
    ax.set_title("Checkerboard corners: truth (rings), distorted, restored (crosses)",
                 fontsize=10)
    return fig


def corner_scatter_figure(points_px: dict[str, NDArray], stds: dict[str, float], path) -> None:
    """Checkerboard corners in the truth, distorted and restored views (as the paper's Fig.
    15d); the truth hollow and the restored corners on top; the legend below the axes."""
    save_figure(draw_corners(points_px, stds), path)


NOT_RESTORED_GREY = (150, 110)
"""The two 8-bit greys of the stripes that mark pixels not restored: light and dark, both
distinct from the black background and from the object's own levels."""


def as_rgb8(image8: NDArray) -> NDArray:
    """An 8-bit image (H, W, 3), or grey (H, W) repeated in three channels: what the figures
    and movies draw, whether the camera was colour or grey."""
    img = np.asarray(image8)
    return np.repeat(img[..., None], 3, axis=2) if img.ndim == 2 else img


def mark_not_restored(rgb8: NDArray, valid: NDArray, period_px: int = 8) -> NDArray:
    """``rgb8`` with the pixels outside ``valid`` hatched in two greys (diagonal stripes).

    Parameters
    ----------
    rgb8 : (H, W, 3) or (H, W) ndarray of uint8
        A displayed image (grey: drawn in RGB, :func:`as_rgb8`).
    valid : (H, W) ndarray of bool
        Pixels restored (kept as they are).
    period_px : int
        The stripes' period, pixels.

    Returns
    -------
    (H, W, 3) ndarray of uint8
    """
    h, w = valid.shape
    rows, cols = np.ogrid[:h, :w]
    light, dark = NOT_RESTORED_GREY
    stripes = np.where((rows + cols) % period_px < period_px // 2, light, dark).astype(np.uint8)
    return np.where(valid[..., None], as_rgb8(rgb8), stripes[..., None])


def crop_box(mask: NDArray, margin: float = 0.04) -> tuple[slice, slice]:
    """Rows and columns of ``mask``'s bounding box, widened by ``margin`` of the image each
    side (the whole image when the mask is empty): the views drawn where the object is."""
    h, w = mask.shape
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not rows.size:
        return slice(0, h), slice(0, w)
    dr, dc = int(margin * h), int(margin * w)
    return (slice(max(rows[0] - dr, 0), min(rows[-1] + 1 + dr, h)),
            slice(max(cols[0] - dc, 0), min(cols[-1] + 1 + dc, w)))


def _luminance(img: NDArray) -> NDArray:
    a = np.asarray(img, float)
    return a.mean(axis=2) if a.ndim == 3 else a


def views_figure(
    panels: list[tuple[str, NDArray | None]], mask: NDArray, path: str | Path,
    object_fraction: float | None = None,
) -> None:
    """Views side by side, cropped to the restored region, the restored one shown only where
    it was restored (hatched grey elsewhere, :func:`mark_not_restored`), its difference from
    the truth where there is one, and the mask of restored pixels last.

    Parameters
    ----------
    panels : list of (title, (H, W, 3) or (H, W) ndarray or None)
        Linear images on the object's radiance scale (1 = white), colour or grey; None panels
        are skipped. A title may carry the scores; the truth's starts with ``truth`` and the
        restored view's with ``restored``.
    mask : (H, W) ndarray of bool
        Pixels restored.
    path : str or Path
    object_fraction : float, optional
        Of the object's pixels in the flat-water view (the truth), the fraction restored: the
        pixels the scores are computed on (``Scores.view_restored_fraction``); shown beside
        the mask's share of the whole image.
    """
    shown = [(t, im) for t, im in panels if im is not None]
    by_name = {t.split(" ")[0].rstrip(":"): im for t, im in shown}
    rows, cols = crop_box(mask)
    diff = None
    if "truth" in by_name and "restored" in by_name:
        diff = np.abs(_luminance(by_name["restored"]) - _luminance(by_name["truth"]))
        diff = np.where(mask, diff, np.nan)
    n = len(shown) + 1 + (diff is not None)
    crop = mask[rows, cols]
    aspect = crop.shape[0] / crop.shape[1]
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 4.2 * aspect + 1.0))
    for ax, (title, img) in zip(axes, shown, strict=False):
        rgb = as_rgb8(to_srgb8(img, 1.0))
        if title.startswith("restored"):
            rgb = mark_not_restored(rgb, mask)
        ax.imshow(rgb[rows, cols])
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
    if diff is not None:
        ax = axes[len(shown)]
        top = robust_limit(diff)
        im = ax.imshow(diff[rows, cols], cmap="magma", vmin=0.0, vmax=top)
        ax.set_title("|restored − truth| (restored pixels;\nscale to the 99th percentile)",
                     fontsize=9)
        ax.set_axis_off()
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
    white = np.full(mask.shape + (3,), 255, np.uint8)
    axes[-1].imshow(mark_not_restored(white, mask)[rows, cols])
    share = f"restored pixels: {mask.mean():.0%} of the image"
    if object_fraction is not None:
        share += f",\n{object_fraction:.0%} of the object's pixels (the scored ones)"
    axes[-1].set_title(share, fontsize=9)
    axes[-1].set_axis_off()
    fig.canvas.draw()  # the images' drawn boxes (equal aspect) place the note just below them
    bottom = min(ax.get_window_extent().y0 for ax in axes) / fig.bbox.height
    fig.text(0.5, bottom - 0.02, "hatched grey: not restored (no estimated surface, or no ray "
             "to the object: metrics.json's view_status_counts); white in the last panel: "
             "restored. Drawn: the restored region's box.\n"
             "The scores compare the views on the restored pixels where the flat-water view "
             "sees the object.", ha="center", va="top", fontsize=9)
    save_figure(fig, path)


def confidence_figure(
    surface: Heightfield, residual_px: NDArray, threshold_px: float, path: str | Path
) -> None:
    """Where the surface reproduces its spots: each node's nearest-sample residual, px, on a
    scale that ends at twice the frame's threshold."""
    fig, ax = plt.subplots(figsize=(6, 5))
    im = ax.pcolormesh(surface.x, surface.y, residual_px, cmap="viridis", shading="auto",
                       vmin=0.0, vmax=2.0 * threshold_px)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    fig.colorbar(im, ax=ax, label=f"spot residual (px); threshold {threshold_px:.2f} px")
    ax.set_title("Forward consistency: predicted vs detected spots")
    save_figure(fig, path)


def calibration_figure(images: list[NDArray], fit: Any, camera: str, path: str | Path,
                       shown: int = 4) -> None:
    """A camera's checkerboard calibration (as OpenCV's tutorial shows it): up to ``shown``
    views with the corners found (+) and reprojected by the fit (o), each view's RMS, and
    every corner's reprojection error as a field over the image (arrows x50).

    Parameters
    ----------
    images : list of (H, W) arrays
        The views given to :func:`~restoration.rig_calibration.calibrate_device`.
    fit : DeviceFit
    camera : str
    path : str or Path
    shown : int
    """
    n = min(shown, len(fit.views))
    fig = plt.figure(figsize=(4.2 * max(n, 2), 7.4))
    grid = fig.add_gridspec(2, max(n, 2), height_ratios=(1.0, 1.1))
    for i in range(n):
        ax = fig.add_subplot(grid[0, i])
        img = np.asarray(images[fit.views[i]], float)
        ax.imshow(img.mean(axis=2) if img.ndim == 3 else img, cmap="gray")
        c, r = fit.corners_px[i], fit.reprojected_px[i]
        ax.plot(c[:, 0], c[:, 1], "+", color="tab:red", ms=7, label="found")
        ax.plot(r[:, 0], r[:, 1], "o", mfc="none", color="tab:cyan", ms=5, label="reprojected")
        ax.set_title(f"view {fit.views[i]}: RMS {fit.view_rms_px[i]:.3f} px", fontsize=9)
        ax.set_axis_off()
        if i == 0:
            ax.legend(fontsize=7, loc="lower left")
    bars = fig.add_subplot(grid[1, 0])
    bars.bar([str(v) for v in fit.views], fit.view_rms_px, color="tab:blue")
    bars.axhline(fit.rms_px, color="0.3", lw=1, ls="--")
    bars.set_xlabel("view")
    bars.set_ylabel("reprojection RMS (px)")
    bars.set_title(f"every view (dashed: all, {fit.rms_px:.3f} px)", fontsize=9)
    field_ax = fig.add_subplot(grid[1, 1:])
    c = np.concatenate(fit.corners_px)
    e = np.concatenate(fit.reprojected_px) - c
    field_ax.quiver(c[:, 0], c[:, 1], e[:, 0], e[:, 1], np.hypot(e[:, 0], e[:, 1]),
                    angles="xy", scale_units="xy", scale=1 / 50.0, cmap="viridis", width=0.003)
    h, w = np.asarray(images[0]).shape[:2]
    field_ax.set_xlim(0, w)
    field_ax.set_ylim(h, 0)
    field_ax.set_aspect("equal")
    field_ax.set_title("reprojection error over the image (arrows x50)", fontsize=9)
    fig.suptitle(f"{camera}: fx {fit.fx_px:.2f} px, k1 {fit.distortion[0]:.4f}, RMS "
                 f"{fit.rms_px:.3f} px over {fit.n_used} views ({fit.n_rejected} without the "
                 "board)", fontsize=10)
    save_figure(fig, path)


def flat_reference_figure(reference: Any, size_px: tuple[int, int], path: str | Path,
                          scale: float = 50.0) -> None:
    """The flat-water reference against the calibration: each detected spot's residual from
    where the rig predicts it (arrows ``scale`` times their length, coloured by length) over
    camera s's image of ``size_px`` (H, W), with the RMS the status checks.

    Parameters
    ----------
    reference : ReferenceGrid
        Its ``ref_px``, ``pred_px`` and ``observed`` (:mod:`restoration.features`).
    size_px : (int, int)
    path : str or Path
    scale : float
    """
    fig, ax = plt.subplots(figsize=(7.5, 5.2))
    h, w = size_px
    if reference.pred_px is not None:
        seen = reference.observed & np.isfinite(reference.pred_px).all(axis=1)
        at = reference.pred_px[seen]
        d = reference.ref_px[seen] - at
        length = np.hypot(d[:, 0], d[:, 1])
        q = ax.quiver(at[:, 0], at[:, 1], d[:, 0], d[:, 1], length, angles="xy",
                      scale_units="xy", scale=1.0 / scale, cmap="viridis", width=0.002)
        fig.colorbar(q, ax=ax, label="detected - predicted (px)")
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_aspect("equal")
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")
    ax.set_title(f"Flat-water reference against the calibration: RMS {reference.rms_px:.3f} px "
                 f"(arrows x{scale:g})", fontsize=10)
    save_figure(fig, path)
