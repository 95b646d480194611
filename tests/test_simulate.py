"""simulate: closed forms, batching, statuses, resets, closed loop, noise."""

import control
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
import scipy.linalg

import obsjax
from obsjax._simulate import _Args, _drift

A28 = np.array([[-2.0, 1.0], [0.0, -1.0]])
B28 = np.array([[0.0], [1.0]])
C28 = np.array([[1.0, 0.0]])
PLANT = obsjax.LTI(A28, B28, C28)
TS = jnp.linspace(0.0, 4.0, 41)
U = obsjax.signals.multisine([1.0, 0.5], [1.0, 2.7])
TIGHT = dict(rtol=1e-10, atol=1e-12)


@pytest.mark.extended
def test_luenberger_error_matches_closed_form():
    """x̃(t) = exp((A - LC) t) x̃(0), whatever the input (Theorem 1 with T = I)."""
    obs = obsjax.Luenberger.from_poles(PLANT, [-3.0, -3.0])
    x0, xh0 = jnp.array([1.0, -2.0]), jnp.array([0.0, 0.5])
    tr = obsjax.simulate(PLANT, obs, x0, xh0, TS, u=U, **TIGHT)
    F = A28 - np.asarray(obs.gain) @ C28
    ref = np.stack([scipy.linalg.expm(F * t) @ np.asarray(xh0 - x0) for t in np.asarray(TS)])
    np.testing.assert_allclose(tr.error, ref, atol=1e-9)
    assert int(tr.status) == 0


@pytest.mark.extended
def test_reduced_order_error_matches_closed_form():
    obs = obsjax.ReducedOrder.from_poles(PLANT, [-3.0])
    x0, xh0 = jnp.array([1.0, -2.0]), jnp.array([0.0, 0.5])
    tr = obsjax.simulate(PLANT, obs, x0, xh0, TS, u=U, **TIGHT)
    # y is measured exactly; the unmeasured part decays as exp(-3 t)
    np.testing.assert_allclose(tr.error[:, 0], 0.0, atol=1e-12)
    ref = np.exp(-3.0 * np.asarray(TS)) * float(xh0[1] - x0[1])
    np.testing.assert_allclose(tr.error[:, 1], ref, atol=1e-9)


def test_functional_observer_closed_form():
    """ŝ − aᵀx = kᵀ exp(F t)(z(0) − T x(0)) and T A − F T = G C."""
    A = np.array([[-2, 1, 0, 0], [0, -2, 1, 0], [0, 0, -1, 1], [1, 0, 0, -3.0]])
    B = np.array([[0], [0], [0], [1.0]])
    C = np.array([[1, 0, 0, 0], [0, 0, 1, 0.0]])
    plant = obsjax.LTI(A, B, C)
    a = np.array([0.0, 1.0, 0.0, 1.0])
    fo = obsjax.FunctionalObserver(plant, a, [-3.0])
    assert fo.order == 1  # ν − 1 with ν = 2
    T, F, G = map(np.asarray, (fo.T, fo.F, fo.G))
    np.testing.assert_allclose(T @ A - F @ T, G @ C, atol=1e-10)
    np.testing.assert_allclose(np.asarray(fo.k) @ T + np.asarray(fo.e) @ C, a, atol=1e-10)
    x0, xh0 = jnp.array([1.0, 1.0, -1.0, 2.0]), jnp.zeros(4)
    tr = obsjax.simulate(plant, fo, x0, xh0, TS, u=U, **TIGHT)
    ref = np.exp(-3.0 * np.asarray(TS)) * float(np.asarray(fo.k) @ (T @ np.asarray(xh0 - x0)))
    np.testing.assert_allclose(tr.error[:, 0], ref, atol=1e-9)


@pytest.mark.extended
def test_vmap_over_64_initial_conditions_equals_loop():
    obs = obsjax.Luenberger.from_poles(PLANT, [-2.0, -4.0])
    key = jr.PRNGKey(0)
    x0s = jr.normal(key, (64, 2))
    xh0s = jnp.zeros((64, 2))
    f = jax.jit(lambda x0, xh0: obsjax.simulate(PLANT, obs, x0, xh0, TS, u=U).error)
    batched = jax.vmap(f)(x0s, xh0s)
    looped = jnp.stack([f(x0s[i], xh0s[i]) for i in range(64)])
    np.testing.assert_allclose(batched, looped, rtol=1e-7, atol=1e-9)


