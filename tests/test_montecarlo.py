"""Tests of obsjax.monte_carlo: closed forms, chunk/shard/resume invariance, failure accounting."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg

import obsjax
from obsjax.montecarlo import summarise

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# Module-level samplers: the compiled chunk kernel is cached on them, so tests reuse one compilation.
A = np.array([[-2.0, 1.0], [0.0, -1.0]])
PLANT = obsjax.LTI(A, [[0.0], [1.0]], [[1.0, 0.0]])
OBS = obsjax.Luenberger.from_poles(PLANT, [-3.0, -3.0])
TS = np.linspace(0.0, 3.0, 16)


def x0_normal(key):
    return jr.normal(key, (2,))


def xhat0_zero(key):
    return jnp.zeros(2)


def run(n=40, chunk_size=16, **kw):
    kw.setdefault("x0_sampler", x0_normal)
    kw.setdefault("xhat0_sampler", xhat0_zero)
    kw.setdefault("ts", TS)
    kw.setdefault("progress", False)
    return obsjax.monte_carlo(
        kw.pop("plant", PLANT),
        kw.pop("observer", OBS),
        jr.PRNGKey(7),
        n,
        chunk_size=chunk_size,
        **kw,
    )


def _x0_of(i, key=jr.PRNGKey(7)):
    return np.asarray(x0_normal(jr.split(jr.fold_in(key, i), 4)[0]))


@pytest.fixture(scope="module")
def base():
    return run()


def test_matches_closed_form_error(base):
    # Luenberger on the exact model: x̃(t) = exp((A − LC) t) x̃(0) with x̃(0) = x̂0 − x0 = −x0 (thesis (2.7)).
    F = np.asarray(OBS.observer_matrix)
    ref = np.empty((40, TS.size))
    for i in range(40):
        e0 = -_x0_of(i)
        ref[i] = [np.linalg.norm(scipy.linalg.expm(F * t) @ e0) for t in TS]
    np.testing.assert_allclose(base.error_norm, ref, rtol=2e-5, atol=1e-7)
    # bands are the empirical quantiles of the closed-form norms
    np.testing.assert_allclose(
        base.bands, np.quantile(ref, base.quantiles, axis=0), rtol=2e-5, atol=1e-7
    )
    assert base.complete and base.n_failed == 0 and base.failure_fraction == 0.0


def test_band_is_the_quantile_of_the_successful_rows(base):
    """``band(q)`` at a level the result holds returns that band (computed once with the result), and at
    another level the same quantile computed afresh: both equal NumPy's quantile of the successful rows."""
    rows = base.error_norm[base.ok]
    for q in (*base.quantiles, 0.3, 0.99):
        np.testing.assert_array_equal(base.band(q), np.quantile(rows, q, axis=0))
    q = base.quantiles[0]
    b = base.band(q)
    b[:] = -1.0  # a copy: the result's bands are not changed through it
    assert np.all(base.bands[0] >= 0.0)


def test_chunk_size_does_not_change_result(base):
    other = run(chunk_size=24)  # 40 = 24 + 16 (padded last chunk)
    np.testing.assert_array_equal(other.status, base.status)
    np.testing.assert_allclose(other.error_norm, base.error_norm, rtol=0, atol=1e-12)


def test_convergence_time_closed_form():
    # ‖x̃(t)‖ = ‖x̃0‖ e^{−λ t}: it stays below 5 % of ‖x̃0‖ from t* = ln(20)/λ on.  The crossing is
    # interpolated log-linearly between save times, which is exact for an exponential: t* on any
    # grid, not the next save time; a decay too slow for the horizon never converges (inf).
    lam = np.array([1.0, 2.0, 0.5])
    for num in (81, 9, 5):  # fine and coarse grids give the same t*
        ts = np.linspace(0.0, 4.0, num)
        norms = np.exp(-np.outer(lam, ts)) * np.array([[3.0], [1.0], [2.0]])
        res = summarise(ts, norms, np.zeros(3, dtype=int), conv_tol=0.05)
        tstar = np.log(20.0) / lam
        np.testing.assert_allclose(res.convergence_time[:2], tstar[:2], rtol=1e-12)
        assert np.isinf(res.convergence_time[2])  # ln 20 / 0.5 = 6 > 4
        # absolute threshold
        res_abs = summarise(ts, norms, np.zeros(3, dtype=int), conv_tol=0.1, conv_relative=False)
        t_abs = np.log(np.array([3.0, 1.0, 2.0]) / 0.1) / lam
        np.testing.assert_allclose(res_abs.convergence_time[:2], t_abs[:2], rtol=1e-12)
        assert np.isinf(res_abs.convergence_time[2])  # ln 20 / 0.5 = 6 > 4


def test_ise_on_an_uneven_grid_and_the_caller_array_untouched():
    """ISE: the trapezoid of ‖x̃‖² on the save grid, uneven spacing included (scipy.integrate.trapezoid, and
    for a linear ‖x̃‖² the exact integral); every row successful (summarise then copies nothing but
    the rows it keeps) and one failed row give the same statistics of the others; the caller's array
    is left as it was."""
    from scipy.integrate import trapezoid

    ts = np.array([0.0, 0.1, 0.35, 0.4, 1.0, 2.5, 2.6])
    norms = np.vstack([np.sqrt(1.0 + 2.0 * ts), np.exp(-ts), 3.0 * np.exp(-2.0 * ts)])
    before = norms.copy()
    res = summarise(ts, norms, np.zeros(3, dtype=int), conv_tol=0.05)
    np.testing.assert_array_equal(norms, before)
    np.testing.assert_allclose(res.ise, trapezoid(norms**2, ts, axis=1), rtol=1e-14)
    assert res.ise[0] == pytest.approx(2.6 + 2.6**2, rel=1e-14)  # ∫ (1 + 2t) dt on [0, 2.6]
    with_failure = summarise(
        ts, np.vstack([norms, np.full(ts.shape, np.nan)]), np.array([0, 0, 0, 1]), conv_tol=0.05
    )
    np.testing.assert_array_equal(with_failure.ise[:3], res.ise)
    np.testing.assert_array_equal(with_failure.convergence_time[:3], res.convergence_time)
    np.testing.assert_array_equal(with_failure.bands, res.bands)
    np.testing.assert_array_equal(with_failure.error_norm_mean, res.error_norm_mean)
    assert np.isnan(with_failure.ise[3]) and np.isnan(with_failure.convergence_time[3])


