"""Render Alterman's sun-and-pinhole sensor (:mod:`wai_core.alterman`) and write its folder.

Scene (system A)
----------------
The sun, the water surface, the opaque pinhole plate, the screen and camera a. Sunlight reaches
camera a only through a specular refraction from a delta direction, which a camera-side tracer
can never connect, so the scene is rendered with ``ptracer`` (as the structured light):
sun -> water (``water_interface``, ``refract``) -> hole -> screen -> camera, ``max_depth = 3``.
In the particle tracer's importance transport the interface weighs a crossing by ``1 - F`` only
(no ``eta^2``: that radiance factor belongs to camera-side transport), as Mitsuba's
``dielectric`` does; tests compare the two.

- **Sun.** A ``directionalarea`` emitter (light along one direction from a surface), placed
  above the highest crest allowed (``h0 + depth``), in one of two beams (``[render] beam``):

  ``full``: one rectangle covering every sun ray that can reach a hole. Any light through a
  hole crossed the surface within the refraction cone (critical angle) above it, between the
  plate and the crest limit; the rest of the sunlight could only land on the opaque plate.
  Exact, but ~1 % of its photons pass a hole.

  ``holes`` (default): per frame, a small patch around each hole's chief ray (the sunlight
  that passes the hole's centre through *this* surface, :func:`wai_core.alterman.chief_rays`),
  twice the hole across and 1.2 times its beam along the plane of incidence, all the same size
  so the emitter's area (and the photons' weight) stays fixed. A hole's light comes from a
  patch of surface ~1 hole wide (the waves are ~100x longer), so the patches hold every ray
  that reaches the screen: the same image as ``full`` (tests compare them) at ~20x the photons
  per spot. A surface whose beams would not fit, or whose patches would overlap (which would
  double the light), is refused with a pointer to ``full``.
- **Water.** The same sea as the structured-light render, sampled on a grid that covers the
  beam at every height it crosses, so no sunlight enters the water through the side of the mesh
  (it would reach the holes unrefracted).
- **Plate.** A mesh built in numpy: the rectilinear grid whose lines are the holes' edges, with
  the hole cells left out. Black ``diffuse``: light that hits it is absorbed.
- **Screen.** The one-way diffuser (:mod:`mitsuba_wai.bsdfs`): diffuse transmission of light
  from above towards camera a below.
- **Overcast.** With the sun off there is no emitter and the image is black: skylight is not
  modelled (through a pinhole it would be a disc of Snell's window ~2 gap wide, wider than the
  pitch: no usable spot either).

Folder
------
``sunspots.exr`` / ``sunspots_flat.exr`` (camera a, wavy / flat water), ``view.exr`` /
``view_truth.exr`` (camera v, exactly as ``wai render``), ``heightfield.npz``, ``surface.ply``
and ``scene.json`` (base configuration, the sensor's configuration and derived layout, seeds,
variant), each image with a PNG preview; written atomically.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from numpy.typing import NDArray

from mitsuba_wai import mesh as meshes
from mitsuba_wai.render import FrameRenderer, Rendered, RenderSteps, render_image
from mitsuba_wai.scene_record import render_seed, scene_record
from mitsuba_wai.scenes import rectangle_to_world, sensor_dict, sun_frame, water_bsdf
from mitsuba_wai.surface_sampling import file_surface, labelled, wave_surface
from mitsuba_wai.variant import mitsuba, select_variant
from wai_core.alterman import (
    AltermanSystem,
    ChiefRays,
    SensorLayout,
    chief_rays,
    layout_record,
    sensor_layout,
    sun_is_up,
)
from wai_core.errors import WaiInputError
from wai_core.geometry import critical_angle_rad
from wai_core.heightfield import Heightfield, grid_faces
from wai_core.layout import surface_extent
from wai_core.rig_checks import check_surface_in_rig

SCENE_A_DEPTH = 3
# Margin (mm) between the top of the sun's emitting rectangle and the highest crest allowed.
_EMITTER_CLEARANCE_MM = 10.0


# ----------------------------------------------------------------------------------------------
# Geometry of the render (beyond the calibration)
# ----------------------------------------------------------------------------------------------


def crest_limit_mm(system: AltermanSystem) -> float:
    """Highest surface the sun beam is laid out for: ``h0 + depth`` (crests as high as the
    troughs may be deep), mm."""
    return system.base.water.h0_mm + system.sensor.plate.depth_mm


def hole_region(layout: SensorLayout, top_mm: float) -> NDArray:
    """Where light that passes a hole can have crossed a surface below ``top_mm``:
    ``[[x0, x1], [y0, y1]]`` mm, the holes grown by the refraction cone at that height."""
    cone = (top_mm - layout.plate_z_mm) * np.tan(critical_angle_rad(layout.n_water))
    p = layout.pinholes_mm[:, :2]
    grow = cone + layout.hole_mm
    return np.stack([p.min(axis=0) - grow, p.max(axis=0) + grow], axis=1)


def _box_corners(rect: NDArray, z_lo: float, z_hi: float) -> NDArray:
    """The 8 corners (8, 3) of ``rect`` x ``[z_lo, z_hi]``, mm."""
    x, y, z = np.meshgrid(rect[0], rect[1], [z_lo, z_hi], indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)


def water_extent(system: AltermanSystem, layout: SensorLayout) -> NDArray:
    """Extent (mm) of the water to model: the structured-light extent and every point where a
    beam ray is between the plate and the crest limit (so all of them meet the mesh's top)."""
    top = crest_limit_mm(system)
    corners = _box_corners(hole_region(layout, top), layout.plate_z_mm, top)
    # Shift each corner along the sun to the other end of the height range.
    d = layout.sun_dir
    span = (top - layout.plate_z_mm) / -d[2]
    pts = np.concatenate([corners, corners - span * d, corners + span * d])[:, :2]
    beam = np.stack([pts.min(axis=0), pts.max(axis=0)], axis=1)
    ext = surface_extent(system.base)
    margin = 2.0 * layout.pitch_mm
    return np.stack([np.minimum(ext[:, 0], beam[:, 0] - margin),
                     np.maximum(ext[:, 1], beam[:, 1] + margin)], axis=1)


def _emitter_plane(system: AltermanSystem, layout: SensorLayout) -> tuple[NDArray, NDArray]:
    """Bounds ``[[a0, a1], [b0, b1]]`` (sun frame) of every sun ray that crosses the hole region
    between the plate and the crest limit, and the distance ``w_e`` of an emitting plane
    perpendicular to the sun that lies wholly above that limit, mm."""
    top = crest_limit_mm(system)
    a, b, w = sun_frame(layout.sun_dir)
    corners = _box_corners(hole_region(layout, top), layout.plate_z_mm, top)
    ua, ub, uw = corners @ a, corners @ b, corners @ w
    bounds = np.array([[ua.min(), ua.max()], [ub.min(), ub.max()]])
    # Height of a point (ua, ub, w_e) is ua a_z + w_e w_z (b is horizontal): the lowest corner
    # must clear the crest limit, and the plane must lie beyond every corner of the box.
    z_min_a = min(bounds[0, 0] * a[2], bounds[0, 1] * a[2])
    w_e = max((top + _EMITTER_CLEARANCE_MM - z_min_a) / w[2], uw.max() + 1.0)
    return bounds, np.array(w_e)


def full_beam_to_world(system: AltermanSystem, layout: SensorLayout) -> NDArray:
    """4x4 ``to_world`` of the ``full`` beam's rectangle: perpendicular to the sun, normal along
    the light's travel, covering every sun ray that can reach a hole."""
    a, b, w = sun_frame(layout.sun_dir)
    bounds, w_e = _emitter_plane(system, layout)
    centre = bounds[0].mean() * a + bounds[1].mean() * b + w_e * w
    half = (bounds[:, 1] - bounds[:, 0]) / 2
    m = np.eye(4)
    # Columns (b, a, -w): right-handed (b x a = -w), so the rectangle's normal is the travel
    # direction, along which directionalarea emits.
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = half[1] * b, half[0] * a, -w, centre
    return m


def patch_half_mm(system: AltermanSystem, layout: SensorLayout) -> NDArray:
    """Half sizes ``(along a, along b)`` (mm) of each hole's emitting patch in the ``holes`` beam.

    A hole's light in air is a beam as wide as the hole across the plane of incidence and
    ``hole cos(theta_i) / cos(theta_t)`` along it. Across, the patch is twice the hole. Along,
    it is 1.2 times the beam for a surface tilted 12 deg towards the sun (beyond the paper's
    slopes, 0.18 rad): at low suns neighbouring holes' beams are only ``pitch cos(theta_sun)``
    minus the height step between them apart, so a wide patch would overlap its neighbour.
    """
    hole, pitch = layout.hole_mm, layout.pitch_mm
    th = np.radians(system.sensor.sun.zenith_deg)
    th_i = max(th - np.radians(12.0), 0.0)
    cos_t = np.sqrt(1.0 - (np.sin(th_i) / layout.n_water) ** 2)
    along = 1.2 * (hole / 2.0) * np.cos(th_i) / cos_t
    return np.array([min(along, 0.4 * pitch * np.cos(th)), min(hole, 0.4 * pitch)])


def hole_preimages(layout: SensorLayout, rays: ChiefRays) -> tuple[NDArray, NDArray]:
    """Sun-frame ``(a, b)`` of each hole's chief ray (K, 2) and of its corners' rays (K, 4, 2):
    each corner carried back along the refracted chief direction to the tangent plane of the
    surface at the chief ray's crossing (the beam is parallel and the surface flat across a
    hole), mm."""
    a, b, _ = sun_frame(layout.sun_dir)
    half = layout.hole_mm / 2.0
    offsets = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]])
    c = layout.pinholes_mm[:, None, :] + offsets
    q, n, t = (v[:, None, :] for v in (rays.surface_mm, rays.normals, rays.water_dirs))
    lam = np.sum(n * (q - c), axis=-1) / np.sum(n * t, axis=-1)
    pts = c + lam[..., None] * t
    frame = np.stack([a, b], axis=1)
    return rays.surface_mm @ frame, pts @ frame


