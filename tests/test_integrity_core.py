"""Integrity of the integration core: every door checks, statuses tell the truth (early), lock-step batches
isolate failures.  Breakpoints as segment boundaries (plant jumps, observer events) are tested in
``test_segments.py``."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import obsjax
from obsjax._integrate import _validate
from obsjax._integrate._schedule import MAX_RESET_SEGMENTS

A28 = np.array([[-2.0, 1.0], [0.0, -1.0]])
B28 = np.array([[0.0], [1.0]])
C28 = np.array([[1.0, 0.0]])
PLANT = obsjax.LTI(A28, B28, C28)
OBS = obsjax.Luenberger.from_poles(PLANT, [-3.0, -3.0])
TS = np.linspace(0.0, 2.0, 11)
X0, XH0 = jnp.array([1.0, -1.0]), jnp.zeros(2)


def sim(*args, **kw):
    kw.setdefault("throw", False)
    return obsjax.simulate(*args, **kw)


# ---------------------------------------------------------------- bad input: one test per class


def _plant3():
    return obsjax.LTI(np.diag([-1.0, -2.0, -3.0]), None, [[1.0, 1.0, 1.0]])


def _giode(F=np.diag([-4.0, -5.0, -6.0]), G=np.ones((3, 1)), T0=None):
    return obsjax.GeneralizedInverseODE(_plant3(), F, G, T0, horizon=(0.0, 10.0))


SHAPE_CASES = {
    "x0": (lambda: sim(PLANT, OBS, jnp.ones(3), XH0, TS), "`x0`"),
    "xhat0": (lambda: sim(PLANT, OBS, X0, jnp.zeros(3), TS), "`xhat0`"),
    # a batch's wrongly shaped estimates were named `xhat0`, which simulate_batch does not take
    "xhat0s (lock step)": (
        lambda: obsjax.simulate_batch(PLANT, OBS, jnp.ones((3, 2)), jnp.zeros((3, 3)), TS, lockstep=True),
        "`xhat0s` must have shape (3, 2)",
    ),
    "xhat0s (masked)": (
        lambda: obsjax.simulate_batch(PLANT, OBS, jnp.ones((3, 2)), jnp.zeros((3, 3)), TS, throw=False),
        "`xhat0s` must have shape (3, 2)",
    ),
    "xhat0s (fixed steps, vmap)": (
        lambda: obsjax.simulate_batch(
            PLANT, OBS, jnp.ones((3, 2)), jnp.zeros((3, 3)), TS, adaptive=False, dt0=0.1, throw=False
        ),
        "`xhat0s` must have shape (3, 2)",
    ),
    "observer n": (
        lambda: sim(PLANT, obsjax.Luenberger.from_poles(_plant3(), [-4.0, -5.0, -6.0]), X0, XH0, TS),
        "`observer`",
    ),
    "observer m": (
        lambda: sim(obsjax.LTI(A28, B28, np.eye(2)), OBS, X0, XH0, TS),
        "`observer` expects m = 1",
    ),
    # the plant's inputs against the observer model's: the message was an inner dot_general error
    "observer p": (
        lambda: sim(obsjax.LTI(A28, np.ones((2, 2)), C28), OBS, X0, XH0, TS),
        "`observer` expects p = 1 input(s) (its model's inputs) but `plant` has p = 2",
    ),
    "u": (lambda: sim(PLANT, OBS, X0, XH0, TS, u=lambda t: jnp.ones(2)), "`u(t)`"),
    "controller": (
        lambda: sim(PLANT, OBS, X0, XH0, TS, controller=lambda t, xh: jnp.ones(3)),
        "`controller(t, x̂)`",
    ),
    "noise sigma": (
        lambda: sim(PLANT, OBS, X0, XH0, TS, noise=obsjax.noise.BandLimitedNoise([0.1, 0.1, 0.1]), key=jax.random.key(0)),
        "`noise.sigma`",
    ),
    # a (1,) σ for two outputs was taken as one intensity for both
    "noise sigma (1,) for m = 2": (
        lambda: sim(
            obsjax.LTI(A28, B28, np.eye(2)),
            obsjax.Luenberger.from_poles(obsjax.LTI(A28, B28, np.eye(2)), [-4.0, -5.0]),
            X0, XH0, TS, noise=obsjax.noise.BandLimitedNoise([0.1]), key=jax.random.key(0),
        ),
        "`noise.sigma`",
    ),
}


@pytest.mark.parametrize("case", list(SHAPE_CASES))
def test_dimension_mismatch_names_the_argument(case):
    call, name = SHAPE_CASES[case]
    with pytest.raises(ValueError, match="must|expects|has") as e:
        call()
    msg = str(e.value)
    assert name in msg and ("got" in msg or "but `plant` has" in msg), msg


VALUE_CASES = {
    "A nan": (lambda: obsjax.LTI([[np.nan, 0.0], [0.0, -1.0]], None, [[1.0, 0.0]]), "`A`"),
    "B inf": (lambda: obsjax.LTI(A28, [[np.inf], [1.0]], C28), "`B`"),
    "A complex": (lambda: obsjax.LTI(A28 + 1j, B28, C28), "`A` must be real"),
    "LTV A(t) nan": (lambda: obsjax.LTV(lambda t: jnp.full((2, 2), jnp.nan), lambda t: jnp.ones((1, 2))), "`A(t)"),
    "Nonlinear n = 0": (lambda: obsjax.Nonlinear(lambda t, x, u: x, lambda t, x, u: x[:1], n=0, m=1), "`n`"),
    "jump_ts nan": (lambda: obsjax.LTI(A28, B28, C28, jump_ts=[0.5, np.nan]), "`jump_ts`"),
    "white sigma nan": (lambda: obsjax.noise.WhiteNoise(np.nan), "`sigma`"),
    "band sigma < 0": (lambda: obsjax.noise.BandLimitedNoise(-0.1), "`sigma`"),
    # a boolean was read as 1.0 and a complex dt raised float()'s TypeError
    "band sigma bool": (lambda: obsjax.noise.BandLimitedNoise(True), "`sigma` must be a real intensity"),
    "white sigma bool list": (lambda: obsjax.noise.WhiteNoise([0.1, True]), "`sigma` must be a real intensity"),
    "band dt bool": (lambda: obsjax.noise.BandLimitedNoise(0.1, dt=True), "`dt`"),
    "band dt complex": (lambda: obsjax.noise.BandLimitedNoise(0.1, dt=1j), "`dt`"),
    "cvar level complex": (lambda: obsjax.risk_weights(("cvar", 1j), 10), "CVaR level"),
    "multisine frequency nan": (lambda: obsjax.signals.multisine([1.0], [np.nan]), "`frequencies`"),
    "multisine amplitude inf": (lambda: obsjax.signals.multisine([np.inf], [1.0]), "`amplitudes`"),
    # explicit observer gains: finite at construction (NaN/inf used to fail later, naming nothing)
    "Luenberger L nan": (lambda: obsjax.Luenberger(PLANT, L=[[np.nan], [1.0]]), "`L` must be finite"),
    "ReducedOrder G inf": (lambda: obsjax.ReducedOrder(PLANT, G=[[np.inf]]), "`G` must be finite"),
    "FunctionalObserver a nan": (lambda: obsjax.FunctionalObserver(PLANT, [np.nan, 1.0], []), "`a` must be finite"),
    "GeneralizedInverseODE F nan": (lambda: _giode(F=np.diag([-4.0, np.nan, -6.0])), "`F` must be finite"),
    "GeneralizedInverseODE G nan": (lambda: _giode(G=np.full((3, 1), np.nan)), "`G` must be finite"),
    "GeneralizedInverseODE T0 inf": (lambda: _giode(T0=np.full((3, 3), np.inf)), "`T0` must be finite"),
    "MinimalAdaptive a0 nan": (
        lambda: obsjax.MinimalAdaptiveObserver(2, [-1.0], 1.0, 1.0, a0=[np.nan, 0.0]), "`a0` must be finite"
    ),
    "NonMinimalAdaptive b0 nan": (
        lambda: obsjax.NonMinimalAdaptiveObserver(2, [-1.0], 1.0, 1.0, b0=[0.0, np.inf]), "`b0` must be finite"
    ),
    "max_steps = 0": (lambda: sim(PLANT, OBS, X0, XH0, TS, max_steps=0), "`max_steps`"),
    "dt0 = 0": (lambda: sim(PLANT, OBS, X0, XH0, TS, dt0=0.0, adaptive=False), "`dt0`"),
    "dt0 < 0": (lambda: sim(PLANT, OBS, X0, XH0, TS, dt0=-0.1), "`dt0`"),
    "rtol = 0": (lambda: sim(PLANT, OBS, X0, XH0, TS, rtol=0.0), "`rtol`"),
    # a string tolerance raised numpy's TypeError from `isfinite`, naming nothing (called through the
    # options check: the test session's runtime type checker refuses a str before simulate runs)
    "rtol str": (lambda: _validate.check_options("1e-6", 1e-8, None, True, 100, None), "`rtol` must be a finite number"),
    "atol None": (lambda: _validate.check_options(1e-6, None, None, True, 100, None), "`atol` must be a finite number"),
    "ts nan": (lambda: sim(PLANT, OBS, X0, XH0, np.array([0.0, np.nan, 1.0])), "`ts`"),
    "ts decreasing": (lambda: sim(PLANT, OBS, X0, XH0, TS[::-1]), "`ts` must be strictly increasing"),
    # a key without a noise model was ignored: a study meant to be noisy ran noise-free without a word
    "key without noise": (lambda: sim(PLANT, OBS, X0, XH0, TS, key=jax.random.key(0)), "`key` is given but `noise`"),
    "keys without noise": (
        lambda: obsjax.simulate_batch(PLANT, OBS, jnp.ones((2, 2)), jnp.zeros((2, 2)), TS,
                                      keys=jax.random.split(jax.random.key(0), 2)),
        "`keys` is given but `noise`",
    ),
    "x0 complex": (lambda: sim(PLANT, OBS, X0 + 1j, XH0, TS), "`x0` must be real"),
    # a complex input failed inside the integration with a message naming nothing
    "u complex": (lambda: sim(PLANT, OBS, X0, XH0, TS, u=lambda t: jnp.ones(1) * (1 + 1j)), "`u(t)` must return real"),
}


@pytest.mark.parametrize("case", list(VALUE_CASES))
def test_bad_value_names_the_argument(case):
    call, name = VALUE_CASES[case]
    with pytest.raises(ValueError) as e:
        call()
    assert name in str(e.value), str(e.value)


def test_reset_period_far_below_the_horizon_is_refused():
    """T = 1e-6 on [0, 4] would be 4·10⁶ segments: a clear error, not a hang."""
    lsr = obsjax.LeastSquaresReset(PLANT, gamma=1.0, p0=1.0, T=1e-6)
    with pytest.raises(ValueError, match=r"reset period T = 1e-06 gives 4\d+ reset segments on \[0, 4\]"):
        sim(PLANT, lsr, X0, XH0, np.linspace(0.0, 4.0, 5))
    with pytest.raises(ValueError, match="`max_segments`"):
        sim(PLANT, lsr, X0, XH0, np.linspace(0.0, 4.0, 5), max_segments=MAX_RESET_SEGMENTS + 1)


def test_float32_inputs_are_promoted_to_float64():
    ts32 = np.linspace(0.0, 2.0, 11, dtype=np.float32)
    a = sim(PLANT, OBS, np.asarray(X0, np.float32), np.zeros(2, np.float32), ts32)
    b = sim(PLANT, OBS, X0, XH0, ts32.astype(np.float64))
    assert a.x.dtype == a.ts.dtype == jnp.float64 and int(a.status) == 0
    np.testing.assert_array_equal(a.error, b.error)


def test_decreasing_ts_under_jit_never_integrates_backwards():
    """Issue item 1: traced save times are checked with eqx.error_if, whatever `throw` says."""
    f = jax.jit(lambda ts: obsjax.simulate(PLANT, OBS, X0, XH0, ts, throw=False).error_norm)
    np.testing.assert_allclose(f(jnp.asarray(TS)), sim(PLANT, OBS, X0, XH0, TS).error_norm, atol=1e-12)
    with pytest.raises(Exception, match="strictly increasing"):
        jax.block_until_ready(f(jnp.asarray(TS[::-1])))
    with pytest.raises(Exception, match="strictly increasing"):
        jax.block_until_ready(f(jnp.asarray(TS).at[3].set(TS[2])))
    # an infinite time increases too: it ended in status 1 with advice to raise max_steps
    for bad in (jnp.asarray(TS).at[-1].set(jnp.inf), jnp.asarray(TS).at[0].set(-jnp.inf)):
        with pytest.raises(Exception, match="`ts` must hold finite save times"):
            jax.block_until_ready(f(bad))


@pytest.mark.extended
def test_traced_dt0_is_checked_under_jit():
    """A traced initial/fixed step: a positive one integrates as the concrete one does; zero, negative
    and NaN raise with a message naming `dt0`, whatever `throw` says (never a silent stall or NaN)."""
    for adaptive in (True, False):
        f = jax.jit(
            lambda dt0, adaptive=adaptive: obsjax.simulate(
                PLANT, OBS, X0, XH0, TS, dt0=dt0, adaptive=adaptive, throw=False
            ).error_norm
        )
        ref = sim(PLANT, OBS, X0, XH0, TS, dt0=0.05, adaptive=adaptive).error_norm
        np.testing.assert_allclose(f(jnp.asarray(0.05)), ref, rtol=1e-12, atol=1e-14)
        for bad in (0.0, -0.1, np.nan):
            with pytest.raises(Exception, match="`dt0` must be finite and > 0"):
                jax.block_until_ready(f(jnp.asarray(bad)))


# ---------------------------------------------------------------- statuses that tell the truth, early


def test_overflowing_error_with_a_finite_state_is_nonfinite():
    """Issue item 3: a finite estimate whose ‖x̃‖ overflows is not a success."""
    xh0 = jnp.array([1e200, 0.0])
    assert np.all(np.isfinite(xh0 - X0))
    tr = sim(PLANT, OBS, X0, xh0, TS)
    assert int(tr.status) == obsjax._simulate.NONFINITE
    with pytest.raises(Exception, match="diverged or contains non-finite"):
        obsjax.simulate(PLANT, OBS, X0, xh0, TS)


@pytest.mark.extended
def test_error_norm_of_tiny_errors_does_not_underflow():
    """‖x̃‖ of an error of 1e-200 was 0 (the squares underflow); the norm is scaled by the largest entry,
    against NumPy's norm of the rescaled error, and its derivative still matches central differences."""
    tr = obsjax.simulate(PLANT, OBS, X0 * 1e-200, XH0, TS)
    ref = np.linalg.norm(np.asarray(tr.error) * 1e200, axis=-1) * 1e-200
    assert np.all(ref > 0)
    np.testing.assert_allclose(tr.error_norm, ref, rtol=1e-14)
    assert tr.error_norm.shape == (len(TS),)

    def last(x0):
        return obsjax.simulate(PLANT, OBS, x0, XH0, TS, rtol=1e-10, atol=1e-12).error_norm[-1]

    g = jax.grad(last)(X0)
    h = 1e-6
    fd = [(last(X0 + h * e) - last(X0 - h * e)) / (2 * h) for e in np.eye(2)]
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def _xhat0_sometimes_huge(key):
    return jnp.where(jax.random.uniform(key) < 0.25, 1e200, 0.0) * jnp.ones(2)


