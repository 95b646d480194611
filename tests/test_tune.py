"""Gradient tuning: finite-difference gradients of every tunable leaf, the noise trade-off, robustness."""

import functools
import itertools
import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optax
import pytest

import obsjax
from obsjax.montecarlo import summarise

PLANT = obsjax.LTI([[-2.0, 1.0], [0.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]])
TS = jnp.linspace(0.0, 5.0, 101)
X0S = jr.normal(jr.PRNGKey(0), (8, 2)) * 2.0
XH0S = jnp.zeros((8, 2))
NOISE = obsjax.noise.BandLimitedNoise(0.05, dt=0.02)
U = obsjax.signals.multisine([1.0], [1.3])


def _fd(f, x, h=1e-6):
    x = np.asarray(x, dtype=float)
    g = np.zeros_like(x)
    for i in range(x.size):
        up, dn = x.copy(), x.copy()
        up.flat[i] += h
        dn.flat[i] -= h
        g.flat[i] = (f(jnp.asarray(up)) - f(jnp.asarray(dn))) / (2 * h)
    return g


def _batch_loss(obs_of, loss=obsjax.losses.ise):
    def J(p):
        obs = obs_of(p)

        def one(x0, xh0):
            return loss(obsjax.simulate(PLANT, obs, x0, xh0, TS, u=U, rtol=1e-10, atol=1e-12))

        return jnp.mean(jax.vmap(one)(X0S, XH0S))

    return jax.jit(J)


@pytest.mark.parametrize(
    "name,obs_of,p0",
    [
        ("Luenberger.poles", lambda p: obsjax.Luenberger.from_poles(PLANT, p), [-2.0, -3.5]),
        ("Luenberger.L", lambda p: obsjax.Luenberger(PLANT, L=p), [[3.0], [4.0]]),
        ("ReducedOrder.poles", lambda p: obsjax.ReducedOrder.from_poles(PLANT, p), [-3.0]),
        ("ReducedOrder.G", lambda p: obsjax.ReducedOrder(PLANT, G=p), [[2.0]]),
    ],
)
@pytest.mark.extended
def test_gradient_of_every_tunable_leaf_matches_fd(name, obs_of, p0):
    J = _batch_loss(obs_of)
    g = np.asarray(jax.grad(J)(jnp.asarray(p0)))
    np.testing.assert_allclose(g, _fd(J, p0), rtol=2e-4, atol=1e-7)


@pytest.mark.parametrize("loss", [obsjax.losses.itae, obsjax.losses.peak, obsjax.losses.terminal])
@pytest.mark.extended
def test_gradient_of_each_loss_matches_fd(loss):
    J = _batch_loss(lambda p: obsjax.Luenberger.from_poles(PLANT, p), loss)
    p0 = [-2.0, -3.5]
    g = np.asarray(jax.grad(J)(jnp.asarray(p0)))
    np.testing.assert_allclose(g, _fd(J, p0), rtol=2e-4, atol=1e-7)


@pytest.mark.extended
def test_tune_finds_interior_optimum_of_the_noise_tradeoff():
    """Example (2.8) with measurement noise: from slow and from fast poles, tune lands in between."""
    obs_slow = obsjax.Luenberger.from_poles(PLANT, [-0.5, -0.6])
    obs_fast = obsjax.Luenberger.from_poles(PLANT, [-16.0, -19.2])
    kw = dict(where=lambda o: o.poles, loss=obsjax.losses.ise, x0s=X0S, xhat0s=XH0S, ts=TS,
              noise=NOISE, key=jr.PRNGKey(1), steps=45, optimizer=optax.adam(0.1), progress=False)
    r_slow = obsjax.tune(obs_slow, PLANT, **kw)
    r_fast = obsjax.tune(obs_fast, PLANT, **kw)
    s_slow = -np.asarray(r_slow.observer.poles)
    s_fast = -np.asarray(r_fast.observer.poles)
    for r in (r_slow, r_fast):
        h = r.history["loss"]
        assert h[r.history["best_step"]] < 0.5 * h[0]
        assert r.history["skipped"] == 0
    # interior: both runs end strictly inside (0.5, 16), near each other
    assert np.all(s_slow > 1.0) and np.all(s_slow < 10.0)
    assert np.all(s_fast > 1.0) and np.all(s_fast < 10.0)
    assert abs(np.mean(s_slow) - np.mean(s_fast)) < 0.5 * np.mean(s_fast)
    assert np.all(np.asarray(r_slow.observer.poles) < 0)  # sign kept by the reparametrisation


@pytest.mark.extended
def test_tune_skips_nonfinite_steps_and_returns_best():
    obs = obsjax.Luenberger.from_poles(PLANT, [-2.0, -2.5])

    def loss(traj):  # non-finite once the estimate gets good: a step that must be skipped
        v = obsjax.losses.ise(traj)
        return jnp.where(v < 0.8 * 1.1, jnp.nan, v)

    with pytest.warns(obsjax.TuneWarning, match="rejected .the loss is not finite"):
        r = obsjax.tune(obs, PLANT, where=lambda o: o.poles, loss=loss, x0s=X0S[:2],
                        xhat0s=XH0S[:2], ts=TS, steps=12, optimizer=optax.sgd(0.5), progress=False)
    h = r.history
    assert h["skipped"] > 0 and h["skipped"] == int(np.sum(~h["accepted"]))
    assert np.isfinite(h["loss"][h["best_step"]])
    assert h["loss"][h["best_step"]] == np.nanmin(h["loss"])
    assert np.all(np.isfinite(np.asarray(r.observer.poles)))
    # a rejected point is never evaluated again: every evaluated point is new
    assert len({tuple(p) for p in h["params"][0]}) == len(h["params"][0])


