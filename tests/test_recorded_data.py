"""Observers on recorded data: Measurements (holds, readers, bad data), estimate against simulate, batches of
experiments of different lengths, vmap over initial estimates, reset observers on data."""

import csv

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import obsjax

PLANT = obsjax.LTI([[-2.0, 1.0], [0.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]])
OBS = obsjax.Luenberger.from_poles(PLANT, [-3.0, -4.0])
X0, XH0 = jnp.array([1.0, -1.0]), jnp.zeros(2)
SPAN = 4.0


def _u(t):
    return jnp.array([jnp.sin(2.0 * t) + 0.5 * jnp.cos(0.7 * t)])


@pytest.fixture(scope="module")
def truth():
    """simulate on the finest grid (every coarser sample grid is a subset of it)."""
    ts = np.linspace(0.0, SPAN, 81)
    tr = obsjax.simulate(PLANT, OBS, X0, XH0, ts, u=_u, rtol=1e-11, atol=1e-12)
    return ts, np.asarray(tr.y), np.asarray(jax.vmap(_u)(ts)), np.asarray(tr.xhat)


_est = eqx.filter_jit(lambda obs, data, xh0: obsjax.estimate(obs, data, xh0, rtol=1e-11, atol=1e-12))


@pytest.mark.parametrize("hold,order", [("zoh", 1), ("linear", 2), ("cubic", 3)])
@pytest.mark.extended
def test_estimate_agrees_with_simulate_to_the_interpolation_error_of_the_hold(truth, hold, order):
    ts, y, u, xhat = truth
    # two sample rates (every 4th and every 2nd point of the fine grid) in one stacked, masked batch
    runs = [(slice(None, None, 4), 4), (slice(None, None, 2), 2)]
    data = obsjax.Measurements.stack([obsjax.Measurements(ts[s], y[s], u[s], hold=hold) for s, _ in runs])
    est = _est(OBS, data, XH0)
    assert est.xhat.shape == (2, 41, 2) and not bool(est.valid[0, 21:].any())
    errs = []
    for b, (s, _) in enumerate(runs):
        K = len(ts[s])
        assert int(est.status[b]) == 0 and bool(est.valid[b, :K].all())
        errs.append(float(np.max(np.abs(np.asarray(est.xhat[b, :K]) - xhat[s]))))
    h = SPAN / 20
    # the error is of the size of the hold's interpolation error ...
    bound = {"zoh": 3.0 * h, "linear": 0.5 * h**2, "cubic": 0.5 * h**3}[hold]
    assert errs[0] < bound, (errs, bound)
    # ... and shrinks at the hold's order when the sampling interval halves
    rate = np.log2(errs[0] / errs[1])
    assert order - 0.3 < rate < order + 1.3, (errs, rate)


@pytest.mark.extended
def test_vmap_over_initial_estimates_and_jit(truth):
    ts, y, u, _ = truth
    data = obsjax.Measurements(ts[::4], y[::4], u[::4], hold="linear")
    xh0s = jnp.array([[0.0, 0.0], [1.0, -1.0], [2.0, 3.0]])
    f = eqx.filter_jit(lambda x: obsjax.estimate(OBS, data, x))
    batch = jax.vmap(f)(xh0s)
    for i in range(3):
        one = f(xh0s[i])
        np.testing.assert_allclose(np.asarray(batch.xhat[i]), np.asarray(one.xhat), rtol=1e-10, atol=1e-12)
    # x̂0 = x0 and noise-free data: the Luenberger estimate stays on the true state up to the hold's error
    assert float(jnp.max(jnp.abs(batch.xhat[1, :, 0] - data.y[:, 0]))) < 0.02
    # the innovation is y − C x̂ at the samples
    np.testing.assert_allclose(np.asarray(batch.innovation[2]), np.asarray(data.y - batch.xhat[2][:, :1]), atol=1e-12)


@pytest.mark.extended
def test_experiments_of_different_lengths_batch_with_a_mask(truth):
    ts, y, u, _ = truth
    a = obsjax.Measurements(ts[::4], y[::4], u[::4], hold="cubic")
    b = obsjax.Measurements(ts[:41:2], y[:41:2], u[:41:2], hold="cubic")  # 21 samples on [0, 2]
    data = obsjax.Measurements.stack([a, b])
    assert data.ts.shape == (2, 21) and data.batched
    bb = obsjax.Measurements.stack([b, b, a])  # shapes equal, padding irrelevant here
    est = obsjax.estimate(OBS, data, jnp.stack([XH0, XH0 + 1.0]))
    for i, d in enumerate((a, b)):
        one = obsjax.estimate(OBS, d, XH0 + float(i))
        np.testing.assert_allclose(np.asarray(est.xhat[i, : d.K]), np.asarray(one.xhat), rtol=1e-9, atol=1e-10)
    # the loss ignores padding: masked mean equals the unbatched value
    l_batch = jax.vmap(obsjax.losses.output_error)(est)
    for i, d in enumerate((a, b)):
        one = obsjax.estimate(OBS, d, XH0 + float(i))
        assert abs(float(l_batch[i]) - float(obsjax.losses.output_error(one))) < 1e-12
    assert bb.ts.shape == (3, 21)