def test_convergence_time_is_the_last_crossing():
    """A norm that dips below the threshold and rises again converges at its last crossing; one
    never above the threshold converges at 0; a row still above at the end never converges."""
    ts = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    norms = np.array(
        [
            [1.0, 0.01, 0.2, 0.02, 0.01],  # below 0.05 at t = 1, above at t = 2, below from t = 3
            [0.0, 0.0, 0.0, 0.0, 0.0],  # no error at all
            [1.0, 0.5, 0.2, 0.1, 0.06],  # still above 5 % at t = 4
        ]
    )
    res = summarise(ts, norms, np.zeros(3, dtype=int), conv_tol=0.05)
    # log-linear between (2, 0.2) and (3, 0.02): 0.2·10^(−(t − 2)) = 0.05 at t = 2 + log10(4)
    assert res.convergence_time[0] == pytest.approx(2.0 + np.log10(4.0), rel=1e-12)
    assert res.convergence_time[1] == 0.0
    assert np.isinf(res.convergence_time[2])


def test_overflowing_error_counts_as_failed_even_with_status_zero():
    """Defence in depth: a row whose ‖x̃‖ overflows (inf, NaN, or an ISE beyond float64) is a
    failure (status 2) in the result, whatever the solver reported; every statistic stays finite."""
    ts = np.linspace(0.0, 2.0, 5)
    good = np.exp(-np.outer([1.0, 2.0, 3.0], ts))
    blowup = [1.0, 1e10, 1e300, np.inf, np.inf]
    nan = [1.0, np.nan, 1.0, 1.0, 1.0]
    ise_overflow = [1.0, 1e200, 1e200, 1e200, 1e200]  # finite norms, ∫‖x̃‖² beyond float64
    rows = np.vstack([good, blowup, nan, ise_overflow])
    status = np.array([0, 0, 1, 0, 0, 0])
    res = summarise(ts, rows, status)
    np.testing.assert_array_equal(res.status, [0, 0, 1, 2, 2, 2])
    assert res.n_failed == 4 and res.failure_fraction == pytest.approx(4 / 6)
    np.testing.assert_array_equal(res.ok, [True, True, False, False, False, False])
    assert np.all(np.isfinite(res.bands))
    np.testing.assert_allclose(res.bands, np.quantile(good[:2], res.quantiles, axis=0))
    s = res.summary()
    for k in ("final_median", "final_p95", "ise_mean", "ise_cvar95", "conv_median", "conv_p95"):
        assert np.isfinite(s[k]), k
    assert s["failed"] == 4
    assert s["ise_mean"] == pytest.approx(np.nanmean(res.ise[:2]))
    assert np.all(np.isnan(res.ise[2:])) and np.all(np.isnan(res.convergence_time[2:]))
    assert "failed=4" in repr(res)


def test_resume_after_interruption_equals_uninterrupted(base, tmp_path):
    ck = tmp_path / "ck"
    part = run(checkpoint=ck, max_chunks=2)  # stop after 2 of 3 chunks
    assert not part.complete and part.n_done == 32 and part.n_computed == 32
    assert np.all(part.status[32:] == -1)
    assert sorted(os.listdir(ck)) == ["chunk_000000.npz", "chunk_000001.npz", "meta.json"]
    resumed = run(checkpoint=ck)
    assert resumed.complete and resumed.n_computed == 8  # only the missing chunk was computed
    np.testing.assert_array_equal(resumed.status, base.status)
    np.testing.assert_array_equal(resumed.error_norm, base.error_norm)
    np.testing.assert_array_equal(resumed.bands, base.bands)
    # a further call loads everything and computes nothing
    again = run(checkpoint=ck)
    assert again.n_computed == 0
    np.testing.assert_array_equal(again.error_norm, base.error_norm)


def test_checkpoint_of_other_study_raises(tmp_path):
    ck = tmp_path / "ck"
    run(n=16, checkpoint=ck)
    other = obsjax.Luenberger.from_poles(PLANT, [-4.0, -4.0])
    with pytest.raises(ValueError, match="different study"):
        run(n=16, checkpoint=ck, observer=other)


# ---- failures: counted, never averaged --------------------------------------------------------------------

BLOWUP = obsjax.Nonlinear(lambda t, x, u: x**2, lambda t, x, u: x, n=1, m=1)
SCALAR_MODEL = obsjax.LTI([[0.0]], None, [[1.0]])
SCALAR_OBS = obsjax.Luenberger(SCALAR_MODEL, L=[[1.0]])


def x0_uniform(key):
    return jr.uniform(key, (1,), minval=0.0, maxval=1.0)


