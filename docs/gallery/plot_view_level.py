"""
The level from the view
=======================

On rough water (GGX micro-roughness alpha 0.01) the pattern's spots blur, and the slopes'
integrability no longer pins the structured light's level: raising the surface and bending it
back moves every spot by microns. Camera v sees the same surface from below. Its lines of
sight, traced through the structured light's surface rebuilt at each level to a speckle object,
land where the flow from its view to its flat-water view puts them only at the right level:
the left panel is their mean (clipped) squared miss against the level, beside the surface's
error against the renderer's truth; the right panel the misses over camera v's image at the
level the view picks. ``wai restore DIR --method structured-light-view`` takes that level
(``restoration.view_level``).
"""

import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from mitsuba_wai import render_folder
from restoration import StructuredLight, StructuredLightView, ViewLevelCalibration
from restoration.surface import reconstruct
from restoration.view_level import CLIP_PX, view_residual_px, view_samples
from wai_core import load_system
from wai_core.heightfield import load_heightfield

cfg = load_system("paper").replace("object", texture="speckle").replace(
    "water", roughness=0.01).replace("render", spp_pattern=64).replace("waves", seed=0)
folder = Path(tempfile.mkdtemp()) / "rough"
render_folder(cfg, folder, progress=False)
truth = load_heightfield(folder / "heightfield.npz")

cal = ViewLevelCalibration.from_folder(folder)
images = cal.load_images(folder)
plain = StructuredLight()(images, cal)
obs = cal.observe(plain.features.ij, plain.features.spot_px)
samples = view_samples(images, cal)
start = plain.surface.anchor.anchor_mm

levels = start + np.linspace(-0.5, 0.5, 11)
miss, error = [], []
for level in levels:
    est = reconstruct(obs, level)
    r = view_residual_px(est, samples, cal)
    miss.append(np.mean(np.minimum(r[np.isfinite(r)], CLIP_PX) ** 2))
    hf = est.heightfield
    x, y = np.meshgrid(hf.x, hf.y)
    e = (hf.z - truth.height(x, y))[np.isfinite(hf.z)]
    error.append(np.sqrt(np.mean(e**2)))

view = StructuredLightView()(images, cal)
chosen = view.surface.anchor.anchor_mm

fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
ax.plot(levels - start, miss, "o-", color="tab:blue", label="view: mean squared miss (px$^2$)")
ax.set_xlabel("level less the integrability level (mm)")
ax.set_ylabel("camera v's miss (px$^2$)", color="tab:blue")
tx = ax.twinx()
tx.plot(levels - start, error, "s--", color="tab:red", label="surface RMSE by the truth (mm)")
tx.set_ylabel("surface RMSE against the truth (mm)", color="tab:red")
ax.axvline(chosen - start, color="k", lw=0.8)
ax.text(chosen - start, ax.get_ylim()[1] * 0.95, " the view's level", fontsize=8, va="top")
ax.set_title(f"Rough water: the structured light alone says {plain.status.value}",
             fontsize=10)

r = view_residual_px(view.surface, samples, cal)
ok = np.isfinite(r)
sc = bx.scatter(samples.px[ok, 0], samples.px[ok, 1], c=np.minimum(r[ok], CLIP_PX), s=4,
                cmap="magma", vmin=0, vmax=1)
bx.set_xlim(0, cfg.camera_v.width_px)
bx.set_ylim(cfg.camera_v.height_px, 0)
bx.set_aspect("equal")
bx.set_xlabel("column (px)")
bx.set_ylabel("row (px)")
fig.colorbar(sc, ax=bx, label="miss of each line of sight (flat-water px)")
bx.set_title(f"At the view's level: {view.status.value}", fontsize=10)
fig.tight_layout()