@pytest.mark.extended
def test_overflowing_members_are_failures_of_a_study():
    """Issue item 3 in a study: the overflowing rows are counted failed, and no statistic sees them."""
    res = obsjax.monte_carlo(PLANT, OBS, jax.random.key(2), 32, x0_sampler=np.asarray(X0),
                             xhat0_sampler=_xhat0_sometimes_huge, ts=TS, chunk_size=32, progress=False)
    huge = np.array([float(_xhat0_sometimes_huge(jax.random.split(jax.random.fold_in(jax.random.key(2), i), 4)[1])[0])
                     for i in range(32)]) > 0
    assert 0 < huge.sum() < 32
    np.testing.assert_array_equal(res.status == 2, huge)
    assert res.n_failed == huge.sum()
    assert np.all(np.isfinite(res.bands)) and np.all(np.isfinite(res.ise[~huge]))


@pytest.mark.extended
def test_every_field_of_a_failed_trajectory_carries_the_failure():
    """With throw=True a computation that reads only x, x̂, y or z (not x̃) of a failed trajectory still raises
    under jit (the check is not dead code of an unread field); with throw=False the status says so."""
    xh0 = jnp.array([1e200, 0.0])  # finite estimate, overflowing Σ‖x̃‖²
    for field in ("x", "xhat", "y", "z"):
        f = jax.jit(lambda xh, field=field: getattr(obsjax.simulate(PLANT, OBS, X0, xh, TS), field))
        with pytest.raises(Exception, match="diverged or contains non-finite"):
            jax.block_until_ready(f(xh0))