def test_failures_are_counted_not_averaged():
    # ẋ = x² blows up at t = 1/x0: every trajectory with x0 > 1/t1 must fail, every other must succeed.
    ts = np.linspace(0.0, 2.0, 11)
    res = obsjax.monte_carlo(
        BLOWUP,
        SCALAR_OBS,
        jr.PRNGKey(3),
        48,
        x0_sampler=x0_uniform,
        xhat0_sampler=np.zeros(1),
        ts=ts,
        chunk_size=16,
        progress=False,
        simulate_kwargs={"max_steps": 2048},
    )
    x0 = np.array(
        [float(x0_uniform(jr.split(jr.fold_in(jr.PRNGKey(3), i), 4)[0])[0]) for i in range(48)]
    )
    expect_fail = x0 > 1.0 / ts[-1]
    assert 0 < expect_fail.sum() < 48
    np.testing.assert_array_equal(res.status > 0, expect_fail)
    assert res.n_failed == expect_fail.sum()
    assert res.failure_fraction == pytest.approx(expect_fail.mean())
    assert np.all(np.isfinite(res.bands))
    assert np.all(np.isnan(res.error_norm[expect_fail]))
    assert np.all(np.isnan(res.convergence_time[expect_fail]))
    # the statistics are those of the successful trajectories alone
    ok_norms = res.error_norm[~expect_fail]
    np.testing.assert_allclose(res.bands, np.quantile(ok_norms, res.quantiles, axis=0))
    assert res.summary()["failed"] == expect_fail.sum()
    # survivors against the closed form x(t) = x0 / (1 − x0 t), x̂ from x̂' = y − x̂ (L = 1, model ẋ = 0)
    i = int(np.flatnonzero(~expect_fail)[0])
    sol = scipy.integrate.solve_ivp(
        lambda t, s: [s[0] ** 2, s[0] - s[1]],
        (0, 2),
        [x0[i], 0.0],
        t_eval=ts,
        rtol=1e-10,
        atol=1e-12,
    )
    np.testing.assert_allclose(res.error_norm[i], np.abs(sol.y[1] - sol.y[0]), rtol=1e-4, atol=1e-6)


# ---- a resetting observer and sampled plants ---------------------------------------------------------------


class _ResettingGain(obsjax.AbstractObserver):
    """Scalar test observer with a reset: x̂' = a x̂ + k(t)(y − x̂), k' = −k, k(jT⁺) = k0."""

    a: jax.Array
    k0: jax.Array
    T: jax.Array

    def init(self, t0, xhat0, y0):
        return (jnp.asarray(xhat0), self.k0)

    def vector_field(self, t, z, y, u):
        xh, k = z
        return (self.a * xh + k * (y - xh), -k)

    def estimate(self, t, z, y):
        return z[0]

    @property
    def reset_period(self):
        return self.T

    def reset(self, t, z):
        return (z[0], self.k0)


SCALAR_PLANT = obsjax.LTI([[0.5]], None, [[1.0]])
RESET_OBS = _ResettingGain(jnp.array(0.5), jnp.array(4.0), jnp.array(0.5))


def scale_a(key, plant):
    # model uncertainty: true a ~ U(0.3, 0.7)
    return eqx.tree_at(lambda p: p.A, plant, jr.uniform(key, (1, 1), minval=0.3, maxval=0.7))


@pytest.mark.extended
def test_resetting_observer_with_sampled_plants_against_scipy():
    ts = np.linspace(0.0, 2.0, 9)
    key = jr.PRNGKey(11)
    res = obsjax.monte_carlo(
        SCALAR_PLANT,
        RESET_OBS,
        key,
        6,
        x0_sampler=x0_uniform,
        xhat0_sampler=np.zeros(1),
        ts=ts,
        param_sampler=scale_a,
        chunk_size=4,
        progress=False,
        simulate_kwargs={"rtol": 1e-9, "atol": 1e-11},
    )
    for i in range(6):
        kx, _, _, kp = jr.split(jr.fold_in(key, i), 4)
        a_true = float(scale_a(kp, SCALAR_PLANT).A[0, 0])
        x = float(x0_uniform(kx)[0])
        s = np.array([x, 0.0, 4.0])
        errs = [abs(s[1] - s[0])]
        for j in range(4):  # segments of T = 0.5, reset k = k0 at each
            s[2] = 4.0
            sol = scipy.integrate.solve_ivp(
                lambda t, v: [a_true * v[0], 0.5 * v[1] + v[2] * (v[0] - v[1]), -v[2]],
                (0.5 * j, 0.5 * (j + 1)),
                s,
                t_eval=[0.5 * j + 0.25, 0.5 * (j + 1)],
                rtol=1e-11,
                atol=1e-13,
            )
            errs += list(np.abs(sol.y[1] - sol.y[0]))
            s = sol.y[:, -1].copy()
        np.testing.assert_allclose(res.error_norm[i], errs, rtol=1e-6, atol=1e-9)


# ---- plots --------------------------------------------------------------------------------------------------


def test_plot_and_summary(base):
    import matplotlib

    matplotlib.use("Agg")
    fig = base.plot(label="Luenberger")
    assert len(fig.axes) == 2 and fig.axes[0].get_yscale() == "log"
    s = base.summary()
    assert s["n"] == 40 and s["failed"] == 0
    table = obsjax.montecarlo.comparison_table({"a": base, "b": base})
    assert table.count("\n") == 3 and "ISE" in table


# ---- bad input: one test per ValueError ---------------------------------------------------------------------


@pytest.mark.extended
def test_lockstep_agrees_with_independent_solves():
    """Lock-step batches take other steps than independent solves: the same study to the tolerance."""
    tight = dict(rtol=1e-10, atol=1e-12)
    ind = run(simulate_kwargs=tight)
    lock = run(lockstep=True, simulate_kwargs=tight)
    np.testing.assert_array_equal(lock.status, 0)
    np.testing.assert_allclose(lock.error_norm, ind.error_norm, atol=1e-8)


def test_lockstep_refuses_param_sampler():
    with pytest.raises(ValueError, match="lockstep=True"):
        run(lockstep=True, param_sampler=lambda k, p: p)


