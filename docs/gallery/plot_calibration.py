"""
Calibrating a camera from checkerboards
=======================================

Camera v given a real lens (k1 = -0.2, the principal point 15 px off), ten checkerboards
rendered through it, and the lens recovered as ``wai calibrate`` does (OpenCV's
``findChessboardCornersSB`` and ``calibrateCameraExtended``): the detected corners on one
view, and each view's reprojection error.
"""

import matplotlib.pyplot as plt

from mitsuba_wai.checkerboards import Board, render_checkerboards
from restoration.rig_calibration import calibrate_device, find_corners
from wai_core import load_system, with_keys

cfg = with_keys(load_system("paper"), {"camera_v.distortion": [-0.2, 0.05, 0, 0, 0],
                                       "camera_v.principal_offset_px": [15.0, -10.0]})
dev = cfg.camera_v
images = render_checkerboards(cfg, "camera_v", 10, seed=3)
fit = calibrate_device(images, Board(), (dev.height_px, dev.width_px))
true_fx = dev.focal_mm * dev.width_px / dev.sensor_width_mm
print(f"fx {fit.fx_px:.2f} px (true {true_fx:.2f}), k1 {fit.distortion[0]:.4f} (true -0.2), "
      f"RMS {fit.rms_px:.3f} px over {fit.n_used} views")

corners = find_corners(images[0], Board())
fig, axes = plt.subplots(1, 2, figsize=(12, 4), gridspec_kw={"width_ratios": [1.4, 1]})
axes[0].imshow(images[0], cmap="gray")
axes[0].plot(corners[:, 0], corners[:, 1], "r+", ms=8)
axes[0].set_title("view 0: the corners found", fontsize=9)
axes[0].set_axis_off()
axes[1].bar(range(len(fit.view_rms_px)), fit.view_rms_px)
axes[1].set_xlabel("view")
axes[1].set_ylabel("reprojection RMS (px)")
axes[1].set_title(f"every view (all: {fit.rms_px:.3f} px)", fontsize=9)

plt.show()
