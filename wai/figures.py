"""Figures of the paper's kind, drawn from render and restore folders (matplotlib, Agg)."""

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


def save_figure(fig: plt.Figure, path: str | Path) -> None:
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fig.savefig(tmp, dpi=120, bbox_inches="tight")
    plt.close(fig)
    os.replace(tmp, path)


def surface_figure(surface: Heightfield, h0_mm: float, title: str, path: str | Path) -> None:
    """3-D view and height map of a surface (the paper's Fig. 10), heights relative to h0."""
    fig = plt.figure(figsize=(11, 4.2))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    step = max(1, surface.x.size // 120)
    xx, yy = np.meshgrid(surface.x[::step], surface.y[::step])
    eta = surface.z[::step, ::step] - h0_mm
    ax.plot_surface(xx, yy, eta, cmap="viridis", linewidth=0, antialiased=True)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("η (mm)")
    ax2 = fig.add_subplot(1, 2, 2)
    im = ax2.pcolormesh(surface.x, surface.y, surface.z - h0_mm, cmap="viridis", shading="auto")
    ax2.set_aspect("equal")
    ax2.set_xlabel("x (mm)")
    ax2.set_ylabel("y (mm)")
    fig.colorbar(im, ax=ax2, label="η = z − h0 (mm)")
    fig.suptitle(title)
    save_figure(fig, path)


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


def deflection_figure(curves: dict[str, tuple[NDArray, NDArray]], path: str | Path) -> None:
    """Deflection ψ of the reflected ray against the surface inclination θ (the paper's Fig. 8)."""
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for label, (theta_deg, psi_deg) in curves.items():
        ax.plot(theta_deg, psi_deg, label=label)
    ax.set_xlabel("surface inclination θ (deg)")
    ax.set_ylabel("deflection ψ of the reflected ray (deg)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    save_figure(fig, path)


def features_figure(
    images: list[NDArray], points: list[NDArray], titles: list[str], path: str | Path
) -> None:
    """Pattern images with their detected features marked (the paper's Fig. 11c-d)."""
    fig, axes = plt.subplots(1, len(images), figsize=(6 * len(images), 4.5))
    for ax, img, pts, title in zip(np.atleast_1d(axes), images, points, titles, strict=True):
        ax.imshow(to_srgb8(img))
        ax.plot(pts[:, 0], pts[:, 1], "r+", ms=3, mew=0.6)
        ax.set_title(title)
        ax.set_axis_off()
    save_figure(fig, path)


def surfaces_figure(est: Heightfield, truth: Heightfield, h0_mm: float, path: str | Path) -> None:
    """Recovered and true surface over the reconstructed region (the paper's Fig. 11e-f)."""
    xx, yy = np.meshgrid(est.x, est.y)
    true_z = np.where(np.isfinite(est.z), truth.height(xx, yy), np.nan)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    vmin = np.nanmin([np.nanmin(est.z), np.nanmin(true_z)]) - h0_mm
    vmax = np.nanmax([np.nanmax(est.z), np.nanmax(true_z)]) - h0_mm
    for ax, z, title in zip(axes, (est.z, true_z), ("recovered", "ground truth"), strict=True):
        im = ax.pcolormesh(est.x, est.y, z - h0_mm, vmin=vmin, vmax=vmax, shading="auto")
        ax.set_aspect("equal")
        ax.set_title(f"{title} surface")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
    fig.colorbar(im, ax=axes, label="z − h0 (mm)")
    save_figure(fig, path)


def sweep_figure(
    x: NDArray, ys: dict[str, NDArray], xlabel: str, ylabel: str, path: str | Path,
    vlines: dict[str, float] | None = None,
) -> None:
    """Several measured curves against one swept parameter, with optional predicted bounds."""
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for label, y in ys.items():
        ax.plot(x, y, "o-", label=label)
    for label, v in (vlines or {}).items():
        ax.axvline(v, color="gray", ls="--", lw=1)
        ax.annotate(label, (v, ax.get_ylim()[1]), rotation=90, va="top", ha="right", fontsize=8)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    save_figure(fig, path)