@pytest.mark.extended  # 15 s
def test_padding_does_not_run_an_unstable_model_past_the_data():
    """An inverted pendulum's Kalman filter on a 2 s and a 90 s experiment, stacked: the short one was padded
    with samples continuing at its own interval, so its filter predicted open loop over 88 s without an
    update and overflowed (status 2 for data that are fine alone).  The padding now follows the last sample
    within 1e-6 of the span: the stacked estimates equal the single ones, status 0."""
    from obsjax.observers import ContinuousDiscreteKalman

    A, B, C = np.array([[0.0, 1.0], [19.6, 0.0]]), np.array([[0.0], [1.0]]), np.array([[1.0, 0.0]])
    kf = ContinuousDiscreteKalman(obsjax.LTI(A, B, C), 1e-3 * jnp.eye(2), 1e-4 * jnp.eye(1), jnp.eye(2))
    rng = np.random.default_rng(0)

    def experiment(T):
        ts = np.arange(0.0, T, 0.05)
        return obsjax.Measurements(ts, 0.01 * np.sin(ts) + 1e-3 * rng.normal(size=ts.size), -0.206 * np.sin(ts))

    short, long_ = experiment(2.0), experiment(90.0)
    both = obsjax.estimate(kf, obsjax.Measurements.stack([short, long_]), jnp.zeros(2), throw=False)
    assert np.asarray(both.status).tolist() == [0, 0]
    for i, d in enumerate((short, long_)):
        one = obsjax.estimate(kf, d, jnp.zeros(2))
        np.testing.assert_allclose(np.asarray(both.xhat[i, : d.K]), np.asarray(one.xhat), rtol=1e-9, atol=1e-12)


@pytest.mark.extended
@pytest.mark.parametrize("scale", [1.0, 1e-6])
def test_padding_is_relative_to_the_span(scale):
    """The same two experiments (an unstable filter, 10 and 800 samples) in a time unit 1e6 times
    smaller: the padding followed the last sample by an absolute 1e-6 for spans below 1, i.e. 880 spans
    past a 9e-7 s experiment, where the filter overflowed (stacked status [2, 0] against 0 alone).  It is
    relative to the span now: in both units the stacked estimate equals the single one."""
    from obsjax.observers import ContinuousDiscreteKalman

    a = 1.0 / scale  # an unstable pole at +1 per time unit
    kf = ContinuousDiscreteKalman(obsjax.LTI([[a]], C=[[1.0]]), a * jnp.eye(1), 0.01 * jnp.eye(1), jnp.eye(1))
    tA, tB = np.arange(10) * 0.1 * scale, np.arange(800) * 0.1 * scale
    dA = obsjax.Measurements(tA, 0.1 * np.exp(tA * a)[:, None])
    dB = obsjax.Measurements(tB, 0.1 * np.exp(-tB * a)[:, None])
    both = obsjax.estimate(kf, obsjax.Measurements.stack([dA, dB]), jnp.zeros(1), throw=False)
    assert np.asarray(both.status).tolist() == [0, 0]
    one = obsjax.estimate(kf, dA, jnp.zeros(1))
    np.testing.assert_allclose(np.asarray(both.xhat[0, : dA.K]), np.asarray(one.xhat), rtol=1e-9)


@pytest.mark.extended
def test_sample_schedule_is_invariant_under_a_change_of_time_unit():
    """Forty irregular samples about 1 ns apart, given in ns and in s: the schedule's tolerance was
    1e-9·max(1, t_K − t_0), an absolute 1e-9 for spans below 1, so in seconds every pair was refused as
    "closer than the tolerance".  It is 1e-9 of the span now: both records are accepted, and the
    estimates (of the same observer in the two units) agree; a pair closer than 1e-9 of the span is
    refused in both units."""
    rng = np.random.default_rng(0)
    t_ns = np.cumsum(rng.uniform(0.5, 1.5, 40))
    t_ns -= t_ns[0]
    out = []
    for scale in (1.0, 1e-9):
        plant = obsjax.LTI([[-1.0 / scale, 1.0 / scale], [0.0, -1.0 / scale]], C=[[1.0, 0.0]])
        obs = obsjax.Luenberger.from_poles(plant, [-3.0 / scale, -4.0 / scale])
        y = (np.exp(-0.05 * t_ns) * np.cos(t_ns))[:, None]
        est = obsjax.estimate(obs, obsjax.Measurements(t_ns * scale, y), jnp.zeros(2), rtol=1e-10, atol=1e-12)
        assert int(est.status) == 0
        out.append(np.asarray(est.xhat))
        close = t_ns * scale
        close[5] = close[4] + 0.5e-9 * (close[-1] - close[0])
        with pytest.raises(ValueError, match="two samples closer than"):
            obsjax.Measurements(close, y)
    np.testing.assert_allclose(out[1], out[0], rtol=1e-7, atol=1e-9)


