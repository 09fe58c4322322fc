"""Inverse rendering: the structured light's surface refitted to camera s's whole pattern image.

The structured light reduces each spot to a centre and each centre to a normal; where the spots
blur (rough water, a blurred diffuser or projector) their centres are biased while their light
is still where the surface sent it. This method fits the surface to the image itself: the
pattern model (:mod:`restoration.pattern_model`: every dot's particles through a B-spline
surface into camera s, with the microfacets of the water's roughness) is compared with the
captured pattern and the spline's coefficients are moved down the loss's exact gradient:

    minimise  1/2 |W (M(c) - I)|^2 / |W (I - mean I)|^2  +  lambda/2 |L c|^2

``I`` the pattern image, ``M(c)`` the model blurred by ``blur_px`` (its dots' brightness and
the background by linear least squares before each pass), ``W`` the pixels near the model's
particles (the light of dots the fit does not model stays out), ``L`` second differences of the
coefficients (the smoothness where no particle lands). L-BFGS within each pass, the image
term's loss and gradient on Dr.Jit (:mod:`restoration.pattern_jit`) where camera s is an ideal
pinhole, else the NumPy model's hand-written adjoint (``InverseRenderingOptions.backend``).

It starts from the structured light's surface and fits the dots the structured light matched
(from flat water, the periodic pattern's local minima hold the fit once spots move by more than
half their spacing: measured, docs/results.md). The level stays near the start's: raising
the surface and bending it back moves every spot by microns, so the image hardly determines it.
Where the structured light (at the view's level) is not ``ok``, the start ``"schlieren-sl"``
takes Schlieren's surface at the level the structured light or camera s's spots give
(:class:`~restoration.SchlierenLevelled`): every dot's spot is predicted through it, a dot whose
prediction lands clearly on one detected spot takes it (the labels the structured light could
not give), and the detected spots of the others are left out of the loss.

The truth-free status: the share of each dot's light the fit explains (the residual's energy
against the image's contrast in a window about the dot's spot); the frame is ``inconsistent``
when the median dot's share is below ``min_explained``; a start that is not ``ok`` passes its
status on.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter
from scipy.optimize import minimize
from scipy.spatial import cKDTree

from restoration.calibration import Calibration, LevelTrack
from restoration.features import detect_spots
from restoration.features.camera_s import pinhole_spots
from restoration.fit import SMOOTHNESS as FIT_SMOOTHNESS
from restoration.fit import BSplineSurface, knot_step, spline_through
from restoration.options import InverseRenderingOptions, StructuredLightOptions
from restoration.pattern_level import dot_crossings_mm, dots_on_spots, predicted_spots_px
from restoration.pattern_model import DotParticles, PatternModel, Raster, Traced
from restoration.result import RestoreResult, Status
from restoration.schlieren_level import SchlierenLevelled
from restoration.structured_light import StructuredLight
from restoration.view_level import StructuredLightView
from wai_core.errors import WaiInputError
from wai_core.optics import pattern_index
from wai_core.timings import Timings

__all__ = ["METHOD", "MIN_DOTS", "SCHLIEREN_START", "PatternFit", "fit_pattern",
           "refit_schlieren", "refit_to_pattern", "restore_inverse_rendering"]

Array = NDArray[np.float64]

SMOOTHNESS = 1e-6
"""Weight of the coefficients' second differences in the loss (whose image term is normalised
by the image's contrast energy)."""


@dataclass
class PatternFit:
    """The surface fitted to the pattern image, and how the fit went.

    Attributes
    ----------
    spline : BSplineSurface
        The fitted surface (absolute heights, mm).
    amplitudes : (K,) ndarray
        Each dot's fitted brightness.
    background : float
        The fitted background.
    explained : (K,) ndarray
        Each dot's share of its light the fit explains (NaN: its spot left the image).
    loss : list of float
        The loss after each pass.
    iterations : int
        Loss evaluations.
    curve : list of float
        The loss after each L-BFGS iteration, the passes in turn (the first entry: at the
        start, once the dots' brightness is fitted).
    traced : Traced
        The particles through the final surface.
    timings_ms : dict of str to float
        ``fit`` (the passes), ``descent`` (their L-BFGS descents), ``explained``, ``total``
        (ms) and ``ms_per_evaluation`` (the descents' time over their loss evaluations).
    """

    spline: BSplineSurface
    amplitudes: Array
    background: float
    explained: Array
    loss: list[float]
    iterations: int
    traced: Traced
    curve: list[float] = field(default_factory=list)
    timings_ms: dict[str, float] = field(default_factory=dict)


