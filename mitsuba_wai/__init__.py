"""Rendering: ocean waves become meshes in Mitsuba 3 scenes of the paper's two optical systems.

A frame in memory, or a render folder on disk::

    import mitsuba_wai as mw
    from wai_core import load_system

    cfg = load_system("paper")
    frame = mw.render_frame(cfg)                # images + true surface, in memory
    mw.render_folder(cfg, "renders/f1")         # what ``wai render`` writes

The Mitsuba variant is chosen on first use (:func:`select_variant`: ``cuda_ad_rgb`` with a
GPU, else ``llvm_ad_rgb``; neither is an error in one line); importing this package loads no
renderer. Renders are reproducible bit for bit for a seed: the particle-traced images (patterns,
sun spots) come from :mod:`mitsuba_wai.particles`, which sums in a fixed order.
"""

from mitsuba_wai.frame import Frame, render_frame
from mitsuba_wai.render import FrameRenderer, render_folder
from mitsuba_wai.sequence import render_sequence
from mitsuba_wai.surface_sampling import file_surface, wave_surface
from mitsuba_wai.variant import select_variant
from mitsuba_wai.waves import sea_surface

__all__ = [
    "Frame",
    "FrameRenderer",
    "file_surface",
    "render_folder",
    "render_frame",
    "render_sequence",
    "sea_surface",
    "select_variant",
    "wave_surface",
]