@pytest.mark.extended
def test_tune_over_sampled_plants_with_risk_measures():
    keys = jr.split(jr.PRNGKey(3), 6)
    A = jnp.stack([jnp.array([[-2.0, 1.0], [0.0, -1.0]]) + 0.3 * jr.normal(k, (2, 2)) for k in keys])
    plants = obsjax.LTI(jnp.asarray(A[0]), [[0.0], [1.0]], [[1.0, 0.0]])
    plants = eqx.tree_at(lambda p: (p.A, p.B, p.C, p.D), plants,
                         (A, jnp.broadcast_to(plants.B, (6, 2, 1)), jnp.broadcast_to(plants.C, (6, 1, 2)),
                          jnp.broadcast_to(plants.D, (6, 1, 1))))
    obs = obsjax.Luenberger.from_poles(PLANT, [-1.0, -1.2])
    res = {}
    where = lambda o: o.poles  # noqa: E731  (one object: the three calls share one compilation)
    for risk in ("mean", ("cvar", 0.5), "worst"):
        r = obsjax.tune(obs, plants, where=where, loss=obsjax.losses.ise, x0s=X0S[:6],
                        xhat0s=XH0S[:6], ts=TS, plant_batched=True, risk=risk, steps=5,
                        optimizer=optax.adam(0.1), progress=False)
        res[risk if isinstance(risk, str) else "cvar"] = r.history["loss"][0]
        assert r.history["loss"][r.history["best_step"]] < r.history["loss"][0]
    assert res["mean"] <= res["cvar"] <= res["worst"]


def test_risk_measure_values():
    x = jnp.arange(10.0)
    assert float(obsjax.risk_measure(x, "mean")) == 4.5
    assert float(obsjax.risk_measure(x, "worst")) == 9.0
    assert float(obsjax.risk_measure(x, ("cvar", 0.8))) == 8.5
    with pytest.raises(ValueError, match="CVaR level"):
        obsjax.risk_measure(x, ("cvar", 1.5))


@pytest.mark.parametrize("alpha, n, k", [(0.95, 20, 1), (0.95, 100, 5), (0.7, 10, 3), (0.95, 2000, 100), (0.95, 19, 1)])
def test_cvar_averages_the_worst_ceil_of_one_minus_alpha_n(alpha, n, k):
    """(1 − 0.95)·20 = 1.0000000000000009 in floating point: the ceiling made it the worst 2 of 20 (19.5
    instead of 20.0 on 1..20), in risk_measure, tune's weights and monte_carlo's ise_cvar95 alike."""
    x = jnp.arange(1.0, n + 1.0)
    expected = float(np.mean(np.arange(n - k + 1.0, n + 1.0)))
    assert float(obsjax.risk_measure(x, ("cvar", alpha))) == pytest.approx(expected, rel=1e-14)
    w = obsjax.risk_weights(("cvar", alpha), n)
    assert np.count_nonzero(w) == k and np.sum(w * np.asarray(x)) == pytest.approx(expected, rel=1e-14)
    rows = np.tile(np.sqrt(np.asarray(x))[:, None], (1, 3))  # ‖x̃‖² = i on the grid: ISE = 2 i over [0, 2]
    s = summarise(np.array([0.0, 1.0, 2.0]), rows, np.zeros(n, int)).summary(cvar_alpha=alpha)
    assert s[f"ise_cvar{int(round(alpha * 100))}"] == pytest.approx(2 * expected, rel=1e-12)


def test_risk_measure_and_weights_refuse_what_is_not_a_batch_of_real_losses():
    """A (4, 2) array was averaged over both axes (2.0, a number mixing scenarios and columns), complex losses
    and an empty batch (a silent NaN mean) were accepted, a −inf loss gave a finite CVaR where tune's weights
    give NaN, and a batch size of 2.7 was truncated to 2."""
    with pytest.raises(ValueError, match=r"non-empty 1-D array .* got shape \(4, 2\)"):
        obsjax.risk_measure(jnp.zeros((4, 2)), ("cvar", 0.5))
    with pytest.raises(ValueError, match=r"got shape \(0,\)"):
        obsjax.risk_measure(jnp.zeros(0), "mean")
    with pytest.raises(ValueError, match="real numbers, got dtype complex"):
        obsjax.risk_measure(jnp.array([1 + 1j, 2.0]), "mean")
    with pytest.raises(ValueError, match="got booleans"):
        obsjax.risk_measure(np.array([True, False]), "mean")
    for risk in ("mean", "worst", ("cvar", 0.5)):
        for bad in (-np.inf, np.inf, np.nan):
            x = jnp.array([bad, 1.0, 2.0])
            assert np.isnan(float(obsjax.risk_measure(x, risk))), (risk, bad)
            assert not np.isfinite(np.sum(obsjax.risk_weights(risk, 3) * np.sort(np.asarray(x))))
    assert float(jax.jit(lambda v: obsjax.risk_measure(v, ("cvar", 0.5)))(jnp.arange(4.0))) == 2.5
    for batch in (0, -3, True):
        with pytest.raises(ValueError, match="`batch` must be a positive integer"):
            obsjax.risk_weights("mean", batch)
    with pytest.raises(Exception, match="batch"):  # refused by name (or by the test run's type check)
        obsjax.risk_weights("mean", 2.7)
    np.testing.assert_array_equal(obsjax.risk_weights("mean", np.int64(4)), np.full(4, 0.25))