def test_no_valid_sample_is_refused_or_nan(truth):
    """A mask with no sample is refused at construction; an estimate with no valid row (the mask
    traced, or padding only) scores NaN, not the zero loss it used to (which reads as a perfect fit)."""
    ts, y, u, _ = truth
    with pytest.raises(ValueError, match="`mask` marks every sample as padding"):
        obsjax.Measurements(ts, y, u, mask=np.zeros(len(ts), bool))
    est = obsjax.estimate(OBS, obsjax.Measurements(ts, y, u), XH0)
    assert np.isfinite(float(obsjax.losses.output_error(est)))
    none = eqx.tree_at(lambda e: e.valid, est, jnp.zeros_like(est.valid))
    assert np.isnan(float(obsjax.losses.output_error(none)))
    assert np.isnan(float(obsjax.losses.output_error(none, integral=True)))
    # valid samples, but no interval with both ends valid: the integral is undefined, not 0
    alternate = eqx.tree_at(lambda e: e.valid, est, jnp.arange(est.valid.shape[0]) % 2 == 0)
    assert np.isnan(float(obsjax.losses.output_error(alternate, integral=True)))
    assert float(obsjax.losses.output_error(alternate)) > 0.0
    # and an empty batch of simulations is a clear error, not an IndexError
    with pytest.raises(ValueError, match="at least one member"):
        obsjax.simulate_batch(PLANT, OBS, jnp.zeros((0, 2)), jnp.zeros((0, 2)), ts)


@pytest.mark.extended
def test_reset_observer_on_data_agrees_with_simulate():
    plant = obsjax.chen_yen_example()
    obs = obsjax.LeastSquaresReset(plant, gamma=20.0, p0=0.1, T=0.9)
    x0, xh0 = jnp.zeros(2), jnp.array([5.0, -5.0])
    ts = np.linspace(0.0, 3.0, 61)
    tr = obsjax.simulate(plant, obs, x0 + 1.0, xh0, ts, rtol=1e-10, atol=1e-12)
    data = obsjax.Measurements(ts, np.asarray(tr.y), hold="cubic")
    est = obsjax.estimate(obs, data, xh0, rtol=1e-10, atol=1e-12)
    assert int(est.status) == 0
    err = np.max(np.abs(np.asarray(est.xhat) - np.asarray(tr.xhat)))
    assert err < 1e-2, err  # C(t) has cos √t: the hold is coarse near t = 0
    # the resets happened: Φ is back to I right after t = 0.9 (a save time at the reset is right-continuous)
    i = int(np.argmin(np.abs(ts - 1.8)))
    np.testing.assert_allclose(np.asarray(est.z.Phi[i]), np.eye(2), atol=1e-9)


@pytest.mark.extended
def test_derivative_in_T_with_resets_on_sample_instants():
    """Reset instants 0.25·k on samples 0.05·k: each is a zero-length segment between two breakpoints,
    whose solve carried no derivative of its ends, so the flow after the reset lost its term −δτ f⁺:
    with save times between the samples (a smooth loss) autodiff gave +157.9 where central differences
    give −16.9.  Now the resets move through the jump condition (as in simulate): the smooth loss's
    derivative equals central differences, and a loss on the samples (a kink at each interior
    coincidence) gets the derivative from the left, as documented."""
    model = obsjax.LTI([[0.0, 1.0], [-2.0, -0.5]], [[0.0], [1.0]], [[1.0, 0.0]])
    obs = obsjax.LeastSquaresReset(model, 5.0, 1.0, 0.25)
    t = 0.05 * np.arange(13)  # resets at 0.25 and 0.5 on samples; t1 = 0.6
    data = obsjax.Measurements(t, np.sin(3 * t)[:, None], np.cos(t)[:, None], hold="linear")
    mid = np.r_[0.0, t[:-1] + 0.025]

    def loss(T, ts):
        o = eqx.tree_at(lambda q: q.T, obs, T)
        est = obsjax.estimate(o, data, jnp.zeros(2), ts=ts, rtol=1e-11, atol=1e-12, max_segments=8)
        return jnp.sum(est.xhat**2) + jnp.sum(est.innovation**2)

    J = jax.jit(lambda T: loss(T, mid))
    h = 1e-6
    fd = (float(J(0.25 + h)) - float(J(0.25 - h))) / (2 * h)
    assert float(jax.grad(J)(jnp.asarray(0.25))) == pytest.approx(fd, rel=1e-4)
    Js = jax.jit(lambda T: loss(T, jnp.asarray(t)))
    left = (float(Js(0.25)) - float(Js(0.25 - h))) / h
    right = (float(Js(0.25 + h)) - float(Js(0.25))) / h
    assert abs(left - right) > 0.1 * abs(left)  # the premise: a kink
    assert float(jax.grad(Js)(jnp.asarray(0.25))) == pytest.approx(left, rel=1e-4)


