"""Render a frame of both systems and write a render folder that the restoration can read alone.

A render folder holds:

``pattern.exr`` / ``pattern_flat.exr``
    Camera s's image of the diffuser with wavy / flat water (linear float RGB).
``view.exr`` / ``view_truth.exr``
    Camera v's image of the object through wavy / flat water. **Ground truth** is the view the
    same camera would have through perfectly flat water at the mean level ``h0``: the image that
    restoration aims to recover, in that view's pixel geometry.
``heightfield.npz`` / ``surface.ply``
    The true surface (``x`` (n,), ``y`` (m,), ``z`` (m, n), mm, lab frame) and the mesh rendered.
``scene.json``
    Everything that made the renders: configuration, derived layout, seeds, variant, versions.

Each image also gets a PNG preview. The folder appears atomically when complete.

With ``[sensor]`` enabled (:mod:`mitsuba_wai.degrade`) the EXR holds the sensor's reading as
``DN / full scale`` (linear, in [0, 1]) and ``NAME.png`` is no preview but the integer image
the camera writes at the ADC depth (8-bit PNG, or 16-bit PNG for 9 to 16 bits, the DN stretched
to 65535): a folder stripped of its EXRs reads the same. With ``[motion]`` the wavy images are
blurred over the exposure and the surface files hold the surface at mid-exposure.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mitsuba_wai import mesh as meshes
from mitsuba_wai.ambient import SCENE_SUN_DEPTH, sky_image, smooth, sun_s_scene, view_emitters
from mitsuba_wai.crosstalk import Crosstalk, camera_v_filter
from mitsuba_wai.degrade import subframe_plan
from mitsuba_wai.diffuser import screen_blur
from mitsuba_wai.dots import DotEmitter
from mitsuba_wai.frame_images import render_frame_images
from mitsuba_wai.lens import scene_lenses
from mitsuba_wai.particles import (
    _direct_scene,
    pass_split,
    render_particles,
    render_particles_water,
)
from mitsuba_wai.render_files import write_images, write_surface
from mitsuba_wai.scene_record import render_seed, scene_record
from mitsuba_wai.scenes import (
    pattern_depth,
    pattern_scene,
    view_scene,
    water_bsdf,
    water_channel_indices,
)
from mitsuba_wai.seawater import (
    coefficients_per_mm,
    glow,
    glow_sigma_px,
    view_path_lengths,
    water_view,
)
from mitsuba_wai.surface_sampling import file_surface, labelled, moving_surface, wave_surface
from mitsuba_wai.textures import object_texture
from mitsuba_wai.variant import mitsuba, select_variant
from mitsuba_wai.view_tracer import _direct_parts, render_view
from mitsuba_wai.water_hit import WaterGeometry
from wai_core.config import SensorConfig, SystemConfig
from wai_core.heightfield import Heightfield
from wai_core.io import write_json
from wai_core.outputs import atomic_dir, check_output_dir
from wai_core.rig_checks import check_surface_in_rig
from wai_core.signals import raise_if_interrupted
from wai_core.timings import Timings

# Most samples Mitsuba takes in one wavefront (2^32 - 1); more spp are rendered in passes.
MAX_WAVEFRONT = 0xFFFFFFFF
# The sun's particles in system S are seeded this far from the projector's (independent noise).
AMBIENT_SEED_OFFSET = 0x5BD1E995
OUTPUT_COMMAND = "render"
"""Command named in a render folder's output marker (:mod:`wai_core.outputs`)."""