class _Objective:
    """The loss and its gradient in the coefficients (the brightness held)."""

    def __init__(self, model: PatternModel, raster: Raster, observed: Array, shape: tuple,
                 t: Array, smoothness: float) -> None:
        self.model, self.raster, self.observed = model, raster, observed
        self.shape = shape
        self.mask = np.ones_like(observed)
        self.norm = 1.0
        self.t = t
        self.amplitudes = np.ones(model.particles.n_dots)
        self.light = model.particles.weight  # each particle's share of its dot's light
        self.background = 0.0
        self.smoothness = smoothness
        self.calls = 0

    def spline(self, like: BSplineSurface, c: Array) -> BSplineSurface:
        return BSplineSurface(like.x0_mm, like.y0_mm, like.step_mm, c.reshape(self.shape))

    def _second(self, c: Array) -> tuple[float, Array]:
        z = c.reshape(self.shape)
        dxx = z[:, 2:] - 2 * z[:, 1:-1] + z[:, :-2]
        dyy = z[2:] - 2 * z[1:-1] + z[:-2]
        g = np.zeros_like(z)
        g[:, 2:] += dxx
        g[:, 1:-1] -= 2 * dxx
        g[:, :-2] += dxx
        g[2:] += dyy
        g[1:-1] -= 2 * dyy
        g[:-2] += dyy
        s = self.smoothness
        return 0.5 * s * float(np.sum(dxx**2) + np.sum(dyy**2)), s * g.ravel()

    def set_mask(self, traced: Traced, reach_px: float, unmodelled_px: Array | None = None
                 ) -> None:
        """Score only the pixels within ``reach_px`` (full-resolution px) of a particle, and
        nearer to a particle than to any spot of ``unmodelled_px`` (U, 2), the detected spots
        of dots the fit does not model: their light stays out of its loss."""
        h, w = self.raster.shape
        yy, xx = np.mgrid[0:h, 0:w]
        centres = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
        dist = cKDTree(traced.px[traced.ok]).query(centres, distance_upper_bound=reach_px)[0]
        near = dist < reach_px
        if unmodelled_px is not None and len(unmodelled_px):
            other = cKDTree(unmodelled_px).query(centres[near],
                                                 distance_upper_bound=reach_px)[0]
            near[np.flatnonzero(near)[other < dist[near]]] = False
        self.mask = near.reshape(h, w).astype(float)
        obs = self.observed[self.mask > 0]
        self.norm = float(np.sum((obs - obs.mean()) ** 2)) if obs.size else 1.0
        self.norm = self.norm or 1.0

    def weights(self, traced: Traced) -> Array:
        p = self.model.particles
        return np.where(traced.ok, self.amplitudes[p.dot] * self.light, 0.0)

    def image(self, traced: Traced) -> Array:
        r = self.raster
        return r.blur(r.splat(traced.px, self.weights(traced), traced.ok)) + self.background

    def __call__(self, c: Array, like: BSplineSurface) -> tuple[float, Array]:
        self.calls += 1
        traced = self.model.trace(self.spline(like, c), self.t)
        self.t = np.where(np.isfinite(traced.t), traced.t, self.t)
        res = (self.image(traced) - self.observed) * self.mask
        loss = 0.5 * float(np.sum(res**2)) / self.norm
        _, grad_px = self.raster.sample(self.raster.blur(res) / self.norm, traced.px)
        grad_px *= self.weights(traced)[:, None]
        contrib = np.einsum("pa,pak->pk", grad_px, traced.jacobian)
        grad = np.bincount(traced.index.ravel(), contrib.ravel(), minlength=c.size)
        reg, reg_grad = self._second(c)
        return loss + reg, grad + reg_grad

    def fit_amplitudes(self, traced: Traced, iterations: int = 25) -> None:
        """Dots' brightness and the background by least squares (conjugate gradients on the
        normal equations, from the current values), clipped at zero."""
        p, r = self.model.particles, self.raster
        ok = traced.ok
        k = p.n_dots

        def forward(x: Array) -> Array:
            w = np.where(ok, x[p.dot] * self.light, 0.0)
            return r.blur(r.splat(traced.px, w, ok)) + x[k]

        def adjoint(img: Array) -> Array:
            img = img * self.mask
            v, _ = r.sample(r.blur(img), traced.px)
            out = np.bincount(p.dot, np.where(ok, v * self.light, 0.0), minlength=k)
            return np.r_[out, img.sum()]

        x = np.r_[self.amplitudes, self.background]
        resid = adjoint(self.observed - forward(x))
        # Jacobi preconditioner: a dot's own overlap, its spots spread over one blur.
        diag = np.r_[np.full(k, 1.0 / (4 * np.pi * r.sigma_px**2)), self.observed.size]
        z = resid / diag
        d = z.copy()
        rz = float(resid @ z)
        for _ in range(iterations):
            ad = adjoint(forward(d))
            alpha = rz / float(d @ ad)
            x += alpha * d
            resid -= alpha * ad
            z = resid / diag
            rz_new = float(resid @ z)
            if rz_new < 1e-12 * max(rz, 1e-300):
                break
            d = z + (rz_new / rz) * d
            rz = rz_new
        self.amplitudes = np.maximum(x[:k], 0.0)
        self.background = float(x[k])


