"""The pattern fit's loss on Dr.Jit: the same loss as the NumPy model, a gradient that is its
finite difference, reruns that agree bit for bit, and where it serves."""

from __future__ import annotations

import numpy as np
import pytest

from restoration import InverseRenderingOptions
from restoration.fit import BSplineSurface
from restoration.inverse_rendering import _backend, _Objective
from restoration.pattern_jit import JitImageLoss
from restoration.pattern_model import DotParticles, PatternModel, Raster
from wai_core import load_system, with_keys
from wai_core.errors import WaiInputError


def _setup(roughness: float, seed: int = 0):
    """A loss at a wavy spline's coefficients against the image of another (NumPy's
    objective, its mask, brightness and the particles' hits set as a pass sets them)."""
    rig = load_system("paper").rig
    rng = np.random.default_rng(seed)
    parts = DotParticles.of(rig, rig.dot_panel_px[rig.lit][::5], order=3,
                            roughness=roughness, facets=4)
    shape = (rig.camera_s.height_px, rig.camera_s.width_px)
    model = PatternModel(rig, parts, shape)
    h0 = rig.cfg.water.h0_mm
    t0 = model.flat_t(h0)
    xy = (parts.origin_mm + t0[:, None] * parts.dirs)[:, :2]
    spline = BSplineSurface.covering(xy, 12.0, h0)
    spline.coeffs += rng.normal(0.0, 0.3, spline.coeffs.shape)
    truth = BSplineSurface(spline.x0_mm, spline.y0_mm, spline.step_mm,
                           spline.coeffs + rng.normal(0.0, 0.3, spline.coeffs.shape))
    raster = Raster(shape, 1.5)
    image_of = _Objective(model, raster, np.zeros(shape), truth.coeffs.shape, t0, 0.0)
    observed = image_of.image(model.trace(truth, t0)) + rng.normal(0.0, 1e-3, shape)
    obj = _Objective(model, raster, observed, spline.coeffs.shape, t0, 0.0)
    traced = model.trace(spline, t0)
    obj.t = traced.t
    obj.set_mask(traced, 8.0)
    obj.fit_amplitudes(traced)
    loss = JitImageLoss(model, raster, spline, observed, obj.mask, obj.norm,
                        obj.amplitudes[parts.dot] * obj.light, obj.background, traced.t,
                        backend="llvm")
    return obj, loss, spline, rng


@pytest.mark.parametrize("roughness", [0.0, 0.005])
def test_the_same_loss_as_the_numpy_model(roughness):
    # Two implementations written apart (a hand-written adjoint with finite-difference ray
    # Jacobians, and Dr.Jit's automatic one): the same loss to rounding, the same gradient
    # to the NumPy Jacobians' finite differences.
    obj, loss, spline, rng = _setup(roughness)
    c = spline.coeffs.ravel() + rng.normal(0.0, 0.02, spline.coeffs.size)
    t = obj.t.copy()
    numpy_loss, numpy_grad = obj(c, spline)
    jit_loss, jit_grad = loss(c)
    assert jit_loss == pytest.approx(numpy_loss, rel=1e-10)
    assert np.linalg.norm(jit_grad - numpy_grad) < 2e-3 * np.linalg.norm(numpy_grad)
    assert np.allclose(loss.t, obj.t, atol=1e-9) and not np.allclose(obj.t, t, atol=1e-9)


def test_its_gradient_is_its_finite_difference():
    obj, loss, spline, rng = _setup(0.005, seed=3)
    c = spline.coeffs.ravel()
    for _ in range(3):
        _, grad = loss(c)
        v = rng.normal(size=c.size)
        eps = 1e-4
        start = loss.t
        up = loss(c + eps * v)[0]
        loss._t = loss._jit.Float64(start)  # each side from the same hits
        down = loss(c - eps * v)[0]
        loss._t = loss._jit.Float64(start)
        fd = (up - down) / (2 * eps)
        assert np.isclose(grad @ v, fd, rtol=0.02, atol=0.005 * np.linalg.norm(grad))


def test_reruns_agree_bit_for_bit_and_the_threads_come_back():
    import drjit as dr

    _, loss, spline, _ = _setup(0.005, seed=5)
    c = spline.coeffs.ravel()
    threads = dr.thread_count()
    start = loss.t
    with loss.in_order():
        assert dr.thread_count() == 1
        first = loss(c)
        loss._t = loss._jit.Float64(start)
        second = loss(c)
    assert dr.thread_count() == threads
    assert first[0] == second[0] and np.array_equal(first[1], second[1])


def test_the_backend_serves_the_ideal_pinhole_only():
    rig = load_system("paper").rig
    assert _backend("auto", rig) in ("llvm", "cuda") and _backend("numpy", rig) == "numpy"
    lens = with_keys(load_system("paper"), {"camera_s.principal_offset_px": [3.0, 0.0]}).rig
    assert _backend("auto", lens) == "numpy"
    with pytest.raises(WaiInputError, match="ideal pinhole"):
        _backend("drjit", lens)
    with pytest.raises(WaiInputError, match="backend"):
        InverseRenderingOptions(backend="torch")
