"""Restoration: from renders plus calibration to a surface and an undistorted image.

Reads only the images and ``scene.json``; the true surface and view are read only to score. Never
imports the wave generator or the renderer.
"""
