"""Fixed-step explicit Runge–Kutta integration of the plant–observer system, written directly as ``lax.scan``.

``simulate(..., adaptive=False)`` with an explicit diffrax solver (``Tsit5``, ``Dopri5``, ``Dopri8``, ``Bosh3``,
``Heun``, ``Midpoint``, ``Ralston``, ``Euler``) comes here.  It takes the solver's Butcher tableau and evaluates

    k_i = f(t + c_i h, y + h Σ_{j<i} a_ij k_j),      y(t + h) = y + h Σ_i b_i k_i,

over a step grid fixed before tracing.  diffrax's generic step (error estimate, dense-output coefficients,
solver state, the while loop of ``diffeqsolve``) is several times the cost of these stage evaluations on the
small float64 states of an observer; with fixed steps none of it is needed.  Results agree with diffrax's
``ConstantStepSize`` solve to rounding when the step grids coincide (tested).

The grid: its nodes are the save times and the breakpoints of the schedule (reset instants, plant jumps,
event times; a reset or event within the schedule's tolerance of a save time is moved onto it, a plant jump
never is); each interval between consecutive nodes is cut into ⌈Δ/dt0⌉ equal steps.  An interval that ends
at a plant jump ends one float before it, as the segmented back-end does, so no stage sees the vector field
after the jump; a jump within the tolerance of t0 or t1, which the schedule leaves out, cuts the interval
around it too (:func:`edge_jumps`).  An outer ``lax.scan`` over intervals (with ``jax.checkpoint``, so
reverse mode stores one state per interval) runs an inner ``lax.scan`` of K steps, K the largest step count
of any interval (shorter intervals mask their extra steps).  The jump of a breakpoint (reset, then event update) is applied at the start of the interval it
opens, before the state there is saved (right-continuous, like the segmented back-end).

With traced breakpoints (a reset period T being tuned, traced event times) and concrete save times and dt0,
:func:`integrate_traced` builds the same grid inside the trace: the nodes are sorted by value, and one
``lax.scan`` of a length fixed before tracing (⌈(t1 − t0)/dt0⌉ + the number of intervals, a bound on the steps
of any placement of the breakpoints) walks the intervals step by step.  Its result at a traced T equals the
concrete grid's at the same T to rounding.  Its derivative in the breakpoint times is that of the jump
condition at each breakpoint (see :func:`integrate_traced`), on a grid that does not move: the derivative of
the exact solution, to the method's order.  It replaces, for ``tune``'s fixed-step kernels, a ``lax.scan``
over reset segments holding one ``diffeqsolve`` each, whose tracing under ``jvp`` and ``vmap`` took most of a
first tune step.

Traced save times or dt0, and white noise (an SDE), go to the diffrax back-end.
"""

from __future__ import annotations

import functools
import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value
from . import _system
from ._status import SOLVER_FAILED, SUCCESS, finite_or_zero

_EULER = (np.zeros((0, 0)), np.ones(1), np.zeros(1))


def tableau_of(solver):
    """(a (s, s) strictly lower, b (s,), c (s,)) of an explicit RK solver, trimmed to the stages that b uses;
    ``None`` for solvers that are not explicit Runge–Kutta methods."""
    if isinstance(solver, diffrax.Euler):
        return _EULER
    if not isinstance(solver, diffrax.AbstractERK):
        return None
    tab = getattr(solver, "tableau", None)
    if not isinstance(tab, diffrax.ButcherTableau):
        return None
    b = np.asarray(tab.b_sol, dtype=np.float64)
    s = len(b)
    a = np.zeros((s, s))
    for i, row in enumerate(tab.a_lower):
        a[i + 1, : i + 1] = np.asarray(row)
    c = np.concatenate([[0.0], np.asarray(tab.c, dtype=np.float64)])
    # stages after the last non-zero weight feed nothing (Tsit5's and Dopri5's FSAL stage).
    used = int(np.max(np.nonzero(b)[0])) + 1
    return a[:used, :used], b[:used], c[:used]


def edge_jumps(ts_np, jumps, tol):
    """The plant's jump times in [t0, t1] that the schedule leaves out, those within `tol` of t0 or t1
    (NumPy, possibly empty; empty when the jump times are traced).  The fixed-step grids cut the interval
    around each of them (:func:`_cut_at_edge_jumps`): no stage of a step may see the vector field of the
    other side of a jump, or the step is only first-order accurate."""
    jv = concrete_value(jumps) if jumps is not None else None
    if jv is None or ts_np is None:
        return np.zeros(0)
    jv = np.asarray(jv, dtype=np.float64).ravel()
    t0, t1 = float(ts_np[0]), float(ts_np[-1])
    inside = (jv >= t0) & (jv <= t1)
    return np.sort(jv[inside & ((jv <= t0 + tol) | (jv >= t1 - tol))])


