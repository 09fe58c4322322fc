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
    "confidence_figure",
    "corner_scatter_figure",
    "error_map_figure",
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
    """Checkerboard corners in the truth, distorted and restored views (the paper's Fig. 15d)."""
    fig, ax = plt.subplots(figsize=(7, 5.5))
    style = {"truth": ("r", "o"), "distorted": ("m", "x"), "restored": ("b", "+")}
    for name, pts in points_px.items():
        color, marker = style[name]
        label = name if name == "truth" else f"{name} (STD {stds[name]:.2f} px)"
        ax.scatter(pts[:, 0], pts[:, 1], c=color, marker=marker, s=22, label=label)
    ax.invert_yaxis()
    ax.set_aspect("equal")
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")
    ax.legend(loc="best")
    ax.set_title("Checkerboard corners")
    save_figure(fig, path)


def views_figure(
    panels: list[tuple[str, NDArray | None]], mask: NDArray, path: str | Path
) -> None:
    """Views side by side, the restored one shown only where it was restored (hatched grey
    elsewhere), and the mask of restored pixels last.

    Parameters
    ----------
    panels : list of (title, (H, W, 3) ndarray or None)
        Linear images on the object's radiance scale (1 = white); None panels are skipped.
        A title may carry the scores.
    mask : (H, W) ndarray of bool
        Pixels restored.
    path : str or Path
    """
    shown = [(t, im) for t, im in panels if im is not None]
    fig, axes = plt.subplots(1, len(shown) + 1, figsize=(4.6 * (len(shown) + 1), 4))
    for ax, (title, img) in zip(axes, shown, strict=False):
        rgb = to_srgb8(img, 1.0)
        if title.startswith("restored"):
            grey = np.full_like(rgb, 96)
            rgb = np.where(mask[..., None], rgb, grey)
        ax.imshow(rgb)
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
    axes[-1].imshow(mask, cmap="gray", vmin=0, vmax=1)
    axes[-1].set_title(f"restored pixels ({mask.mean():.0%}); black: not restored", fontsize=9)
    axes[-1].set_axis_off()
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
