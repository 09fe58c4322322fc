"""Figures of the paper's kind, drawn from render and restore folders (matplotlib, Agg)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from restoration.figures import (  # noqa: F401  (re-exported for the experiments)
    corner_scatter_figure,
    error_map_figure,
    plt,
    profile_figure,
    save_figure,
    side_by_side,
)
from wai_core.config import SystemConfig
from wai_core.heightfield import Heightfield
from wai_core.io import to_srgb8
from wai_core.report import write_report


def footprint_outline(cfg: SystemConfig) -> NDArray:
    """The outline (K, 2) mm, closed, of the flat water camera s's spots come from: the convex
    hull of the dots' flat-water hits it sees (where the structured light measures)."""
    from scipy.spatial import ConvexHull

    from wai_core.layout import flat_pattern_hits

    q, _, seen = flat_pattern_hits(cfg)
    pts = q[seen][:, :2]
    hull = pts[ConvexHull(pts).vertices]
    return np.vstack([hull, hull[:1]])


def surface_figure(surface: Heightfield, h0_mm: float, title: str, path: str | Path,
                   footprint_mm: NDArray | None = None) -> None:
    """3-D view and height map of a surface (as the paper's Fig. 10), heights relative to h0;
    ``footprint_mm`` (K, 2), when given, outlined on the map (camera s's view of the water,
    :func:`footprint_outline`)."""
    fig = plt.figure(figsize=(12, 4.8))
    # The 3-D axes get the wider share and padded labels: in a tight layout their z label
    # otherwise lands on the height map's y label.
    grid = fig.add_gridspec(1, 2, width_ratios=(1.15, 1.0), wspace=0.3)
    ax = fig.add_subplot(grid[0, 0], projection="3d")
    step = max(1, surface.x.size // 120)
    xx, yy = np.meshgrid(surface.x[::step], surface.y[::step])
    eta = surface.z[::step, ::step] - h0_mm
    ax.plot_surface(xx, yy, eta, cmap="viridis", linewidth=0, antialiased=True)
    ax.set_xlabel("x (mm)", labelpad=8)
    ax.set_ylabel("y (mm)", labelpad=8)
    ax.set_zlabel("η (mm)", labelpad=4)
    ax.set_box_aspect(None, zoom=0.85)
    ax2 = fig.add_subplot(grid[0, 1])
    im = ax2.pcolormesh(surface.x, surface.y, surface.z - h0_mm, cmap="viridis", shading="auto")
    ax2.set_aspect("equal")
    ax2.set_xlabel("x (mm)")
    ax2.set_ylabel("y (mm)")
    fig.colorbar(im, ax=ax2, label="η = z − h0 (mm)")
    if footprint_mm is not None:
        ax2.plot(footprint_mm[:, 0], footprint_mm[:, 1], "w--", lw=1.3,
                 label="measured by the structured light (camera s's spots)")
        ax2.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), fontsize=8, frameon=False)
    fig.suptitle(title)
    save_figure(fig, path)


def deflection_figure(curves: dict[str, tuple[NDArray, NDArray]], path: str | Path) -> None:
    """Deflection ψ of the reflected ray against the surface inclination θ (the paper's Fig. 8)."""
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    # Curves can coincide (both meridional ones have slope 2): the first drawn is broad and
    # pale, each later one narrower, dashed and marked, so every curve stays visible.
    styles = [
        {"lw": 5.0, "alpha": 0.45, "ls": "-"},
        {"lw": 2.0, "ls": "--", "marker": "o", "markevery": 20, "ms": 4},
        {"lw": 1.5, "ls": "-.", "marker": "s", "markevery": (10, 20), "ms": 4},
        {"lw": 1.2, "ls": ":", "marker": "^", "markevery": (5, 20), "ms": 4},
    ]
    meridional = sorted(curves, key=lambda label: "meridional" not in label)
    for k, label in enumerate(meridional):
        theta_deg, psi_deg = curves[label]
        ax.plot(theta_deg, psi_deg, label=label, zorder=2 + k, **styles[k % len(styles)])
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


def render_overview(render_dir: Path, cfg: SystemConfig, view_gain: float) -> None:
    """Fig. 10 (the simulated surface), flat-vs-wavy pattern and view, and the rig's diagram,
    into ``render_dir``."""
    from wai_core.heightfield import load_heightfield
    from wai_core.io import read_exr

    waves = cfg.waves
    surface = load_heightfield(render_dir / "heightfield.npz")
    surface_figure(
        surface,
        cfg.water.h0_mm,
        f"Simulated sea surface (U = {waves.wind_speed_m_s} m/s, t = {waves.time_s} s, "
        f"seed {waves.seed}), as the paper's Fig. 10",
        render_dir / "fig10_surface.png",
        footprint_outline(cfg),
    )
    img = {n: read_exr(render_dir / f"{n}.exr") for n in ("pattern_flat", "pattern")}
    side_by_side(
        [img["pattern_flat"], img["pattern"]],
        ["pattern, flat water (reference)", "pattern, wavy water"],
        render_dir / "pattern_flat_vs_wavy.png",
        [None, None],
    )
    views = {n: read_exr(render_dir / f"{n}.exr") for n in ("view_truth", "view")}
    side_by_side(
        [views["view_truth"], views["view"]],
        ["view, flat water (ground truth)", "view, wavy water"],
        render_dir / "view_flat_vs_wavy.png",
        [1 / view_gain, 1 / view_gain],
    )
    rig_figure(cfg, render_dir / "rig.png")
    write_report(render_dir)  # the folder's index.html, with these figures


