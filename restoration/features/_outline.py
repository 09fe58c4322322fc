"""Convex outlines in camera s, shared by the flat-water reference and the wavy-water matching:
the diffuser's extent and its outline in the image, where camera s can see a spot, and the
distances of points inside the edges of a convex polygon.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from restoration.features._types import BoolArray, FloatArray
from restoration.undistort import diffuser_pinhole_px
from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError


def _diffuser(cfg: SystemConfig) -> FloatArray:
    """Diffuser extent ``[[x0, x1], [y0, y1]]``, mm (:func:`wai_core.layout.diffuser_rect`)."""
    try:
        return cfg.rig.diffuser_rect
    except ValueError as exc:
        raise WaiInputError(f"config: {exc}") from None


def _outline_px(cfg: SystemConfig) -> FloatArray:
    """The diffuser's corners (4, 2) in camera s, pixels, in order around it (read-only). Per
    rig: the reference keeps it
    (:attr:`~restoration.features.reference.ReferenceGrid.outline_px`)."""
    (x0, x1), (y0, y1) = _diffuser(cfg)
    z = cfg.diffuser.z_mm
    corners = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])
    cols, rows, _ = cfg.rig.camera_s.project(corners)
    out = np.stack([cols, rows], axis=1)
    out.setflags(write=False)
    return out


def _visible_outline(cfg: SystemConfig) -> FloatArray:
    """Where camera s can see a spot: the diffuser's outline clipped to the image, (M, 2) px
    (read-only). Per rig: the reference keeps it
    (:attr:`~restoration.features.reference.ReferenceGrid.visible_px`)."""
    cam = cfg.camera_s
    w, h = cam.width_px - 0.5, cam.height_px - 0.5
    frame = np.array([[-0.5, -0.5], [w, -0.5], [w, h], [-0.5, h]], np.float32)
    if cfg.rig.optics("camera_s").has_port:
        # The real image's border in the pinhole's pixels: bowed by the port, sampled.
        t = np.linspace(0.0, 1.0, 65)[:-1, None]
        ends = zip(frame, np.roll(frame, -1, 0), strict=True)
        border = np.vstack([c0 + t * (c1 - c0) for c0, c1 in ends])
        seen = diffuser_pinhole_px(cfg, border)
        frame = cv2.convexHull(seen[np.isfinite(seen).all(axis=1)].astype(np.float32))[:, 0]
    area, poly = cv2.intersectConvexConvex(_outline_px(cfg).astype(np.float32), frame)
    if area <= 0 or poly is None:
        raise WaiInputError("camera s does not see the diffuser")
    out = poly[:, 0].astype(np.float64)
    out.setflags(write=False)
    return out


def _edge_distances(poly: FloatArray, pts: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Signed distances (N, M) of points (N, 2) inside each edge of a convex polygon (M, 2),
    positive inwards, and the edges' inward unit normals (M, 2)."""
    edge = np.roll(poly, -1, axis=0) - poly
    normal = np.stack([-edge[:, 1], edge[:, 0]], axis=1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    normal *= np.sign(np.sum((poly.mean(axis=0) - poly) * normal, axis=1, keepdims=True))
    return np.einsum("pmk,mk->pm", pts[:, None, :] - poly[None], normal), normal


@dataclass(frozen=True)
class _Outline:
    """A convex polygon (M, 2) with its inward unit edge normals (M, 2), computed once."""

    poly: FloatArray
    normal: FloatArray

    @classmethod
    def of(cls, poly: FloatArray) -> _Outline:
        poly = np.asarray(poly, dtype=np.float64)
        return cls(poly, _edge_distances(poly, poly[:1])[1])

    def inside(self, pts: FloatArray, margin: FloatArray) -> BoolArray:
        """Points (N, 2) at least ``margin`` (N,) inside, pixels."""
        dist = np.einsum("pmk,mk->pm", pts[:, None, :] - self.poly[None], self.normal)
        return (dist >= margin[:, None]).all(axis=1)
