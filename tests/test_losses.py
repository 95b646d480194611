"""The losses on their own (no solve): against NumPy on the same samples, in any units; bad arguments."""

import math
from fractions import Fraction
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import obsjax
from obsjax.tuning._losses import tail_count

RNG = np.random.default_rng(7)
TS = np.sort(np.concatenate([[0.0, 6.0], RNG.uniform(0.0, 6.0, 42)]))  # non-uniform
ERR = np.exp(-0.8 * TS)[:, None] * RNG.normal(size=(TS.size, 3)) + 0.05 * np.sin(3 * TS)[:, None]


def _traj(err, ts=TS):
    return SimpleNamespace(ts=jnp.asarray(ts), error=jnp.asarray(err))


@pytest.mark.parametrize("units", [1e-200, 1e200])
def test_itae_and_peak_do_not_underflow_or_overflow(units):
    """‖x̃‖ was √Σx̃²: errors of 1e-200 gave itae = peak = 0 and errors of 1e200 gave NaN, both representable
    values; an infinite error gave a NaN peak instead of inf."""
    err = units * ERR
    nrm = units * np.linalg.norm(ERR, axis=1)
    f = (TS - TS[0]) * nrm
    itae_ref = np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(TS))
    np.testing.assert_allclose(float(obsjax.losses.itae(_traj(err))), itae_ref, rtol=1e-12)
    pk = float(obsjax.losses.peak(_traj(err)))
    assert nrm.max() <= pk <= nrm.max() * (1 + math.log(TS.size) / 50)
    g = jax.grad(lambda e: obsjax.losses.peak(_traj(e)) / units)(jnp.asarray(err))
    assert np.all(np.isfinite(np.asarray(g)))
    inf_err = np.array(ERR).copy()
    inf_err[5, 1] = np.inf
    assert float(obsjax.losses.peak(_traj(inf_err))) == np.inf
    assert float(obsjax.losses.itae(_traj(inf_err))) == np.inf


def test_peak_checks_a_traced_sharpness():
    """Under jit a negative sharpness gave −3.36 for a maximum of 1.0 ("never below the maximum")."""
    tr = _traj(ERR)
    assert float(jax.jit(lambda s: obsjax.losses.peak(tr, s))(50.0)) >= np.linalg.norm(ERR, axis=1).max()
    with pytest.raises(Exception, match="`sharpness` must be a positive finite scalar"):
        jax.block_until_ready(jax.jit(lambda s: obsjax.losses.peak(tr, s))(-1.0))


@pytest.mark.parametrize("units", [1e-13, 1.0, 1e8])
def test_itae_and_peak_in_any_units(units):
    """An absolute smoothing constant (√(‖x̃‖² + 1e-24), and a 1e-12 floor in peak) made itae 83× and peak
    4.7× too large for errors of order 1e-13 (states in small units)."""
    err = units * ERR
    nrm = np.linalg.norm(err, axis=1)
    f = (TS - TS[0]) * nrm
    itae_np = np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(TS))
    np.testing.assert_allclose(obsjax.losses.itae(_traj(err)), itae_np, rtol=1e-12)
    p = float(obsjax.losses.peak(_traj(err)))
    M = nrm.max()
    assert M <= p <= M * (1 + math.log(TS.size) / 50.0)
    np.testing.assert_allclose(p / units, float(obsjax.losses.peak(_traj(ERR))), rtol=1e-12)  # scale invariant
    np.testing.assert_allclose(obsjax.losses.ise(_traj(err)) / units**2, obsjax.losses.ise(_traj(ERR)), rtol=1e-12)


def test_peak_is_the_documented_smooth_maximum():
    K, s = 1001, 50.0
    flat = _traj(np.ones((K, 1)), np.linspace(0.0, 1.0, K))
    np.testing.assert_allclose(obsjax.losses.peak(flat, s), 1 + math.log(K) / s, rtol=1e-12)  # the bound, met
    spike = np.full((K, 1), 0.1)
    spike[K // 3] = 2.0
    np.testing.assert_allclose(obsjax.losses.peak(_traj(spike, np.linspace(0.0, 1.0, K)), s), 2.0, rtol=1e-12)
    zero = _traj(np.zeros((K, 2)), np.linspace(0.0, 1.0, K))
    assert float(obsjax.losses.peak(zero, s)) == 0.0 and float(obsjax.losses.itae(zero)) == 0.0
    assert np.all(np.asarray(jax.grad(lambda e: obsjax.losses.peak(_traj(e)))(jnp.zeros((5, 2)))) == 0.0)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="`sharpness` must be a positive finite scalar"):
            obsjax.losses.peak(flat, bad)


