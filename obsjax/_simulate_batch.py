"""A batch of trajectories of one plant-observer pair, adaptively integrated in lock step."""

from __future__ import annotations

from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _integrate
from ._config import require_x64
from ._integrate import _compiled, _masked, _validate
from ._integrate._lockstep import lockstep_norm, per_member
from ._integrate._status import NONFINITE, is_finite
from ._integrate._system import initial_state
from ._integrate._system import with_content as _with_content
from ._simulate import Trajectory, _raise_if, simulate, trajectory

__all__ = ["lockstep_norm", "simulate_batch"]
from .systems._noise import AbstractNoise, BandLimitedNoise, WhiteNoise, realise_band_limited


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
    rtol: float | jax.Array = 1e-6,
    atol: float | jax.Array = 1e-8,
    dt0: float | jax.Array | None = None,
    adaptive: bool = True,
    max_steps: int | np.integer | None = 16384,
    max_segments: int | np.integer | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    lockstep: bool = True,
    throw: bool = True,
) -> Trajectory:
    """Simulate a batch of initial conditions (and noise keys) of one plant and observer.

    With ``lockstep=True`` (the default) and an adaptive solve, the batch is one ODE: the joint state (x, z) of
    all B members is stacked, the vector field is ``jax.vmap``-ed over members, and a step is accepted when
    every participating member meets ``rtol``/``atol`` (the largest member error, :func:`lockstep_norm`).
    All members take the steps of the most demanding one (the lock-step waste, batch × steps ÷ Σ own steps,
    is small when members are alike, ≈ 1.2–1.4 for Chen & Yen's example), but the solver's bookkeeping
    (step-size control, saving, the while loop) runs once per step for the whole batch instead of once per
    member per step as under ``jax.vmap(simulate)``.  On the CPU that makes the batch several times faster
    (benchmarks/results/a_chen_yen_throughput.md).

    **Failure isolation.**  One member never decides the fate of the others: a member that becomes
    non-finite stops taking part in the step control, and one that alone would force the shared step below
    (t1 − t0)/max_steps while the median member would not is evicted from it.  Every such member (and every
    member, if the shared solve itself fails) is then integrated again alone, exactly as
    :func:`obsjax.simulate` would, and gets that result and status; the others keep their lock-step result.

    **Derivative in a reset period.**  With a traced reset period T (or traced event times), the steps of
    every back-end stay where they are and each breakpoint τ moves the state by the jump condition
    y⁺ + δτ (∂R/∂t + ∂R/∂y f⁻ − f⁺), the first-order motion of the exact solution, so dJ/dT is accurate
    to the tolerance even under band-limited noise, whose kinks the steps cross (Chen & Yen's example,
    three members, σ = 0.05, T = 0.33, rtol 1e-6: lock step −28.496, own steps −28.503, against −28.500
    from central differences of tight solves; with steps that moved with T the lock-step batch gave
    −32.75).

    With ``lockstep=False`` every member takes its own steps, as under ``jax.vmap`` of
    :func:`obsjax.simulate`. When the solver is an explicit Runge–Kutta pair with an error estimate (Tsit5,
    Dopri5, Bosh3, Dopri8, …), the observer has no event times, ``max_steps`` is set and the adjoint is
    diffrax's default, ``ForwardMode`` or ``DirectAdjoint``, the batch runs on a masked adaptive Runge–Kutta
    loop instead: one loop in which each member steps with its own step size and PID history (diffrax's
    tableau and controller), crosses its own resets and jumps, and is masked once finished, so the loop's
    bookkeeping is paid once per iteration for the whole batch; on the CPU a large batch runs in blocks of
    members whose arrays stay in the cache (2.0× the throughput of ``jax.vmap(simulate)`` on one CPU core for
    Chen & Yen's example: benchmarks/results/g_numba_dopri5.md). Member by member it is the solve of
    :func:`obsjax.simulate` (first step 0.01 when `dt0` is not given, ``max_steps`` per segment, the same
    status codes), up to rounding and the step choices near save times. In reverse mode a step that is
    rejected because its stages left the domain of the vector field (a step across an undeclared switch into a
    region where the field is NaN) contributes zero to the gradient, as in :func:`obsjax.simulate` and the
    lock-step batch (its cotangent is zero, its partial derivatives NaN). Other problems are
    ``jax.vmap(simulate)``. With fixed steps (``adaptive=False``, already lock step) or with white noise (a
    fixed-step SDE), this is ``jax.vmap`` of :func:`obsjax.simulate` over the members.

    **Arguments:** as :func:`obsjax.simulate`, except

    - `x0s`, `xhat0s`: (B, n) initial plant states and estimates.
    - `keys`: (B,) PRNG keys, one per member, required with `noise` (each member draws its own noise) and
      refused without it.
    - `lockstep`: see above.

    **Returns:** a :class:`obsjax.Trajectory` whose fields have a leading batch axis B (as from
    ``jax.vmap(simulate)``); ``status`` is per member, with the meaning of :func:`obsjax.simulate`'s.

    **Example:**::

        plant, obs = obsjax.chen_yen_example()
        x0s = jax.random.normal(jax.random.key(0), (1024, 2))
        traj = obsjax.simulate_batch(plant, obs, x0s, jnp.zeros((1024, 2)), jnp.linspace(0., 10., 41))
        traj.error_norm.shape  # (1024, 41)
    """
    require_x64("obsjax.simulate_batch")
    return _simulate_members(
        plant, observer, x0s, xhat0s, ts, keys, lockstep=lockstep, plant_batched=False,
        u=u, controller=controller, noise=noise, solver=solver, rtol=rtol, atol=atol, dt0=dt0, adaptive=adaptive,
        max_steps=max_steps, max_segments=max_segments, adjoint=adjoint, throw=throw,
    )


