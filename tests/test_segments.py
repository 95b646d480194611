"""Breakpoints are segment boundaries of the integration: the plant's declared jumps (gradients with respect to
the reset period against central finite differences when every reset segment holds several jumps) and the
observer's discrete events (sampled-data observers against their discrete closed form)."""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import obsjax

A28 = np.array([[-2.0, 1.0], [0.0, -1.0]])
B28 = np.array([[0.0], [1.0]])
C28 = np.array([[1.0, 0.0]])
PLANT = obsjax.LTI(A28, B28, C28)
X0, XH0 = jnp.array([1.0, -1.0]), jnp.zeros(2)


def sim(*args, **kw):
    kw.setdefault("throw", False)
    return obsjax.simulate(*args, **kw)


# ---------------------------------------------------------------- item 6: jumps as segment boundaries

SWITCH = obsjax.switching_ltv_example(period=0.3, horizon=7.5)
SWITCH_UNDECLARED = obsjax.LTV(SWITCH.A_fn, SWITCH.C_fn)
LSR3 = obsjax.LeastSquaresReset(SWITCH, gamma=1.0, p0=1.0, T=1.93)
TS6 = jnp.array([0.0, 7.5])
X06 = jnp.array([1.0, -0.5, 0.8])


def _terminal(T, rtol, declared):
    obs = eqx.tree_at(lambda o: o.T, LSR3, T)
    plant = SWITCH if declared else SWITCH_UNDECLARED
    tr = obsjax.simulate(plant, obs, X06, jnp.zeros(3), TS6, rtol=rtol, atol=rtol * 1e-2, max_segments=4)
    return jnp.sum(tr.error[-1] ** 2)


_TERMINAL = jax.jit(jax.value_and_grad(_terminal), static_argnums=2)  # one compilation for values and slopes


@pytest.mark.extended
def test_reset_period_gradient_with_several_jumps_per_segment():
    """Issue item 6: a 3-state plant switching every 0.3 s, T = 1.93 (every reset segment of [0, 7.5] holds
    5-6 jumps), terminal squared error: d/dT against central differences at rtol 1e-6 and 1e-10."""
    T, h = 1.93, 1e-4
    edges = np.append(np.arange(4) * T, 7.5)
    jumps = np.asarray(SWITCH.jump_ts)
    assert min(np.sum((jumps > a) & (jumps < b)) for a, b in zip(edges[:-1], edges[1:])) >= 5
    for rtol, tol in ((1e-6, 1e-3), (1e-10, 1e-6)):
        g = float(_TERMINAL(T, rtol, True)[1])
        fd = (float(_TERMINAL(T + h, rtol, True)[0]) - float(_TERMINAL(T - h, rtol, True)[0])) / (2 * h)
        assert abs(g) > 1e-3
        np.testing.assert_allclose(g, fd, rtol=tol)


@pytest.mark.extended
def test_undeclared_jumps_give_finite_gradients():
    """Steps across an undeclared switch leave the LSR gain's domain on rejected steps (NaN stages); their
    gradient is zero, so the derivative is finite (not exact: declare the jumps)."""
    value, slope = _TERMINAL(1.93, 1e-6, False)
    assert np.isfinite(float(value)) and np.isfinite(float(slope))