def render_image(
    scene: object, spp: int, seed: int, particle_depth: int | None = None,
    stratified: bool = False, emitter: object = None, camera: object = None,
    geometry: WaterGeometry | None = None,
) -> tuple[NDArray[np.float32], int]:
    """Render a loaded scene to linear RGB (H, W, 3); non-finite pixels are zeroed and counted.

    Parameters
    ----------
    scene : mitsuba.Scene
    spp : int
        Samples per pixel, >= 1, any number: a camera-side render that would exceed Mitsuba's
        wavefront (2^32 samples) runs in near-equal passes of whole samples per pixel, pass
        ``k`` seeded ``seed + k``, averaged in float64.
    seed : int
        Sampler seed (0 .. 2^32 - 1); the same seed gives the same image, bit for bit.
    particle_depth : int, optional
        Render with the deterministic particle tracer (:mod:`mitsuba_wai.particles`) of this
        ``max_depth`` instead of the scene's integrator: for the ``ptracer`` scenes.
    stratified : bool
        The particle tracer's stratified emission (:func:`mitsuba_wai.particles.emitter_samples`);
        camera-side renders take the sampler of the scene's sensor.
    emitter : callable, optional
        The particle tracer's emitter in place of the scene's (``render_particles``'s).
    camera : mitsuba_wai.lens.CameraLens, optional
        The particle tracer's camera in place of the scene's sensor (``render_particles``'s).
    geometry : mitsuba_wai.water_hit.WaterGeometry, optional
        The water the particle tracer's direct pass asks (``render_particles``'s).

    Returns
    -------
    image : (H, W, 3) ndarray of float32
    n_nonfinite : int
        Pixels zeroed: rare invalid splats of the particle tracer, never hidden.
    """
    import drjit as dr

    if particle_depth is not None:
        return render_particles(scene, spp, seed, particle_depth, stratified, emitter, camera,
                                geometry)
    mi = mitsuba()
    size = scene.sensors()[0].film().crop_size()
    passes = pass_split(spp, int(size[0]) * int(size[1]), MAX_WAVEFRONT)
    total, bad = None, None
    for k, spp_k in enumerate(passes):
        img = mi.render(scene, spp=spp_k, seed=(int(seed) + k) % 2**32)
        dr.eval(img)
        arr = np.asarray(img, dtype=np.float32)[..., :3]
        if len(passes) == 1:
            total = arr
        else:
            total = (0.0 if total is None else total) + arr.astype(np.float64) * (spp_k / spp)
        bad = ~np.isfinite(arr).all(axis=2) | (False if bad is None else bad)
    out = np.asarray(total, dtype=np.float32)
    out[bad] = 0.0
    return out, int(bad.sum())


