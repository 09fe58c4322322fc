"""What the restoration knows of a rig: its configuration, the view's gain, per-rig caches.

A calibration is read from ``scene.json`` (written by ``wai render``, or by hand for one's own
captures: the ``config`` section alone is enough) or built from a configuration in memory. It
is shared by every frame of the rig; per-rig work (the flat-water reference, detected once) is
cached on it. Per-sequence state (a video's level) is not: see :class:`LevelTrack`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from restoration.features import ReferenceGrid, prepare_reference
from restoration.reverse_trace import Restoration, restore_view
from wai_core.config import SystemConfig, config_from_dict
from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera
from wai_core.heightfield import Heightfield
from wai_core.images import find_image, read_image
from wai_core.io import read_json

__all__ = ["Calibration", "LevelTrack", "RigCalibration", "read_scene_record"]


def read_scene_record(folder: str | Path) -> dict[str, Any]:
    """``folder/scene.json`` as a dict with a ``config`` table (checked)."""
    path = Path(folder) / "scene.json"
    record = read_json(path)
    if not isinstance(record, dict) or not isinstance(record.get("config"), dict):
        raise WaiInputError(f"{path}: needs a 'config' table (the system configuration)")
    return record


def record_view_gain(record: dict[str, Any]) -> float:
    """The factor the view's values carry over the object's radiance: rendered radiance gains
    n^2 entering the water (``derived.view_radiance_gain``, written by the renderer); a
    capture's record has none, and its images are taken as they are (1)."""
    derived = record.get("derived")
    gain = derived.get("view_radiance_gain", 1.0) if isinstance(derived, dict) else 1.0
    if not isinstance(gain, int | float) or not np.isfinite(gain) or gain <= 0:
        raise WaiInputError(f"scene.json: derived.view_radiance_gain must be > 0, not {gain!r}")
    return float(gain)


@dataclass
class RigCalibration:
    """The basics every method's calibration holds: the system configuration (water, camera v,
    object) and the view's radiance gain.

    Attributes
    ----------
    cfg : SystemConfig
    view_gain : float
        The view image divided by this is the object's radiance scale (1 for captures, n^2 for
        renders).
    """

    cfg: SystemConfig
    view_gain: float = 1.0

    IMAGES: ClassVar[tuple[str, ...]] = ("view",)
    """Stems of the images a frame of this method needs."""

    @cached_property
    def camera_v(self) -> PinholeCamera:
        """The observation camera (built once: the view asks for it every frame)."""
        return self.cfg.camera_v.camera()

    def radiance(self, view: NDArray) -> NDArray:
        """A view image of this rig on the object's radiance scale: divided by
        :attr:`view_gain` (what scores and restored images are expressed in)."""
        return view / self.view_gain

    def restore_view(
        self, distorted: NDArray, surface: Heightfield, warp_step_px: int = 8,
        gain: float = 1.0,
    ) -> Restoration:
        """The view ``distorted`` ((H, W, 3)) restored into the flat-water view's geometry by
        reverse ray tracing through ``surface`` (absolute heights, mm), solving every
        ``warp_step_px``-th pixel, on the radiance scale: ``gain`` is divided out of the
        restored pixels (:attr:`view_gain` for a raw view; 1 for one already divided).
        Resampling is linear, so this equals dividing first, without a copy of the view."""
        cfg = self.cfg
        distorted = np.asarray(distorted)
        if not np.issubdtype(distorted.dtype, np.floating):  # integer captures
            distorted = distorted.astype(np.float64)
        return restore_view(
            distorted, self.camera_v, surface, cfg.water.h0_mm, cfg.water.n_water,
            cfg.object_z_mm, warp_step_px=warp_step_px, gain=gain,
        )

    def image_size(self, name: str) -> tuple[int, int]:
        """``(height, width)`` in pixels that image ``name`` must have."""
        if name == "view":
            dev = self.cfg.camera_v
            return dev.height_px, dev.width_px
        raise KeyError(name)

    def load_images(self, folder: str | Path) -> dict[str, NDArray[np.float32]]:
        """A frame's images from ``folder`` (EXR, PNG or TIFF by stem), sizes checked."""
        images = {}
        for name in self.IMAGES:
            path = find_image(folder, name)
            img = read_image(path)
            h, w = self.image_size(name)
            if img.shape[:2] != (h, w):
                raise WaiInputError(
                    f"{path} is {img.shape[1]}x{img.shape[0]} but the calibration says {w}x{h}"
                )
            images[name] = img
        return images


@dataclass
class Calibration(RigCalibration):
    """The structured light's calibration: the rig, and once prepared the flat-water
    reference grid (detected and labelled once per rig, reused by every frame).

    Examples
    --------
    >>> from restoration import Calibration
    >>> from wai_core import load_system
    >>> cal = Calibration(load_system("paper"))
    >>> cal.image_size("pattern")
    (600, 800)
    """

    reference: ReferenceGrid | None = None

    IMAGES: ClassVar[tuple[str, ...]] = ("pattern", "pattern_flat", "view")

    @classmethod
    def from_record(cls, record: dict[str, Any]) -> Calibration:
        """From a ``scene.json`` record (see :func:`read_scene_record`)."""
        return cls(config_from_dict(record["config"]), record_view_gain(record))

    @classmethod
    def from_folder(cls, folder: str | Path) -> Calibration:
        """From ``folder/scene.json``."""
        return cls.from_record(read_scene_record(folder))

    def image_size(self, name: str) -> tuple[int, int]:
        if name in ("pattern", "pattern_flat"):
            dev = self.cfg.camera_s
            return dev.height_px, dev.width_px
        return super().image_size(name)

    def prepare(self, pattern_flat: NDArray) -> ReferenceGrid:
        """Detect and label the flat-water pattern once; later frames reuse it."""
        if self.reference is None:
            self.reference = prepare_reference(pattern_flat, self.cfg)
        return self.reference


@dataclass
class LevelTrack:
    """A sequence's water level between frames: where each frame's level search starts.

    A video's mean level drifts far less between frames than the search's first step, so
    starting at the previous frame's level saves evaluations. Per sequence, never per rig:
    one calibration may serve several sequences at once.

    Examples
    --------
    >>> track = LevelTrack()
    >>> track.start_mm is None
    True
    """

    start_mm: float | None = None

    def update(self, anchor: dict[str, Any]) -> None:
        """Take the level of a frame whose level came from integrability."""
        if anchor.get("method") == "integrability":
            self.start_mm = float(anchor["anchor_mm"])
