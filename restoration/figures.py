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
    "corner_scatter_figure",
    "error_map_figure",
    "plt",
    "profile_figure",
    "save_figure",
    "side_by_side",
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
