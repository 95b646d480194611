"""Gradient tuning of observer gains with optax: checked arguments, backtracking, a stop rule."""

from __future__ import annotations

import math
import warnings
from functools import partial
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optax

from .. import _trace_cache
from .._checks import as_float_array, device_array, runtime_checks_as_nan, scalar_value
from .._config import require_x64
from .._integrate import _diffrax, _masked, _schedule, _validate
from .._simulate import SUCCESS, _check_ts, num_segments, simulate
from .._simulate_batch import simulate_batch, simulate_plants
from ..montecarlo._fingerprint import content_key
from ..systems._noise import WhiteNoise
from ._losses import cvar_level as _cvar_level
from ._losses import tail_count

#: Factor applied to the step after a rejected step (its inverse, up to 1, after an accepted one).
BACKTRACK = 0.5

#: ``mode="auto"`` differentiates in forward mode when the tuned leaves hold at most this many real
#: scalars (a complex entry counts twice), in reverse mode otherwise
#: (``benchmarks/results/j_forward_gradient.md`` measures where the two cross).
FORWARD_MODE_MAX_SCALARS = 4
#: With fixed steps (``adaptive=False``), whose reverse pass through one ``lax.scan`` costs about 3 forward
#: passes whatever the batch, each tangent of forward mode costs 1–2.5 forward passes once the batch is
#: large enough for the scan's arrays to set the pace (1024 scenarios, 3 scalars, CPU time: a 3-state
#: chain 8.7× in forward mode against 3.1× in reverse mode, Chen & Yen's example 5.6× against 3.7×), and
#: about 0.5–1 for small batches (64 scenarios: Chen & Yen 2.6× against 3.5×, the chain 4.7× against
#: 4.1×; a 4-state chain, 4 scalars, 4.9× against 3.6×).  ``mode="auto"`` therefore uses forward mode with
#: fixed steps only for one scalar, or when scalars × scenarios is at most this.
FIXED_STEP_FORWARD_MAX_WORK = 192

_MODES = ("auto", "forward", "reverse")


class TuneWarning(UserWarning):
    """:func:`obsjax.tune` rejected a step, stopped early, or met a kink of the loss (the message
    says which)."""


class TuneResult(eqx.Module):
    """Outcome of :func:`obsjax.tune`.

    - `observer`: the best observer evaluated (lowest loss), always a valid one with a finite loss.
    - `history`: a dict with one entry per evaluation of J(θ) and ∇J (the initial point included):

      - ``loss`` (k,): J at each evaluated point, NaN where the point was rejected;
      - ``params``: one array per tuned leaf, each (k, …): the leaf at each evaluated point;
      - ``accepted`` (k,) bool: whether the point was accepted (valid observer, finite J and ∇J);
      - ``step_scale`` (k,): the backtracking factor s of the step that led to the point (1 = the
        optimizer's full step);
      - ``rejections``: a list of ``(index, reason)`` for the rejected points;
      - ``skipped``: the number of rejected points; ``best_step``: the index of `observer`'s point.
    - `converged`: True when the stopping rule (``rtol``, ``patience``) ended the run, or the
      optimizer's full step no longer moves the gains (a stationary point).
    - `stop_reason`: ``"converged"``, ``"stationary"`` (the optimizer's full, unscaled update leaves
      θ unchanged, e.g. ∇J = 0: a flat loss), ``"steps"`` (the budget of evaluations is spent) or
      ``"rejections"`` (``max_rejections`` consecutive rejected steps, or a step scaled down by
      backtracking that no longer moves θ).
    - `steps_taken`: the number of evaluations made (≤ ``steps``).
    """

    observer: Any
    history: dict
    converged: bool = eqx.field(static=True, default=False)
    stop_reason: str = eqx.field(static=True, default="steps")
    steps_taken: int = eqx.field(static=True, default=0)


def risk_measure(losses, risk):
    """Aggregate per-scenario losses: ``"mean"``, ``"worst"`` (max) or ``("cvar", α)`` — the mean of
    the worst ⌈(1 − α)·N⌉ losses (conditional value at risk at level α).

    `losses`: a non-empty 1-D array of real numbers (N,), one per scenario.  A non-finite loss (a failed or
    diverged scenario) makes the result NaN whatever the risk measure, as in :func:`tune`
    (:func:`risk_weights`): a failed scenario is never averaged away, nor chosen as a best case.
    """
    if getattr(losses, "dtype", None) == bool or isinstance(losses, bool):
        raise ValueError("`losses` must hold real numbers, got booleans.")
    losses = jnp.asarray(losses)
    if not jnp.issubdtype(losses.dtype, jnp.floating) and not jnp.issubdtype(losses.dtype, jnp.integer):
        raise ValueError(f"`losses` must hold real numbers, got dtype {losses.dtype}.")
    if losses.ndim != 1 or losses.shape[0] == 0:
        raise ValueError(
            f"`losses` must be a non-empty 1-D array (N,) of per-scenario losses, got shape {tuple(losses.shape)}."
        )
    losses = losses.astype(jnp.result_type(float))
    if risk == "mean":
        out = jnp.mean(losses)
    elif risk in ("worst", "max"):
        out = jnp.max(losses)
    elif isinstance(risk, tuple) and len(risk) == 2 and risk[0] == "cvar":
        alpha = _cvar_level(risk[1])
        k = tail_count(alpha, losses.shape[0])
        out = jnp.mean(jax.lax.top_k(losses, k)[0])
    else:
        raise ValueError(f"`risk` must be 'mean', 'worst' or ('cvar', α), got {risk!r}.")
    return jnp.where(jnp.all(jnp.isfinite(losses)), out, jnp.nan)


