"""The sensor model against its own physical definitions: photon transfer, read noise,
saturation, quantisation, seeding; and its configuration section."""

import numpy as np
import pytest

from wai_core.config import SensorConfig, config_from_dict
from wai_core.errors import WaiInputError
from wai_core.sensor import (
    expose,
    exposure_for,
    full_scale_dn,
    gain_e_per_dn,
    integer_image,
    noise_rng,
    to_unit,
)

# A 12-bit camera of 10 000 e- full well: g = 10000 / 4095 = 2.442 e-/DN, read noise 2.9 DN.
SENSOR = SensorConfig(enabled=True, full_well_e=10000.0, read_noise_e=7.0, bits=12,
                      dark_level_dn=100.0)
FLAT = np.ones((200, 200))  # a flat field of radiance 1: the exposure is then electrons


def _frames(sensor, electrons, seed=0):
    """Two frames of a flat field; their difference cancels any fixed pattern (PTC practice)."""
    rng = np.random.default_rng(seed)
    return expose(FLAT, electrons, sensor, rng), expose(FLAT, electrons, sensor, rng)


def test_photon_transfer_gives_the_gain():
    # var(DN) = (mu - d) / g + (sigma_r / g)^2 + 1/12: the slope against the mean is 1 / g.
    means, variances = [], []
    for electrons in (500.0, 1500.0, 3000.0, 5000.0, 7000.0, 9000.0):
        a, b = _frames(SENSOR, electrons)
        means.append(0.5 * (a.mean() + b.mean()))
        variances.append(np.var(a - b) / 2)
    slope = np.polyfit(means, variances, 1)[0]
    assert 1 / slope == pytest.approx(gain_e_per_dn(SENSOR), rel=0.03)
    # the means sit where the exposure puts them
    assert means[0] == pytest.approx(500 / gain_e_per_dn(SENSOR) + 100, rel=0.01)


def test_dark_frames_give_the_read_noise():
    a, b = _frames(SENSOR, 0.0, seed=1)
    std_dn = np.sqrt(np.var(a - b) / 2 - 1 / 12)  # less the quantisation's 1/12 DN^2
    assert std_dn * gain_e_per_dn(SENSOR) == pytest.approx(SENSOR.read_noise_e, rel=0.03)
    assert a.mean() == pytest.approx(100.0, abs=0.05)  # the dark level, DN


def test_saturation_clips_at_the_full_well():
    rng = np.random.default_rng(2)
    top = full_scale_dn(SENSOR)
    bright = expose(FLAT, 5 * SENSOR.full_well_e, SENSOR, rng)
    assert bright.max() <= top
    # The dark level lifts a full well over the ADC's range: a bright field reads full scale.
    assert np.all(bright == top)
    assert np.all(to_unit(bright, SENSOR) == 1.0)
    assert np.all(expose(FLAT, 1e9, SENSOR, None) == top)


@pytest.mark.parametrize("bits", [8, 12, 16])
def test_bits_quantise(bits):
    s = SensorConfig(enabled=True, bits=bits, read_noise_e=3.0)
    dn = expose(np.linspace(0, 1, 5000), 0.8 * s.full_well_e, s, noise_rng(0, "ramp"))
    assert np.all(dn == np.rint(dn)) and dn.max() <= 2**bits - 1
    raw = integer_image(to_unit(dn, s), s)
    assert raw.dtype == (np.uint8 if bits == 8 else np.uint16)
    # The container's full scale maps back to the DN exactly.
    back = np.rint(raw.astype(float) * (2**bits - 1) / np.iinfo(raw.dtype).max)
    assert np.array_equal(back, dn)


def test_noise_is_seeded_by_scene_and_image():
    img = np.full((50, 50), 0.5)
    a = expose(img, 2000.0, SENSOR, noise_rng(3, "pattern"))
    assert np.array_equal(a, expose(img, 2000.0, SENSOR, noise_rng(3, "pattern")))
    assert not np.array_equal(a, expose(img, 2000.0, SENSOR, noise_rng(3, "view")))
    assert not np.array_equal(a, expose(img, 2000.0, SENSOR, noise_rng(4, "pattern")))


def test_averaged_frames_and_exposure():
    # The mean of N frames has 1/N of one frame's variance; the exposure puts p99.9 at the
    # signal level.
    one = expose(FLAT, 4000.0, SENSOR, noise_rng(0, "a"))
    avg = expose(FLAT, 4000.0, SENSOR, noise_rng(0, "b"), frames=16)
    assert np.var(avg) == pytest.approx(np.var(one) / 16, rel=0.15)
    ramp = np.linspace(0, 2.0, 100_001)
    x = exposure_for(ramp, SENSOR)
    assert np.percentile(ramp, 99.9) * x == pytest.approx(0.5 * SENSOR.full_well_e)
    assert exposure_for(np.zeros(10), SENSOR) == 0.0


def test_sections_are_optional_and_checked(paper_cfg):
    data = paper_cfg.to_dict()
    for name in ("sensor", "motion"):
        data.pop(name)
    cfg = config_from_dict(data)
    assert not cfg.sensor.enabled and cfg.motion.exposure_s == 0.0
    assert "sensor" in cfg.to_dict() and "motion" in cfg.to_dict()  # recorded in scene.json
    for section, key, value, match in [
        ("sensor", "bits", 4, r"\[sensor\]\.bits"),
        ("sensor", "full_well_e", 0.0, r"\[sensor\]\.full_well_e"),
        ("sensor", "read_noise_e", -1.0, r"\[sensor\]\.read_noise_e"),
        ("sensor", "enabled", "yes", r"\[sensor\]\.enabled"),
        ("sensor", "gain", 1.0, r"\[sensor\]\.gain"),
        ("motion", "exposure_s", -0.01, r"\[motion\]\.exposure_s"),
        ("motion", "max_subframes", 0, r"\[motion\]\.max_subframes"),
    ]:
        bad = paper_cfg.to_dict()
        bad[section][key] = value
        with pytest.raises(WaiInputError, match=match):
            config_from_dict(bad)