def test_bad_n():
    with pytest.raises(ValueError, match="`n`"):
        run(n=0)


def test_bad_chunk_size():
    with pytest.raises(ValueError, match="`chunk_size`"):
        run(chunk_size=0)


def test_missing_sampler():
    with pytest.raises(ValueError, match="`x0_sampler` is required"):
        run(x0_sampler=None)


def test_sampler_array_of_wrong_rank():
    with pytest.raises(ValueError, match="`xhat0_sampler` given as an array"):
        run(xhat0_sampler=np.zeros((2, 2)))


def test_bad_key():
    with pytest.raises(ValueError, match="`key`"):
        obsjax.monte_carlo(PLANT, OBS, 3, 4, x0_sampler=x0_normal, xhat0_sampler=xhat0_zero, ts=TS)


def test_bad_quantiles():
    with pytest.raises(ValueError, match="`quantiles`"):
        run(quantiles=(0.9, 0.1))


def test_bad_conv_tol():
    with pytest.raises(ValueError, match="`conv_tol`"):
        run(conv_tol=0.0)


def test_simulate_kwargs_throw_refused():
    with pytest.raises(ValueError, match="must not contain 'throw'"):
        run(simulate_kwargs={"throw": True})


def test_bad_plant():
    with pytest.raises(ValueError, match="`plant`"):
        run(plant="not a plant")


def test_bad_observer():
    with pytest.raises(ValueError, match="`observer`"):
        run(observer=PLANT)


def test_too_many_devices():
    with pytest.raises(ValueError, match="`devices`"):
        run(devices=len(jax.devices()) + 1)


def test_bad_max_chunks():
    with pytest.raises(ValueError, match="`max_chunks`"):
        run(max_chunks=-1)


def test_bad_param_sampler():
    with pytest.raises(ValueError, match="`param_sampler`"):
        run(param_sampler=3)


def _unregister_duration_listener(listener):
    # public in recent jax; jax 0.6.1 (the lower bound in pyproject.toml) has only the private form
    unregister = getattr(jax.monitoring, "unregister_event_duration_listener", None)
    if unregister is None:
        from jax._src import monitoring

        unregister = monitoring._unregister_event_duration_listener_by_callback
    unregister(listener)


@pytest.mark.extended
def test_max_segments_lets_studies_of_two_periods_share_one_program():
    """``simulate_kwargs["max_segments"]`` at least ceil(span/T) of either period: the second period's study
    traces and compiles nothing, and equals a study that holds exactly its own count of segments."""
    kw = dict(x0_sampler=x0_uniform, xhat0_sampler=np.zeros(1), ts=np.linspace(0.0, 2.0, 9), chunk_size=8,
              progress=False)
    obs_b = eqx.tree_at(lambda o: o.T, RESET_OBS, jnp.array(0.3))  # 7 segments on [0, 2]; RESET_OBS: 4
    shared = {"simulate_kwargs": {"max_segments": 9}}
    obsjax.monte_carlo(SCALAR_PLANT, RESET_OBS, jr.PRNGKey(6), 16, **kw, **shared)
    events = []

    def listener(event, duration, **_):
        if event.endswith(("jaxpr_trace_duration", "backend_compile_duration")):
            events.append(event)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        b_shared = obsjax.monte_carlo(SCALAR_PLANT, obs_b, jr.PRNGKey(6), 16, **kw, **shared)
    finally:
        _unregister_duration_listener(listener)
    assert events == []
    b_own = obsjax.monte_carlo(SCALAR_PLANT, obs_b, jr.PRNGKey(6), 16, **kw)
    np.testing.assert_array_equal(b_shared.status, b_own.status)
    np.testing.assert_allclose(b_shared.error_norm, b_own.error_norm, rtol=1e-12, atol=1e-14)
    with pytest.raises(ValueError, match=r"max_segments'\]` = 6 is below the 7 reset segments"):
        obsjax.monte_carlo(SCALAR_PLANT, obs_b, jr.PRNGKey(6), 16, **kw, simulate_kwargs={"max_segments": 6})
    for bad in (2.5, 0, True):
        with pytest.raises(ValueError, match="max_segments"):
            obsjax.monte_carlo(SCALAR_PLANT, obs_b, jr.PRNGKey(6), 16, **kw, simulate_kwargs={"max_segments": bad})


def test_bad_ts():
    with pytest.raises(ValueError, match="`ts`"):
        run(ts=np.array([1.0, 0.0]))


# ---- sharding over 4 host devices (subprocess, so the rest of the suite keeps one device) -------------------

_SHARD_SCRIPT = textwrap.dedent(
    """
    import os, sys
    sys.path.insert(0, {root!r})
    import jax, jax.numpy as jnp, jax.random as jr, numpy as np
    import obsjax
    from tests.test_montecarlo import PLANT, OBS, x0_normal, xhat0_zero, SCALAR_PLANT, RESET_OBS, x0_uniform, scale_a
    assert len(jax.devices()) == 4, jax.devices()
    ts = np.linspace(0.0, 3.0, 16)
    noise = obsjax.noise.BandLimitedNoise(0.05, dt=0.05)
    kw = dict(x0_sampler=x0_normal, xhat0_sampler=xhat0_zero, ts=ts, noise=noise, chunk_size=24, progress=False)
    one = obsjax.monte_carlo(PLANT, OBS, jr.PRNGKey(5), 50, devices=1, **kw)
    four = obsjax.monte_carlo(PLANT, OBS, jr.PRNGKey(5), 50, devices=4, **kw)
    assert np.array_equal(one.status, four.status)
    d1 = float(np.max(np.abs(one.error_norm - four.error_norm)))
    kw2 = dict(x0_sampler=x0_uniform, xhat0_sampler=np.zeros(1), ts=np.linspace(0, 2, 9), param_sampler=scale_a,
               chunk_size=8, progress=False)
    r1 = obsjax.monte_carlo(SCALAR_PLANT, RESET_OBS, jr.PRNGKey(6), 20, devices=1, **kw2)
    r4 = obsjax.monte_carlo(SCALAR_PLANT, RESET_OBS, jr.PRNGKey(6), 20, devices=4, **kw2)
    d2 = float(np.max(np.abs(r1.error_norm - r4.error_norm)))
    tight = dict(simulate_kwargs=dict(rtol=1e-10, atol=1e-12))
    one_t = obsjax.monte_carlo(PLANT, OBS, jr.PRNGKey(5), 50, devices=1, **kw, **tight)
    lock4 = obsjax.monte_carlo(PLANT, OBS, jr.PRNGKey(5), 50, devices=4, lockstep=True, **kw, **tight)
    d3 = float(np.max(np.abs(one_t.error_norm - lock4.error_norm)))
    print("MAXDIFF", d1, d2, one.n_failed, r4.n_failed, d3)
    """
)


