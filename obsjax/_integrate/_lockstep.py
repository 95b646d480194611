"""The lock-step back-end: a batch of trajectories of one plant–observer pair as one adaptive ODE.

The joint states of all B members are stacked, the vector field is ``jax.vmap``-ed over members, and one
adaptive solve per segment of the schedule (``_segments.py``) integrates them together.  A step is accepted
when every *participating* member meets rtol/atol (:class:`LockstepController`), exactly the test a member's
own solve applies.  The solver's bookkeeping then runs once per step for the whole batch.

Failure isolation.  One member must not decide the fate of the others:

- a member whose state becomes non-finite stops participating (its error is ignored); a member whose
  candidate step is not finite (a too-long step) rejects the step like any other, until it is evicted;
- a member that alone forces the shared step below a floor, dt_floor = (t1 − t0)/max_steps (the pace at
  which max_steps would just cover the horizon), while the median member's demanded step is above it, for
  ``PATIENCE`` consecutive steps (a stiffness or an escape, not the few short steps around a kink of an
  input), is *evicted*: it stops participating for the rest of the solve;
- afterwards every evicted or non-finite member, and every member if the shared solve itself failed, is
  integrated again alone by the diffrax back-end (``_diffrax.py``, the path :func:`obsjax.simulate` takes),
  and its result and status replace the lock-step ones.  The others keep their lock-step result.

So a member's result is either the lock-step one, accurate to the tolerances on every step, or exactly the
one ``simulate`` gives it alone; only members that fail alone are reported failed.
"""

from __future__ import annotations

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import without_diffrax_save_time_checks
from . import _diffrax, _segments, _system
from ._schedule import Schedule
from ._status import COLLAPSE_ULPS, SOLVER_FAILED, SUCCESS, finite_gradient, frozen, is_finite, ulp

tmap = jax.tree_util.tree_map

# Consecutive steps a member may hold the shared step below the floor before it is evicted.
PATIENCE = 32


def member_rms(y):
    """Root mean square of each batch member over all leaves of a pytree with leading batch axis, (B,)."""
    leaves = jax.tree_util.tree_leaves(y)
    ss = sum(jnp.sum(jnp.abs(leaf.reshape(leaf.shape[0], -1)) ** 2, axis=1) for leaf in leaves)
    count = sum(int(np.prod(leaf.shape[1:])) for leaf in leaves)
    return jnp.sqrt(ss / count)


def lockstep_norm(y):
    """Error norm of a lock-step batch: max over members of each member's RMS (non-finite members ignored)."""
    r = member_rms(y)
    return jnp.max(jnp.where(jnp.isfinite(r), r, 0.0))


