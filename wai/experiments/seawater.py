"""The seed paper's blue-green argument (section 2.2, Fig. 3) in numbers: spot SNR after water.

:func:`seawater_snr` renders system S's flat-water pattern in one colour after another (equal
radiant power: each colour's R + G + B is 1), through water whose Beer-Lambert optical depth
equals a given length of sea-water path (``[water_optics]`` with ``a`` and ``b`` scaled by
``distance / mean path``: ``exp(-c L)`` depends on ``c L`` alone), and reads each image with the
same camera (``[sensor]`` on, one exposure for every case: the one that puts the clear-water
blue-green reference's 99.9th percentile at ``signal_level`` of the full well), so the water
dims the spots and the noise stays. For each detected spot (the flat geometry's spot for each
dot in view): peak = the highest DN of the channel sum in the 3 x 3 pixels around it, minus
the background's mean; SNR = peak / the background's standard deviation (pixels 5 px or more
from every spot where the noiseless image is under 0.1 % of its 99.9th percentile).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from wai_core.config import SystemConfig

BACKGROUND_DISTANCE_PX = 5.0
"""Background pixels lie at least this far from every spot (camera s's spots: ~1.4 px sigma)."""
BACKGROUND_LEVEL = 1e-3
"""... and below this fraction of the expected image's 99.9th percentile: no spot's tail (the
render's own noise in the faint tails of the larger, oblique spots would read as the
sensor's)."""

COLOURS: dict[str, tuple[float, float, float]] = {
    "red": (1.0, 0.0, 0.0),
    "blue_green": (0.0, 0.75, 1.0),  # the paper's pattern ([pattern].color)
}


def _spot_pixels(cfg: SystemConfig) -> tuple[np.ndarray, np.ndarray]:
    """Rounded camera-s pixels (rows, cols) of the flat-water spots in view."""
    from wai_core.layout import flat_pattern_hits

    _, s, seen = flat_pattern_hits(cfg)
    cols, rows, _ = cfg.rig.camera_s.project(s[seen])
    return np.rint(rows).astype(int), np.rint(cols).astype(int)


def spot_snr(dn: np.ndarray, noiseless: np.ndarray, rows: np.ndarray,
             cols: np.ndarray) -> dict[str, float]:
    """Peak over background noise of the spots at ``rows``, ``cols`` in a sensor image.

    Parameters
    ----------
    dn : (H, W, 3) ndarray
        The noisy reading, DN.
    noiseless : (H, W, 3) ndarray
        The expected image (any scale): where it is dark is the background.
    rows, cols : (K,) ndarray of int
        The spots' pixels.

    Returns
    -------
    dict
        ``snr_median``, ``snr_p10`` (over spots), ``peak_dn`` (median), ``background_dn``,
        ``noise_dn``, ``spots``.
    """
    from scipy.ndimage import distance_transform_edt

    mono, ref = dn.sum(axis=2), noiseless.sum(axis=2)
    h, w = mono.shape
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    far = np.ones((h, w), dtype=bool)
    far[rows[inside], cols[inside]] = False
    # Background: 5 px or more from every spot and dark in the expected image.
    back = (distance_transform_edt(far) >= BACKGROUND_DISTANCE_PX) & (
        ref < BACKGROUND_LEVEL * np.percentile(ref, 99.9))
    mean, noise = float(mono[back].mean()), float(mono[back].std())
    keep = (rows >= 1) & (rows < h - 1) & (cols >= 1) & (cols < w - 1)
    r, c = rows[keep], cols[keep]
    windows = np.stack([mono[r + i, c + j] for i in (-1, 0, 1) for j in (-1, 0, 1)])
    peaks = windows.max(axis=0) - mean
    snr = peaks / max(noise, 1e-12)
    return {"snr_median": float(np.median(snr)), "snr_p10": float(np.percentile(snr, 10)),
            "peak_dn": float(np.median(peaks)), "background_dn": mean, "noise_dn": noise,
            "spots": int(keep.sum())}


def seawater_snr(
    config: str = "paper",
    distances_m: tuple[float, ...] = (0.0, 1.0, 5.0),
    colours: dict[str, tuple[float, float, float]] | None = None,
    turbidity: float = 1.0,
    seed: int = 0,
    signal_level: float = 0.5,
    spp: int | None = None,
    water: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Detected spot SNR of each pattern colour after each length of sea water (module notes).

    Parameters
    ----------
    config : str
        Scene name or TOML file (its ``[water_optics]`` coefficients are used, enabled or not).
    distances_m : tuple of float
        Water path lengths to emulate, m (0: clear water).
    colours : dict of str to (3,) tuple, optional
        Pattern colours by name (default :data:`COLOURS`); each is normalised to R + G + B = 1.
    turbidity : float
        ``[water_optics].turbidity`` (scales the scattering before the path scaling).
    seed : int
        Scene seed (render and sensor noise).
    signal_level : float
        The shared exposure's fraction of the full well at the clear blue-green reference.
    spp : int, optional
        Particle-tracer samples per pixel (default the scene's).
    water : dict, optional
        Other ``[water_optics]`` values (e.g. a water type's ``absorption_per_m``,
        ``scattering_per_m``), applied before the path scaling.

    Returns
    -------
    dict
        ``mean_path_mm`` (the rig's mean water path, projector -> camera s),
        ``electrons_per_unit`` (the shared exposure), and ``rows``: one dict per colour and
        distance with ``colour``, ``distance_m``, ``transmittance`` (R, G, B: exp(-c D)) and
        the :func:`spot_snr` values; ``snr_ratio`` (blue-green / red) per distance when both
        are present.
    """
    from mitsuba_wai import (
        FrameRenderer,
        coefficients_per_mm,
        flat_like,
        pattern_path_lengths_mm,
        render_seed,
        wave_surface,
    )
    from wai_core import sensor as sensors
    from wai_core.system import load_rig

    colours = COLOURS if colours is None else colours
    base = load_rig(config).replace("waves", seed=int(seed))
    base = base.replace("sensor", enabled=True, signal_level=float(signal_level))
    base = base.replace("water_optics", **{**(water or {}), "turbidity": float(turbidity)})
    if spp is not None:
        base = base.replace("render", spp_pattern=int(spp))
    mean_mm = float(pattern_path_lengths_mm(base).mean())
    rows_px, cols_px = _spot_pixels(base)
    flat = flat_like(wave_surface(base), base.water.h0_mm)
    render_s = render_seed(base)

    def flat_pattern(cfg: SystemConfig) -> np.ndarray:
        r = FrameRenderer(cfg, flat, systems=("pattern",))
        return r.render(flat, render_s, ("pattern",))["pattern"]

    images: dict[tuple[str, float], np.ndarray] = {}
    for name, colour in colours.items():
        col = np.asarray(colour, dtype=float)
        cfg_c = base.replace("pattern", color=tuple(float(v) for v in col / col.sum()))
        for d in distances_m:
            scale = float(d) * 1000.0 / mean_mm
            cfg_d = cfg_c.replace("water_optics", enabled=d > 0,
                                  absorption_scale=scale * base.water_optics.absorption_scale,
                                  turbidity=scale * base.water_optics.turbidity)
            images[(name, float(d))] = flat_pattern(cfg_d)
    ref_name = "blue_green" if "blue_green" in colours else next(iter(colours))
    ref = images.get((ref_name, 0.0))
    if ref is None:
        ref = flat_pattern(base.replace("water_optics", enabled=False))
    x = sensors.exposure_for(ref, base.sensor)
    a, b = coefficients_per_mm(base.water_optics)
    out_rows = []
    for (name, d), img in images.items():
        rng = sensors.noise_rng(int(seed), f"seawater/{name}/{d:g}")
        dn = sensors.expose(img, x, base.sensor, rng)
        row = {"colour": name, "distance_m": d,
               "transmittance": np.exp(-(a + b) * d * 1000.0).tolist()}
        row.update(spot_snr(dn, img, rows_px, cols_px))
        out_rows.append(row)
    ratio = {}
    for d in distances_m:
        by = {r["colour"]: r for r in out_rows if r["distance_m"] == float(d)}
        if "red" in by and "blue_green" in by:
            ratio[f"{d:g}"] = by["blue_green"]["snr_median"] / max(by["red"]["snr_median"], 1e-12)
    return {"mean_path_mm": mean_mm, "electrons_per_unit": x, "turbidity": float(turbidity),
            "rows": out_rows, "snr_ratio": ratio}


def format_snr(result: dict[str, Any]) -> str:
    """A plain-text table of :func:`seawater_snr`'s result."""
    lines = [f"mean water path of the rig {result['mean_path_mm']:.0f} mm, turbidity "
             f"{result['turbidity']:g}",
             f"{'colour':<11} {'path m':>6} {'T(R,G,B)':>20} {'peak DN':>9} {'noise DN':>9} "
             f"{'SNR':>8}"]
    for r in result["rows"]:
        t = ",".join(f"{v:.3f}" for v in r["transmittance"])
        lines.append(f"{r['colour']:<11} {r['distance_m']:>6g} {t:>20} {r['peak_dn']:>9.1f} "
                     f"{r['noise_dn']:>9.2f} {r['snr_median']:>8.1f}")
    for d, q in result["snr_ratio"].items():
        lines.append(f"blue-green / red SNR at {d} m: {q:.2f}")
    return "\n".join(lines)