def test_summary_refuses_a_cvar_level_outside_zero_one_and_names_each_level_apart():
    """summary(1.5) returned the maximum, summary(−0.5) the mean, and 0.995 was reported as ise_cvar100, the
    key of α = 1."""
    rows = np.tile(np.sqrt(np.arange(1.0, 201.0))[:, None], (1, 3))
    res = summarise(np.array([0.0, 1.0, 2.0]), rows, np.zeros(200, int))
    for bad in (1.0, 1.5, -0.5, float("nan")):
        with pytest.raises(ValueError, match="CVaR level"):
            res.summary(bad)
    s = res.summary(0.995)
    assert "ise_cvar99.5" in s and s["ise_cvar99.5"] == pytest.approx(2 * 200.0, rel=1e-12)  # the worst 1
    assert res.summary(0.9)["ise_cvar90"] == pytest.approx(2 * np.mean(np.arange(181.0, 201.0)), rel=1e-12)


def test_tune_bad_inputs():
    obs = obsjax.Luenberger(PLANT, L=[[0.0], [4.0]])
    with pytest.raises(ValueError, match="zero entries"):
        obsjax.tune(obs, PLANT, where=lambda o: o.L, loss=obsjax.losses.ise, x0s=X0S, xhat0s=XH0S, ts=TS,
                    steps=1, progress=False)
    with pytest.raises(ValueError, match="same batch"):
        obsjax.tune(obs, PLANT, where=lambda o: o.L, loss=obsjax.losses.ise, x0s=X0S, xhat0s=XH0S[:3],
                    ts=TS, steps=1, progress=False, positive=False)


def test_risk_weights_reproduce_risk_measure():
    """tune applies the risk measure as weights on the sorted losses; they must equal risk_measure
    (top_k for CVaR), including ties and an unsorted batch."""
    x = jr.normal(jr.PRNGKey(5), (11,)).at[3].set(2.5).at[7].set(2.5)
    for risk in ("mean", "worst", ("cvar", 0.5), ("cvar", 0.9), ("cvar", 0.0)):
        w = obsjax.risk_weights(risk, x.shape[0])
        assert np.isclose(w.sum(), 1.0)
        np.testing.assert_allclose(np.sum(w * np.sort(np.asarray(x))), float(obsjax.risk_measure(x, risk)),
                                   rtol=1e-14)
    with pytest.raises(ValueError, match="CVaR level"):
        obsjax.risk_weights(("cvar", 1.0), 4)
    with pytest.raises(ValueError, match="`risk` must be"):
        obsjax.tune(obsjax.Luenberger.from_poles(PLANT, [-1.0, -2.0]), PLANT, where=lambda o: o.poles,
                    loss=obsjax.losses.ise, x0s=X0S, xhat0s=XH0S, ts=TS, steps=1, progress=False, risk="median")


@pytest.mark.extended
def test_tune_reuses_its_compilation_across_risks_and_initial_gains():
    # The count is kept in an itertools.count: the kernel is keyed on the content of the loss with what it
    # closes over, and a list that grew between calls would itself be a change of content (traced again,
    # as a changed global is); a counter object has no content the key reads.
    traces = itertools.count()

    def loss(traj):  # runs once per trace
        next(traces)
        return obsjax.losses.ise(traj)

    where = lambda o: o.poles  # noqa: E731
    ts = jnp.linspace(0.0, 1.0, 11)
    for p, risk in [([-1.0, -2.0], "mean"), ([-3.0, -4.0], ("cvar", 0.5)), ([-2.0, -5.0], "worst")]:
        r = obsjax.tune(obsjax.Luenberger.from_poles(PLANT, p), PLANT, where=where, loss=loss, x0s=X0S[:4],
                        xhat0s=XH0S[:4], ts=ts, steps=2, optimizer=optax.adam(0.1), risk=risk, progress=False)
        assert r.history["skipped"] == 0
    assert next(traces) == 1


# -- robust tuning of the high-gain factor ε of the trajectory linearization observer (Huang & Zhu) ---------
#
# Scenario set: Van der Pol plants ẋ2 = μ(1 − x1²)x2 − x1 + d sin 2t with sampled μ ∈ U(0.7, 1.3) and an
# unmodelled disturbance d ∈ U(0, 2) (the observer's model has μ = 1, d = 0), x(0) near the limit cycle,
# x̂(0) = x(0) + 0.5 N(0, I), band-limited noise σ = 0.1 on y = x1.  Small ε: peaking and noise gain
# ∝ 1/ε^k; large ε: slow convergence and a model-error bias ∝ ε: the ISE has an interior minimiser.