class LockstepController(diffrax.AbstractAdaptiveStepSizeController):
    """Integral step-size control on the worst participating member, with eviction (module docstring).

    Its state is the (B,) mask of evicted members and a (B,) count of consecutive steps below the floor; a
    solve starts from the mask passed in ``args[1]``, so a member evicted in one segment stays out of the
    later ones.  The proposed step carries no gradient.
    """

    rtol: float | jax.Array
    atol: float | jax.Array
    dt_floor: jax.Array
    dt_min: jax.Array
    safety: float = 0.9
    factormin: float = 0.2
    factormax: float = 10.0

    @property
    def norm(self):
        return lockstep_norm

    def wrap(self, direction):
        return self

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        pid = diffrax.PIDController(rtol=self.rtol, atol=self.atol, norm=lockstep_norm)
        tnext, _ = pid.init(terms, t0, t1, y0, dt0, args, func, error_order)  # t0 + a step without gradient
        return tnext, (args[1], jnp.zeros(args[1].shape, jnp.int32))

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, state):
        evicted, count = state
        def scale(a, b, e):
            b = jnp.where(jnp.isnan(b), a, b)
            return e / (self.atol + jnp.maximum(jnp.abs(a), jnp.abs(b)) * self.rtol)

        r = member_rms(tmap(scale, y0, y1_candidate, y_error))
        dt = t1 - t0
        # members whose state is already not finite take no part; a member whose candidate is not finite
        # (a too-long step) rejects the step like any other, until it is evicted
        live = jax.vmap(is_finite)(y0)
        r = jnp.where(jnp.isfinite(r), r, jnp.inf)
        count = jnp.where(self._outliers(r, evicted, live, dt, error_order), count + 1, 0)
        evicted = evicted | (count >= PATIENCE)
        use = ~evicted & live
        err = jax.lax.stop_gradient(jnp.max(jnp.where(use, r, 0.0)))
        keep = err < 1
        # the arithmetic of diffrax's PIDController (integral control), so that a batch without evictions
        # takes the very steps it took with ``PIDController(norm=lockstep_norm)``
        factor = jnp.clip(
            self.safety * (1 / err) ** (1 / error_order) * 1 * 1,
            min=jnp.where(keep, 1, self.factormin),
            max=jnp.where(keep, self.factormax, self.safety),
        )
        step = dt * jax.lax.stop_gradient(factor).astype(jnp.result_type(dt))
        # as GuardedController: never below the smallest step, and a step at it is accepted
        # (t0 + dt_min is rounded: the step taken can exceed dt_min by an ulp of t1, see GuardedController)
        slack = 2 * ulp(jnp.maximum(jnp.abs(t0), jnp.abs(t1)))
        at_floor = jax.lax.stop_gradient(dt) <= self.dt_min + slack
        keep = keep | at_floor
        next_t0 = jnp.where(keep, t1, t0)
        # (an accepted floor step grows again as the PID proposes; see GuardedController)
        next_t1 = jnp.where(step < self.dt_min, next_t0 + self.dt_min, next_t0 + step)
        return keep, next_t0, frozen(next_t1, next_t0), False, (evicted, count), diffrax.RESULTS.successful

    def _outliers(self, r, evicted, live, dt, error_order):
        """Members whose own demanded step is below the floor while the median member's is above it."""
        alive = ~evicted & live
        own = jnp.clip(self.safety * r ** (-1.0 / error_order), self.factormin, None)
        demand = jax.lax.stop_gradient(dt * own)
        low = alive & (demand < self.dt_floor)

        def median_ok():
            return jnp.nanmedian(jnp.where(alive, demand, jnp.nan)) >= self.dt_floor

        return low & jax.lax.cond(jnp.any(low), median_ok, lambda: jnp.asarray(False))


def per_member(args_b: _system.Args, fn, plant_batched: bool = False):
    """``fn(args_i, *member_arrays)`` vmapped over members; the noise path (if any) is per member, and so
    is the plant with `plant_batched` (every array leaf of ``args_b.plant`` with a leading member axis)."""
    if args_b.noise_path is None and not plant_batched:
        return jax.vmap(lambda *a: fn(args_b, *a))

    def one(plant, path, *a):
        return fn(_system.Args(plant, args_b.observer, args_b.u, args_b.controller, path, args_b.content), *a)

    plant_axis = eqx.if_array(0) if plant_batched else None

    def run(*a):
        in_axes = (plant_axis, eqx.if_array(0)) + (eqx.if_array(0),) * len(a)
        return eqx.filter_vmap(one, in_axes=in_axes)(args_b.plant, args_b.noise_path, *a)

    return run


def member_args(args_b: _system.Args, i) -> _system.Args:
    """The single-trajectory arguments of member i."""
    if args_b.noise_path is None:
        return args_b
    path = tmap(lambda a: a[i], args_b.noise_path)
    return _system.Args(args_b.plant, args_b.observer, args_b.u, args_b.controller, path, args_b.content)


def _drift(t, y, a):
    args_b, _ = a
    x, z = y
    return per_member(args_b, lambda ai, xx, zz: _system.drift(t, (xx, zz), ai))(x, z)


def _drift_finite_gradient(t, y, a, both_modes=False):
    """:func:`_drift` whose reverse-mode derivative leaves out the members whose state or vector field is
    not finite.  Such a member's result is replaced afterwards (:func:`_isolate`) and its cotangent is zero,
    but the partial derivatives of its vector field are NaN, and 0 × NaN, summed over the members into the
    derivative of the shared parameters, made the gradient NaN for the whole batch (the diffrax back-end
    drops such steps per trajectory, :class:`_diffrax.FiniteGradientSolver`).  ``both_modes``: for
    ``diffrax.DirectAdjoint``, which allows forward mode too (a ``custom_jvp`` that masks the tangents)."""
    args_b, _ = a
    x, z = y

    def one(ai, xx, zz):
        return finite_gradient(
            lambda tt, aa, x_, z_: _system.drift(tt, (x_, z_), aa), t, ai, xx, zz, both_modes=both_modes
        )

    return per_member(args_b, one)(x, z)


def _drift_finite_tangent(t, y, a):
    return _drift_finite_gradient(t, y, a, both_modes=True)