def _neighbour_pairs(ij: NDArray) -> tuple[NDArray, NDArray]:
    """Index pairs of grid neighbours (4- and diagonal) among full-grid indices ``ij`` (K, 2)."""
    shape = ij.max(axis=0) + 1
    grid = np.full((shape[1], shape[0]), -1)
    grid[ij[:, 1], ij[:, 0]] = np.arange(len(ij))
    pairs = [
        (grid[: shape[1] - dj, max(-di, 0) : shape[0] - max(di, 0)],
         grid[dj:, max(di, 0) : shape[0] + min(di, 0)])
        for di, dj in ((1, 0), (0, 1), (1, 1), (-1, 1))
    ]
    first = np.concatenate([p[0].ravel() for p in pairs])
    second = np.concatenate([p[1].ravel() for p in pairs])
    ok = (first >= 0) & (second >= 0)
    return first[ok], second[ok]


def hole_beam_vertices(
    system: AltermanSystem, layout: SensorLayout, rays: ChiefRays
) -> NDArray:
    """Vertices (4 K, 3) of the ``holes`` beam's patches, mm: one rectangle per hole in the
    emitting plane, centred on the hole's chief ray.

    Raises
    ------
    WaiInputError
        If a hole's beam does not fit its patch or two patches overlap (waves too steep for
        this beam: use ``beam = "full"``).
    """
    a, b, w = sun_frame(layout.sun_dir)
    _, w_e = _emitter_plane(system, layout)
    half = patch_half_mm(system, layout)
    centre, corners = hole_preimages(layout, rays)
    if not rays.ok.all() or np.any(np.abs(corners - centre[:, None, :]) > 0.97 * half):
        raise WaiInputError("a hole's sun beam does not fit its emitting patch: use beam = full")
    i, k = _neighbour_pairs(layout.ij)
    gap = np.abs(centre[i] - centre[k]) - 2.0 * half
    if np.any((gap < 0).all(axis=1)):
        raise WaiInputError("the holes' sun patches overlap: use [render] beam = full")
    signs = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    ab = centre[:, None, :] + signs * half
    return (ab[..., :1] * a + ab[..., 1:] * b + w_e * w).reshape(-1, 3)