@pytest.mark.extended
def test_sharded_equals_unsharded():
    env = dict(os.environ)
    env["XLA_FLAGS"] = (
        env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"
    ).strip()
    env["JAX_PLATFORMS"] = "cpu"
    out = subprocess.run(
        [sys.executable, "-c", _SHARD_SCRIPT.format(root=ROOT)],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    line = [ln for ln in out.stdout.splitlines() if ln.startswith("MAXDIFF")][0]
    d1, d2, f1, f4, d3 = line.split()[1:]
    assert float(d1) <= 1e-12 and float(d2) <= 1e-12
    # lock-step shards: the same study to the accuracy of either solve (the noise path's kinks every 0.05 s
    # are stepped over, not declared: at rtol 1e-10 each solve is within ~2.5e-7 of a rtol 1e-13 one)
    assert float(d3) <= 1e-6
    assert int(f1) == 0 and int(f4) == 0
    print(line)


@pytest.mark.extended
def test_band_limited_noise_is_simulates_realisation():
    # Trajectory i of the study sees the path simulate(noise=..., key=k_noise_i) draws (run outside jit).
    noise = obsjax.noise.BandLimitedNoise(0.2, dt=0.1)
    # (tight tolerances: the path has kinks every dt, where two solves' step sequences may part ways)
    tol = {"rtol": 1e-10, "atol": 1e-12}
    res = run(n=3, chunk_size=4, noise=noise, simulate_kwargs=tol)
    for i in range(3):
        kx, kh, kn, _ = jr.split(jr.fold_in(jr.PRNGKey(7), i), 4)
        traj = obsjax.simulate(
            PLANT, OBS, x0_normal(kx), xhat0_zero(kh), TS, noise=noise, key=kn, **tol
        )
        np.testing.assert_allclose(res.error_norm[i], traj.error_norm, rtol=1e-7, atol=1e-9)
    F = np.asarray(OBS.observer_matrix)  # the noise-free error differs: the noise is really there
    clean = [np.linalg.norm(scipy.linalg.expm(F * t) @ _x0_of(0)) for t in TS]
    assert np.max(np.abs(res.error_norm[0] - clean)) > 1e-3


# ---- noisy plants for tuning, and the CLI's reproduce dispatcher ---------------------------------------------


def test_noisy_batch_paths_are_the_split_keys_paths():
    from obsjax.montecarlo import noisy_batch, with_noise

    noise = obsjax.noise.BandLimitedNoise(0.3, dt=0.1)
    key = jr.PRNGKey(4)
    batch = noisy_batch(PLANT, noise, key, 3, 0.0, 2.0)
    assert batch.plant_arrays.A.shape == (3, 2, 2)
    for b, k in enumerate(jr.split(key, 3)):
        one = with_noise(PLANT, noise, k, 0.0, 2.0)
        np.testing.assert_array_equal(batch.path.values[b], one.path.values)
        x = jnp.array([0.3, -0.2])
        # y = C x + v(t), v the linear interpolation of the samples
        v = np.interp(
            0.55, 0.1 * np.arange(one.path.values.shape[0]), np.asarray(one.path.values[:, 0])
        )
        np.testing.assert_allclose(one.h(0.55, x, jnp.zeros(1)), [0.3 + v], rtol=1e-12)
        assert one.n == 2 and one.m == 1 and one.p == 1


def test_noisy_output_refuses_other_noise():
    from obsjax.montecarlo import with_noise

    with pytest.raises(ValueError, match="BandLimitedNoise"):
        with_noise(PLANT, obsjax.noise.WhiteNoise(0.1), jr.PRNGKey(0), 0.0, 1.0)


def test_reproduce_aliases_and_missing_modules(capsys, tmp_path):
    from obsjax import cli

    assert cli.resolve_document("chen-yen") == ("chen_yen",)
    assert cli.resolve_document("Hassan") == ("luenberger", "adaptive")
    assert cli.resolve_document("lovass-nagy") == ("lovass_nagy",)
    assert cli.resolve_document("huang-zhu") == ("huang_zhu",)
    assert cli.resolve_document("byrski-fuksa") == ("byrski_fuksa",)
    assert cli.resolve_document("Byrski_Fuksa") == ("byrski_fuksa",)
    assert cli.resolve_document("luenberger") == ("luenberger",)
    with pytest.raises(ValueError, match="unknown document"):
        cli.resolve_document("no-such-paper")
    assert "luenberger" in cli.available_reproductions()
    rc = cli.run_reproductions(["definitely_absent_module"], str(tmp_path))
    assert rc == 0 and "[skip] definitely_absent_module" in capsys.readouterr().out


def test_cli_reproduce_unknown_document_exits():
    from obsjax import cli

    with pytest.raises(SystemExit):
        cli.main(["reproduce", "no-such-paper"])


@pytest.mark.extended
def test_white_noise_is_simulates_realisation():
    # White measurement noise (an SDE, Euler–Maruyama): trajectory i sees simulate's path for its key.
    noise = obsjax.noise.WhiteNoise(0.1)
    res = run(n=2, chunk_size=2, noise=noise)
    for i in range(2):
        kx, kh, kn, _ = jr.split(jr.fold_in(jr.PRNGKey(7), i), 4)
        traj = obsjax.simulate(PLANT, OBS, x0_normal(kx), xhat0_zero(kh), TS, noise=noise, key=kn)
        np.testing.assert_allclose(res.error_norm[i], traj.error_norm, rtol=1e-9, atol=1e-12)


@pytest.mark.extended
def test_demo_smoke(tmp_path, capsys):
    # The `obsjax demo` pipeline at toy sizes: the paper's figures against SciPy, tuning, two studies, PNGs.
    import matplotlib

    matplotlib.use("Agg")
    from obsjax import cli

    out = cli.demo(str(tmp_path / "demo"), n=40, steps=2, batch=2)
    text = capsys.readouterr().out
    assert "t=10: 0.03347 [0.03347]" in text and "t=10: 0.003707 [0.003707]" in text
    assert all(os.path.getsize(p) > 10_000 for p in out["figures"]) and len(out["figures"]) == 3
    assert len(out["results"]) == 2 and all(
        r.complete and r.n == 40 for r in out["results"].values()
    )
    assert len(out["history"]["loss"]) == 2


# ---- several processes (jax.distributed on localhost, CPU collectives) ---------------------------------------


@pytest.mark.extended
def test_two_processes_equal_one_process():
    # benchmarks/multihost_local.py starts 2 processes that call jax.distributed.initialize and run the Chen &
    # Yen study over a mesh spanning both, then the same study in one ordinary process.
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    n, chunk = 48, 24
    out = subprocess.run(
        [sys.executable, os.path.join(ROOT, "benchmarks", "multihost_local.py"), "--n", str(n),
         "--chunk-size", str(chunk), "--t1", "2", "--no-write", "--no-small-chunk", "--repeat", "1",
         "--timeout", "200"],
        env=env, capture_output=True, text=True, timeout=300, cwd=ROOT, check=False,
    )  # fmt: skip
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-3000:])
    line = next(ln for ln in out.stdout.splitlines() if ln.startswith("RESULT "))
    r = json.loads(line[len("RESULT ") :])
    assert r["processes"] == 2 and r["global_devices"] == 2
    # every process returns the single-process result (the study, and the interrupted-then-resumed one)
    assert r["max_diff"] <= 1e-12 and r["max_diff_resumed"] <= 1e-12 and r["status_equal"]
    assert r["failed"] == 0
    # interrupted after one chunk, then resumed: only the missing chunk is computed, on both processes
    assert r["part_n_done"] == [chunk, chunk] and r["resumed_n_computed"] == [n - chunk, n - chunk]
    # only process 0 touched its checkpoint directory; process 1 got the finished chunk from it
    assert r["ckpt_written_by"] == [0]
    assert r["ckpt_files_p0"] == ["chunk_000000.npz", "chunk_000001.npz", "meta.json"]
    # a mesh that leaves a process out, or process 0's checkpoint of another study, is refused by every
    # process (no hang)
    assert r["partial_mesh_refused"] and r["other_study_refused"]