@dataclass
class FrameRenderer:
    """Loaded scenes of both systems whose water surface is swapped per frame.

    Scenes are loaded once; a new surface only rewrites the mesh's vertex buffers, so Dr.Jit's
    compiled kernels are reused from frame to frame (what makes sweeps and benchmarks fast).
    The grid (vertex count) is fixed by the first surface. ``systems`` names the renders to
    prepare (``"pattern"``: system S, ``"view"``: system V); only those can be rendered.

    Flat water (a surface of one height) is rendered by a second renderer, ``flat``, whose mesh
    is a plane of a few vertices over the same span (``flat_only``): the plane is the same
    geometry at any resolution, and a frame's flat and wavy renders then leave each scene's
    acceleration structure to be rebuilt once a frame, not twice (on the paper's finest mesh,
    640 000 triangles, a rebuild per scene takes longer than the render). Renderers of the
    same configuration and span (a dataset's mesh levels) may share one ``flat``.
    """

    cfg: SystemConfig
    grid: Heightfield
    texture: NDArray | None = None
    systems: tuple[str, ...] = ("pattern", "view")
    flat: FrameRenderer | None = None
    flat_only: bool = False
    variant: str = field(init=False)
    nonfinite_pixels: dict[str, int] = field(init=False, default_factory=dict)

    def __post_init__(self) -> None:
        self.variant = select_variant()
        # A rough BSDF or a port takes one index: sea water's three are rendered one channel
        # at a time, each by a renderer of its own (three times the cost, only then).
        self._channels = channel_renderers(self.cfg, self.grid, self.texture, self.systems,
                                           self.flat_only)
        if self._channels:
            self._scenes = {k: None for k in self.systems}
            return
        # Real cameras (mitsuba_wai.lens); refused here, before any render, where they cannot go.
        self._lenses = scene_lenses(self.cfg)
        self._stratified = self.cfg.render.sampling == "stratified"
        mi = mitsuba()
        tm = meshes.heightfield_mesh(self.grid)
        # Where the direct tracers may take the renders, the scenes are loaded around a plane
        # of a few vertices (no acceleration structure of the fine mesh to build) and take
        # the surface when a render goes through them (SceneWater.sync).
        lazy = not (self.cfg.ambient.enabled or self.cfg.crosstalk.enabled)
        scene_tm = meshes.heightfield_mesh(meshes.plane_grid(self.grid)) if lazy else tm
        self._scenes: dict[str, Any] = {}
        self._params: dict[str, Any] = {}
        # Each scene owns its mesh object: Mitsuba meshes cannot be shared between scenes.
        ambient = self.cfg.ambient
        if "pattern" in self.systems:
            water_s = meshes.to_mitsuba(scene_tm, "water", water_bsdf(self.cfg, "S"))
            self._scenes["pattern"] = mi.load_dict(pattern_scene(self.cfg, water_s))
            if ambient.enabled and ambient.sun_irradiance > 0:
                water_sun = meshes.to_mitsuba(tm, "water", water_bsdf(self.cfg, "A"))
                self._scenes["pattern_sun"] = mi.load_dict(
                    sun_s_scene(self.cfg, water_sun, self.grid)
                )
        if "view" in self.systems:
            tex = self.texture if self.texture is not None else object_texture(self.cfg.object)
            water_v = meshes.to_mitsuba(scene_tm, "water", water_bsdf(self.cfg, "V"))
            scene_v = view_scene(self.cfg, water_v, tex)
            if ambient.enabled:
                scene_v.update(view_emitters(self.cfg))
            self._scenes["view"] = mi.load_dict(scene_v)
        self._params = {k: mi.traverse(scene) for k, scene in self._scenes.items()}
        # [crosstalk]: the projector's light on the object, the view's texture per frame.
        self._crosstalk = (Crosstalk(self.cfg, self._scenes["view"], tex)
                           if "view" in self._scenes and self.cfg.crosstalk.enabled else None)
        self._lit_object = False  # the view's texture holds a frame's crosstalk now
        # Stratified: the projector's dots drawn directly (mitsuba_wai.dots), same emission as
        # the scene's projector at a fraction of its cost; independent: Mitsuba's projector.
        self._emitters = (
            {"pattern": DotEmitter(self.cfg)}
            if self._stratified and "pattern" in self._scenes else {}
        )
        # The renders the direct tracers take ask the water alone, on its grid: no acceleration
        # structure to build a surface, the systems' scenes brought up to date only when used.
        self._direct = self._direct_renders() if lazy else frozenset()
        self._water = meshes.SceneWater(self._params,
                                        WaterGeometry.own(tm) if self._direct else None)
        if lazy:
            self._water.set(*meshes.surface_buffers(self.grid))
            self._water.sync(k for k in self._scenes if k not in self._direct)

    def _direct_renders(self) -> frozenset[str]:
        """The renders :meth:`render` gives the direct tracers (system S's dots,
        :func:`~mitsuba_wai.particles._direct_scene`; system V's two steps,
        :func:`~mitsuba_wai.view_tracer._direct_parts`): those that ask only the water, where
        neither daylight nor crosstalk lights the scenes."""
        direct = set()
        emitter = self._emitters.get("pattern")
        if emitter is not None and _direct_scene(self._scenes["pattern"],
                                                 pattern_depth(self.cfg), emitter):
            direct.add("pattern")
        if ("view" in self._scenes and self._stratified
                and _direct_parts(self._scenes["view"]) is not None):
            direct.add("view")
        return frozenset(direct)

    def _geometry(self, key: str) -> WaterGeometry | None:
        """The water a direct render ``key`` asks; None: its scene's own (brought up to date)."""
        return self._water.shared if key in self._direct else None

    def scene(self, key: str) -> Any:
        """The loaded scene ``key`` (``"pattern"``, ``"view"``) holding the last surface."""
        if self._channels:
            raise ValueError("sea water's three indices render through each channel's renderer "
                             "(its scene(key))")
        self._water.sync([key])
        return self._scenes[key]

    def _set_surface(self, surface: Heightfield) -> None:
        for channel in self._channels:
            channel._set_surface(surface)
        if self._channels:
            return
        if surface.z.shape != self.grid.z.shape:
            raise ValueError("surface grid differs from the renderer's mesh grid")
        self._water.set(*meshes.surface_buffers(surface))
        self._water.sync(k for k in self._scenes if k not in self._direct)

    def render(
        self,
        surface: Heightfield,
        seed: int,
        which: tuple[str, ...] = ("pattern", "view"),
        spp: int | dict[str, int] | None = None,
        crosstalk: bool = True,
    ) -> dict[str, NDArray[np.float32]]:
        """Render the pattern (camera s) and/or the view (camera v) through ``surface``, with
        the configuration's samples per pixel or, if given, ``spp`` for every image (an int)
        or per image (a dict keyed ``pattern`` / ``view``). With ``[crosstalk]`` on, the view
        shows the projector's light on the object unless ``crosstalk`` is False (the truth:
        the object's own light)."""
        missing = set(which) - set(self._scenes)
        if missing:
            raise ValueError(f"renderer was not prepared for {sorted(missing)}")
        level_mm = None if self.flat_only else meshes.flat_level_mm(surface)
        if level_mm is not None:
            return self._render_flat(level_mm, seed, which, spp, crosstalk)
        if self._channels:
            return self._render_channels(surface, seed, which, spp, crosstalk)
        self._set_surface(surface)
        if self._crosstalk is not None and "view" in which:
            self._light_object(seed if crosstalk else None)
        out = {}
        given = spp if isinstance(spp, dict) else {"pattern": spp, "view": spp}
        spp = {
            "pattern": given.get("pattern") or self.cfg.render.spp_pattern,
            "view": given.get("view") or self.cfg.render.spp_view,
        }
        # The pattern by the deterministic particle tracer (same image for the same seed).
        depth = {"pattern": pattern_depth(self.cfg), "view": None}
        lit = self.cfg.water_optics.enabled or self.cfg.ambient.enabled
        for key in (k for k in ("pattern", "view") if k in which):
            if key == "pattern" and lit:
                out[key], bad = self._pattern_in_daylight_water(spp[key], seed)
            elif key == "view" and self._stratified and (
                    not self.cfg.ambient.enabled or self._lenses[key] is not None):
                # The three steps system V needs, traced directly (mitsuba_wai.view_tracer):
                # Mitsuba's path integrator's image at half its cost; with the ambient sun and
                # sky and a pinhole, and for "independent", Mitsuba's own integrator (the
                # tracer's general steps carry a lens through daylight: the same expectation).
                out[key], bad = render_view(self._scenes[key], spp[key], seed,
                                            self._lenses[key], self._geometry(key))
            else:
                out[key], bad = render_image(self._scenes[key], spp[key], seed, depth[key],
                                             self._stratified, self._emitters.get(key),
                                             self._lenses.get(key), self._geometry(key))
            if key == "view" and self.cfg.water_optics.enabled:
                lengths = view_path_lengths(self.scene("view"), self.cfg)
                out[key] = water_view(out[key], lengths, self.cfg)
            if key == "pattern":
                out[key] = screen_blur(out[key], self.cfg)  # a no-op unless [diffuser].blur_mm
            else:
                out[key] = camera_v_filter(self.cfg, out[key])  # a no-op without a filter
            self.nonfinite_pixels[key] = self.nonfinite_pixels.get(key, 0) + bad
        return out

    def _render_flat(self, level_mm: float, seed: int, which: tuple[str, ...],
                     spp: int | dict[str, int] | None,
                     crosstalk: bool) -> dict[str, NDArray[np.float32]]:
        """The renders of flat water at ``level_mm``, by :attr:`flat` (made on first use)."""
        if self.flat is None:
            self.flat = FrameRenderer(self.cfg, meshes.plane_grid(self.grid), self.texture,
                                      self.systems, flat_only=True)
        before = dict(self.flat.nonfinite_pixels)
        out = self.flat.render(meshes.flat_like(self.flat.grid, level_mm), seed, which, spp,
                               crosstalk)
        for key, bad in self.flat.nonfinite_pixels.items():
            self.nonfinite_pixels[key] = (self.nonfinite_pixels.get(key, 0) + bad
                                          - before.get(key, 0))
        return out

    def _light_object(self, seed: int | None) -> None:
        """The view's object texture: lit by the projector through the surface the scenes
        hold now (``seed``: its particles'), or its own (None)."""
        if seed is None and not self._lit_object:
            return
        mi = mitsuba()
        tex = self._crosstalk.texture(seed) if seed is not None else self._crosstalk.albedo
        params = self._params["view"]
        params["object.emitter.radiance.data"] = mi.TensorXf(np.ascontiguousarray(tex[::-1]))
        params.update()
        self._lit_object = seed is not None

    def _render_channels(self, surface: Heightfield, seed: int, which: tuple[str, ...],
                         spp: int | dict[str, int] | None,
                         crosstalk: bool = True) -> dict[str, NDArray[np.float32]]:
        """Each image's channel ``c`` from the renderer of channel ``c``'s index."""
        parts = [channel.render(surface, seed, which, spp, crosstalk)
                 for channel in self._channels]
        for channel in self._channels:
            for key, bad in channel.nonfinite_pixels.items():
                self.nonfinite_pixels[key] = max(self.nonfinite_pixels.get(key, 0), bad)
        return {key: np.stack([parts[c][key][..., c] for c in range(3)], axis=-1)
                for key in parts[0]}

    def _particles(self, key: str, spp: int, seed: int, depth: int,
                   air_segments: int) -> tuple[NDArray[np.float32], int]:
        """One particle-traced image of system S, through the water when it is modelled."""
        w = self.cfg.water_optics
        lens = self._lenses["pattern"]  # the sun's caustics reach camera s through it too
        if not w.enabled:
            return render_particles(self._scenes[key], spp, seed, depth, self._stratified,
                                    self._emitters.get(key), lens, self._geometry(key))
        a, b = coefficients_per_mm(w)
        direct, scattered, bad = render_particles_water(
            self._scenes[key], spp, seed, depth, a, b, air_segments, self._stratified,
            self._emitters.get(key), lens, self._geometry(key),
        )
        return direct + glow(scattered, w.forward_fraction, glow_sigma_px(self.cfg, "S")), bad

    def _pattern_in_daylight_water(self, spp: int, seed: int) -> tuple[NDArray[np.float32], int]:
        """Camera s's image with ``[water_optics]`` and / or ``[ambient]``: the pattern, the
        sun's caustics (their own particles, seeded apart) and the sky's constant light."""
        image, bad = self._particles("pattern", spp, seed, pattern_depth(self.cfg), 0)
        if self.cfg.ambient.enabled:
            if "pattern_sun" in self._scenes:
                sun_seed = (int(seed) + AMBIENT_SEED_OFFSET) % 2**32
                sun, bad_sun = self._particles(
                    "pattern_sun", self.cfg.ambient.sun_spp, sun_seed, SCENE_SUN_DEPTH, 1
                )
                # The particles' noise is no feature of the sunlight (a smooth caustic field).
                sun = smooth(sun, self.cfg.ambient.sun_smooth_px)
                image, bad = image + sun, bad + bad_sun
            image = image + sky_image(self.cfg)
        return image.astype(np.float32), bad


