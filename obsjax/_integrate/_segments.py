"""The segmented scan: one solve per segment between consecutive breakpoints of a :class:`Schedule`.

``integrate(solve, act, carry0, ts, schedule)`` runs a ``lax.scan`` over the Nb + 1 segments
[t0, b1], [b1, b2], …, [b_Nb, t1].  Segment k ≥ 1 first applies ``act`` (the reset and/or update of
breakpoint k) to the carried state, then calls ``solve`` on [s0, s1] with its save times.  A segment that
ends at a plant jump τ ends at the float just below τ (diffrax's ``prevbefore``), so no stage of the solve
evaluates the vector field on the far side of the discontinuity; the next segment starts at τ.

Save times are handled in windows: segment k saves the ``schedule.window`` save times starting at its first
one (clipped into [s0, s1]; the ones beyond its own are discarded), so the cost of saving is
O(segments × window) rather than O(segments × len(ts)); the window is the largest number of save times that
fall into one segment (len(ts) when the breakpoints are traced).

Derivative in the breakpoint times.  Without `drift`, the segment ends move with the reset period T (and with
traced event times), so the derivative with respect to them flows into diffrax's derivative with respect to
t0 and t1 of each solve.  Given `drift` (an ODE, when the breakpoints are traced: both the single solve of
``_diffrax.py`` and the lock-step batch of ``_lockstep.py`` give it), the solves run
on the breakpoints without their derivative (their steps do not move with T), and a breakpoint τ moves the
state through the jump condition instead: the state that leaves it is act(τ + δτ, y⁻ + δτ f⁻) − δτ f⁺, with
f⁻ = f(τ⁻, y⁻) (the end of the previous segment) and f⁺ = f(τ, y⁺), δτ of value 0 carrying τ's derivative.
That is the first-order motion of the exact solution (as in ``_fixed_step.integrate_traced`` and the masked
loop of ``_adaptive_rk.py``): it differs from the derivative of steps that move with τ by the tolerance, and
does not suffer from steps that cross kinks of the vector field (band-limited noise), whose motion is
differentiated inaccurately.  The save times are fixed and carry no T-derivative (their clip uses
``stop_gradient`` bounds).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ._schedule import Schedule
from ._status import SUCCESS, finite_or_zero, first_failure, is_floating

tmap = jax.tree_util.tree_map


def segment_bounds(sched: Schedule, fixed: bool = False):
    """(starts, ends) of the Nb + 1 segments; ends before a jump are one float below it.  `fixed`: the
    breakpoints without their derivative (t0 and t1 keep theirs)."""
    t0 = jnp.reshape(sched.t0, (1,))
    t1 = jnp.reshape(sched.t1, (1,))
    times = jax.lax.stop_gradient(sched.times) if fixed else sched.times
    starts = jnp.concatenate([t0, times])
    nxt = jnp.concatenate([times, t1])
    before = jnp.nextafter(jax.lax.stop_gradient(nxt), jnp.asarray(-jnp.inf, nxt.dtype))
    ends = jnp.where(jnp.concatenate([sched.jump, jnp.zeros(1, bool)]), before, nxt)
    # ties (two breakpoints at one instant) give zero-length segments, never negative ones
    ends = jnp.where(ends > starts, ends, starts)
    return starts, ends


def integrate(solve, act, carry0, ts, sched: Schedule, row, drift=None):
    """Run every segment; returns (the solution at `ts` with leading axis len(ts), the first failure code,
    the carry at t1).

    - `row`: the pytree structure of one saved row (``jax.ShapeDtypeStruct`` leaves or arrays).

    - `solve(s0, s1, carry, save_ts) -> (saved, code, carry_end)`: `saved` a pytree with leading axis
      len(save_ts); `code` an int status (0 ok).
    - `act(t, carry, do_reset, do_event) -> carry`: the jump at a breakpoint.
    - `drift(t, carry)`: the vector field of an ODE; given, traced breakpoints move by the jump condition
      (module docstring) and the solves' times carry no derivative of them.
    """
    if sched.size == 0:
        return solve(sched.t0, sched.t1, carry0, ts)
    moving = drift is not None and sched.concrete is None
    starts, ends = segment_bounds(sched, fixed=moving)
    W, N = sched.window, ts.shape[0]
    ts_pad = jnp.concatenate([ts, jnp.broadcast_to(ts[-1], (W,))])
    no = jnp.zeros(1, bool)
    xs = (
        starts,
        ends,
        jnp.concatenate([no, sched.reset]),
        jnp.concatenate([no, sched.event]),
        sched.first_save[:-1],
        jnp.diff(sched.first_save),
    )
    if moving:
        times = sched.times
        motion = jnp.concatenate([jnp.zeros(1, times.dtype), times - jax.lax.stop_gradient(times)])
        # the vector field on both sides of a moving breakpoint is read one float below it: where a plant
        # jump falls on the same instant (a zero-length segment between the two), that is the vector
        # field before the jump, i.e. the derivative from below, as the fixed-step back-end gives
        xs = xs + (motion, jnp.nextafter(starts, jnp.asarray(-jnp.inf, starts.dtype)))
    buf0 = tmap(lambda s: jnp.zeros((N + W,) + tuple(s.shape), s.dtype), row)

    def body(carry, x):
        state, buf, code = carry
        s0, s1, do_reset, do_event, i0, count = x[:6]
        if moving:
            state = moving_act(act, drift, s0, x[6], x[7], state, do_reset, do_event)
        else:
            state = act(s0, state, do_reset, do_event)
        lo, hi = jax.lax.stop_gradient(s0), jax.lax.stop_gradient(s1)
        save_ts = jnp.clip(jax.lax.dynamic_slice_in_dim(ts_pad, i0, W), lo, hi)
        saved, c, state = solve(s0, s1, state, save_ts)
        inside = jnp.arange(W) < count

        def put(b, v):
            old = jax.lax.dynamic_slice_in_dim(b, i0, W)
            new = jnp.where(inside.reshape((W,) + (1,) * (v.ndim - 1)), v, old)
            return jax.lax.dynamic_update_slice_in_dim(b, new, i0, axis=0)

        return (state, tmap(put, buf, saved), first_failure(code, c)), None

    init = (carry0, buf0, jnp.asarray(SUCCESS, jnp.int32))
    (end, buf, code), _ = jax.lax.scan(body, init, xs)
    return tmap(lambda b: b[:N], buf), code, end


def moving_act(act, drift, t, d, t_left, state, do_reset, do_event):
    """The jump at breakpoint `t`, plus its first-order motion when t moves by δt = `d` (value 0):
    act(t + δt, y⁻ + δt f⁻) − δt f⁺, f⁻ = drift(t_left, y⁻) and f⁺ = drift(t_left, y⁺), `t_left` one float
    below t: where a plant jump falls on t too, both are the vector field before it (the derivative from
    below, the reset just before the plant's jump; elsewhere the float makes no difference), on the
    floating leaves of the carry (others, such as an eviction mask, pass through).  Non-finite values of
    the drift count as 0 (the zero motion must not turn into NaN; the next solve reports the failure
    itself)."""
    f_minus = finite_or_zero(drift(t_left, state))
    out = act(t + d, tmap(lambda v, g: _moved(v, d, g), state, f_minus), do_reset, do_event)
    f_plus = finite_or_zero(drift(t_left, out))
    return tmap(lambda v, g: _moved(v, -d, g), out, f_plus)


def _moved(v, d, g):
    """v + d g for a floating leaf; other leaves (the lock-step back-end's eviction mask) do not move."""
    return v + d * g if is_floating(v) else v
