"""System configuration: the scene as data (a TOML file in ``scenes/``, or ``scene.json``).

Every section maps to a frozen dataclass. Unknown keys, missing keys and values of the wrong kind
raise :class:`~wai_core.errors.WaiInputError` naming the key, so a typo never passes silently.
One rule for what may be left out: the sections that describe the rig and what it looks at,
everything the restoration reads (:data:`RIG_SECTIONS`: ``[water]``, ``[projector]``,
``[pattern]``, ``[camera_s]``, ``[camera_v]``, ``[diffuser]``, ``[object]``), are required,
so a rig of one's own never silently takes the paper's water level or diffuser height; the
sections that only drive the simulation (``[waves]``, ``[render]``, and the field's
degradations ``[sensor]``, ``[motion]``, ``[water_optics]``, ``[ambient]``, ``[crosstalk]``,
off by default and free then) may be left out. Within a section, a key that has a default
(its dataclass's) may be left out; the devices' geometry has none. ``scene.json`` records
every value used.
"""

from __future__ import annotations

import dataclasses
import functools
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, get_type_hints

import numpy as np

from wai_core.errors import WaiInputError
from wai_core.geometry import pinhole_of
from wai_core.sections import (
    CAMERA_V_FILTERS,
    PARTICLE_SHARES,
    SAMPLINGS,
    SKIMAGE_TEXTURES,
    AmbientConfig,
    CrosstalkConfig,
    DeviceConfig,
    DiffuserConfig,
    MotionConfig,
    ObjectConfig,
    PatternConfig,
    RenderConfig,
    SensorConfig,
    WaterConfig,
    WaterOpticsConfig,
    WavesConfig,
)

if TYPE_CHECKING:
    from wai_core.rig import Rig


