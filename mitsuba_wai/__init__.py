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

from mitsuba_wai.alterman import SunRenderer, alterman_surface, render_alterman_folder
from mitsuba_wai.checkerboards import Board, render_checkerboards
from mitsuba_wai.degrade import render_exposure, resolve_exposure, sense, subframe_plan
from mitsuba_wai.frame import Frame, render_frame
from mitsuba_wai.frame_images import render_flat_water, render_frame_images
from mitsuba_wai.lens import lens_keys
from mitsuba_wai.memory import check_render_memory, describe_devices, render_bytes
from mitsuba_wai.mesh import flat_like
from mitsuba_wai.reference import render_reference, windowed_centroids
from mitsuba_wai.render import OUTPUT_COMMAND, FrameRenderer, Rendered, render_folder
from mitsuba_wai.scene_record import render_seed
from mitsuba_wai.seawater import coefficients_per_mm, pattern_path_lengths_mm
from mitsuba_wai.sequence import render_frames, render_sequence
from mitsuba_wai.surface_sampling import file_surface, wave_grid_axes, wave_surface
from mitsuba_wai.textures import object_texture
from mitsuba_wai.variant import select_variant
from mitsuba_wai.warp_trace import ViewWarpTracer
from mitsuba_wai.waves import mesh_spacing_mm, sea_surface
from mitsuba_wai.waves_jit import JitWaveGrid

__all__ = [
    "OUTPUT_COMMAND",
    "Board",
    "Frame",
    "FrameRenderer",
    "JitWaveGrid",
    "SunRenderer",
    "ViewWarpTracer",
    "alterman_surface",
    "check_render_memory",
    "coefficients_per_mm",
    "describe_devices",
    "file_surface",
    "flat_like",
    "lens_keys",
    "mesh_spacing_mm",
    "object_texture",
    "pattern_path_lengths_mm",
    "render_alterman_folder",
    "render_bytes",
    "render_checkerboards",
    "render_exposure",
    "Rendered",
    "render_folder",
    "render_frame",
    "render_flat_water",
    "render_frame_images",
    "render_frames",
    "render_reference",
    "render_seed",
    "render_sequence",
    "resolve_exposure",
    "sea_surface",
    "select_variant",
    "sense",
    "subframe_plan",
    "wave_grid_axes",
    "wave_surface",
    "windowed_centroids",
]