def channel_renderers(cfg: SystemConfig, grid: Heightfield, texture: NDArray | None,
                      systems: tuple[str, ...],
                      flat_only: bool = False) -> tuple[FrameRenderer, ...]:
    """Three renderers, one per colour channel with that channel's index of sea water, where
    ``index_model = "quan_fry"`` meets a rough surface or a housing port (each takes one
    index: 0.006 apart across the channels); none otherwise."""
    w = cfg.water
    if not ((w.roughness > 0 or cfg.rig.ported) and w.index_model == "quan_fry"):
        return ()
    return tuple(
        FrameRenderer(cfg.replace("water", index_model="constant", n_water=float(n)), grid,
                      texture, systems, flat_only=flat_only)
        for n in water_channel_indices(cfg)
    )


@dataclass(frozen=True)
class Rendered:
    """A render written: the folder, and the record it holds (``scene.json``'s, or a
    sequence's ``sequence.json``).

    Attributes
    ----------
    folder : Path
    record : dict
        Configuration, derived layout, seeds, variant, versions and ``timings_s`` per step (a
        sequence: its ``reference`` and each of its ``frames`` with ``render_s``).

    Examples
    --------
    >>> Rendered(Path("f1"), {"variant": "llvm_ad_rgb", "timings_s": {"a": 1.0, "b": 2.0}}).seconds
    3.0
    """

    folder: Path
    record: dict[str, Any]

    @property
    def variant(self) -> str:
        """The Mitsuba variant that rendered it."""
        return str(self.record["variant"])

    @property
    def seconds(self) -> float:
        """Wall time of the render, s: every step of a frame's, or the reference's and every
        frame's rendering of a sequence."""
        if "frames" in self.record:
            return float(self.record["reference"]["render_s"]
                         + sum(f["render_s"] for f in self.record["frames"]))
        return float(sum(self.record["timings_s"].values()))


