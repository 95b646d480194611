"""Gradient tuning: finite-difference gradients of every tunable leaf, the noise trade-off, robustness."""

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
    for risk in ("mean", ("cvar", 0.5), "worst"):
        r = obsjax.tune(obs, plants, where=lambda o: o.poles, loss=obsjax.losses.ise, x0s=X0S[:6],
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