class _VdP(eqx.Module):
    mu: jax.Array
    d: jax.Array

    def __call__(self, t, x, u):
        return jnp.array([x[1], self.mu * (1 - x[0] ** 2) * x[1] - x[0] + self.d * jnp.sin(2 * t)])


EPS_S = 8
EPS_TS = jnp.linspace(0.0, 6.0, 601)
EPS_KW = dict(solver=diffrax.Heun(), dt0=0.01, adaptive=False)  # fixed steps: a smooth loss in ε
EPS_NOISE = obsjax.noise.BandLimitedNoise(0.1, dt=0.02)
EPS_KEY = jr.PRNGKey(4)
WHERE_EPS = lambda o: o.eps  # noqa: E731  (one object: tune's compilation is reused across calls)


@functools.cache
def _eps_problem():
    h = lambda t, x, u: x[:1]  # noqa: E731
    model = obsjax.Nonlinear(_VdP(jnp.array(1.0), jnp.array(0.0)), h, 2, 1)
    k1, k2, k3, k4 = jr.split(jr.PRNGKey(0), 4)
    mus = jr.uniform(k1, (EPS_S,), minval=0.7, maxval=1.3)
    ds = jr.uniform(k2, (EPS_S,), minval=0.0, maxval=2.0)
    plants = eqx.tree_at(lambda p: (p.f_fn.mu, p.f_fn.d), model, (mus, ds))
    x0s = jnp.array([2.0, 0.0]) + 0.3 * jr.normal(k3, (EPS_S, 2))
    xh0s = x0s + 0.5 * jr.normal(k4, (EPS_S, 2))
    # gain designed along the equilibrium ξ̄ = 0 (the paper's K_o(0, μ̄)): a constant high gain
    obs = obsjax.TrajectoryLinearization(model, [-1.0, -2.0], 2.0, 0.2,
                                         nominal=lambda t: (jnp.zeros(2), jnp.zeros(0)))
    keys = jr.split(EPS_KEY, EPS_S)  # the keys tune draws its noise paths from

    @jax.jit
    def losses(eps):
        """Per-scenario ISE by plain simulate (not tune's code path)."""
        o = eqx.tree_at(WHERE_EPS, obs, eps)

        def one(pl, x0, xh0, k):
            tr = obsjax.simulate(pl, o, x0, xh0, EPS_TS, noise=EPS_NOISE, key=k, **EPS_KW)
            return obsjax.losses.ise(tr)

        return eqx.filter_vmap(one, in_axes=(eqx.if_array(0), 0, 0, 0))(plants, x0s, xh0s, keys)

    def R(eps, risk):
        return float(obsjax.risk_measure(losses(jnp.asarray(float(eps))), risk))

    return obs, plants, x0s, xh0s, R


def _tune_eps(eps0, risk, optimizer, steps):
    obs, plants, x0s, xh0s, _ = _eps_problem()
    return obsjax.tune(eqx.tree_at(WHERE_EPS, obs, jnp.asarray(eps0)), plants, where=WHERE_EPS,
                       loss=obsjax.losses.ise, x0s=x0s, xhat0s=xh0s, ts=EPS_TS, noise=EPS_NOISE, key=EPS_KEY,
                       plant_batched=True, risk=risk, optimizer=optimizer, steps=steps,
                       simulate_kwargs=EPS_KW, progress=False)


@pytest.mark.parametrize("risk", ["mean", ("cvar", 0.75), "worst"])
@pytest.mark.extended
def test_tune_gradient_wrt_eps_over_a_plant_batch_matches_fd(risk):
    """One sgd step of tune reveals its gradient: θ1 = θ0 − lr·dJ/dθ with ε = exp(θ), so
    dJ/dε = (log ε0 − log ε1) / (lr·ε0); against central differences of the risk of plain simulations."""
    *_, R = _eps_problem()
    eps0, lr, h = 0.3, 1e-3, 1e-5
    r = _tune_eps(eps0, risk, optax.sgd(lr), 2)
    eps1 = float(r.history["params"][0][1])
    g_tune = (np.log(eps0) - np.log(eps1)) / (lr * eps0)
    fd = (R(eps0 + h, risk) - R(eps0 - h, risk)) / (2 * h)
    assert r.history["loss"][0] == pytest.approx(R(eps0, risk), rel=1e-10)
    assert abs(fd) > 0.1
    np.testing.assert_allclose(g_tune, fd, rtol=1e-5)