def simulate_plants(plants, observer, x0s, xhat0s, ts, *, keys=None, **kwargs) -> Trajectory:
    """Member b: plant b with the shared `observer`, from (x0s[b], xhat0s[b]) (and keys[b] with noise).

    Every array leaf of `plants` has a leading axis B (a batch of plants, e.g. drawn by ``jax.vmap`` of a
    parameter sampler; the static fields, among them ``jump_ts``, are shared).  Each member takes its own
    adaptive steps, as ``simulate_batch(..., lockstep=False)``: on the masked adaptive Runge–Kutta loop where
    the problem allows it (see :func:`simulate_batch`), else ``jax.vmap(simulate)`` over plants, initial
    states and keys.  Member by member it is :func:`obsjax.simulate` on that member's plant (to rounding and
    the step choices near save times).  `kwargs`: :func:`obsjax.simulate`'s options.  Used by ``tune``
    (``plant_batched=True``) and ``monte_carlo`` (``param_sampler``).
    """
    require_x64("obsjax.simulate_batch")
    return _simulate_members(plants, observer, x0s, xhat0s, ts, keys, lockstep=False, plant_batched=True,
                             **kwargs)


def _first_plant(plants, B):
    """Member 0 of a batch of plants (the one the shapes and the schedule are checked on)."""
    for leaf in jax.tree_util.tree_leaves(plants):
        if eqx.is_array(leaf) and (jnp.ndim(leaf) == 0 or jnp.shape(leaf)[0] != B):
            raise ValueError(
                f"every array of the batch of plants must have a leading axis of length {B} (one plant per "
                f"member), got an array of shape {tuple(jnp.shape(leaf))}."
            )
    return jax.tree_util.tree_map(lambda a: a[0] if eqx.is_array(a) else a, plants)