def _explained(obj: _Objective, traced: Traced, window_px: float) -> Array:
    """Each dot's share of its light the fit explains: 1 - (residual energy) / (the image's
    contrast energy), both in a Gaussian window of ``window_px`` about the dot's particles."""
    p, r = obj.model.particles, obj.raster
    res = (obj.image(traced) - obj.observed) * obj.mask
    contrast = (obj.observed - obj.background) * obj.mask
    e_res = gaussian_filter(res**2, window_px)
    e_img = gaussian_filter(contrast**2, window_px)
    v_res, _ = r.sample(e_res, traced.px)
    v_img, _ = r.sample(e_img, traced.px)
    ok = traced.ok
    n = np.bincount(p.dot, ok.astype(float), minlength=p.n_dots)
    s_res = np.bincount(p.dot, np.where(ok, v_res, 0.0), minlength=p.n_dots)
    s_img = np.bincount(p.dot, np.where(ok, v_img, 0.0), minlength=p.n_dots)
    with np.errstate(invalid="ignore", divide="ignore"):
        share = 1.0 - s_res / s_img
    return np.where(n > 0.5 * np.bincount(p.dot, minlength=p.n_dots), share, np.nan)


def fit_pattern(image: Array, start: BSplineSurface, model: PatternModel, *,
                blur_px: float = 1.5, passes: int = 2, iterations: int = 30,
                smoothness: float = SMOOTHNESS, window_px: float = 6.0,
                reach_px: float = 8.0, n_water: float | None = None,
                backend: str = "numpy", unmodelled_px: Array | None = None) -> PatternFit:
    """Fit the spline ``start`` to the pattern ``image`` (H, W) through ``model``.

    Parameters
    ----------
    image : (H, W) ndarray
        Camera s's pattern image (its channels summed), linear values.
    start : BSplineSurface
        The start (absolute heights, mm); its knots are kept.
    model : PatternModel
        The dots to fit and their particles.
    blur_px : float
        The Gaussian blur of model and image, px.
    passes, iterations : int
        Outer passes (each refits the brightness first) and L-BFGS iterations per pass.
    smoothness : float
        Weight of the coefficients' second differences.
    window_px : float
        Width of each dot's window in :attr:`PatternFit.explained`, px.
    reach_px : float
        Pixels within this of a particle are scored, px.
    n_water : float, optional
        The water's index: each particle's light weighted by Fresnel's reflectance at its
        facet, taken on the surface at the start of each pass
        (:meth:`~restoration.pattern_model.PatternModel.reflectance`); None: the dot's
        Gaussian alone.
    backend : str
        Where the loss and its gradient are evaluated: ``"numpy"`` (the hand-written
        adjoint) or a Dr.Jit backend of :func:`restoration.pattern_jit.jit_module`
        (``"llvm"``, ``"cuda"``, ``"auto"``; camera s an ideal pinhole).
    unmodelled_px : (U, 2) ndarray, optional
        Detected spots (image px) of dots ``model`` leaves out: the pixels nearer to one of
        them than to a particle are not scored.

    Returns
    -------
    PatternFit
    """
    timings = Timings()
    raster = Raster(model.shape, blur_px)
    t = model.flat_t(float(np.mean(start.coeffs)))
    spline = start
    obj = _Objective(model, raster, np.asarray(image, float), start.coeffs.shape, t,
                     smoothness)
    losses: list[float] = []
    curve: list[float] = []
    descent_calls = 0

    def step(intermediate_result: Any) -> None:
        curve.append(float(intermediate_result.fun))

    with timings("fit"):
        for _ in range(int(passes)):
            traced = model.trace(spline, obj.t)
            if n_water is not None:
                obj.light = model.reflectance(spline, traced, n_water)
            obj.set_mask(traced, reach_px, unmodelled_px)
            obj.fit_amplitudes(traced)
            fun = obj if backend == "numpy" else _JitObjective(obj, spline, backend)
            before = obj.calls

            def evaluate(c: Array, like: BSplineSurface, fun: Any = fun) -> tuple[float, Array]:
                value = fun(c, like)
                if not curve:  # L-BFGS evaluates its start first: the curve's first entry
                    curve.append(float(value[0]))
                return value

            with timings("descent"), nullcontext() if fun is obj else fun.loss.in_order():
                res = minimize(evaluate, spline.coeffs.ravel(), args=(spline,), jac=True,
                               method="L-BFGS-B", options={"maxiter": int(iterations)},
                               callback=step)
            descent_calls += obj.calls - before
            if fun is not obj:
                obj.t = fun.loss.t
            spline = obj.spline(spline, res.x)
            losses.append(float(res.fun))
    with timings("explained"):
        traced = model.trace(spline, obj.t)
        explained = _explained(obj, traced, window_px)
    timings.add("total", timings.total("fit", "explained"))
    timings.add("ms_per_evaluation", timings.total("descent") / max(descent_calls, 1))
    return PatternFit(spline, obj.amplitudes, obj.background, explained, losses, obj.calls,
                      traced, curve=curve, timings_ms=timings.to_dict())