def test_loss_gradients_match_central_differences_including_a_zero_error():
    err = ERR.copy()
    err[5] = 0.0  # ‖x̃‖ = 0 at one save time: the norm has no derivative there; the losses stay finite
    for loss in (obsjax.losses.itae, obsjax.losses.peak):
        J = jax.jit(lambda e, loss=loss: loss(_traj(e)))
        g = np.asarray(jax.grad(J)(jnp.asarray(err)))
        assert np.all(np.isfinite(g)) and np.all(g[5] == 0.0)
        d = RNG.normal(size=err.shape)
        d[5] = 0.0
        h = 1e-6
        fd = (float(J(jnp.asarray(err + h * d))) - float(J(jnp.asarray(err - h * d)))) / (2 * h)
        np.testing.assert_allclose(np.sum(g * d), fd, rtol=1e-6)


def test_tail_count_is_exact_for_any_n():
    assert tail_count(0.95, 20) == 1  # (1 − 0.95)·20 = 1.0000000000000009 in binary
    assert tail_count(0.1, 123456789) == 111111111  # a fixed rounding slack gave 111111110
    assert tail_count(0.999, 10) == 1 and tail_count(0.0, 7) == 7
    for alpha in np.round(RNG.uniform(0, 1, 200), 3):
        for n in (1, 7, 20, 1000, 10**9 + 7):
            assert tail_count(alpha, n) == max(1, math.ceil((1 - Fraction(str(alpha))) * n))


def test_output_error_weights_are_checked():
    """A negative weight gave a negative loss (tune_on_data would maximise that output's error); NaN gave
    NaN; a (1,) weight for two outputs was broadcast."""
    innov = RNG.normal(size=(30, 2))
    est = SimpleNamespace(ts=jnp.linspace(0.0, 3.0, 30), innovation=jnp.asarray(innov), valid=jnp.ones(30, bool))
    w = np.array([2.0, 0.5])
    np.testing.assert_allclose(obsjax.losses.output_error(est, weight=w), np.mean(np.sum(w * innov**2, 1)), rtol=1e-13)
    for bad, match in (([-1.0, 1.0], "≥ 0"), ([np.nan, 1.0], "finite"), ([0.0, 0.0], "at least one"),
                       ([2.0], r"shape \(2,\)"), (np.eye(2), r"shape \(2,\)"), ([1j, 1.0], "real")):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            obsjax.losses.output_error(est, weight=bad)
    with pytest.raises(Exception, match="`weight` must be finite and ≥ 0"):
        jax.block_until_ready(jax.jit(lambda w: obsjax.losses.output_error(est, weight=w))(jnp.asarray([-1.0, 1.0])))


def test_multisine_phases_must_have_the_shape_of_the_amplitudes():
    a, w = np.array([[1.0, 0.5, 0.2], [0.3, 0.2, 0.1]]), np.array([[0.7, 1.9, 3.1], [0.4, 1.1, 2.3]])
    ph = RNG.uniform(0, 2 * np.pi, size=(2, 3))
    u = obsjax.signals.multisine(a, w, ph)
    t = 0.37
    np.testing.assert_allclose(u(t), np.sum(a * np.sin(w * t + ph), axis=1), rtol=1e-14)
    with pytest.raises(ValueError, match="`phases` must have the shape of `amplitudes`"):
        obsjax.signals.multisine(a, w, ph.T)  # the right size, scrambled before
    with pytest.raises(ValueError, match="`phases` must have the shape of `amplitudes`"):
        obsjax.signals.multisine(a, w, ph.ravel())
    with pytest.raises(ValueError, match="`phases` must have the shape of `amplitudes`"):
        obsjax.signals.multisine([1.0, 0.5], [1.0, 2.0], [[0.1], [0.2]])
    np.testing.assert_allclose(obsjax.signals.multisine(1.0, 2.0, 0.3)(t), np.sin(2.0 * t + 0.3), rtol=1e-14)
