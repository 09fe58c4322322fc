"""The files of a render folder: each image as EXR with its PNG preview, and the true surface."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mitsuba_wai import mesh as meshes
from wai_core.config import SensorConfig
from wai_core.heightfield import Heightfield
from wai_core.images import record_previews
from wai_core.io import write_exr, write_png
from wai_core.sensor import integer_image

__all__ = ["write_images", "write_surface"]


def write_images(
    folder: Path, images: dict[str, NDArray], view_gain: float, sensor: SensorConfig | None = None
) -> None:
    """Each image as ``NAME.exr`` and a ``NAME.png`` preview, recorded as the tool's own
    (:func:`wai_core.images.record_previews`); views (``view*``) are shown at the exposure
    that undoes the radiance gain, others at their own 99.5th percentile.

    With an enabled ``sensor`` the images are ``DN / full scale`` and ``NAME.png`` is the
    camera's integer image at the ADC depth (:func:`wai_core.sensor.integer_image`)."""
    import cv2

    for name, img in images.items():
        write_exr(folder / f"{name}.exr", img)
        if sensor is not None and sensor.enabled:
            raw = integer_image(img, sensor)
            if not cv2.imwrite(str(folder / f"{name}.png"), np.ascontiguousarray(raw[..., ::-1])):
                raise OSError(f"could not write {folder / f'{name}.png'}")
            continue
        exposure = 1.0 / view_gain if name.startswith("view") else None
        write_png(folder / f"{name}.png", img, exposure=exposure)
    # The previews are the tool's own: they never make the frame's images ambiguous.
    record_previews(folder, {f"{name}.png": (f"{name}.exr", img) for name, img in images.items()})


def write_surface(folder: Path, surface: Heightfield) -> None:
    """The true surface as ``heightfield.npz`` and the mesh rendered as ``surface.ply``."""
    surface.save(folder / "heightfield.npz")
    meshes.heightfield_mesh(surface).export(folder / "surface.ply")
