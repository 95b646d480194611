"""Gradient tuning of observer gains with optax."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optax

from .._checks import as_float_array, concrete_value
from .._config import require_x64
from .._simulate import num_segments, simulate


class TuneResult(eqx.Module):
    """Outcome of :func:`obsjax.tune`.

    - `observer`: the best observer seen (lowest loss), never one from a non-finite step.
    - `history`: dict with ``loss`` (steps,), ``params`` (list per tuned leaf, each (steps, …)),
      ``skipped`` (number of steps whose loss or gradient was non-finite and was not applied),
      ``best_step``.
    """

    observer: Any
    history: dict


def risk_measure(losses, risk):
    """Aggregate per-scenario losses: ``"mean"``, ``"worst"`` (max) or ``("cvar", α)`` — the mean of the
    worst ⌈(1 − α)·N⌉ losses (conditional value at risk at level α)."""
    if risk == "mean":
        return jnp.mean(losses)
    if risk in ("worst", "max"):
        return jnp.max(losses)
    if isinstance(risk, tuple) and len(risk) == 2 and risk[0] == "cvar":
        alpha = float(risk[1])
        if not 0.0 <= alpha < 1.0:
            raise ValueError(f"CVaR level α must be in [0, 1), got {alpha}.")
        k = max(1, int(math.ceil((1.0 - alpha) * losses.shape[0])))
        return jnp.mean(jax.lax.top_k(losses, k)[0])
    raise ValueError(f"`risk` must be 'mean', 'worst' or ('cvar', α), got {risk!r}.")


def risk_weights(risk, batch: int) -> np.ndarray:
    """Weights w (batch,) on the ascending-sorted losses, so that ``risk_measure(l, risk) = Σ_i w_i l_(i)``.

    The risk measure then enters :func:`tune` as data rather than as traced code, so one compilation
    serves ``"mean"``, ``"worst"`` and every ``("cvar", α)``.  A non-finite loss sorts last and makes the
    weighted sum non-finite whatever its weight (a failed scenario is never averaged away).
    """
    batch = int(batch)
    w = np.zeros(batch)
    if risk == "mean":
        w[:] = 1.0 / batch
    elif risk in ("worst", "max"):
        w[-1] = 1.0
    elif isinstance(risk, tuple) and len(risk) == 2 and risk[0] == "cvar":
        alpha = float(risk[1])
        if not 0.0 <= alpha < 1.0:
            raise ValueError(f"CVaR level α must be in [0, 1), got {alpha}.")
        k = max(1, int(math.ceil((1.0 - alpha) * batch)))
        w[batch - k :] = 1.0 / k
    else:
        raise ValueError(f"`risk` must be 'mean', 'worst' or ('cvar', α), got {risk!r}.")
    return w


def _sorted_weighted(losses, weights):
    s = jnp.sort(losses)
    # 0·NaN would be NaN anyway; spelled out so that a failed scenario always poisons the value
    return jnp.where(jnp.all(jnp.isfinite(losses)), jnp.sum(weights * s), jnp.nan)


@eqx.filter_jit
def _value_and_grad(theta, signs, observer, plant, x0s, xhat0s, keys, weights, spec):
    """J(θ) and ∇J for :func:`tune`.  Module-level, with every array an argument: calls that differ only
    in array values (initial gains, scenarios, risk weights, keys) reuse one compilation.
    ``spec`` holds the static rest (where, loss, single, plant_batched, noise, u, max_segments,
    simulate_kwargs, and ts as a tuple of floats: simulate needs concrete save times)."""
    where, loss, single, plant_batched, noise, u, max_segments, simulate_kwargs, ts = spec
    ts = np.asarray(ts, dtype=float)  # concrete inside the trace
    plant_axis = eqx.if_array(0) if plant_batched else None

    def J(th):
        new = tuple(th) if signs is None else tuple(s * jnp.exp(t) for s, t in zip(signs, th))
        obs = eqx.tree_at(where, observer, new[0] if single else new)

        def one(pl, x0, xh0, k):
            traj = simulate(
                pl, obs, x0, xh0, ts, u=u, noise=noise, key=k, throw=False,
                max_segments=max_segments, **dict(simulate_kwargs),
            )
            val = loss(traj)
            return jnp.where(traj.status == 0, val, jnp.nan)

        losses = eqx.filter_vmap(one, in_axes=(plant_axis, 0, 0, 0))(plant, x0s, xhat0s, keys)
        return _sorted_weighted(losses, weights)

    return jax.value_and_grad(J)(theta)


def _as_tuple(x):
    return tuple(x) if isinstance(x, (tuple, list)) else (x,)


def tune(
    observer,
    plant,
    *,
    where: Callable,
    loss: Callable,
    x0s,
    xhat0s,
    ts,
    optimizer: optax.GradientTransformation | None = None,
    steps: int = 100,
    positive: bool = True,
    key=None,
    progress: bool = True,
    noise=None,
    u: Callable | None = None,
    plant_batched: bool = False,
    risk="mean",
    simulate_kwargs: dict | None = None,
) -> TuneResult:
    """Tune observer gains by gradient descent through simulated error trajectories.

    Minimises  J(θ) = risk_i [ loss(simulate(plant_i, observer(θ), x0_i, x̂0_i, ts, noise_i)) ]  over the
    leaves selected by ``where``, with an optax optimizer, differentiating through the diffrax solves.

    **Arguments:**

    - `observer`: the observer to tune (its other leaves stay fixed).
    - `plant`: the true plant; with ``plant_batched=True`` every leaf has a leading batch axis (sampled
      plants, model uncertainty) matching ``x0s``.
    - `where`: ``lambda obs: obs.poles`` or ``lambda obs: (obs.gamma, obs.T)``: the tuned leaves.
    - `loss`: trajectory -> scalar, e.g. :func:`obsjax.losses.ise`.
    - `x0s`, `xhat0s`: (batch, n) initial states and estimates.
    - `ts`: save times.
    - `optimizer`: optax transformation (default ``optax.adam(1e-2)``).
    - `steps`: number of gradient steps.
    - `positive`: keep each tuned leaf's sign: leaf = sign(leaf₀)·exp(θ) (a reparametrisation, never
      clipping); gains, rates, periods stay positive and real poles stay in the left half-plane.  Every
      tuned entry must then be nonzero.
    - `key`: PRNG key for the noise (fixed across steps: common random numbers give a smooth objective).
    - `noise`, `u`: passed to :func:`obsjax.simulate`.
    - `risk`: ``"mean"``, ``"worst"`` or ``("cvar", α)`` across the batch.
    - `simulate_kwargs`: extra keyword arguments of :func:`obsjax.simulate` (solver, rtol, dt0, …).

    A step whose loss or gradient is non-finite is skipped (not applied) and counted; the best observer
    seen is returned.  After each update the observer's ``check()`` re-validates its invariants
    (``eqx.tree_at`` skips ``__check_init__``).  Observers with a reset period T are simulated with a
    number of segments recomputed from the current T (a retrace happens only when it grows past a
    power-of-two bucket).

    The gradient is compiled once per problem structure and reused across calls: calls that differ only in
    array values (initial gains, scenario batches of the same size, the risk measure, which enters as
    weights on the sorted losses, see :func:`risk_weights`) do not recompile, provided they pass the same
    ``where`` and ``loss`` objects (a lambda written inside a loop is a new object each time).

    **Returns:** :class:`TuneResult`.
    """
    require_x64("obsjax.tune")
    x0s = as_float_array(x0s, "x0s")
    xhat0s = as_float_array(xhat0s, "xhat0s")
    if x0s.ndim != 2 or xhat0s.ndim != 2 or x0s.shape[0] != xhat0s.shape[0]:
        raise ValueError(
            f"`x0s` and `xhat0s` must be (batch, n) with the same batch, got {tuple(x0s.shape)} and {tuple(xhat0s.shape)}."
        )
    if steps < 1:
        raise ValueError(f"`steps` must be >= 1, got {steps}.")
    batch = x0s.shape[0]
    optimizer = optax.adam(1e-2) if optimizer is None else optimizer
    simulate_kwargs = dict(simulate_kwargs or {})
    if noise is not None and key is None:
        raise ValueError("`key` is required when `noise` is given.")
    keys = jr.split(jr.PRNGKey(0) if key is None else key, batch)

    leaves0 = tuple(jnp.asarray(leaf) for leaf in _as_tuple(where(observer)))
    if any(leaf is None for leaf in _as_tuple(where(observer))):
        raise ValueError("`where` selected a leaf that is None; select array-valued gains.")
    if positive:
        signs = []
        thetas = []
        for i, leaf in enumerate(leaves0):
            v = np.asarray(leaf)
            if np.iscomplexobj(v):
                raise ValueError(f"tuned leaf {i} is complex: use positive=False for complex parameters.")
            if np.any(v == 0):
                raise ValueError(
                    f"tuned leaf {i} has zero entries {v.tolist()}: positive=True keeps signs through "
                    "leaf = sign·exp(θ), so every entry must be nonzero."
                )
            signs.append(jnp.sign(leaf))
            thetas.append(jnp.log(jnp.abs(leaf)))
        signs = tuple(signs)
        theta0 = tuple(thetas)

        def to_leaves(theta):
            return tuple(s * jnp.exp(t) for s, t in zip(signs, theta))
    else:
        theta0 = leaves0

        def to_leaves(theta):
            return tuple(theta)

    single = not isinstance(where(observer), (tuple, list))

    def build(theta):
        new = to_leaves(theta)
        return eqx.tree_at(where, observer, new[0] if single else new)

    span = float(np.asarray(ts)[-1] - np.asarray(ts)[0])

    def segments_for(obs):
        T = obs.reset_period
        if T is None:
            return None
        ns = num_segments(T, 0.0, span)
        return int(2 ** math.ceil(math.log2(max(ns, 1))))

    weights = jnp.asarray(risk_weights(risk, batch))
    spec_kwargs = tuple(sorted(simulate_kwargs.items()))
    ts_key = tuple(float(v) for v in np.asarray(ts, dtype=float).ravel())

    def value_and_grad(theta, max_segments):
        # array leaves of a batched plant are mapped; callables (LTV's A(t), C(t)) are shared
        spec = (where, loss, single, plant_batched, noise, u, max_segments, spec_kwargs, ts_key)
        return _value_and_grad(
            theta, signs if positive else None, observer, plant, x0s, xhat0s, keys, weights, spec
        )

    opt_state = optimizer.init(theta0)
    update = jax.jit(optimizer.update)
    theta = theta0
    losses, params = [], [[] for _ in leaves0]
    skipped = 0
    best = (np.inf, observer, -1)
    it = range(steps)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(it, desc="tune", leave=False)
        it = bar
    seg_bucket = None  # only ever grows: a shrinking T would otherwise trigger a recompilation
    for step in it:
        obs_now = build(theta).check()
        need = segments_for(obs_now)
        if need is not None:
            seg_bucket = need if seg_bucket is None else max(seg_bucket, need)
        val, grads = value_and_grad(theta, seg_bucket)
        val = float(val)
        finite = np.isfinite(val) and all(bool(jnp.all(jnp.isfinite(g))) for g in grads)
        losses.append(val)
        for i, leaf in enumerate(to_leaves(theta)):
            params[i].append(np.asarray(leaf))
        if not finite:
            skipped += 1
            continue
        if val < best[0]:
            best = (val, obs_now, step)
        updates, opt_state = update(grads, opt_state, theta)
        theta = optax.apply_updates(theta, updates)
        if bar is not None:
            bar.set_postfix(loss=f"{val:.4g}")
    history = {
        "loss": np.asarray(losses),
        "params": [np.stack(p) for p in params],
        "skipped": skipped,
        "best_step": best[2],
    }
    if best[2] < 0:
        raise ValueError("tune: every step produced a non-finite loss; check the gains and the loss.")
    return TuneResult(observer=best[1], history=history)