@pytest.mark.extended
def test_undeclared_jumps_give_the_masked_batch_the_gradient_of_simulate():
    """The same on the masked loop of ``simulate_batch(lockstep=False)`` (adaptive steps per member): its
    rejected steps' NaN stages made the gradient NaN for the whole batch (status 0 for every member); now each
    member's derivative is that of its own solve by :func:`obsjax.simulate` (the diffrax back-end, the same
    steps up to rounding; ``jax.vmap`` over the members)."""
    x0s = jnp.array([[1.0, -0.5, 0.8], [0.3, 0.2, -1.0]])
    ts = jnp.linspace(0.0, 7.5, 16)
    kw = dict(rtol=1e-6, atol=1e-8, max_segments=4)

    def obs(T, g):
        return eqx.tree_at(lambda o: (o.T, o.gamma), LSR3, (T, g))

    def masked(T, g):
        tr = obsjax.simulate_batch(SWITCH_UNDECLARED, obs(T, g), x0s, jnp.zeros((2, 3)), ts, lockstep=False, **kw)
        return jnp.sum(tr.error**2), tr.status

    def alone(T, g):
        one = lambda x0: obsjax.simulate(SWITCH_UNDECLARED, obs(T, g), x0, jnp.zeros(3), ts, dt0=0.01, **kw)
        tr = jax.vmap(one)(x0s)
        return jnp.sum(tr.error**2), tr.status

    (v, st), g = jax.jit(jax.value_and_grad(masked, argnums=(0, 1), has_aux=True))(1.93, 1.0)
    (v1, st1), g1 = jax.jit(jax.value_and_grad(alone, argnums=(0, 1), has_aux=True))(1.93, 1.0)
    assert np.all(np.asarray(st) == 0) and np.all(np.asarray(st1) == 0)
    np.testing.assert_allclose(float(v), float(v1), rtol=1e-5)
    assert abs(float(g[0])) > 1e-2 and abs(float(g[1])) > 1.0
    np.testing.assert_allclose(np.array(g, float), np.array(g1, float), rtol=1e-4)


@pytest.mark.extended
def test_undeclared_jumps_with_direct_adjoint_give_the_default_gradient_in_both_modes():
    """``adjoint=diffrax.DirectAdjoint()`` allows both modes of differentiation; its rejected steps' NaN stages
    made the reverse-mode gradient NaN on every back-end (the diffrax solve of ``simulate``, the lock-step and
    the masked batch), with status 0.  Now reverse mode gives the default adjoint's gradient on each (the
    same steps: stop-gradient step sizes); forward mode (checked on the lock-step batch here, and on the
    masked loop against a closed form in test_adaptive_rk) gives it too."""
    x0s = jnp.array([[1.0, -0.5, 0.8], [0.3, 0.2, -1.0]])
    ts = jnp.linspace(0.0, 7.5, 16)
    kw = dict(rtol=1e-6, atol=1e-8, max_segments=4)
    direct = diffrax.DirectAdjoint()

    def obs(T, g):
        return eqx.tree_at(lambda o: (o.T, o.gamma), LSR3, (T, g))

    def loss(backend, adjoint):
        extra = {} if adjoint is None else {"adjoint": adjoint}

        def fn(p):
            if backend == "simulate":
                one = lambda x0: obsjax.simulate(
                    SWITCH_UNDECLARED, obs(p[0], p[1]), x0, jnp.zeros(3), ts, dt0=0.01, **kw, **extra
                )
                tr = jax.vmap(one)(x0s)
            else:
                tr = obsjax.simulate_batch(
                    SWITCH_UNDECLARED, obs(p[0], p[1]), x0s, jnp.zeros((2, 3)), ts,
                    lockstep=backend == "lockstep", **kw, **extra,
                )  # fmt: skip
            return jnp.sum(tr.error**2), tr.status

        return fn

    p = jnp.array([1.93, 1.0])
    for backend in ("simulate", "lockstep", "masked"):
        (_, st), ref = jax.jit(jax.value_and_grad(loss(backend, None), has_aux=True))(p)
        (_, st_d), rev = jax.jit(jax.value_and_grad(loss(backend, direct), has_aux=True))(p)
        assert np.all(np.asarray(st) == 0) and np.all(np.asarray(st_d) == 0), backend
        assert np.all(np.isfinite(np.asarray(rev))), (backend, rev)
        np.testing.assert_allclose(np.asarray(rev), np.asarray(ref), rtol=1e-6, err_msg=backend)
        if backend == "lockstep":
            fwd = jax.jit(jax.jacfwd(lambda q: loss(backend, direct)(q)[0]))(p)
            np.testing.assert_allclose(np.asarray(fwd), np.asarray(ref), rtol=1e-6, err_msg=backend)


# ---------------------------------------------------------------- events: sampled-data observers


class SampledLuenberger(obsjax.AbstractObserver):
    """x̂' = A x̂ + B u between samples, x̂⁺ = x̂ + K (y − C x̂) at t0 + k h, k < n (a sampled-data observer;
    the count n is static, so the horizon may be traced)."""

    model: obsjax.LTI
    K: jax.Array
    h: float = eqx.field(static=True)
    n: int = eqx.field(static=True)

    def init(self, t0, xhat0, y0):
        return xhat0

    def vector_field(self, t, z, y, u):
        return self.model.A @ z + self.model.B @ u

    def estimate(self, t, z, y):
        return z

    def event_times(self, t0, t1):
        return t0 + self.h * jnp.arange(self.n)

    def update(self, t, z, y, u):
        return z + self.K @ (y - self.model.C @ z)