# ------------------------------------------------------------------------------------------------ bad data


def _ok(K=5):
    ts = np.linspace(0.0, 1.0, K)
    return ts, np.sin(ts)[:, None], np.cos(ts)[:, None]


@pytest.mark.parametrize(
    "ts_fix, match",
    [
        (lambda t: t[[0, 1, 1, 2, 3]], r"`ts` must be strictly increasing, got a duplicate time: ts\[1\]"),
        (lambda t: t[[0, 2, 1, 3, 4]], r"`ts` must be strictly increasing, got a time that goes backwards"),
        (lambda t: np.where(np.arange(5) == 2, np.nan, t), r"`ts` must hold finite times, got nan at sample 2"),
        (lambda t: t[:1], r"`ts` must be a 1-D array of at least 2 sample times"),
        (lambda t: t.reshape(5, 1), r"`ts` must be a 1-D array"),
    ],
)
def test_bad_times_are_refused(ts_fix, match):
    ts, y, u = _ok()
    K = np.asarray(ts_fix(ts)).reshape(-1).shape[0]
    with pytest.raises(ValueError, match=match):
        obsjax.Measurements(ts_fix(ts), y[:K] if K <= 5 else y, u[:K] if K <= 5 else u)


def test_nan_samples_are_refused_or_skipped():
    ts, y, u = _ok(6)
    y[3, 0] = np.nan
    with pytest.raises(ValueError, match=r"`y` holds non-finite samples \(1 of them\), the first at sample 3"):
        obsjax.Measurements(ts, y, u)
    u2 = u.copy()
    u2[1, 0] = np.inf
    with pytest.raises(ValueError, match=r"`u` holds non-finite samples .* sample 1"):
        obsjax.Measurements(ts, np.sin(ts), u2)
    d = obsjax.Measurements(ts, y, u2, missing="skip")  # bridged by the hold; the missing output masked
    assert d.K == 6 and np.all(np.isfinite(np.asarray(d.y))) and np.all(np.isfinite(np.asarray(d.u)))
    assert np.flatnonzero(~np.asarray(d.mask)).tolist() == [3]
    assert float(d.y[3, 0]) == y[2, 0] and float(d.u[1, 0]) == u[0, 0]  # zero-order hold: last value
    dl = obsjax.Measurements(ts, y, u2, missing="skip", hold="linear")  # linear: the line between
    assert float(dl.y[3, 0]) == pytest.approx((y[2, 0] * (ts[4] - ts[3]) + y[4, 0] * (ts[3] - ts[2])) / (ts[4] - ts[2]))
    with pytest.raises(ValueError, match=r"`missing` must be one of 'raise', 'skip', got 'drop'"):
        obsjax.Measurements(ts, y, u, missing="drop")
    y3 = np.full_like(y, np.nan)
    y3[2, 0] = 1.0
    with pytest.raises(ValueError, match=r"`missing='skip'`: 5 of 6 samples lack an output .* 1 remain"):
        obsjax.Measurements(ts, y3, u, missing="skip")
    with pytest.raises(ValueError, match=r"`mask` must hold booleans .* got values \[0, 1, 2\]"):
        obsjax.Measurements(ts, np.sin(ts), u, mask=[1, 2, 0, 1, 1, 1])
    assert np.asarray(obsjax.Measurements(ts, np.sin(ts), u, mask=[1, 0, 1, 1, 1, 1]).mask).tolist()[:2] == [True, False]