@pytest.mark.extended
def test_tune_eps_robustly_matches_a_grid_search():
    """Mean and worst-case ISE over the scenario set, tuned from ε = 0.2 by gradient descent, against a grid
    search of the same risk (plain simulate): interior minimisers, bracketed by the grid, and different."""
    *_, R = _eps_problem()
    grid = np.geomspace(0.1, 1.5, 13)
    tuned = {}
    for risk in ("mean", "worst"):
        vals = np.array([R(e, risk) for e in grid])
        k = int(np.argmin(vals))
        assert 0 < k < len(grid) - 1, vals  # interior: small ε amplifies noise, large ε is slow/biased
        r = _tune_eps(0.2, risk, optax.adam(0.1), 18)
        eps_star = float(r.observer.eps)
        J_star = R(eps_star, risk)
        assert J_star == pytest.approx(r.history["loss"][r.history["best_step"]], rel=1e-10)
        assert J_star < 0.7 * r.history["loss"][0]  # from ε = 0.2
        assert grid[k - 1] < eps_star < grid[k + 1], (eps_star, grid[k])
        assert J_star <= vals.min() * 1.002
        assert J_star <= min(vals[k - 1], vals[k + 1])
        tuned[risk] = (eps_star, grid[k])
    # risk aversion moves the optimum (here to a gentler gain: the worst scenarios peak hardest)
    assert tuned["worst"][1] > tuned["mean"][1]
    assert tuned["worst"][0] > 1.1 * tuned["mean"][0]


# -- tune's guarantees: validated arguments, backtracking across validity boundaries, a stopping rul

from obsjax._checks import concrete_value  # noqa: E402

SCALAR = obsjax.LTI([[-1.0]], None, [[1.0]])
TS1 = jnp.linspace(0.0, 1.0, 11)
X0_1, XH0_1 = jnp.ones((1, 1)), jnp.zeros((1, 1))


class _Gain(obsjax.AbstractObserver):
    """x̂' = −x̂ + k (y − x̂) for the plant ẋ = −x, y = x: the error obeys e' = −(1 + k) e, so
    ‖x̃(t)‖ = e^{−(1 + k) t} from x0 = 1, x̂0 = 0.  Valid (a decaying error) for k > −1 only."""

    k: jax.Array

    def init(self, t0, xhat0, y0):
        return jnp.asarray(xhat0)

    def vector_field(self, t, z, y, u):
        return -z + self.k * (y - z)

    def estimate(self, t, z, y):
        return z

    def check(self):
        v = concrete_value(self.k)
        if v is not None and not float(v) > -1.0:
            raise ValueError(f"`k` must be > -1 (a decaying error), got {float(v)}.")
        return self


WHERE_K = lambda o: o.k  # noqa: E731


def _terminal_target(target):
    def loss(traj):
        return (jnp.sqrt(jnp.sum(traj.error[-1] ** 2)) - target) ** 2

    return loss


LOSS_09 = _terminal_target(0.9)  # optimum 1 + k = −ln 0.9: k* = −0.8946, near the boundary k = −1


def LOSS_05(traj):  # optimum k* = ln 2 − 1, minimum 0.1 (so that relative changes mean something)
    return _terminal_target(0.5)(traj) + 0.1



def _tune_k(k0, loss, **kw):
    kw.setdefault("progress", False)
    kw.update(x0s=X0_1, xhat0s=XH0_1, ts=TS1, positive=False)
    return obsjax.tune(_Gain(jnp.asarray(k0)), SCALAR, where=WHERE_K, loss=loss, **kw)


@pytest.mark.extended
def test_a_step_across_a_validity_boundary_is_rejected_and_backtracked():
    """sgd with a large rate steps k below −1 (check() fails): the step is halved until the point is
    valid; the run goes on, warns, never evaluates a point twice and returns the best observer."""
    match = r"rejected \(the observer is invalid: `k` must be > -1"
    with pytest.warns(obsjax.TuneWarning, match=match):
        r = _tune_k(1.0, LOSS_09, optimizer=optax.sgd(20.0), steps=12)
    h = r.history
    assert h["skipped"] >= 2 and len(h["rejections"]) == h["skipped"]
    assert list(h["step_scale"][:4]) == [1.0, 1.0, 0.5, 0.25]  # two rejections, accepted at 1/4
    assert list(h["accepted"][:4]) == [True, False, False, True]
    assert all("`k` must be > -1" in why for _, why in h["rejections"])
    k = h["params"][0]
    assert len(np.unique(k)) == len(k)  # no point evaluated twice
    assert np.all(k[h["accepted"]] > -1.0) and np.any(k[~h["accepted"]] <= -1.0)
    assert np.all(np.isnan(h["loss"][~h["accepted"]]))
    assert np.all(np.isfinite(h["loss"][h["accepted"]]))
    assert float(r.observer.k) > -1.0 and float(r.observer.k) == k[h["best_step"]]
    assert h["loss"][h["best_step"]] == np.nanmin(h["loss"]) < h["loss"][0]
    assert r.steps_taken == 12 and r.stop_reason == "steps" and not r.converged


def test_consecutive_rejections_stop_the_run_with_the_best_observer():
    def loss(traj):  # finite only at the initial point: every step is rejected
        v = LOSS_09(traj)
        return jnp.where(jnp.abs(traj.error[-1, 0] + np.exp(-2.0)) < 1e-6, v, jnp.nan)

    with pytest.warns(obsjax.TuneWarning, match="3 consecutive rejections: stopping"):
        r = _tune_k(1.0, loss, optimizer=optax.sgd(0.5), steps=50, max_rejections=3)
    assert r.stop_reason == "rejections" and not r.converged and r.steps_taken == 4
    assert r.history["best_step"] == 0 and float(r.observer.k) == 1.0
    np.testing.assert_array_equal(r.history["step_scale"], [1.0, 1.0, 0.5, 0.25])
    assert "the loss is not finite" in r.history["rejections"][0][1]


