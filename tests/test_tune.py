"""Gradient tuning: finite-difference gradients of every tunable leaf, the noise trade-off, robustness."""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optax
import pytest

import obsjax

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
def test_gradient_of_every_tunable_leaf_matches_fd(name, obs_of, p0):
    J = _batch_loss(obs_of)
    g = np.asarray(jax.grad(J)(jnp.asarray(p0)))
    np.testing.assert_allclose(g, _fd(J, p0), rtol=2e-4, atol=1e-7)


@pytest.mark.parametrize("loss", [obsjax.losses.itae, obsjax.losses.peak, obsjax.losses.terminal])
def test_gradient_of_each_loss_matches_fd(loss):
    J = _batch_loss(lambda p: obsjax.Luenberger.from_poles(PLANT, p), loss)
    p0 = [-2.0, -3.5]
    g = np.asarray(jax.grad(J)(jnp.asarray(p0)))
    np.testing.assert_allclose(g, _fd(J, p0), rtol=2e-4, atol=1e-7)


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


def test_tune_skips_nonfinite_steps_and_returns_best():
    obs = obsjax.Luenberger.from_poles(PLANT, [-2.0, -2.5])

    def loss(traj):  # non-finite once the estimate gets good: a step that must be skipped
        v = obsjax.losses.ise(traj)
        return jnp.where(v < 0.8 * 1.1, jnp.nan, v)

    r = obsjax.tune(obs, PLANT, where=lambda o: o.poles, loss=loss, x0s=X0S[:2], xhat0s=XH0S[:2],
                    ts=TS, steps=12, optimizer=optax.sgd(0.5), progress=False)
    assert r.history["skipped"] > 0
    assert np.isfinite(r.history["loss"][r.history["best_step"]])
    assert np.all(np.isfinite(np.asarray(r.observer.poles)))


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


def test_tune_reuses_its_compilation_across_risks_and_initial_gains():
    traces = []

    def loss(traj):  # runs once per trace
        traces.append(1)
        return obsjax.losses.ise(traj)

    where = lambda o: o.poles  # noqa: E731
    ts = jnp.linspace(0.0, 1.0, 11)
    for p, risk in [([-1.0, -2.0], "mean"), ([-3.0, -4.0], ("cvar", 0.5)), ([-2.0, -5.0], "worst")]:
        r = obsjax.tune(obsjax.Luenberger.from_poles(PLANT, p), PLANT, where=where, loss=loss, x0s=X0S[:4],
                        xhat0s=XH0S[:4], ts=ts, steps=2, optimizer=optax.adam(0.1), risk=risk, progress=False)
        assert r.history["skipped"] == 0
    assert len(traces) == 1


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
