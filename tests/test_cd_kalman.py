"""The continuous–discrete Kalman filter against the discrete Kalman filter of the exactly discretised model
(matrix exponential, a NumPy loop), in estimate and in simulate; the gradient of output_error against finite
differences; tune_on_data on a held-out experiment."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.linalg

import obsjax

A = np.array([[0.0, 1.0], [-2.0, -0.5]])
B = np.array([[0.0], [1.0]])
C = np.array([[1.0, 0.0]])
QW = np.diag([1e-2, 5e-2])
RV = np.array([[4e-2]])
P0 = np.eye(2)
H = 0.05
MODEL = obsjax.LTI(A, B, C)


def discretise(A, B, Qw, h):
    """Exact ZOH discretisation: Ad = e^{Ah}, Bd = ∫ e^{Aτ} dτ B, Qd = ∫ e^{Aτ} Qw e^{Aᵀτ} dτ (Van Loan,
    "Computing integrals involving the matrix exponential", IEEE TAC 23(3), 1978)."""
    n, p = B.shape
    F = scipy.linalg.expm(np.block([[A, B], [np.zeros((p, n + p))]]) * h)
    V = scipy.linalg.expm(np.block([[-A, Qw], [np.zeros((n, n)), A.T]]) * h)
    return F[:n, :n], F[:n, n:], V[n:, n:].T @ V[:n, n:]


def discrete_kalman(y, u, x0, P0, Ad, Bd, Qd, C, Rv, update=None):
    """Filtered means and covariances x̂_k|k, P_k|k (the prior at the first sample is x0, P0); no
    update where ``update[k]`` is False (a missing measurement)."""
    x, P, xs, Ps = x0.copy(), P0.copy(), [], []
    for k in range(len(y)):
        if update is not None and not update[k]:
            xs.append(x.copy())
            Ps.append(P.copy())
            x, P = Ad @ x + Bd @ u[k], Ad @ P @ Ad.T + Qd
            continue
        S = C @ P @ C.T + Rv
        K = np.linalg.solve(S, C @ P).T
        x = x + K @ (y[k] - C @ x)
        P = (np.eye(len(x)) - K @ C) @ P @ (np.eye(len(x)) - K @ C).T + K @ Rv @ K.T
        xs.append(x.copy())
        Ps.append(P.copy())
        x, P = Ad @ x + Bd @ u[k], Ad @ P @ Ad.T + Qd
    return np.array(xs), np.array(Ps)


def experiment(K, seed, h=H):
    """Noisy samples of the discretised plant (process and measurement noise), with a random ZOH input."""
    rng = np.random.default_rng(seed)
    Ad, Bd, Qd = discretise(A, B, np.diag([4e-4, 1e-2]) / h, h)
    x, ys, us = np.zeros(2), [], rng.normal(size=(K, 1))
    Lq = np.linalg.cholesky(Qd)
    for k in range(K):
        ys.append(C @ x + 0.05 * rng.normal(size=1))
        x = Ad @ x + Bd @ us[k] + Lq @ rng.normal(size=2)
    return obsjax.Measurements(h * np.arange(K), np.array(ys), us)


def test_continuous_discrete_equals_discrete_kalman_of_the_exact_discretisation():
    data = experiment(61, 0)
    kf = obsjax.observers.ContinuousDiscreteKalman(MODEL, QW, RV, P0)
    xh0 = np.array([0.3, -0.2])
    est = obsjax.estimate(kf, data, xh0, solver=diffrax.Dopri8(), rtol=1e-12, atol=1e-13)
    xs, Ps = discrete_kalman(np.asarray(data.y), np.asarray(data.u), xh0, P0, *discretise(A, B, QW, H), C, RV)
    np.testing.assert_allclose(np.asarray(est.xhat), xs, rtol=0, atol=1e-8)
    np.testing.assert_allclose(np.asarray(est.z.P), Ps, rtol=0, atol=1e-8)
    # the innovation is the one-step prediction error y_k − C x̂_k|k−1 (before the update)
    prior = np.concatenate([xh0[None], np.asarray(est.xhat[:-1]) @ discretise(A, B, QW, H)[0].T
                            + np.asarray(data.u[:-1]) @ discretise(A, B, QW, H)[1].T])
    np.testing.assert_allclose(np.asarray(est.innovation), np.asarray(data.y) - prior @ C.T, atol=1e-8)


@pytest.mark.extended
def test_missing_measurements_skip_the_update_and_keep_the_input():
    """missing="skip" dropped a sample with a missing output together with its recorded input: the
    zero-order hold then applied the previous input over the gap (0.82 off the filter that skips the
    update only).  Now the sample stays (the estimate is aligned with the recorded times), its update is
    skipped and its input is used."""
    data = experiment(41, 3)
    y = np.asarray(data.y).copy()
    missing = [5, 6, 20]
    y[missing] = np.nan
    gappy = obsjax.Measurements(np.asarray(data.ts), y, np.asarray(data.u), missing="skip")
    assert gappy.K == 41 and np.flatnonzero(~np.asarray(gappy.mask)).tolist() == missing
    kf = obsjax.observers.ContinuousDiscreteKalman(MODEL, QW, RV, P0)
    xh0 = np.array([0.3, -0.2])
    est = obsjax.estimate(kf, gappy, xh0, solver=diffrax.Dopri8(), rtol=1e-12, atol=1e-13)
    update = np.ones(41, bool)
    update[missing] = False
    xs, Ps = discrete_kalman(
        np.nan_to_num(y), np.asarray(data.u), xh0, P0, *discretise(A, B, QW, H), C, RV, update=update
    )
    np.testing.assert_allclose(np.asarray(est.xhat), xs, rtol=0, atol=1e-8)
    np.testing.assert_allclose(np.asarray(est.z.P), Ps, rtol=0, atol=1e-8)
    # a missing validation state is never fed to the observer: the estimate does not move
    x_ref = np.asarray(est.xhat)[:, :1].copy()
    x_ref[[3, 9]] = np.nan
    with_ref = obsjax.Measurements(np.asarray(data.ts), y, np.asarray(data.u), missing="skip", x_ref=x_ref, x_index=[0])
    assert np.flatnonzero(~np.asarray(with_ref.mask)).tolist() == missing
    est2 = obsjax.estimate(kf, with_ref, xh0, solver=diffrax.Dopri8(), rtol=1e-12, atol=1e-13)
    np.testing.assert_array_equal(np.asarray(est2.xhat), np.asarray(est.xhat))


@pytest.mark.extended
def test_continuous_discrete_kalman_in_simulate_samples_the_plant_at_its_period():
    # simulate with a sampling period and estimate on the plant's samples are the same filter: the plant
    # is free (u = 0), so the samples are exact and the two drivers must agree to the solver tolerance
    kf = obsjax.ContinuousDiscreteKalman(MODEL, QW, RV, P0, period=0.1)
    ts = np.linspace(0.0, 2.0, 21)
    x0, xh0 = jnp.array([1.0, -1.0]), jnp.zeros(2)
    tr = obsjax.simulate(MODEL, kf, x0, xh0, ts, rtol=1e-11, atol=1e-12)
    data = obsjax.Measurements(ts, np.asarray(tr.y), np.zeros((21, 1)))
    est = obsjax.estimate(kf, data, xh0, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(np.asarray(est.xhat), np.asarray(tr.xhat), atol=1e-8)
    # and both equal the NumPy filter on the samples
    xs, _ = discrete_kalman(np.asarray(tr.y), np.zeros((21, 1)), np.zeros(2), P0, *discretise(A, B, QW, 0.1), C, RV)
    np.testing.assert_allclose(np.asarray(tr.xhat), xs, atol=1e-8)
    with pytest.raises(ValueError, match="needs `period`"):
        obsjax.simulate(MODEL, obsjax.ContinuousDiscreteKalman(MODEL, QW, RV, P0), x0, xh0, ts)
    with pytest.raises(ValueError, match=r"`period` \(the sampling interval\) must be finite and > 0"):
        obsjax.ContinuousDiscreteKalman(MODEL, QW, RV, P0, period=-1.0)
    with pytest.raises(ValueError, match=r"`times` \(the sampling instants\) must be finite and strictly increasing"):
        obsjax.ContinuousDiscreteKalman(MODEL, QW, RV, P0, times=[0.0, 0.2, 0.2])
    with pytest.raises(ValueError, match=r"give `period` .* or `times` .*, not both"):
        obsjax.ContinuousDiscreteKalman(MODEL, QW, RV, P0, period=0.1, times=[0.0, 0.2])
    irregular = obsjax.ContinuousDiscreteKalman(MODEL, QW, RV, P0, times=[0.0, 0.3, 0.35, 1.2])
    np.testing.assert_array_equal(irregular.event_times(0.0, 1.0), [0.0, 0.3, 0.35, 1.2])
    with pytest.raises(ValueError, match=r"`Rv` must be positive definite"):
        obsjax.ContinuousDiscreteKalman(MODEL, QW, -RV, P0)


@pytest.fixture(scope="module")
def runs():
    return experiment(80, 1), experiment(60, 2), experiment(100, 3)


@pytest.mark.extended
def test_output_error_gradient_matches_finite_differences(runs):
    data = runs[0]
    kf = obsjax.ContinuousDiscreteKalman(MODEL, QW, RV, P0)

    @eqx.filter_jit
    def J(qw, rv):
        k = eqx.tree_at(lambda o: (o.Qw, o.Rv), kf, (qw, rv))
        est = obsjax.estimate(k, data, jnp.zeros(2), rtol=1e-10, atol=1e-12)
        return obsjax.losses.output_error(est) + 0.1 * obsjax.losses.output_error(est, integral=True)

    q, r = jnp.asarray(QW), jnp.asarray(RV)
    gq, gr = jax.grad(J, argnums=(0, 1))(q, r)
    eps = 1e-6
    E = [jnp.zeros((2, 2)).at[i, i].set(eps) for i in range(2)]
    fd_q = [(J(q + e, r) - J(q - e, r)) / (2 * eps) for e in E]
    fd_r = (J(q, r + eps) - J(q, r - eps)) / (2 * eps)
    np.testing.assert_allclose(np.diag(np.asarray(gq)), np.asarray(fd_q), rtol=1e-5)
    np.testing.assert_allclose(float(gr[0, 0]), float(fd_r), rtol=1e-5)
    assert abs(float(gq[1, 1])) > 1e-6 and abs(float(gr[0, 0])) > 1e-6


@pytest.mark.extended
def test_tune_on_data_improves_a_held_out_experiment(runs):
    train = [runs[0], runs[1]]  # different lengths: padded and masked
    held_out = runs[2]
    kf = obsjax.ContinuousDiscreteKalman(MODEL, Qw=1e-4 * np.eye(2), Rv=np.array([[1.0]]), P0=np.eye(2))
    res = obsjax.tune_on_data(kf, train, where=lambda o: (o.Qw, o.Rv), xhat0=jnp.zeros(2),
                              optimizer=optax.adam(0.3), steps=12, progress=False)
    assert res.history["loss"][res.history["best_step"]] < 0.8 * res.history["loss"][0]
    Qw = np.asarray(res.observer.Qw)
    assert Qw[0, 1] == 0.0 and np.all(np.diag(Qw) > 0)  # structural zeros stay zero
    val = lambda o: float(obsjax.losses.output_error(obsjax.estimate(o, held_out, jnp.zeros(2))))
    before, after = val(kf), val(res.observer)
    print(before, after)
    assert after < 0.8 * before, (before, after)


@pytest.mark.extended
def test_tune_on_data_checks_its_arguments(runs):
    kf = obsjax.ContinuousDiscreteKalman(MODEL, QW, RV, P0)
    with pytest.raises(ValueError, match=r"`datasets` must be an obsjax.Measurements or a non-empty list"):
        obsjax.tune_on_data(kf, [], where=lambda o: o.Rv, xhat0=jnp.zeros(2))
    with pytest.raises(ValueError, match=r"`xhat0` must be \(n,\) or \(2, n\)"):
        obsjax.tune_on_data(kf, list(runs[:2]), where=lambda o: o.Rv, xhat0=jnp.zeros((3, 2)))
    with pytest.raises(ValueError, match=r"`estimate_kwargs` must not contain 'throw'"):
        obsjax.tune_on_data(kf, runs[0], where=lambda o: o.Rv, xhat0=jnp.zeros(2), estimate_kwargs={"throw": True})
    with pytest.raises(ValueError, match=r"`where` must be a callable"):
        obsjax.tune_on_data(kf, runs[0], where="Rv", xhat0=jnp.zeros(2))
    with pytest.raises(ValueError, match=r"`state_error` needs validation states"):
        obsjax.losses.state_error(obsjax.estimate(kf, runs[1], jnp.zeros(2)))


@pytest.mark.extended
def test_sampling_instants_from_a_period_hold_at_clock_times():
    """With t0 a clock time (1e8 s, or a Unix time 1.7e9 s), (t1 − t0)/period read 2.9999995 and the
    update at t1 was dropped: P11(t1) = 0.0357 instead of 0.0189.  The count now uses the schedule's
    time tolerance (relative to the horizon plus the times' rounding)."""
    A, C = np.array([[0.0, 1.0], [-2.0, -0.5]]), np.array([[1.0, 0.0]])
    plant = obsjax.LTI(A, np.zeros((2, 1)), C)
    kf = obsjax.ContinuousDiscreteKalman(plant, 0.01 * np.eye(2), np.array([[0.04]]), np.eye(2), period=0.1)
    for t0 in (1.7e9, 1e8):
        for k in (3, 5, 10):
            ts = t0 + 0.1 * np.arange(k + 1)
            ev = kf.event_times(ts[0], ts[-1])
            assert len(ev) == k + 1 and ev[-1] == ts[-1], (t0, k, ev)
    run = lambda ts: obsjax.simulate(plant, kf, np.array([1.0, 0.0]), np.zeros(2), ts, rtol=1e-10, atol=1e-12)
    P0 = run(np.array([0.0, 0.1, 0.2, 0.3])).z.P[-1, 0, 0]
    P8 = run(1e8 + np.array([0.0, 0.1, 0.2, 0.3])).z.P[-1, 0, 0]
    np.testing.assert_allclose(P8, P0, rtol=1e-5)  # the times at 1e8 carry a rounding of 1.5e-8
    assert float(P0) == pytest.approx(0.018859, abs=1e-6)


def test_white_measurement_noise_is_refused_by_observers_with_discrete_updates():
    """White noise has no value at an instant: the updates saw the noise-free output, so a study with
    WhiteNoise(100) gave the estimate of the noise-free one without a word."""
    cd = obsjax.ContinuousDiscreteKalman(MODEL, Qw=QW, Rv=RV, P0=P0, period=H)
    ts = jnp.linspace(0.0, 1.0, 11)
    with pytest.raises(ValueError, match="has no value at an instant"):
        obsjax.simulate(MODEL, cd, jnp.array([1.0, 0.0]), jnp.zeros(2), ts,
                        noise=obsjax.noise.WhiteNoise(0.2), key=jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="has no value at an instant"):
        obsjax.simulate_batch(MODEL, cd, jnp.ones((2, 2)), jnp.zeros((2, 2)), ts,
                              noise=obsjax.noise.WhiteNoise(0.2), keys=jax.random.split(jax.random.PRNGKey(0), 2))