class _HiddenState(obsjax.AbstractObserver):
    """The estimate is a Luenberger-like copy; a second state leaf becomes NaN without reaching x̂."""

    def init(self, t0, xhat0, y0):
        return (xhat0, jnp.zeros(()))

    def vector_field(self, t, z, y, u):
        return (-z[0], jnp.where(t > 0.5, jnp.nan, 0.0))

    def estimate(self, t, z, y):
        return z[0]


def test_a_nonfinite_observer_state_is_nonfinite_even_if_the_estimate_is_finite():
    fixed = sim(PLANT, _HiddenState(), X0, XH0, TS, adaptive=False, dt0=0.05)  # the tableau scan
    assert np.all(np.isfinite(fixed.xhat)) and np.all(np.isfinite(fixed.error))
    assert int(fixed.status) == 2
    assert int(sim(PLANT, _HiddenState(), X0, XH0, TS).status) == 2  # diffrax segments stop at once


class _NaNAfter(_HiddenState):
    """As _HiddenState, with the hidden leaf's vector field NaN after `tau`."""

    tau: float = 0.5

    def vector_field(self, t, z, y, u):
        return (-z[0], jnp.where(t > self.tau, jnp.nan, 0.0))


def test_a_floor_step_rounded_above_the_floor_still_ends_the_solve():
    """The floor step t0 + dt_floor is rounded to a float, so the step taken can exceed dt_floor by an ulp of
    t1.  From just below 0.5 (where the floats' spacing doubles) the guard must still take it as a floor step:
    its non-finite candidate ends the solve (dt_min_reached, status 2), instead of being rejected and proposed
    again until max_steps (status 1).  Found on a GPU, where rounding led the solve there at rtol 1e-6."""
    import diffrax

    from obsjax._integrate._status import GuardedController

    ctrl = GuardedController(1e-8, 1e-8, 0.0, 2.0)
    t0 = jnp.asarray(0.49999999999999883)
    t1 = t0 + ctrl.dt_floor
    assert float(t1 - t0) > float(ctrl.dt_floor)  # the rounding this test is about
    y0 = (jnp.ones(2), jnp.zeros(()))
    cand = (jnp.ones(2), jnp.asarray(jnp.nan))
    err = (jnp.zeros(2), jnp.asarray(jnp.nan))
    _, state = ctrl.init(None, 0.0, 2.0, y0, 0.01, None, lambda t, y, a: y, 5)
    keep, *_, result = ctrl.adapt_step_size(t0, t1, y0, cand, None, err, 5, state)
    assert bool(keep) and result == diffrax.RESULTS.dt_min_reached
    # and through simulate: the case that ran to max_steps on the CPU (steps end 1.2e-15 below 0.5)
    tr = sim(PLANT, _NaNAfter(), X0, XH0, TS, rtol=1e-8)
    assert int(tr.status) == 2


