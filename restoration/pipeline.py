"""The paper's method end to end on a render folder: features, normals, surface, restored view.

Reads only the images (``pattern.exr``, ``pattern_flat.exr``, ``view.exr``) and the calibration
in ``scene.json``. The true surface and view are never read here; :mod:`restoration.scoring` reads
them to score.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from restoration.anchor import find_anchor, integration_residual_mm
from restoration.features import (
    Matches,
    ReferenceGrid,
    features_from_reference,
    prepare_reference,
)
from restoration.normals import points_on_rays, projector_rays
from restoration.reverse_trace import Restoration, restore_view
from restoration.surface import SurfaceEstimate, reconstruct_surface
from wai_core.config import SystemConfig, config_from_dict
from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera
from wai_core.io import read_exr, read_json
from wai_core.pattern import dot_grid


@dataclass(frozen=True)
class RestoreOptions:
    """Choices of the restoration (defaults: the most accurate at real-time speed).

    ``integrator='paper'``, ``n_refine=0``, ``gridder='clough_tocher'`` and ``anchor='gauge'``
    is the paper's method as published (q_k on z = h0, central differences, bicubic-type
    interpolation, mean height = h0). ``anchor='integrability'`` finds the absolute height
    from the data instead (:mod:`restoration.anchor`); when the data do not pin it (standard
    error above ``anchor_max_sigma_mm``, e.g. over calm water) the gauge's h0 is used and the
    estimate says so (``SurfaceEstimate.anchor["method"] == "gauge_fallback"``).
    """

    integrator: str = "trapezoid"
    n_refine: int = 3
    gridder: str = "tangent_blend"
    grid_spacing_mm: float = 2.0
    warp_step_px: int = 8
    anchor: str = "integrability"
    anchor_max_sigma_mm: float = 1.0


@dataclass
class Calibration:
    """What the restoration knows of the system: the configuration in ``scene.json`` and, once
    prepared, the flat-water reference grid (per rig, not per frame)."""

    cfg: SystemConfig
    view_gain: float
    reference: ReferenceGrid | None = None
    last_level_mm: float | None = None
    """Mean level found from integrability in the previous frame (a video's level drifts by
    far less than the search's first step between frames): where the next search starts."""

    def prepare(self, pattern_flat: NDArray) -> ReferenceGrid:
        """Detect and label the flat-water pattern once; later frames reuse it."""
        if self.reference is None:
            self.reference = prepare_reference(pattern_flat, self.cfg)
        return self.reference

    @property
    def camera_v(self) -> PinholeCamera:
        return self.cfg.camera_v.camera()


@dataclass
class RestoreResult:
    """Everything one restoration produced (no ground truth involved)."""

    features: Matches
    surface: SurfaceEstimate
    view: Restoration
    timings_ms: dict[str, float] = field(default_factory=dict)


def load_calibration(render_dir: str | Path) -> Calibration:
    """Read ``scene.json`` of a render folder as calibration."""
    record = read_json(Path(render_dir) / "scene.json")
    if not isinstance(record, dict) or "config" not in record:
        raise WaiInputError(f"{render_dir}/scene.json holds no 'config'")
    cfg = config_from_dict(record["config"])
    gain = float(record.get("derived", {}).get("view_radiance_gain", cfg.water.n_water**2))
    return Calibration(cfg, gain)


def load_inputs(render_dir: str | Path, cal: Calibration) -> dict[str, NDArray[np.float32]]:
    """The three images the restoration may read, checked against the calibration's sizes."""
    render_dir = Path(render_dir)
    sizes = {
        "pattern": cal.cfg.camera_s,
        "pattern_flat": cal.cfg.camera_s,
        "view": cal.cfg.camera_v,
    }
    images = {}
    for name, dev in sizes.items():
        img = read_exr(render_dir / f"{name}.exr")
        if img.shape[:2] != (dev.height_px, dev.width_px):
            raise WaiInputError(
                f"{name}.exr is {img.shape[1]}x{img.shape[0]} but scene.json says "
                f"{dev.width_px}x{dev.height_px}"
            )
        images[name] = img
    return images


def panel_positions(cfg: SystemConfig, ij: NDArray) -> NDArray:
    """Projector panel ``(col, row)`` of the dots with grid indices ``ij`` (K, 2)."""
    grid_ij, panel = dot_grid(cfg.pattern, cfg.projector.camera())
    side = int(grid_ij[:, 0].max()) * 2 + 1
    half = side // 2
    index = (np.asarray(ij)[:, 1] + half) * side + (np.asarray(ij)[:, 0] + half)
    return panel[index]


ANCHORS = ("integrability", "gauge")
METHODS = ("structured-light", "alterman")
"""Surface sensing methods: this module's, and Alterman's sun sensor (restoration.alterman)."""


SEARCH_INTEGRATOR = "trapezoid"
"""Integrator of the anchor search (see :func:`estimate_surface`)."""


def estimate_surface(
    ij: NDArray,
    spot_px: NDArray,
    cfg: SystemConfig,
    options: RestoreOptions,
    start_mm: float | None = None,
) -> SurfaceEstimate:
    """Surface from matched features, anchored by the gauge's h0 or by integrability (searched
    from ``start_mm``, default h0)."""
    if options.anchor not in ANCHORS:
        raise WaiInputError(f"unknown anchor {options.anchor!r} (known: {', '.join(ANCHORS)})")
    keep = np.isfinite(spot_px).all(axis=1)
    ij, spot_px = ij[keep], spot_px[keep]
    panel = panel_positions(cfg, ij)
    projector = cfg.projector.camera()
    fixed = (ij, panel, spot_px, projector, cfg.camera_s.camera(), cfg.diffuser.z_mm)
    # Every reconstruction weighs its differences by the dots' spacing on z = h0: the anchor
    # search's reconstructions then share one factorisation.
    weight_xy = points_on_rays(*projector_rays(panel, projector), cfg.water.h0_mm)[:, :2]

    def reconstruct(anchor_mm: float, integrator: str = options.integrator) -> SurfaceEstimate:
        return reconstruct_surface(
            *fixed,
            anchor_mm,
            integrator=integrator,
            n_refine=options.n_refine,
            grid_spacing_mm=options.grid_spacing_mm,
            gridder=options.gridder,
            weight_xy_mm=weight_xy,
        )

    def probe(anchor_mm: float) -> SurfaceEstimate:
        # The level is a property of the data, not of the integrator: search it with the
        # trapezoid rule, whose fit error is the integrability residual itself (integrators
        # that resample onto a grid add their own resampling error to it).
        return reconstruct(anchor_mm, SEARCH_INTEGRATOR)

    h0 = cfg.water.h0_mm
    if options.anchor == "gauge":
        est = reconstruct(h0)
        est.anchor.update(method="gauge", anchor_mm=h0)
        return est
    search = find_anchor(probe, h0 if start_mm is None else start_mm, step_mm=3.0)
    info = {
        "searched_mm": search.anchor_mm,
        "sigma_mm": search.sigma_mm,
        "evaluations": search.evaluations,
    }
    if search.sigma_mm <= options.anchor_max_sigma_mm:
        est = search.estimate
        if options.integrator != SEARCH_INTEGRATOR:
            est = reconstruct(search.anchor_mm)
        est.anchor.update(method="integrability", anchor_mm=search.anchor_mm, **info)
    else:  # the slopes do not pin the level (calm water): trust the gauge, and say so
        est = reconstruct(h0)
        est.anchor.update(method="gauge_fallback", anchor_mm=h0, **info)
    return est


# Most label shifts tried when the pattern leaves the labels ambiguous (each costs a surface).
MAX_SHIFT_CANDIDATES = 24
# A shifted labelling must keep this fraction of the features on lit dots to be considered.
MIN_SHIFT_KEEP = 0.8


def shifted(features: Matches, shift: NDArray, keep: NDArray) -> Matches:
    """``features`` relabelled ``ij + shift``, keeping the rows ``keep``."""
    di, dj = (int(v) for v in shift)
    counts = {**features.counts, "label_shift_di": di, "label_shift_dj": dj}
    return replace(
        features,
        ij=features.ij[keep] + shift,
        ref_px=features.ref_px[keep],
        spot_px=features.spot_px[keep],
        observed=features.observed[keep],
        counts=counts,
        alt_shifts=features.alt_shifts - shift,
    )


def resolve_label_shift(
    features: Matches,
    surface: SurfaceEstimate,
    reference: ReferenceGrid,
    cfg: SystemConfig,
    options: RestoreOptions,
) -> tuple[Matches, SurfaceEstimate]:
    """Among lattice shifts that the lit/unlit evidence cannot tell apart, keep the labelling
    whose slopes integrate best.

    A labelling shifted by whole dots pairs every spot with a neighbouring projector ray: the
    normals then describe no surface, and the integration residual grows (on the paper's rig
    by 2-3x per dot of shift). ``counts`` gains ``label_shift_candidates`` (tried) and
    ``label_shift_di/dj`` (applied on top of the pattern's choice).
    """
    best = (integration_residual_mm(surface), features, surface)
    tried = 1
    for shift in features.alt_shifts[:MAX_SHIFT_CANDIDATES]:
        if not shift.any():
            continue
        keep = reference.lit_at(features.ij + shift)
        if keep.sum() < MIN_SHIFT_KEEP * len(keep):
            continue
        candidate = shifted(features, shift, keep)
        try:
            est = estimate_surface(candidate.ij, candidate.spot_px, cfg, options)
        except WaiInputError:
            continue
        tried += 1
        residual = integration_residual_mm(est)
        if residual < best[0]:
            best = (residual, candidate, est)
    _, chosen, est = best
    chosen.counts["label_shift_candidates"] = tried
    return chosen, est


def restore(
    images: dict[str, NDArray], cal: Calibration, options: RestoreOptions = RestoreOptions()
) -> RestoreResult:
    """Run the restoration on already-loaded images (the per-frame hot path).

    The flat-water reference is prepared on the first call and kept in ``cal``, and so is the
    level found, where the next frame's search starts.
    """
    cfg = cal.cfg
    reference = cal.prepare(images["pattern_flat"])
    t0 = time.perf_counter()
    features = features_from_reference(images["pattern"], reference, cfg)
    t1 = time.perf_counter()
    surface = estimate_surface(features.ij, features.spot_px, cfg, options, cal.last_level_mm)
    if len(features.alt_shifts) > 1:
        features, surface = resolve_label_shift(features, surface, reference, cfg, options)
    if surface.anchor.get("method") == "integrability":
        cal.last_level_mm = surface.anchor["anchor_mm"]
    t2 = time.perf_counter()
    view = restore_view(
        images["view"] / cal.view_gain,
        cal.camera_v,
        surface.heightfield,
        cfg.water.h0_mm,
        cfg.water.n_water,
        cfg.object_z_mm,
        warp_step_px=options.warp_step_px,
    )
    t3 = time.perf_counter()
    timings = {
        "features": 1e3 * (t1 - t0),
        "surface": 1e3 * (t2 - t1),
        "reverse_trace": 1e3 * (t3 - t2),
        "end_to_end": 1e3 * (t3 - t0),
    }
    return RestoreResult(features, surface, view, timings)