class RenderSteps:
    """The skeleton of writing one render folder: a progress bar over its steps, each step's
    wall time, a pending interrupt raised between steps, the output location checked before the
    renders and the folder written atomically after them.

    Parameters
    ----------
    out_dir : path
        The render folder to create (the output policy of :mod:`wai_core.outputs`).
    steps : sequence of str
        The steps, in the order they run; the last is ``"write"`` (:meth:`write`).
    desc : str
        The progress bar's label.
    progress : bool
        Show the progress bar.
    overwrite : bool
        Replace an existing folder at ``out_dir`` that is not a previous render folder.

    Each step is a block, ``with steps("load scenes"): ...``; :meth:`write` is the last.
    """

    def __init__(self, out_dir: str | Path, steps: Sequence[str], desc: str, progress: bool,
                 overwrite: bool = False) -> None:
        from tqdm import tqdm

        self.out_dir = Path(out_dir)
        self.steps = tuple(steps)
        self.overwrite = overwrite
        self.timings = Timings()
        self._bar = tqdm(total=len(self.steps), desc=desc, disable=not progress, unit="step",
                         leave=False)
        self._bar.set_postfix_str(self.steps[0])

    def __enter__(self) -> RenderSteps:
        return self

    def __exit__(self, *exc: object) -> None:
        self._bar.close()

    @contextlib.contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        """Time the block as step ``name``; then raise a pending interrupt and advance the
        bar, whose label names the step now running."""
        with self.timings(name):
            yield
        raise_if_interrupted()
        following = self.steps.index(name) + 1
        self._bar.set_postfix_str(
            self.steps[following] if following < len(self.steps) else "done", refresh=False
        )
        self._bar.update(1)

    @property
    def timings_s(self) -> dict[str, float]:
        """Wall time of each step done so far, s."""
        return {name: ms / 1e3 for name, ms in self.timings.ms.items()}

    def check_output(self) -> None:
        """Refuse an output location that cannot or may not be written, before the renders."""
        check_output_dir(self.out_dir, OUTPUT_COMMAND, self.overwrite)

    def write(
        self,
        record: dict[str, Any],
        images: dict[str, NDArray],
        surface: Heightfield,
        nonfinite_pixels: dict[str, int],
        *,
        view_gain: float,
        sensor: SensorConfig | None = None,
    ) -> dict[str, Any]:
        """Step ``"write"``: the images (:func:`write_images`), the surface (:func:`write_surface`)
        and ``scene.json`` (``record`` with ``timings_s`` and ``nonfinite_pixels_zeroed``),
        into a folder that appears at ``out_dir`` when complete. Returns ``record``."""
        with atomic_dir(self.out_dir, command=OUTPUT_COMMAND, overwrite=self.overwrite) as tmp:
            with self("write"):
                write_images(tmp, images, view_gain=view_gain, sensor=sensor)
                write_surface(tmp, surface)
            record["timings_s"] = self.timings_s
            record["nonfinite_pixels_zeroed"] = nonfinite_pixels
            write_json(tmp / "scene.json", record)
        return record


