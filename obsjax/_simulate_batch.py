"""A batch of trajectories of one plant-observer pair, adaptively integrated in lock step."""

from __future__ import annotations

from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._checks import as_float_array, concrete_value
from ._config import require_x64
from ._simulate import (
    NONFINITE,
    SOLVER_FAILED,
    SUCCESS,
    Trajectory,
    _Args,
    _check_ts,
    _concrete_span,
    _drift,
    _segmented,
    _signals,
    _zeros_input,
    simulate,
)
from .observers._base import AbstractObserver
from .systems._noise import AbstractNoise, BandLimitedNoise, WhiteNoise, realise_band_limited
from .systems._plants import AbstractSystem


def _member_rms(y):
    """Root mean square of each batch member over all leaves of a pytree with leading batch axis, (B,)."""
    leaves = jax.tree_util.tree_leaves(y)
    ss = sum(jnp.sum(jnp.abs(leaf.reshape(leaf.shape[0], -1)) ** 2, axis=1) for leaf in leaves)
    count = sum(int(np.prod(leaf.shape[1:])) for leaf in leaves)
    return jnp.sqrt(ss / count)


def lockstep_norm(y):
    """Error norm of a lock-step batch: max over members of each member's RMS (non-finite members ignored).

    diffrax's PID controller accepts a step when this is ≤ 1, so every member meets rtol/atol on every step,
    exactly the test a member's own solve applies.  A member that has produced non-finite values is left out,
    so one diverging trajectory does not stall the others (it ends with status 2).
    """
    r = _member_rms(y)
    return jnp.max(jnp.where(jnp.isfinite(r), r, 0.0))