@pytest.mark.extended
def test_study_kernels_carry_no_host_callbacks():
    """Runtime checks inside a study become NaN (status 2), not host callbacks: a multi-device CPU program
    with callbacks runs its shards one after another (benchmarks/results/d_sharding.md)."""
    import equinox as eqx

    from obsjax._checks import runtime_checks_as_nan

    plant = obsjax.chen_yen_example()
    obs = obsjax.LeastSquaresReset(plant, 20.0, 0.1, 0.25)
    # traced save times: obsjax checks them (increasing, finite) with eqx.error_if at run time
    ts = jnp.linspace(0.0, 1.0, 5)

    def f(x0, ts):
        return obsjax.simulate(plant, obs, x0, jnp.zeros(2), ts, throw=False, max_segments=4).error_norm

    plain = str(jax.make_jaxpr(f)(jnp.ones(2), ts))
    assert "callback" in plain
    with runtime_checks_as_nan():
        inside = str(jax.make_jaxpr(lambda x, t: f(x, t))(jnp.ones(2), ts))  # a new function: no jit-cached trace
        batch = str(
            jax.make_jaxpr(
                lambda x, t: obsjax.simulate_batch(plant, obs, x, x, t, throw=False, max_segments=4).error
            )(jnp.ones((3, 2)), ts)
        )
        fired = jax.jit(lambda x: eqx.error_if(x, x > 0, "fires"))(jnp.ones(()))
    assert "callback" not in inside
    assert "callback" not in batch
    # no trace made inside a study is reused outside it
    assert "callback" in str(jax.make_jaxpr(lambda x, t: f(x, t))(jnp.ones(2), ts))
    assert np.isnan(fired)
    with pytest.raises(Exception, match="fires"):  # outside a study, checks raise again
        jax.block_until_ready(jax.jit(lambda x: eqx.error_if(x, x > 0, "fires"))(jnp.ones(())))