@dataclass(frozen=True)
class SystemConfig:
    """The whole sensing system: water, waves, projector, pattern, cameras, diffuser, object."""

    water: WaterConfig = field(default_factory=WaterConfig)
    waves: WavesConfig = field(default_factory=WavesConfig)
    projector: DeviceConfig | None = None
    pattern: PatternConfig = field(default_factory=PatternConfig)
    camera_s: DeviceConfig | None = None
    camera_v: DeviceConfig | None = None
    diffuser: DiffuserConfig = field(default_factory=DiffuserConfig)
    object: ObjectConfig = field(default_factory=ObjectConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    water_optics: WaterOpticsConfig = field(default_factory=WaterOpticsConfig)
    ambient: AmbientConfig = field(default_factory=AmbientConfig)
    crosstalk: CrosstalkConfig = field(default_factory=CrosstalkConfig)

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (JSON/TOML-able)."""
        return dataclasses.asdict(self)

    def replace(self, section: str, **changes: Any) -> SystemConfig:
        """Copy with some keys of one section changed, e.g. ``cfg.replace('waves', seed=3)``."""
        return dataclasses.replace(
            self, **{section: dataclasses.replace(getattr(self, section), **changes)}
        )

    @property
    def object_z_mm(self) -> float:
        """Height of the object plane, mm (z_a = h0 + 1000 in the paper)."""
        return self.water.h0_mm + self.object.height_above_water_mm

    @functools.cached_property
    def rig(self) -> Rig:
        """What the devices imply (:class:`wai_core.rig.Rig`), derived once for this
        configuration: every stage asks it for the cameras, the dot grid and the flat-water
        geometry."""
        from wai_core.rig import Rig

        return Rig(self)

    def __getstate__(self) -> dict[str, Any]:
        # The rig is derived: a pickled configuration (a sweep's worker) derives its own.
        return {k: v for k, v in self.__dict__.items() if k != "rig"}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)


_SECTIONS = {
    "water": WaterConfig,
    "waves": WavesConfig,
    "projector": DeviceConfig,
    "pattern": PatternConfig,
    "camera_s": DeviceConfig,
    "camera_v": DeviceConfig,
    "diffuser": DiffuserConfig,
    "object": ObjectConfig,
    "render": RenderConfig,
    "sensor": SensorConfig,
    "motion": MotionConfig,
    "water_optics": WaterOpticsConfig,
    "ambient": AmbientConfig,
    "crosstalk": CrosstalkConfig,
}


def _coerce(value: Any, hint: Any, where: str) -> Any:
    """Convert a TOML/JSON value to the dataclass field's type, or raise naming ``where``."""
    origin = getattr(hint, "__origin__", None)
    try:
        if hint is bool:
            if not isinstance(value, bool):
                raise TypeError
            return value
        if hint is float:
            if isinstance(value, bool):
                raise TypeError
            out = float(value)
            if not np.isfinite(out):
                raise WaiInputError(f"config: {where} is not finite")
            return out
        if hint is int:
            if isinstance(value, bool) or float(value) != int(value):
                raise TypeError
            return int(value)
        if hint is str:
            if not isinstance(value, str):
                raise TypeError
            return value
        if origin is tuple:
            args = hint.__args__
            if len(args) == 2 and args[1] is Ellipsis:
                return tuple(_coerce(v, args[0], where) for v in value)
            if len(value) != len(args):
                raise WaiInputError(f"config: {where} needs {len(args)} values, got {len(value)}")
            return tuple(_coerce(v, a, where) for v, a in zip(value, args, strict=True))
    except (TypeError, ValueError) as exc:
        if isinstance(exc, WaiInputError):
            raise
        raise WaiInputError(f"config: {where} has a value of the wrong kind: {value!r}") from None
    return value


def parse_section(cls: type, data: Any, name: str) -> Any:
    """An instance of the dataclass ``cls`` from the table ``[name]``, each value coerced to its
    field's type; unknown, missing or wrongly typed keys raise WaiInputError naming the key."""
    if not isinstance(data, dict):
        raise WaiInputError(f"config: section [{name}] must be a table")
    hints = get_type_hints(cls)
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise WaiInputError(f"config: unknown key [{name}].{unknown[0]}")
    kwargs = {k: _coerce(v, hints[k], f"[{name}].{k}") for k, v in data.items()}
    try:
        return cls(**kwargs)
    except TypeError:
        missing = sorted(
            f.name
            for f in fields(cls)
            if f.name not in data
            and f.default is dataclasses.MISSING
            and f.default_factory is dataclasses.MISSING
        )
        raise WaiInputError(f"config: missing key [{name}].{missing[0]}") from None


DEVICE_SECTIONS = ("projector", "camera_s", "camera_v")
"""The devices: their pose and size have no default."""
RIG_SECTIONS = ("water", "projector", "pattern", "camera_s", "camera_v", "diffuser", "object")
"""The sections a configuration must give: the rig and what it looks at, everything the
restoration reads (see the module notes)."""

MAX_WAVE_COMPONENTS = 200_000
"""Most harmonics (``n_frequencies * n_directions``) a sea state may sum (the paper's 64 x 24
is 1536): each costs ~80 bytes per array set and its share of every height evaluated."""
MAX_REFERENCE_FRAMES = 1024
"""Most noisy frames averaged into a simulated flat-water reference (each is simulated)."""
ROTATION_TOLERANCE = 1e-3
"""Largest |R^T R - I| entry accepted for a device's rotation (Table 1's rounding is 5e-5)."""
MAX_PORT_TILT_DEG = 30.0
"""Largest tilt of a housing port's normal off its device's axis, deg (``port_tilt_deg``): a
window that far off square is a mounting error, not a housing."""


def config_from_dict(data: dict[str, Any]) -> SystemConfig:
    """Build and check a :class:`SystemConfig` from nested dicts."""
    unknown = sorted(set(data) - set(_SECTIONS))
    if unknown:
        raise WaiInputError(f"config: unknown section [{unknown[0]}]")
    missing = [name for name in RIG_SECTIONS if name not in data]
    if missing:
        raise WaiInputError(
            f"config: missing section [{missing[0]}] (the sections that describe the rig, "
            f"{', '.join(f'[{n}]' for n in RIG_SECTIONS)}, are required; only the "
            "simulation's, [waves], [render] and the degradations, may be left out)"
        )
    cfg = SystemConfig(**{k: parse_section(_SECTIONS[k], v, k) for k, v in data.items()})
    validate(cfg)
    return cfg


def read_toml(path: str | Path) -> dict[str, Any]:
    """The tables of a TOML file; a missing or unparsable file raises WaiInputError."""
    path = Path(path)
    if not path.is_file():
        raise WaiInputError(f"config file not found: {path}")
    try:
        return tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise WaiInputError(f"config file {path} is not valid TOML: {exc}") from None


def load_config(path: str | Path) -> SystemConfig:
    """Read a scene TOML file (e.g. ``scenes/paper.toml``).

    A file with a top-level ``extends = "other.toml"`` (relative to its own folder) is that
    scene with the file's keys in place of its own: a variant states only what differs
    (``scenes/schlieren.toml``)."""
    return config_from_dict(_scene_tables(Path(path), depth=0))


def _scene_tables(path: Path, depth: int) -> dict[str, Any]:
    """The tables of scene file ``path``, those of the scene it extends under them."""
    data = read_toml(path)
    parent = data.pop("extends", None)
    if parent is None:
        return data
    if not isinstance(parent, str):
        raise WaiInputError(f"{path}: extends must name a scene TOML file, not {parent!r}")
    if depth >= 8:
        raise WaiInputError(f"{path}: extends goes more than 8 files deep (a loop?)")
    tables = config_from_dict(_scene_tables(path.parent / parent, depth + 1)).to_dict()
    for section, table in data.items():
        if not isinstance(table, dict):
            raise WaiInputError(f"config: [{section}] must be a table")
        tables.setdefault(section, {}).update(table)
    return tables


def validate(cfg: SystemConfig) -> None:
    """Reject impossible geometry with a message naming the problem."""
    w = cfg.water
    if w.surface not in ("dielectric", "mirror"):
        raise WaiInputError(f"config: [water].surface must be dielectric or mirror: {w.surface}")
    if w.n_water <= 1.0:
        raise WaiInputError("config: [water].n_water must exceed 1 (water is denser than air)")
    if w.h0_mm <= 0:
        raise WaiInputError("config: [water].h0_mm must be positive (water above the projector)")
    if not 0 < cfg.diffuser.z_mm < w.h0_mm:
        raise WaiInputError("config: [diffuser].z_mm must lie between the projector and the water")
    if cfg.object.height_above_water_mm <= 0:
        raise WaiInputError("config: [object].height_above_water_mm must be positive")
    texture = cfg.object.texture
    if texture == "speckle" and not cfg.object.speckle_mm > 0:
        raise WaiInputError("config: [object].speckle_mm must be > 0")
    if texture.startswith("skimage:") and texture.partition(":")[2] not in SKIMAGE_TEXTURES:
        raise WaiInputError(f"config: [object].texture {texture!r} is not a scikit-image sample "
                            f"image (skimage: one of {', '.join(SKIMAGE_TEXTURES)})")
    wv = cfg.waves
    if wv.wind_speed_m_s < 0 or wv.n_frequencies < 1 or wv.n_directions < 1:
        raise WaiInputError("config: [waves] needs wind_speed >= 0 and at least one component")
    components = wv.n_frequencies * wv.n_directions
    if components > MAX_WAVE_COMPONENTS:
        raise WaiInputError(
            f"config: [waves] n_frequencies x n_directions = {components:.3g} harmonics would "
            f"need about {components * 80 / 2**30:.3g} GiB before any height is evaluated; at "
            f"most {MAX_WAVE_COMPONENTS} are accepted"
        )
    if not 0 < wv.omega_min_rel < wv.omega_max_rel:
        raise WaiInputError("config: [waves] needs 0 < omega_min_rel < omega_max_rel")
    if not (np.isfinite(wv.height_scale) and wv.height_scale >= 0):
        raise WaiInputError(f"config: [waves].height_scale must be >= 0, not {wv.height_scale}")
    if wv.seed < 0:
        raise WaiInputError(f"config: [waves].seed must be >= 0, not {wv.seed}")
    if cfg.pattern.spacing_px <= 2 * cfg.pattern.sigma_px:
        raise WaiInputError("config: [pattern].spacing_px must exceed twice sigma_px")
    if cfg.pattern.code not in ("none", "colour"):
        raise WaiInputError(
            f"config: [pattern].code must be 'none' or 'colour', not {cfg.pattern.code!r}"
        )
    if cfg.pattern.code_seed < 0:
        raise WaiInputError("config: [pattern].code_seed must be >= 0")
    for name in ("projector", "camera_s", "camera_v"):
        dev: DeviceConfig = getattr(cfg, name)
        if min(dev.width_px, dev.height_px) < 2 or dev.focal_mm <= 0 or dev.sensor_width_mm <= 0:
            raise WaiInputError(f"config: [{name}] needs positive size, focal length and sensor")
        _check_rotation(dev.rotation, name)
        try:
            pinhole_of(dev)
        except (ValueError, np.linalg.LinAlgError) as exc:
            raise WaiInputError(f"config: [{name}] {exc}") from None
    if cfg.render.spp_pattern < 1 or cfg.render.spp_view < 1:
        raise WaiInputError("config: [render] spp must be at least 1")
    _check_choice(cfg.render.particle_shares, PARTICLE_SHARES, "[render].particle_shares")
    _check_choice(cfg.render.sampling, SAMPLINGS, "[render].sampling")
    _validate_degradations(cfg.sensor, cfg.motion)
    _validate_light(cfg.water_optics, cfg.ambient)
    _validate_effects(cfg)


INDEX_MODELS = ("constant", "quan_fry")
"""Values of ``[water].index_model``."""
DISPERSIONS = ("gravity", "capillary")
"""Values of ``[waves].dispersion``."""
POLARISATIONS = ("none", "linear")
"""Values of ``[pattern].polarisation``."""

RENDERER_EFFECTS: dict[str, tuple[str, ...]] = {
    "water": ("index_model", "roughness"),
    "waves": ("dispersion",),
    "pattern": ("polarisation",),
    "diffuser": ("half_width_deg", "reflectance", "blur_mm"),
    "crosstalk": ("enabled", "camera_v_filter"),
    **{
        name: ("principal_offset_px", "distortion", "port_thickness_mm", "aperture_mm")
        for name in DEVICE_SECTIONS
    },
}
"""The physics a render can carry that the geometric model leaves out, per section: each key
is off at its default, and the restoration never reads it."""


def renderer_effects(cfg: SystemConfig) -> dict[str, Any]:
    """The renderer-only effects of ``cfg`` that are on: ``"section.key"`` to its value.

    Examples
    --------
    >>> from wai_core import load_system
    >>> cfg = load_system("paper")
    >>> renderer_effects(cfg)
    {}
    >>> renderer_effects(cfg.replace("water", index_model="quan_fry"))
    {'water.index_model': 'quan_fry'}
    """
    on = {}
    for section, keys in RENDERER_EFFECTS.items():
        value, default = getattr(cfg, section), _SECTIONS[section]
        for key in keys:
            off = next(f for f in fields(default) if f.name == key).default
            if getattr(value, key) != off:
                on[f"{section}.{key}"] = getattr(value, key)
    return on


def with_keys(cfg: SystemConfig, changes: dict[str, Any]) -> SystemConfig:
    """A checked copy of ``cfg`` with ``"section.key"`` values changed (values as TOML gives).

    Examples
    --------
    >>> from wai_core import load_system
    >>> cfg = with_keys(load_system("paper"), {"camera_v.distortion": [-0.1, 0, 0, 0, 0]})
    >>> cfg.camera_v.distortion
    (-0.1, 0.0, 0.0, 0.0, 0.0)
    """
    data = cfg.to_dict()
    for name, value in changes.items():
        section, _, key = name.partition(".")
        if section not in data or not isinstance(data[section], dict) or key not in data[section]:
            raise WaiInputError(f"config: unknown key {name!r} (section.key)")
        data[section][key] = value
    return config_from_dict(data)


def _validate_effects(cfg: SystemConfig) -> None:
    """The renderer-only effects (:data:`RENDERER_EFFECTS`): checked even when off."""
    w = cfg.water
    _check_choice(w.index_model, INDEX_MODELS, "[water].index_model")
    # Quan & Fry's fit spans 0-35 PSU and 0-30 C (400-700 nm); a little beyond is harmless.
    if not 0 <= w.salinity_psu <= 40:
        raise WaiInputError(f"config: [water].salinity_psu must be 0 .. 40, not {w.salinity_psu:g}")
    if not -2 <= w.temperature_c <= 35:
        raise WaiInputError(
            f"config: [water].temperature_c must be -2 .. 35, not {w.temperature_c:g}"
        )
    if not 0 <= w.roughness < 1:
        raise WaiInputError(f"config: [water].roughness must be 0 .. 1, not {w.roughness:g}")
    _check_choice(cfg.waves.dispersion, DISPERSIONS, "[waves].dispersion")
    _check_choice(cfg.pattern.polarisation, POLARISATIONS, "[pattern].polarisation")
    d = cfg.diffuser
    if not 0 <= d.half_width_deg < 90:
        raise WaiInputError(
            f"config: [diffuser].half_width_deg must be 0 .. 90, not {d.half_width_deg:g}"
        )
    if not 0 <= d.reflectance < 1:
        raise WaiInputError(f"config: [diffuser].reflectance must be 0 .. 1, not {d.reflectance:g}")
    if d.blur_mm < 0:
        raise WaiInputError(f"config: [diffuser].blur_mm must be >= 0, not {d.blur_mm:g}")
    for name in DEVICE_SECTIONS:
        _check_device_optics(getattr(cfg, name), name)
    c = cfg.crosstalk
    _check_choice(c.camera_v_filter, CAMERA_V_FILTERS, "[crosstalk].camera_v_filter")
    if not (np.isfinite(c.scale) and c.scale >= 0):
        raise WaiInputError(f"config: [crosstalk].scale must be >= 0, not {c.scale:g}")
    if c.particles < 1024:
        raise WaiInputError(f"config: [crosstalk].particles must be >= 1024, not {c.particles}")


def _check_device_optics(dev: DeviceConfig, name: str) -> None:
    """A device's lens, port and aperture keys."""
    if max(abs(v) for v in dev.principal_offset_px) >= min(dev.width_px, dev.height_px) / 2:
        raise WaiInputError(f"config: [{name}].principal_offset_px must lie inside the image")
    if dev.port_thickness_mm < 0 or dev.port_gap_mm <= 0 or dev.port_n <= 1:
        raise WaiInputError(
            f"config: [{name}] needs port_thickness_mm >= 0, port_gap_mm > 0 and port_n > 1"
        )
    tilt = tuple(float(v) for v in dev.port_tilt_deg)
    if len(tilt) != 2 or not all(np.isfinite(v) and abs(v) <= MAX_PORT_TILT_DEG for v in tilt):
        raise WaiInputError(
            f"config: [{name}].port_tilt_deg must be two angles within +-{MAX_PORT_TILT_DEG:g} "
            f"deg, not {list(dev.port_tilt_deg)}"
        )
    if any(tilt) and not dev.port_thickness_mm > 0:
        raise WaiInputError(
            f"config: [{name}].port_tilt_deg tilts a port: it needs port_thickness_mm > 0"
        )
    if dev.aperture_mm < 0:
        raise WaiInputError(f"config: [{name}].aperture_mm must be >= 0, not {dev.aperture_mm:g}")
    if dev.aperture_mm > 0 and name != "projector":
        raise WaiInputError(
            f"config: [{name}].aperture_mm: only the projector's defocus is modelled "
            "(the cameras are pinholes)"
        )
    if dev.aperture_mm > 0 and dev.focus_mm <= 0:
        raise WaiInputError(
            f"config: [{name}].focus_mm must be positive when aperture_mm is (the plane in focus)"
        )


def _check_choice(value: str, choices: tuple[str, ...], key: str) -> None:
    """A key with a fixed set of values: anything else is refused, naming the key."""
    if value not in choices:
        raise WaiInputError(f"config: {key} must be one of {', '.join(choices)}, not {value!r}")


def _check_rotation(rotation: Any, name: str) -> None:
    """A device's rotation must be one: 3 x 3, orthonormal to :data:`ROTATION_TOLERANCE`,
    determinant +1 (a zero or scaled matrix is refused, not re-orthonormalised)."""
    r = np.asarray(rotation, dtype=float)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise WaiInputError(f"config: [{name}].rotation must be a finite 3 x 3 matrix")
    error = float(np.abs(r.T @ r - np.eye(3)).max())
    if error > ROTATION_TOLERANCE or np.linalg.det(r) <= 0:
        raise WaiInputError(
            f"config: [{name}].rotation is not a rotation (|R^T R - I| up to {error:.3g}, "
            f"det {np.linalg.det(r):.3g}; it must be orthonormal with det +1)"
        )


def _validate_degradations(s: SensorConfig, m: MotionConfig) -> None:
    """[sensor] and [motion]: checked even when disabled, so a typo'd value never waits."""
    positive = {"full_well_e": s.full_well_e, "signal_level": s.signal_level}
    for key, value in positive.items():
        if value <= 0:
            raise WaiInputError(f"config: [sensor].{key} must be positive, not {value:g}")
    non_negative = {
        "electrons_per_unit_s": s.electrons_per_unit_s,
        "electrons_per_unit_v": s.electrons_per_unit_v, "read_noise_e": s.read_noise_e,
        "gain_e_per_dn": s.gain_e_per_dn, "dark_level_dn": s.dark_level_dn,
        "reference_frames": s.reference_frames,
    }
    for key, value in non_negative.items():
        if value < 0:
            raise WaiInputError(f"config: [sensor].{key} must be >= 0, not {value:g}")
    if s.reference_frames > MAX_REFERENCE_FRAMES:
        raise WaiInputError(
            f"config: [sensor].reference_frames = {s.reference_frames}: each frame is simulated, "
            f"so at most {MAX_REFERENCE_FRAMES} are accepted (the mean of N frames has 1/sqrt(N) "
            "of one frame's noise)"
        )
    if not 8 <= s.bits <= 16:
        raise WaiInputError(f"config: [sensor].bits must be 8 .. 16, not {s.bits}")
    if s.dark_level_dn >= 2**s.bits - 1:
        raise WaiInputError("config: [sensor].dark_level_dn must lie below the ADC full scale")
    if m.exposure_s < 0:
        raise WaiInputError(f"config: [motion].exposure_s must be >= 0, not {m.exposure_s:g}")
    if m.max_shift_px <= 0:
        raise WaiInputError(
            f"config: [motion].max_shift_px must be positive, not {m.max_shift_px:g}"
        )
    if m.max_subframes < 1:
        raise WaiInputError(f"config: [motion].max_subframes must be >= 1, not {m.max_subframes}")


def _validate_light(w: WaterOpticsConfig, a: AmbientConfig) -> None:
    """[water_optics] and [ambient]: checked even when disabled."""
    values = {
        "absorption_per_m": min(w.absorption_per_m), "scattering_per_m": min(w.scattering_per_m),
        "turbidity": w.turbidity, "absorption_scale": w.absorption_scale,
        "glow_sigma_deg": w.glow_sigma_deg,
    }
    for key, value in values.items():
        if value < 0:
            raise WaiInputError(f"config: [water_optics].{key} must be >= 0, not {value:g}")
    if not 0 <= w.forward_fraction <= 1:
        raise WaiInputError(
            f"config: [water_optics].forward_fraction must be 0 .. 1, not {w.forward_fraction:g}"
        )
    if w.glow_sigma_deg >= 45:
        raise WaiInputError("config: [water_optics].glow_sigma_deg must be below 45")
    for key in ("sky_radiance", "sun_irradiance"):
        if getattr(a, key) < 0:
            raise WaiInputError(f"config: [ambient].{key} must be >= 0, not {getattr(a, key):g}")
    for key in ("sun_color", "sky_color"):
        if min(getattr(a, key)) < 0:
            raise WaiInputError(f"config: [ambient].{key} must be >= 0")
    if a.sun_smooth_px < 0:
        raise WaiInputError(
            f"config: [ambient].sun_smooth_px must be >= 0, not {a.sun_smooth_px:g}"
        )
    if a.sun_spp < 1:
        raise WaiInputError(f"config: [ambient].sun_spp must be >= 1, not {a.sun_spp}")
    if not 0 <= a.sun_zenith_deg < 90:
        raise WaiInputError(
            f"config: [ambient].sun_zenith_deg must be 0 .. 90 (sun up), not {a.sun_zenith_deg:g}"
        )