def test_traced_reset_period_must_be_covered_by_max_segments():
    """Under jit the bound max_segments·T ≥ t1 − t0 is checked (too small a bound would drop resets)."""
    lsr = obsjax.LeastSquaresReset(PLANT, gamma=1.0, p0=1.0, T=1.5)
    f = jax.jit(lambda T: sim(PLANT, eqx.tree_at(lambda o: o.T, lsr, T), X0, XH0, TS, max_segments=2).status)
    assert int(f(1.5)) == 0
    with pytest.raises(Exception, match="raise `max_segments`"):
        jax.block_until_ready(f(0.3))


@pytest.mark.extended
def test_nan_start_or_gain_stops_at_once():
    """A NaN x0 (or x̂0, or gain) is NONFINITE, found within a few steps: with a step budget that a regular run
    does not meet (status 1) the NaN runs still end with status 2, not by exhausting the budget."""
    budget = dict(max_steps=24)
    assert int(sim(PLANT, OBS, X0, XH0, np.linspace(0.0, 40.0, 3), rtol=1e-12, atol=1e-14, **budget).status) == 1
    nan_gain = eqx.tree_at(lambda o: o.L, obsjax.Luenberger(PLANT, L=[[1.0], [1.0]]), jnp.array([[jnp.nan], [1.0]]))
    for x0, xh0, obs in ((X0.at[0].set(jnp.nan), XH0, OBS), (X0, XH0.at[1].set(jnp.inf), OBS), (X0, XH0, nan_gain)):
        tr = sim(PLANT, obs, x0, xh0, np.linspace(0.0, 40.0, 3), rtol=1e-12, atol=1e-14, **budget)
        assert int(tr.status) == 2