SAMPLED = SampledLuenberger(PLANT, jnp.array([[0.6], [0.3]]), 0.25, 10)  # the 10th sample is past t1 = 2
TS_EV = np.linspace(0.0, 2.0, 17)  # every 0.125: on and between the samples; the last sample is t1
U = obsjax.signals.multisine([1.0, 0.5], [1.0, 2.7])


def _sampled_closed_form(K, x0, xh0):
    """x̃ = x̂ − x: x̃ ← (I − K C) x̃ at each sample (t0 included), x̃' = A x̃ between (u cancels)."""
    M = np.eye(2) - np.asarray(K) @ C28
    out, e, last = [], M @ np.asarray(xh0 - x0), 0.0
    for t in TS_EV:
        k = np.floor(t / 0.25 + 1e-9)
        while last < k * 0.25 - 1e-12:
            e = M @ scipy.linalg.expm(A28 * 0.25) @ e
            last += 0.25
        out.append(scipy.linalg.expm(A28 * (t - last)) @ e)
    return np.stack(out)


@pytest.mark.extended
def test_sampled_data_observer_matches_the_discrete_closed_form():
    ref = _sampled_closed_form(SAMPLED.K, X0, XH0)
    a = sim(PLANT, SAMPLED, X0, XH0, TS_EV, u=U, rtol=1e-11, atol=1e-13)
    b = sim(PLANT, SAMPLED, X0, XH0, TS_EV, u=U, adaptive=False, dt0=1e-2)  # the tableau scan
    c = jax.jit(lambda ts: sim(PLANT, SAMPLED, X0, XH0, ts, u=U, rtol=1e-11, atol=1e-13).error)(TS_EV)  # traced
    assert int(a.status) == int(b.status) == 0
    np.testing.assert_allclose(a.error, ref, atol=1e-9)
    np.testing.assert_allclose(b.error, ref, atol=1e-9)
    np.testing.assert_allclose(c, ref, atol=1e-9)


@pytest.mark.extended
def test_events_in_lock_step_and_their_gradient():
    x0s = jnp.array([[1.0, -1.0], [0.5, 2.0], [-1.0, 0.0]])
    xh0s = jnp.zeros((3, 2))
    lock = obsjax.simulate_batch(PLANT, SAMPLED, x0s, xh0s, TS_EV, rtol=1e-11, atol=1e-13)
    for i in range(3):
        np.testing.assert_allclose(lock.error[i], _sampled_closed_form(SAMPLED.K, x0s[i], xh0s[i]), atol=1e-9)

    @jax.jit
    def loss(k):  # fixed steps: the tableau scan with its events, differentiated by JAX
        obs = eqx.tree_at(lambda o: o.K, SAMPLED, jnp.array([[k], [0.3]]))
        return jnp.sum(sim(PLANT, obs, X0, XH0, TS_EV, adaptive=False, dt0=0.01).error ** 2)

    g = jax.grad(loss)(0.6)
    ref = lambda k: np.sum(_sampled_closed_form(np.array([[k], [0.3]]), X0, XH0) ** 2)
    np.testing.assert_allclose(g, (ref(0.6 + 1e-5) - ref(0.6 - 1e-5)) / 2e-5, rtol=1e-6)


class _Recorder(obsjax.AbstractObserver):
    """z = (clock, last clock seen by an event, last y seen by an event); resets zero the clock."""

    def init(self, t0, xhat0, y0):
        return (jnp.zeros(()), jnp.full((), -1.0), jnp.zeros(1))

    def vector_field(self, t, z, y, u):
        return (jnp.ones(()), jnp.zeros(()), jnp.zeros(1))

    def estimate(self, t, z, y):
        return jnp.zeros(2)

    @property
    def reset_period(self):
        return jnp.asarray(0.5)

    def reset(self, t, z):
        return (jnp.zeros(()), z[1], z[2])

    def event_times(self, t0, t1):
        return np.array([0.0, 0.3, 0.5, 1.0])

    def update(self, t, z, y, u):
        return (z[0], z[0], y)