def risk_weights(risk, batch: int | np.integer) -> np.ndarray:
    """Weights w (batch,) on the ascending-sorted losses, so that
    ``risk_measure(l, risk) = Σ_i w_i l_(i)``.

    The risk measure then enters :func:`tune` as data rather than as traced code, so one compilation
    serves ``"mean"``, ``"worst"`` and every ``("cvar", α)``.  A non-finite loss sorts last and
    makes the weighted sum non-finite whatever its weight (a failed scenario is never averaged
    away).
    """
    b = None if isinstance(batch, bool) else scalar_value(batch)
    if b is None or np.ndim(b) != 0 or not float(b).is_integer() or float(b) < 1:
        raise ValueError(f"`batch` must be a positive integer (the number of scenarios), got {batch!r}.")
    batch = int(b)
    w = np.zeros(batch)
    if risk == "mean":
        w[:] = 1.0 / batch
    elif risk in ("worst", "max"):
        w[-1] = 1.0
    elif isinstance(risk, tuple) and len(risk) == 2 and risk[0] == "cvar":
        alpha = _cvar_level(risk[1])
        k = tail_count(alpha, batch)
        w[batch - k :] = 1.0 / k
    else:
        raise ValueError(f"`risk` must be 'mean', 'worst' or ('cvar', α), got {risk!r}.")
    return w


def _sorted_weighted(losses, weights):
    s = jnp.sort(losses)
    # 0·NaN would be NaN anyway; spelled out so that a failed scenario always poisons the value
    return jnp.where(jnp.all(jnp.isfinite(losses)), jnp.sum(weights * s), jnp.nan)


def _loss_value(loss, traj):
    """``loss(traj)`` for one trajectory, checked to be a real scalar (refused while tracing)."""
    val = jnp.asarray(loss(traj))
    if val.shape != () or not jnp.issubdtype(val.dtype, jnp.floating):
        raise ValueError(
            "`loss` must map a trajectory to a real scalar (e.g. obsjax.losses.ise), "
            f"got an array of shape {val.shape} and dtype {val.dtype}: reduce it (sum, "
            "mean) to one number."
        )
    return jnp.where(traj.status == SUCCESS, val, jnp.nan)


# eqx.filter_jit; the traced program saved when the trace cache is on; XLA:CPU's faster-compiling emitter
@_trace_cache.filter_jit(fast_compile=True)
def _value_and_grad(theta, signs, observer, plant, x0s, xhat0s, keys, weights, spec):
    """J(θ) and ∇J for :func:`tune`.  Module-level, with every array an argument: calls that differ
    only in array values (initial gains, scenarios, risk weights, keys) reuse one compilation.
    ``spec`` holds the static rest (where, loss, single, plant_batched, noise, u, max_segments,
    simulate_kwargs, ts as a tuple of floats: simulate needs concrete save times, the mode of
    differentiation, ``"forward"`` or ``"reverse"``, and the batch kernel, ``"masked"`` for
    ``simulate_batch(lockstep=False)`` on the masked adaptive Runge–Kutta loop or ``"vmap"`` for
    ``jax.vmap(simulate)``), and a digest of the functions' content (globals they read included)."""
    where, loss, single, plant_batched, noise, u, max_segments, simulate_kwargs, ts, mode, kernel, _ = spec
    ts = np.asarray(ts, dtype=float)  # concrete inside the trace
    plant_axis = eqx.if_array(0) if plant_batched else None
    sim_kwargs = _solve_kwargs(simulate_kwargs, mode)

    def J(th):
        new = tuple(th) if signs is None else tuple(s * jnp.exp(t) for s, t in zip(signs, th))
        obs = eqx.tree_at(where, observer, new[0] if single else new)
        if kernel == "masked":
            # one plant per scenario (plant_batched) or one shared by all
            batch = simulate_plants if plant_batched else partial(simulate_batch, lockstep=False)
            traj = batch(
                plant,
                obs,
                x0s,
                xhat0s,
                ts,
                keys=keys if noise is not None else None,
                u=u,
                noise=noise,
                throw=False,
                max_segments=max_segments,
                **sim_kwargs,
            )
            losses = jax.vmap(lambda tr: _loss_value(loss, tr))(traj)
            return _sorted_weighted(losses, weights)

        def one(pl, x0, xh0, k):
            traj = simulate(
                pl,
                obs,
                x0,
                xh0,
                ts,
                u=u,
                noise=noise,
                key=k if noise is not None else None,
                throw=False,
                max_segments=max_segments,
                **sim_kwargs,
            )
            return _loss_value(loss, traj)

        losses = eqx.filter_vmap(one, in_axes=(plant_axis, 0, 0, 0))(plant, x0s, xhat0s, keys)
        return _sorted_weighted(losses, weights)

    if mode == "forward":
        return _forward_value_and_grad(J, theta)
    return jax.value_and_grad(J)(theta)


def batch_kernel(observer, ts, *, plant_batched=False, noise=None, mode="reverse",
                 simulate_kwargs=None) -> str:
    """How :func:`tune` simulates its scenarios: ``"masked"`` — one
    ``simulate_batch(..., lockstep=False)``, each scenario with its own adaptive steps on the masked
    Runge–Kutta loop — when the problem allows it (adaptive steps of an explicit Runge–Kutta pair, no
    white noise, no observer events, ``max_steps`` set, an adjoint the loop implements; a plant
    shared by the scenarios or, with `plant_batched`, one plant per scenario); ``"vmap"`` —
    ``jax.vmap(simulate)`` — otherwise.  Both solve every scenario as :func:`obsjax.simulate` does (to
    rounding; the masked loop's step budget is ``max_steps`` per segment, shared by a scenario's
    segments)."""
    del plant_batched  # both kernels take a batch of plants
    kw = _solve_kwargs(simulate_kwargs or {}, mode)
    ts_np = np.asarray(ts, dtype=float)
    return "masked" if _masked.eligible_options(observer, ts_np, noise=noise, **kw) else "vmap"


def _solve_kwargs(simulate_kwargs, mode) -> dict:
    """simulate's keyword arguments in tune's kernel: forward mode differentiates through
    ``diffrax.ForwardMode()`` unless an adjoint is given."""
    kw = dict(simulate_kwargs)
    if mode == "forward" and "adjoint" not in kw:
        kw["adjoint"] = diffrax.ForwardMode()
    return kw