class _JitObjective:
    """:class:`_Objective`'s loss and gradient for one pass, its image term on Dr.Jit
    (:class:`restoration.pattern_jit.JitImageLoss`; the brightness, the mask and each
    particle's light held as the pass set them)."""

    def __init__(self, obj: _Objective, like: BSplineSurface, backend: str) -> None:
        from restoration.pattern_jit import JitImageLoss

        p = obj.model.particles
        self.obj = obj
        self.loss = JitImageLoss(obj.model, obj.raster, like, obj.observed, obj.mask, obj.norm,
                                 obj.amplitudes[p.dot] * obj.light, obj.background, obj.t,
                                 backend)

    def __call__(self, c: Array, like: BSplineSurface) -> tuple[float, Array]:
        self.obj.calls += 1
        loss, grad = self.loss(c)
        reg, reg_grad = self.obj._second(c)
        return loss + reg, grad + reg_grad


METHOD = "inverse-rendering"
"""The method's name; started at the view's level, ``inverse-rendering-view``; falling back on
Schlieren's surface, ``inverse-rendering-schlieren``."""

SCHLIEREN_START = "schlieren-sl"
"""The start that falls back on :class:`~restoration.SchlierenLevelled`'s surface where the
structured light at the view's level is not ``ok``."""

_NAMES = {StructuredLight.name: METHOD, StructuredLightView.name: f"{METHOD}-view",
          SCHLIEREN_START: f"{METHOD}-schlieren"}


def _method(options: InverseRenderingOptions) -> str:
    """The result's method name for ``options``' start."""
    return _NAMES[options.start]


def restore_inverse_rendering(
    images: dict[str, NDArray],
    cal: Calibration,
    options: InverseRenderingOptions | None = None,
    track: LevelTrack | None = None,
) -> RestoreResult:
    """Run the method on loaded images (``pattern``, ``pattern_flat``, ``view``; and
    ``view_flat`` for the start ``"schlieren-sl"``).

    Returns a :class:`~restoration.result.RestoreResult`: the start's when it gives no
    surface (its status and reason); otherwise the refitted surface (on the start's grid and
    support), the view restored through it, and the status (module notes). ``counts`` gains
    ``dots_fitted`` and ``loss_evaluations``, ``timings_ms`` ``image_fit``, the surface's
    anchor ``image_fit_explained`` (the median dot's share), ``image_fit_loss`` (after each
    pass), ``image_fit_evaluations`` and ``image_fit_start`` (the method whose surface the
    fit started from).

    Examples
    --------
    >>> from restoration import Calibration                              # doctest: +SKIP
    >>> cal = Calibration.from_folder("renders/demo")                    # doctest: +SKIP
    >>> restore_inverse_rendering(cal.load_images("renders/demo"), cal).status  # doctest: +SKIP
    <Status.OK: 'ok'>
    """
    options = InverseRenderingOptions() if options is None else options
    if options.start == StructuredLight.name:
        return refit_to_pattern(StructuredLight(_start_options(options))(images, cal, track),
                                images, cal, options)
    light = StructuredLightView(_start_options(options))(images, cal, track)
    if options.start == StructuredLightView.name or light.status == Status.OK:
        return refit_to_pattern(light, images, cal, options)
    return refit_schlieren(SchlierenLevelled().from_light(images, cal, light), images, cal,
                           options)


