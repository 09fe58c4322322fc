"""What a dataset is made of: its spec, and the parameters each frame draws from its seed.

Frame ``i`` of a dataset of seed ``s`` draws its sea state from ``default_rng([s, i])``
(:func:`sample_params`), so a frame's parameters depend on neither the number of frames nor the
workers that render them.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np

from wai.dataset.store import FORMAT
from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError

__all__ = ["DatasetSpec", "FrameParams", "Ranges", "flat_seed", "frame_config", "sample_params"]


@dataclass(frozen=True)
class Ranges:
    """The ranges frame parameters are drawn from, uniformly.

    Attributes
    ----------
    wind_speed_m_s : (float, float)
        Wind speed U at 19.5 m, m/s.
    wind_direction_deg : (float, float)
        Mean wave direction, deg from lab +x towards +y.
    time_s : (float, float)
        Time of the sea state, s.
    wave_seed : (int, int)
        The wave phases' seed, integers in ``[lo, hi)``.
    signal_level : (float, float)
        With degradations: the sensor's exposure (fraction of the full well).
    read_noise_e : (float, float)
        With degradations: the sensor's read noise, e- rms.
    """

    wind_speed_m_s: tuple[float, float] = (0.5, 2.0)
    wind_direction_deg: tuple[float, float] = (0.0, 360.0)
    time_s: tuple[float, float] = (0.0, 100.0)
    wave_seed: tuple[int, int] = (0, 2**31 - 1)
    signal_level: tuple[float, float] = (0.2, 0.8)
    read_noise_e: tuple[float, float] = (2.0, 10.0)

    def __post_init__(self) -> None:
        for f in fields(self):
            lo, hi = getattr(self, f.name)
            if not lo < hi:
                raise ValueError(f"Ranges.{f.name}: needs lo < hi, not {lo}, {hi}")
        if self.wind_speed_m_s[0] <= 0:
            raise ValueError("Ranges.wind_speed_m_s: the wind must be > 0")

    def to_json(self) -> str:
        """The ranges as the JSON the store records."""
        return json.dumps(asdict(self), sort_keys=True)


@dataclass(frozen=True)
class FrameParams:
    """The parameters of one frame (one row of the manifest).

    ``signal_level`` and ``read_noise_e`` are 0 where degradations are off.
    """

    frame: int
    wind_speed_m_s: float
    wind_direction_deg: float
    time_s: float
    wave_seed: int
    signal_level: float = 0.0
    read_noise_e: float = 0.0


def sample_params(
    seed: int, index: int, ranges: Ranges = Ranges(), degrade: bool = False
) -> FrameParams:
    """Frame ``index``'s parameters, drawn from ``default_rng([seed, index])``.

    Examples
    --------
    >>> p = sample_params(0, 3)
    >>> 0.5 <= p.wind_speed_m_s <= 2.0 and 0.0 <= p.time_s < 100.0
    True
    >>> p == sample_params(0, 3)
    True
    """
    if seed < 0:
        raise WaiInputError(f"--seed must be >= 0, not {seed}")
    if index < 0:
        raise ValueError(f"frame index must be >= 0, not {index}")
    rng = np.random.default_rng([int(seed), int(index)])
    r = ranges
    # Draw every value in a fixed order, degradations included, so turning them on does not
    # change a frame's sea state.
    wind = float(rng.uniform(*r.wind_speed_m_s))
    direction = float(rng.uniform(*r.wind_direction_deg))
    t = float(rng.uniform(*r.time_s))
    wave_seed = int(rng.integers(*r.wave_seed))
    level = float(rng.uniform(*r.signal_level))
    noise = float(rng.uniform(*r.read_noise_e))
    return FrameParams(int(index), wind, direction, t, wave_seed,
                       level if degrade else 0.0, noise if degrade else 0.0)


def flat_seed(seed: int) -> int:
    """The sampler seed of the flat-water renders every frame of a dataset of ``seed`` shares
    (0 .. 2^32 - 1): drawn from its own stream, apart from the frames' ``[seed, i]``.

    Examples
    --------
    >>> flat_seed(0) == flat_seed(0) != flat_seed(1)
    True
    >>> 0 <= flat_seed(7) < 2**32
    True
    """
    if seed < 0:
        raise WaiInputError(f"--seed must be >= 0, not {seed}")
    return int(np.random.SeedSequence(int(seed), spawn_key=(0,)).generate_state(1)[0])


@dataclass(frozen=True)
class DatasetSpec:
    """What a dataset is made of (what a rerun must match to continue it).

    Attributes
    ----------
    config : str
        A packaged scene's name or a scene TOML file (:func:`wai_core.load_rig`).
    seed : int
        The dataset's seed (:func:`sample_params`).
    ranges : Ranges
    spp : int or None
        Samples per pixel of every render (None: the scene's).
    size_px : (int, int) or None
        Both cameras' (width, height), px, at the scene's field of view (None: the scene's).
    degrade : bool
        Sensor noise on, with exposure and read noise drawn per frame (:class:`Ranges`).
    """

    config: str = "paper"
    seed: int = 0
    ranges: Ranges = field(default_factory=Ranges)
    spp: int | None = None
    size_px: tuple[int, int] | None = None
    degrade: bool = False

    def base_config(self) -> SystemConfig:
        """The scene, with ``size_px`` applied to both cameras."""
        from mitsuba_wai import lens_keys
        from wai_core.system import load_rig

        cfg = load_rig(self.config)
        if self.size_px is not None:
            w, h = self.size_px
            for cam in ("camera_s", "camera_v"):
                cfg = cfg.replace(cam, width_px=int(w), height_px=int(h))
        if lens_keys(cfg.camera_v):
            raise WaiInputError(f"--config {self.config}: camera v has a lens or port "
                                f"({', '.join(lens_keys(cfg.camera_v))}); the dataset's warp "
                                "is a pinhole camera's")
        return cfg

    def attrs(self, cfg: SystemConfig) -> dict[str, Any]:
        """The identity attributes of the store (``_IDENTITY``)."""
        return {
            "format": FORMAT, "seed": int(self.seed), "config": str(self.config),
            "config_json": json.dumps(cfg.to_dict(), sort_keys=True, default=str),
            "ranges": self.ranges.to_json(), "spp": int(self.spp or 0),
            "size_px": json.dumps(list(self.size_px) if self.size_px else None),
            "degrade": bool(self.degrade),
        }


def frame_config(base: SystemConfig, p: FrameParams) -> SystemConfig:
    """``base`` with frame ``p``'s sea state (and sensor, when degraded).

    Examples
    --------
    >>> from wai_core import load_system
    >>> cfg = frame_config(load_system("paper"), FrameParams(0, 1.5, 90.0, 12.0, 3))
    >>> cfg.waves.wind_speed_m_s, cfg.waves.seed, cfg.sensor.enabled
    (1.5, 3, False)
    """
    cfg = base.replace("waves", wind_speed_m_s=p.wind_speed_m_s,
                       wind_direction_deg=p.wind_direction_deg, time_s=p.time_s,
                       seed=p.wave_seed)
    if p.signal_level > 0:
        cfg = cfg.replace("sensor", enabled=True, signal_level=p.signal_level,
                          read_noise_e=p.read_noise_e)
    return cfg
