"""A camera sensor: exposure, photon shot noise, read noise, full well and ADC (pure NumPy).

A rendered image is linear radiance ``L`` (arbitrary render units). The sensor turns it into
digital numbers (DN), per pixel and colour channel independently:

    e_mean = x L                                   x: exposure, e- per radiance unit
    e      = min(Poisson(e_mean), FW)              photon shot noise; the well saturates at FW
    DN     = clip(round(e / g + r / g + d), 0, F)  r ~ N(0, sigma_r^2): read noise, e- rms

with conversion gain ``g`` (e-/DN, default ``FW / F``: the ADC spans the well), dark level
``d`` (DN) and full scale ``F = 2^bits - 1``. The photon-transfer relation follows: on a flat
field of mean ``mu`` DN (above ``d``), ``var(DN) = (mu - d) / g + (sigma_r / g)^2 + 1/12``
(the last term is the quantisation), so the slope of variance against mean is ``1 / g``.

The exposure ``x`` is a camera setting: by default chosen so that the 99.9th percentile of the
camera's flat-water reference reaches ``signal_level`` of the well (:func:`exposure_for`).
Images leave the sensor as ``DN / F`` (linear, in [0, 1]), what :func:`wai_core.images.read_image`
makes of an integer PNG at the ADC depth (:func:`integer_image`).

Noise is seeded: :func:`noise_rng` draws from the scene seed and the image's name, so the same
seed gives the same noise and different images (or frames) different noise.
"""

from __future__ import annotations

import zlib

import numpy as np
from numpy.typing import NDArray

from wai_core.config import SensorConfig

__all__ = [
    "expose",
    "exposure_for",
    "full_scale_dn",
    "gain_e_per_dn",
    "integer_image",
    "noise_rng",
    "to_unit",
]

EXPOSURE_PERCENTILE = 99.9
"""Percentile of the reference image that ``signal_level`` places in the well."""


def full_scale_dn(sensor: SensorConfig) -> int:
    """The ADC's largest code ``F = 2^bits - 1``, DN."""
    return 2 ** int(sensor.bits) - 1


def gain_e_per_dn(sensor: SensorConfig) -> float:
    """Conversion gain ``g``, e-/DN: the configured one, else ``full_well_e / F``."""
    if sensor.gain_e_per_dn > 0:
        return float(sensor.gain_e_per_dn)
    return float(sensor.full_well_e) / full_scale_dn(sensor)


def exposure_for(reference: NDArray, sensor: SensorConfig) -> float:
    """Exposure ``x`` (e- per radiance unit) that brings the reference image's 99.9th
    percentile to ``signal_level * full_well_e``.

    Parameters
    ----------
    reference : (H, W) or (H, W, 3) ndarray
        Linear radiance, e.g. the flat-water image of the camera.
    sensor : SensorConfig

    Returns
    -------
    float
        e- per radiance unit; 0 for a black reference (nothing to expose for).
    """
    level = float(np.percentile(np.asarray(reference, dtype=np.float64), EXPOSURE_PERCENTILE))
    if not np.isfinite(level) or level <= 0:
        return 0.0
    return float(sensor.signal_level * sensor.full_well_e / level)


def noise_rng(seed: int, name: str) -> np.random.Generator:
    """The generator of one image's sensor noise, from the scene seed and the image's name
    (e.g. ``"pattern"`` or ``"frame003/view"``): reproducible, distinct per image."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), zlib.crc32(name.encode())]))


def expose(
    radiance: NDArray,
    electrons_per_unit: float,
    sensor: SensorConfig,
    rng: np.random.Generator | None,
    frames: int = 1,
) -> NDArray[np.float64]:
    """The sensor's reading of a radiance image, DN (float: averaged frames keep fractions).

    Parameters
    ----------
    radiance : ndarray, any shape
        Linear radiance (negative values count as 0).
    electrons_per_unit : float
        Exposure ``x``, e- per radiance unit.
    sensor : SensorConfig
    rng : numpy.random.Generator or None
        Noise source; None gives the noiseless reading ``clip(min(x L, FW) / g + d, 0, F)``
        (no shot or read noise, no quantisation: the expectation of a ground truth).
    frames : int
        Frames averaged (>= 1), each with its own noise and quantisation.

    Returns
    -------
    ndarray of float64, the shape of ``radiance``
        DN, in ``[0, F]``.
    """
    e_mean = np.maximum(np.asarray(radiance, dtype=np.float64), 0.0) * float(electrons_per_unit)
    fw, g, d = sensor.full_well_e, gain_e_per_dn(sensor), sensor.dark_level_dn
    top = full_scale_dn(sensor)
    if rng is None:
        return np.clip(np.minimum(e_mean, fw) / g + d, 0.0, top)
    total = np.zeros(e_mean.shape)
    for _ in range(max(int(frames), 1)):
        e = np.minimum(rng.poisson(e_mean).astype(np.float64), fw)
        if sensor.read_noise_e > 0:
            e += rng.normal(0.0, sensor.read_noise_e, e.shape)
        total += np.clip(np.rint(e / g + d), 0.0, top)
    return total / max(int(frames), 1)


def to_unit(dn: NDArray, sensor: SensorConfig) -> NDArray[np.float32]:
    """DN as a fraction of the ADC full scale, ``DN / F`` (float32), what the EXR holds."""
    return (np.asarray(dn, dtype=np.float64) / full_scale_dn(sensor)).astype(np.float32)


def integer_image(unit: NDArray, sensor: SensorConfig) -> NDArray:
    """The integer image a camera writes at the ADC depth, from ``DN / F``.

    8 bits: uint8 DN. 9 to 16 bits: uint16 ``round(DN * 65535 / F)``: the DN stretched to the
    16-bit full scale, so a reader dividing by 65535 (:func:`wai_core.images.read_image`)
    gets ``DN / F`` back within 1/131070; ``round(v * F / 65535)`` recovers the DN.

    Parameters
    ----------
    unit : ndarray, any shape
        ``DN / F`` in [0, 1].
    sensor : SensorConfig

    Returns
    -------
    ndarray of uint8 or uint16, the shape of ``unit``
    """
    unit = np.clip(np.asarray(unit, dtype=np.float64), 0.0, 1.0)
    if sensor.bits <= 8:
        return np.rint(unit * 255).astype(np.uint8)
    return np.rint(unit * 65535).astype(np.uint16)