def _cut_at_edge_jumps(start, end, jumps, xp=np):
    """Intervals [start, end] that hold an edge jump τ (start < τ ≤ end) lose the side of τ nearer to their
    end: they start at τ when τ is nearer their start, else end one float before τ (either way at most the
    schedule's tolerance is left out, the convention by which the schedule merged τ with t0 or t1)."""
    for tau in np.asarray(jumps, dtype=np.float64):
        inside = (start < tau) & (tau <= end)
        lower = (tau - start) <= (end - tau)
        before = np.nextafter(tau, -np.inf)
        start = xp.where(inside & lower, tau, start)
        end = xp.where(inside & ~lower, xp.maximum(before, start), end)
    return start, end


def grid(ts, dt0, breakpoints, tol, jumps=()):
    """The concrete step grid, or ``None`` when the save times or dt0 are traced.

    `breakpoints`: ``Schedule.concrete``, i.e. NumPy (times, reset, event, jump) sorted by time; `tol`: the
    schedule's tolerance; `jumps`: :func:`edge_jumps`.  Returns a dict of NumPy arrays over the intervals
    between consecutive nodes: ``start``, ``end``, ``h`` step size, ``nsteps``, ``reset`` and ``event`` (what
    to apply at the interval's start); ``save_idx`` (len(ts),) the node of each save time; ``K`` the largest
    step count.
    """
    ts = concrete_value(ts)
    dt0 = concrete_value(dt0)
    if ts is None or dt0 is None or breakpoints is None:
        return None
    ts = np.asarray(ts, dtype=np.float64)
    dt0 = float(np.asarray(dt0).reshape(()))
    if not dt0 > 0:
        raise ValueError(f"`dt0` must be > 0 for fixed steps, got {dt0}.")
    times, is_reset, is_event, is_jump = breakpoints
    t1 = float(ts[-1])
    # nodes (t, kind, reset, event, jump, save index): the breakpoints (a reset or event within tol of a save
    # time moved onto it), then the save times that are no breakpoint.  A save time at a breakpoint is the
    # state after it, i.e. the node of the (last) breakpoint there, except at t1, where no interval starts
    # after the node.  A plant jump is never moved: the plant switches at its own time, and a node moved
    # off it leaves stages of the step beside it on the wrong side of the switch (an O(h) error); a save
    # time within tol of it keeps its own node, at the end of an interval of a few floats.
    times = np.asarray(times, dtype=np.float64)
    N = len(ts)
    hi = np.clip(np.searchsorted(ts, times), 0, N - 1)
    lo = np.clip(hi - 1, 0, N - 1)
    near = np.where(np.abs(ts[lo] - times) <= np.abs(ts[hi] - times), lo, hi)
    close = (np.abs(ts[near] - times) <= tol) & ~np.asarray(is_jump, bool)
    snapped = np.where(close, ts[near], times)
    merged = np.zeros(N, bool)
    merged[near[close & (ts[near] != t1)]] = True
    nodes = [(float(t), 0, bool(r), bool(e), bool(j), -1)
             for t, r, e, j in zip(snapped, is_reset, is_event, is_jump)]
    nodes += [(float(t), 1, False, False, False, i) for i, t in enumerate(ts) if not merged[i]]
    nodes.sort(key=lambda nd: (nd[0], nd[1]))
    save_idx = np.zeros(N, np.int64)
    last_breakpoint = {}
    for k, nd in enumerate(nodes):
        if nd[1] == 0:
            last_breakpoint[nd[0]] = k
        else:
            save_idx[nd[5]] = k
    for i in np.flatnonzero(merged):  # the state after the (last) breakpoint at that instant
        save_idx[i] = last_breakpoint[float(ts[i])]
    t_node = np.array([nd[0] for nd in nodes])
    start, end = t_node[:-1], t_node[1:].copy()
    ends_at_jump = np.array([nd[4] for nd in nodes[1:]], bool)
    end[ends_at_jump] = np.maximum(np.nextafter(end[ends_at_jump], -np.inf), start[ends_at_jump])
    start, end = _cut_at_edge_jumps(start, end, jumps)
    span = end - start
    nsteps = np.maximum(1, np.ceil(span / dt0 - 1e-9)).astype(np.int64)
    return dict(
        start=start,
        end=end,
        h=span / nsteps,
        nsteps=nsteps,
        reset=np.array([nd[2] for nd in nodes[:-1]], bool),
        event=np.array([nd[3] for nd in nodes[:-1]], bool),
        save_idx=save_idx,
        K=int(nsteps.max()),
    )