def test_an_invalid_initial_point_raises():
    def loss(traj):
        return jnp.nan * LOSS_09(traj)

    with pytest.raises(ValueError, match="cannot be tuned from: the loss is not finite"):
        _tune_k(1.0, loss, steps=3)
    with pytest.raises(ValueError, match="`k` must be > -1"):
        _tune_k(-2.0, LOSS_09, steps=3)


@pytest.mark.extended
def test_a_flat_loss_stops_as_a_stationary_point():
    """x̂(0) = x(0): the error is zero for every gain, J ≡ 0 and ∇J = 0.  tune reported
    stop_reason="rejections", converged=False, with nothing rejected; it is a stationary point."""
    plant = obsjax.LTI([[-1.0, 1.0], [0.0, -2.0]], C=[[1.0, 0.0]])
    obs = obsjax.Luenberger.from_poles(plant, [-3.0, -4.0])
    x0s = jnp.array([[1.0, -1.0]])
    with pytest.warns(obsjax.TuneWarning, match="stationary point"):
        res = obsjax.tune(obs, plant, where=lambda o: o.poles, loss=obsjax.losses.ise, x0s=x0s, xhat0s=x0s,
                          ts=jnp.linspace(0, 2, 11), optimizer=optax.adam(0.1), steps=20, progress=False)  # fmt: skip
    assert res.stop_reason == "stationary" and res.converged
    assert res.history["skipped"] == 0 and float(res.history["loss"][0]) == 0.0


def test_stopping_rule_converges_to_the_closed_form_optimum():
    """‖x̃(1)‖ = e^{−(1+k)}: (‖x̃(1)‖ − 1/2)² is minimal at k* = ln 2 − 1.  With rtol the run stops
    once the loss stalls, well before the budget; without it, the whole budget runs."""
    rtol, patience = 1e-10, 3
    r = _tune_k(0.0, LOSS_05, optimizer=optax.sgd(1.0), steps=400, rtol=rtol, patience=patience)
    assert r.converged and r.stop_reason == "converged" and r.steps_taken < 100
    assert float(r.observer.k) == pytest.approx(np.log(2.0) - 1.0, abs=1e-4)
    # the rule: the last `patience` accepted losses did not beat the reference by more than rtol
    acc = r.history["loss"][r.history["accepted"]]
    ref = [acc[0]]
    for v in acc[1:]:
        ref.append(v if v < ref[-1] - rtol * abs(ref[-1]) else ref[-1])
    assert len(set(ref[-patience - 1 :])) == 1 and ref[-patience - 2] != ref[-patience - 1]
    full = _tune_k(0.0, LOSS_05, optimizer=optax.sgd(1.0), steps=30)
    assert full.stop_reason == "steps" and full.steps_taken == 30 and not full.converged
    assert len(full.history["loss"]) == 30 and full.history["skipped"] == 0


def test_rejected_steps_do_not_retrace():
    traces = []

    def loss(traj):
        traces.append(1)
        return LOSS_09(traj)

    with pytest.warns(obsjax.TuneWarning):
        r = _tune_k(1.0, loss, optimizer=optax.sgd(20.0), steps=8)
    assert r.history["skipped"] >= 2 and len(traces) == 1


# -- bad arguments: each named, before anything is traced ------------------------------------------


def _bad_call(**overrides):
    traces = []

    def loss(traj):
        traces.append(1)
        return obsjax.losses.ise(traj)

    kw = dict(where=lambda o: o.poles, loss=loss, x0s=X0S[:2], xhat0s=XH0S[:2], ts=TS, steps=2,
              progress=False)  # fmt: skip
    obs = overrides.pop("observer", obsjax.Luenberger.from_poles(PLANT, [-1.0, -2.0]))
    plant = overrides.pop("plant", PLANT)
    kw.update(overrides)
    try:
        obsjax.tune(obs, plant, **kw)
    finally:
        assert not traces  # refused before the loss was ever traced
    raise AssertionError("tune accepted a bad argument")