@pytest.mark.extended
def test_throw_false_reports_per_trajectory_status_under_vmap():
    obs = obsjax.Luenberger.from_poles(PLANT, [-2.0, -4.0])
    x0s = jnp.array([[1.0, 0.0], [jnp.nan, 0.0], [0.0, 1.0]])

    def run(x0):
        return obsjax.simulate(PLANT, obs, x0, jnp.zeros(2), TS, throw=False)

    tr = jax.vmap(run)(x0s)
    assert tr.status.tolist()[0] == 0 and tr.status.tolist()[2] == 0
    assert tr.status.tolist()[1] != 0
    assert np.all(np.isfinite(tr.error[0])) and np.all(np.isfinite(tr.error[2]))


@pytest.mark.extended
def test_throw_true_raises_on_solver_failure():
    obs = obsjax.Luenberger.from_poles(PLANT, [-2.0, -4.0])
    with pytest.raises(Exception, match="did not reach the end"):
        obsjax.simulate(PLANT, obs, jnp.ones(2), jnp.zeros(2), TS, max_steps=3)


@pytest.mark.extended
def test_fixed_step_matches_adaptive():
    obs = obsjax.Luenberger.from_poles(PLANT, [-2.0, -4.0])
    a = obsjax.simulate(PLANT, obs, jnp.ones(2), jnp.zeros(2), TS, u=U, **TIGHT)
    b = obsjax.simulate(PLANT, obs, jnp.ones(2), jnp.zeros(2), TS, u=U, dt0=1e-3, adaptive=False)
    np.testing.assert_allclose(a.x, b.x, atol=1e-9)


class _ClockReset(obsjax.AbstractObserver):
    """Luenberger observer plus a clock reset every T (a minimal hybrid observer for the tests)."""

    inner: obsjax.Luenberger
    T: jax.Array

    def init(self, t0, xhat0, y0):
        return (xhat0, jnp.zeros(()))

    def vector_field(self, t, z, y, u):
        return (self.inner.vector_field(t, z[0], y, u), jnp.ones(()))

    def estimate(self, t, z, y):
        return z[0]

    @property
    def reset_period(self):
        return self.T

    def reset(self, t, z):
        return (z[0], jnp.zeros(()))


@pytest.mark.extended
def test_segmented_resets_match_smooth_solve_and_reset_clock():
    obs = obsjax.Luenberger.from_poles(PLANT, [-3.0, -3.0]).prepare()
    r = _ClockReset(obs, jnp.asarray(0.33))
    a = obsjax.simulate(PLANT, obs, jnp.ones(2), jnp.zeros(2), TS, u=U, **TIGHT)
    b = obsjax.simulate(PLANT, r, jnp.ones(2), jnp.zeros(2), TS, u=U, **TIGHT)
    np.testing.assert_allclose(a.xhat, b.xhat, atol=1e-9)
    t = np.asarray(TS)
    np.testing.assert_allclose(b.z[1], t - 0.33 * np.floor(t / 0.33 + 1e-9), atol=1e-9)
    # the same under jit with a traced period and a static segment bound
    c = jax.jit(lambda T: obsjax.simulate(PLANT, eqx.tree_at(lambda o: o.T, r, T), jnp.ones(2), jnp.zeros(2), TS,
                                          u=U, max_segments=16, **TIGHT).z[1])(0.33)
    np.testing.assert_allclose(c, b.z[1], atol=1e-9)