def _forward_value_and_grad(J, theta):
    """J(θ) and ∇J by forward mode: one ``jax.jvp`` per real coordinate of θ, vmapped
    (``jax.jacfwd``), the value computed once beside them.  A complex entry z = a + ib is two real
    coordinates; its gradient is returned as ∂J/∂a − i ∂J/∂b, the convention of ``jax.grad``."""
    cplx = tuple(jnp.iscomplexobj(t) for t in theta)
    reals = tuple(jnp.stack([t.real, t.imag]) if c else t for t, c in zip(theta, cplx))

    def Jr(r):
        val = J(tuple(x[0] + 1j * x[1] if c else x for x, c in zip(r, cplx)))
        return val, val

    jac, val = jax.jacfwd(Jr, has_aux=True)(reals)
    grads = tuple(g[0] - 1j * g[1] if c else g for g, c in zip(jac, cplx))
    return val, grads


def n_real_scalars(leaves) -> int:
    """The number of real scalars in `leaves` (a complex entry counts twice): what tune's
    ``mode="auto"`` compares with ``FORWARD_MODE_MAX_SCALARS``."""
    return int(sum(np.size(x) * (2 if np.iscomplexobj(x) else 1) for x in leaves))


def _resolve_mode(mode, leaves0, simulate_kwargs, batch: int = 1) -> str:
    """``"forward"`` or ``"reverse"`` from tune's `mode`, the tuned leaves, a given adjoint, whether the
    steps are fixed and the number of scenarios `batch`."""
    if mode not in _MODES:
        raise ValueError(f"`mode` must be 'auto', 'forward' or 'reverse', got {mode!r}.")
    adjoint = simulate_kwargs.get("adjoint")
    forward_ok = adjoint is None or isinstance(
        adjoint, (diffrax.ForwardMode, diffrax.DirectAdjoint)
    )
    reverse_ok = not isinstance(adjoint, diffrax.ForwardMode)
    if mode == "forward" and not forward_ok:
        raise ValueError(
            "`mode='forward'` needs an adjoint that supports forward mode, but "
            f"`simulate_kwargs['adjoint']` is {type(adjoint).__name__}: drop it (tune then uses "
            "diffrax.ForwardMode()) or pass diffrax.ForwardMode() or diffrax.DirectAdjoint()."
        )
    if mode == "reverse" and not reverse_ok:
        raise ValueError(
            "`mode='reverse'` cannot differentiate through `simulate_kwargs['adjoint']` = "
            "diffrax.ForwardMode() (forward mode only): use mode='forward' or 'auto', or drop the "
            "adjoint."
        )
    if mode != "auto":
        return mode
    if not forward_ok:
        return "reverse"
    if not reverse_ok:
        return "forward"
    k = n_real_scalars(leaves0)
    if k > FORWARD_MODE_MAX_SCALARS:
        return "reverse"
    if not simulate_kwargs.get("adaptive", True) and k > 1 and k * batch > FIXED_STEP_FORWARD_MAX_WORK:
        return "reverse"
    return "forward"


# --------------------------------------------------------------------------------------------------
# Validation of tune's arguments (in the order a reader meets them in the signature)
# --------------------------------------------------------------------------------------------------


def _as_tuple(x):
    return tuple(x) if isinstance(x, (tuple, list)) else (x,)


def _is_int(x) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


def _check_types(
    observer, plant, where, loss, optimizer, steps, positive, rtol, patience, max_rejections
):
    _validate.check_observer(observer)
    _validate.check_plant(plant)
    if not callable(where):
        raise ValueError(
            f"`where` must be a callable selecting the tuned leaves (e.g. lambda o: o.poles), got "
            f"{type(where).__name__}."
        )
    if not callable(loss):
        raise ValueError(
            "`loss` must be a callable trajectory -> scalar (e.g. obsjax.losses.ise), got "
            f"{type(loss).__name__}."
        )
    if optimizer is not None and not (
        callable(getattr(optimizer, "init", None)) and callable(getattr(optimizer, "update", None))
    ):
        raise ValueError(
            "`optimizer` must be an optax.GradientTransformation (e.g. optax.adam(1e-2)) or None, "
            "got "
            f"{type(optimizer).__name__} {optimizer!r}."
        )
    if not _is_int(steps) or steps < 1:
        raise ValueError(
            f"`steps` (the budget of evaluations) must be an integer >= 1, got {steps!r} "
            f"({type(steps).__name__})."
        )
    if not isinstance(positive, (bool, np.bool_)):
        raise ValueError(f"`positive` must be True or False, got {positive!r}.")
    if rtol is not None and not (
        isinstance(rtol, (int, float, np.floating)) and 0 <= rtol < math.inf
    ):
        raise ValueError(
            f"`rtol` (the stopping rule's relative improvement) must be >= 0 or None, got {rtol!r}."
        )
    if not _is_int(patience) or patience < 1:
        raise ValueError(f"`patience` must be an integer >= 1, got {patience!r}.")
    if not _is_int(max_rejections) or max_rejections < 1:
        raise ValueError(f"`max_rejections` must be an integer >= 1, got {max_rejections!r}.")