@dataclasses.dataclass(frozen=True)
class _Solve:
    args_b: _system.Args
    opt: _diffrax.Options
    ctrl: LockstepController
    drift: object

    def __call__(self, s0, s1, carry, save_ts):
        state, evicted = carry
        opt = self.opt
        with without_diffrax_save_time_checks():  # save_ts lie in [s0, s1], nondecreasing (``_segments``)
            sol = diffrax.diffeqsolve(
                diffrax.ODETerm(self.drift), opt.solver, s0, s1, opt.dt0, state, args=(self.args_b, evicted),
                saveat=diffrax.SaveAt(ts=save_ts, t1=True, controller_state=True),
                stepsize_controller=self.ctrl, max_steps=opt.max_steps, throw=False,
                **({} if opt.adjoint is None else {"adjoint": opt.adjoint}),
            )
        ok = sol.result == diffrax.RESULTS.successful
        code = jnp.where(ok, SUCCESS, SOLVER_FAILED).astype(jnp.int32)
        end = tmap(lambda a: a[-1], sol.ys)
        return tmap(lambda a: a[:-1], sol.ys), code, (end, evicted | sol.controller_state[0])


def integrate(args_b: _system.Args, state0, ts, sched: Schedule, opt: _diffrax.Options):
    """Integrate the batch `state0` = (x0s (B, n), z0s) in lock step over the schedule.

    Returns ((xs, zs) with leading axes (B, len(ts)), codes (B,)): each member's status code from the
    lock-step solve, or from its own solve when it was integrated again alone.
    """
    B = jax.tree_util.tree_leaves(state0)[0].shape[0]
    t0, t1 = sched.t0, sched.t1
    budget = 16384 if opt.max_steps is None else opt.max_steps
    eps = jnp.finfo(jnp.result_type(t0)).eps
    ctrl = LockstepController(
        opt.rtol, opt.atol,
        dt_floor=jax.lax.stop_gradient((t1 - t0) / budget),
        dt_min=jax.lax.stop_gradient(COLLAPSE_ULPS * eps * jnp.maximum(jnp.abs(t0), jnp.abs(t1))),
    )

    def act(t, carry, do_reset, do_event):
        state, evicted = carry

        def one(ai, x, z):
            return _system.act(ai, t, (x, z), do_reset, do_event, sched.has_reset, sched.has_event)

        return per_member(args_b, one)(*state), evicted

    carry0 = (state0, jnp.zeros((B,), bool))
    row = jax.eval_shape(lambda s: s, state0)
    # reverse mode by the default adjoint: the failed members' NaN partials are kept out of the gradient
    # (a custom_vjp, which has no forward mode); DirectAdjoint, which allows both modes, gets a custom_jvp
    # that masks their tangents; ForwardMode and other adjoints get the plain field
    reverse = opt.adjoint is None or type(opt.adjoint) is diffrax.RecursiveCheckpointAdjoint
    direct = type(opt.adjoint) is diffrax.DirectAdjoint
    f = _drift_finite_gradient if reverse else (_drift_finite_tangent if direct else _drift)
    f = _system.for_check_mode(f)
    solve = _Solve(args_b, opt, ctrl, f)

    def drift(t, carry):  # the batch's vector field; the eviction mask does not move
        return f(t, carry[0], (args_b, carry[1])), carry[1]

    saved, code, (_, evicted) = _segments.integrate(solve, act, carry0, ts, sched, row, drift=drift)
    return _isolate(args_b, state0, ts, sched, opt, saved, code, evicted)


def _isolate(args_b, state0, ts, sched, opt, saved, code, evicted):
    """Integrate alone every member that was evicted or became non-finite (all of them if the shared solve
    failed); the others keep their lock-step result.  Returns ((xs, zs) as (B, T, ...), codes (B,))."""
    out = tmap(lambda a: jnp.swapaxes(a, 0, 1), saved)  # (T, B, ...) -> (B, T, ...)
    B = jax.tree_util.tree_leaves(out)[0].shape[0]
    redo = evicted | ~jax.vmap(is_finite)(out) | (code != SUCCESS)

    def alone(i):
        first = tmap(lambda a: a[i], state0)
        return _diffrax.integrate(member_args(args_b, i), first, ts, sched, opt)

    def kept(i):
        return tmap(lambda a: a[i], out), jnp.asarray(SUCCESS, jnp.int32)

    def rerun():
        return jax.lax.map(lambda i: jax.lax.cond(redo[i], alone, kept, i), jnp.arange(B))

    return jax.lax.cond(jnp.any(redo), rerun, lambda: (out, jnp.zeros((B,), jnp.int32)))