def refit_to_pattern(start: RestoreResult, images: dict[str, NDArray], cal: Calibration,
                     options: InverseRenderingOptions | None = None) -> RestoreResult:
    """The surface of ``start`` (a structured light's result on ``images``) refitted to the
    pattern image, the dots it labelled: :func:`restore_inverse_rendering` after its start."""
    options = InverseRenderingOptions() if options is None else options
    if start.surface is None:
        return replace(start, method=_method(options))
    surface = start.surface
    timings = Timings()
    with timings("image_fit"):
        xy = surface.points_mm[:, :2]
        spline = spline_through(xy, surface.points_mm[:, 2], surface.slopes, knot_step(xy),
                                FIT_SMOOTHNESS)
    return _refit(start, images, cal, options, cal.cfg.rig.dot_index(surface.ij), spline,
                  timings)


def refit_schlieren(start: RestoreResult, images: dict[str, NDArray], cal: Calibration,
                    options: InverseRenderingOptions | None = None) -> RestoreResult:
    """The surface of ``start`` (:class:`~restoration.SchlierenLevelled`'s result on
    ``images``, whose samples are camera v's lines of sight, not dots) refitted to the
    pattern image: the dots labelled where their spots, predicted through that surface at
    its level, land clearly nearest one detected spot
    (:func:`~restoration.pattern_level.dots_on_spots`); the other detected spots' light is
    left out of the loss. Its status is ``start``'s, and ``inconsistent`` where the fit
    explains too little (as :func:`refit_to_pattern`'s) or no dot could be labelled."""
    options = InverseRenderingOptions() if options is None else options
    if start.surface is None:
        return replace(start, method=_method(options))
    surface = start.surface
    timings = Timings()
    with timings("image_fit"):  # the labels and the start's spline: the fit's time
        reference = cal.prepare(images["pattern_flat"])
        spots = pinhole_spots(detect_spots(images["pattern"], scales=reference.spot_scales),
                              cal.cfg)
        level = float(np.mean(surface.points_mm[:, 2]))
        predicted = (predicted_spots_px(surface.heightfield, level, cal)
                     + reference.flat_shift_at(cal.cfg.rig.dot_ij))
        dots, found = dots_on_spots(predicted, spots.centres_px, reference.median_spacing_px)
    if len(dots) < MIN_DOTS:  # the start as it was, not ok where it said ok
        status, message = start.status, start.message
        if status == Status.OK:
            status = Status.INCONSISTENT
            message = (f"the surface sends {len(dots)} dots clearly onto a spot (fewest "
                       f"{MIN_DOTS})")
        return replace(start, method=_method(options), status=status, message=message,
                       timings_ms=_with_fit_time(start, timings))
    with timings("image_fit"):
        crossing = dot_crossings_mm(level, cal)[2][dots]
        spline = spline_through(surface.points_mm[:, :2], surface.points_mm[:, 2],
                                surface.slopes, knot_step(crossing[:, :2]), FIT_SMOOTHNESS)
    unmodelled = np.delete(spots.in_image_px, found, axis=0)
    return _refit(start, images, cal, options, dots, spline, timings, unmodelled)


MIN_DOTS = 20
"""Fewest dots a fit from Schlieren's surface needs labelled."""


