"""Shared core: ray geometry, calibration (the system configuration), heightfields and file I/O.

Everything else depends on this package; it depends on nothing of the project.
"""
