"""
What the waves do to the dots
=============================

The flat-water pattern is the calibration; each wavy spot's shift from its flat-water place is
what the surface's slope did to its ray (the paper's eq. 3-7). Drawn here: a part of both
images, and the shifts of the detected spots as arrows (ten times their length).
"""

import matplotlib.pyplot as plt
import numpy as np
from scipy.spatial import cKDTree

import mitsuba_wai as mw
import restoration as rs
from wai_core import load_system
from wai_core.io import to_srgb8

cfg = load_system("paper").replace("waves", wind_speed_m_s=1.5)
frame = mw.render_frame(cfg, spp=2)
flat = rs.detect_spots(frame.images["pattern_flat"]).centres_px
wavy = rs.detect_spots(frame.images["pattern"]).centres_px
dist, near = cKDTree(flat).query(wavy, distance_upper_bound=10.0)
ok = np.isfinite(dist)
shift = wavy[ok] - flat[near[ok]]
print(f"{len(flat)} flat spots, {len(wavy)} wavy; median shift {np.median(dist[ok]):.2f} px")

fig, axes = plt.subplots(1, 3, figsize=(15, 4))
box = (slice(200, 400), slice(250, 550))
for ax, name in zip(axes[:2], ("pattern_flat", "pattern"), strict=True):
    ax.imshow(to_srgb8(frame.images[name][box], 10.0))
    ax.set_title(f"{name} (a part)", fontsize=9)
    ax.set_axis_off()
axes[2].quiver(flat[near[ok], 0], flat[near[ok], 1], shift[:, 0], shift[:, 1],
               angles="xy", scale_units="xy", scale=0.1, width=0.002)
axes[2].invert_yaxis()
axes[2].set_aspect("equal")
axes[2].set_title("spot shifts x10 (px)", fontsize=9)

plt.show()