def simulate_batch(
    plant,
    observer,
    x0s,
    xhat0s,
    ts,
    *,
    keys=None,
    u: Callable | None = None,
    controller: Callable | None = None,
    noise: AbstractNoise | None = None,
    solver: diffrax.AbstractSolver | None = None,
    rtol: float = 1e-6,
    atol: float = 1e-8,
    dt0: float | None = None,
    adaptive: bool = True,
    max_steps: int | None = 16384,
    max_segments: int | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    lockstep: bool = True,
    throw: bool = True,
) -> Trajectory:
    """Simulate a batch of initial conditions (and noise keys) of one plant and observer.

    With ``lockstep=True`` (the default) and an adaptive solve, the batch is one ODE: the joint state (x, z) of
    all B members is stacked, the vector field is ``jax.vmap``-ed over members, and diffrax's PID controller
    judges a step by :func:`lockstep_norm`, the largest member error, so every member meets ``rtol``/``atol``
    on every step.  All members take the steps of the most demanding one (the lock-step waste, batch × steps ÷
    Σ own steps, is small when members are alike, ≈ 1.2–1.4 for Chen & Yen's example), but the solver's
    bookkeeping (step-size control, saving, the while loop) runs once per step for the whole batch instead of
    once per member per step as under ``jax.vmap(simulate)``, where every member's solver state is carried
    and selected in the vmapped while loop.  On the CPU that makes the batch several times faster
    (benchmarks/results/a_chen_yen_throughput.md).

    With ``lockstep=False``, with fixed steps (``adaptive=False``, already lock step) or with white noise
    (a fixed-step SDE), this is ``jax.vmap`` of :func:`obsjax.simulate` over the members.

    **Arguments:** as :func:`obsjax.simulate`, except

    - `x0s`, `xhat0s`: (B, n) initial plant states and estimates.
    - `keys`: (B,) PRNG keys, one per member, required with `noise` (each member draws its own noise).
    - `lockstep`: see above.

    **Returns:** a :class:`obsjax.Trajectory` whose fields have a leading batch axis B (as from
    ``jax.vmap(simulate)``); ``status`` is per member: a solver failure of the shared solve fails every
    member (status 1), a non-finite member only itself (status 2).

    **Example:**::

        plant, obs = obsjax.chen_yen_example()
        x0s = jax.random.normal(jax.random.key(0), (1024, 2))
        traj = obsjax.simulate_batch(plant, obs, x0s, jnp.zeros((1024, 2)), jnp.linspace(0., 10., 41))
        traj.error_norm.shape  # (1024, 41)
    """
    require_x64("obsjax.simulate_batch")
    if not isinstance(plant, AbstractSystem):
        raise ValueError(f"`plant` must be an obsjax plant (LTI, LTV, Nonlinear), got {type(plant).__name__}.")
    if not isinstance(observer, AbstractObserver):
        raise ValueError(f"`observer` must be an obsjax observer, got {type(observer).__name__}.")
    x0s = as_float_array(x0s, "x0s")
    xhat0s = as_float_array(xhat0s, "xhat0s")
    if x0s.ndim != 2 or x0s.shape[1] != plant.n:
        raise ValueError(f"`x0s` must have shape (B, {plant.n}) (a batch of plant states), got {tuple(x0s.shape)}.")
    if xhat0s.ndim != 2 or xhat0s.shape[0] != x0s.shape[0]:
        raise ValueError(
            f"`xhat0s` must have shape ({x0s.shape[0]}, n̂) (one estimate per member of `x0s`), got "
            f"{tuple(xhat0s.shape)}."
        )
    B = x0s.shape[0]
    if noise is not None:
        if keys is None:
            raise ValueError("`keys` (one PRNG key per member) is required when `noise` is given.")
        if jnp.shape(keys)[:1] != (B,):
            raise ValueError(f"`keys` must hold {B} keys (one per member), got shape {tuple(jnp.shape(keys))}.")

    common = dict(
        u=u, controller=controller, noise=noise, solver=solver, rtol=rtol, atol=atol, dt0=dt0,
        adaptive=adaptive, max_steps=max_steps, max_segments=max_segments, adjoint=adjoint, throw=throw,
    )
    if not lockstep or not adaptive or isinstance(noise, WhiteNoise):
        if noise is None:
            return jax.vmap(lambda a, b: simulate(plant, observer, a, b, ts, **common))(x0s, xhat0s)
        return jax.vmap(lambda a, b, k: simulate(plant, observer, a, b, ts, key=k, **common))(x0s, xhat0s, keys)

    ts_np = concrete_value(ts)
    ts = _check_ts(ts)
    observer = observer.prepare()
    t0, t1 = ts[0], ts[-1]
    noise_paths = None
    if isinstance(noise, BandLimitedNoise):
        t0c, t1c = _concrete_span(ts_np)
        noise_paths = eqx.filter_vmap(lambda k: realise_band_limited(noise, k, t0c, t1c, plant.m))(keys)
    elif noise is not None:
        raise ValueError(f"`noise` must be WhiteNoise or BandLimitedNoise, got {type(noise).__name__}.")

    def per_member(fn, ctx):
        """vmap of fn(args, *batched) over members; ctx = (plant, observer, noise paths or None)."""
        pl, ob, paths = ctx
        if paths is None:
            return jax.vmap(lambda *a: fn(_Args(pl, ob, u, controller, None), *a))
        return lambda *a: eqx.filter_vmap(lambda path, *b: fn(_Args(pl, ob, u, controller, path), *b))(paths, *a)

    ctx = (plant, observer, noise_paths)

    def member_init(args, x0, xh0):
        u0 = _zeros_input(plant) if u is None else jnp.asarray(u(t0)).reshape(plant.p)
        v0 = 0.0 if args.noise_path is None else args.noise_path(t0)
        return observer.init(t0, xh0, plant.h(t0, x0, u0) + v0)

    z0s = per_member(member_init, ctx)(x0s, xhat0s)
    if jax.tree_util.tree_leaves(z0s)[0].shape[0] != B:
        raise ValueError("the observer state must have a leading batch axis after vmapping `init`.")

    def drift_b(t, state, ctx):
        x, z = state
        return per_member(lambda args, xx, zz: _drift(t, (xx, zz), args), ctx)(x, z)

    if solver is None:
        pick = getattr(observer, "recommended_solver", None)
        solver = pick(ts_np) if pick is not None else diffrax.Tsit5()
    ctrl = diffrax.PIDController(rtol=rtol, atol=atol, norm=lockstep_norm)
    if plant.jumps is not None:
        ctrl = diffrax.ClipStepSizeController(ctrl, jump_ts=plant.jumps)
    term = diffrax.ODETerm(drift_b)

    def solve(s0, s1, state, save_ts):
        sol = diffrax.diffeqsolve(
            term, solver, s0, s1, dt0, state, args=ctx,
            saveat=diffrax.SaveAt(ts=save_ts, t1=True),
            stepsize_controller=ctrl, max_steps=max_steps, throw=False,
            **({} if adjoint is None else {"adjoint": adjoint}),
        )
        return sol.ys, sol.result == diffrax.RESULTS.successful

    state0 = (x0s, z0s)
    T = observer.reset_period
    if T is None:
        ys, ok = solve(t0, t1, state0, ts)
        xs, zs = jax.tree_util.tree_map(lambda a: a[:-1], ys)
    else:
        reset_b = lambda t, z: jax.vmap(lambda zz: observer.reset(t, zz))(z)
        xs, zs, ok = _segmented(reset_b, solve, state0, ts, T, max_segments, ts_np)
    # (T, B, ...) -> (B, T, ...)
    xs, zs = jax.tree_util.tree_map(lambda a: jnp.swapaxes(a, 0, 1), (xs, zs))

    def outputs(args, x_t, z_t):
        y, xhat = jax.vmap(lambda t, x, z: _signals(args, t, x, z)[1:])(ts, x_t, z_t)
        return y, xhat, xhat - jax.vmap(observer.target)(ts, x_t)

    y_s, xhat_s, error = per_member(outputs, ctx)(xs, zs)
    finite = jnp.all(jnp.isfinite(error).reshape(B, -1), axis=1) & jnp.all(jnp.isfinite(y_s).reshape(B, -1), axis=1)
    status = jnp.where(ok, jnp.where(finite, SUCCESS, NONFINITE), SOLVER_FAILED).astype(jnp.int32)
    if throw:
        error = eqx.error_if(
            error,
            jnp.any(status == SOLVER_FAILED),
            "obsjax.simulate_batch: the lock-step solve did not reach the end of the horizon (max_steps reached "
            "or step size underflow). Raise `max_steps`, loosen `rtol`/`atol`, or pass throw=False.",
        )
        error = eqx.error_if(
            error,
            jnp.any(status == NONFINITE),
            "obsjax.simulate_batch: a trajectory contains non-finite values. Pass throw=False to get a "
            "per-trajectory status instead.",
        )
    return Trajectory(
        ts=jnp.broadcast_to(ts, (B,) + ts.shape), x=xs, xhat=xhat_s, y=y_s, error=error, z=zs, status=status
    )