@pytest.mark.extended
def test_gradient_wrt_reset_period_matches_finite_differences():
    obs = obsjax.Luenberger.from_poles(PLANT, [-3.0, -3.0]).prepare()
    r = _ClockReset(obs, jnp.asarray(0.347))

    def f(T):
        tr = obsjax.simulate(PLANT, eqx.tree_at(lambda o: o.T, r, T), jnp.ones(2), jnp.zeros(2), TS, **TIGHT)
        return jnp.sum(tr.z[1] ** 2)

    g = jax.grad(f)(0.347)
    h = 1e-6
    fd = (f(0.347 + h) - f(0.347 - h)) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_traced_period_without_max_segments_is_a_clear_error():
    obs = obsjax.Luenberger.from_poles(PLANT, [-3.0, -3.0]).prepare()
    r = _ClockReset(obs, jnp.asarray(0.33))
    with pytest.raises(ValueError, match="max_segments"):
        jax.jit(lambda T: obsjax.simulate(PLANT, eqx.tree_at(lambda o: o.T, r, T), jnp.ones(2), jnp.zeros(2), TS).x)(0.33)


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.extended
def test_separation_principle_random_systems(seed):
    """Thesis ch. 2 Theorem 4 / (3.12): the closed loop through the estimate has eig(A+BK) ∪ eig(A−LC)."""
    rng = np.random.default_rng(seed)
    n, m, p = 3, 1 + seed % 2, 1 + (seed + 1) % 2
    A, B, C = rng.standard_normal((n, n)), rng.standard_normal((n, p)), rng.standard_normal((m, n))
    plant = obsjax.LTI(A, B, C)
    K = -control.place(A, B, [-1.0, -1.5, -2.0])
    obs = obsjax.Luenberger.from_poles(plant, [-3.0, -4.0, -5.0]).prepare()
    args = _Args(plant, obs, None, lambda t, xh: K @ xh, None)

    def joint(v):
        dx, dz = _drift(0.0, (v[:n], v[n:]), args)
        return jnp.concatenate([dx, dz])

    J = np.asarray(jax.jacfwd(joint)(jnp.zeros(2 * n)))
    eig = np.sort_complex(np.linalg.eigvals(J))
    ref = np.sort_complex(np.concatenate([np.linalg.eigvals(A + B @ K), np.linalg.eigvals(A - np.asarray(obs.L) @ C)]))
    np.testing.assert_allclose(eig, ref, atol=1e-7)
    # and the simulated closed loop follows the composite matrix exponential
    x0 = jnp.asarray(rng.standard_normal(n))
    tr = obsjax.simulate(plant, obs, x0, jnp.zeros(n), TS, controller=lambda t, xh: K @ xh, **TIGHT)
    v0 = np.concatenate([np.asarray(x0), np.zeros(n)])
    refx = np.stack([(scipy.linalg.expm(J * t) @ v0)[:n] for t in np.asarray(TS)])
    np.testing.assert_allclose(tr.x, refx, atol=1e-8)


@pytest.mark.extended
def test_band_limited_noise_is_keyed_and_vmappable():
    obs = obsjax.Luenberger.from_poles(PLANT, [-3.0, -3.0])
    noise = obsjax.noise.BandLimitedNoise(0.1, dt=0.05)

    def run(k):
        return obsjax.simulate(PLANT, obs, jnp.ones(2), jnp.zeros(2), TS, noise=noise, key=k).y

    keys = jr.split(jr.PRNGKey(1), 3)
    ys = jax.vmap(run)(keys)
    np.testing.assert_allclose(ys[0], run(keys[0]), atol=1e-12)
    assert np.max(np.abs(ys[0] - ys[1])) > 1e-3
    clean = obsjax.simulate(PLANT, obs, jnp.ones(2), jnp.zeros(2), TS).y
    resid = np.asarray(ys[:, :, 0] - clean[None, :, 0])
    assert 0.05 < resid.std() < 0.2  # σ = 0.1 samples, linearly interpolated


