"""``simulate_batch(lockstep=False)`` and ``monte_carlo``'s default kernel on the masked adaptive Runge–Kutta
loop: member by member the solve of ``obsjax.simulate`` (checked against ``jax.vmap(simulate)``, which runs
diffrax's ``diffeqsolve`` segment by segment, and against tight solves), its status codes, its gradients
against central finite differences, and the problems it leaves to ``jax.vmap(simulate)``."""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optax
import pytest

import obsjax
from obsjax._integrate import _masked

CY_PLANT = obsjax.chen_yen_example()
CY_OBS = obsjax.LeastSquaresReset(CY_PLANT, gamma=20.0, p0=0.1, T=0.25)
TS = jnp.linspace(0.0, 3.0, 17)  # save times on and off the reset instants


def _batch(b=8, seed=0):
    x0s = jr.normal(jr.key(seed), (b, 2))
    return x0s, jnp.tile(jnp.array([5.0, -5.0]), (b, 1))


@pytest.fixture
def spy(monkeypatch):
    """Counts the batches that reach the masked back-end."""
    calls = []
    real = _masked.integrate

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(_masked, "integrate", counting)
    return calls


def _vmap_sim(plant, obs, x0s, xh0s, ts, **kw):
    return jax.vmap(lambda a, b: obsjax.simulate(plant, obs, a, b, ts, **kw))(x0s, xh0s)


