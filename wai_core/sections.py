"""The sections of a system configuration, each a frozen dataclass with its keys' defaults
(:mod:`wai_core.config` reads, checks and assembles them into a
:class:`~wai_core.config.SystemConfig`)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class WaterConfig:
    """Mean water level (mm), refractive index and the surface's material."""

    h0_mm: float = 150.0
    n_water: float = 4.0 / 3.0
    """The index the geometric model (the restoration) uses; the render's too, unless
    ``index_model`` gives it per wavelength."""
    surface: str = "dielectric"
    index_model: str = "constant"
    """Renderer only. ``"constant"``: ``n_water`` at every wavelength; ``"quan_fry"``: sea
    water's index per colour channel from Quan & Fry (1995) at ``salinity_psu`` and
    ``temperature_c`` (dispersion), while the restoration keeps ``n_water``."""
    salinity_psu: float = 35.0
    temperature_c: float = 20.0
    roughness: float = 0.0
    """Renderer only. Micro-roughness of the surface below the mesh's scale: the GGX alpha
    of Mitsuba's ``roughdielectric`` (0: a smooth interface)."""


@dataclass(frozen=True)
class WavesConfig:
    """Longuet-Higgins sea state (eq. 38-43)."""

    wind_speed_m_s: float = 1.0
    """U at 19.5 m (eq. 42), m/s; the paper's Fig. 10 has 1."""
    time_s: float = 10.0
    seed: int = 0
    wind_direction_deg: float = 0.0
    """Mean wave direction, degrees from +x towards +y."""
    n_frequencies: int = 64
    """M in eq. 38."""
    n_directions: int = 24
    """N in eq. 38."""
    omega_min_rel: float = 0.5
    """Lowest frequency summed, in units of the Pierson-Moskowitz peak frequency."""
    omega_max_rel: float = 2.5
    """Highest frequency summed, in units of the peak frequency (the paper's cut: 2.5). The
    band [0.5, 2.5] keeps ~96 % of the spectrum's variance (Hs within 2 %) and, as in the
    paper's Fig. 11b, leaves the reflected pattern free of caustics at U = 1 m/s (at 3 omega_p
    it already folds: ``wai experiment stability``)."""
    mesh_points_per_wavelength: float = 48.0
    """Vertex spacing = shortest wavelength / this: shading normals are interpolated linearly,
    so the spot error goes as the spacing squared; 48 keeps it at hundredths of a pixel."""
    dispersion: str = "gravity"
    """``"gravity"``: deep-water waves, omega^2 = g k; ``"capillary"``: gravity-capillary
    waves, omega^2 = g k + (sigma / rho) k^3 (what matters past ~5 omega_p at low wind)."""
    height_scale: float = 1.0
    """Multiplies every harmonic's amplitude: waves of the same shape, wavelengths and speed,
    their heights and slopes this many times the fully developed sea's of eq. 42 (a young or
    swell-laden sea is steeper at the same U; the sweeps take the surface towards eq. 35's
    ordering limit with it). 1: the spectrum as the paper has it."""


@dataclass(frozen=True)
class DeviceConfig:
    """A pinhole camera or projector with Table 1's pose convention ``u_cam = R u_lab + t``."""

    width_px: int
    height_px: int
    sensor_width_mm: float
    focal_mm: float
    rotation: tuple[tuple[float, ...], ...]
    translation_mm: tuple[float, float, float]
    # What a real device does that the pinhole model leaves out: renderer only (the geometric
    # model and the restoration use its pinhole, wai_core.rig); all off by default.
    principal_offset_px: tuple[float, float] = (0.0, 0.0)
    """Principal point minus the image centre ``((W - 1) / 2, (H - 1) / 2)``, pixels."""
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    """Brown-Conrady lens distortion ``(k1, k2, p1, p2, k3)`` as OpenCV defines it."""
    port_thickness_mm: float = 0.0
    """A flat port (housing window) perpendicular to the axis; 0: no housing (the device's
    pinhole sits in the water)."""
    port_gap_mm: float = 5.0
    """Air between the pinhole and the port's inner face, mm."""
    port_n: float = 1.49
    """The port's refractive index (1.49: acrylic; 1.52: glass)."""
    port_tilt_deg: tuple[float, float] = (0.0, 0.0)
    """The port's normal off the optical axis, towards ``+x_cam`` and ``+y_cam``, deg
    (:mod:`wai_core.lens`); ``port_gap_mm`` is then measured along the normal."""
    aperture_mm: float = 0.0
    """Projector only: lens aperture diameter, mm (0: a pinhole, every dot in focus)."""
    focus_mm: float = 0.0
    """Projector only: distance along the axis to the plane in focus, mm (with aperture)."""