def test_lengths_holds_and_shapes_are_checked():
    ts, y, u = _ok()
    with pytest.raises(ValueError, match=r"`y` has 4 samples but `ts` has 5"):
        obsjax.Measurements(ts, y[:4], u)
    with pytest.raises(ValueError, match=r"`u` has 6 samples but `ts` has 5"):
        obsjax.Measurements(ts, y, np.zeros((6, 1)))
    with pytest.raises(ValueError, match=r"`hold` must be one of 'zoh', 'linear', 'cubic', got 'foh'"):
        obsjax.Measurements(ts, y, u, hold="foh")
    with pytest.raises(ValueError, match=r"`x_index` \(which states `x_ref` holds"):
        obsjax.Measurements(ts, y, u, x_ref=y)
    with pytest.raises(ValueError, match=r"`x_index` must list integer state indices"):  # not truncated to 1
        obsjax.Measurements(ts, y, u, x_ref=y, x_index=1.9)
    assert obsjax.Measurements(ts, y, u, x_ref=y, x_index=np.array([1])).x_index == (1,)
    d = obsjax.Measurements(ts, y)  # no input, but the observer's model has one
    with pytest.raises(ValueError, match=r"`data` has p = 0 inputs but the observer's model has p = 1"):
        obsjax.estimate(OBS, d, XH0)
    with pytest.raises(ValueError, match=r"`data` has m = 2 outputs but the observer's model has m = 1"):
        obsjax.estimate(OBS, obsjax.Measurements(ts, np.hstack([y, y]), u), XH0)
    with pytest.raises(ValueError, match=r"`xhat0` must have shape \(2,\)"):
        obsjax.estimate(OBS, obsjax.Measurements(ts, y, u), jnp.zeros(3))
    with pytest.raises(ValueError, match=r"`ts` must lie within the data's sample times"):
        obsjax.estimate(OBS, obsjax.Measurements(ts, y, u), XH0, ts=np.linspace(0.0, 2.0, 5))
    with pytest.raises(ValueError, match=r"`data` must be an obsjax.Measurements, got dict"):
        obsjax.estimate(OBS, {"ts": ts}, XH0)
    with pytest.raises(ValueError, match=r"`datasets`\[1\] has hold='linear'"):
        obsjax.Measurements.stack([obsjax.Measurements(ts, y, u), obsjax.Measurements(ts, y, u, hold="linear")])


def test_traced_bad_times_fail_under_jit():
    ts, y, u = _ok()
    bad = ts[[0, 1, 1, 2, 3]]
    f = jax.jit(lambda t: obsjax.Measurements(t, y, u).ts)
    with pytest.raises(Exception, match="strictly increasing sample times"):
        jax.block_until_ready(f(bad))
    g = jax.jit(lambda yy: obsjax.Measurements(ts, yy, u).y)
    with pytest.raises(Exception, match=r"`y` must hold finite samples"):
        jax.block_until_ready(g(np.where(np.arange(5)[:, None] == 2, np.nan, y)))


def _swapped_times():
    ts, y, u = _ok()
    data = obsjax.Measurements(ts, y, u)
    bad = (ts[[0, 2, 1, 3, 4]], np.where(np.arange(5) == 3, np.nan, ts))
    return ts, data, bad


def test_sample_times_replaced_after_construction_are_refused_eagerly():
    """The driver's schedule no longer checks the samples inside its compiled program (a host callback
    there kept the program out of the persistent cache): estimate checks them before it, so times swapped
    in with ``eqx.tree_at`` past the constructor's checks (decreasing, NaN) are still refused."""
    ts, data, bad = _swapped_times()
    for b in bad:
        swapped = eqx.tree_at(lambda d: d.ts, data, jnp.asarray(b))
        with pytest.raises(ValueError, match=r"`data.ts` must hold finite, non-decreasing sample times"):
            obsjax.estimate(OBS, swapped, XH0)


@pytest.mark.extended
def test_sample_times_replaced_after_construction_are_refused_under_jit():
    """The same swapped times traced under jit are refused by the check made outside the driver; good
    traced times give the eager estimate, and the checks of `throw` still fire under jit."""
    ts, data, bad = _swapped_times()
    f = jax.jit(lambda t: obsjax.estimate(OBS, eqx.tree_at(lambda d: d.ts, data, t), XH0).xhat)
    for b in bad:
        with pytest.raises(Exception, match=r"`data.ts` must hold finite, non-decreasing sample times"):
            jax.block_until_ready(f(jnp.asarray(b)))
    ok = f(jnp.asarray(ts))
    np.testing.assert_allclose(np.asarray(ok), np.asarray(obsjax.estimate(OBS, data, XH0).xhat), rtol=1e-12, atol=1e-14)
    # throw=True under jit: a NaN initial estimate makes the estimate non-finite, and reading it raises
    nan0 = jnp.full(2, jnp.nan)
    g = jax.jit(lambda x: obsjax.estimate(OBS, data, x).xhat)
    with pytest.raises(Exception, match="obsjax.estimate: the estimate diverged"):
        jax.block_until_ready(g(nan0))
    assert int(jnp.max(jax.jit(lambda x: obsjax.estimate(OBS, data, x, throw=False).status)(nan0))) != 0