@pytest.mark.parametrize("solver", [diffrax.Tsit5(), diffrax.Dopri5()], ids=["Tsit5", "Dopri5"])
@pytest.mark.extended
def test_masked_batch_is_simulate_member_by_member(spy, solver):
    """Chen & Yen (12 resets on [0, 3]): the same steps as diffrax's segmented solve, so the two agree to
    rounding; both are within the tolerance of a tight solve."""
    x0s, xh0s = _batch()
    kw = dict(solver=solver, rtol=1e-6, atol=1e-8)
    got = obsjax.simulate_batch(CY_PLANT, CY_OBS, x0s, xh0s, TS, lockstep=False, **kw)
    assert len(spy) == 1
    ref = _vmap_sim(CY_PLANT, CY_OBS, x0s, xh0s, TS, **kw)
    tight = _vmap_sim(CY_PLANT, CY_OBS, x0s, xh0s, TS, rtol=1e-12, atol=1e-14)
    assert got.error.shape == (8, 17, 2) and got.ts.shape == (8, 17)
    np.testing.assert_array_equal(got.status, 0)
    np.testing.assert_allclose(got.error, ref.error, rtol=0, atol=1e-11)
    np.testing.assert_allclose(got.z.Phi, ref.z.Phi, rtol=0, atol=1e-11)
    np.testing.assert_allclose(got.z.Qinv, ref.z.Qinv, rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(got.error, tight.error, rtol=5e-5, atol=1e-5)  # global error at rtol 1e-6


@pytest.mark.extended
def test_masked_batch_crosses_plant_jumps_and_resets(spy):
    """A 3-state plant switching every 0.3 s with resets every 1.93 s: the jumps are stepped onto from
    below, the resets exactly, as in simulate."""
    plant = obsjax.switching_ltv_example(period=0.3, horizon=4.0)
    obs = obsjax.LeastSquaresReset(plant, gamma=1.0, p0=1.0, T=1.93)
    x0s = jr.normal(jr.key(1), (4, 3))
    xh0s = jnp.zeros((4, 3))
    ts = jnp.linspace(0.0, 4.0, 9)
    got = obsjax.simulate_batch(plant, obs, x0s, xh0s, ts, lockstep=False, rtol=1e-8, atol=1e-10)
    assert len(spy) == 1
    ref = _vmap_sim(plant, obs, x0s, xh0s, ts, rtol=1e-8, atol=1e-10)
    np.testing.assert_array_equal(got.status, 0)
    np.testing.assert_allclose(got.error, ref.error, rtol=0, atol=1e-10)


@pytest.mark.extended
def test_masked_batch_with_band_limited_noise_draws_each_members_noise(spy):
    x0s, xh0s = _batch(5)
    keys = jr.split(jr.key(3), 5)
    noise = obsjax.noise.BandLimitedNoise(0.05, 0.05)
    kw = dict(noise=noise, rtol=1e-8, atol=1e-10)
    got = obsjax.simulate_batch(CY_PLANT, CY_OBS, x0s, xh0s, TS, keys=keys, lockstep=False, **kw)
    assert len(spy) == 1
    ref = jax.vmap(lambda a, b, k: obsjax.simulate(CY_PLANT, CY_OBS, a, b, TS, key=k, **kw))(x0s, xh0s, keys)
    np.testing.assert_allclose(got.y, ref.y, atol=1e-12)  # the same noise draw per member
    # the noise path's kinks (every 0.05 s) are stepped over, not declared: where an error estimate sits at
    # the acceptance threshold, rounding can flip a decision and the two solves part by the (kink-limited)
    # accuracy of either
    np.testing.assert_allclose(got.error, ref.error, atol=1e-5)


CUBIC = obsjax.Nonlinear(lambda t, x, u: -x + x**3, lambda t, x, u: x, n=1, m=1)  # escapes for |x0| > 1
CUBIC_OBS = obsjax.Luenberger.from_poles(obsjax.LTI([[-1.0]], None, [[1.0]]), [-3.0])


@pytest.mark.extended
def test_masked_batch_status_per_member(spy):
    """Members that escape in finite time are NONFINITE, one started at NaN too, one out of steps
    SOLVER_FAILED; the others are unaffected: the codes of jax.vmap(simulate)."""
    ts = np.linspace(0.0, 1.0, 11)
    x0s = jnp.linspace(-0.9, 0.9, 12)[:, None].at[jnp.array([2, 7])].set(jnp.array([[1.5], [-1.4]]))
    x0s = x0s.at[9, 0].set(jnp.nan)
    xh0s = jnp.zeros((12, 1))
    kw = dict(rtol=1e-8, atol=1e-10, throw=False)
    got = obsjax.simulate_batch(CUBIC, CUBIC_OBS, x0s, xh0s, ts, lockstep=False, **kw)
    ref = _vmap_sim(CUBIC, CUBIC_OBS, x0s, xh0s, ts, **kw)
    want = np.zeros(12, int)
    want[[2, 7, 9]] = 2
    np.testing.assert_array_equal(got.status, want)
    np.testing.assert_array_equal(got.status, ref.status)
    ok = want == 0
    np.testing.assert_allclose(np.asarray(got.error)[ok], np.asarray(ref.error)[ok], atol=1e-12)
    few = obsjax.simulate_batch(CUBIC, CUBIC_OBS, x0s[:2], xh0s[:2], ts, lockstep=False, max_steps=3, **kw)
    ref_few = _vmap_sim(CUBIC, CUBIC_OBS, x0s[:2], xh0s[:2], ts, max_steps=3, **kw)
    np.testing.assert_array_equal(few.status, [1, 1])
    np.testing.assert_array_equal(ref_few.status, [1, 1])
    assert len(spy) == 2
    with pytest.raises(Exception, match="diverged"):
        obsjax.simulate_batch(CUBIC, CUBIC_OBS, x0s, xh0s, ts, lockstep=False, rtol=1e-8, atol=1e-10)


@pytest.mark.extended
def test_masked_batch_gradients_match_finite_differences():
    """d/d(p0, T) of the mean ISE (T a traced leaf: the resets move with it), reverse mode through the
    checkpointed loop and forward mode (ForwardMode), against central differences."""
    x0s, xh0s = _batch(4)
    # no save time on a reset instant: there the loss has a kink in T (the gain changes at the reset)
    ts = jnp.linspace(0.03, 1.97, 20)

    def loss(theta, adjoint=None):
        obs = eqx.tree_at(lambda o: (o.p0, o.T), CY_OBS, (theta[0], theta[1]))
        tr = obsjax.simulate_batch(
            CY_PLANT, obs, x0s, xh0s, ts, lockstep=False, rtol=1e-10, atol=1e-12, max_segments=10,
            adjoint=adjoint,
        )
        return jnp.mean(jnp.sum(tr.error_norm**2, axis=1))

    theta = jnp.array([0.1, 0.25])
    g_rev = jax.jit(jax.grad(loss))(theta)
    g_fwd = jax.jit(jax.jacfwd(lambda th: loss(th, diffrax.ForwardMode())))(theta)
    lj = jax.jit(loss)
    h = jnp.array([1e-5, 1e-5])
    fd = np.array([(lj(theta + h * e) - lj(theta - h * e)) / (2 * h[i]) for i, e in enumerate(jnp.eye(2))])
    assert np.all(np.abs(fd) > 1e-3)
    np.testing.assert_allclose(g_rev, fd, rtol=2e-4)
    np.testing.assert_allclose(g_fwd, g_rev, rtol=1e-9)


@pytest.mark.extended
def test_problems_the_masked_loop_does_not_take_go_through_vmap(spy):
    """An implicit solver, no bound on the steps, and observer events are jax.vmap(simulate), bit for bit."""
    x0s, xh0s = _batch(3)
    ts = jnp.linspace(0.0, 1.0, 5)
    for kw in (dict(solver=diffrax.Kvaerno5()), dict(max_steps=None)):
        got = obsjax.simulate_batch(CY_PLANT, CY_OBS, x0s, xh0s, ts, lockstep=False, **kw)
        np.testing.assert_array_equal(got.error, _vmap_sim(CY_PLANT, CY_OBS, x0s, xh0s, ts, **kw).error)
    assert spy == []
    plan = obsjax._integrate._validate.plan(
        CY_PLANT, CY_OBS.prepare(), ts, np.asarray(ts), noise=None, key=None, solver=diffrax.Tsit5(),
        rtol=1e-6, atol=1e-8, dt0=None, adaptive=True, max_steps=100, max_segments=None,
        adjoint=diffrax.BacksolveAdjoint(),
    )
    assert not _masked.eligible(plan)


@pytest.mark.extended
def test_monte_carlo_default_kernel_is_the_masked_loop(spy):
    """monte_carlo without a param_sampler runs each chunk on the masked loop; every trajectory equals
    simulate on its own draw."""
    key = jr.key(7)
    ts = np.linspace(0.0, 2.0, 9)
    res = obsjax.monte_carlo(CY_PLANT, CY_OBS, key, 24, x0_sampler=lambda k: jr.normal(k, (2,)),
                             xhat0_sampler=np.array([5.0, -5.0]), ts=ts, chunk_size=12, progress=False)
    assert len(spy) >= 1  # traced once per chunk shape
    # trajectory i draws x0 from the first of four keys split from fold_in(key, i)
    x0s = jax.vmap(lambda i: jr.normal(jr.split(jr.fold_in(key, i), 4)[0], (2,)))(jnp.arange(24))
    ref = _vmap_sim(CY_PLANT, CY_OBS, x0s, jnp.tile(jnp.array([5.0, -5.0]), (24, 1)), ts)
    assert res.n_failed == 0
    np.testing.assert_allclose(res.error_norm, ref.error_norm, rtol=0, atol=1e-11)


# ---------------------------------------------------------------------------------------------- a batch of
# plants: tune(plant_batched=True) and monte_carlo(param_sampler=...) on the same loop

LIN_C = np.array([[1.0, 0.0]])
LIN_NOM = obsjax.LTI(np.array([[0.0, 1.0], [-2.0, -0.3]]), None, LIN_C)
LIN_OBS = obsjax.Luenberger.from_poles(LIN_NOM, [-2.0, -3.0])


def _sampled_plants(b, seed=0, spread=0.3):
    """b plants A = A_nom + spread·N(0, 1) (each a different system), as a batch (leading axis b)."""
    draw = lambda k: eqx.tree_at(lambda p: p.A, LIN_NOM, LIN_NOM.A + spread * jr.normal(k, (2, 2)))
    return eqx.filter_vmap(draw)(jr.split(jr.key(seed), b))


def _vmap_plants(plants, obs, x0s, xh0s, ts, **kw):
    one = lambda p, a, b: obsjax.simulate(p, obs, a, b, ts, **kw)
    return eqx.filter_vmap(one)(plants, x0s, xh0s)


@pytest.mark.extended
def test_a_batch_of_plants_runs_member_by_member_on_the_masked_loop(spy):
    """Member b integrates plant b: equal to simulate on that plant (to rounding), with the statuses of
    simulate; the members' plants really differ (their errors part by far more than the rounding)."""
    from obsjax._simulate_batch import simulate_plants

    B = 6
    plants = _sampled_plants(B)
    x0s = jr.normal(jr.key(1), (B, 2))
    x0s = x0s.at[4, 1].set(jnp.nan)  # a member that starts non-finite fails alone
    xh0s = jnp.zeros((B, 2))
    ts = jnp.linspace(0.0, 5.0, 11)
    kw = dict(rtol=1e-8, atol=1e-10, throw=False)
    got = simulate_plants(plants, LIN_OBS, x0s, xh0s, ts, **kw)
    assert len(spy) == 1
    ref = _vmap_plants(plants, LIN_OBS, x0s, xh0s, ts, **kw)
    np.testing.assert_array_equal(got.status, [0, 0, 0, 0, 2, 0])
    np.testing.assert_array_equal(got.status, ref.status)
    ok = np.asarray(got.status) == 0
    np.testing.assert_allclose(np.asarray(got.error)[ok], np.asarray(ref.error)[ok], rtol=0, atol=1e-12)
    # the same initial state under each member's plant: the trajectories differ by O(spread)
    same = simulate_plants(plants, LIN_OBS, jnp.tile(x0s[:1], (B, 1)), xh0s, ts, **kw)
    assert float(jnp.max(jnp.abs(same.x[1:] - same.x[:1]))) > 1e-2
    with pytest.raises(ValueError, match="leading axis of length 6"):
        simulate_plants(LIN_NOM, LIN_OBS, x0s, xh0s, ts, **kw)  # one plant, not a batch


@pytest.mark.extended
def test_gradients_over_a_batch_of_plants_match_finite_differences():
    """d/d(poles) of the mean ISE over a batch of plants, reverse mode and forward mode (ForwardMode)
    through the masked loop, against central differences, under jit."""
    from obsjax._simulate_batch import simulate_plants

    B = 4
    plants = _sampled_plants(B, seed=2)
    x0s = jr.normal(jr.key(3), (B, 2))
    xh0s = jnp.zeros((B, 2))
    ts = jnp.linspace(0.0, 4.0, 21)

    def loss(poles, adjoint=None):
        obs = eqx.tree_at(lambda o: o.poles, LIN_OBS, poles)
        tr = simulate_plants(plants, obs, x0s, xh0s, ts, rtol=1e-10, atol=1e-12, adjoint=adjoint)
        return jnp.mean(jnp.sum(tr.error_norm**2, axis=1))

    p = jnp.asarray(LIN_OBS.poles)
    g_rev = jax.jit(jax.grad(loss))(p)
    g_fwd = jax.jit(jax.jacfwd(lambda q: loss(q, diffrax.ForwardMode())))(p)
    lj = jax.jit(loss)
    h = 1e-5
    fd = np.array([(lj(p + h * e) - lj(p - h * e)) / (2 * h) for e in jnp.eye(2)])
    assert np.all(np.abs(fd) > 1e-3)
    np.testing.assert_allclose(g_rev, fd, rtol=1e-5)
    np.testing.assert_allclose(g_fwd, g_rev, rtol=1e-9)


@pytest.mark.extended
def test_tune_over_a_batch_of_plants_takes_the_masked_loop(spy):
    plants = _sampled_plants(4, seed=4)
    r = obsjax.tune(LIN_OBS, plants, where=lambda o: o.poles, loss=obsjax.losses.ise,
                    x0s=jr.normal(jr.key(5), (4, 2)), xhat0s=jnp.zeros((4, 2)), ts=jnp.linspace(0.0, 4.0, 21),
                    plant_batched=True, steps=2, optimizer=optax.adam(0.05), progress=False)  # fmt: skip
    assert r.history["kernel"] == "masked" and len(spy) >= 1
    assert np.all(np.isfinite(r.history["loss"]))


@pytest.mark.extended
def test_monte_carlo_with_a_param_sampler_takes_the_masked_loop(spy):
    """Each trajectory draws its own plant (from the fourth key of fold_in(key, i)) and equals simulate on
    that plant and draw."""
    key = jr.key(8)
    ts = np.linspace(0.0, 4.0, 9)

    def sampler(k, plant):
        return eqx.tree_at(lambda p: p.A, plant, plant.A + 0.3 * jr.normal(k, (2, 2)))

    res = obsjax.monte_carlo(LIN_NOM, LIN_OBS, key, 10, x0_sampler=lambda k: jr.normal(k, (2,)),
                             xhat0_sampler=np.zeros(2), ts=ts, param_sampler=sampler, chunk_size=5,
                             progress=False)  # fmt: skip
    assert len(spy) >= 1 and res.n_failed == 0
    ks = jax.vmap(lambda i: jr.split(jr.fold_in(key, i), 4))(jnp.arange(10))
    plants = eqx.filter_vmap(lambda k: sampler(k, LIN_NOM))(ks[:, 3])
    x0s = jax.vmap(lambda k: jr.normal(k, (2,)))(ks[:, 0])
    ref = _vmap_plants(plants, LIN_OBS, x0s, jnp.zeros((10, 2)), ts)
    np.testing.assert_allclose(res.error_norm, ref.error_norm, rtol=0, atol=1e-11)


@pytest.mark.extended
def test_masked_batch_counts_max_steps_per_segment_as_simulate():
    """An oscillator (ω = 20) on [0, 3] with a plant jump at 0.001 (two segments): `simulate` bounds each
    segment's solve by max_steps; the masked loop shared max_steps × (segments) among them, so a member
    whose long segment needed more than max_steps came back with status 0 where simulate says 1.  At the
    smallest max_steps simulate accepts, and one below it, both back-ends now agree."""
    A, C = np.array([[0.0, 1.0], [-400.0, 0.0]]), np.array([[1.0, 0.0]])
    plant = obsjax.LTI(A, np.zeros((2, 0)), C, jump_ts=(0.001,))
    obs = obsjax.Luenberger(plant, L=[[3.0], [4.0]])
    ts, x0, xh0 = jnp.linspace(0.0, 3.0, 4), jnp.array([1.0, 0.0]), jnp.zeros(2)

    def status(max_steps, masked):
        kw = dict(max_steps=max_steps, throw=False, dt0=0.01)
        if masked:
            return int(obsjax.simulate_batch(plant, obs, x0[None], xh0[None], ts, lockstep=False, **kw).status[0])
        return int(obsjax.simulate(plant, obs, x0, xh0, ts, **kw).status)

    lo, hi = 16, 4096  # simulate fails at lo, succeeds at hi
    assert status(lo, False) == 1 and status(hi, False) == 0
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if status(mid, False) else (lo, mid)
    assert (status(hi, True), status(lo, True)) == (0, 1)
