"""Each method's choices, with their defaults in one place per method.

:class:`SurfaceOptions` holds what both surface-sensing methods choose (integrator, passes,
gridding, the view's warp); :class:`StructuredLightOptions` adds the level and refinement of
the paper's method, :class:`AltermanOptions` the sun sensor's refinement tolerance,
:class:`SchlierenOptions` synthetic Schlieren's sampling and optical flow. An option
one method does not have cannot be given to it: the options refuse it when they are built.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any, TypeVar

from restoration.integrate import GRIDDERS, INTEGRATORS
from wai_core.errors import WaiInputError

__all__ = [
    "ANCHORS", "FLOW_QUALITIES", "INVERSE_BACKENDS", "INVERSE_STARTS", "AltermanOptions",
    "InverseRenderingOptions",
    "SchlierenOptions", "StructuredLightOptions", "SurfaceOptions", "checked_options",
]

OptionsT = TypeVar("OptionsT", bound="SurfaceOptions")

ANCHORS = ("integrability", "gauge")
"""How the absolute level is set: from the slopes' integrability, or the gauge's h0."""


@dataclass(frozen=True)
class SurfaceOptions:
    """The choices every surface-sensing method makes.

    Attributes
    ----------
    integrator : str
        A name in :data:`restoration.integrate.INTEGRATORS` (``fourth_order``, ``trapezoid``,
        ``paper``, ``spline``, ``frankot_chellappa``, ``dct_poisson``).
    n_refine : int
        Most refinement passes of the surface samples after the first pass (0: the samples
        stay on ``z = h0``, as published).
    gridder : str
        A name in :data:`restoration.integrate.GRIDDERS`.
    grid_spacing_mm : float
        Node spacing of the reconstructed heightfield, mm.
    warp_step_px : int
        Spacing of the reverse trace's solved nodes in camera v, px (pixels between are
        interpolated).
    """

    integrator: str = "fourth_order"
    n_refine: int = 8
    gridder: str = "tangent_blend"
    grid_spacing_mm: float = 2.0
    warp_step_px: int = 8

    def __post_init__(self) -> None:
        for name, value, known in (
            ("integrator", self.integrator, tuple(INTEGRATORS)),
            ("gridder", self.gridder, GRIDDERS),
        ):
            if value not in known:
                raise WaiInputError(f"unknown {name} {value!r} (known: {', '.join(known)})")
        if int(self.n_refine) != self.n_refine or self.n_refine < 0:
            raise WaiInputError(f"n_refine must be an integer >= 0, not {self.n_refine}")
        if not self.grid_spacing_mm > 0 or int(self.warp_step_px) < 1:
            raise WaiInputError("grid spacing must be > 0 mm and the warp step >= 1 px")

    @classmethod
    def from_choices(cls, **choices: Any) -> SurfaceOptions:
        """These options with the ``choices`` that are not None (a CLI's unset flags), the
        others at their defaults.

        Raises
        ------
        WaiInputError
            For a choice this method does not have (named, with the ones it has).

        Examples
        --------
        >>> from restoration import AltermanOptions
        >>> AltermanOptions.from_choices(n_refine=0, anchor=None).n_refine
        0
        >>> AltermanOptions.from_choices(anchor="integrability")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        wai_core.errors.WaiInputError: AltermanOptions has no option 'anchor' (its options: ...
        """
        known = {f.name for f in fields(cls)}
        given = {k: v for k, v in choices.items() if v is not None}
        unknown = sorted(set(given) - known)
        if unknown:
            raise WaiInputError(
                f"{cls.__name__} has no option {unknown[0]!r} (its options: "
                f"{', '.join(sorted(known))})"
            )
        return cls(**given)

    def to_dict(self) -> dict[str, Any]:
        """The options as plain values (what ``metrics.json`` records)."""
        return asdict(self)


@dataclass(frozen=True)
class StructuredLightOptions(SurfaceOptions):
    """The structured light's choices (defaults: the most accurate at real-time speed).

    ``integrator='paper'``, ``n_refine=0``, ``gridder='clough_tocher'`` and ``anchor='gauge'``
    is the paper's method as published (q_k on z = h0, central differences, bicubic-type
    interpolation, mean height = h0). ``anchor='integrability'`` finds the absolute height
    from the data instead (:mod:`restoration.anchor`); when the data do not pin it (standard
    error above ``anchor_max_sigma_mm``, e.g. over calm water) the gauge's h0 is used and the
    estimate says so (its anchor's method is ``gauge_fallback``).

    Attributes
    ----------
    integrator, n_refine, gridder, grid_spacing_mm, warp_step_px
        As :class:`SurfaceOptions`; the refinement passes move the reflection points along
        their projector rays and stop once a pass moves no height by more than
        ``refine_tol_mm``.
    refine_tol_mm : float
        The refinement's convergence, mm: an unconverged refinement biases the level search
        (docs/results.md, "Accuracy").
    anchor : str
        One of :data:`ANCHORS`.
    anchor_max_sigma_mm : float
        Largest standard error of the integrability level that is used, mm (beyond it, the
        gauge's h0).
    level_max_sigma_px : float
        Largest standard error of the integrability level of an ``ok`` frame, in camera-s
        pixels on the diffuser (the level's error in mm over
        :attr:`~restoration.calibration.Calibration.diffuser_mm_per_px`: 0.025 px is
        0.02 mm on the paper's rig); a frame whose level is less certain is
        ``uncertain_level`` (the level is still the data's).
    anchor_step_mm : float
        How far below its start the level search's first probe lies, mm
        (:func:`restoration.anchor.find_anchor`).
    converge_mm : float
        When the last of the ``n_refine`` passes still moves a height by more than this (mm),
        the fixed point has not converged (a diffuser close to the water contracts slowly)
        and the level search is run again with up to ``max_refine`` passes per probe.
    max_refine : int
        Most refinement passes of that second search (it stops earlier once converged).
    fit_spots : bool
        After the reconstruction, fit a smooth surface and its level to the detected spots
        through the exact reflection model (:func:`restoration.fit_level.fit_level`); slower than
        real time, so off by default (docs/results.md, "Accuracy").
    flat_referenced : bool
        Refer every spot to the flat reference, as the paper's dot shifts do: the spot less
        its dot's flat-water shift from the calibrated prediction
        (:func:`restoration.features.flat_shifts`). What displaces both images alike (the
        cameras' and the projector's calibration errors, the spots' centroid bias) then drops
        out, and the flat reference's level, the configuration's ``water.h0_mm``, becomes the
        datum: an error in it moves the level by about as much (docs/results.md, "Calibrating
        a real rig"). Off, the spots are taken as detected and the level comes from the data
        alone.
    spot_bias : bool or None
        Correct each spot for where its light's centre lies off its dot's centre ray on the
        estimated surface (Fresnel's reflectance across the dot, the water's microfacets, the
        surface's curvature; :mod:`restoration.spot_bias`; on rough water scaled by the share
        of the modelled shift the flat reference's spots show, the rest taken back by the
        neighbours' light: :meth:`restoration.Calibration.spot_bias_gain`) and estimate the
        surface again.
        None (the default): on where the scene's water is rough (``[water] roughness`` > 0:
        the microfacets move every spot along the projector's tilt, and the level the view
        or the slopes give follows them; 0.2-1.2 s a frame there, each dot's 32 facets
        traced), off on smooth water, where it takes about a third off the error but moves a
        few frames' levels the wrong way, for about 0.1 s a frame (docs/results.md, "Where a
        spot's light centre lies"). :meth:`spot_bias_for` says which for a scene.

    Examples
    --------
    >>> from restoration import StructuredLightOptions
    >>> StructuredLightOptions().integrator
    'fourth_order'
    >>> StructuredLightOptions(integrator="paper", n_refine=0, anchor="gauge").n_refine
    0
    """

    refine_tol_mm: float = 0.01
    anchor: str = "integrability"
    anchor_max_sigma_mm: float = 1.0
    level_max_sigma_px: float = 0.025
    anchor_step_mm: float = 3.0
    converge_mm: float = 1.0
    max_refine: int = 40
    fit_spots: bool = False
    flat_referenced: bool = True
    spot_bias: bool | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.anchor not in ANCHORS:
            raise WaiInputError(f"unknown anchor {self.anchor!r} (known: {', '.join(ANCHORS)})")
        if int(self.max_refine) < int(self.n_refine):
            raise WaiInputError(
                f"max_refine must be >= n_refine, not {self.max_refine} < {self.n_refine}"
            )
        if not self.level_max_sigma_px > 0:
            raise WaiInputError(
                f"level_max_sigma_px must be > 0, not {self.level_max_sigma_px}"
            )
        if not self.refine_tol_mm > 0:
            raise WaiInputError(f"refine_tol_mm must be > 0, not {self.refine_tol_mm}")
        if not self.anchor_step_mm > 0:
            raise WaiInputError(f"anchor_step_mm must be > 0, not {self.anchor_step_mm}")

    def spot_bias_for(self, cfg: Any) -> bool:
        """Whether the spots are corrected for their bias (:attr:`spot_bias`) in the scene
        ``cfg``: as set, or, where unset, where its water is rough.

        Examples
        --------
        >>> from dataclasses import replace
        >>> from wai_core import load_system
        >>> cfg = load_system("paper")
        >>> rough = replace(cfg, water=replace(cfg.water, roughness=0.01))
        >>> opts = StructuredLightOptions()
        >>> opts.spot_bias_for(cfg), opts.spot_bias_for(rough)
        (False, True)
        >>> StructuredLightOptions(spot_bias=False).spot_bias_for(rough)
        False
        """
        if self.spot_bias is not None:
            return bool(self.spot_bias)
        return float(cfg.water.roughness) > 0


@dataclass(frozen=True)
class AltermanOptions(SurfaceOptions):
    """The sun sensor's choices. Its normals do not depend on the height, so the level is
    always the gauge's: there is no anchor to choose.

    Attributes
    ----------
    integrator, n_refine, gridder, grid_spacing_mm, warp_step_px
        As :class:`SurfaceOptions`; the refinement moves each sample along its pinhole's
        refracted sunlight to the reconstructed height.
    refine_tol_mm : float
        Refinement stops once a pass changes no height by more than this, mm.

    Examples
    --------
    >>> from restoration import AltermanOptions
    >>> AltermanOptions().integrator, AltermanOptions(n_refine=0).n_refine
    ('fourth_order', 0)
    """

    refine_tol_mm: float = 1e-4

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.refine_tol_mm > 0:
            raise WaiInputError(f"refine_tol_mm must be > 0, not {self.refine_tol_mm}")


FLOW_QUALITIES = ("fine", "medium")
"""Values of :attr:`SchlierenOptions.flow`."""


@dataclass(frozen=True)
class SchlierenOptions(SurfaceOptions):
    """Synthetic Schlieren's choices (:mod:`restoration.schlieren`). Its slopes do not pin
    the level (a wrong level bends them into another, nearly integrable field): the level is
    the gauge's, or with ``schlieren-sl`` the structured light's or camera s's spots', so
    there is no anchor to choose.

    Attributes
    ----------
    integrator, n_refine, gridder, grid_spacing_mm, warp_step_px
        As :class:`SurfaceOptions`; the refinement moves each sample along its pixel's line
        of sight to the reconstructed height, where its slope is measured again.
    refine_tol_mm : float
        Refinement stops once a pass changes no height by more than this, mm.
    sample_step_px : int
        Pixels between the slope samples (a square lattice over camera v), px.
    flow : str
        The displacement's optical flow: ``fine`` (DIS at full resolution, small patches,
        more refinement: ~0.05 px on a speckle object) or ``medium`` (OpenCV's preset, ~4x
        faster, about twice the error).
    flow_check_px : float
        A sample is kept where the flow from the view to the flat-water view and back
        returns within this, px.
    max_residual_px : float
        The frame is ``inconsistent`` when the median of its samples' residual (where the
        surface sends each line of sight on the object against where the flow put it, in
        flat-water pixels) exceeds this, px.
    edge_margin_px : float
        A sample is kept where the flow puts it this far or more inside the flat view's
        textured part (from the image's border and from the pixels that do not see the
        object), px (0: anywhere).
    level_search_mm : float
        ``schlieren-sl`` where the structured light gives no level: the half-width of the
        search for the level camera s's spots show (:mod:`restoration.pattern_level`) about
        the gauge's h0, mm (0: the gauge's level, ``gauge_level``).

    Examples
    --------
    >>> from restoration import SchlierenOptions
    >>> SchlierenOptions().sample_step_px, SchlierenOptions(flow="medium").flow
    (8, 'medium')
    """

    n_refine: int = 12
    refine_tol_mm: float = 1e-3
    sample_step_px: int = 8
    flow: str = "fine"
    flow_check_px: float = 0.5
    max_residual_px: float = 0.25
    edge_margin_px: float = 32.0
    level_search_mm: float = 20.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.refine_tol_mm > 0:
            raise WaiInputError(f"refine_tol_mm must be > 0, not {self.refine_tol_mm}")
        if int(self.sample_step_px) != self.sample_step_px or self.sample_step_px < 1:
            raise WaiInputError(f"sample_step_px must be an integer >= 1, not "
                                f"{self.sample_step_px}")
        if self.flow not in FLOW_QUALITIES:
            raise WaiInputError(f"unknown flow {self.flow!r} (known: "
                                f"{', '.join(FLOW_QUALITIES)})")
        for name in ("flow_check_px", "max_residual_px"):
            if not getattr(self, name) > 0:
                raise WaiInputError(f"{name} must be > 0, not {getattr(self, name)}")
        for name in ("edge_margin_px", "level_search_mm"):
            if not getattr(self, name) >= 0:
                raise WaiInputError(f"{name} must be >= 0, not {getattr(self, name)}")


INVERSE_STARTS = ("structured-light", "structured-light-view", "schlieren-sl")
"""Values of :attr:`InverseRenderingOptions.start`."""
INVERSE_BACKENDS = ("auto", "drjit", "numpy")
"""Values of :attr:`InverseRenderingOptions.backend`."""


@dataclass(frozen=True)
class InverseRenderingOptions(StructuredLightOptions):
    """Inverse rendering's choices (:mod:`restoration.inverse_rendering`): the structured
    light's (its start) and the fit's.

    Attributes
    ----------
    blur_px : float
        The Gaussian blur of the model and the pattern image in the loss, px.
    passes : int
        Outer passes (each refits the dots' brightness first).
    iterations : int
        L-BFGS iterations per pass.
    quadrature_order : int
        Gauss-Hermite points per axis of each dot's Gaussian.
    facets : int
        Microfacet slopes per point on rough water.
    roughness : float or None
        The micro-roughness (GGX alpha) the model gives its particles' facets; None: the
        scene's ``[water] roughness``. Default 0, smooth particles: on rough renders the
        scene's facets bend the fitted shape (each modelled spot moves along the
        projector's tilt by about twice what a rough flat-water render shows),
        and smooth particles fit closer, at a fifth of the time (docs/results.md,
        "Inverse rendering").
    min_explained : float
        The frame is ``inconsistent`` when the median dot's share of its light the fit
        explains is below this.
    fresnel : bool
        Weight each particle by Fresnel's reflectance at its facet (the scene's index), taken
        on the surface at the start of each pass.
    start : str
        The surface the fit starts from and the level it keeps: ``"structured-light"`` (the
        paper's method) or ``"structured-light-view"`` (its level pinned by camera v's view of
        the object: :class:`~restoration.StructuredLightView`; needs the view's flat-water
        image, ``view_flat`` or a render's ``view_truth``), or ``"schlieren-sl"``: that
        start where it is ``ok``, else :class:`~restoration.SchlierenLevelled`'s surface
        (Schlieren at the level the structured light or camera s's spots give) and the dots
        its predicted spots label (Schlieren's default options).
    backend : str
        Where the fit's loss and gradient are evaluated: ``"drjit"`` (Dr.Jit's automatic
        adjoint, :mod:`restoration.pattern_jit`, on the CUDA device where there is one, else
        LLVM, its descents on one thread so that a rerun is the same fit bit for bit; camera
        s an ideal pinhole), ``"numpy"`` (the hand-written
        adjoint, any lens), ``"auto"`` (Dr.Jit where it models the rig, else NumPy).

    Examples
    --------
    >>> from restoration import InverseRenderingOptions
    >>> InverseRenderingOptions().blur_px, InverseRenderingOptions(roughness=0.01).roughness
    (1.5, 0.01)
    """

    blur_px: float = 1.5
    passes: int = 2
    iterations: int = 30
    quadrature_order: int = 4
    facets: int = 8
    roughness: float | None = 0.0
    min_explained: float = 0.5
    fresnel: bool = True
    start: str = "structured-light"
    backend: str = "auto"

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("passes", "iterations", "quadrature_order", "facets"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise WaiInputError(f"{name} must be an integer >= 1, not {value}")
        if not self.blur_px > 0:
            raise WaiInputError(f"blur_px must be > 0, not {self.blur_px}")
        if self.roughness is not None and not 0 <= self.roughness < 1:
            raise WaiInputError(f"roughness must be in [0, 1), not {self.roughness}")
        if not 0 <= self.min_explained < 1:
            raise WaiInputError(f"min_explained must be in [0, 1), not {self.min_explained}")
        if self.backend not in INVERSE_BACKENDS:
            raise WaiInputError(f"unknown backend {self.backend!r} (known: "
                                f"{', '.join(INVERSE_BACKENDS)})")
        if self.start not in INVERSE_STARTS:
            raise WaiInputError(f"unknown start {self.start!r} (known: "
                                f"{', '.join(INVERSE_STARTS)})")


def checked_options(method: str, cls: type[OptionsT], options: SurfaceOptions | None) -> OptionsT:
    """``options`` when they are ``cls`` (the options of ``method``), ``cls()`` when None.

    Raises
    ------
    WaiInputError
        For another method's options (they hold choices this method does not have).
    """
    if options is None:
        return cls()
    if not isinstance(options, cls):
        raise WaiInputError(
            f"{method}: options must be {cls.__name__}, not {type(options).__name__}"
        )
    return options