@pytest.mark.extended
def test_white_noise_steady_state_covariance_matches_lyapunov():
    """Under white measurement noise σ dW, the error covariance solves (A−LC)P + P(A−LC)ᵀ + σ² L Lᵀ = 0."""
    obs = obsjax.Luenberger.from_poles(PLANT, [-2.0, -3.0])
    sigma = 0.2
    ts = jnp.array([0.0, 8.0])
    noise = obsjax.noise.WhiteNoise(sigma)

    def run(k):
        return obsjax.simulate(PLANT, obs, jnp.zeros(2), jnp.zeros(2), ts, noise=noise, key=k, dt0=2e-3).error[-1]

    errs = np.asarray(jax.jit(jax.vmap(run))(jr.split(jr.PRNGKey(2), 1024)))
    L = np.asarray(obs.gain)
    F = A28 - L @ C28
    P = scipy.linalg.solve_continuous_lyapunov(F, -(sigma**2) * L @ L.T)
    emp = np.cov(errs.T)
    np.testing.assert_allclose(np.diag(emp), np.diag(P), rtol=0.15)


@pytest.mark.extended
def test_white_noise_statistics_do_not_depend_on_where_the_save_times_fall():
    """Under white noise a save time between two Euler–Maruyama steps returned the straight line between
    them, whose variance is below the path's (0.90 of it at mid-step here): the statistics at the save
    times depended on the save grid.  The steps now end at the save times, so with save times at the
    middles of the dt0 grid (then spaced dt0) the scalar error e' = −k e + L σ ξ has, at every save time,
    the stationary variance of the scheme, L²σ² dt0 / (1 − (1 − k dt0)²)."""
    a, L, sig, dt0 = 1.0, 3.0, 0.5, 0.05
    k = a + L
    plant = obsjax.LTI([[-a]], [[0.0]], [[1.0]])  # x = 0, so e = x̂
    obs = obsjax.Luenberger(plant, L=[[L]])
    # the middles of the steps of [0, 2.3] (46 steps of dt0), and its end
    ts = jnp.concatenate([jnp.array([0.0]), 2.025 + dt0 * jnp.arange(6), jnp.array([2.3])])
    N = 4000
    tb = obsjax.simulate_batch(
        plant, obs, jnp.zeros((N, 1)), jnp.zeros((N, 1)), ts, keys=jr.split(jr.PRNGKey(21), N),
        noise=obsjax.noise.WhiteNoise(sig), dt0=dt0,
    )  # fmt: skip
    assert np.all(np.asarray(tb.status) == 0)
    e = np.asarray(tb.error[:, 1:-1, 0])
    v = L**2 * sig**2 * dt0 / (1 - (1 - k * dt0) ** 2)
    ratio = (e**2).mean(0) / v
    se = np.sqrt(2 / N)  # of a variance estimate, Gaussian samples
    assert np.all(np.abs(ratio - 1) < 3 * se), ratio  # before: 0.90 at every save time (−4.5 s.e.)


@pytest.mark.extended
def test_a_traced_negative_noise_intensity_is_refused_under_jit():
    """The eager call refused WhiteNoise(−0.5) and BandLimitedNoise(−0.5); under jit both gave status 0."""
    obs = obsjax.Luenberger.from_poles(PLANT, [-3.0, -3.0])
    ts = jnp.linspace(0.0, 1.0, 6)
    for make in (obsjax.noise.WhiteNoise, lambda s: obsjax.noise.BandLimitedNoise(s, dt=0.1)):
        run = jax.jit(lambda s: obsjax.simulate(PLANT, obs, jnp.ones(2), jnp.zeros(2), ts, noise=make(s),
                                                key=jr.PRNGKey(0), throw=False).status)  # fmt: skip
        assert int(run(0.5)) == 0
        with pytest.raises(Exception, match="`sigma` must be ≥ 0"):
            jax.block_until_ready(run(-0.5))


def test_lti_from_control_and_nonlinear_plant():
    sys = control.ss(A28, B28, C28, 0)
    p = obsjax.LTI.from_control(sys)
    np.testing.assert_allclose(p.A, A28)
    vdp = obsjax.Nonlinear(lambda t, x, u: jnp.array([x[1], -x[0] + (1 - x[0] ** 2) * x[1]]),
                           lambda t, x, u: x[:1], n=2, m=1)
    lin = obsjax.LTI([[0.0, 1.0], [-1.0, 1.0]], None, [[1.0, 0.0]])
    obs = obsjax.Luenberger.from_poles(lin, [-5.0, -6.0])
    tr = obsjax.simulate(vdp, obs, jnp.array([0.1, 0.0]), jnp.zeros(2), jnp.linspace(0, 1, 11))
    assert tr.x.shape == (11, 2) and int(tr.status) == 0