def hole_beam_faces(n_holes: int) -> NDArray:
    """Two triangles per patch, wound so that their normal is the sun's travel direction."""
    base = 4 * np.arange(n_holes)[:, None]
    return np.concatenate([base + [0, 2, 1], base + [0, 3, 2]])


def plate_mesh(layout: SensorLayout) -> trimesh.Trimesh:
    """The opaque plate: a rectilinear grid whose lines are the holes' edges (and the plate's
    border), with the cells inside holes removed; faces wound counter-clockwise from above."""
    half = layout.hole_mm / 2.0
    cx = np.unique(layout.pinholes_mm[layout.ij[:, 1] == 0, 0])
    cy = np.unique(layout.pinholes_mm[layout.ij[:, 0] == 0, 1])
    rect = layout.plate_rect_mm
    xs = np.unique(np.concatenate([rect[0], cx - half, cx + half]))
    ys = np.unique(np.concatenate([rect[1], cy - half, cy + half]))
    xx, yy = np.meshgrid(xs, ys)
    vertices = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, layout.plate_z_mm)], axis=1)
    mid_x, mid_y = (xs[1:] + xs[:-1]) / 2, (ys[1:] + ys[:-1]) / 2
    in_x = np.abs(mid_x[None, :] - cx[:, None]).min(axis=0) < half
    in_y = np.abs(mid_y[None, :] - cy[:, None]).min(axis=0) < half
    hole = (in_y[:, None] & in_x[None, :]).ravel()
    faces = grid_faces(ys.size, xs.size)
    # grid_faces lists all cells' first triangles, then all second triangles.
    keep = np.tile(~hole, 2)
    return trimesh.Trimesh(vertices=vertices, faces=faces[keep], process=False)


