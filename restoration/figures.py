"""Figures of a restoration: the views side by side, surface error, profile, corners.

Matplotlib with the Agg backend (no display needed); each figure is written atomically.
"""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from numpy.typing import NDArray  # noqa: E402

from wai_core.heightfield import Heightfield  # noqa: E402
from wai_core.io import to_srgb8  # noqa: E402

__all__ = [
    "as_rgb8",
    "confidence_figure",
    "corner_scatter_figure",
    "error_map_figure",
    "mark_not_restored",
    "plt",
    "profile_figure",
    "save_figure",
    "side_by_side",
    "views_figure",
]


def save_figure(fig: plt.Figure, path: str | Path) -> None:
    """Write ``fig`` to ``path`` through a temporary file and a rename, and close it."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fig.savefig(tmp, dpi=120, bbox_inches="tight")
    plt.close(fig)
    os.replace(tmp, path)


def side_by_side(
    images: list[NDArray], titles: list[str], path: str | Path, exposures: list[float | None]
) -> None:
    """Linear images next to each other with titles, tone-mapped for display."""
    fig, axes = plt.subplots(1, len(images), figsize=(5 * len(images), 4))
    panels = zip(np.atleast_1d(axes), images, titles, exposures, strict=True)
    for ax, img, title, exposure in panels:
        ax.imshow(to_srgb8(img, exposure))
        ax.set_title(title)
        ax.set_axis_off()
    save_figure(fig, path)


def error_map_figure(est: Heightfield, error_mm: NDArray, path: str | Path) -> None:
    """Absolute height error over the reconstructed region (the paper's Fig. 12)."""
    fig, ax = plt.subplots(figsize=(6, 5))
    im = ax.pcolormesh(est.x, est.y, np.abs(error_mm), cmap="magma", shading="auto")
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    fig.colorbar(im, ax=ax, label="|z_est − z_true| (mm)")
    ax.set_title("Absolute error of the reconstructed surface")
    save_figure(fig, path)


def profile_figure(
    x_mm: NDArray, est_mm: NDArray, true_mm: NDArray, y_mm: float, path: str | Path
) -> None:
    """True and reconstructed heights along one line (the paper's Fig. 11f)."""
    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.plot(x_mm, true_mm, "r-", label="ground truth")
    ax.plot(x_mm, est_mm, "b--", label="reconstructed")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_title(f"Surface profile at y = {y_mm:.0f} mm")
    ax.legend()
    save_figure(fig, path)


def corner_scatter_figure(points_px: dict[str, NDArray], stds: dict[str, float], path) -> None:
    """Checkerboard corners in the truth, distorted and restored views (the paper's Fig. 15d);
    the legend sits below the axes, clear of the corners."""
    fig, ax = plt.subplots(figsize=(7, 6.2))
    style = {"truth": ("r", "o"), "distorted": ("m", "x"), "restored": ("b", "+")}
    for name, pts in points_px.items():
        color, marker = style[name]
        label = name if name == "truth" else f"{name} (STD {stds[name]:.2f} px)"
        ax.scatter(pts[:, 0], pts[:, 1], c=color, marker=marker, s=22, label=label)
    ax.invert_yaxis()
    ax.set_aspect("equal")
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=3, fontsize=8,
              frameon=False)
    ax.set_title("Checkerboard corners")
    save_figure(fig, path)


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


def views_figure(
    panels: list[tuple[str, NDArray | None]], mask: NDArray, path: str | Path,
    object_fraction: float | None = None,
) -> None:
    """Views side by side, the restored one shown only where it was restored (hatched grey
    elsewhere, :func:`mark_not_restored`), and the mask of restored pixels last.

    Parameters
    ----------
    panels : list of (title, (H, W, 3) or (H, W) ndarray or None)
        Linear images on the object's radiance scale (1 = white), colour or grey; None panels
        are skipped.
        A title may carry the scores.
    mask : (H, W) ndarray of bool
        Pixels restored.
    path : str or Path
    object_fraction : float, optional
        Of the object's pixels in the flat-water view (the truth), the fraction restored: the
        pixels the scores are computed on (``Scores.view_restored_fraction``); shown beside
        the mask's share of the whole image.
    """
    shown = [(t, im) for t, im in panels if im is not None]
    aspect = mask.shape[0] / mask.shape[1]
    fig, axes = plt.subplots(1, len(shown) + 1,
                             figsize=(4.6 * (len(shown) + 1), 4.6 * aspect + 0.9))
    for ax, (title, img) in zip(axes, shown, strict=False):
        rgb = as_rgb8(to_srgb8(img, 1.0))
        if title.startswith("restored"):
            rgb = mark_not_restored(rgb, mask)
        ax.imshow(rgb)
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
    white = np.full(mask.shape + (3,), 255, np.uint8)
    axes[-1].imshow(mark_not_restored(white, mask))
    share = f"restored pixels: {mask.mean():.0%} of the image"
    if object_fraction is not None:
        share += f",\n{object_fraction:.0%} of the object's pixels (the scored ones)"
    axes[-1].set_title(share, fontsize=9)
    axes[-1].set_axis_off()
    fig.canvas.draw()  # the images' drawn boxes (equal aspect) place the note just below them
    bottom = min(ax.get_window_extent().y0 for ax in axes) / fig.bbox.height
    fig.text(0.5, bottom - 0.02, "hatched grey: not restored (no estimated surface, or no ray "
             "to the object: metrics.json's view_status_counts); white in the last panel: "
             "restored.\n"
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