def test_samples_closer_than_the_schedule_tolerance_are_refused():
    """Two samples 1e-10 apart (a merged sensor stream) are one instant for estimate's update schedule: one
    update was lost and a saved row came back as zeros with status 0.  Refused, eagerly and under jit; a
    pair just outside the tolerance is kept, and gives the two updates."""
    ts, y, u = _ok()
    close = ts.copy()
    close[3] = close[2] + 1e-10
    with pytest.raises(ValueError, match=r"`ts` holds two samples closer than .* ts\[2\] = .* ts\[3\]"):
        obsjax.Measurements(close, y, u)
    f = jax.jit(lambda t: obsjax.Measurements(t, y, u).ts)
    with pytest.raises(Exception, match="two samples closer than"):
        jax.block_until_ready(f(close))
    apart = ts.copy()
    apart[3] = apart[2] + 1e-7  # 100 times the tolerance (the span is 1)
    est = obsjax.estimate(OBS, obsjax.Measurements(apart, y, u), XH0)
    assert int(est.status) == 0 and np.all(np.abs(np.asarray(est.xhat[2:4])) > 0)


def test_nan_validation_states_fail_under_jit():
    ts, y, u = _ok()
    xr = np.asarray(y).copy()
    xr[2, 0] = np.nan
    f = jax.jit(lambda x: obsjax.estimate(OBS, obsjax.Measurements(ts, y, u, x_ref=x, x_index=(0,)), XH0).state_error)
    with pytest.raises(Exception, match=r"`x_ref` must hold finite samples"):
        jax.block_until_ready(f(xr))


def _write_csv(path, header, rows):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)


def test_from_csv_and_from_dataframe(tmp_path):
    ts, y, u = _ok(6)
    p = tmp_path / "run.csv"
    _write_csv(p, ["time", "theta", "volts", "omega"], np.hstack([ts[:, None], y, u, 2 * y]).tolist())
    d = obsjax.Measurements.from_csv(p, t="time", y="theta", u=["volts"], x=["omega"], x_index=[1], hold="linear")
    np.testing.assert_array_equal(np.asarray(d.ts), ts)
    np.testing.assert_array_equal(np.asarray(d.u), u)
    assert d.hold == "linear" and d.x_index == (1,) and d.names == (("theta",), ("volts",))
    with pytest.raises(ValueError, match=r"column 'speed' \(argument `y`\) is not in .*available columns: "
                                         r"\['time', 'theta', 'volts', 'omega'\]"):
        obsjax.Measurements.from_csv(p, t="time", y=["speed"])
    with pytest.raises(ValueError, match=r"column 'tt' \(argument `t`\)"):
        obsjax.Measurements.from_csv(p, t="tt", y=["theta"])
    # an empty field reads as NaN: refused, or skipped
    rows = np.hstack([ts[:, None], y, u, y]).astype(object)
    rows[2, 1] = ""
    _write_csv(p, ["time", "theta", "volts", "omega"], rows.tolist())
    with pytest.raises(ValueError, match=r"`y` holds non-finite samples .* sample 2"):
        obsjax.Measurements.from_csv(p, t="time", y=["theta"], u=["volts"])
    skipped = obsjax.Measurements.from_csv(p, t="time", y=["theta"], u=["volts"], missing="skip")
    assert skipped.K == 6 and np.flatnonzero(~np.asarray(skipped.mask)).tolist() == [2]
    rows[3, 2] = "n/a"
    _write_csv(p, ["time", "theta", "volts", "omega"], rows.tolist())
    with pytest.raises(ValueError, match=r"line 5, column 'volts' is not a number: 'n/a'"):
        obsjax.Measurements.from_csv(p, t="time", y=["theta"], u=["volts"])
    # a spreadsheet's "CSV UTF-8" starts with a byte-order mark: its first column was named '\ufefftime'
    p.write_bytes("\ufefftime,theta\n0.0,1.0\n0.5,2.0\n".encode("utf-8"))
    d = obsjax.Measurements.from_csv(p, t="time", y="theta")
    np.testing.assert_array_equal(np.asarray(d.ts), [0.0, 0.5])
    # a column named twice: reading it by name would take one of the two silently
    _write_csv(p, ["time", "theta", "theta", "omega"], [[0.0, 1.0, 10.0, 0.0], [0.1, 2.0, 20.0, 0.0]])
    with pytest.raises(ValueError, match=r"names a column more than once: 'theta' \(columns \[1, 2\]\)"):
        obsjax.Measurements.from_csv(p, t="time", y=["theta"])
    # any mapping of columns works as a data frame (pandas itself is optional)
    frame = {"t": ts, "y": y[:, 0], "u": u[:, 0]}
    d2 = obsjax.Measurements.from_dataframe(frame, t="t", y=["y"], u=["u"])
    np.testing.assert_array_equal(np.asarray(d2.y), y)
    pd = pytest.importorskip("pandas")
    df = pd.DataFrame(frame)
    d3 = obsjax.Measurements.from_dataframe(df, t="t", y=["y"], u=["u"])
    np.testing.assert_array_equal(np.asarray(d3.to_dataframe()["y"]), y[:, 0])