def _simulate_members(plant, observer, x0s, xhat0s, ts, keys, *, lockstep, plant_batched, u=None,
                      controller=None, noise=None, solver=None, rtol=1e-6, atol=1e-8, dt0=None, adaptive=True,
                      max_steps=16384, max_segments=None, adjoint=None, throw=True):
    max_steps, max_segments = _validate.plain_int(max_steps), _validate.plain_int(max_segments)
    if plant_batched:
        x0s = _validate.check_state(x0s, "x0s", "(B, n) (a batch of plant states)", 2)
        plant0 = _first_plant(plant, x0s.shape[0])
    else:
        plant0 = plant
    _validate.check_types(plant0, observer, noise)
    x0s = _validate.check_state(x0s, "x0s", f"(B, {plant0.n}) (a batch of plant states)", 2)
    B = x0s.shape[0]
    xhat0s = _validate.check_state(xhat0s, "xhat0s", f"({B}, n̂) (one estimate per member)", 2)
    if x0s.shape[1] != plant0.n:
        raise ValueError(f"`x0s` must have shape (B, {plant0.n}) (a batch of plant states), got {tuple(x0s.shape)}.")
    if xhat0s.shape[0] != B:
        raise ValueError(
            f"`xhat0s` must have shape ({B}, n̂) (one estimate per member of `x0s`), got "
            f"{tuple(xhat0s.shape)}."
        )
    if B == 0:
        raise ValueError(f"`x0s` must hold at least one member, got shape {tuple(x0s.shape)}.")
    n_obs = _validate.estimate_dim(observer)
    if n_obs is not None and xhat0s.shape[1] != n_obs:
        raise ValueError(
            f"`xhat0s` must have shape ({B}, {n_obs}) (one estimate per member, of the observer's state "
            f"dimension {n_obs}), got {tuple(xhat0s.shape)}."
        )
    _validate.check_keys_need_noise(noise, keys, "keys")
    if noise is not None:
        if keys is None:
            raise ValueError("`keys` (one PRNG key per member) is required when `noise` is given.")
        if jnp.shape(keys)[:1] != (B,):
            raise ValueError(f"`keys` must hold {B} keys (one per member), got shape {tuple(jnp.shape(keys))}.")

    common = dict(
        u=u, controller=controller, noise=noise, solver=solver, rtol=rtol, atol=atol, dt0=dt0,
        adaptive=adaptive, max_steps=max_steps, max_segments=max_segments, adjoint=adjoint, throw=throw,
    )
    if not adaptive or isinstance(noise, WhiteNoise):
        return _vmap_simulate(plant, observer, x0s, xhat0s, ts, keys, common, plant_batched)

    ts_np = _validate.concrete_times(ts)
    ts = _validate.check_ts(ts)
    dt0 = _validate.check_options(rtol, atol, dt0, adaptive, max_steps, noise)
    observer = observer.prepare()
    observer = _validate.check_span(observer, ts_np)
    _validate.check_dimensions(plant0, observer, x0s[0], xhat0s[0], ts[0], u, controller, noise)
    plan = _validate.plan(
        plant0, observer, ts, ts_np, noise=noise, key=None, solver=solver, rtol=rtol, atol=atol, dt0=dt0,
        adaptive=True, max_steps=max_steps, max_segments=max_segments, adjoint=adjoint,
    )
    if not lockstep and not _masked.eligible(plan):
        return _vmap_simulate(plant, observer, x0s, xhat0s, ts, keys, common, plant_batched)
    paths = None
    if isinstance(noise, BandLimitedNoise):
        t0c, t1c = _validate.concrete_span(ts_np)
        paths = eqx.filter_vmap(lambda k: realise_band_limited(noise, k, t0c, t1c, plant0.m))(keys)
    args_b = _with_content(plant, observer, u, controller, paths)
    state0 = per_member(args_b, lambda a, x, xh: initial_state(a, ts[0], x, xh), plant_batched)(x0s, xhat0s)
    traj = _compiled.call(_solve_batch, args_b, state0, plan, ts, lockstep, plant_batched)  # once per structure
    return _raise_if(traj, throw, "obsjax.simulate_batch", traj.status)


def _solve_batch(args_b, state0, plan, ts, lockstep: bool, plant_batched: bool) -> Trajectory:
    """The batch back-end's solve and the members' trajectories (one program, see ``_integrate._compiled``)."""
    each = lambda fn: per_member(args_b, fn, plant_batched)
    if lockstep:
        (xs, zs), codes = _integrate.integrate_batch(args_b, state0, plan)
    else:
        (xs, zs), codes = _masked.integrate(args_b, state0, plan, plant_batched)
    codes = jnp.where(jax.vmap(is_finite)(state0), codes, NONFINITE).astype(jnp.int32)  # as simulate
    return each(lambda a, x, z, c: trajectory(a, ts, x, z, c))(xs, zs, codes)


def _vmap_simulate(plant, observer, x0s, xhat0s, ts, keys, common, plant_batched=False):
    """``jax.vmap`` of :func:`obsjax.simulate` over the members (their plants with `plant_batched`, and their
    noise keys, with noise)."""
    plant_axis = eqx.if_array(0) if plant_batched else None
    key_axis = None if common["noise"] is None else 0

    def one(pl, a, b, k):
        return simulate(pl, observer, a, b, ts, key=k, **common)

    return eqx.filter_vmap(one, in_axes=(plant_axis, 0, 0, key_axis))(
        plant, x0s, xhat0s, keys if common["noise"] is not None else None
    )