@pytest.mark.parametrize(
    "overrides,match",
    [
        (dict(observer=PLANT), "`observer` must be an obsjax observer"),
        (dict(plant="plant"), "`plant` must be an obsjax plant"),
        (dict(where="poles"), "`where` must be a callable"),
        (dict(loss=3.0), "`loss` must be a callable"),
        (dict(optimizer="adam"), "`optimizer` must be an optax.GradientTransformation"),
        (dict(steps=10.0), r"`steps` .* must be an integer >= 1, got 10.0 \(float\)"),
        (dict(steps=True), "`steps`"),
        (dict(steps=0), "`steps`"),
        (dict(positive="yes"), "`positive`"),
        (dict(rtol=-1e-3), "`rtol`"),
        (dict(patience=0), "`patience`"),
        (dict(max_rejections=0), "`max_rejections`"),
        (dict(x0s=X0S[:2, :1]), r"`x0s` must be \(batch, 2\)"),
        (dict(x0s=X0S[:2].at[0, 0].set(jnp.nan)), "`x0s` must be finite"),
        (dict(ts=TS[::-1]), "`ts` must be strictly increasing"),
        (dict(noise=NOISE), "`key` is required"),
        (dict(noise="white"), "`noise` must be an obsjax noise model"),
        (dict(u=1.0), "`u` must be a callable"),
        (dict(simulate_kwargs={"throw": True}), "must not contain 'throw'"),
        (dict(simulate_kwargs=[("rtol", 1e-3)]), "`simulate_kwargs` must be a dict"),
        (dict(plant_batched=True), "`plant_batched=True` needs a leading axis"),
        (dict(risk="median"), "`risk` must be"),
        (dict(where=lambda o: o.L), "`where` selects None"),
        (dict(where=lambda o: o.gain), "derived property such as `gain`"),
        (dict(where=lambda o: (o.poles, o.observer_matrix)), "`where` entry 1 selects"),
        (dict(where=lambda o: o.gamma), "`where` failed on the observer: AttributeError"),
        (dict(observer=obsjax.Luenberger(PLANT, L=[[0.0], [4.0]]), where=lambda o: o.L), "zero"),
    ],
)
def test_bad_argument_is_named_before_tracing(overrides, match):
    with pytest.raises(ValueError, match=match):
        _bad_call(**overrides)


def test_empty_batch_is_refused_naming_x0s():
    """Review finding 4: x0s and xhat0s of shape (0, n) passed the checks and risk_weights then divided
    by zero (ZeroDivisionError)."""
    with pytest.raises(ValueError, match=r"`x0s` and `xhat0s` must hold at least one scenario .*\(0, 2\)"):
        _bad_call(x0s=X0S[:0], xhat0s=XH0S[:0])


def test_where_selecting_a_leaf_twice_is_refused():
    """Review finding 5: ``where=lambda o: (o.poles, o.poles)`` was accepted; eqx.tree_at kept the last
    assignment only, so entry 0 was reported in the history but never used."""
    with pytest.raises(ValueError, match="`where` must select each leaf at most once, got entries 0 and 1"):
        _bad_call(where=lambda o: (o.poles, o.poles))
    with pytest.raises(ValueError, match="entries 0 and 2"):
        _bad_call(where=lambda o: (o.poles, o.model.A, o.poles))


def test_where_may_select_two_fields_that_hold_one_array_object():
    """Two fields holding the same array object are two leaves for eqx.tree_at (it tells positions
    apart): selecting both is not a duplicate."""
    from obsjax.tuning._tune import _selected_leaves

    obs = obsjax.LeastSquaresReset(obsjax.chen_yen_example(), gamma=20.0, p0=0.1, T=0.3337)
    shared = jnp.array(0.5)
    obs = eqx.tree_at(lambda o: (o.gamma, o.p0), obs, (shared, shared))
    assert obs.gamma is obs.p0
    leaves, single = _selected_leaves(obs, lambda o: (o.gamma, o.p0))
    assert len(leaves) == 2 and not single
    with pytest.raises(ValueError, match="at most once"):
        _selected_leaves(obs, lambda o: (o.gamma, o.gamma))


def test_where_selecting_a_method_is_refused():
    kb = obsjax.KalmanBucy(PLANT, Qw=0.1 * jnp.eye(2), Rv=0.01 * jnp.eye(1), P0=jnp.eye(2))
    with pytest.raises(ValueError, match="selects a method that is not an array leaf"):
        _bad_call(observer=kb, where=lambda o: o.gain)


def test_vector_valued_loss_is_refused_at_trace_time():
    with pytest.raises(ValueError, match=r"`loss` must map a trajectory to a real scalar.*\(11,\)"):
        _tune_k(1.0, lambda traj: traj.error_norm, steps=2)


# -- kinks: save times at reset instants -----------------------------------------------------------


class _ResettingGain(obsjax.AbstractObserver):
    """x̂' = a x̂ + k(t)(y − x̂), k' = −k, k(jT⁺) = k0: x̂ continuous, its slope jumping at resets."""

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


RESETTING = _ResettingGain(jnp.array(0.5), jnp.array(4.0), jnp.array(0.5))
PLANT_R = obsjax.LTI([[0.5]], None, [[1.0]])
TS_R = jnp.linspace(0.0, 1.8, 19)  # a 0.1 grid: 0.5, 1.0, 1.5 (multiples of T = 0.5) are save times
WHERE_T = lambda o: o.T  # noqa: E731
WHERE_K0 = lambda o: o.k0  # noqa: E731


def test_reset_coincidences():
    from obsjax.tuning._tune import reset_coincidences

    hits = reset_coincidences(2.3, np.linspace(0.0, 10.0, 101))
    np.testing.assert_allclose(hits, [2.3, 4.6, 6.9, 9.2])
    assert reset_coincidences(2.31, np.linspace(0.0, 10.0, 101)) == []
    assert reset_coincidences(0.5, TS_R) == pytest.approx([0.5, 1.0, 1.5])
    assert reset_coincidences(0.5, np.linspace(0.0, 2.0, 21)) == pytest.approx([0.5, 1.0, 1.5, 2.0])