# ----------------------------------------------------------------------------------------------
# Scene and renderer
# ----------------------------------------------------------------------------------------------


def sun_scene(system: AltermanSystem, layout: SensorLayout, water_mesh: object) -> dict:
    """System A: sun (if up), water, plate, screen, camera a (see the module notes)."""

    from mitsuba_wai.bsdfs import register

    register()
    plate = plate_mesh(layout)
    screen = layout.screen_rect_mm
    centre = np.array([screen[0].mean(), screen[1].mean(), layout.screen_z_mm])
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "ptracer", "max_depth": SCENE_A_DEPTH, "hide_emitters": True},
        # Box filter: splats land in one pixel, so spot centroids stay unbiased.
        "sensor": sensor_dict(layout.camera, rfilter="box"),
        "water": water_mesh,
        "plate": meshes.to_mitsuba(
            plate, "plate", {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}}
        ),
        "screen": {
            "type": "rectangle",
            "to_world": rectangle_to_world(centre, screen[:, 1] - screen[:, 0], facing_down=False),
            "bsdf": {"type": "oneway_diffuser"},
        },
    }
    if sun_is_up(system.sensor.sun):
        scene["sun"] = sun_emitter(system, layout)
    return scene


def sun_emitter(system: AltermanSystem, layout: SensorLayout) -> object:
    """The sun as a ``directionalarea`` emitter on the ``full`` beam's rectangle or on the
    ``holes`` beam's patches (placed for flat water; :class:`SunRenderer` moves them)."""
    import mitsuba as mi

    emitter = {
        "type": "directionalarea",
        "radiance": {"type": "rgb", "value": system.sensor.sun.irradiance},
    }
    if system.sensor.render.beam == "full":
        to_world = mi.ScalarTransform4f(full_beam_to_world(system, layout).tolist())
        return {"type": "rectangle", "to_world": to_world, "emitter": emitter}
    flat = chief_rays(layout, flat_surface(layout))
    patches = trimesh.Trimesh(
        vertices=hole_beam_vertices(system, layout, flat),
        faces=hole_beam_faces(len(layout.ij)),
        process=False,
    )
    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}}
    return meshes.to_mitsuba(patches, "sun", black, emitter=emitter)