@pytest.mark.extended
def test_event_semantics_reset_first_then_update_with_the_measurement():
    ts = np.array([0.0, 0.3, 0.4, 0.5, 0.75, 1.0])
    for kw in (dict(rtol=1e-10, atol=1e-12), dict(adaptive=False, dt0=0.01)):
        tr = sim(PLANT, _Recorder(), X0, XH0, ts, **kw)
        clock, seen, y_seen = tr.z
        # resets at t0 + kT < t1 only (none at t1 = 1.0); events on all of [t0, t1]
        np.testing.assert_allclose(clock, [0.0, 0.3, 0.4, 0.0, 0.25, 0.5], atol=1e-9)
        # events at 0 and 0.3 record the clock; at 0.5 the reset (first) has zeroed it; at t1 no reset
        np.testing.assert_allclose(seen, [0.0, 0.3, 0.3, 0.0, 0.0, 0.5], atol=1e-9)
        # the update sees y(t_e): the saved measurement at the same instant
        at = np.array([0, 1, 3, 5])
        np.testing.assert_allclose(np.asarray(y_seen)[at], np.asarray(tr.y)[at], atol=1e-9)


def test_a_save_time_just_before_a_reset_or_update_is_refused():
    """A save time less than the schedule's tolerance (1e-9 of the horizon) before an observer update or a
    reset was taken at the instant: on a 1000 s horizon the save time 0.5 µs before the Kalman update at
    t = 3 showed the updated estimate (1.7e-3 from the value before it, which the fixed-step path gave).
    It is refused now, on every path."""
    plant = obsjax.LTI([[0.0, 1.0], [-2.0, -0.3]], [[0.0], [1.0]], [[1.0, 0.0]])
    kf = obsjax.ContinuousDiscreteKalman(plant, Qw=0.1 * np.eye(2), Rv=np.array([[0.01]]), P0=np.eye(2), period=1.0)
    ls = obsjax.LeastSquaresReset(plant, gamma=5.0, p0=0.4, T=1.0)
    x0, xh0 = np.array([1.0, -1.0]), np.zeros(2)
    ts = np.array([0.0, 3.0 - 5e-7, 3.0, 1000.0])
    for obs in (kf, ls):
        with pytest.raises(ValueError, match=r"ts\[1\] .* before the (observer update \(event\)|reset) at t = 3\.0"):
            obsjax.simulate(plant, obs, x0, xh0, ts)
        with pytest.raises(ValueError, match="within the schedule's time tolerance"):
            obsjax.simulate(plant, obs, x0, xh0, ts, adaptive=False, dt0=0.01)
        with pytest.raises(ValueError, match="within the schedule's time tolerance"):
            obsjax.simulate_batch(plant, obs, x0[None], xh0[None], ts, lockstep=False)


@pytest.mark.extended
def test_save_times_at_an_update_to_rounding_or_clearly_before_it_are_accepted():
    """The other side of the refusal above: save times at the update instants to rounding and 2e-5
    before one are taken as before, the one before seeing the state before the update."""
    plant = obsjax.LTI([[0.0, 1.0], [-2.0, -0.3]], [[0.0], [1.0]], [[1.0, 0.0]])
    kf = obsjax.ContinuousDiscreteKalman(plant, Qw=0.1 * np.eye(2), Rv=np.array([[0.01]]), P0=np.eye(2), period=1.0)
    x0, xh0 = np.array([1.0, -1.0]), np.zeros(2)
    # at the instant to rounding (0.1·30 is 3.0000000000000004) and 2e-6 before it: accepted
    ts = np.concatenate([np.arange(0, 41) * 0.1, [3.0 - 2e-5]])
    ts.sort()
    tr = obsjax.simulate(plant, kf, x0, xh0, ts, rtol=1e-10, atol=1e-12)
    assert int(tr.status) == 0
    before, at = np.asarray(tr.xhat)[30], np.asarray(tr.xhat)[31]  # 3 − 2e-5 and 3.0000000000000004
    assert np.max(np.abs(before - at)) > 1e-4  # the update lies between them