def _check_data(plant, x0s, xhat0s, ts, noise, key, u, plant_batched, simulate_kwargs):
    x0s = as_float_array(x0s, "x0s")
    xhat0s = as_float_array(xhat0s, "xhat0s")
    if x0s.ndim != 2 or xhat0s.ndim != 2 or x0s.shape[0] != xhat0s.shape[0]:
        raise ValueError(
            "`x0s` and `xhat0s` must be (batch, n) with the same batch, got "
            f"{tuple(x0s.shape)} and "
            f"{tuple(xhat0s.shape)}."
        )
    if x0s.shape[0] < 1:
        raise ValueError(
            "`x0s` and `xhat0s` must hold at least one scenario (batch >= 1), got shapes "
            f"{tuple(x0s.shape)} and {tuple(xhat0s.shape)}."
        )
    if not plant_batched and x0s.shape[1] != plant.n:
        raise ValueError(
            f"`x0s` must be (batch, {plant.n}) for a plant with n = {plant.n}, got "
            f"{tuple(x0s.shape)}."
        )
    for name, arr in (("x0s", x0s), ("xhat0s", xhat0s)):
        if not np.all(np.isfinite(np.asarray(arr))):
            raise ValueError(f"`{name}` must be finite, got NaN or inf entries.")
    ts_np = np.asarray(_check_ts(ts), dtype=float)  # finite and strictly increasing
    _validate.check_noise(noise)
    if noise is not None and key is None:
        raise ValueError("`key` is required when `noise` is given.")
    if u is not None and not callable(u):
        raise ValueError(f"`u` must be a callable t -> (p,) or None, got {type(u).__name__}.")
    if plant_batched:
        sizes = {
            int(jnp.shape(leaf)[0]) if jnp.ndim(leaf) else -1
            for leaf in jax.tree_util.tree_leaves(eqx.filter(plant, eqx.is_array))
        }
        if sizes and sizes != {x0s.shape[0]}:
            raise ValueError(
                "`plant_batched=True` needs a leading axis of length batch = "
                f"{x0s.shape[0]} on every array "
                f"leaf of `plant`, found leading sizes {sorted(sizes)}."
            )
    if not isinstance(simulate_kwargs, dict):
        raise ValueError(
            f"`simulate_kwargs` must be a dict or None, got {type(simulate_kwargs).__name__}."
        )
    for bad in ("throw", "noise", "key", "max_segments", "u"):
        if bad in simulate_kwargs:
            raise ValueError(f"`simulate_kwargs` must not contain {bad!r}: tune sets it.")
    return x0s, xhat0s, ts_np


def _selected_leaves(observer, where):
    """The leaves `where` selects, checked to be array leaves stored in the observer."""
    try:
        selection = where(observer)
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"`where` failed on the observer: {type(e).__name__}: {e}") from None
    leaves = {id(leaf) for leaf in jax.tree_util.tree_leaves(observer)}
    for i, sel in enumerate(_as_tuple(selection)):
        what = "`where`" if not isinstance(selection, (tuple, list)) else f"`where` entry {i}"
        if sel is None:
            raise ValueError(
                f"{what} selects None (an unset optional field): select array-valued gains, e.g. "
                "lambda o: o.poles."
            )
        if not isinstance(sel, (jax.Array, np.ndarray)) or id(sel) not in leaves:
            kind = "a method" if callable(sel) else f"a {type(sel).__name__}"
            raise ValueError(
                f"{what} selects {kind} that is not an array leaf stored in the observer (a "
                "derived property such as `gain` or `observer_matrix` is recomputed from the "
                "stored gains and cannot be set): select the stored gains, e.g. "
                "lambda o: o.poles or lambda o: (o.gamma, o.T)."
            )
    _check_distinct(observer, where, selection)
    # strongly typed copies: a weakly typed leaf (jnp.asarray(1.0)) would retrace after the first
    # update (through NumPy: a dtype conversion by JAX compiles a program)
    leaves0 = tuple(_strong(leaf) for leaf in _as_tuple(selection))
    return leaves0, not isinstance(selection, (tuple, list))


@jax.jit
def _signed_exp(signs, theta):
    """leaf = sign · exp(θ), by XLA's exp as inside the kernel (one compiled program; NumPy's exp
    differs from it by an ulp in one value of seven, and the observer tune returns would not be the one
    it evaluated)."""
    return tuple(s * jnp.exp(t) for s, t in zip(signs, theta))


def _unused_keys(batch):
    """Keys of the shape and dtype of ``jr.split(key, batch)`` for a tune without noise, where the
    kernel reads none (zeros made by NumPy: drawing them would compile JAX's key programs)."""
    shape = jax.eval_shape(lambda: jr.split(jr.PRNGKey(0), batch))
    try:
        return device_array(np.zeros(shape.shape, shape.dtype))
    except TypeError:  # a typed key dtype (jax_enable_custom_prng): NumPy has no such dtype
        return jr.split(jr.PRNGKey(0), batch)


def _strong(leaf):
    """A strongly typed copy of a concrete leaf, by way of NumPy (`jnp.asarray` of a traced one)."""
    if isinstance(leaf, jax.core.Tracer):
        return jnp.asarray(leaf, dtype=jnp.asarray(leaf).dtype)
    return device_array(np.array(leaf))


class _Position:
    """A stand-in for one leaf position of the observer (one object per position)."""

    __slots__ = ()


def _check_distinct(observer, where, selection) -> None:
    """Refuse a `where` that selects one leaf position twice: ``eqx.tree_at`` would set it twice, the
    last assignment winning, and the other entry would be tuned and reported in the history but never
    used.  Positions are told apart as ``eqx.tree_at`` does, by applying `where` to the observer with
    a distinct stand-in at each leaf, so two fields that hold the same array object stay two leaves;
    should `where` fail on the stand-ins, the selected arrays are compared by identity."""
    picked = _as_tuple(selection)
    try:
        tagged = jax.tree_util.tree_map(lambda _: _Position(), observer)
        marks = _as_tuple(where(tagged))
        if len(marks) != len(picked) or not all(isinstance(m, _Position) for m in marks):
            raise TypeError
    except Exception:  # noqa: BLE001 - `where` needs the arrays themselves
        marks = picked
    first: dict[int, int] = {}
    for i, m in enumerate(marks):
        j = first.setdefault(id(m), i)
        if j != i:
            raise ValueError(
                f"`where` must select each leaf at most once, got entries {j} and {i} that are the "
                "same leaf of the observer: select it once."
            )


def _log_parametrisation(leaves0):
    """signs, θ0 with leaf = sign · exp(θ) (positive=True)."""
    signs, thetas = [], []
    for i, leaf in enumerate(leaves0):
        v = np.asarray(leaf)
        if np.iscomplexobj(v):
            raise ValueError(
                f"tuned leaf {i} is complex: use positive=False for complex parameters."
            )
        if np.any(v == 0):
            raise ValueError(
                f"tuned leaf {i} has zero entries {v.tolist()}: positive=True keeps signs through "
                "leaf = sign·exp(θ), so every entry must be nonzero."
            )
        if not np.all(np.isfinite(v)):
            raise ValueError(f"tuned leaf {i} must be finite, got {v.tolist()}.")
        # (host arithmetic: θ0 and the signs are concrete, and each JAX operation run eagerly compiles
        # a program on its first call in a process)
        signs.append(device_array(np.sign(v)))
        thetas.append(device_array(np.log(np.abs(v))))
    return tuple(signs), tuple(thetas)