@pytest.mark.extended
def test_kink_in_T_at_a_save_time_is_one_sided_and_tune_warns():
    """With save times on the reset instants the ISE has a kink in T: autodiff returns the
    derivative from one side (here the left: a slightly shorter period puts the reset before the
    save time), which differs from the other side's.  tune warns when T is tuned, and is silent
    when only k0 is."""

    def J(T):
        obs = eqx.tree_at(WHERE_T, RESETTING, T)
        tr = obsjax.simulate(PLANT_R, obs, jnp.ones(1), jnp.zeros(1), TS_R, rtol=1e-11, atol=1e-13,
                             max_segments=8)  # fmt: skip
        return obsjax.losses.ise(tr)

    g = float(jax.jit(jax.grad(J))(0.5))
    Jj = jax.jit(J)
    h = 1e-4  # second-order one-sided differences
    f0, fl1, fl2, fr1, fr2 = (float(Jj(0.5 + d)) for d in (0.0, -h, -2 * h, h, 2 * h))
    left = (3 * f0 - 4 * fl1 + fl2) / (2 * h)
    right = (-3 * f0 + 4 * fr1 - fr2) / (2 * h)
    assert g == pytest.approx(left, rel=1e-5)
    assert abs(right - left) > 0.05 * abs(left)  # a genuine kink, not rounding
    # off the grid the derivative is two-sided and autodiff matches central differences
    g2 = float(jax.jit(jax.grad(J))(0.53))
    assert g2 == pytest.approx((float(Jj(0.53 + h)) - float(Jj(0.53 - h))) / (2 * h), rel=1e-5)

    kw = dict(loss=obsjax.losses.ise, x0s=jnp.ones((1, 1)), xhat0s=jnp.zeros((1, 1)), ts=TS_R)
    kw.update(steps=1, progress=False)
    match = r"save times 0\.5, 1, 1\.5 coincide with reset instants"
    with pytest.warns(obsjax.TuneWarning, match=match):
        obsjax.tune(RESETTING, PLANT_R, where=WHERE_T, **kw)
    with warnings.catch_warnings():
        warnings.simplefilter("error", obsjax.TuneWarning)
        obsjax.tune(RESETTING, PLANT_R, where=WHERE_K0, **kw)  # T fixed: the loss is smooth in k0
        obsjax.tune(eqx.tree_at(WHERE_T, RESETTING, jnp.array(0.53)), PLANT_R, where=WHERE_T, **kw)


@pytest.mark.slow
def test_least_squares_reset_kink_on_chen_yen_example():
    """The numbers quoted in LeastSquaresReset's and tune's docstrings: Chen & Yen's example,
    γ = 20, p0 = 0.1, x̂(0) = (5, −5), the ISE on a 0.1 s grid over [0, 10], T = 2.3 (four save
    times on reset instants): autodiff −11.84 = the left derivative, −13.97 from the right; tune
    warns."""
    plant = obsjax.chen_yen_example()
    obs = obsjax.LeastSquaresReset(plant, 20.0, 0.1, 2.3)
    ts = jnp.linspace(0.0, 10.0, 101)

    def J(T):
        o = eqx.tree_at(WHERE_T, obs, T)
        xh0 = jnp.array([5.0, -5.0])
        kw = dict(rtol=1e-10, atol=1e-12, max_segments=8)
        tr = obsjax.simulate(plant, o, jnp.zeros(2), xh0, ts, **kw)
        return obsjax.losses.ise(tr)

    g = float(jax.jit(jax.grad(J))(2.3))
    Jj = jax.jit(J)
    h = 1e-4
    f0, fl1, fl2, fr1, fr2 = (float(Jj(2.3 + d)) for d in (0.0, -h, -2 * h, h, 2 * h))
    left, right = (3 * f0 - 4 * fl1 + fl2) / (2 * h), (-3 * f0 + 4 * fr1 - fr2) / (2 * h)
    assert g == pytest.approx(left, rel=1e-4) and g == pytest.approx(-11.84, abs=0.01)
    assert right == pytest.approx(-13.97, abs=0.01)
    with pytest.warns(obsjax.TuneWarning, match=r"save times 2\.3, 4\.6, 6\.9, 9\.2 coincide"):
        obsjax.tune(obs, plant, where=WHERE_T, loss=obsjax.losses.ise, x0s=jnp.zeros((1, 2)),
                    xhat0s=jnp.array([[5.0, -5.0]]), ts=ts, steps=1, progress=False)  # fmt: skip


def test_reset_coincidences_at_clock_times():
    """At a Unix-time origin (1.7e9 s) the relative test alone found 2 of the 13 resets (T = 0.3) that fall
    on samples every 0.1 (and 3 in ms): the schedule merges all 13 within its time tolerance, so the
    kink warning now uses that tolerance too."""
    from obsjax.tuning._tune import reset_coincidences

    for k in (1.0, 1e-3, 1e3):
        for t0 in (0.0, 1.7e9):
            ts = k * (t0 + 0.1 * np.arange(41))
            assert len(reset_coincidences(k * 0.3, ts)) == 13, (k, t0)
    assert reset_coincidences(0.1 * np.sqrt(2.0), 1.7e9 + 0.1 * np.arange(41)) == []  # none falls on a sample