def test_nan_checks_are_counted_across_threads():
    """equinox's error mode is one per process: when two threads are inside ``runtime_checks_as_nan`` (a
    study running beside a tuning), the first to leave does not switch the checks back under the other,
    and the last to leave restores raising checks (the state before it was taken is not lost)."""
    import threading

    import equinox as eqx
    import equinox._errors as E

    from obsjax._checks import runtime_checks_as_nan

    def check(v):  # a new function each time: no jit-cached trace
        return jax.jit(lambda x: eqx.error_if(x, x > 0, "fires"))(jnp.full((), v))

    mode = E.EQX_ON_ERROR
    entered, leave, left = threading.Event(), threading.Event(), threading.Event()

    def other():
        with runtime_checks_as_nan():
            entered.set()
            leave.wait(60)
        left.set()

    t = threading.Thread(target=other)
    t.start()
    assert entered.wait(60)
    with runtime_checks_as_nan():
        leave.set()
        assert left.wait(60)  # the other thread has left; this one is still inside
        assert E.EQX_ON_ERROR == "nan" and np.isnan(check(1.0))
    t.join()
    assert E.EQX_ON_ERROR == mode
    with pytest.raises(Exception, match="fires"):
        jax.block_until_ready(check(2.0))


@pytest.mark.extended
def test_an_input_signal_with_arrays_is_a_simulate_kwarg(tmp_path):
    """u = multisine(...) (an eqx.Module holding arrays) was refused as unhashable, so the input signal of
    the README could not drive a study.  Its arrays now travel as kernel arguments: each trajectory equals
    simulate's with the same draw and input, and a changed amplitude is another study for the checkpoint."""
    u = obsjax.signals.multisine([1.0], [1.3])
    ts = jnp.linspace(0.0, 2.0, 5)
    key = jr.key(0)

    def run(u, ckpt=None):
        return obsjax.monte_carlo(PLANT, OBS, key, 4, x0_sampler=lambda k: jr.normal(k, (2,)), xhat0_sampler=jnp.zeros(2),
                                  ts=ts, chunk_size=4, progress=False, checkpoint=ckpt, simulate_kwargs=dict(u=u))
    res = run(u, tmp_path / "ck")
    for i in range(4):
        x0 = jr.normal(jr.split(jr.fold_in(key, i), 4)[0], (2,))
        one = obsjax.simulate(PLANT, OBS, x0, jnp.zeros(2), ts, u=u)
        np.testing.assert_allclose(res.error_norm[i], np.asarray(one.error_norm), rtol=1e-9, atol=1e-12)
    louder = obsjax.signals.multisine([3.0], [1.3])
    with pytest.raises(ValueError, match="holds a different study"):
        run(louder, tmp_path / "ck")
    assert run(u, tmp_path / "ck").n_computed == 0  # the same study: resumed


# ---- review findings: the fingerprint of classes, the sampler form, complex samplers -------------------
#
# Module-level classes, read as globals by the samplers below (the fingerprint follows a function's
# globals), each changed by a test through monkeypatch and restored after it.


class _FpScale:
    s = 1.0


class _FpStatic:
    @staticmethod
    def g(x):
        return 1.0 * x


class _FpUnit:
    @staticmethod
    def g(x):
        return x


class _FpTriple:
    @staticmethod
    def g(x):
        return 3.0 * x


_FpRole = _FpUnit  # a global that is rebound to another class


class _FpBase:
    s = 1.0


class _FpDerived(_FpBase):
    def __call__(self, k):
        return self.s * jr.normal(k, (2,))


def _fp_reads_class_attribute(k):
    return _FpScale.s * jr.normal(k, (2,))


def _fp_reads_staticmethod(k):
    return _FpStatic.g(jr.normal(k, (2,)))


def _fp_reads_rebound_global(k):
    return _FpRole.g(jr.normal(k, (2,)))


def _fp(obj):
    from obsjax.montecarlo._fingerprint import fingerprint

    digest, opaque = fingerprint({"s": obj})
    assert not opaque
    return digest


_FP_CASES = {
    # a class attribute read by a sampler (the class a global of the sampler)
    "class attribute": (_fp_reads_class_attribute, lambda mp: mp.setattr(_FpScale, "s", 2.0)),
    # a staticmethod of a class read by a sampler
    "class staticmethod": (
        _fp_reads_staticmethod,
        lambda mp: mp.setattr(_FpStatic, "g", staticmethod(lambda x: 2.0 * x)),
    ),
    # a global rebound to another class (same name, other methods)
    "global rebound to another class": (
        _fp_reads_rebound_global,
        lambda mp: mp.setitem(globals(), "_FpRole", _FpTriple),
    ),
    # an attribute of a base class, read through an instance of a subclass
    "base class attribute via instance": (_FpDerived(), lambda mp: mp.setattr(_FpBase, "s", 2.0)),
}


@pytest.mark.parametrize("case", sorted(_FP_CASES))
def test_fingerprint_hashes_classes_reached_through_globals_and_bases(case, monkeypatch):
    """Review finding 1: a class reached through visit() (a global, a closure cell, a base class) was
    memoised before _class() looked at it, so it was hashed as a bare reference to itself: changing its
    attributes, or rebinding the global to another class, left the digest unchanged (checkpoints of
    another study were resumed, compiled kernels served stale)."""
    obj, change = _FP_CASES[case]
    before = _fp(obj)
    assert _fp(obj) == before  # deterministic
    change(monkeypatch)
    assert _fp(obj) != before


def test_fingerprint_hashes_classes_read_through_a_closure():
    def make(cls):
        return lambda k: cls.s * jr.normal(k, (2,))

    class K:
        s = 1.0

    class L:
        s = 1.0

    f = make(K)
    before = _fp(f)
    K.s = 2.0
    assert _fp(f) != before
    K.s = 1.0
    assert _fp(f) == before
    assert _fp(make(L)) != before  # another class with the same content but another name


class _FpSelf:
    scale = 1.0

    def draw(self, k):
        return _FpSelf.scale * jr.normal(k, (2,))  # the class refers to itself through a global

    @classmethod
    def make(cls):
        return cls()


