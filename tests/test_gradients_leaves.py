"""Gradients of the tunable leaves not covered elsewhere, through ``obsjax.simulate``, against
central finite differences: Kalman–Bucy Qw, Rv, P0; extended Kalman Q, R, P0; TLO ρ̄;
Kreisselmeier poles; finite-window α, β.

Each loss is a scalar of a short simulation with fixed Heun steps (the loss is then a smooth
function of the parameters, and autodiff and differences see the same discrete map); matrix leaves
are perturbed along symmetric directions (their checks require symmetry), and the autodiff gradient
contracted with the same direction is compared.
"""

from __future__ import annotations

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import obsjax
from obsjax._reproduce.adaptive import KREISSELMEIER_2

# Fixed Heun steps (simulate's direct fixed-step path): the loss is then a smooth function of the
# gains (no step-size decisions), so central differences are clean, and a 2-stage solver compiles
# fast.
FIXED = dict(solver=diffrax.Heun(), dt0=0.01, adaptive=False)


def _symmetric_directions(n):
    dirs = []
    for i in range(n):
        for j in range(i, n):
            E = np.zeros((n, n))
            E[i, j] = E[j, i] = 1.0
            dirs.append(E)
    return dirs


def _compiled(J):
    """J and ∇J compiled once per problem (the tests of one family share them)."""
    return jax.jit(J), jax.jit(jax.grad(J))


def _check(compiled, params, name, directions, h=1e-5, rtol=2e-6):
    """<∇J, V> against (J(p + hV) − J(p − hV)) / 2h for each direction V of the leaf `name`."""
    Jj, gradj = compiled
    g = gradj(params)[name]
    for V in directions:
        V = jnp.asarray(V)
        up = dict(params, **{name: params[name] + h * V})
        dn = dict(params, **{name: params[name] - h * V})
        fd = (float(Jj(up)) - float(Jj(dn))) / (2 * h)
        ad = float(jnp.sum(g * V))
        assert abs(fd) > 1e-7, (name, V, fd)  # the leaf matters: the test can fail
        assert ad == pytest.approx(fd, rel=rtol, abs=1e-10), (name, V.tolist(), ad, fd)


# ---- Kalman-Bucy: Qw, Rv, P0
# ---------------------------------------------------------------------------------

PLANT = obsjax.LTI([[-0.5, 1.0], [-1.0, 0.2]], [[0.0], [1.0]], [[1.0, 0.0]])
MODEL = obsjax.LTI([[-0.5, 1.0], [-1.2, 0.1]], [[0.0], [1.0]], [[1.0, 0.0]])  # a mismatched model
U = obsjax.signals.multisine([1.0], [1.3])
TS = jnp.linspace(0.0, 3.0, 31)


@functools.cache
def _kb_problem():
    kb = obsjax.KalmanBucy(
        MODEL, Qw=0.2 * jnp.eye(2), Rv=0.05 * jnp.eye(1), P0=jnp.array([[1.0, 0.3], [0.3, 2.0]])
    )
    params = {"Qw": kb.Qw, "Rv": kb.Rv, "P0": kb.P0}

    def J(p):
        obs = eqx.tree_at(lambda o: (o.Qw, o.Rv, o.P0), kb, (p["Qw"], p["Rv"], p["P0"]))
        tr = obsjax.simulate(PLANT, obs, jnp.array([1.0, -1.0]), jnp.zeros(2), TS, u=U, **FIXED)
        return obsjax.losses.ise(tr)

    return _compiled(J), params


@pytest.mark.parametrize("name", ["Qw", "Rv", "P0"])
def test_kalman_bucy_gradients(name):
    compiled, params = _kb_problem()
    _check(compiled, params, name, _symmetric_directions(params[name].shape[0]))


# ---- extended Kalman filter: Q, R, P0
# --------------------------------------------------------------------------

DUFFING = obsjax.Nonlinear(
    lambda t, x, u: jnp.array([x[1], -x[0] - 0.3 * x[1] - 0.5 * x[0] ** 3 + u[0]]),
    lambda t, x, u: x[:1],
    2,
    1,
    1,
)


@functools.cache
def _ekf_problem():
    ekf = obsjax.ExtendedKalman(
        DUFFING, Q=jnp.array([[0.1, 0.02], [0.02, 0.2]]), R=0.02, P0=jnp.eye(2)
    )
    params = {"Q": ekf.Q, "R": ekf.R, "P0": ekf.P0}

    def J(p):
        obs = eqx.tree_at(lambda o: (o.Q, o.R, o.P0), ekf, (p["Q"], p["R"], p["P0"]))
        tr = obsjax.simulate(DUFFING, obs, jnp.array([1.0, 0.5]), jnp.zeros(2), TS, u=U, **FIXED)
        return obsjax.losses.ise(tr)

    return _compiled(J), params