def test_holds_evaluate_through_diffrax_interpolation():
    ts = np.array([0.0, 0.1, 0.25, 0.3, 0.5, 0.8])  # irregular
    y = np.sin(3 * ts)
    for hold in ("linear", "cubic"):
        d = obsjax.Measurements(ts, y, hold=hold)
        np.testing.assert_allclose(np.asarray(d.evaluate(ts)[0][:, 0]), y, atol=1e-14)  # interpolates
    d = obsjax.Measurements(ts, y, hold="zoh")
    assert float(d.evaluate(0.29)[0][0]) == y[2] and float(d.evaluate(0.3)[0][0]) == y[3]  # right-continuous
    # the cubic hold reproduces quadratics exactly (the three-point slopes are exact for them)
    q = 1.0 + 2.0 * ts - 3.0 * ts**2
    dq = obsjax.Measurements(ts, q, hold="cubic")
    tt = np.linspace(0.0, 0.8, 17)
    np.testing.assert_allclose(np.asarray(dq.evaluate(tt)[0][:, 0]), 1.0 + 2.0 * tt - 3.0 * tt**2, atol=1e-13)


W_MODEL = 1.0


def _A_global(t):
    return jnp.array([[-2.0, W_MODEL], [0.0, -1.0]])


@pytest.mark.extended
def test_estimate_traces_again_after_a_changed_global():
    """An observer whose LTV model reads a global: after the global changes, estimate gives the estimate
    of the new model (that of a new function object with the value written in), not the program compiled
    before (the driver was keyed on the function's identity)."""
    global W_MODEL
    ts = np.linspace(0.0, 2.0, 21)
    data = obsjax.Measurements(ts, np.sin(ts)[:, None], np.zeros((21, 1)))
    B, C = (lambda t: jnp.array([[0.0], [1.0]])), (lambda t: jnp.array([[1.0, 0.0]]))

    def run(A):
        model = obsjax.LTV(A=A, B=B, C=C)
        obs = obsjax.KalmanBucy(model, Qw=jnp.eye(2), Rv=jnp.eye(1), P0=jnp.eye(2))
        return np.asarray(obsjax.estimate(obs, data, jnp.ones(2)).xhat)

    first = run(_A_global)
    try:
        W_MODEL = 5.0
        second = run(_A_global)
    finally:
        W_MODEL = 1.0
    fresh = run(lambda t: jnp.array([[-2.0, 5.0], [0.0, -1.0]]))
    assert np.max(np.abs(second - first)) > 1e-2
    np.testing.assert_allclose(second, fresh, rtol=1e-12, atol=1e-14)


@pytest.mark.extended
@pytest.mark.parametrize("K_short", [2, 3, 12])
def test_cubic_hold_padding_leaves_the_short_experiments_unchanged(K_short):
    """Stacked with a longer one, a cubic-hold experiment's last sample became interior and its slope was
    taken from the repeated padding value (about 0): estimates 1.25e-2 off on its last interval.  The
    padding value lies on the parabola through the last three samples (the secant for two), so the held
    signal and the estimates equal those of the experiment alone."""
    rng = np.random.default_rng(K_short)

    def experiment(K):
        ts = np.cumsum(np.r_[0.0, rng.uniform(0.05, 0.2, K - 1)])
        return obsjax.Measurements(ts, np.sin(3 * ts) + 0.1 * rng.normal(size=K), np.cos(2 * ts), hold="cubic")

    short, long_ = experiment(K_short), experiment(40)
    st = obsjax.Measurements.stack([short, long_])
    one = jax.tree_util.tree_map(lambda a: a[0], st)
    tm = np.linspace(short.ts[0], short.ts[-1], 31)
    np.testing.assert_allclose(np.asarray(one.evaluate(tm)[0]), np.asarray(short.evaluate(tm)[0]), atol=1e-10)  # was 4e-2 off
    kw = dict(rtol=1e-12, atol=1e-14)
    both = obsjax.estimate(OBS, st, jnp.zeros(2), **kw)
    alone = obsjax.estimate(OBS, short, jnp.zeros(2), **kw)
    np.testing.assert_allclose(np.asarray(both.xhat[0, :K_short]), np.asarray(alone.xhat), atol=1e-10)