def rig_figure(cfg: SystemConfig, path: str | Path, rays: int = 5) -> None:
    """The rig's two systems in its x-z plane (y = 0), drawn from the configuration: the
    projector's dots reflected by flat water onto the diffuser that camera s images (system
    S), and camera v's rays refracted up to the object (system V), with each device's
    centre, axis and field of view. Lengths in mm, z up."""
    from wai_core.geometry import intersect_plane_z, refract
    from wai_core.layout import flat_pattern_hits

    rig = cfg.rig
    h0, zd = cfg.water.h0_mm, cfg.diffuser.z_mm
    fig, ax = plt.subplots(figsize=(10, 5.6))
    q, s_hit, seen = flat_pattern_hits(cfg)
    # Dots near the plane y = 0 (within an eighth of the seen pattern's half width).
    chosen = np.flatnonzero(seen & (np.abs(q[:, 1]) <= np.abs(q[seen, 1]).max() / 8))
    chosen = chosen[np.linspace(0, len(chosen) - 1, min(rays, len(chosen))).astype(int)]
    p_c = rig.projector.pose.center_lab_mm
    s_c = rig.camera_s.pose.center_lab_mm
    for k in chosen:
        ax.plot([p_c[0], q[k, 0], s_hit[k, 0]], [p_c[2], q[k, 2], s_hit[k, 2]], "-",
                color="tab:cyan", lw=0.9)
        ax.plot([s_hit[k, 0], s_c[0]], [s_hit[k, 2], s_c[2]], ":", color="tab:cyan", lw=0.9)
    cam_v = rig.camera_v
    cols = np.linspace(0, cam_v.width_px - 1, rays)
    o, d = cam_v.pixel_rays(cols, np.full(rays, (cam_v.height_px - 1) / 2.0))
    o = np.broadcast_to(o, d.shape)
    w, _ = intersect_plane_z(o, d, h0)
    up, tir = refract(d, np.array([0.0, 0.0, 1.0]), cfg.water.n_water)
    ok = ~tir
    z_obj = rig.object_center_mm[2]
    top, _ = intersect_plane_z(w, up, z_obj)
    for i in np.flatnonzero(ok):
        ax.plot([o[i, 0], w[i, 0], top[i, 0]], [o[i, 2], w[i, 2], top[i, 2]], "-",
                color="tab:orange", lw=0.9)
    span = np.array([min(p_c[0], s_c[0], o[:, 0].min(), rig.diffuser_rect[0][0]) - 60,
                     max(s_c[0], o[:, 0].max(), rig.diffuser_rect[0][1]) + 60])
    ax.axhline(h0, color="tab:blue", lw=1.5)
    ax.text(span[0] + 5, h0 + 6, f"mean water level h0 = {h0:g} mm", color="tab:blue",
            fontsize=8)
    rect = rig.diffuser_rect
    ax.plot(rect[0], [zd, zd], color="0.3", lw=4, solid_capstyle="butt")
    ax.text(rect[0][1] + 6, zd - 4, f"diffuser\nz = {zd:g} mm", fontsize=8, color="0.3",
            va="center")
    top_z = h0 + 140
    ax.text(span[0] + 5, top_z - 18, f"to the object (the checkerboard), "
            f"{z_obj - h0:g} mm above the water", fontsize=8, color="tab:orange")
    for name, color in (("projector", "tab:cyan"), ("camera_s", "tab:cyan"),
                        ("camera_v", "tab:orange")):
        dev = rig.device(name)
        c, axis = dev.pose.center_lab_mm, dev.pose.axis_lab
        ax.plot(c[0], c[2], "s", color=color, ms=9, mec="k", zorder=3)
        ax.annotate("", xy=(c[0] + 40 * axis[0], c[2] + 40 * axis[2]), xytext=(c[0], c[2]),
                    arrowprops={"arrowstyle": "->", "color": "k"})
        ax.text(c[0], c[2] - 24, name.replace("_", " "), fontsize=9, ha="center")
    ax.set_xlim(*span)
    ax.set_ylim(min(p_c[2], s_c[2], o[:, 2].min()) - 40, top_z)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_title("The rig in its x-z plane: system S (cyan: projector -> water -> diffuser, "
                 "seen by camera s) and\nsystem V (orange: camera v's rays refracted up to the "
                 "object), from the configuration", fontsize=9)
    save_figure(fig, path)
