"""Alterman et al.'s method (STELLA MARIS, ICCP 2014): the surface from sun spots behind pinholes.

The sensor (:mod:`wai_core.alterman`) images the refracted sun through an array of pinholes onto
a screen. Per frame:

1. detect the sun spots (:func:`restoration.features.detect_spots`) and give each to its pinhole:
   the mutually nearest flat-water reference spot, within half the pitch; failures are counted;
2. refracted sun direction ``t = (s - P) / |s - P|`` from the pinhole ``P`` to its spot ``s`` on
   the screen (the spot's pixel back-projected onto the screen plane);
3. normal by Snell's law with the known sun direction ``d``: ``d x N = n (t x N)``, so
   ``N ~ d - n t`` (the isoplanatic assumption: one normal per pinhole);
4. the normal belongs to the point where the line through ``P`` along ``-t`` crosses the surface:
   at ``h0`` first (the published method), then, as in the structured light's refinement, at the
   height the integration gives, repeated until the heights settle. The normals themselves do not
   depend on that height (the sun is a known direction, not a known point), so unlike the
   structured light the absolute height cannot come from integrability: the gauge's ``h0`` is the
   mean height of the samples;
5. the slopes are integrated (:func:`restoration.integrate.integrate`) on the pinhole grid and
   gridded (:func:`restoration.integrate.to_heightfield`); the view is restored by the same
   reverse ray tracing (:func:`restoration.reverse_trace.restore_view`).

When the method cannot run on valid input (no sun, sun spots out of view, too few spots) it says
so with a status instead of a surface: it never makes one up.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from restoration.calibration import RigCalibration, read_scene_record, record_view_gain
from restoration.features import Matches, Spots, detect_spots
from restoration.integrate import MIN_SAMPLES
from restoration.normals import slopes_from_normals, spots_on_diffuser
from restoration.options import AltermanOptions
from restoration.ray_surface import RaySurface, integrate_along_rays
from restoration.result import RestoreResult, Status
from wai_core.alterman import (
    AltermanSystem,
    SensorLayout,
    alterman_from_dict,
    sensor_layout,
    sun_is_up,
)
from wai_core.config import config_from_dict
from wai_core.errors import RestorationFailed, WaiInputError
from wai_core.timings import Timings

Array = NDArray[np.float64]

METHOD = "alterman"
OK = Status.OK
NO_SUN = Status.NO_SUN
SUN_OUT_OF_VIEW = Status.SUN_OUT_OF_VIEW
TOO_FEW_SPOTS = Status.TOO_FEW_SPOTS
MIN_SPOTS = 16
"""Fewest matched spots the method integrates (as the structured light's features)."""


@dataclass(frozen=True)
class SpotReference:
    """The flat-water sun spots, each labelled with its pinhole (calibration, once per rig).

    Attributes
    ----------
    ij : (R, 2) ndarray of int
        Pinhole grid index of each observed reference spot.
    ref_px : (R, 2) ndarray
        Detected flat-water spot centres in camera a, px.
    counts : dict of str to int
        ``predicted_in_view``, ``observed``, ``unmatched_predicted``, ``unassigned_spots``.
    """

    ij: NDArray[np.int64]
    ref_px: Array
    counts: dict[str, int]


@dataclass
class AltermanCalibration(RigCalibration):
    """What the method knows: the base configuration (water, camera v, object), the sensor's
    configuration and layout, and, once prepared, the flat-water spot reference."""

    system: AltermanSystem | None = None
    layout: SensorLayout | None = None
    reference: SpotReference | None = None

    IMAGES: ClassVar[tuple[str, ...]] = ("sunspots", "sunspots_flat", "view")

    @classmethod
    def from_system(cls, system: AltermanSystem, view_gain: float = 1.0) -> AltermanCalibration:
        """From a sensor system in memory (e.g. :func:`wai_core.load_system` ``("alterman")``)."""
        return cls(system.base, view_gain, system=system, layout=sensor_layout(system))

    @classmethod
    def from_record(cls, record: dict[str, Any]) -> AltermanCalibration:
        """From a ``scene.json`` record of a sun-sensor render (with an ``alterman`` table)."""
        if not isinstance(record.get("alterman"), dict):
            raise WaiInputError("scene.json is not a sun-sensor render (no 'alterman' entry)")
        system = AltermanSystem(
            config_from_dict(record["config"]), alterman_from_dict(record["alterman"])
        )
        return cls.from_system(system, record_view_gain(record))

    @classmethod
    def from_folder(cls, folder: str | Path) -> AltermanCalibration:
        """From ``folder/scene.json``."""
        return cls.from_record(read_scene_record(folder))

    def image_size(self, name: str) -> tuple[int, int]:
        if name in ("sunspots", "sunspots_flat"):
            cam = self.layout.camera
            return cam.height_px, cam.width_px
        return super().image_size(name)


# ----------------------------------------------------------------------------------------------
# Can the method run?
# ----------------------------------------------------------------------------------------------


def sun_status(system: AltermanSystem, layout: SensorLayout) -> tuple[Status, str]:
    """From the calibration alone: is there a sun, and do its spots land in camera a's view?"""
    if not sun_is_up(system.sensor.sun):
        return NO_SUN, "no direct sunlight (sun off, below the horizon or zero irradiance)"
    _, seen = layout.flat_spots_px()
    if seen.sum() < MIN_SPOTS:
        return SUN_OUT_OF_VIEW, (
            f"the refracted sun reaches only {int(seen.sum())} pinhole spots on the screen in "
            f"camera a's view (need {MIN_SPOTS})"
        )
    return OK, ""


# ----------------------------------------------------------------------------------------------
# Correspondence
# ----------------------------------------------------------------------------------------------


def _mutual_nearest(a: Array, b: Array, max_px: float) -> tuple[NDArray, NDArray, NDArray]:
    """For points ``a`` (N, 2): the index of the nearest ``b`` (M, 2), whether it lies within
    ``max_px``, and whether ``a`` is in turn the nearest of that ``b`` (mutual)."""
    if len(a) == 0 or len(b) == 0:
        none = np.zeros(len(a), bool)
        return np.zeros(len(a), int), none, none
    dist, idx = cKDTree(b).query(a)
    back = cKDTree(a).query(b)[1]
    return idx, dist <= max_px, back[idx] == np.arange(len(a))


def prepare_spot_reference(flat_img: NDArray, layout: SensorLayout) -> SpotReference:
    """Label the flat-water spots with their pinholes: each predicted spot (calibration) takes
    the mutually nearest detected spot within a third of the pitch.

    Parameters
    ----------
    flat_img : (H, W) or (H, W, 3) ndarray
        Camera a's image of the sun spots over flat water (linear intensity).
    layout : SensorLayout
        The sensor's calibration (predicted spots, pitch in pixels).
    """
    pred_px, seen = layout.flat_spots_px()
    spots = detect_spots(flat_img)
    centres = spots.centres_px[~spots.suspicious]
    idx, near, mutual = _mutual_nearest(pred_px[seen], centres, layout.pitch_px / 3.0)
    ok = near & mutual
    rows = np.flatnonzero(seen)[ok]
    return SpotReference(
        ij=layout.ij[rows],
        ref_px=centres[idx[ok]],
        counts={
            "predicted_in_view": int(seen.sum()),
            "observed": int(ok.sum()),
            "unmatched_predicted": int((~ok).sum()),
            "unassigned_spots": int(len(spots) - ok.sum()),
        },
    )


def match_spots(spots: Spots, ref: SpotReference, max_px: float) -> Matches:
    """Give each reference pinhole the mutually nearest wavy-water spot within ``max_px``.

    Counts: ``detected``, ``reference``, ``matched``; reference spots dropped as
    ``rejected_far`` (nearest spot beyond ``max_px``), ``rejected_ambiguous`` (that spot is
    nearer another reference) or ``rejected_border`` (spot cut by the image border, merged or
    saturated); ``unmatched_reference`` (all dropped) and ``unassigned_spots`` (spots given to
    no pinhole).

    Parameters
    ----------
    spots : Spots
        Spots detected in the wavy frame (centres in px).
    ref : SpotReference
        The flat-water spots and their pinholes.
    max_px : float
        Largest move of a spot from its flat-water place, px (half the pitch: beyond it the
        spot would be nearer its neighbour's place).

    Returns
    -------
    Matches
        Pinhole grid index, flat-water and wavy spot centre (px) of each kept match.
    """
    idx, near, mutual = _mutual_nearest(ref.ref_px, spots.centres_px, max_px)
    suspicious = spots.suspicious[idx] if len(spots) else np.zeros(len(idx), bool)
    ok = near & mutual & ~suspicious
    counts = {
        "detected": len(spots),
        "reference": len(ref.ij),
        "matched": int(ok.sum()),
        "rejected_far": int((~near).sum()),
        "rejected_ambiguous": int((near & ~mutual).sum()),
        "rejected_border": int((near & mutual & suspicious).sum()),
        "unmatched_reference": int((~ok).sum()),
        "unassigned_spots": int(len(spots) - ok.sum()),
    }
    return Matches(
        ij=ref.ij[ok],
        ref_px=ref.ref_px[ok],
        spot_px=spots.centres_px[idx[ok]],
        observed=np.ones(int(ok.sum()), bool),
        counts=counts,
    )


# ----------------------------------------------------------------------------------------------
# Normals and samples
# ----------------------------------------------------------------------------------------------


def refracted_dirs(pinholes_mm: ArrayLike, spots_mm: ArrayLike) -> Array:
    """Unit refracted sun directions ``t = (s - P) / |s - P|`` (K, 3), pointing down."""
    v = np.asarray(spots_mm, dtype=float) - np.asarray(pinholes_mm, dtype=float)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def snell_normals(sun_dir: ArrayLike, t: ArrayLike, n_water: float) -> Array:
    """Unit normals (K, 3), pointing up, that refract the sun direction ``d`` into ``t``.

    Snell's law in vector form, ``1 (d x N) = n (t x N)``, makes ``N`` parallel to ``d - n t``
    (for air into water of index ``n``).
    """
    w = np.asarray(sun_dir, dtype=float) - n_water * np.asarray(t, dtype=float)
    w /= np.linalg.norm(w, axis=-1, keepdims=True)
    return w * np.where(w[..., 2:3] < 0, -1.0, 1.0)


def reconstruct_alterman(
    ij: NDArray,
    pinholes_mm: Array,
    spots_mm: Array,
    layout: SensorLayout,
    options: AltermanOptions,
) -> RaySurface:
    """Surface from matched spots: Snell normals, samples at h0 then refined along the lines
    of the refracted sunlight, integrated on the pinhole grid (``options.integrator``) with
    mean height h0, gridded (``options.gridder``)
    (:func:`~restoration.ray_surface.integrate_along_rays`).

    Parameters
    ----------
    ij : (K, 2) ndarray of int
        Pinhole grid indices (4-neighbours on the grid are neighbours on the surface).
    pinholes_mm, spots_mm : (K, 3) ndarray
        Pinhole centres and their spots on the screen, mm.
    layout : SensorLayout
        The sensor's calibration (sun direction, water index and level).
    options : AltermanOptions
        ``integrator``, ``n_refine`` (0: samples stay on z = h0, the published method),
        ``refine_tol_mm``, ``gridder``, ``grid_spacing_mm``.
    """
    t = refracted_dirs(pinholes_mm, spots_mm)
    normals = snell_normals(layout.sun_dir, t, layout.n_water)
    slopes = slopes_from_normals(normals)

    def slopes_at(points: Array, index: NDArray) -> tuple[Array, Array]:
        return normals[index], slopes[index]  # the sun's normals hold at any height

    return integrate_along_rays(ij, pinholes_mm, t, slopes_at, layout.h0_mm, options,
                                options.refine_tol_mm)


# ----------------------------------------------------------------------------------------------
# The method end to end
# ----------------------------------------------------------------------------------------------


def _spot_features(
    images: dict[str, NDArray], cal: AltermanCalibration
) -> tuple[Matches | None, Status, str]:
    """Reference (once) and this frame's matches, or the status that stops the method."""
    if cal.reference is None:
        cal.reference = prepare_spot_reference(images["sunspots_flat"], cal.layout)
    ref = cal.reference
    if ref.counts["observed"] == 0:
        return None, NO_SUN, "no sun spot on the flat-water reference (overcast?)"
    spots = detect_spots(images["sunspots"])
    if len(spots) == 0:
        return None, NO_SUN, "no sun spot in the frame (overcast?)"
    matches = match_spots(spots, ref, max_px=0.5 * cal.layout.pitch_px)
    if len(matches) < max(MIN_SPOTS, MIN_SAMPLES):
        return matches, TOO_FEW_SPOTS, (
            f"only {len(matches)} sun spots matched to pinholes (need {MIN_SPOTS})"
        )
    return matches, OK, ""


def restore_alterman(
    images: dict[str, NDArray],
    cal: AltermanCalibration,
    options: AltermanOptions | None = None,
) -> RestoreResult:
    """Run the method on loaded images (``sunspots``, ``sunspots_flat``, ``view``).

    Returns a :class:`~restoration.result.RestoreResult`: status ``ok`` with the features,
    surface, restored view and timings, or ``no_sun`` / ``sun_out_of_view`` /
    ``too_few_spots`` / ``failed`` (the spots give no surface:
    :class:`~wai_core.errors.RestorationFailed`) and no surface.
    """
    options = AltermanOptions() if options is None else options
    status, message = sun_status(cal.system, cal.layout)
    if status != OK:
        return RestoreResult(METHOD, status, message)
    timings = Timings()
    with timings("features"):
        matches, status, message = _spot_features(images, cal)
    if matches is None or status != OK:
        counts = {} if matches is None else matches.counts
        return RestoreResult(METHOD, status, message, counts=counts)
    try:
        with timings("surface"):
            pinholes = cal.layout.pinholes_mm[cal.layout.index_of(matches.ij)]
            spots_mm = spots_on_diffuser(matches.spot_px, cal.layout.camera,
                                         cal.layout.screen_z_mm)
            surface = reconstruct_alterman(matches.ij, pinholes, spots_mm, cal.layout, options)
    except RestorationFailed as exc:
        return RestoreResult(METHOD, Status.FAILED, str(exc), counts=matches.counts)
    with timings("reverse_trace"):
        view = cal.restore_view(images["view"], surface.heightfield, options.warp_step_px,
                                gain=cal.view_gain)
    timings.add("end_to_end", timings.total())
    matches.timings_ms.update({"detect_and_match": timings.ms["features"]})
    return RestoreResult(METHOD, OK, "", matches, surface, view, timings.to_dict(), matches.counts)