@dataclass(frozen=True)
class PatternConfig:
    """Grid of Gaussian dots on the projector panel."""

    spacing_px: float = 28.0
    sigma_px: float = 3.0
    color: tuple[float, float, float] = (0.0, 0.75, 1.0)
    power: float = 2.0e5
    # "none": every dot in ``color`` (the paper's pattern, matched by ordering); "colour": each
    # dot one of four blue-green mixes whose 3 x 3 windows are locally unique
    # (wai_core.pattern.dot_codes), decoded without ordering (restoration.features.decode).
    code: str = "none"
    code_seed: int = 0
    polarisation: str = "none"
    """Renderer only. ``"none"``: unpolarised light; ``"linear"``: an LCD's linearly polarised
    light, its electric field at ``polarisation_deg`` from the panel's x axis towards y."""
    polarisation_deg: float = 0.0


@dataclass(frozen=True)
class DiffuserConfig:
    """Horizontal translucent screen at ``z = z_mm`` (z_h)."""

    z_mm: float = 60.0
    # A real screen (renderer only; the geometric model assumes an ideal Lambertian one).
    half_width_deg: float = 0.0
    """Half width at half maximum of the transmitted radiance's angular profile, deg
    (0: Lambertian, whose radiance is the same in every direction)."""
    reflectance: float = 0.0
    """Share of the arriving light the screen reflects diffusely back into the water."""
    blur_mm: float = 0.0
    """Standard deviation of the spread inside the screen's thickness, mm."""


@dataclass(frozen=True)
class ObjectConfig:
    """Textured plane above the water, seen by camera v."""

    height_above_water_mm: float = 1000.0
    size_mm: tuple[float, float] = (3200.0, 2400.0)
    texture: str = "checkerboard"
    """``checkerboard``, ``speckle`` (a lab tank's random pattern for synthetic Schlieren),
    ``skimage:NAME`` or an image file."""
    squares: tuple[int, int] = (16, 12)
    speckle_mm: float = 8.0
    """``speckle``: the pattern's feature size, mm (the width of its smoothing)."""
    speckle_seed: int = 0
    """``speckle``: the seed of its random field."""


SKIMAGE_TEXTURES = (
    "astronaut", "binary_blobs", "brick", "camera", "cat", "cell", "checkerboard", "chelsea",
    "clock", "coffee", "coins", "colorwheel", "grass", "gravel", "horse", "hubble_deep_field",
    "immunohistochemistry", "logo", "microaneurysms", "moon", "page", "retina", "rocket",
    "shepp_logan_phantom", "text",
)
"""The scikit-image sample images ``[object].texture = "skimage:NAME"`` takes: the 2-D grey
and colour images that ship with scikit-image (no download)."""

SAMPLINGS = ("stratified", "independent")
"""Values of ``[render].sampling``."""
PARTICLE_SHARES = ("emitted", "delivered")
"""Values of ``[render].particle_shares``."""


@dataclass(frozen=True)
class RenderConfig:
    """Samples per pixel of the two renders and how they are placed."""

    spp_pattern: int = 4
    """Particle-tracer samples (light paths) per pixel of camera s."""
    spp_view: int = 4
    """Path-tracer samples per pixel of camera v."""
    sampling: str = "stratified"
    """``"stratified"``: the testbed's own renderers, the projector's dots drawn directly
    (every dot its share of the particles, each a shifted R2 point set; ``mitsuba_wai.dots``)
    and the view traced in its three steps with multi-jittered pixel samples
    (``mitsuba_wai.view_tracer``), so 4 samples per pixel beat 8 and 16 independent ones
    (docs/results.md); ``"independent"``: Mitsuba's own projector, ``path`` integrator and
    independent sampler."""
    particle_shares: str = "emitted"
    """How the projector's dots share the pattern's particles (stratified sampling):
    ``"emitted"``, by emitted power (every particle of a colour weighs the same); ``"delivered"``,
    by the power each spot delivers to the diffuser times its size there (every spot's centroid
    equally noisy; mitsuba_wai.dots)."""


@dataclass(frozen=True)
class SensorConfig:
    """Both cameras' sensor (:mod:`wai_core.sensor`): exposure, shot and read noise, full well,
    ADC. Off by default: the renders are then noiseless linear radiance."""

    enabled: bool = False
    signal_level: float = 0.5
    """Fraction of the full well reached by the 99.9th percentile of each camera's flat-water
    reference (pattern_flat for camera s, view_truth for camera v): the exposure setting."""
    electrons_per_unit_s: float = 0.0
    """Camera s's exposure, e- per radiance unit of the render; 0: from ``signal_level``."""
    electrons_per_unit_v: float = 0.0
    """Camera v's exposure, e- per radiance unit; 0: from ``signal_level``."""
    full_well_e: float = 10000.0
    read_noise_e: float = 5.0
    bits: int = 12
    gain_e_per_dn: float = 0.0
    """Conversion gain, e-/DN; 0: ``full_well_e / (2^bits - 1)`` (the ADC spans the well)."""
    dark_level_dn: float = 0.0
    reference_frames: int = 16
    """Frames averaged into pattern_flat (a calibration); 0: a noiseless reference."""


