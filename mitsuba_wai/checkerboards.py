"""Calibration images: a planar checkerboard seen by a device through its real optics.

The field calibrates a camera from photographs of a checkerboard in a dozen poses (Zhang 2000;
OpenCV's ``calibrateCamera``). Here every pixel's ray comes from the device's optics as the
renderer models them (:class:`wai_core.lens.DeviceOptics`: principal point and lens
distortion) and is intersected with the board, supersampled for antialiasing, so a calibration
from these images can be compared with the true intrinsics of the scene.

A camera in a housing is calibrated twice, as in the field: its lens in air, out of the housing
(``medium="air"``: the port left off), and the port in the water (``medium="water"``: the
board seen through the port from the water, every ray bent twice by it).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray

from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError
from wai_core.lens import DeviceOptics

__all__ = ["Board", "board_poses", "pixel_rays", "render_checkerboard", "render_checkerboards"]

CAMERAS = ("camera_v", "camera_s")
SUPERSAMPLING = 4
"""Rays per pixel along each axis."""


@dataclass(frozen=True)
class Board:
    """A checkerboard: ``cols`` x ``rows`` inner corners, squares of ``square_mm``, a white
    margin of one square around the squares.

    Examples
    --------
    >>> Board().size_mm
    (200.0, 140.0)
    """

    cols: int = 9
    rows: int = 6
    square_mm: float = 20.0

    def __post_init__(self) -> None:
        if self.cols < 3 or self.rows < 3 or not self.square_mm > 0:
            raise WaiInputError(
                f"board: needs at least 3x3 inner corners and squares > 0 mm, not "
                f"{self.cols}x{self.rows}, {self.square_mm} mm"
            )

    @property
    def size_mm(self) -> tuple[float, float]:
        """Width and height of the squares' area, mm."""
        return (self.cols + 1) * self.square_mm, (self.rows + 1) * self.square_mm

    def corners_mm(self) -> NDArray[np.float32]:
        """The inner corners (cols * rows, 3) on the board's plane, mm, row by row."""
        j, i = np.mgrid[1:self.rows + 1, 1:self.cols + 1]
        pts = np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=1) * self.square_mm
        return pts.astype(np.float32)

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


def _rotation(tilt_x: float, tilt_y: float, spin: float) -> NDArray:
    cx, sx, cy, sy, cz, sz = (f(a) for a in (tilt_x, tilt_y, spin) for f in (np.cos, np.sin))
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rx @ ry @ rz


def board_poses(optics: DeviceOptics, board: Board, n: int, seed: int,
                fill: float = 0.6, max_tilt_deg: float = 35.0, n_medium: float = 1.0,
                ) -> list[tuple[NDArray, NDArray]]:
    """``n`` seeded board poses in the device's frame: rotation (3, 3) (columns: the board's
    axes) and the position of its squares' corner (3,) mm. The board spans about ``fill`` of
    the image width, tilted up to ``max_tilt_deg``, shifted so that it stays in view (in a
    medium of index ``n_medium``, whose refraction narrows the field of view about n-fold)."""
    rng = np.random.default_rng(seed)
    cam = optics.camera
    half_w = (cam.width_px / 2.0) / cam.focal_px / n_medium  # tan of the half field of view
    half_h = (cam.height_px / 2.0) / cam.focal_px / n_medium
    width, height = board.size_mm
    distance = width / (2.0 * fill * half_w)
    poses = []
    for _ in range(n):
        tilt = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 2))
        rot = _rotation(tilt[0], tilt[1], np.radians(rng.uniform(-15.0, 15.0)))
        room_x = max(half_w * distance - 0.75 * width, 0.0)
        room_y = max(half_h * distance - 0.75 * height, 0.0)
        centre = np.array([rng.uniform(-room_x, room_x), rng.uniform(-room_y, room_y), distance])
        origin = centre - rot @ np.array([width / 2.0, height / 2.0, 0.0])
        poses.append((rot, origin))
    return poses


Rays = list[tuple[NDArray | None, NDArray]]