def flat_surface(layout: SensorLayout) -> Heightfield:
    """Flat water at h0 over the samples (the reference the restoration calibrates with)."""
    lo = layout.samples_mm[:, :2].min(axis=0) - 2 * layout.pitch_mm
    hi = layout.samples_mm[:, :2].max(axis=0) + 2 * layout.pitch_mm
    x, y = np.linspace(lo[0], hi[0], 5), np.linspace(lo[1], hi[1], 5)
    return Heightfield(x, y, np.full((5, 5), layout.h0_mm))


def check_surface(system: AltermanSystem, layout: SensorLayout, surface: Heightfield) -> None:
    """Reject a surface that reaches the plate or rises above the crest limit of the beam."""
    z = surface.z[np.isfinite(surface.z)]
    if z.min() <= layout.plate_z_mm + layout.hole_mm:
        raise WaiInputError(
            f"the surface dips to z = {z.min():.1f} mm, onto the pinhole plate at "
            f"{layout.plate_z_mm:.1f} mm: increase [plate].depth_mm"
        )
    if z.max() > crest_limit_mm(system):
        raise WaiInputError(
            f"the surface rises to z = {z.max():.1f} mm, above h0 + [plate].depth_mm = "
            f"{crest_limit_mm(system):.1f} mm that the sun beam covers: increase depth_mm"
        )


@dataclass
class SunRenderer:
    """The loaded scene of system A whose water surface is swapped per frame (as
    :class:`~mitsuba_wai.render.FrameRenderer`); the grid is fixed by the first surface."""

    system: AltermanSystem
    grid: Heightfield
    layout: SensorLayout = field(init=False)
    variant: str = field(init=False)
    nonfinite_pixels: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        self.variant = select_variant()
        mi = mitsuba()
        self.layout = sensor_layout(self.system)
        water = meshes.to_mitsuba(
            meshes.heightfield_mesh(self.grid), "water", water_bsdf(self.system.base, "A")
        )
        self._scene = mi.load_dict(sun_scene(self.system, self.layout, water))
        self._params = mi.traverse(self._scene)

    def render(self, surface: Heightfield, seed: int) -> NDArray[np.float32]:
        """Camera a's image (H, W, 3) of the screen, sunlight through ``surface``."""
        mi = mitsuba()
        if surface.z.shape != self.grid.z.shape:
            raise ValueError("surface grid differs from the renderer's mesh grid")
        check_surface(self.system, self.layout, surface)
        meshes.set_mesh_geometry(self._params, meshes.heightfield_mesh(surface), prefix="water.")
        if "sun.vertex_positions" in self._params:
            # The holes beam follows this surface's chief rays (same patch sizes, same area).
            rays = chief_rays(self.layout, surface)
            vertices = hole_beam_vertices(self.system, self.layout, rays)
            self._params["sun.vertex_positions"] = mi.Float(vertices.astype(np.float32).ravel())
            self._params.update()
        # The deterministic particle tracer: the same seed gives the same image, bit for bit.
        img, bad = render_image(self._scene, self.system.sensor.render.spp, seed, SCENE_A_DEPTH)
        self.nonfinite_pixels += bad
        return img


def alterman_surface(system: AltermanSystem, heightfield: Heightfield | None) -> Heightfield:
    """The true surface on the grid system A needs: the wave model or a given surface."""
    extent = water_extent(system, sensor_layout(system))
    if heightfield is None:
        return wave_surface(system.base, extent)
    return file_surface(system.base, heightfield, extent)


