"""
An effect the restoration can be told: sea water's index
========================================================

The error budget renders an effect the geometric model leaves out and restores the frame
twice: with the paper's model (n = 4/3) and with the scene's own water (``wai experiment
budget``'s "modelled" column). Here sea water at 35 PSU and 5 °C, Quan & Fry's index per
colour channel: the surface does not care (reflection does not depend on n), the restored
view's corners do.
"""

import matplotlib.pyplot as plt

import mitsuba_wai as mw
import restoration as rs
from wai_core import load_system

sea = load_system("paper").replace("water", index_model="quan_fry", salinity_psu=35.0,
                                   temperature_c=5.0)
paper = load_system("paper")
frame = mw.render_frame(sea, spp=4)
rows = []
for told, cfg in (("n = 4/3 (the paper's model)", paper), ("sea water (told)", sea)):
    cal = rs.Calibration(cfg, frame.view_gain)
    result = rs.StructuredLight()(frame.images, cal)
    truth = rs.Truth(frame.surface, cal.radiance(frame.images["view_truth"]))
    scores = rs.score(result, cal.radiance(frame.images["view"]), cal, truth)
    rows.append((told, scores.rmse_mm, scores.corner_std_restored_px))
    print(f"{told}: RMSE {scores.rmse_mm:.3f} mm, corner STD "
          f"{scores.corner_std_restored_px:.3f} px")

fig, axes = plt.subplots(1, 2, figsize=(10, 3.4))
names = [r[0] for r in rows]
axes[0].bar(names, [r[1] for r in rows], color=["0.6", "tab:blue"])
axes[0].set_ylabel("surface RMSE (mm)")
axes[1].bar(names, [r[2] for r in rows], color=["0.6", "tab:blue"])
axes[1].set_ylabel("restored corner STD (px)")
for ax in axes:
    ax.tick_params(axis="x", labelsize=8)

plt.show()