class _FpPing:
    s = 1.0

    def other(self):
        return _FpPong  # mutually recursive classes


class _FpPong:
    s = 1.0

    def other(self):
        return _FpPing


def _fp_reads_ping(k):
    return _FpPing.s * jr.normal(k, (2,))


def test_fingerprint_of_self_referencing_classes_terminates(monkeypatch):
    """Classes that refer to themselves or to each other are walked once (a later visit is a
    reference), and their attributes still enter the digest."""
    a = _fp(_FpSelf().draw)
    b = _fp(_fp_reads_ping)
    assert _fp(_FpSelf().draw) == a and _fp(_fp_reads_ping) == b
    monkeypatch.setattr(_FpSelf, "scale", 2.0)
    assert _fp(_FpSelf().draw) != a
    monkeypatch.setattr(_FpPong, "s", 2.0)  # reached only through _FpPing.other's global
    assert _fp(_fp_reads_ping) != b


def test_fingerprint_of_classes_with_slots_named_tuples_and_cached_properties_is_complete():
    """Now that a class reached through a global is hashed by content, its layout descriptors (a slot's,
    a named tuple field's accessor) and a cached_property's lock must not make it opaque (a checkpoint
    would be refused without a study_id)."""
    import functools
    from typing import NamedTuple

    class Slotted:
        __slots__ = ("a",)

        def __init__(self):
            self.a = 1.0

    class Pair(NamedTuple):
        x: float
        y: float

    class Lazy:
        @functools.cached_property
        def c(self):
            return 2.0

    for cls in (Slotted, Pair, Lazy, Slotted()):
        _fp(cls)  # asserts that nothing is opaque


class _McScale:
    s = 1.0


def _x0_class_scaled(key):
    return _McScale.s * jr.normal(key, (1,))


def test_changed_class_attribute_is_neither_a_stale_kernel_nor_a_resumed_checkpoint(tmp_path, monkeypatch):
    """End to end (review finding 1): after ``_McScale.s = 100`` a new study must draw x0 at the new
    scale (before the fix the kernel compiled at scale 1 was served: ‖x̃(0)‖ 100× too small), and a
    checkpoint written at scale 1 must be refused, not resumed."""
    kw = dict(x0_sampler=_x0_class_scaled, xhat0_sampler=jnp.zeros(1), ts=np.linspace(0.0, 1.0, 3),
              chunk_size=4, progress=False, simulate_kwargs=dict(adaptive=False, dt0=0.25))  # fmt: skip
    key = jr.PRNGKey(3)
    first = obsjax.monte_carlo(SCALAR_MODEL, SCALAR_OBS, key, 4, checkpoint=tmp_path / "ck", **kw)
    monkeypatch.setattr(_McScale, "s", 100.0)
    again = obsjax.monte_carlo(SCALAR_MODEL, SCALAR_OBS, key, 4, **kw)
    np.testing.assert_allclose(again.error_norm[:, 0], 100.0 * first.error_norm[:, 0], rtol=1e-12)
    with pytest.raises(ValueError, match="holds a different study"):
        obsjax.monte_carlo(SCALAR_MODEL, SCALAR_OBS, key, 4, checkpoint=tmp_path / "ck", **kw)


def test_sampler_form_counts_required_positional_parameters_only():
    """Review finding 2: ``def s(k, sigma=0.5)`` was taken as the (key, x0) form and called with x0 as
    sigma; a parameter with a default is the user's setting, not the slot for x0."""
    from obsjax.montecarlo._montecarlo import _n_positional

    def spread(k, sigma=0.5):
        return sigma * jr.normal(k, (1,))

    assert _n_positional(spread) == 1
    assert _n_positional(lambda k, x0: x0) == 2
    assert _n_positional(lambda k, x0, scale=2.0: x0) == 2
    assert _n_positional(lambda *a: a[0]) == 99
    key = jr.PRNGKey(5)
    x0 = jnp.array([10.0])
    res = obsjax.monte_carlo(SCALAR_MODEL, SCALAR_OBS, key, 3, x0_sampler=x0, xhat0_sampler=spread,
                             ts=np.linspace(0.0, 1.0, 3), chunk_size=4, progress=False,
                             simulate_kwargs=dict(adaptive=False, dt0=0.25))  # fmt: skip
    for i in range(3):
        kh = jr.split(jr.fold_in(key, i), 4)[1]
        expected = float(jnp.linalg.norm(x0 - 0.5 * jr.normal(kh, (1,))))
        assert res.error_norm[i, 0] == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize(
    "overrides,match",
    [
        (dict(x0_sampler=lambda k: jr.normal(k, (2,)) * (1 + 1j)), r"`x0_sampler` must return a real .*complex128"),
        (dict(xhat0_sampler=lambda k: jnp.ones(2) * 1j), r"`xhat0_sampler` must return a real .*complex128"),
        (dict(xhat0_sampler=lambda k, x0: x0 + 1j), r"`xhat0_sampler` must return a real .*complex128"),
        (dict(xhat0_sampler=np.array([0.0, 5j])), r"`xhat0_sampler` given as an array must be real.*complex128"),
        (dict(x0_sampler=np.array([1.0 + 0j, 0.0])), r"`x0_sampler` given as an array must be real.*complex128"),
    ],
)
def test_complex_sampler_output_is_refused(overrides, match):
    """Review finding 3: complex sampler output was cast to its real part (x̂0 = (0, 5j) gave
    ‖x̃(0)‖ = 1 instead of a refusal, as simulate refuses a complex x̂0)."""
    with pytest.raises(ValueError, match=match):
        run(n=2, chunk_size=2, ts=TS[:2], **overrides)
