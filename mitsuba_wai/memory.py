"""Peak memory of the renders, estimated from the configuration before anything is loaded.

The constants are bytes per pixel the renders hold at their peak, measured as the peak resident
memory of ``wai render`` over the paper's scene with one device's size changed at a time
(800 x 600 to 4800 x 3600 px, 1 and 4 spp; 2-core VM, LLVM variant): the slope of the peak
against the pixels, the imports' ~0.5 GiB left out (they are already in memory when the check
runs). :func:`render_bytes` and :func:`checkerboard_bytes` sum them for a configuration;
:func:`wai_core.memory.check_memory` compares the sum with the memory available.
"""

from __future__ import annotations

from wai_core.config import SystemConfig

__all__ = ["check_render_memory", "checkerboard_bytes", "describe_devices", "render_bytes"]

CAMERA_BYTES_PER_PX = 170
"""Peak bytes per pixel of a camera while its images render: the wavefront of one sample per
pixel (every pass holds at least that once the film exceeds a pass's samples), the passes'
float64 sums and the images. Measured: 163-181 for camera s, 148-177 for camera v."""
KEPT_BYTES_PER_PX = 24
"""Bytes per pixel of the other camera's two finished float32 RGB images, held while the larger
one renders (both cameras at 3200 x 2400 px peak 0.2 GiB above one alone)."""
PANEL_BYTES_PER_PX = 44
"""Bytes per pixel of the projector's panel image as it is built: its float64 luminance, the
float64 RGB product and the float32 image (:func:`wai_core.pattern.pattern_image`)."""
DOT_PROFILE_BYTES = 8
"""Bytes per dot and panel row or column: the float64 Gaussian profiles of every dot along the
panel's columns and rows, summed into the panel."""
CHECKERBOARD_BYTES_PER_PX = 480
"""Peak bytes per pixel of a camera while its board views render: 16 sub-pixel ray arrays of
float64 (384) and one view's intersections (measured: 504 at 3 views, 575 at 12)."""
CHECKERBOARD_BYTES_PER_PX_VIEW = 8
"""Bytes per pixel of each board view kept until the camera's views are written."""


def _pixels(cfg: SystemConfig, name: str) -> int:
    dev = getattr(cfg, name)
    return int(dev.width_px) * int(dev.height_px)


def _panel_bytes(cfg: SystemConfig) -> float:
    """The projector's panel image as it is built: its dots' profiles and its pixels."""
    dots = len(cfg.rig.dot_ij)
    w, h = cfg.projector.width_px, cfg.projector.height_px
    return DOT_PROFILE_BYTES * dots * (w + h) + PANEL_BYTES_PER_PX * w * h


def render_bytes(cfg: SystemConfig) -> float:
    """Estimated peak memory of rendering one frame of ``cfg`` (both systems), bytes.

    Examples
    --------
    >>> from wai_core import load_system
    >>> cfg = load_system("paper")
    >>> round(render_bytes(cfg) / 2**20)        # MiB, the paper's 800 x 600 cameras
    149
    >>> big = cfg.replace("camera_s", width_px=20000, height_px=20000)
    >>> round(render_bytes(big) / 2**30)        # GiB
    63
    """
    cameras = [_pixels(cfg, name) for name in ("camera_s", "camera_v")]
    return (CAMERA_BYTES_PER_PX * max(cameras) + KEPT_BYTES_PER_PX * min(cameras)
            + _panel_bytes(cfg))


def checkerboard_bytes(cfg: SystemConfig, views: int) -> float:
    """Estimated peak memory of rendering ``views`` board views per camera of ``cfg`` (one
    camera at a time), bytes."""
    per_px = CHECKERBOARD_BYTES_PER_PX + CHECKERBOARD_BYTES_PER_PX_VIEW * views
    return per_px * max(_pixels(cfg, name) for name in ("camera_s", "camera_v"))


def describe_devices(cfg: SystemConfig,
                     devices: tuple[str, ...] = ("camera_s", "camera_v", "projector")) -> str:
    """The ``devices``' sizes, largest first, as a message names them
    (``[camera_s] 20000 x 20000 px, [camera_v] 800 x 600 px, [projector] 1000 x 1000 px``)."""
    names = sorted(devices, key=lambda n: -_pixels(cfg, n))
    return ", ".join(f"[{n}] {getattr(cfg, n).width_px} x {getattr(cfg, n).height_px} px"
                     for n in names)


def check_render_memory(cfg: SystemConfig, scene: str, views: int = 0) -> None:
    """Refuse a render of ``cfg`` (``views`` > 0: that many checkerboard views per camera)
    whose estimated peak memory exceeds the memory available, naming ``scene`` and the
    devices' sizes (:func:`wai_core.memory.check_memory`)."""
    from wai_core.memory import check_memory

    devices: tuple[str, ...] = ("camera_s", "camera_v", "projector")
    need, work = render_bytes(cfg), "rendering a frame"
    if views:  # the boards are seen by the cameras alone
        devices, need = ("camera_s", "camera_v"), checkerboard_bytes(cfg, views)
        work = f"rendering {views} checkerboard views per camera"
    check_memory(need, f"{scene}: {describe_devices(cfg, devices)}", work)