# --------------------------------------------------------------------------------------------------
# Kinks: save times at reset instants
# --------------------------------------------------------------------------------------------------


def reset_coincidences(T, ts, rtol: float = 1e-8) -> list[float]:
    """Save times t_i (i ≥ 1) that coincide with a reset instant t0 + kT (k ≥ 1), to `rtol` of the
    period.

    At such a time the trajectory, hence the loss, has a kink (or a jump) in T: an infinitesimal
    change of T moves the reset to the other side of t_i, and autodiff returns the derivative from
    one side only."""
    ts = np.asarray(ts, dtype=float)
    T = float(np.asarray(T))
    if not (T > 0 and math.isfinite(T)):
        return []
    r = (ts[1:] - ts[0]) / T
    k = np.round(r)
    # plus the schedule's own time tolerance (the rounding of clock times such as 1.7e9 s, which merges a
    # reset with a save time the relative test alone did not see: 2 of 13 coincidences were reported)
    tol = _schedule.tolerance(ts[-1] - ts[0], max(abs(ts[0]), abs(ts[-1]))) / T
    hit = (k >= 1) & (np.abs(r - k) <= rtol * np.maximum(1.0, r) + tol)
    return [float(t) for t in ts[1:][hit]]


def _period_depends_on(build, theta, T0) -> bool:
    """Does the reset period change when the tuned leaves change?"""
    if T0 is None:
        return False
    bumped = tuple(device_array(t + 1e-3 * (np.abs(t) + 1.0)) for t in map(np.asarray, theta))
    try:
        T1 = build(bumped).reset_period
    except Exception:  # noqa: BLE001
        return True
    return T1 is None or not np.allclose(np.asarray(T1), np.asarray(T0), rtol=0.0, atol=0.0)


def _warn_kinks(obs, ts, step, warned) -> None:
    """`ts`: the save times, or a list of them (one per experiment, each with its own t0)."""
    T = obs.reset_period
    grids = ts if isinstance(ts, list) else [ts]
    hits = sorted({t for g in grids for t in reset_coincidences(T, g)})
    key = float(np.asarray(T))
    if hits and key not in warned:
        warned.add(key)
        shown = ", ".join(f"{t:g}" for t in hits[:5]) + (", ..." if len(hits) > 5 else "")
        warnings.warn(
            f"tune: at evaluation {step} the save times {shown} coincide with reset instants "
            f"t0 + kT of the observer (T = {key:.12g}); the loss has a kink in T there and "
            "autodiff returns one side of it at each such time (from the left inside the horizon, from the "
            "right at its end), so the derivative need not be either one-sided derivative of the loss. "
            "Choose T off the save grid "
            "(or save times off the multiples of T).",
            TuneWarning,
            stacklevel=3,
        )


# --------------------------------------------------------------------------------------------------
# tune
# --------------------------------------------------------------------------------------------------