def test_divergent_trajectory_is_nonfinite_not_solver_failure():
    """An observer whose error grows like e^{28 t}: the state overflows and the solve stops (status 2), where
    the NaN rejection loop used to end at max_steps with status 1."""
    unstable = obsjax.Luenberger(PLANT, L=[[-30.0], [0.0]])
    tr = sim(PLANT, unstable, X0, XH0, np.linspace(0.0, 30.0, 7), rtol=1e-3, atol=1e-6, max_steps=4096)
    assert int(tr.status) == 2
    assert np.isfinite(tr.error_norm[1])  # rows before the divergence are kept


# ---------------------------------------------------------------- item 4: lock-step batches isolate failures

CUBIC = obsjax.Nonlinear(lambda t, x, u: -x + x**3, lambda t, x, u: x, n=1, m=1)  # escapes for |x0| > 1
CUBIC_OBS = obsjax.Luenberger.from_poles(obsjax.LTI([[-1.0]], None, [[1.0]]), [-3.0])
TS_C = np.linspace(0.0, 1.0, 11)
TIGHT = dict(rtol=1e-8, atol=1e-10)


# independent solves of 64 members, compiled once for both tests below
_ALONE = jax.jit(jax.vmap(lambda a, b: sim(CUBIC, CUBIC_OBS, a, b, TS_C, **TIGHT)))


