"""Fixed-step explicit Runge–Kutta integration of the plant–observer system, written directly as ``lax.scan``.

``simulate(..., adaptive=False)`` with an explicit diffrax solver (``Tsit5``, ``Dopri5``, ``Dopri8``, ``Bosh3``,
``Heun``, ``Midpoint``, ``Ralston``, ``Euler``) comes here.  It takes the solver's Butcher tableau and evaluates

    k_i = f(t + c_i h, y + h Σ_{j<i} a_ij k_j),      y(t + h) = y + h Σ_i b_i k_i,

over a step grid fixed before tracing.  diffrax's generic step (error estimate, dense-output coefficients,
solver state, the while loop of ``diffeqsolve``) is several times the cost of these stage evaluations on the
small float64 states of an observer; with fixed steps none of it is needed.  Results agree with diffrax's
``ConstantStepSize`` solve to rounding when the step grids coincide (tested).

The grid: the breakpoints are the save times, the reset instants t0 + kT of a resetting observer and the
plant's ``jump_ts``; each interval between consecutive breakpoints is cut into ⌈Δ/dt0⌉ equal steps.  An
interval that ends at a plant jump ends one float before it, as diffrax's ``ClipStepSizeController`` does, so
no stage sees the vector field after the jump.  An outer ``lax.scan`` over intervals (with
``jax.checkpoint``, so reverse mode stores one state per interval) runs an inner ``lax.scan`` of K steps, K
the largest step count of any interval (shorter intervals mask their extra steps).  A reset at a breakpoint is
applied before the state there is saved (right-continuous, like the segmented adaptive solve).

The path needs concrete save times, reset period and jump times (they fix the grid); otherwise, and for
white noise (an SDE), :func:`obsjax.simulate` uses diffrax.
"""

from __future__ import annotations

import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from ._checks import concrete_value

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


def grid(ts, dt0, reset_period=None, jumps=None):
    """The concrete step grid, or ``None`` when any of its inputs is traced.

    Returns a dict of NumPy arrays over the N − 1 intervals between N breakpoints: ``start`` (N − 1,),
    ``h`` (N − 1,) step size, ``nsteps`` (N − 1,), ``reset`` (N − 1,) whether to reset at the interval's start;
    and ``save_idx`` (len(ts),) the breakpoint index of each save time; ``K`` the largest step count.
    """
    ts = concrete_value(ts)
    dt0 = concrete_value(dt0)
    if ts is None or dt0 is None:
        return None
    ts = np.asarray(ts, dtype=np.float64)
    dt0 = float(np.asarray(dt0).reshape(()))
    if not dt0 > 0:
        raise ValueError(f"`dt0` must be > 0 for fixed steps, got {dt0}.")
    t0, t1 = float(ts[0]), float(ts[-1])
    tol = 1e-9 * max(1.0, abs(t1 - t0))
    resets = np.zeros(0)
    if reset_period is not None:
        T = concrete_value(reset_period)
        if T is None:
            return None
        T = float(np.asarray(T).reshape(()))
        if not T > 0:
            raise ValueError(f"the reset period `T` must be > 0, got {T}.")
        k = np.arange(1, int(math.ceil((t1 - t0) / T)) + 1)
        resets = t0 + k * T
        resets = resets[resets < t1 - tol]
    jump = np.zeros(0)
    if jumps is not None:
        jump = np.asarray(jumps, dtype=np.float64).reshape(-1)
        jump = jump[(jump > t0 + tol) & (jump < t1 - tol)]
    # breakpoints: save times first, so that a reset or jump within tol of a save time takes its value.
    pts = list(ts)
    for extra in (resets, jump):
        for v in extra:
            if np.min(np.abs(np.asarray(pts) - v)) > tol:
                pts.append(float(v))
    bp = np.sort(np.asarray(pts))
    near = lambda vals: np.array([bool(len(vals)) and np.min(np.abs(vals - b)) <= tol for b in bp])
    is_reset = near(resets)
    is_jump = near(jump)
    start = bp[:-1]
    end = bp[1:].copy()
    # an interval ending at a jump stops one float before it (diffrax's prevbefore).
    end[is_jump[1:]] = np.nextafter(end[is_jump[1:]], -np.inf)
    span = end - start
    nsteps = np.maximum(1, np.ceil(span / dt0 - 1e-9)).astype(np.int64)
    save_idx = np.searchsorted(bp, ts - tol)
    return dict(
        start=start,
        h=span / nsteps,
        nsteps=nsteps,
        reset=is_reset[:-1],
        save_idx=save_idx,
        K=int(nsteps.max()),
    )


def integrate(drift, args, state0, g, tableau, reset=None):
    """Run the grid ``g`` from ``state0``; returns the states at the save times (leading axis len(ts)).

    `drift(t, y, args)` is the joint vector field; `reset(t, state) -> state` is applied at flagged breakpoints.
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
        t_start, h, n, do_reset = xs
        if reset is not None:
            state = jax.lax.cond(do_reset, lambda q: reset(t_start, q), lambda q: q, state)
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
    )
    end, starts = jax.lax.scan(interval, state0, xs)
    # breakpoint states: the (post-reset) state at each interval's start, then the final state.
    bps = tmap(lambda s_, e: jnp.concatenate([s_, e[None]], axis=0), starts, end)
    idx = jnp.asarray(g["save_idx"])
    return tmap(lambda v: v[idx], bps)