def tune(
    observer,
    plant,
    *,
    where,
    loss,
    x0s,
    xhat0s,
    ts,
    optimizer=None,
    steps=100,
    positive=True,
    key=None,
    progress=True,
    noise=None,
    u=None,
    plant_batched=False,
    risk="mean",
    simulate_kwargs=None,
    rtol=None,
    patience=10,
    max_rejections=8,
    mode="auto",
) -> TuneResult:
    """Tune observer gains by gradient descent through simulated error trajectories.

    Minimises  J(θ) = risk_i [ loss(simulate(plant_i, observer(θ), x0_i, x̂0_i, ts, noise_i)) ]
    over the leaves selected by ``where``, with an optax optimizer, differentiating through the
    diffrax solves.

    **Arguments** (validated by tune itself, each bad one a ``ValueError`` naming it, so they carry
    no type annotations that a run-time type checker would enforce first):

    - `observer`: the observer to tune (its other leaves stay fixed).
    - `plant`: the true plant; with ``plant_batched=True`` every array leaf has a leading batch axis
      (sampled plants, model uncertainty) matching ``x0s``.
    - `where`: ``lambda obs: obs.poles`` or ``lambda obs: (obs.gamma, obs.T)``: the tuned leaves,
      which must be array leaves stored in the observer (not ``None``, not a derived property such
      as ``gain``), each selected once (``(o.gamma, o.gamma)`` is refused).
    - `loss`: trajectory -> real scalar, e.g. :func:`obsjax.losses.ise`.
    - `x0s`, `xhat0s`: (batch, n) initial states and estimates.
    - `ts`: save times (concrete, strictly increasing): the points where the loss sees the
      trajectory.
    - `optimizer`: optax transformation (default ``optax.adam(1e-2)``).
    - `steps`: the budget of evaluations of J and ∇J, the initial point and rejected points included
      (at most ``steps − 1`` updates).
    - `positive`: keep each tuned leaf's sign: leaf = sign(leaf₀)·exp(θ) (a reparametrisation, never
      clipping); gains, rates, periods stay positive and real poles stay in the left half-plane.
      Every tuned entry must then be nonzero.
    - `key`: PRNG key for the noise (fixed across steps: common random numbers give a smooth
      objective).
    - `noise`, `u`: passed to :func:`obsjax.simulate`.
    - `risk`: ``"mean"``, ``"worst"`` or ``("cvar", α)`` across the batch.
    - `simulate_kwargs`: extra keyword arguments of :func:`obsjax.simulate` (solver, rtol, dt0, …).
    - `rtol`, `patience`: the stopping rule.  With ``rtol`` given, tune stops (``converged=True``)
      once `patience` consecutive accepted points have not lowered the reference loss by more than
      ``rtol·|reference|``, the reference being the loss at the last such improvement; ``steps`` is
      then only a bound.  ``rtol=None`` (the default) runs the whole budget.
    - `max_rejections`: stop after this many consecutive rejected points (see below).
    - `mode`: how ∇J is computed: ``"reverse"`` (``jax.value_and_grad`` through the solves, with
      diffrax's default ``RecursiveCheckpointAdjoint``), ``"forward"`` (``jax.jacfwd``: one tangent
      per tuned real scalar, carried through the solves with ``diffrax.ForwardMode()``) or
      ``"auto"`` (the default): forward mode when the tuned leaves hold at most four real scalars
      (``FORWARD_MODE_MAX_SCALARS``; a complex entry counts twice; e.g. (γ, p0, T) or ε), reverse
      mode otherwise (a gain matrix, many poles); with fixed steps (``adaptive=False``) forward mode
      only for one scalar or when scalars × scenarios ≤ 192 (``FIXED_STEP_FORWARD_MAX_WORK``).  The
      cost of forward mode grows with the number of scalars, that of reverse mode does not; which
      one is cheaper per step also depends on the solve (``benchmarks/results/j_forward_gradient.md``):
      with adaptive steps forward mode was the cheaper up to 3–4 scalars (Chen & Yen's example,
      (γ, p0, T), masked kernel: 3.4× against 4.1× with 64 scenarios, 3.5× against 5.4× with 1024 on
      a loaded machine),
      and compiles in about half the time; fixed steps run as one ``lax.scan`` whose reverse pass
      costs about 3 forward passes, while each tangent costs more as the batch grows (3 scalars,
      1024 scenarios: 5.6× against 3.7× on Chen & Yen's example).  Both differentiate the same
      computation, so they agree to round-off.  An ``adjoint`` in ``simulate_kwargs``
      decides under ``"auto"`` (``diffrax.ForwardMode()`` forward, ``RecursiveCheckpointAdjoint``
      or ``BacksolveAdjoint`` reverse); one that cannot do the requested mode is refused.

    **Batch kernel.**  With adaptive steps of an explicit Runge–Kutta pair (the default Tsit5,
    Dopri5, …), ``max_steps`` set, no white noise, no observer events and an adjoint the loop
    implements, the scenarios are one ``simulate_batch(..., lockstep=False)`` (with
    ``plant_batched=True``, the same loop with one plant per scenario): each with its own adaptive
    steps on the masked Runge–Kutta loop, resets crossed inside one loop.  Otherwise they are ``jax.vmap`` of
    :func:`obsjax.simulate`.  Both solve each scenario as :func:`obsjax.simulate` does (the same
    tableau and step-size control, to rounding; the masked loop's step budget is ``max_steps`` per
    segment, shared by a scenario's segments), and both are differentiated in either mode.  On
    Chen & Yen's example with (γ, p0, T) tuned, a step of tune took 0.047 s on the masked kernel
    against 0.19 s on the vmap kernel (forward mode; 0.057 s against 0.23 s in reverse mode); on a
    linear plant without resets the masked kernel's reverse mode was the cheaper too, but its
    forward mode at 6 scalars was 1.2× dearer (``benchmarks/results/j_forward_gradient.md``).
    ``history["kernel"]`` says which one ran.

    **Guarantees.**  The arguments are checked before anything is traced (the objects and numbers
    first, then the data, then what ``where`` selects); each bad one raises ``ValueError`` naming it
    (a ``where`` that selects None or a derived property, an optimizer that is not an optax
    transformation, a float ``steps``, …).  A loss that does not return a real scalar is refused
    when the first evaluation is traced, before any step. The initial observer must be valid and
    give a finite loss.  Every later point is *accepted* only when the updated observer passes its
    ``check()`` (``eqx.tree_at`` skips ``__check_init__``, so what the observer's own ``check()``
    validates is caught there: e.g. a reset period, γ or p0 of :class:`obsjax.LeastSquaresReset`
    stepped to zero or below, filter poles of the adaptive observers (``MinimalAdaptiveObserver``,
    ``NonMinimalAdaptiveObserver``, ``Kreisselmeier``) or a ``KudvaNarendra`` K stepped out of the
    left half-plane; a :class:`obsjax.Luenberger` pole stepped into the right half-plane with
    ``positive=False`` is *not* refused by ``check()``, since an unstable observer is a valid one: such
    a point is accepted when its loss is finite, and only compares worse) and J and ∇J are
    finite (every trajectory has status 0).  A rejected point is recorded in the history, announced
    by a :class:`obsjax.TuneWarning`, and the step is retried from the last accepted point with the
    optimizer's update scaled by ``BACKTRACK`` = 1/2 (the optimizer's state is not advanced, and no
    point is evaluated twice); after an accepted point the scale grows back by 2, up to 1.  After
    ``max_rejections`` consecutive rejections (a scale of 2⁻⁸ with the default) tune stops with
    ``stop_reason="rejections"``.  Whatever the stop, the best accepted observer and the full
    history are returned.

    **Kinks.**  For an observer with a reset period T that is tuned (directly or through a leaf it
    depends on), a save time that coincides with a reset instant t0 + kT puts a kink (or, where the
    estimate jumps at resets, a jump) into J as a function of T, and autodiff takes one side of each
    (Chen & Yen's example, γ = 20, p0 = 0.1, x̂(0) = (5, −5), the ISE on a 0.1 s grid over [0, 10] at
    T = 2.3: autodiff −11.84, the left derivative, against −13.97 from the right).  The side is the
    left one at a save time inside the horizon and the right one at its end t1 (no reset is applied
    there), so where both occur the derivative is neither one-sided derivative of J (a review: 0.553
    against 0.581 from the left and −0.409 from the right, with a reset instant at t1 = 12 T).  tune detects such coincidences at every accepted point and warns
    (:class:`obsjax.TuneWarning`); move T or the save times off each other's grid.  See
    :func:`reset_coincidences`.  A reset instant on a plant's jump time (a switching plant with T a
    multiple of its period) is a kink too; every back-end returns the derivative from below there
    (the reset just before the jump).

    **Band-limited noise and a tuned T.**  The noise path is piecewise linear, with a kink every
    ``noise.dt``, and adaptive steps cross those kinks.  A step that crosses one is not
    differentiated accurately with respect to its own position, so the steps must not move with T:
    both kernels keep their steps where they are and move each reset instant by the jump condition
    (the state leaving t0 + kT gains δT·k·(∂reset/∂y f⁻ − f⁺), f∓ the vector field on either side),
    as the fixed-step path does.  Chen & Yen's example (γ = 20, p0 = 0.1, T = 0.33, σ = 0.05,
    ``dt`` = 0.05, three scenarios, ISE over [0, 2.9]; central differences of tight solves −28.5):

    | solve (atol = rtol / 100) | ∂J/∂T | before (steps moving with T) |
    |---|---|---|
    | adaptive, rtol 1e-6 (the default) | −28.50 | −36.3 |
    | adaptive, rtol 1e-8 | −28.48 | −32.3 |
    | adaptive, rtol 1e-12 | −28.48 | −28.6 |
    | fixed steps, h = dt/4 | −28.5 | −30.0 |

    The derivatives in the other gains (γ, p0, …) were never affected: they agreed to 5 digits between
    rtol 1e-6 and 1e-12.

    **White noise and a tuned T.**  Under :class:`obsjax.noise.WhiteNoise` the measurement enters the
    estimate as a Brownian increment, and moving a reset by δT changes the estimate by O(√δT) on each
    path: the pathwise loss has no derivative in T (Chen & Yen's example, per path central differences at
    h = 1e-2 … 3e-4 do not converge).  tune refuses such a problem with a ``ValueError`` before
    compiling; use band-limited noise, or tune the other gains with T fixed.

    Observers with a reset period T are simulated with a number of segments recomputed from the
    current T (a retrace happens only when it grows past a power-of-two bucket).

    The gradient is compiled once per problem structure and reused across calls: calls that differ
    only in array values (initial gains, scenario batches of the same size, the risk measure, which
    enters as weights on the sorted losses, see :func:`risk_weights`) do not recompile, provided
    they pass the same ``where`` and ``loss`` objects (a lambda written inside a loop is a new
    object each time).

    **Returns:** :class:`TuneResult` (`observer`, `history`, `converged`, `stop_reason`,
    `steps_taken`); ``history["mode"]`` says which mode computed the gradients, ``history["kernel"]``
    which batch kernel (``"masked"`` or ``"vmap"``) simulated the scenarios.

    **Example:**::

        obs = obsjax.Luenberger.from_poles(plant, [-1.0, -1.2])
        res = obsjax.tune(obs, plant, where=lambda o: o.poles, loss=obsjax.losses.ise, x0s=x0s,
                          xhat0s=jnp.zeros_like(x0s), ts=jnp.linspace(0, 5, 51),
                          optimizer=optax.adam(0.1), steps=200, rtol=1e-4, patience=10)
        res.observer.poles, res.converged, res.stop_reason
    """
    require_x64("obsjax.tune")
    _check_types(
        observer, plant, where, loss, optimizer, steps, positive, rtol, patience, max_rejections
    )
    simulate_kwargs = {} if simulate_kwargs is None else simulate_kwargs
    if isinstance(simulate_kwargs, dict):
        simulate_kwargs = _validate.plain_int_kwargs(simulate_kwargs)
    x0s, xhat0s, ts_np = _check_data(
        plant, x0s, xhat0s, ts, noise, key, u, plant_batched, simulate_kwargs
    )
    batch = x0s.shape[0]
    weights = device_array(risk_weights(risk, batch))
    leaves0, single = _selected_leaves(observer, where)
    mode = _resolve_mode(mode, leaves0, simulate_kwargs, batch)
    kernel = batch_kernel(
        observer, ts_np, plant_batched=plant_batched, noise=noise, mode=mode,
        simulate_kwargs=simulate_kwargs,
    )  # fmt: skip
    optimizer = optax.adam(1e-2) if optimizer is None else optimizer
    keys = _unused_keys(batch) if key is None else jr.split(key, batch)

    if positive:
        signs, theta0 = _log_parametrisation(leaves0)

        def to_leaves(theta):  # (the kernel has its own)
            return _signed_exp(signs, tuple(theta))
    else:
        signs, theta0 = None, leaves0

        def to_leaves(theta):
            return tuple(theta)

    def build(theta):
        new = to_leaves(theta)
        return eqx.tree_at(where, observer, new[0] if single else new)

    depends = _period_depends_on(build, theta0, build(theta0).reset_period)
    if depends and isinstance(noise, WhiteNoise):
        raise ValueError(
            "tune: `where` selects the observer's reset period (directly or through a leaf it depends on), "
            f"and {_diffrax.WHITE_NOISE_TIMES}"
        )

    span = float(ts_np[-1] - ts_np[0])
    spec_kwargs = tuple(sorted(simulate_kwargs.items()))
    ts_key = tuple(float(v) for v in ts_np)
    seg_bucket = [None]  # only ever grows: a shrinking T would otherwise trigger a recompilation
    first_call = [True]
    # the kernel is keyed on its static arguments, functions by identity: a loss, input or plant function
    # that reads a global changed since the last call must be traced again (see `content_key`)
    content = content_key((where, loss, u, noise, observer, plant, spec_kwargs))

    def evaluate(theta):
        """(observer, J, ∇J, None) at an acceptable point, or (None, J or NaN, None, reason)."""
        try:
            obs = build(theta).check()
        except (
            ValueError,
            RuntimeError,
        ) as e:  # RuntimeError: an eqx.error_if run eagerly by check()
            return None, math.nan, None, f"the observer is invalid: {_checked_message(e)}"
        T = obs.reset_period
        if T is not None:
            ns = num_segments(T, 0.0, span)
            need = int(2 ** math.ceil(math.log2(max(ns, 1))))
            seg_bucket[0] = need if seg_bucket[0] is None else max(seg_bucket[0], need)
        spec = (
            where, loss, single, plant_batched, noise, u, seg_bucket[0], spec_kwargs, ts_key, mode,
            kernel, content,
        )  # fmt: skip
        try:
            # the kernel's runtime checks as NaN (a firing check rejects the step): no host
            # callbacks, so the compiled kernel can be saved to the persistent compilation cache
            with runtime_checks_as_nan():
                val, grads = _value_and_grad(
                    theta, signs, observer, plant, x0s, xhat0s, keys, weights, spec
                )
            val = float(val)
        except (ValueError, RuntimeError) as e:
            # an eqx.error_if that fired at run time (JAX raises it as a RuntimeError, or as a
            # ValueError from a cached kernel), or a retrace refused for this point; at the initial
            # point: re-raised
            if first_call[0]:
                raise
            return None, math.nan, None, f"a check failed while simulating: {_checked_message(e)}"
        finally:
            first_call[0] = False
        if not math.isfinite(val):
            return None, val, None, "the loss is not finite (a trajectory failed or diverged)"
        if not all(np.all(np.isfinite(np.asarray(g))) for g in grads):
            # the kernel's checks are NaN here: a check that fired only in the derivative (a gain
            # without a derivative at this point, e.g. a robust placement whose minimiser is not
            # isolated) leaves the loss finite and the gradient NaN
            return None, val, None, (
                "the gradient is not finite (a trajectory's derivative overflowed, or a check fired "
                "while differentiating: e.g. Luenberger poles placed with method='robust' where that "
                "gain has no derivative; jax.grad of the same loss through simulate raises the "
                "check's message)"
            )
        return obs, val, grads, None

    result = _descend(
        evaluate, depends, to_leaves, theta0, optimizer, steps, rtol, patience, max_rejections, ts_np,
        progress,
    )  # fmt: skip
    result.history["mode"] = mode
    result.history["kernel"] = kernel
    return result