def _refit(start: RestoreResult, images: dict[str, NDArray], cal: Calibration,
           options: InverseRenderingOptions, dots: NDArray, spline: BSplineSurface,
           timings: Timings, unmodelled_px: Array | None = None) -> RestoreResult:
    """``start``'s surface, as ``spline``, refitted to the pattern image through the dots
    ``dots`` (indices of the rig's), ``unmodelled_px`` the detected spots of none of them;
    ``timings`` holds the ``image_fit`` time spent before (the start's spline)."""
    surface = start.surface
    with timings("image_fit"):
        rig = cal.cfg.rig
        roughness = (float(cal.cfg.water.roughness) if options.roughness is None
                     else float(options.roughness))
        particles = DotParticles.of(rig, rig.dot_panel_px[dots], options.quadrature_order,
                                    roughness, options.facets)
        pattern = _gray(images["pattern"])
        model = PatternModel(rig, particles, pattern.shape)
        backend = _backend(options.backend, rig)
        fit = fit_pattern(pattern, spline, model, blur_px=options.blur_px,
                          passes=options.passes, iterations=options.iterations,
                          n_water=pattern_index(cal.cfg) if options.fresnel else None,
                          backend=backend, unmodelled_px=unmodelled_px)
        xy = surface.points_mm[:, :2]
        z, zx, zy = fit.spline.evaluate(xy[:, 0], xy[:, 1])[:3]
        keep = np.isfinite(z)
        points = np.column_stack([xy, np.where(keep, z, surface.points_mm[:, 2])])
        slopes = np.where(keep[:, None], np.column_stack([zx, zy]), surface.slopes)
        heightfield = fit.spline.to_heightfield(surface.heightfield)
        refit = surface.refitted(heightfield, points, slopes,
                                 image_fit=fit.timings_ms["total"])
    with timings("reverse_trace"):
        view = cal.restore_view(images["view"], heightfield, options.warp_step_px,
                                gain=cal.view_gain)
    explained = float(np.nanmedian(fit.explained)) if np.isfinite(fit.explained).any() else 0.0
    refit.anchor.update(image_fit_explained=explained, image_fit_loss=fit.loss,
                        image_fit_evaluations=fit.iterations, image_fit_curve=fit.curve,
                        image_fit_backend=backend, image_fit_start=start.method,
                        image_fit_ms_per_evaluation=fit.timings_ms["ms_per_evaluation"])
    status, message = start.status, start.message
    if status == Status.OK and explained < options.min_explained:
        status = Status.INCONSISTENT
        message = (f"the fit explains {explained:.0%} of the median dot's light (threshold "
                   f"{options.min_explained:.0%})")
    counts = {**start.counts, "dots_fitted": int(particles.n_dots),
              "loss_evaluations": int(fit.iterations)}
    return replace(start, method=_method(options), status=status, message=message, surface=refit,
                   view=view, timings_ms=_with_fit_time(start, timings), counts=counts,
                   consistency=None)


def _with_fit_time(start: RestoreResult, timings: Timings) -> dict[str, float]:
    """``start``'s times with the fit's steps of ``timings`` (``image_fit``, and
    ``reverse_trace`` where it ran) and ``image_fit`` added to ``end_to_end``, ms."""
    times = {**start.timings_ms, **timings.to_dict()}
    times["end_to_end"] = start.timings_ms.get("end_to_end", 0.0) + times["image_fit"]
    return times


def _backend(choice: str, rig: Any) -> str:
    """The fit's backend for ``choice`` (:attr:`InverseRenderingOptions.backend`) on ``rig``:
    Dr.Jit's (``"cuda"`` where a CUDA device is present, else ``"llvm"``) where camera s is an
    ideal pinhole and ``choice`` is not ``"numpy"``; ``"numpy"`` otherwise.

    Raises
    ------
    WaiInputError
        For ``"drjit"`` on a rig whose camera s has a lens model or a port.
    """
    from restoration.pattern_jit import jit_module, usable

    if choice == "numpy":
        return "numpy"
    if usable(rig):
        return jit_module("auto").__name__.split(".")[1]
    if choice == "drjit":
        raise WaiInputError("inverse rendering's backend 'drjit' models camera s as an ideal "
                            "pinhole; this rig's has a lens model or a port (backend 'auto' "
                            "or 'numpy')")
    return "numpy"


def _gray(image: NDArray) -> Array:
    """A pattern image as one channel (its channels summed), float."""
    image = np.asarray(image, float)
    return image[..., :3].sum(axis=2) if image.ndim == 3 else image


def _start_options(options: InverseRenderingOptions) -> StructuredLightOptions:
    """The structured light's own options among ``options``."""
    names = {f.name for f in fields(StructuredLightOptions)}
    return StructuredLightOptions(**{k: v for k, v in asdict(options).items() if k in names})
