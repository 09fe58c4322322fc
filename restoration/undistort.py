"""Real devices as the ideal pinholes the restoration models.

A device whose principal point is off the image centre or whose lens distorts
(``principal_offset_px``, ``distortion``) is seen through its ideal pinhole (same pose and
focal length, centred, undistorted). Camera v's images are resampled into that pinhole's
geometry when they are read (:class:`PinholeRemap`: the view is restored pixel by pixel);
camera s's spots are detected in the image as taken, where they are compact, and their
centres mapped to the pinhole (:func:`pinhole_px`: resampling a wide-angle lens's edges would
stretch them); a projector's dots are given the panel positions whose pinhole rays are their
real rays (:func:`pinhole_panel_px`). Every stage after that works with the pinhole. A
housing port makes a device's rays miss a common centre, which no pinhole reproduces: the
restoration refuses it (:func:`check_no_port`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from wai_core.distortion import distort, distortion_one_to_one
from wai_core.lens import DeviceOptics

__all__ = ["PinholeRemap", "diffuser_pinhole_px"]


@dataclass(frozen=True, eq=False)
class PinholeRemap:
    """Where each pixel of a device's ideal pinhole lies in its real image (its lens's
    principal point and distortion; a port stays: see :class:`~wai_core.port.PortCamera`).

    Attributes
    ----------
    map_cols, map_rows : (H, W) ndarray of float32
        Real-image coordinates (px) of every ideal pixel: the real optics' projection of the
        ideal pixel's ray (:func:`wai_core.distortion.distort` with the principal point).

    Examples
    --------
    >>> import numpy as np
    >>> from wai_core import load_system, with_keys
    >>> cfg = with_keys(load_system("paper"), {"camera_v.principal_offset_px": [3.0, 0.0]})
    >>> remap = PinholeRemap.of(cfg.rig.optics("camera_v"), "camera_v")
    >>> real = np.zeros((600, 800), np.float32); real[300, 403] = 1.0
    >>> ideal = remap.apply(real)  # ideal pixel c sees real pixel c + 3
    >>> ideal_lens = load_system("paper").rig.optics("camera_v")
    >>> int(np.argmax(ideal[300])), PinholeRemap.of(ideal_lens, "camera_v") is None
    (400, True)
    """

    map_cols: NDArray[np.float32]
    map_rows: NDArray[np.float32]

    @classmethod
    def of(cls, optics: DeviceOptics, name: str) -> PinholeRemap | None:
        """The remap of a device with ``optics`` (config section ``name``; a rig's
        :meth:`~wai_core.rig.Rig.optics`), None for a lens that is its pinhole's."""
        if optics.lens_free:
            return None
        cam = optics.camera
        f = cam.focal_px
        rows, cols = np.mgrid[0:cam.height_px, 0:cam.width_px].astype(np.float64)
        x = (cols - (cam.width_px - 1) / 2.0) / f
        y = (rows - (cam.height_px - 1) / 2.0) / f
        beyond = np.zeros(x.shape, dtype=bool)
        if optics.distorted:
            beyond = ~distortion_one_to_one(x, y, optics.distortion)
            x, y = distort(x, y, optics.distortion)
        cx, cy = optics.principal_px
        # Rays past the lens's fold are not the lens's: those ideal pixels see nothing.
        cols = np.where(beyond, -1.0, f * x + cx)
        rows = np.where(beyond, -1.0, f * y + cy)
        return cls(cols.astype(np.float32), rows.astype(np.float32))

    @cached_property
    def seen(self) -> NDArray[np.bool_]:
        """(H, W) bool: the ideal pixels whose bilinear sample lies wholly on the real sensor
        (all four neighbours inside it); elsewhere :meth:`apply` gives 0 or a blend with 0,
        no data of the real image."""
        h, w = self.map_cols.shape
        return ((self.map_cols >= 0) & (self.map_cols <= w - 1)
                & (self.map_rows >= 0) & (self.map_rows <= h - 1))

    def seen_at(self, map_cols: NDArray[np.float32], map_rows: NDArray[np.float32]
                ) -> NDArray[np.bool_]:
        """Whether a bilinear sample of an image :meth:`apply` made, at ideal pixels
        ``(map_cols, map_rows)`` (any shape), draws on :attr:`seen` pixels only."""
        seen = self.seen.astype(np.float32)
        at = cv2.remap(seen, np.asarray(map_cols, np.float32), np.asarray(map_rows, np.float32),
                       cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return at >= 1.0 - 1e-6

    def apply(self, image: ArrayLike) -> NDArray:
        """``image`` (H, W) or (H, W, C) of the real device resampled into the ideal pinhole
        (bilinear; 0 where the ideal pixel sees past the real image's border)."""
        img = np.asarray(image)
        if not np.issubdtype(img.dtype, np.floating):
            img = img.astype(np.float32)
        return cv2.remap(img, self.map_cols, self.map_rows, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def diffuser_pinhole_px(cfg: Any, px: ArrayLike) -> NDArray:
    """Camera s's pixels ``px`` (K, 2) as the pixels (K, 2) of its ideal pinhole that see the
    same points of the diffuser plane: the lens's principal point and distortion undone and,
    behind a port, each real ray followed to the plane
    (:meth:`~wai_core.lens.DeviceOptics.plane_pinhole_px`); ``px`` itself for an ideal camera
    (the same array); NaN where the lens cannot map a pixel.

    Examples
    --------
    >>> import numpy as np
    >>> from wai_core import load_system, with_keys
    >>> cfg = with_keys(load_system("paper"), {"camera_s.principal_offset_px": [3.0, 0.0]})
    >>> diffuser_pinhole_px(cfg, np.array([[402.5, 299.5]]))  # the centre
    array([[399.5, 299.5]])
    """
    return cfg.rig.optics("camera_s").plane_pinhole_px(px, float(cfg.diffuser.z_mm),
                                                        cfg.rig.port_index("camera_s"))