# ---------------------------------------------------------------- bad input
def test_lti_bad_shapes():
    with pytest.raises(ValueError, match="`A` must be a square"):
        obsjax.LTI(np.ones((2, 3)), None, np.ones((1, 3)))
    with pytest.raises(ValueError, match="`C` must have shape"):
        obsjax.LTI(A28, B28, np.ones((1, 3)))
    with pytest.raises(ValueError, match="`B` must be a 2-D"):
        obsjax.LTI(A28, np.ones(2), C28)
    with pytest.raises(ValueError, match="`D` must have shape"):
        obsjax.LTI(A28, B28, C28, np.ones((2, 1)))
    with pytest.raises(ValueError, match="`C` must be a 2-D"):
        obsjax.LTI(A28, B28, np.ones(2))


def test_booleans_are_refused_where_numbers_belong():
    """A mask passed as save times, a state, a matrix or measurements was read as 1/0 without a word."""
    obs = obsjax.Luenberger.from_poles(PLANT, [-3.0, -3.0])
    with pytest.raises(ValueError, match="`ts` must hold numbers, got booleans"):
        obsjax.simulate(PLANT, obs, jnp.ones(2), jnp.zeros(2), np.array([False, True]))
    with pytest.raises(ValueError, match="`x0` must hold numbers, got booleans"):
        obsjax.simulate(PLANT, obs, np.array([True, False]), jnp.zeros(2), TS)
    with pytest.raises(ValueError, match="`xhat0s` must hold numbers, got booleans"):
        obsjax.simulate_batch(PLANT, obs, jnp.ones((2, 2)), np.zeros((2, 2), bool), TS)
    with pytest.raises(ValueError, match="`A` must hold numbers, got booleans"):
        obsjax.LTI(np.eye(2, dtype=bool), B28, C28)
    with pytest.raises(ValueError, match="`y` must hold numbers, got booleans"):
        obsjax.Measurements(np.arange(3.0), np.array([True, False, True]))


def test_simulate_bad_inputs():
    obs = obsjax.Luenberger.from_poles(PLANT, [-3.0, -3.0])
    with pytest.raises(ValueError, match="`x0` must have shape"):
        obsjax.simulate(PLANT, obs, jnp.ones(3), jnp.zeros(2), TS)
    with pytest.raises(ValueError, match="strictly increasing"):
        obsjax.simulate(PLANT, obs, jnp.ones(2), jnp.zeros(2), TS[::-1])
    with pytest.raises(ValueError, match="`key` is required"):
        obsjax.simulate(PLANT, obs, jnp.ones(2), jnp.zeros(2), TS, noise=obsjax.noise.WhiteNoise(0.1))
    with pytest.raises(ValueError, match="`dt0` is required"):
        obsjax.simulate(PLANT, obs, jnp.ones(2), jnp.zeros(2), TS, adaptive=False)
    with pytest.raises(ValueError, match="`observer` must be"):
        obsjax.simulate(PLANT, "L", jnp.ones(2), jnp.zeros(2), TS)


def test_observer_constructor_errors():
    with pytest.raises(ValueError, match="exactly one of"):
        obsjax.Luenberger(PLANT, L=[[1.0], [1.0]], poles=[-1.0, -2.0])
    with pytest.raises(ValueError, match="`L` must have shape"):
        obsjax.Luenberger(PLANT, L=[[1.0, 1.0]])
    with pytest.raises(ValueError, match="not observable"):
        obsjax.Luenberger.from_poles(obsjax.LTI([[1.0, 0.0], [0.0, 2.0]], None, [[1.0, 0.0]]), [-1.0, -2.0])
    with pytest.raises(ValueError, match="fewer outputs than states"):
        obsjax.ReducedOrder.from_poles(obsjax.LTI(A28, B28, np.eye(2)), [])
    with pytest.raises(ValueError, match="ν − 1"):
        obsjax.FunctionalObserver(PLANT, [1.0, 1.0], [-3.0, -4.0])


