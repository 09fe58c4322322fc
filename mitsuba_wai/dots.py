"""The projector's dots as an emitter sampled directly: each dot a stratified point set of its own.

Mitsuba's ``projector`` draws each particle's point on its irradiance image by inverting the
image's 2D distribution (a walk down a 1000 x 1000 mip hierarchy per particle), a quarter of the
pattern's render time. The image is a sum of Gaussian dots
(:func:`wai_core.pattern.pattern_image`), so the same emission can be drawn in two cheap steps:

1. The dot. Particle ``i`` of ``n`` takes the dot whose share ``p_j`` covers ``(i + u) / n``,
   ``u`` one random shift per pass (systematic sampling): every dot gets ``n p_j`` particles in
   expectation and within one of it in every pass. By default (``[render] particle_shares =
   "emitted"``) the share is the dot's emitted power ``w_j``. With ``"delivered"`` it is the
   power the dot delivers to
   the diffuser times its spot's size there, ``p_j ~ w_j R_j a_j`` (``w_j`` its brightness,
   :func:`wai_core.layout.dot_weights`; ``R_j`` the Fresnel reflectance at its flat-water
   incidence, 1 for the ``mirror``; ``a_j`` the spot's linear size on the diffuser per panel
   pixel), not its emitted power: the weights ``1 / R`` make a dot below the critical angle
   about 50 times brighter than one beyond it, though all reach the diffuser about equally
   bright, and the spots beyond it land obliquely, 1.6 times wider in camera s. A spot's
   centroid error grows with its width and shrinks with its particles, so this share gives
   every spot about the same centroid noise (beyond the critical angle 1.2 times the others'
   in the paper's flat-water pattern at 4 spp, against 21 times with ``p_j ~ w_j``), but the
   particles taken from the others double their noise, and the restored surface is less
   accurate over ten seeds (docs/results.md, "Particles where they are needed").
2. The point. The dot's ``m``-th particle takes the ``m``-th point of a shifted R2 sequence
   (:func:`mitsuba_wai.particles.kronecker`; a shift of its own per dot, so no two dots share
   a point set and its small centroid error), mapped to the Gaussian by Box-Muller.

The ray leaves the projector's centre through that panel point (and starts at the diffuser
plane, see :attr:`DotEmitter.skipped_vertices`), as
:meth:`wai_core.geometry.PinholeCamera.pixel_rays` maps it (the projector shares the pinhole
mapping of Mitsuba's perspective camera), and carries the projector's weight (Mitsuba's
``projector.cpp``: irradiance x scale x pi x image area at z = 1, over the sample's density),
for a dot of colour ``c_j``: its emitted flux over its share of the particles,
``c_j * w_j / p_j * 2 pi sigma^2 / (W H) * scale * pi * A``, the same for all of a dot's
particles. Unbiased, because the shifts are uniform and every dot's expected count times its
weight is its flux.

With ``[projector] aperture_mm`` > 0 the projector is a thin lens of that diameter, in focus at
``z_cam = focus_mm``: a particle's ray starts at a point uniform on the lens disk (centred on
the projector's centre, perpendicular to its axis; a further shifted Kronecker pair, its own
shift per dot, mapped to the disk concentrically) and passes where its panel point's pinhole ray
meets the plane in focus, so a spot at distance ``z`` blurs by a disk of diameter
``aperture |z - focus| / focus``. The weights stay those of the pinhole (the lens moves light,
it makes none); with the aperture 0 nothing of this runs.

With ``[projector]`` ``principal_offset_px``, ``distortion`` or a port
(``port_thickness_mm``), the panel point is measured from the principal point and is the
distorted image point: its ray is the undistorted one's, through the port
(:class:`mitsuba_wai.lens.CameraLens`), the particle's weight times the port's transmittance.

It differs from the bitmap only by what the raster leaves out (the bilinear interpolation
between pixel centres, the tails cut at the panel's edge): the same flux and spots to the
tolerance of ``tests/mitsuba_wai/test_particles.py``. The coded pattern's dots are drawn in
proportion to their share alone, whatever their colour, so a blue dot gets as many particles
as a green one.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mitsuba_wai.lens import CameraLens, lens_keys
from mitsuba_wai.particles import kronecker
from mitsuba_wai.variant import mitsuba
from wai_core.config import SystemConfig
from wai_core.geometry import fresnel_reflectance, intersect_plane_z, reflect
from wai_core.pattern import dot_colours

__all__ = ["DotEmitter"]

# Rays start this far (mm) above the diffuser plane, clear of its surface at float32 precision.
_PAST_MM = 1e-3

# The lens sample's two coordinates, 2^32 / phi_4^3 and 2^32 / phi_4^4 (mod 2^32; phi_4 the
# positive root of x^5 = x + 1): the last two of Roberts' 4D sequence, whose steps are
# rationally independent of the R2 pair's, so the four coordinates fill the 4D cube evenly.
_LENS_KRONECKER = (2700274806, 2313257605)


def _lens_kronecker(index: Any, k: int, shift: Any) -> Any:
    """Coordinate ``k`` (0, 1) of the lens sample: ``frac(index alpha_k + shift / 2^32)`` as
    :func:`mitsuba_wai.particles.kronecker`, float32 in [0, 1), (n,)."""
    mi = mitsuba()
    bits = index * mi.UInt32(_LENS_KRONECKER[k]) + shift
    return mi.Float(bits >> 8) * (1.0 / 2**24)


class DotEmitter:
    """System S's projector as its dots: configured once per scene, called per pass.

    Parameters
    ----------
    cfg : SystemConfig
        The configuration whose ``[pattern]`` and ``[projector]`` the scene's ``projector``
        emitter was built from (:func:`mitsuba_wai.scenes.pattern_scene`).

    Attributes
    ----------
    n_dots : int
        Lit dots (the others are never drawn).
    share : (n_dots,) ndarray
        Each lit dot's expected fraction of the particles (sums to 1).
    skipped_vertices : int
        Path vertices the rays start past (1: the diffuser's pass-through), which the particle
        tracer counts towards its ``max_depth``.
    camera_unoccluded : bool
        True: nothing can block a path vertex's connection to camera s in system S, so the
        particle tracer casts no shadow rays.

    Examples
    --------
    >>> from mitsuba_wai.variant import select_variant
    >>> from wai_core import load_system
    >>> _ = select_variant()
    >>> emitter = DotEmitter(load_system("paper"))
    >>> emitter.n_dots > 100
    True
    """

    def __init__(self, cfg: SystemConfig) -> None:

        mi = mitsuba()
        projector = cfg.rig.projector
        panel_px = cfg.rig.dot_panel_px
        weights = cfg.rig.dot_weights
        colours = dot_colours(cfg.pattern, projector)
        lit = weights > 0
        panel_px, weights, colours = panel_px[lit], weights[lit], colours[lit]
        self.n_dots = int(lit.sum())
        sigma = cfg.pattern.sigma_px
        w, h = projector.width_px, projector.height_px
        tan_x = np.tan(np.radians(projector.fov_x_deg) / 2.0)
        area = 4.0 * tan_x**2 * h / w  # the panel's area on the plane z_cam = 1
        # Each dot's share of the particles, and a particle's weight: its dot's flux over its
        # share (by emitted power the same for every particle of a colour, multiplied in the
        # order that keeps the default renders' bits).
        if cfg.render.particle_shares == "delivered":
            share = weights * _flat_reflectance(cfg, projector, panel_px)
            share = share * _spot_size(cfg, projector, panel_px)
            self.share = share / share.sum()
            self._cdf = np.concatenate([[0.0], np.cumsum(self.share)])
            unit = 2.0 * np.pi * sigma**2 / (w * h) * cfg.pattern.power * np.pi * area
            flux = colours * (unit * weights / self.share)[:, None]
        else:
            self.share = weights / weights.sum()
            self._cdf = np.concatenate([[0.0], np.cumsum(weights) / weights.sum()])
            flux = colours * (weights.sum() * 2.0 * np.pi * sigma**2 / (w * h)
                              * cfg.pattern.power * np.pi * area)
        # Panel coordinates of each dot relative to the principal point, in focal lengths
        # (distorted ones with [projector] distortion; mitsuba_wai.lens: offset, port).
        f = projector.focal_px
        optics = cfg.rig.optics("projector")
        self._optics = (CameraLens(optics, cfg.water.n_water) if lens_keys(cfg.projector)
                        else None)
        centre = (panel_px - list(optics.principal_px)) / f
        self._centre = mi.Point2f(*(mi.Float(centre[:, k]) for k in range(2)))
        self._colour = mi.Color3f(*(mi.Float(flux[:, k]) for k in range(3)))
        self._sigma = sigma / f
        self._origin = mi.Point3f(*projector.pose.center_lab_mm.tolist())
        self._axes = [mi.Vector3f(*row.tolist()) for row in projector.pose.R]  # cam axes, lab
        self._lens_radius = cfg.projector.aperture_mm / 2.0  # mm; 0: the pinhole
        self._focus = cfg.projector.focus_mm
        # The rays start just past the diffuser plane, which lies between the projector and
        # the water (a checked rule of the configuration): its pass-through from below changes
        # nothing (weight 1, a delta vertex that connects to no camera), so the particle
        # tracer skips that vertex's intersection and counts it towards ``max_depth``.
        self._start_z = float(cfg.diffuser.z_mm) + _PAST_MM
        self.skipped_vertices = 1
        # Below the diffuser lies nothing but camera s, and the water stays above the diffuser
        # (the rig checks refuse other surfaces): a connection to the camera cannot be blocked,
        # so the tracer skips the shadow rays (about a tenth of the pattern's time). A rough
        # water surface ([water].roughness) is not a delta BSDF: the diffuser must block its
        # own connections to the camera, so those need the shadow rays.
        self.camera_unoccluded = cfg.water.roughness == 0

    def __call__(self, time: float, n: int, seed: int) -> tuple[Any, Any]:
        """Rays and weights of ``n`` particles, the point sets shifted by ``seed``.

        Parameters
        ----------
        time : float
            The rays' time.
        n : int
            Particles, >= 1.
        seed : int
            Seed of the shifts (the same seed, the same particles).

        Returns
        -------
        ray : mitsuba.Ray3f, (n,)
            From the projector's centre (lab, mm; with an aperture, the particle's point on the
            lens) through the sampled panel point (or its point in focus), starting just past
            the diffuser plane.
        weight : mitsuba.Color3f, (n,)
            The particle's power, as Mitsuba's ``Scene.sample_emitter_ray`` returns it.
        travelled_mm : mitsuba.Float, (n,)
            Distance from the projector (its lens point) to the ray's origin, mm (in the water).
        """
        import drjit as dr

        mi = mitsuba()
        rng = np.random.default_rng([int(seed), 0xD075])
        # First particle of each dot (and n after the last): dot j owns [first_j, first_j+1).
        first = np.clip(np.ceil(n * self._cdf - rng.random()), 0, n).astype(np.uint32)
        first[-1] = n
        shifts = rng.integers(0, 2**32, (2, self.n_dots), dtype=np.uint64).astype(np.uint32)
        # Arrays, not literals: the compiled kernel is the same for every seed and pass.
        first_dr = mi.UInt32(first)
        index = dr.arange(mi.UInt32, n)
        # Each particle's dot: how many dots after the first start at or before it (one mark
        # per start, summed along the particles): the last dot whose range begins there, as a
        # binary search over `first` finds it, at a third of its cost.
        starts = mi.UInt32(first[1:-1])
        marks = dr.zeros(mi.UInt32, n)
        dr.scatter_add(marks, mi.UInt32(1), starts, starts < n)
        dot = dr.cumsum(marks)
        local = index - dr.gather(mi.UInt32, first_dr, dot)
        u = [kronecker(local, k, dr.gather(mi.UInt32, mi.UInt32(shifts[k]), dot)) for k in (0, 1)]
        offset = mi.warp.square_to_std_normal(mi.Point2f(*u)) * self._sigma
        xy = dr.gather(mi.Point2f, self._centre, dot) + offset
        lens = None
        if self._lens_radius > 0:  # drawn after the pinhole's shifts, which stay as they are
            lens_shifts = rng.integers(0, 2**32, (2, self.n_dots), dtype=np.uint64)
            lens = mi.Point2f(*(_lens_kronecker(local, k, dr.gather(
                mi.UInt32, mi.UInt32(lens_shifts[k].astype(np.uint32)), dot)) for k in (0, 1)))
        origin, d, passed = self._ray(xy, lens)
        travelled = (self._start_z - origin.z) / d.z
        ray = mi.Ray3f(origin + d * travelled, d)
        ray.time = time
        weight = dr.gather(mi.Color3f, self._colour, dot)
        if self._optics is not None:
            weight = weight * passed
        return ray, weight, travelled

    def _ray(self, xy: Any, lens: Any) -> tuple[Any, Any]:
        """Origin and direction of the rays through panel points ``xy``: the ray construction.

        Parameters
        ----------
        xy : mitsuba.Point2f, (n,)
            Panel points relative to the principal point, in focal lengths (``cam`` frame
            ``x / z``, ``y / z``).
        lens : mitsuba.Point2f (n,) or None
            Points in [0, 1)^2 mapped onto the lens disk; None: the pinhole.

        Returns
        -------
        origin : mitsuba.Point3f, (n,)
            The projector's centre, or the particle's point on the lens disk (lab, mm); with a
            port, the ray's exit point from it into the water.
        direction : mitsuba.Vector3f, (n,)
            Unit direction (in the water), lab.
        passed : mitsuba.Float or float
            Share of the flux that leaves: the port's transmittance (0 beyond the distortion's
            fold), 1 without lens keys.
        """
        import drjit as dr

        mi = mitsuba()
        origin = self._origin
        passed = 1.0
        if self._optics is not None and self._optics.optics.distorted:
            # The panel point is the distorted image point; its ray is the undistorted one's.
            x, y, ok = self._optics.undistort(xy.x, xy.y)
            xy, passed = mi.Point2f(x, y), dr.select(ok, 1.0, 0.0)
        disk = None
        if lens is not None:
            # Thin lens: from the lens point to where the pinhole ray meets the plane in focus,
            # z_cam = f: direction (f x - a, f y - b, f) for lens point (a, b, 0), cam frame.
            disk = mi.warp.square_to_uniform_disk_concentric(lens) * self._lens_radius
            origin = origin + self._axes[0] * disk.x + self._axes[1] * disk.y
            xy = xy - disk / self._focus
        if self._optics is not None and self._optics.optics.has_port:
            origin, d, transmitted = self._optics.port_ray(disk, (xy.x, xy.y))
            return origin, d, passed * transmitted
        d = dr.normalize(self._axes[0] * xy.x + self._axes[1] * xy.y + self._axes[2])
        return origin, d, passed


def _flat_reflectance(cfg: SystemConfig, projector: Any, panel_px: np.ndarray) -> np.ndarray:
    """Fresnel reflectance (K,) of the dots' chief rays at flat water (1 for the ``mirror``).

    Parameters
    ----------
    cfg : SystemConfig
    projector : wai_core.geometry.PinholeCamera
    panel_px : (K, 2) ndarray
        The dots' centres on the panel, pixels.

    Returns
    -------
    (K,) ndarray
        In (0, 1]; 1 beyond the critical angle.
    """
    if cfg.water.surface == "mirror":
        return np.ones(panel_px.shape[0])
    _, d = projector.pixel_rays(panel_px[:, 0], panel_px[:, 1])
    return fresnel_reflectance(d[:, 2], cfg.water.n_water)


def _spot_size(cfg: SystemConfig, projector: Any, panel_px: np.ndarray) -> np.ndarray:
    """Linear size (K,) of the dots' flat-water spots on the diffuser, mm per panel pixel.

    ``sqrt |det J|`` of the map from the panel (pixels) to the diffuser plane (lab x, y, mm)
    through the flat water's mirror reflection, by central differences of half a pixel.
    """
    def diffuser_xy(px: np.ndarray) -> np.ndarray:
        o, d = projector.pixel_rays(px[:, 0], px[:, 1])
        q, _ = intersect_plane_z(o, d, cfg.water.h0_mm)
        s, _ = intersect_plane_z(q, reflect(d, np.array([0.0, 0.0, 1.0])), cfg.diffuser.z_mm)
        return s[:, :2]

    step = np.array([[0.5, 0.0], [0.0, 0.5]])
    jac = np.stack([diffuser_xy(panel_px + e) - diffuser_xy(panel_px - e) for e in step], 2)
    size = np.sqrt(np.abs(np.linalg.det(jac)))
    return np.where(np.isfinite(size) & (size > 0), size, np.nanmedian(size))