@dataclass(frozen=True)
class MotionConfig:
    """Motion blur: the surface moves during the exposure (:mod:`mitsuba_wai.degrade`)."""

    exposure_s: float = 0.0
    max_shift_px: float = 1.0
    """Largest image shift between consecutive sub-frames, px (sets the sub-frame count)."""
    max_subframes: int = 32


# Clear ocean water, Smith & Baker (1981, Appl. Opt. 20, 177, Table I; the data of the seed
# paper's Fig. 3) at the three channels' wavelengths, 600 / 530 / 460 nm (R, G, B), 1/m:
# absorption a(600) = 0.244, a(530) = 0.0507, a(460) = 0.0150 (the "blue-green window");
# scattering b = 0.0012 / 0.0022 / 0.0040 (pure sea water, Morel 1974, as Smith & Baker list).
SMITH_BAKER_ABSORPTION_PER_M = (0.244, 0.0507, 0.0150)
SMITH_BAKER_SCATTERING_PER_M = (0.0012, 0.0022, 0.0040)


@dataclass(frozen=True)
class WaterOpticsConfig:
    """Sea water's absorption and scattering along every underwater path
    (:mod:`mitsuba_wai.seawater`). Off by default: the water is then perfectly clear."""

    enabled: bool = False
    absorption_per_m: tuple[float, float, float] = SMITH_BAKER_ABSORPTION_PER_M
    """Absorption coefficient a per channel (R, G, B), 1/m."""
    scattering_per_m: tuple[float, float, float] = SMITH_BAKER_SCATTERING_PER_M
    """Scattering coefficient b per channel (R, G, B), 1/m."""
    turbidity: float = 1.0
    """Scales b (suspended particles; 1: clear ocean, ~300: coastal, b(530) ~ 0.7 1/m)."""
    absorption_scale: float = 1.0
    """Scales a (dissolved matter)."""
    forward_fraction: float = 0.0
    """Share of the scattered light that still arrives, as a veiling glow (0: Beer-Lambert)."""
    glow_sigma_deg: float = 5.0
    """Angular spread (standard deviation) of the forward-scattered glow, deg."""


@dataclass(frozen=True)
class AmbientConfig:
    """Daylight above the water, in both systems (:mod:`mitsuba_wai.ambient`). Off by default.

    Radiances are in the renders' units: the object plane's white squares have radiance 1."""

    enabled: bool = False
    sky_radiance: float = 1.0
    """Uniform sky radiance above the water (0: no sky)."""
    sun_irradiance: float = 10.0
    """Sun's irradiance on a plane facing it, radiance units x sr (0: no sun)."""
    sun_zenith_deg: float = 30.0
    sun_azimuth_deg: float = 0.0
    """Azimuth of the sun, deg from lab +x towards +y."""
    sun_color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    sky_color: tuple[float, float, float] = (0.6, 0.8, 1.0)
    sun_spp: int = 64
    """Particles per camera-s pixel for the sun's caustics on the diffuser (its own noise)."""
    sun_smooth_px: float = 0.0
    """Gaussian sigma, camera-s px, smoothing the sun's Monte Carlo noise on the diffuser
    (0: raw particles). Noise correlated at the spots' scale (a sigma of 2 .. 6 px) misleads
    the spot detector more than the raw noise does; 12 px or more is safe."""


CAMERA_V_FILTERS = ("none", "red")
"""Values of ``[crosstalk].camera_v_filter``."""


@dataclass(frozen=True)
class CrosstalkConfig:
    """Systems S and V in one scene (:mod:`mitsuba_wai.crosstalk`). Off by default.

    The projector's light that the water transmits (nearly all of it) lights the object, and
    camera v sees its dots on the object through the waves."""

    enabled: bool = False
    particles: int = 1 << 20
    """Projector particles traced to the object per frame (its dots' light on the object)."""
    scale: float = 1.0
    """The projector's light on the object times this (1: as bright as ``[pattern].power``
    makes it against the object's own radiance; more: a dimmer scene, a brighter projector)."""
    camera_v_filter: str = "none"
    """A filter in front of camera v: ``"red"`` passes the red channel only (the pattern is
    blue-green, the scene broadband: what a rig does against the crosstalk)."""

