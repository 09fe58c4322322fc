"""
Where a spot's light centre lies
================================

The restoration takes each spot's centre as the point where its dot's centre ray lands, while
the detector finds the centre of the spot's light. Fresnel's reflectance from below climbs
steeply towards the critical angle (48.6 degrees for water), so a dot met obliquely is
brighter on its more oblique side and its light centre moves. On the paper's rig the dots meet
flat water at 25-68 degrees: the left panel shows each dot's shift on flat water (camera s
pixels) against that angle, smooth and with GGX micro-roughness; beyond the critical angle
the dot is totally reflected and only the geometry moves it. The right panel is the shift over
camera s's image on smooth water. ``wai restore --spot-bias`` corrects each spot by its shift on
the estimated surface less its shift on flat water (``restoration.spot_bias``).
"""

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import LogNorm

from restoration import SpotBiasModel, spot_bias_px
from wai_core import load_system
from wai_core.geometry import critical_angle_rad
from wai_core.light_paths import dot_rays, spots_through

rig = load_system("paper").rig
panel = rig.dot_panel_px[rig.lit]
spot = spots_through(rig, None, panel)
cam = rig.camera_s
seen = (spot >= 0).all(axis=1) & (spot < [cam.width_px, cam.height_px]).all(axis=1)
panel, spot = panel[seen], spot[seen]
_, d = dot_rays(rig, panel)
incidence = np.degrees(np.arccos(np.abs(d[:, 2])))
h0 = rig.cfg.water.h0_mm

fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
for alpha, colour in ((0.0, "tab:blue"), (0.005, "tab:orange"), (0.01, "tab:red")):
    bias = spot_bias_px(rig, panel, None, h0, SpotBiasModel(roughness=alpha))
    label = "smooth" if alpha == 0 else f"GGX alpha {alpha:g}"
    ax.plot(incidence, np.linalg.norm(bias, axis=1), ".", ms=3, color=colour, label=label)
    if alpha == 0:
        smooth = bias
ax.axvline(np.degrees(critical_angle_rad(4.0 / 3.0)), color="k", lw=0.8, ls="--")
ax.text(np.degrees(critical_angle_rad(4.0 / 3.0)) + 0.5, ax.get_ylim()[1] * 0.9,
        "critical angle", fontsize=8)
ax.set_xlabel("angle of incidence on flat water (degrees)")
ax.set_ylabel("light centre less centre ray (px)")
ax.legend(fontsize=8)
ax.set_title("A dot's shift on flat water", fontsize=10)

size = np.linalg.norm(smooth, axis=1)
sc = bx.scatter(spot[:, 0], spot[:, 1], c=np.maximum(size, 1e-3), s=6, cmap="viridis",
                norm=LogNorm(vmin=1e-3, vmax=size.max()))
bx.set_xlim(0, cam.width_px)
bx.set_ylim(cam.height_px, 0)
bx.set_aspect("equal")
bx.set_xlabel("column (px)")
bx.set_ylabel("row (px)")
fig.colorbar(sc, ax=bx, label="shift, smooth water (px)")
bx.set_title("Over camera s's image (log scale)", fontsize=10)
fig.tight_layout()
print(f"smooth water: median shift {np.median(size):.3f} px, largest {size.max():.3f} px")

plt.show()