def integrate(args: _system.Args, state0, sched, g, tableau):
    """The back-end's entry point: run grid `g` (from :func:`grid`) with the explicit RK `tableau` (from
    :func:`tableau_of`) from `state0` = (x0, z0); returns ((xs, zs) at the save times, status code 0)."""
    act = functools.partial(_act, args, sched.has_reset, sched.has_event)
    out = _scan(_system.drift, args, state0, g, tableau, act)
    return out, jnp.asarray(SUCCESS, jnp.int32)


def rk_stepper(drift, args, tableau):
    """``rk_step(t, y, h, t_end)``: one step of the explicit RK `tableau` on ``drift(t, y, args)``.

    Stage times t + c_i h are clipped to `t_end`, the end of the interval: the interval before a plant jump τ
    ends one float below τ, and t + h of its last step, rounded, can land on τ itself, where the vector field
    is already the one after the jump (an O(h) error in that step; seen on a switched plant).

    The drift is wrapped in ``eqx.filter_jit``: its jaxpr is traced once and reused by every stage and by
    every transformation of the loop around it (``jvp``, ``vmap``, the scan's fixed-point passes), instead of
    being traced again for each stage; XLA inlines the calls, so the compiled program is the same.  JAX caches
    that trace by the function object, so the drift is first given one object per mode of equinox's runtime
    checks (:func:`_system.for_check_mode`): a trace with raising checks is never reused by a kernel traced
    with the checks as NaN, nor the other way round."""
    a, b, c = (np.asarray(v) for v in tableau)
    s = len(b)
    tmap = jax.tree_util.tree_map
    f = eqx.filter_jit(_system.for_check_mode(drift))

    def rk_step(t, y, h, t_end):
        ks = []
        for i in range(s):
            yi = y
            coeffs = [(j, a[i, j]) for j in range(i) if a[i, j] != 0.0]
            if coeffs:
                yi = tmap(lambda y0, *kk: y0 + h * sum(float(w) * kk[j] for j, w in coeffs), y, *ks)
            ks.append(f(jnp.minimum(t + float(c[i]) * h, t_end), yi, args))
        terms = [(j, b[j]) for j in range(s) if b[j] != 0.0]
        return tmap(lambda y0, *kk: y0 + h * sum(float(w) * kk[j] for j, w in terms), y, *ks)

    return rk_step


def _act(args, has_reset, has_event, t, state, do_reset, do_event):
    return _system.act(args, t, state, do_reset, do_event, has_reset, has_event)


def _scan(drift, args, state0, g, tableau, act):
    """Run the grid ``g`` from ``state0``; returns the states at the save times (leading axis len(ts)).

    `drift(t, y, args)` is the joint vector field; `act(t, state, do_reset, do_event) -> state` the jump
    applied at the start of every interval (it branches on the flags).
    """
    tmap = jax.tree_util.tree_map
    rk_step = rk_stepper(drift, args, tableau)
    K = g["K"]
    uniform = bool(np.all(g["nsteps"] == K))

    @jax.checkpoint
    def interval(state, xs):
        t_start, t_end, h, n, do_reset, do_event = xs
        state = act(t_start, state, do_reset, do_event)
        at_start = state

        def step(y, j):
            y1 = rk_step(t_start + j * h, y, h, t_end)
            if not uniform:
                y1 = tmap(lambda new, old: jnp.where(j < n, new, old), y1, y)
            return y1, None

        state, _ = jax.lax.scan(step, state, jnp.arange(K))
        return state, at_start

    dtype = jnp.result_type(*jax.tree_util.tree_leaves(state0))
    xs = (
        jnp.asarray(g["start"], dtype),
        jnp.asarray(g["end"], dtype),
        jnp.asarray(g["h"], dtype),
        jnp.asarray(g["nsteps"]),
        jnp.asarray(g["reset"]),
        jnp.asarray(g["event"]),
    )
    end, starts = jax.lax.scan(interval, state0, xs)
    # breakpoint states: the (post-reset) state at each interval's start, then the final state.
    bps = tmap(lambda s_, e: jnp.concatenate([s_, e[None]], axis=0), starts, end)
    idx = jnp.asarray(g["save_idx"])
    return tmap(lambda v: v[idx], bps)