@pytest.mark.extended
def test_lockstep_batch_isolates_failing_members():
    """64 members, 3 escaping in finite time: exactly those 3 fail; the other 61 equal independent solves."""
    x0s = jnp.linspace(-0.9, 0.9, 64)[:, None]
    bad = np.array([5, 30, 50])
    x0s = x0s.at[bad, 0].set(jnp.array([1.5, 1.3, -1.4]))
    xh0s = jnp.zeros((64, 1))
    lock = obsjax.simulate_batch(CUBIC, CUBIC_OBS, x0s, xh0s, TS_C, throw=False, **TIGHT)
    alone = _ALONE(x0s, xh0s)
    np.testing.assert_array_equal(np.flatnonzero(np.asarray(lock.status)), bad)
    np.testing.assert_array_equal(lock.status, alone.status)
    ok = np.asarray(lock.status) == 0
    np.testing.assert_allclose(np.asarray(lock.error)[ok], np.asarray(alone.error)[ok], atol=1e-7)


def _x0_cubic(key):
    k1, k2 = jax.random.split(key)
    return jnp.where(jax.random.uniform(k1) < 0.08, 1.5, jax.random.uniform(k2, (1,), minval=-0.9, maxval=0.9))


@pytest.mark.extended
def test_monte_carlo_lockstep_counts_only_the_failing_members():
    """Issue item 4: a lock-step study counts exactly the members that fail alone (x0 = 1.5 escapes in
    finite time), and the others keep the result of their own solve."""
    key = jax.random.key(1)
    lock = obsjax.monte_carlo(CUBIC, CUBIC_OBS, key, 64, lockstep=True, x0_sampler=_x0_cubic,
                              xhat0_sampler=np.zeros(1), ts=TS_C, chunk_size=64, progress=False,
                              simulate_kwargs=TIGHT)
    # trajectory i draws x0 from the first of four keys split from fold_in(key, i)
    x0s = jax.vmap(lambda i: _x0_cubic(jax.random.split(jax.random.fold_in(key, i), 4)[0]))(jnp.arange(64))
    alone = _ALONE(x0s, jnp.zeros((64, 1)))
    failing = np.asarray(alone.status) > 0
    assert 0 < failing.sum() < 16 and np.all(failing == (np.asarray(x0s)[:, 0] > 1))
    assert lock.n_failed == failing.sum()
    np.testing.assert_array_equal(lock.status > 0, failing)
    np.testing.assert_allclose(lock.error_norm[~failing], np.asarray(alone.error_norm)[~failing], atol=1e-7)


def _rotor(t, x, u):
    """ẋ = rotation at rate x₃² (x₃ constant): finite, but a fast member needs many more steps than the rest."""
    w = x[2] ** 2
    return jnp.array([w * x[1] - x[0], -w * x[0] - x[1], 0.0])


ROTOR = obsjax.Nonlinear(_rotor, lambda t, x, u: x[:1], n=3, m=1)
ROTOR_OBS = obsjax.Luenberger(obsjax.LTI(-np.eye(3), None, [[1.0, 0.0, 0.0]]), L=[[1.0], [0.0], [0.0]])


@pytest.mark.extended
def test_lockstep_evicts_a_finite_member_that_alone_drags_the_step_down():
    """Issue item 4, the stiff case: one member rotating at 2000 rad/s needs more than max_steps alone (status
    1) but stays finite; it is evicted from the shared step control and integrated alone, the other seven keep
    their own result (without isolation the shared solve would fail all eight)."""
    x0s = jnp.stack([jnp.ones(8), jnp.zeros(8), jnp.ones(8)], axis=1).at[3, 2].set(np.sqrt(2000.0))
    xh0s = jnp.zeros((8, 3))
    kw = dict(rtol=1e-8, atol=1e-10, max_steps=1024)
    lock = obsjax.simulate_batch(ROTOR, ROTOR_OBS, x0s, xh0s, TS_C, throw=False, **kw)
    alone = jax.vmap(lambda a, b: sim(ROTOR, ROTOR_OBS, a, b, TS_C, **kw))(x0s, xh0s)
    assert np.asarray(alone.status).tolist() == [0, 0, 0, 1, 0, 0, 0, 0]
    np.testing.assert_array_equal(lock.status, alone.status)
    ok = np.asarray(alone.status) == 0
    assert np.all(np.isfinite(np.asarray(lock.error)[3, :2]))  # finite until it ran out of steps
    np.testing.assert_allclose(np.asarray(lock.error)[ok], np.asarray(alone.error)[ok], atol=1e-7)


