"""Fixed-step explicit Runge–Kutta integration of the plant–observer system, written directly as ``lax.scan``.

``simulate(..., adaptive=False)`` with an explicit diffrax solver (``Tsit5``, ``Dopri5``, ``Dopri8``, ``Bosh3``,
``Heun``, ``Midpoint``, ``Ralston``, ``Euler``) comes here.  It takes the solver's Butcher tableau and evaluates

    k_i = f(t + c_i h, y + h Σ_{j<i} a_ij k_j),      y(t + h) = y + h Σ_i b_i k_i,

over a step grid fixed before tracing.  diffrax's generic step (error estimate, dense-output coefficients,
solver state, the while loop of ``diffeqsolve``) is several times the cost of these stage evaluations on the
small float64 states of an observer; with fixed steps none of it is needed.  Results agree with diffrax's
``ConstantStepSize`` solve to rounding when the step grids coincide (tested).

The grid: its nodes are the save times and the breakpoints of the schedule (reset instants, plant jumps,
event times; a breakpoint within the schedule's tolerance of a save time is moved onto it); each interval
between consecutive nodes is cut into ⌈Δ/dt0⌉ equal steps.  An interval that ends at a plant jump ends one
float before it, as the segmented back-end does, so no stage sees the vector field after the jump.  An outer
``lax.scan`` over intervals (with ``jax.checkpoint``, so reverse mode stores one state per interval) runs an
inner ``lax.scan`` of K steps, K the largest step count of any interval (shorter intervals mask their extra
steps).  The jump of a breakpoint (reset, then event update) is applied at the start of the interval it
opens, before the state there is saved (right-continuous, like the segmented back-end).

The path needs concrete save times and breakpoints (they fix the grid); otherwise, and for white noise (an
SDE), :func:`obsjax.simulate` uses the diffrax back-end.
"""

from __future__ import annotations

import functools

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value
from . import _system
from ._status import SUCCESS

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


def grid(ts, dt0, breakpoints, tol):
    """The concrete step grid, or ``None`` when the save times or dt0 are traced.

    `breakpoints`: ``Schedule.concrete``, i.e. NumPy (times, reset, event, jump) sorted by time; `tol`: the
    schedule's tolerance.  Returns a dict of NumPy arrays over the intervals between consecutive nodes:
    ``start``, ``h`` step size, ``nsteps``, ``reset`` and ``event`` (what to apply at the interval's start);
    ``save_idx`` (len(ts),) the node of each save time; ``K`` the largest step count.
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
    # nodes (t, kind, reset, event, jump, save index): the breakpoints (moved onto a save time within tol),
    # then the save times that are no breakpoint.  A save time at a breakpoint is the state after it, i.e.
    # the node of the (last) breakpoint there, except at t1, where no interval starts after the node.
    times = np.asarray(times, dtype=np.float64)
    N = len(ts)
    hi = np.clip(np.searchsorted(ts, times), 0, N - 1)
    lo = np.clip(hi - 1, 0, N - 1)
    near = np.where(np.abs(ts[lo] - times) <= np.abs(ts[hi] - times), lo, hi)
    close = np.abs(ts[near] - times) <= tol
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
    span = end - start
    nsteps = np.maximum(1, np.ceil(span / dt0 - 1e-9)).astype(np.int64)
    return dict(
        start=start,
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


def _act(args, has_reset, has_event, t, state, do_reset, do_event):
    return _system.act(args, t, state, do_reset, do_event, has_reset, has_event)


def _scan(drift, args, state0, g, tableau, act):
    """Run the grid ``g`` from ``state0``; returns the states at the save times (leading axis len(ts)).

    `drift(t, y, args)` is the joint vector field; `act(t, state, do_reset, do_event) -> state` the jump
    applied at the start of every interval (it branches on the flags).
    """
    a, b, c = (np.asarray(v) for v in tableau)
    s = len(b)
    tmap = jax.tree_util.tree_map

    def rk_step(t, y, h):
        ks = []
        for i in range(s):
            yi = y
            coeffs = [(j, a[i, j]) for j in range(i) if a[i, j] != 0.0]
            if coeffs:
                yi = tmap(lambda y0, *kk: y0 + h * sum(float(w) * kk[j] for j, w in coeffs), y, *ks)
            ks.append(drift(t + float(c[i]) * h, yi, args))
        terms = [(j, b[j]) for j in range(s) if b[j] != 0.0]
        return tmap(lambda y0, *kk: y0 + h * sum(float(w) * kk[j] for j, w in terms), y, *ks)

    K = g["K"]
    uniform = bool(np.all(g["nsteps"] == K))

    @jax.checkpoint
    def interval(state, xs):
        t_start, h, n, do_reset, do_event = xs
        state = act(t_start, state, do_reset, do_event)
        at_start = state

        def step(y, j):
            y1 = rk_step(t_start + j * h, y, h)
            if not uniform:
                y1 = tmap(lambda new, old: jnp.where(j < n, new, old), y1, y)
            return y1, None

        state, _ = jax.lax.scan(step, state, jnp.arange(K))
        return state, at_start

    dtype = jnp.result_type(*jax.tree_util.tree_leaves(state0))
    xs = (
        jnp.asarray(g["start"], dtype),
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