@pytest.mark.parametrize("name", ["Q", "R", "P0"])
def test_extended_kalman_gradients(name):
    compiled, params = _ekf_problem()
    _check(compiled, params, name, _symmetric_directions(params[name].shape[0]))


# ---- TLO: nominal PD-eigenvalues ρ̄
# ----------------------------------------------------------------------------


@pytest.mark.extended
def test_tlo_rho_bar_gradient():
    """Van der Pol with an unmodelled disturbance; the gain designed along ξ̄ = 0 with the
    PD-spectrum ρ̄ ω/ε."""

    def f(d):
        return lambda t, x, u: jnp.array([x[1], (1 - x[0] ** 2) * x[1] - x[0] + d * jnp.sin(2 * t)])

    h = lambda t, x, u: x[:1]  # noqa: E731
    plant, model = obsjax.Nonlinear(f(0.5), h, 2, 1), obsjax.Nonlinear(f(0.0), h, 2, 1)
    tlo = obsjax.TrajectoryLinearization(
        model, [-1.0, -2.0], 2.0, 0.5, nominal=lambda t: (jnp.zeros(2), jnp.zeros(0))
    )
    ts = jnp.linspace(0.0, 2.0, 41)

    def J(p):
        obs = eqx.tree_at(lambda o: o.rho_bar, tlo, p["rho_bar"])
        tr = obsjax.simulate(plant, obs, jnp.array([2.0, 0.0]), jnp.zeros(2), ts, **FIXED)
        return obsjax.losses.ise(tr)

    _check(_compiled(J), {"rho_bar": tlo.rho_bar}, "rho_bar", np.eye(2))


# ---- Kreisselmeier: the poles of F
# ----------------------------------------------------------------------------


@pytest.mark.extended
def test_kreisselmeier_poles_gradient():
    """d/d(poles) of the parameter-error integral ∫‖p − p*‖² (p* = [f − a; b] moves with the
    poles too)."""
    ex = KREISSELMEIER_2
    plant = obsjax.kreisselmeier_form(ex["a"], ex["b"])
    u = obsjax.signals.multisine(ex["amplitudes"], ex["frequencies"])
    obs0 = obsjax.Kreisselmeier(2, [-2.0, -3.0], 2.0)
    ts = jnp.linspace(0.0, 10.0, 41)

    def J(p):
        obs = eqx.tree_at(lambda o: o.poles, obs0, p["poles"])
        pstar = obs.matching_point(jnp.asarray(ex["a"]), jnp.asarray(ex["b"]))
        tr = obsjax.simulate(plant, obs, jnp.ones(2), jnp.zeros(2), ts, u=u, **FIXED)
        e2 = jnp.sum((tr.z.p - pstar) ** 2, axis=-1)
        return jnp.sum(0.5 * (e2[1:] + e2[:-1]) * jnp.diff(ts))

    _check(_compiled(J), {"poles": obs0.poles}, "poles", np.eye(2))


# ---- finite window: the weights α, β of (15), through the simulated observer
# -----------------------------------


@pytest.mark.extended
def test_finite_window_alpha_beta_gradients():
    """Formula (25) (general γᵢ = βᵢ/αᵢ), a plant that differs from the model and an input, so the
    window estimate depends on the weights; T = 1.03 and 3 pieces keep the reset instants (kT/3) off
    the 0.1 grid."""
    model = obsjax.LTI([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[2.0, 0.0]])
    plant = obsjax.LTI([[0.0, 1.0], [-0.4, -0.1]], [[0.0], [1.0]], [[2.0, 0.0]])
    fw = obsjax.FiniteWindow(model, 1.03, alpha=[1.0, 2.0], beta=[0.5, 1.5], n_chunks=3)
    assert fw.formula == "(25)"
    ts = jnp.linspace(0.0, 2.0, 21)

    def J(p):
        obs = eqx.tree_at(lambda o: (o.alpha, o.beta), fw, (p["alpha"], p["beta"]))
        tr = obsjax.simulate(
            plant, obs, jnp.array([1.0, -0.5]), jnp.array([0.3, 0.2]), ts, u=U, **FIXED
        )
        return obsjax.losses.ise(tr)

    params = {"alpha": fw.alpha, "beta": fw.beta}
    compiled = _compiled(J)
    _check(compiled, params, "alpha", np.eye(2), rtol=1e-5)
    _check(compiled, params, "beta", np.eye(2), rtol=1e-5)