def test_date_columns_and_an_index_column_are_not_misread():
    """Datetime and timedelta columns were converted to tick counts (ns, µs) and read as seconds: a 10 ms
    sampling interval became 1e7; and t='index' took the frame's index even where a column named 'index'
    (the old index, after reset_index) held the time.  Both are refused now."""
    base = np.datetime64("2026-01-01T00:00:00", "ns")
    stamps = base + np.arange(5) * np.timedelta64(10, "ms")
    y = np.sin(np.arange(5.0))
    for col in (stamps, stamps - base, (stamps - base).astype("timedelta64[ms]")):
        with pytest.raises(ValueError, match="dates or durations"):
            obsjax.Measurements.from_dataframe({"time": col, "y": y}, t="time", y="y")
    seconds = (stamps - stamps[0]) / np.timedelta64(1, "s")
    m = obsjax.Measurements.from_dataframe({"time": seconds, "y": y}, t="time", y="y")
    np.testing.assert_allclose(np.diff(np.asarray(m.ts)), 0.01, rtol=1e-12)

    class Frame(dict):  # a mapping with an index, as a DataFrame after reset_index()
        index = np.arange(5.0)

    with pytest.raises(ValueError, match="column named 'index'"):
        obsjax.Measurements.from_dataframe(Frame(index=seconds, y=y), t="index", y="y")


def test_evaluate_refuses_times_outside_the_samples():
    """The linear hold extrapolated without a word (3.32 where the last sample is 0.84)."""
    ts = np.linspace(0.0, 1.0, 11)
    m = obsjax.Measurements(ts, np.sin(ts), hold="linear")
    np.testing.assert_allclose(np.asarray(m.evaluate(ts)[0])[:, 0], np.sin(ts), rtol=1e-14)
    for t in (1.5, -0.1, [0.5, 2.0], float("nan")):
        with pytest.raises(ValueError, match="holds the samples on"):
            m.evaluate(t)


def test_csv_rows_of_empty_fields_follow_the_missing_mode(tmp_path):
    """A line of empty fields (",") was dropped silently even with missing="raise", and a sample without
    its time was refused even with missing="skip".  Empty lines are still no samples."""
    p = tmp_path / "gaps.csv"
    p.write_text("t,y\n0,1\n0.1,2\n,\n0.2,3\n\n0.3,4\n,5\n")
    with pytest.raises(ValueError, match="finite times"):
        obsjax.Measurements.from_csv(p, t="t", y="y")
    m = obsjax.Measurements.from_csv(p, t="t", y="y", missing="skip")
    np.testing.assert_array_equal(np.asarray(m.ts), [0.0, 0.1, 0.2, 0.3])
    np.testing.assert_array_equal(np.asarray(m.y)[:, 0], [1.0, 2.0, 3.0, 4.0])


def test_epoch_time_stamps_warn_of_their_resolution():
    """At |t| = 1.7e9 s float64 resolves 2.4e-7 s, 2.4e-4 of a 1 ms sampling interval: the holds and the
    solver silently lost that much relative accuracy.  Such time stamps now warn, naming the remedy; the
    same samples from t = 0 do not."""
    import warnings

    ts = 1.7e9 + 1e-3 * np.arange(50)
    y = np.sin(np.arange(50.0))
    with pytest.warns(UserWarning, match=r"resolves time to 2\.4e-07, 2\.4e-04 of the shortest .*\(ts − ts\[0\]"):
        obsjax.Measurements(ts, y)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        obsjax.Measurements(ts - ts[0], y)
        obsjax.Measurements(1e3 + 1e-3 * np.arange(50), y)  # 1.1e-10 of the interval


@pytest.mark.extended
def test_tune_on_data_warns_of_reset_instants_on_the_samples_of_any_experiment():
    """Samples on reset instants t0 + kT make the derivative in T unreliable; only the first
    experiment of a batch was checked, so a coincidence in the second went without a warning."""
    import optax

    model = obsjax.LTI([[0.0, 1.0], [-2.0, -0.5]], [[0.0], [1.0]], [[1.0, 0.0]])
    obs = obsjax.LeastSquaresReset(model, 5.0, 1.0, 0.25)
    rng = np.random.default_rng(1)
    t_irregular = np.sort(np.r_[0.0, rng.uniform(0.0, 1.97, 39), 1.97]) + 0.0123
    t_grid = 0.05 * np.arange(41)  # 0.25, 0.5, ... are reset instants

    def mk(ts):
        return obsjax.Measurements(ts, np.sin(3 * ts)[:, None], np.cos(ts)[:, None])

    for order in ((t_irregular, t_grid), (t_grid, t_irregular)):
        with pytest.warns(obsjax.TuneWarning, match=r"save times 0\.25, 0\.5, 0\.75, 1, 1\.25, \.\.\. coincide"):
            obsjax.tune_on_data(obs, [mk(t) for t in order], where=lambda o: o.T, xhat0=jnp.zeros(2),
                                optimizer=optax.sgd(0.0), steps=1, progress=False)
