"""A batch with independent adaptive steps in one loop: ``simulate_batch(lockstep=False)`` on the masked
Runge–Kutta back-end (``_adaptive_rk.py``).

``jax.vmap(simulate)`` gives every member its own steps, but under ``vmap`` diffrax's while loop runs its
whole bookkeeping (solver state, dense output, the segmented scan) for every member at every iteration
and the loop runs until the slowest member ends each segment.  :func:`integrate` hands the same problem to
:func:`obsjax._integrate._adaptive_rk.adaptive_rk_solve`: one loop, each member its own step size and
its own segments, resets applied inside the loop.  Member by member it is the solve of
:func:`obsjax.simulate`:

- the same explicit Runge–Kutta pair and PID control (rtol, atol, and the controller's defaults);
- the same first step of every segment: ``dt0`` when given, else 0.01 (what ``diffrax.diffeqsolve``
  takes when it is given ``dt0=None``, see ``_adaptive_rk``'s docstring);
- segments between the same breakpoints (the observer's resets at t0 + kT, stepped onto exactly; the
  plant's jumps, stepped onto the float below);
- ``max_steps`` per segment, as in ``simulate``: a member fails (``SOLVER_FAILED``) when one of its
  segments takes ``max_steps`` attempts without reaching its end (the loop's bound is ``max_steps`` × the
  number of segments, at most 2³⁰);
- the same step floor (64 ulp of the horizon's end, ``_status.GuardedController``), where a step is
  accepted whatever its error (diffrax's ``dtmin``), so a solution escaping in finite time is followed
  until it overflows;
- the status codes of ``_status.py``: a member whose state or vector field becomes non-finite is
  ``NONFINITE``, one that runs out of steps ``SOLVER_FAILED``.

:func:`eligible` says when the problem allows it: adaptive steps of an explicit Runge–Kutta pair with an
embedded error estimate, no white noise (an SDE), no observer events (an update at data times), a bound on
the steps, and an adjoint the loop implements (diffrax's default ``RecursiveCheckpointAdjoint``,
``ForwardMode`` or ``DirectAdjoint``).  Everything else goes through ``jax.vmap(simulate)``.
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from . import _system
from ._adaptive_rk import adaptive_rk_solve, supports_adjoint, supports_solver
from ._status import COLLAPSE_ULPS
from ._validate import Plan

# The back-end's first step when simulate's would be diffeqsolve's default (see the module docstring).
DIFFRAX_FIRST_STEP = 0.01
# The loop's bound (its step counters are int32).
MAX_LOOP_STEPS = 2**30


def _eligible(adaptive, white_noise, has_event, max_steps, solver, adjoint) -> bool:
    return bool(
        adaptive
        and not white_noise
        and not has_event
        and max_steps is not None
        and supports_solver(solver)
        and supports_adjoint(adjoint)
    )


def eligible(plan: Plan) -> bool:
    """Whether the masked back-end integrates this batch as ``jax.vmap(simulate)`` would (to rounding)."""
    opt = plan.opt
    return _eligible(
        opt.adaptive, opt.white_noise is not None, plan.sched.has_event, opt.max_steps, opt.solver,
        opt.adjoint,
    )


def eligible_options(observer, ts_np, *, solver=None, adaptive=True, noise=None, max_steps=16384,
                     adjoint=None, **_) -> bool:
    """:func:`eligible` from ``simulate``'s keyword arguments, before any plan is built (``monte_carlo``
    picks its kernel with it; `ts_np` the concrete save times)."""
    from ..systems._noise import WhiteNoise

    events = observer.event_times(float(ts_np[0]), float(ts_np[-1]))
    return _eligible(
        adaptive, isinstance(noise, WhiteNoise), events is not None, max_steps,
        diffrax.Tsit5() if solver is None else solver, adjoint,
    )


def integrate(args_b: _system.Args, state0_b, plan: Plan, plant_batched: bool = False):
    """Integrate the batch `state0_b` = (x0s (B, n), z0s) with independent adaptive steps.

    With `plant_batched`, every array leaf of ``args_b.plant`` has a leading axis B: member b integrates
    plant b (its static fields, among them the declared jump times, are shared, so the breakpoints of
    `plan` are every member's).

    Returns ((xs, zs) with leading axes (B, len(ts)), codes (B,)).
    """
    opt, sched = plan.opt, plan.sched
    # Arrays of the observer, input and controller are shared; the noise path's are per member, and the
    # plant's either. Everything that is not an array (functions, static fields) is closed over.
    dyn, static = eqx.partition(args_b, eqx.is_array)
    shared = (None if plant_batched else dyn.plant, dyn.observer, dyn.u, dyn.controller)
    member = (dyn.plant if plant_batched else None, dyn.noise_path)
    member_axes = (0 if plant_batched else None, None if dyn.noise_path is None else 0)

    def args_of(a):
        (plant, observer, u, controller), (member_plant, path) = a
        plant = member_plant if plant_batched else plant
        return eqx.combine(_system.Args(plant, observer, u, controller, path, static.content), static)

    def vector_field(t, y, a):
        return _system.drift(t, y, args_of(a))

    def reset(t, y, a):
        x, z = y
        return x, args_of(a).observer.reset(t, z)

    inf = jnp.asarray(jnp.inf, sched.times.dtype)
    has_jump = sched.concrete is None or bool(sched.concrete[3].any())
    reset_ts = jnp.where(sched.reset, sched.times, inf) if sched.has_reset else None
    jump_ts = jnp.where(sched.jump, sched.times, inf) if (sched.size and has_jump) else None
    dt0 = DIFFRAX_FIRST_STEP if opt.dt0 is None else opt.dt0
    # simulate's step floor (GuardedController): a step there is accepted whatever its error, so a solution
    # that escapes in finite time is followed until it overflows (NONFINITE) instead of stalling
    scale = jnp.maximum(jnp.abs(sched.t0), jnp.abs(sched.t1))
    floor = jax.lax.stop_gradient(COLLAPSE_ULPS * jnp.finfo(jnp.result_type(scale)).eps * scale)
    sol = adaptive_rk_solve(
        vector_field,
        state0_b,
        sched.t0,
        sched.t1,
        args=(shared, member),
        args_axes=(None, member_axes),
        solver=opt.solver,
        stepsize_controller=diffrax.PIDController(rtol=opt.rtol, atol=opt.atol, dtmin=floor),
        dt0=dt0,
        ts=plan.ts,
        reset=reset if sched.has_reset else None,
        reset_ts=reset_ts,
        jump_ts=jump_ts,
        max_steps=min(int(opt.max_steps) * (sched.size + 1), MAX_LOOP_STEPS),
        max_steps_per_segment=int(opt.max_steps),
        adjoint=opt.adjoint,
    )
    return sol.ys, sol.status.astype(jnp.int32)