def render_folder(
    cfg: SystemConfig,
    out_dir: str | Path,
    heightfield: Heightfield | None = None,
    progress: bool = True,
    *,
    overwrite: bool = False,
    surface_label: str | None = None,
) -> Rendered:
    """Render one frame of both systems (wavy and flat) and write the render folder atomically.

    Everything that can be checked is checked before the renders start: the surface against
    the rig (:func:`~wai_core.rig_checks.check_surface_in_rig`) and the output location (the
    output policy of :mod:`wai_core.outputs`).

    Parameters
    ----------
    cfg : SystemConfig
    out_dir : path
        Folder to create. An existing one is replaced (once everything is written) only if it
        is a previous render folder, unless ``overwrite``; a file there is always refused.
    heightfield : Heightfield, optional
        A surface to use instead of the wave model (``--heightfield``).
    progress : bool
        Show a progress bar over the render steps.
    overwrite : bool
        Replace an existing folder at ``out_dir`` that is not a previous render folder.
    surface_label : str, optional
        How errors about the surface name its origin (default ``heightfield`` for a given
        surface, ``[waves]`` for the wave model).

    Returns
    -------
    Rendered
        The folder and its ``scene.json`` record, with ``timings_s`` per step.

    Raises
    ------
    WaiInputError
        A surface outside the rig, an output location that cannot or may not be written.
    """
    steps = ("surface", "load scenes", "render wavy and flat", "write")
    with RenderSteps(out_dir, steps, "render", progress, overwrite) as run:
        label = surface_label or ("[waves]" if heightfield is None else "heightfield")
        with run("surface"):
            with labelled(label):
                if heightfield is None:
                    surface, source = wave_surface(cfg), "waves"
                else:
                    surface, source = file_surface(cfg, heightfield), "file"
            check_surface_in_rig(cfg, surface, label)
            # Only the wave model moves; the exposure's first and last surfaces are checked too.
            surface_at = moving_surface(cfg) if heightfield is None else None
            plan = subframe_plan(cfg) if surface_at is not None else None
            if plan is not None and plan.n > 1:
                for t in (plan.times_s[0], plan.times_s[-1]):
                    check_surface_in_rig(cfg, surface_at(t), label)
            run.check_output()
        with run("load scenes"):
            renderer = FrameRenderer(cfg, surface)
        with run("render wavy and flat"):
            cfg, images = render_frame_images(renderer, cfg, surface, render_seed(cfg),
                                              surface_at=surface_at, plan=plan)
        record = scene_record(cfg, renderer.variant, surface, source)
        record = run.write(record, images, surface, renderer.nonfinite_pixels,
                           view_gain=cfg.water.n_water**2, sensor=cfg.sensor)
    return Rendered(Path(out_dir), record)