def pixel_rays(optics: DeviceOptics, n_water: float | None = None) -> Rays:
    """The device's rays in its frame, one ``(origins (H, W, 3) mm or None: the pinhole,
    directions (H, W, 3))`` per sub-pixel position (:data:`SUPERSAMPLING` squared): the same
    for every view, so traced once. In air (``n_water`` None) through the lens alone; in water
    of index ``n_water`` through the port too, from its outer face."""
    cam = optics.camera
    offsets = (np.arange(SUPERSAMPLING) + 0.5) / SUPERSAMPLING - 0.5
    rows, cols = np.mgrid[0:cam.height_px, 0:cam.width_px].astype(np.float64)
    out: Rays = []
    for dy in offsets:
        for dx in offsets:
            o, d, pinhole = optics.rays_cam(cols + dx, rows + dy, n_water or 1.0)
            out.append((None, pinhole) if n_water is None else (o, d))
    return out


def render_checkerboard(rays: Rays, board: Board, rot: NDArray, origin_mm: NDArray,
                        ) -> NDArray[np.float32]:
    """The board at pose (``rot``, ``origin_mm``) seen along ``rays`` (:func:`pixel_rays`):
    (H, W) in [0, 1], black and white squares with a white margin of one square, a mid-grey
    background."""
    normal = rot[:, 2]
    s = board.square_mm
    total = np.zeros(rays[0][1].shape[:2])
    for o, d in rays:
        to_board = origin_mm if o is None else origin_mm - o
        t = (to_board @ normal) / (d @ normal)
        p = t[..., None] * d - to_board
        iu, iv = np.floor(p @ rot[:, 0] / s), np.floor(p @ rot[:, 1] / s)
        on_squares = (iu >= 0) & (iu <= board.cols) & (iv >= 0) & (iv <= board.rows)
        on_board = (iu >= -1) & (iu <= board.cols + 1) & (iv >= -1) & (iv <= board.rows + 1)
        value = np.where(on_board, 1.0, 0.35)
        value = np.where(on_squares & ((iu + iv) % 2 == 0), 0.05, value)
        total += np.where(np.isfinite(t) & (t > 0), value, 0.35)
    return (total / len(rays)).astype(np.float32)


def render_checkerboards(cfg: SystemConfig, device: str, n: int, seed: int = 0,
                         board: Board | None = None, noise: float = 0.002,
                         medium: str = "air") -> list[NDArray[np.float32]]:
    """``n`` calibration images (H, W) of ``board`` by ``device`` (``camera_v`` or
    ``camera_s``) through its configured optics, with seeded Gaussian noise of standard
    deviation ``noise``: in ``"air"`` through its lens (a port left off: the camera out of its
    housing), or in ``"water"`` (``[water].n_water``) through its lens and port.

    Examples
    --------
    >>> from wai_core import load_system
    >>> (img,) = render_checkerboards(load_system("paper"), "camera_v", 1)
    >>> img.shape, bool(img.min() < 0.1 < 0.9 < img.max())
    ((600, 800), True)
    """
    if device not in CAMERAS:
        raise WaiInputError(f"checkerboards: device must be one of {', '.join(CAMERAS)}")
    if n < 1:
        raise WaiInputError(f"--checkerboards must be at least 1, not {n}")
    if medium not in ("air", "water"):
        raise WaiInputError(f"checkerboards: medium must be 'air' or 'water', not {medium!r}")
    board = Board() if board is None else board
    optics = cfg.rig.optics(device)
    if medium == "water" and not optics.has_port:
        raise WaiInputError(f"checkerboards: [{device}] has no port to calibrate in water")
    n_water = cfg.water.n_water if medium == "water" else None
    rng = np.random.default_rng(seed + 1)
    rays = pixel_rays(optics, n_water)
    images = []
    for rot, origin in board_poses(optics, board, n, seed, n_medium=n_water or 1.0):
        img = render_checkerboard(rays, board, rot, origin)
        images.append(np.clip(img + rng.normal(0.0, noise, img.shape), 0, 1).astype(np.float32))
    return images
