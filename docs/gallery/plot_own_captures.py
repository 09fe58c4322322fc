"""
Your own captures: 16-bit frames in, a restored view out
========================================================

A capture folder holds ``scene.json`` (the rig) and three images: ``pattern``,
``pattern_flat`` and ``view``, as EXR, PNG or TIFF. To rehearse the path with a render, write
linear 16-bit PNGs: scale each image so its brightest pixel is near full scale (the pattern's
EXR peaks near 0.09, the view's near 1.65: written as they are, the pattern would use 6 % of
the range and the view would clip) and remember that OpenCV writes BGR. Integer values are
read as linear counts over full scale; the scale does not matter to the surface.
"""

import json
import tempfile
from pathlib import Path

import cv2
import matplotlib.pyplot as plt
import numpy as np

import mitsuba_wai as mw
import restoration as rs
from wai_core import load_system
from wai_core.io import to_srgb8

cfg = load_system("paper")
frame = mw.render_frame(cfg, spp=2)
folder = Path(tempfile.mkdtemp()) / "capture"
folder.mkdir()
for name in ("pattern", "pattern_flat", "view"):
    img = frame.images[name]
    counts = np.clip(img / float(img.max()), 0.0, 1.0) * 65535.0  # exposure: peak at full scale
    cv2.imwrite(str(folder / f"{name}.png"), np.rint(counts).astype(np.uint16)[..., ::-1])
(folder / "scene.json").write_text(json.dumps({"config": cfg.to_dict()}))

done = rs.restore_folder(folder)
print("\n".join(done.summary_lines()))

restored = np.asarray(done.result.view.image)
fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
axes[0].imshow(cv2.imread(str(folder / "view.png"), cv2.IMREAD_UNCHANGED)[..., ::-1] / 65535.0)
axes[0].set_title("view.png (16-bit, as captured)", fontsize=9)
axes[1].imshow(to_srgb8(restored / max(float(restored.max()), 1e-9), 1.0))
axes[1].set_title(f"restored: status {done.result.status}", fontsize=9)
for ax in axes:
    ax.set_axis_off()

plt.show()
