"""
Speed against accuracy over the wind
====================================

Three wind speeds, one seed each, restored by the structured light: the surface's RMSE
against the time the restoration took, each point labelled with its wind and status (``wai
experiment tradeoffs`` charts this for every method and setting over many seeds).
"""

import matplotlib.pyplot as plt

import mitsuba_wai as mw
import restoration as rs
from wai_core import load_system

points = []
for wind in (0.5, 1.0, 1.5):
    cfg = load_system("paper").replace("waves", wind_speed_m_s=wind, seed=2)
    frame = mw.render_frame(cfg, spp=2)
    cal = rs.Calibration(cfg, frame.view_gain)
    result = rs.StructuredLight()(frame.images, cal)
    truth = rs.Truth(frame.surface, cal.radiance(frame.images["view_truth"]))
    scores = rs.score(result, cal.radiance(frame.images["view"]), cal, truth)
    points.append((wind, result.timings_ms["end_to_end"], scores.rmse_mm, result.status))
    print(f"U = {wind} m/s: {result.status}, RMSE {scores.rmse_mm:.3f} mm, "
          f"{result.timings_ms['end_to_end']:.0f} ms")

fig, ax = plt.subplots(figsize=(6.5, 4))
for wind, ms, rmse, status in points:
    ax.plot(ms, rmse, "o")
    ax.annotate(f"U = {wind} m/s ({status})", (ms, rmse), xytext=(5, 5),
                textcoords="offset points", fontsize=8)
ax.set_xlabel("restoration, ms per frame (this machine)")
ax.set_ylabel("surface RMSE (mm)")
ax.grid(alpha=0.3)

plt.show()