# ---------------------------------------------------------------- a derivative in the reset period, eagerly


def _lsr_cost(T):
    lsr = obsjax.LeastSquaresReset(PLANT, gamma=2.0, p0=1.0, T=0.37)
    o = eqx.tree_at(lambda o: o.T, lsr, T)
    return obsjax.losses.ise(sim(PLANT, o, X0, XH0, TS, adaptive=False, dt0=0.01, max_segments=8))


def _fw_cost(T):
    model = obsjax.LTI(A=[[0.0, 1.0], [0.0, 0.0]], B=[[0.0], [1.0]], C=[[2.0, 0.0]])
    o = eqx.tree_at(lambda o: o.T, obsjax.FiniteWindow(model, T=1.037), T)
    u = obsjax.signals.multisine([1.0], [1.3])
    tr = sim(model, o, jnp.array([1.0, 0.5]), jnp.zeros(2), np.linspace(0.0, 2.5, 26), u=u, rtol=1e-10, atol=1e-12,
             max_segments=64)
    return obsjax.losses.ise(tr)


@pytest.mark.parametrize("cost, T0", [(_lsr_cost, 0.37), (_fw_cost, 1.037)], ids=["lsr-fixed", "window-adaptive"])
@pytest.mark.extended
def test_eager_gradient_in_the_reset_period_moves_the_resets(cost, T0):
    """jax.grad without jit: T's primal value is concrete, but the reset instants t0 + kT must still carry
    its derivative (they were read as constants: dJ/dT = 0 with fixed steps, a wrong value with adaptive
    ones).  Checked against jit(grad) and a central difference."""
    eager = float(jax.grad(cost)(jnp.asarray(T0)))
    jitted = float(jax.jit(jax.grad(cost))(jnp.asarray(T0)))
    f = jax.jit(cost)
    h = 1e-5
    fd = float((f(T0 + h) - f(T0 - h)) / (2 * h))
    assert abs(fd) > 1e-3
    assert eager == pytest.approx(jitted, rel=1e-9)
    assert eager == pytest.approx(fd, rel=1e-5)


@pytest.mark.parametrize("kw", [dict(adaptive=False, dt0=0.01), dict(rtol=1e-10, atol=1e-12)], ids=["fixed", "adaptive"])
@pytest.mark.extended
def test_eager_gradient_in_the_save_times(kw):
    """d/ds of a cost over the save times s·ts, without jit: the fixed-step grid was built from the primal
    times and gave 0.  Against jit(grad) and a central difference."""
    def cost(s):
        tr = sim(PLANT, OBS, X0, XH0, jnp.asarray(TS) * s, **kw)
        return jnp.sum(tr.error ** 2) + jnp.sum(tr.x ** 2)

    eager = float(jax.grad(cost)(1.0))
    assert eager == pytest.approx(float(jax.jit(jax.grad(cost))(1.0)), rel=1e-9)
    f = jax.jit(cost)
    assert eager == pytest.approx(float((f(1.0 + 1e-5) - f(1.0 - 1e-5)) / 2e-5), rel=1e-5)