def _checked_message(e: Exception) -> str:
    """The message of a check that fired inside a compiled kernel, without JAX's traceback."""
    text = str(e)
    for line in text.splitlines():
        line = line.strip()
        if line.startswith(
            (
                "equinox._errors._EquinoxRuntimeError:",
                "_EquinoxRuntimeError:",
                "EquinoxRuntimeError:",
            )
        ):
            return line.split(":", 1)[1].strip()
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return lines[0] if lines else type(e).__name__


def _descend(
    evaluate,
    depends,
    to_leaves,
    theta0,
    optimizer,
    steps,
    rtol,
    patience,
    max_rejections,
    ts,
    progress,
):
    """The optimisation loop of :func:`tune`: optax updates, backtracking, a stopping rule.
    `depends`: whether the reset period moves with θ (then save times on reset instants warn)."""
    obs, val, grads, why = evaluate(theta0)
    if why is not None:
        raise ValueError(
            f"tune: the initial observer cannot be tuned from: {why}. Check the initial gains, "
            "x0s, xhat0s and the loss."
        )
    warned: set = set()
    if depends:
        _warn_kinks(obs, ts, 0, warned)
    hist_loss, hist_params, accepted, scales, rejections = (
        [val],
        [to_leaves(theta0)],
        [True],
        [1.0],
        [],
    )
    best = (val, obs, 0)
    reference, since = val, 0
    theta, opt_state = theta0, optimizer.init(theta0)
    update = jax.jit(optimizer.update)
    scale, in_row, stop_reason = 1.0, 0, "steps"
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=steps, initial=1, desc="tune", leave=False)
    while len(hist_loss) < steps and stop_reason == "steps":
        updates, new_state = update(grads, opt_state, theta)
        while len(hist_loss) < steps:
            # on the host (a few scalars; eager JAX operations would each compile a program)
            cand = tuple(
                device_array(np.asarray(t) + scale * np.asarray(d)) for t, d in zip(theta, updates)
            )
            if all(np.array_equal(np.asarray(c), np.asarray(t)) for c, t in zip(cand, theta)):
                if scale == 1.0:  # the optimizer's own step is zero: a stationary point
                    stop_reason = "stationary"
                    warnings.warn(
                        "tune: the optimizer's update no longer changes the gains (a stationary "
                        "point, e.g. a zero gradient: is the loss flat in the tuned gains?); stopping.",
                        TuneWarning,
                        stacklevel=3,
                    )
                    break
                stop_reason = "rejections"  # the scaled step no longer moves θ
                warnings.warn(
                    f"tune: the step scaled by {scale:g} no longer changes the gains; stopping.",
                    TuneWarning,
                    stacklevel=3,
                )
                break
            obs_c, val_c, grads_c, why = evaluate(cand)
            hist_loss.append(val_c if why is None else math.nan)
            hist_params.append(to_leaves(cand))
            accepted.append(why is None)
            scales.append(scale)
            if bar is not None:
                bar.update(1)
            if why is None:
                theta, opt_state, grads, val = cand, new_state, grads_c, val_c
                scale, in_row = min(1.0, scale / BACKTRACK), 0
                if val < best[0]:
                    best = (val, obs_c, len(hist_loss) - 1)
                if depends:
                    _warn_kinks(obs_c, ts, len(hist_loss) - 1, warned)
                if bar is not None:
                    bar.set_postfix(loss=f"{val:.4g}")
                break
            rejections.append((len(hist_loss) - 1, why))
            in_row += 1
            scale *= BACKTRACK
            if in_row >= max_rejections:
                stop_reason = "rejections"
                then = (
                    f"{in_row} consecutive rejections: stopping with the best observer "
                    f"(evaluation {best[2]})"
                )
            else:
                then = f"retrying from the last accepted point with the step scaled by {scale:g}"
            warnings.warn(
                f"tune: evaluation {len(hist_loss) - 1} rejected ({why}); {then}.",
                TuneWarning,
                stacklevel=3,
            )
            if stop_reason != "steps":
                break
        if stop_reason != "steps" or not accepted[-1]:
            break  # stopped, or the budget ran out during a backtracking
        if rtol is not None:
            if val < reference - rtol * abs(reference):
                reference, since = val, 0
            else:
                since += 1
                if since >= patience:
                    stop_reason = "converged"
    if bar is not None:
        bar.close()
    history = {
        "loss": np.asarray(hist_loss),
        "params": [np.stack([np.asarray(p[i]) for p in hist_params]) for i in range(len(theta0))],
        "accepted": np.asarray(accepted),
        "step_scale": np.asarray(scales),
        "rejections": rejections,
        "skipped": len(rejections),
        "best_step": best[2],
    }
    return TuneResult(
        observer=best[1],
        history=history,
        converged=stop_reason in ("converged", "stationary"),
        stop_reason=stop_reason,
        steps_taken=len(hist_loss),
    )