def traced_steps(ts_np, dt0, n_nodes) -> int:
    """The step budget of :func:`integrate_traced`: ⌈(t1 − t0)/dt0⌉ + (number of intervals).

    Every interval of span Δ takes max(1, ⌈Δ/dt0⌉) ≤ Δ/dt0 + 1 steps and the spans sum to t1 − t0, so the
    steps of any placement of the breakpoints fit (a small relative slack absorbs rounding of the spans)."""
    span = float(ts_np[-1]) - float(ts_np[0])
    return math.ceil(span / dt0 * (1.0 + 1e-12) + 1e-9) + max(n_nodes - 1, 0)


def integrate_traced(args: _system.Args, state0, sched, ts_np, dt0, tableau, tol, jumps=()):
    """Fixed steps on a grid whose breakpoints are traced (a tuned reset period T, traced event times).

    The same grid as :func:`grid` (nodes: the save times and the breakpoints, a reset or event within `tol`
    of a save time moved onto it; every interval cut into max(1, ⌈Δ/dt0⌉) equal steps; an interval that ends
    at a plant jump ends one float before it; edge jumps cut as there), but built inside the trace: the nodes are sorted by value, and one
    ``lax.scan`` of a fixed length (:func:`traced_steps`) walks the intervals step by step, applying each
    breakpoint's jump at the first step of the interval it opens; steps past the grid's last are masked.
    Returns ((xs, zs) at the save times, status code): ``SOLVER_FAILED`` if the grid had more steps than the
    budget (it cannot, by the bound; the check guards the bound itself).

    **Derivative in the breakpoint times.**  The grid carries no derivative (its step sizes do not move with
    T); a breakpoint τ that moves (τ = kT, dτ/dT = k) enters through the jump condition of its state map
    y⁺ = J(τ, y⁻) (``observer.reset``, then ``observer.update``) at a moving time: with f⁻ and f⁺ the vector
    field just before and after the jump, the sensitivity s = ∂y/∂T at a fixed time jumps as

        s⁺ = ∂J/∂y (s⁻ + f⁻ dτ/dT) + ∂J/∂t dτ/dT − f⁺ dτ/dT,

    and between breakpoints it follows the method's own variational (discrete) equation.  This is the
    derivative of the exact solution to the order of the method (on the switched example of the tests,
    1e-5, 1e-6 and 5e-8 relative at dt0 = 0.05, 0.025, 0.0125), not the derivative of the discrete
    solution whose step sizes beside each breakpoint move with T (the two differ by about as much).  A
    breakpoint moved onto a save time keeps its derivative, so the state saved there, the state after the
    jump, gets s⁺: the derivative from below of the loss's kink there, as with the diffrax back-end.  It
    costs two evaluations of the vector field per breakpoint, in a ``lax.cond`` that only the steps opening a
    breakpoint's interval run (the step counter does not depend on the members, so the branch stays one under
    ``vmap``).  Carrying the derivative of every step time and step size instead cost about the solve again
    for each tuned scalar: on Chen & Yen's example (``benchmarks/j_forward_gradient.py``, fixed Tsit5 steps,
    (γ, p0, T) tuned) forward mode took 5.9× the forward pass before, 3.0× with the jump condition.
    """
    tmap = jax.tree_util.tree_map
    sg = jax.lax.stop_gradient
    dtype = jnp.result_type(*jax.tree_util.tree_leaves(state0))
    ts_np = np.asarray(ts_np, dtype=np.float64)
    N = len(ts_np)
    ts = jnp.asarray(ts_np, dtype)
    bt = jnp.asarray(sched.times, dtype)
    Nb = int(bt.shape[0])
    # a reset or event within tol of a save time is moved onto it (its value; its derivative is kept); a
    # plant jump stays where the plant switches (see :func:`grid`)
    hi = jnp.clip(jnp.searchsorted(ts, sg(bt)), 0, N - 1)
    lo = jnp.clip(hi - 1, 0, N - 1)
    near = jnp.where(jnp.abs(ts[lo] - sg(bt)) <= jnp.abs(ts[hi] - sg(bt)), lo, hi)
    close = (jnp.abs(ts[near] - sg(bt)) <= tol) & ~sched.jump
    bt = jnp.where(close, bt + sg(ts[near] - bt), bt)
    # nodes: breakpoints, then save times; sorted by (time, breakpoint before save time, given order)
    M = Nb + N
    t_all = jnp.concatenate([bt, ts])
    kind = jnp.concatenate([jnp.zeros(Nb, jnp.int32), jnp.ones(N, jnp.int32)])
    no = jnp.zeros(N, bool)
    order = jnp.lexsort((jnp.arange(M), kind, sg(t_all)))
    tn = t_all[order]
    kind = kind[order]
    reset, event, jump = (jnp.concatenate([f, no])[order] for f in (sched.reset, sched.event, sched.jump))
    # The grid carries no derivative (see the docstring): the nodes' values, and beside them their motion
    # (zero, with the derivative of the node's time) for the jump condition at each breakpoint.
    motion = tn - sg(tn)
    tn = sg(tn)
    start, end = tn[:-1], tn[1:]
    before = jnp.nextafter(end, jnp.asarray(-jnp.inf, dtype))
    end = jnp.where(jump[1:], before, end)
    end = jnp.where(end >= start, end, start)  # never a negative span
    start, end = _cut_at_edge_jumps(start, end, jumps, jnp)
    span = end - start
    nsteps = jnp.maximum(1, jnp.ceil(span / dt0 - 1e-9)).astype(jnp.int32)
    h = span / nsteps
    offsets = jnp.cumsum(nsteps) - nsteps  # the first step of each interval
    total = jnp.sum(nsteps)
    S = traced_steps(ts_np, dt0, M)
    rk_step = rk_stepper(_system.drift, args, tableau)
    has_reset, has_event = sched.has_reset, sched.has_event
    f = eqx.filter_jit(_system.for_check_mode(_system.drift))

    def moving_jump(k, y):
        """The jump at node k, y⁺ = act(τ, y⁻), plus its first-order motion when τ moves by δτ:
        y⁺ + δτ·(∂act/∂t + ∂act/∂y f⁻ − f⁺), written as act(τ + δτ, y⁻ + δτ f⁻) − δτ f⁺ with δτ = `motion`,
        whose value is 0 (the state is unchanged) and whose derivative is the node time's.

        f⁻ and f⁺ are read one float before τ: where a plant jump falls on τ too, they are the vector field
        before it, i.e. the derivative is the one from below (τ just before the plant's jump), as at a
        reset on a save time; elsewhere the float makes no difference.  f⁺ is read at the jumped state
        itself: its own motion enters only multiplied by δτ, i.e. at second order."""
        d = motion[k]
        t_k = start[k]
        t_left = jnp.nextafter(t_k, jnp.asarray(-jnp.inf, dtype))
        f_minus = finite_or_zero(f(t_left, y, args))
        y_moved = tmap(lambda v, g: v + d * g, y, f_minus)
        y_jump = _system.act(args, t_k + d, y_moved, reset[k], event[k], has_reset, has_event)
        f_plus = finite_or_zero(f(t_left, y_jump, args))
        out = tmap(lambda v, g: v - d * g, y_jump, f_plus)
        if args.controller is None:
            # open loop: the jump leaves the plant's state and its vector field alone, so f_x⁺ = f_x⁻ and its
            # motion term is identically zero; dropping it keeps the plant's tangent zero (not carried)
            out = (y[0], out[1])
        return out

    @jax.checkpoint  # reverse mode stores the carry of each step, not its stages
    def body(carry, step):
        y, k, j = carry
        live = step < total
        t_k, h_k, n_k = start[k], h[k], nsteps[k]
        first = live & (j == 0) & (reset[k] | event[k])
        # a branch, not a select: k and j do not depend on the members, so under vmap the jump (and the
        # two evaluations of the vector field in it) runs only at the steps that open a breakpoint's interval
        y = jax.lax.cond(first, moving_jump, lambda _, yy: yy, k, y)
        y1 = rk_step(t_k + j * h_k, y, h_k, end[k])
        y_next = tmap(lambda new, old: jnp.where(live, new, old), y1, y)
        done = j + 1 >= n_k
        k_next = jnp.where(live & done, jnp.minimum(k + 1, M - 2), k)
        j_next = jnp.where(done, 0, j + 1)
        return (y_next, k_next, j_next), y

    zero = jnp.zeros((), jnp.int32)
    (y_end, _, _), ys = jax.lax.scan(body, (state0, zero, zero), jnp.arange(S, dtype=jnp.int32))
    # the state at each node: the (post-jump) state at each interval's first step, then the final state
    bps = tmap(lambda v, e: jnp.concatenate([v[offsets], e[None]], axis=0), ys, y_end)
    pos = jnp.nonzero(kind == 1, size=N)[0]  # save times are sorted among themselves
    out = tmap(lambda v: v[pos], bps)
    code = jnp.where(total <= S, SUCCESS, SOLVER_FAILED).astype(jnp.int32)
    return out, code