@pytest.mark.extended
def test_lockstep_gradient_leaves_out_failed_members():
    """simulate_batch(lockstep=True), the default: a member that starts at NaN (or escapes in finite time)
    made jax.grad NaN for the whole batch, even with a loss that leaves the failed members out (their
    vector field's NaN partials, times a zero cotangent, summed into the shared gain's derivative).  Now
    the gradient is the healthy members' (against central differences); a NaN start is the cheap case of
    the defect, a member escaping in finite time took the same path."""
    plant = obsjax.LTI([[0.0, 1.0], [-1.0, -0.2]], None, [[1.0, 0.0]])
    ts = np.linspace(0, 2, 11)
    X0 = np.array([[1.0, 0.0], [0.5, 0.5], [np.nan, 0.0]])

    @functools.partial(jax.jit, static_argnums=1)
    def loss(Lv, n):
        obs = obsjax.Luenberger(plant, L=Lv.reshape(2, 1))
        tb = obsjax.simulate_batch(plant, obs, X0[:n], np.zeros((n, 2)), ts, rtol=1e-9, atol=1e-12, throw=False)
        ok = tb.status == 0
        return jnp.sum(jnp.where(ok[:, None, None], tb.error, 0.0) ** 2), tb.status

    Lv = jnp.array([2.0, 1.5])
    (_, st), g = jax.value_and_grad(loss, has_aux=True)(Lv, 3)
    np.testing.assert_array_equal(np.asarray(st), [0, 0, 2])
    assert np.all(np.isfinite(np.asarray(g)))
    h = 1e-6  # the loss leaves the failed member out, so these are the healthy members' differences
    fd = [(loss(Lv + h * e, 3)[0] - loss(Lv - h * e, 3)[0]) / (2 * h) for e in np.eye(2)]
    np.testing.assert_allclose(g, fd, rtol=1e-5)


@pytest.mark.extended
def test_a_first_step_whose_candidate_overflows_is_rejected_not_fatal():
    """ẋ1 = −x1³ + x2 from x1 = 300: the first trial step's candidate overflows, its error estimate is
    inf − inf = NaN, and the step-size controller proposed a NaN step for ever: status 1 after max_steps
    with x = inf, for a problem that dt0 = 1e-6 solves.  The step is now rejected (shrunk by factormin),
    in simulate and in both batch back-ends, and the result equals the small-first-step solve."""
    f = lambda t, x, u: jnp.array([-x[0] ** 3 + x[1], -x[1] + 0.5 * x[0] ** 2])  # noqa: E731
    plant = obsjax.Nonlinear(f, lambda t, x, u: x[:1], n=2, m=1, p=0)
    obs = obsjax.Luenberger(obsjax.LTI([[0.0, 1.0], [0.0, -1.0]], None, [[1.0, 0.0]]), L=[[3.0], [2.0]])
    ts = np.linspace(0, 3, 7)
    kw = dict(rtol=1e-9, atol=1e-11, max_steps=2000, throw=False)
    ref = obsjax.simulate(plant, obs, jnp.array([300.0, 0.0]), jnp.zeros(2), ts, dt0=1e-6, **kw)
    assert int(ref.status) == 0
    tr = obsjax.simulate(plant, obs, jnp.array([300.0, 0.0]), jnp.zeros(2), ts, **kw)
    assert int(tr.status) == 0
    np.testing.assert_allclose(tr.x, ref.x, rtol=1e-7)
    tb = obsjax.simulate_batch(plant, obs, jnp.array([[300.0, 0.0], [1.0, 0.0]]), jnp.zeros((2, 2)), ts,
                               lockstep=False, **kw)
    np.testing.assert_array_equal(np.asarray(tb.status), [0, 0])
    np.testing.assert_allclose(tb.x[0], ref.x, rtol=1e-7)


def test_a_step_at_the_floor_does_not_keep_the_solve_there():
    """The step floor is 64 ulp of the horizon's largest time: at clock times in ms (1.7e12) it is 0.024,
    above diffrax's first step 0.01.  Every step after one at the floor was forced to the floor again, so
    one interval of 100 took 4137 floor steps and ran into max_steps (status 1).  An accepted floor step
    now lets the PID controller grow the next one (diffrax's dtmin semantics)."""
    import diffrax

    from obsjax._integrate._status import GuardedController

    A = jnp.array([[-0.5, 1.0, 0.0], [-1.0, -0.3, 0.8], [0.2, 0.0, -1.2]]) / 1e3
    t0 = 1.7e12
    ctrl = GuardedController(1e-6, 1e-8, t0, t0 + 100.0)
    assert float(ctrl.dt_floor) > 0.01
    sol = diffrax.diffeqsolve(diffrax.ODETerm(lambda t, y, a: A @ y + 1e-3), diffrax.Tsit5(), t0, t0 + 100.0,
                              None, jnp.ones(3), stepsize_controller=ctrl, max_steps=4096, throw=False)
    assert sol.result == diffrax.RESULTS.successful and int(sol.stats["num_steps"]) <= 10
    ref = jax.scipy.linalg.expm(A * 100.0) @ jnp.ones(3) + jnp.linalg.solve(A, (jax.scipy.linalg.expm(A * 100.0) - jnp.eye(3)) @ jnp.full(3, 1e-3))
    np.testing.assert_allclose(sol.ys[-1], ref, rtol=1e-5)
