"""Camera s's real optics in the spots' terms: each spot's centre mapped from the image as taken
to the ideal pinhole every later stage models (:func:`pinhole_spots`), which spots the real
image holds (:func:`in_real_image`), and how much a housing port magnifies them there
(:func:`image_scale`)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from restoration.features._types import BoolArray, FloatArray
from restoration.features.detect import Spots
from restoration.undistort import diffuser_pinhole_px
from wai_core.config import SystemConfig
from wai_core.light_paths import real_spot_px

__all__ = ["image_scale", "in_real_image", "pinhole_spots"]


def image_scale(cfg: SystemConfig) -> float:
    """Camera s's real-image pixels per pinhole pixel, the median over the flat-water spots in
    view: a port magnifies the spots in the image as taken (a pinhole pixel of the diffuser
    plane covers several real ones at the image's edge). 1 without a port (a lens's
    distortion is left to the detector's tolerance, as it always was)."""
    rig = cfg.rig
    if not rig.optics("camera_s").has_port:
        return 1.0
    px = rig.flat_spots.px
    px = px[np.isfinite(px).all(axis=1)]
    real = [real_spot_px(rig, px + d) for d in ([0.0, 0.0], [0.5, 0.0], [0.0, 0.5])]
    jx, jy = (real[1] - real[0]) / 0.5, (real[2] - real[0]) / 0.5
    det = np.abs(jx[:, 0] * jy[:, 1] - jx[:, 1] * jy[:, 0])
    seen = np.isfinite(det) & rig.camera_s.in_image(real[0][:, 0], real[0][:, 1])
    return float(np.sqrt(np.median(det[seen]))) if seen.any() else 1.0


def in_real_image(cfg: SystemConfig, pinhole_px: FloatArray, margin_px: float) -> BoolArray:
    """(K,) bool: the spots at camera s's pinhole pixels (K, 2) that lie inside its real image
    less ``margin_px`` (its lens and port: :func:`wai_core.light_paths.real_spot_px`)."""
    real = real_spot_px(cfg.rig, pinhole_px)
    with np.errstate(invalid="ignore"):
        return np.isfinite(real[:, 0]) & cfg.rig.camera_s.in_image(real[:, 0], real[:, 1],
                                                                    margin_px)


def pinhole_spots(spots: Spots, cfg: SystemConfig) -> Spots:
    """``spots`` of camera s with their centres in its ideal pinhole's pixels (the model every
    later stage uses; :func:`restoration.undistort.diffuser_pinhole_px`); the same object for
    an ideal camera. Spots whose centre the lens cannot map are flagged ``border``."""
    centres = diffuser_pinhole_px(cfg, spots.centres_px)
    if centres is spots.centres_px:
        return spots
    lost = ~np.isfinite(centres).all(axis=1)
    centres = np.where(lost[:, None], spots.centres_px, centres)
    return replace(spots, centres_px=centres, border=spots.border | lost,
                   image_px=spots.centres_px)