def test_numpy_integer_max_steps_in_simulate():
    """`max_steps` as a NumPy integer was traced as an array (TracerBoolConversionError inside diffrax);
    it is the same count as a Python int (the other entry points: the extended test below)."""
    plant = obsjax.LTI([[-2.0, 1.0], [0.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]])
    obs = obsjax.Luenberger(plant, L=[[3.0], [4.0]])
    ts = jnp.linspace(0.0, 2.0, 5)
    x0, xh0 = jnp.array([1.0, -1.0]), jnp.zeros(2)
    ref = obsjax.simulate(plant, obs, x0, xh0, ts, max_steps=100).error_norm
    np.testing.assert_array_equal(obsjax.simulate(plant, obs, x0, xh0, ts, max_steps=np.int64(100)).error_norm, ref)


@pytest.mark.extended
def test_numpy_integer_step_counts_are_taken_as_ints():
    """`max_steps` (and `max_segments`) as NumPy integers pass the argument check, but were traced as
    arrays: simulate, the lock-step batch and estimate failed inside diffrax (TracerBoolConversionError)
    and monte_carlo refused them as "got JitTracer".  They are the same counts as Python ints."""
    import jax

    plant = obsjax.LTI([[-2.0, 1.0], [0.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]])
    obs = obsjax.Luenberger(plant, L=[[3.0], [4.0]])
    ts = jnp.linspace(0.0, 2.0, 5)
    x0, xh0 = jnp.array([1.0, -1.0]), jnp.zeros(2)
    ref = obsjax.simulate(plant, obs, x0, xh0, ts, max_steps=100).error_norm
    data = obsjax.Measurements(ts, np.asarray(obsjax.simulate(plant, obs, x0, xh0, ts).y), np.zeros(5))
    est_ref = obsjax.estimate(obs, data, xh0, max_steps=100).xhat
    for ms in (np.int64(100), np.int32(100)):
        np.testing.assert_array_equal(obsjax.simulate(plant, obs, x0, xh0, ts, max_steps=ms).error_norm, ref)
        for lockstep in (True, False):
            tr = obsjax.simulate_batch(plant, obs, x0[None], xh0[None], ts, max_steps=ms, lockstep=lockstep)
            np.testing.assert_allclose(tr.error_norm[0], ref, rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(obsjax.estimate(obs, data, xh0, max_steps=ms).xhat, est_ref)
        res = obsjax.monte_carlo(
            plant, obs, jax.random.PRNGKey(0), 2, x0_sampler=lambda k: x0, xhat0_sampler=lambda k: xh0, ts=ts,
            simulate_kwargs=dict(max_steps=ms), progress=False,
        )
        np.testing.assert_allclose(res.error_norm[0], ref, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("name", ["rtol", "atol"])
def test_array_tolerances_are_refused_by_name(name):
    """rtol/atol as arrays: an (n,) array was accepted by simulate and the lock-step batch (broadcast
    against each leaf of the joint state) and refused by the masked batch with a broadcasting error, a
    (2n,) one the other way round.  Every path refuses them, naming the argument, before any solve."""
    plant = obsjax.LTI([[0.0, 1.0], [-2.0, -0.3]], [[0.0], [1.0]], [[1.0, 0.0]])
    obs = obsjax.Luenberger(plant, L=[[3.0], [4.0]])
    ts, x0, xh0 = np.linspace(0.0, 3.0, 7), np.array([1.0, -1.0]), np.zeros(2)
    for tol in (jnp.full(2, 1e-9), jnp.full(4, 1e-9)):
        kw = {name: tol}
        with pytest.raises(ValueError, match=f"`{name}` must be a scalar"):
            obsjax.simulate(plant, obs, x0, xh0, ts, **kw)
        for lockstep in (True, False):
            with pytest.raises(ValueError, match=f"`{name}` must be a scalar"):
                obsjax.simulate_batch(plant, obs, x0[None], xh0[None], ts, lockstep=lockstep, **kw)
