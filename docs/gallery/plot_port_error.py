"""
Why a housing port is not a pinhole
===================================

A flat port bends every ray twice, so the rays in the water share no centre. Here camera v
behind 10 mm of acrylic 10 mm from its lens: a pinhole matched to it on the mean water level
(its rays' points there) and the error of that pinhole, in pixels, for points 10 mm above that
level. The error grows towards the image's corners: the reason the restoration traces the
port's rays (``wai_core.port.PortCamera``) and never the pinhole shortcut.
"""

import matplotlib.pyplot as plt
import numpy as np

from wai_core import load_system, with_keys
from wai_core.port import PortCamera

cfg = with_keys(load_system("paper"), {"camera_v.port_thickness_mm": 10.0,
                                       "camera_v.port_gap_mm": 10.0})
cam = PortCamera(cfg.rig.optics("camera_v"), cfg.water.n_water)
cols, rows = cam.pixel_grid(step=20)
o, d = cam.pixel_rays(cols, rows)
h0 = cfg.water.h0_mm


def at(z):
    """Where each pixel's water ray reaches the height z, mm."""
    return o + d * ((z - o[..., 2]) / d[..., 2])[..., None]


# The pinhole that sees the mean level's points at the same pixels: its centre is where the
# rays from two heights meet best (least squares), its pixels those points' projections.
p0, p1 = at(h0), at(h0 + 10.0)
centre = cam.pose.center_lab_mm
pin = cam.camera
c0, r0, _ = pin.project(p0 - 0.0)
shift = np.stack([c0 - cols, r0 - rows], axis=-1)  # the pinhole's own offset at h0
c1, r1, _ = pin.project(p1)
error = np.hypot(c1 - cols - shift[..., 0], r1 - rows - shift[..., 1])
print(f"pinhole error 10 mm off the level: median {np.median(error):.2f} px, "
      f"max {error.max():.2f} px")

fig, ax = plt.subplots(figsize=(6.5, 4.2))
im = ax.pcolormesh(cols, rows, error, shading="auto", cmap="viridis")
ax.invert_yaxis()
ax.set_aspect("equal")
ax.set_xlabel("column (px)")
ax.set_ylabel("row (px)")
fig.colorbar(im, ax=ax, label="pinhole error, 10 mm above the level (px)")
ax.set_title("A port camera seen as a pinhole", fontsize=10)

plt.show()