def alterman_record(
    system: AltermanSystem, renderer: SunRenderer, surface: Heightfield, source: str
) -> dict[str, Any]:
    """``scene.json`` of a system-A folder: the base record (configuration, camera v) plus the
    sensor's configuration and derived layout."""
    record = scene_record(system.base, renderer.variant, surface, source)
    layout = renderer.layout
    record["format"] = "wai-render-alterman/1"
    record["method"] = "alterman"
    record["alterman"] = system.sensor.to_dict()
    record["derived"]["alterman"] = {
        **layout_record(layout),
        "water_extent_mm": water_extent(system, layout),
        "crest_limit_mm": crest_limit_mm(system),
        "sun_up": sun_is_up(system.sensor.sun),
    }
    record["integrators"] = {
        "sunspots": {"type": "ptracer", "max_depth": SCENE_A_DEPTH,
                     "spp": system.sensor.render.spp},
        "view": record["integrators"]["view"],
    }
    return record


def render_alterman_folder(
    system: AltermanSystem,
    out_dir: str | Path,
    heightfield: Heightfield | None = None,
    views: dict[str, NDArray] | None = None,
    renderer: SunRenderer | None = None,
    progress: bool = True,
    *,
    overwrite: bool = False,
    surface_label: str | None = None,
) -> Rendered:
    """Render one frame of system A (wavy and flat) and camera v's view; write the folder.

    The surface (against the base rig and the sensor) and the output location are checked
    before anything is rendered, as in :func:`~mitsuba_wai.render.render_folder`.

    Parameters
    ----------
    system : AltermanSystem
    out_dir : path
        Folder to create. An existing one is replaced (once everything is written) only if it
        is a previous render folder, unless ``overwrite``; a file there is always refused.
    heightfield : Heightfield, optional
        A surface to use instead of the wave model.
    views : dict, optional
        ``view`` and ``view_truth`` (H, W, 3) already rendered for this surface and seed (by
        ``wai render`` of the base scene); rendered here when absent.
    renderer : SunRenderer, optional
        A loaded renderer of this system (sweeps reuse it); its grid must match the surface's.
    progress : bool
        Show a progress bar over the steps.
    overwrite : bool
        Replace an existing folder at ``out_dir`` that is not a previous render folder.
    surface_label : str, optional
        How errors about the surface name its origin (default ``heightfield`` or ``[waves]``).

    Returns
    -------
    Rendered
        The folder and its ``scene.json`` record, with ``timings_s`` per step.
    """
    steps = ("surface and scene", "render sun", "render view", "write")
    with RenderSteps(out_dir, steps, "render A", progress, overwrite) as run:
        label = surface_label or ("[waves]" if heightfield is None else "heightfield")
        with run("surface and scene"):
            with labelled(label):
                surface = alterman_surface(system, heightfield)
            source = "waves" if heightfield is None else "file"
            check_surface_in_rig(system.base, surface, label)
            try:
                check_surface(system, sensor_layout(system), surface)
            except WaiInputError as exc:
                raise WaiInputError(f"{label}: {exc}") from None
            run.check_output()
            renderer = renderer if renderer is not None else SunRenderer(system, surface)
            zeroed_before = renderer.nonfinite_pixels
        seed = render_seed(system.base)
        flat = meshes.flat_like(surface, system.base.water.h0_mm)
        with run("render sun"):
            images = {
                "sunspots": renderer.render(surface, seed),
                "sunspots_flat": renderer.render(flat, seed),
            }
        with run("render view"):
            if views is None:
                frame = FrameRenderer(system.base, surface, systems=("view",))
                views = {
                    "view": frame.render(surface, seed, which=("view",))["view"],
                    "view_truth": frame.render(flat, seed, which=("view",),
                                               crosstalk=False)["view"],
                }
            images.update({k: views[k] for k in ("view", "view_truth")})
        record = alterman_record(system, renderer, surface, source)
        zeroed = {"sunspots": renderer.nonfinite_pixels - zeroed_before}
        record = run.write(record, images, surface, zeroed,
                           view_gain=system.base.water.n_water**2)
    return Rendered(Path(out_dir), record)
