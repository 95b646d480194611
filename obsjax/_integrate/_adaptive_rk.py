"""Batched adaptive explicit Runge–Kutta integration, each member with its own step size.

One entry point, :func:`adaptive_rk_solve`, integrates B independent initial-value problems

    dy_b/dt = f(t, y_b, args_b),   y_b(t0_b) = y0_b,   b = 1, …, B,

with an explicit Runge–Kutta pair of diffrax (``Tsit5``, ``Dopri5``, ``Bosh3``, ``Dopri8``, …: its
Butcher tableau, embedded error estimate and dense interpolant are read from the solver) and the
step-size control of ``diffrax.PIDController``, in one loop whose every iteration advances every
member by one step attempt of its own size.  Each member accepts or rejects its own step; finished
members are masked.  Compared with ``jax.vmap(diffeqsolve)`` the loop carries no solver objects and
evaluates no dense output unless a save time falls inside a step; compared with a lock-step solve of
the stacked batch (one step size for all, set by the worst member) no member takes steps it does not
need.

Semantics are diffrax's, member by member (``tests/test_adaptive_rk.py`` compares the solution and
the per-member step counts with ``diffeqsolve``):

- error norm ``norm(err / (atol + rtol · max(|y0|, |y1|)))``, ``norm`` the controller's (RMS by
  default), NaN in the error read as ∞; a step is kept when the norm is below 1;
- the next step ``h · clip(safety · ε_n^{β1} ε_{n-1}^{β2} ε_{n-2}^{β3}, factormin, factormax)`` with
  ``β1 = (pcoeff + icoeff + dcoeff)/q``, ``β2 = −(pcoeff + 2 dcoeff)/q``, ``β3 = dcoeff/q``, q the
  solver's error order, and a factor below ``safety`` after a rejection;
  ``dtmin``/``dtmax``/``force_dtmin`` as there;
- the first step of every segment from the initial step selection of Hairer, Nørsett & Wanner
  (Solving Ordinary Differential Equations I, 2nd ed., Springer 1993, §II.4; diffrax's
  ``PIDController`` implements it too), two evaluations of f, unless ``dt0`` is given; steps that
  would end within 100 ULP of a segment end are rounded onto it.  (diffrax 0.7's ``diffeqsolve``
  wraps its terms before the controller sees them, so the selection is skipped there and every
  solve given ``dt0=None`` starts with a step of 0.01; pass ``dt0=0.01`` to reproduce it step for
  step.)

**Segments, resets and jumps.**  ``reset_ts`` (e.g. t0 + kT, Chen & Yen's covariance resets) and
``jump_ts`` (times where f is discontinuous) cut [t0, t1] into segments.  Each member steps exactly
onto each reset time (onto the last float before a jump time, and restarts at it), applies
``reset(t, y, args)`` at a reset time, and starts the segment afresh: new initial step, new
controller history, first-same-as-last stage recomputed, exactly as a separate ``diffeqsolve`` per
segment would.  All segments of all members run in the one loop, so a member that needs few steps in
one segment does not wait for the others there.

**Derivative in the reset and jump times.**  The steps do not move with a reset or jump time τ
(the times of the loop carry no derivative of τ).  A shift δτ enters at arrival through the jump
condition: the state leaving τ is y⁺ + δτ (∂reset/∂t + ∂reset/∂y f⁻ − f⁺), f⁻ the vector field that
ends the segment, f⁺ the one that starts the next (at a jump time, reset is the identity, and
f⁻ − f⁺ is the jump of the vector field).  This is the first-order motion of the exact solution,
evaluated on the computed one; it needs two evaluations of f at each arrival, and only where the
derivative is taken (a custom JVP).  The segmented diffrax solve of ``simulate`` does the same
(``_segments.py``), so both take the same steps and agree to rounding.  Differentiating steps that
move with τ instead (as this loop did before) gives a derivative that differs from the exact one by
the tolerance, somewhat more than this form does (on Chen & Yen's example, ∂J/∂T at rtol 1e-6 is
2.1e-4 from the exact one against 1.1e-4 here; at 1e-8, 3e-6 against 7e-7), and one that is far off where the vector field has kinks the solver
steps over (band-limited noise: 27 % against 0.07 % at rtol 1e-6, see ``tune``).  It is also dearer:
tuning (γ, p0, T) of Chen & Yen's observer in forward mode cost 4.3 forward passes with the times
carrying T's derivative, 3.0 now.  t1, the save times and t0 keep their own derivatives.

**Layout.**  The members' states are flattened into one (B, n) array for the loop (one operation
per step of the bookkeeping instead of one per leaf); `vector_field` and `reset` still see the
pytree of one member.

**Saving.**  A save time inside an accepted step is evaluated with the solver's dense interpolant
(diffrax's interpolation class); a save time at a reset time records the state after the reset
(right-continuous, like ``obsjax.simulate``; a save time within the schedule's tolerance of a reset
time, 1e-9·(t1 − t0) plus four ulp of the times, counts as on it); save times at t1 record the final state.  Steps are
never shortened for saving.

**Status** per member: 0 success; 1 not finished (``max_steps`` attempts, or the step size
underflowed on finite candidates); 2 non-finite state or vector field (including a step size that
underflowed on a non-finite candidate: the solution left the domain of the vector field).  Values a
failed member did not reach are NaN.

**Differentiation** (``adjoint``): ``diffrax.RecursiveCheckpointAdjoint`` (default; reverse mode
through equinox's checkpointed while loop with ``checkpoints`` checkpoints, as diffrax),
``diffrax.ForwardMode`` (a ``lax.while_loop``: forward mode, ``jax.jvp``/``jax.jacfwd``),
``diffrax.DirectAdjoint`` (a bounded loop, both modes).  As in diffrax, the step-size decisions
carry no derivative (``stop_gradient``); the solution's derivative is that of the discrete scheme on
the chosen steps.  A step rejected because its stages left the domain of the vector field (NaN
stages across an undeclared switch) contributes nothing to the derivative: in reverse mode each such
stage's derivative is zero (:func:`_status.finite_gradient`; with ``DirectAdjoint`` its tangents
are masked, which serves both modes), the reset is applied to the candidate of an arriving member
only and the dense interpolant to those of members with something to save; in forward mode the
rejection's select drops its tangent.  (Such a switch, if it is one in t, still
needs declaring for the derivative in t0: the times of every step move with t0, and a switch the
loop does not know of would move with them.)

**Contract for a back-end** (how ``simulate``/``simulate_batch``/``monte_carlo`` drive it): ``y`` is
the joint plant–observer state ``(x, z)`` with a leading batch axis; ``vector_field`` is the
per-member drift ``f(t, (x, z), args)``; ``args`` the per-member (``args_axes=0``) or shared
(``None``) plant, observer and noise path; ``reset = lambda t, y, args: (y[0], observer.reset(t,
y[1]))`` with ``reset_ts = t0 + T·k``, k = 1 … max_segments − 1 (times at or beyond t1 are ignored,
so a traced T needs only a static bound on the number of segments); ``jump_ts`` the plant's; ``ts``
the save times.  ``max_steps`` bounds the step attempts of a member over the whole horizon (all
segments together).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jax.flatten_util import ravel_pytree
import lineax.internal as lxi
import numpy as np
import optimistix as optx

# the status codes of every back-end (SOLVER_FAILED here: max_steps attempts, or step-size underflow)
from . import _schedule
from ._status import NONFINITE, SOLVER_FAILED, SUCCESS, finite_gradient
_RUNNING = -1

tmap = jtu.tree_map


class AdaptiveRKSolution(eqx.Module):
    """Result of :func:`adaptive_rk_solve` (B members, S save times).

    - `ts`: (B, S) save times.
    - `ys`: the state at the save times, each leaf (B, S, ...); NaN where a failed member did not
      get.
    - `t1`: (B,) end time; `y1`: the final state, each leaf (B, ...) (NaN for failed members).
    - `status`: (B,) int32, 0 success, 1 not finished (max_steps or step-size underflow), 2
      non-finite.
    - `num_steps`, `num_accepted_steps`, `num_rejected_steps`: (B,) int32 step attempts of each
      member, all segments together (initial step selections are not counted, as in diffrax's
      statistics).
    """

    ts: jax.Array
    ys: Any
    t1: jax.Array
    y1: Any
    status: jax.Array
    num_steps: jax.Array
    num_accepted_steps: jax.Array
    num_rejected_steps: jax.Array


# ------------------------------------------------------------------------------------------- the
# method


class _Method(NamedTuple):
    a: np.ndarray  # (s, s) strictly lower
    b: np.ndarray  # (s,)
    b_error: np.ndarray  # (s,)
    c: np.ndarray  # (s,)
    fsal: bool
    order: float  # error order q of the controller's exponents
    interpolation: Callable


def supports_solver(solver) -> bool:
    """Whether `solver` is an explicit Runge–Kutta pair of diffrax with an embedded error estimate."""
    tab = getattr(solver, "tableau", None)
    return (
        isinstance(solver, diffrax.AbstractERK)
        and isinstance(tab, diffrax.ButcherTableau)
        and tab.b_error is not None
        and not tab.implicit
    )


def supports_adjoint(adjoint) -> bool:
    """Whether the loop implements `adjoint` (``None`` is diffrax's default): see ``_loop_kind``."""
    try:
        _loop_kind(adjoint)
    except ValueError:
        return False
    return True


def _method_of(solver, controller) -> _Method:
    tab = getattr(solver, "tableau", None)
    if not supports_solver(solver):
        raise ValueError(
            "`solver` must be an explicit Runge–Kutta pair of diffrax with an embedded error "
            f"estimate (Tsit5, Dopri5, Bosh3, Dopri8, ...), got {type(solver).__name__}."
        )
    s = tab.num_stages
    a = np.zeros((s, s))
    for i, row in enumerate(tab.a_lower):
        a[i + 1, : i + 1] = np.asarray(row, dtype=np.float64)
    c = np.concatenate([[tab.c1], np.asarray(tab.c, dtype=np.float64)])
    order = controller.error_order
    if order is None:
        order = solver.error_order(diffrax.ODETerm(lambda t, y, args: y))
    return _Method(
        a,
        np.asarray(tab.b_sol, np.float64),
        np.asarray(tab.b_error, np.float64),
        c,
        bool(tab.fsal),
        float(order),
        solver.interpolation_cls,
    )


def _loop_kind(adjoint):
    if adjoint is None:
        return "checkpointed", None
    if type(adjoint) is diffrax.RecursiveCheckpointAdjoint:
        return "checkpointed", adjoint.checkpoints
    if isinstance(adjoint, diffrax.ForwardMode):
        return "lax", None
    if type(adjoint) is diffrax.DirectAdjoint:
        return "bounded", None
    raise ValueError(
        "`adjoint` must be diffrax.RecursiveCheckpointAdjoint (reverse mode), diffrax.ForwardMode "
        f"(forward mode) or diffrax.DirectAdjoint (both), got {type(adjoint).__name__}."
    )


def _check_controller(controller):
    if type(controller) is not diffrax.PIDController:
        raise ValueError(
            "`stepsize_controller` must be a diffrax.PIDController (pass the jump times of a "
            f"ClipStepSizeController as `jump_ts`), got {type(controller).__name__}."
        )
    return controller


# ----------------------------------------------------------------------------------------------
# helpers


def _batch_size(y0) -> int:
    leaves = jtu.tree_leaves(y0)
    if not leaves:
        raise ValueError("`y0` must hold at least one array.")
    sizes = {jnp.shape(x)[0] if jnp.ndim(x) else None for x in leaves}
    if len(sizes) != 1 or None in sizes:
        raise ValueError(
            f"every leaf of `y0` must have the same leading batch axis, got shapes "
            f"{[tuple(jnp.shape(x)) for x in leaves]}."
        )
    for x in leaves:
        if not jnp.issubdtype(jnp.result_type(x), jnp.inexact):
            raise ValueError(
                f"`y0` must be floating point, got a leaf of dtype {jnp.result_type(x)}."
            )
    return sizes.pop()


def _per_member(x, B, name, dtype, trailing=0):
    """Broadcast a time array of shape (…) or (B, …) to (B, …) (`trailing` trailing axes)."""
    x = jnp.asarray(x, dtype)
    if x.ndim == trailing:
        return jnp.broadcast_to(x, (B,) + x.shape)
    if x.ndim == trailing + 1 and x.shape[0] == B:
        return x
    raise ValueError(
        f"`{name}` must have {trailing} axes (shared by the batch) or {trailing + 1} with a "
        "leading "
        f"axis of {B} (one per member), got shape {tuple(x.shape)}."
    )


def _where(pred, a, b):
    """Member-wise select between pytrees with a leading batch axis."""
    return tmap(lambda u, v: jnp.where(pred.reshape(pred.shape + (1,) * (u.ndim - 1)), u, v), a, b)


def _axpy(y, coeffs, ks):
    """y + Σ_j coeffs[j]·ks[j] over the non-zero coefficients (ks: list of pytrees)."""
    terms = [(float(w), k) for w, k in zip(coeffs, ks) if w != 0.0]
    if not terms:
        return y
    return tmap(
        lambda y0, *kk: y0 + sum(w * v for (w, _), v in zip(terms, kk)), y, *[k for _, k in terms]
    )


def _scale_member(pred, x):
    """x (B, ...) times a per-member scalar pred (B,)."""
    return pred.reshape(pred.shape + (1,) * (x.ndim - 1)) * x


def _all_finite(tree, B):
    out = jnp.ones((B,), bool)
    for x in jtu.tree_leaves(tree):
        out = out & jnp.all(jnp.isfinite(x.reshape(B, -1)), axis=1)
    return out


def _batched_norm(norm, unravel):
    """Member-wise `norm` of the (B, n) flattened states (`unravel`: one member's row to its pytree).

    diffrax's default RMS norm (``optimistix.rms_norm``) is written here with sums of squares: its
    own ``tree_dot`` becomes a batched ``dot_general`` per leaf under ``jax.vmap``, which XLA's CPU
    backend runs as a small matrix product per member.  Other norms are ``jax.vmap``-ed.
    """
    if norm is not optx.rms_norm and norm is not lxi.rms_norm:
        return jax.vmap(lambda row: norm(unravel(row)))

    def rms(tree):
        leaves = jtu.tree_leaves(tree)
        B = leaves[0].shape[0]
        n = sum(int(np.prod(x.shape[1:])) for x in leaves)
        if n == 0:
            return jnp.zeros((B,), leaves[0].dtype)
        return jnp.sqrt(sum(_sum_squares(x.reshape(B, -1)) for x in leaves) / n)

    return rms


def _sum_squares(x2d):
    """Σ_j x[:, j]² of a (B, n) array; for small n as a sum of columns (elementwise operations
    across the batch, which XLA's CPU backend vectorises; a reduction over a short minor axis it
    does not)."""
    n = x2d.shape[1]
    if n > 32:
        return jnp.sum(x2d * x2d, axis=1)
    return sum(x2d[:, j] * x2d[:, j] for j in range(n))


def _prevbefore(x, n=1):
    """The n-th float below x, without derivative (a loop, not n chained operations: the graph stays
    small)."""
    x = jax.lax.stop_gradient(x)
    down = lambda _, v: jnp.nextafter(v, jnp.array(-jnp.inf, v.dtype))
    return down(0, x) if n == 1 else jax.lax.fori_loop(0, n, down, x)


# ----------------------------------------------------------------------------------------------
# targets


class _Targets(NamedTuple):
    """Segment ends per member, (B, M) each: the time, where the step lands, 100 ULP below that,
    flags."""

    value: jax.Array
    end: jax.Array
    floor: jax.Array
    reset: jax.Array
    final: jax.Array
    motion: jax.Array  # 0 in value; the derivative of a reset or jump time (not of t1)
    tol: jax.Array  # (B,) the schedule's time tolerance of the member's horizon


def _targets(t0, t1, reset_ts, jump_ts, B, dtype) -> tuple[_Targets, jax.Array]:
    tol_b = jax.lax.stop_gradient(_schedule.tolerance_of(t0, t1))  # as simulate's schedule
    rv = None if reset_ts is None else _per_member(reset_ts, B, "reset_ts", dtype, trailing=1)
    jv = None if jump_ts is None else _per_member(jump_ts, B, "jump_ts", dtype, trailing=1)
    reset_on_jump = None
    if rv is not None and jv is not None:
        # A reset at a jump time is one target: the step lands one float before it (the vector field
        # there is the one before the jump), the reset is applied at it, the next segment starts there;
        # its derivative in the reset time is the one from below, as in the other back-ends.  The jump
        # entry itself is moved past t1 (ignored).
        # Each time is compared with its nearest neighbours in the other sorted list: memory and
        # work O(B (R + J) log), not the O(B R J) of an outer comparison (thousands of resets on a
        # plant switching thousands of times would need gigabytes).
        rs, js = jax.lax.stop_gradient(rv), jax.lax.stop_gradient(jv)
        reset_on_jump = _has_neighbour(rs, js, tol_b)
        jump_on_reset = _has_neighbour(js, rs, tol_b)
        jv = jnp.where(jump_on_reset, jnp.maximum(t1[:, None], jv) + 1.0, jv)
    parts, flags, jumps = [], [], []
    for v, is_reset in ((rv, True), (jv, False)):
        if v is not None:
            parts.append(v)
            flags.append(jnp.full(v.shape, is_reset))
            jumps.append(reset_on_jump if is_reset and reset_on_jump is not None else jnp.full(v.shape, not is_reset))
    parts.append(t1[:, None])
    flags.append(jnp.zeros((B, 1), bool))
    jumps.append(jnp.zeros((B, 1), bool))
    value = jnp.concatenate(parts, axis=1)
    order = jnp.argsort(jax.lax.stop_gradient(value), axis=1)
    value = jnp.take_along_axis(value, order, axis=1)
    reset = jnp.take_along_axis(jnp.concatenate(flags, axis=1), order, axis=1)
    jump = jnp.take_along_axis(jnp.concatenate(jumps, axis=1), order, axis=1)
    tol = tol_b[:, None]
    fixed = jax.lax.stop_gradient(value)
    final = fixed >= (t1[:, None] - tol)
    # The steps do not move with a reset or jump time: its derivative enters through the jump
    # condition at arrival (`_arrival`), carried by `motion` (value 0).  t1 keeps its own.
    motion = jnp.where(final, 0.0, value - fixed)
    value = jnp.where(final, t1[:, None], fixed)
    reset = reset & ~final
    jump = jump & ~final
    # a jump (or a reset at a jump time): land on the float before it (the vector field there is the
    # left one)
    end = jnp.where(jump, _prevbefore(value), value)
    floor = _prevbefore(end, 100)
    first = jnp.sum(fixed <= (t0[:, None] + tol), axis=1).astype(jnp.int32)
    first = jnp.minimum(first, value.shape[1] - 1)
    return _Targets(value, end, floor, reset, final, motion, tol_b), first


def _has_neighbour(a, b, tol):
    """(B, Ra) bool: a[i, r] is within tol[i] of some b[i, :] (NaN is near nothing).

    The nearest entries of the sorted b bracket a[i, r] (searchsorted); if any entry is within tol,
    one of those two is."""
    if b.shape[1] == 0 or a.shape[1] == 0:
        return jnp.zeros(a.shape, bool)

    def one(ai, bi, ti):
        bs = jnp.sort(bi)  # NaNs last
        k = jnp.searchsorted(bs, ai)
        lo = bs[jnp.clip(k - 1, 0, bs.shape[0] - 1)]
        hi = bs[jnp.clip(k, 0, bs.shape[0] - 1)]
        return (jnp.abs(ai - lo) <= ti) | (jnp.abs(ai - hi) <= ti)

    return jax.vmap(one)(a, b, tol)


def _pick(arr, k):
    return jnp.take_along_axis(arr, k[:, None], axis=1)[:, 0]


# -------------------------------------------------------------------------------------------------
# loop


class _Carry(NamedTuple):
    tprev: jax.Array  # (B,) start of the current step (= the time of y)
    tnext: jax.Array  # (B,) end of the step to attempt (= tprev while initialising or finished)
    y: Any
    f0: Any  # f(tprev, y) when the method is FSAL (else unused zeros)
    init: jax.Array  # (B,) the member starts a segment: initial step selection this iteration
    seg: jax.Array  # (B,) index of the current segment's end in the targets
    inv_err: jax.Array  # (B,) controller history ε_{n-1}, ε_{n-2} (1/scaled error)
    inv_err2: jax.Array
    at_dtmin: jax.Array
    save_idx: jax.Array  # (B,) next save time to fill
    status: jax.Array
    num_steps: jax.Array
    num_accepted: jax.Array
    seg_steps: jax.Array  # (B,) step attempts in the current segment
    ys: Any  # buffers (B, S + 1, ...): column S absorbs the writes of members that do not save


def adaptive_rk_solve(
    vector_field: Callable,
    y0,
    t0,
    t1,
    *,
    args=None,
    args_axes=None,
    solver: diffrax.AbstractSolver | None = None,
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    dt0=None,
    ts=None,
    reset: Callable | None = None,
    reset_ts=None,
    jump_ts=None,
    max_steps: int = 4096,
    max_steps_per_segment: int | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    block_size: int | None = None,
) -> AdaptiveRKSolution:
    """Integrate a batch of ODEs with an adaptive explicit Runge–Kutta pair, each member its own
    steps.

    See the module docstring for the method, the segments and the status codes.

    **Arguments:**

    - `vector_field`: ``f(t, y, args) -> dy/dt`` for ONE member: ``t`` a scalar, ``y`` a pytree
      without the batch axis, ``args`` one member's args; returns a pytree like ``y``.  It is
      ``jax.vmap``-ed over the members.
    - `y0`: initial states, a pytree whose leaves all carry a leading batch axis of size B.
    - `t0`, `t1`: start and end, scalars (shared) or (B,) (one per member), t1 ≥ t0.
    - `args`: passed to `vector_field` and `reset`; `args_axes` its ``jax.vmap`` in_axes (``None``:
      shared, ``0``: a leading batch axis on every leaf, or a pytree prefix of in_axes).
    - `solver`: an explicit diffrax Runge–Kutta pair (default ``diffrax.Tsit5()``).
    - `stepsize_controller`: a ``diffrax.PIDController`` (default ``rtol=1e-6, atol=1e-8``).
    - `dt0`: first step of every segment (scalar or (B,)); ``None``: diffrax's initial step
      selection.
    - `ts`: save times, (S,) or (B, S), non-decreasing within [t0, t1]; ``None`` saves t1 only.
    - `reset`: ``reset(t, y, args) -> y`` for one member, applied at every time of `reset_ts`.
    - `reset_ts`: (K,) or (B, K) sorted reset times; those at or beyond t1 (or at t0) are ignored.
    - `jump_ts`: (J,) or (B, J) sorted times where `vector_field` is discontinuous in t.
    - `max_steps`: the most step attempts of one member over [t0, t1] (all segments).
    - `max_steps_per_segment`: the most step attempts of one member in one segment (``None``: no
      bound besides `max_steps`), as ``diffeqsolve``'s `max_steps` bounds each segment's solve.
    - `adjoint`: ``diffrax.RecursiveCheckpointAdjoint()`` (default), ``diffrax.ForwardMode()`` or
      ``diffrax.DirectAdjoint()``: which modes of differentiation the loop supports.
    - `block_size`: the most members one loop integrates together; a larger batch is split into
      blocks of (about) equal size that run one after another (``jax.lax.map``), each block its own
      loop.  ``None`` (default): :func:`default_block_size`, i.e. blocks whose state arrays stay
      within the processor's cache on the CPU, and the whole batch at once on other back-ends.  The
      result does not depend on it beyond rounding (members are independent; XLA may round a
      block of a single member differently, 1e-15 in a test); only the speed does.

    **Returns:** an :class:`AdaptiveRKSolution`.

    **Example:**::

        f = lambda t, y, args: -args * y
        sol = adaptive_rk_solve(f, jnp.ones((8, 3)), 0.0, 1.0, args=jnp.linspace(1.0, 2.0, 8),
                                args_axes=0, ts=jnp.linspace(0.0, 1.0, 11))
        sol.ys.shape, sol.num_accepted_steps  # (8, 11, 3), per-member step counts
    """
    solver = diffrax.Tsit5() if solver is None else solver
    ctrl = _check_controller(
        diffrax.PIDController(rtol=1e-6, atol=1e-8)
        if stepsize_controller is None
        else stepsize_controller
    )
    method = _method_of(solver, ctrl)
    kind, checkpoints = _loop_kind(adjoint)
    if not (isinstance(max_steps, int) and max_steps > 0):
        raise ValueError(f"`max_steps` must be a positive int, got {max_steps!r}.")
    if max_steps_per_segment is not None and not (
        isinstance(max_steps_per_segment, int) and max_steps_per_segment > 0
    ):
        raise ValueError(
            f"`max_steps_per_segment` must be a positive int or None, got {max_steps_per_segment!r}."
        )
    if reset_ts is not None and reset is None:
        raise ValueError("`reset_ts` needs `reset` (the map applied to the state at those times).")
    B = _batch_size(y0)
    y0 = tmap(jnp.asarray, y0)
    dtype = jnp.result_type(*jtu.tree_leaves(y0), jnp.asarray(t0), jnp.asarray(t1), float)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(f"times and states must be real floating point, got {dtype}.")
    t0 = _per_member(t0, B, "t0", dtype)
    t1 = _per_member(t1, B, "t1", dtype)
    ts = t1[:, None] if ts is None else _per_member(ts, B, "ts", dtype, trailing=1)
    _check_concrete(t0, t1, ts, max_steps)
    targets, seg0 = _targets(t0, t1, reset_ts, jump_ts, B, dtype)
    dt0 = None if dt0 is None else _per_member(dt0, B, "dt0", dtype)

    # The loop works on one (B, n) array (the members' states flattened): one operation per step of
    # the bookkeeping instead of one per leaf.
    flat0, ravel, unravel = _packing(y0)

    def field(t, u, a):
        return ravel(vector_field(t, unravel(u), a))

    F = jax.vmap(field, in_axes=(0, 0, args_axes))
    # A stage of a step: (f, h·f).  In reverse mode a stage that left the domain of the vector field (a
    # rejected step across an undeclared switch) gets a zero derivative, member by member: its cotangent is
    # zero but its partial derivatives are NaN, and 0 × NaN made the whole batch's gradient NaN (with the
    # product h·f inside, so that the step length, which carries t0's derivative, is spared too).  (A
    # custom_vjp, so the forward-mode loop keeps the plain field, where a where() drops the rejected
    # tangents; DirectAdjoint's bounded loop allows both modes and gets a custom_jvp that masks tangents.)
    def stage(h, t, u, a):
        f = field(t, u, a)
        return f, h * f

    F_stage = jax.vmap(stage, in_axes=(0, 0, 0, args_axes))
    if kind != "lax":  # reverse mode (DirectAdjoint: both modes, a custom_jvp)
        both = kind == "bounded"
        F_stage = jax.vmap(
            lambda h, t, u, a: finite_gradient(stage, h, t, u, a, both_modes=both),
            in_axes=(0, 0, 0, args_axes),
        )
    R = None
    if reset is not None:
        R = jax.vmap(lambda t, u, a: ravel(reset(t, unravel(u), a)), in_axes=(0, 0, args_axes))
    norm = _batched_norm(ctrl.norm, unravel)
    n_targets = targets.value.shape[1]

    def loop(flat0, t0, seg0, ts, targets, dt0, args):
        Bk = flat0.shape[0]
        step = _make_body(
            F, F_stage, R, args, method, ctrl, norm, dt0, targets, ts,
            (max_steps, max_steps_per_segment), kind, Bk, solver,
        )
        return eqxi.while_loop(
            lambda c: jnp.any(c.status == _RUNNING),
            step,
            _initial_carry(flat0, t0, seg0, ts, Bk, dtype),
            max_steps=max_steps + n_targets + 1,
            buffers=lambda c: c.ys,
            kind=kind,
            checkpoints=checkpoints,
        )

    if block_size is None:
        block_size = default_block_size(flat0.shape[1], flat0.dtype)
    elif isinstance(block_size, bool) or not isinstance(block_size, (int, np.integer)) or (
        block_size < 1
    ):
        raise ValueError(f"`block_size` must be a positive int or None, got {block_size!r}.")
    per_member = (flat0, t0, seg0, ts, targets, dt0)
    if B <= block_size:
        final = loop(*per_member, args)
    else:
        final = _blockwise(loop, per_member, args, args_axes, B, int(block_size))
    return _finish(final, ts, t1, jax.vmap(jax.vmap(unravel)), jax.vmap(unravel))


#: Bytes of one member-state array of a block on the CPU (see :func:`default_block_size`).
CPU_BLOCK_BYTES = 32 * 1024


def default_block_size(n: int, dtype=jnp.float64) -> int | float:
    """Members per block of the loop for states of `n` components (the default of `block_size`).

    Every operation of an iteration reads and writes (B, n) arrays, some twenty of them per step of a
    seven-stage pair.  On the CPU a batch whose arrays leave the cache is slower per member than
    the same batch run in blocks: on Chen & Yen's example (n = 12, 4096 members, Dopri5) one loop
    took 1205 ns per member and step, blocks of 1024, 512, 256 and 128 took 940, 870, 825 and 865 ns
    (smaller blocks also wait less for their slowest member).  The default is the largest power of
    two whose (block, n) array is at most ``CPU_BLOCK_BYTES`` (32 KiB), and at least 64; on other
    back-ends (GPU) the whole batch (infinity).
    """
    if jax.default_backend() != "cpu":
        return float("inf")
    per_member = max(1, int(n)) * jnp.dtype(dtype).itemsize
    return max(64, 1 << max(0, (CPU_BLOCK_BYTES // per_member).bit_length() - 1))


def _blockwise(loop, per_member, args, args_axes, B, block_size):
    """`loop` over blocks of the members one after another; the final carries stacked again.

    The batch is cut into ceil(B / block_size) blocks of equal size (the last member repeated to
    fill the last block: at most one member per block is padding).  The leaves of `args` that
    `args_axes` maps are cut along their mapped axis; the others are shared by every block.
    """
    nb = -(-B // block_size)
    c = -(-B // nb)
    pad = nb * c - B

    def blocks(v):
        if pad:
            v = jnp.concatenate([v, jnp.broadcast_to(v[-1:], (pad,) + v.shape[1:])])
        return v.reshape((nb, c) + v.shape[1:])

    leaves, treedef = jtu.tree_flatten(args)
    axes = _leaf_axes(args, args_axes, treedef)
    mapped = []
    for v, ax in zip(leaves, axes):
        if ax is _SHARED:
            continue
        v = jnp.moveaxis(jnp.asarray(v), ax, 0)
        if v.shape[0] != B:
            raise ValueError(
                f"every leaf of `args` mapped by `args_axes` must have {B} members (the batch of "
                f"`y0`) along its mapped axis, got a leaf of shape {tuple(v.shape)} (axis {ax} first)."
            )
        mapped.append(blocks(v))

    def one(xs):
        pm, ml = xs
        it = iter(ml)
        lv = [v if ax is _SHARED else jnp.moveaxis(next(it), 0, ax) for v, ax in zip(leaves, axes)]
        return loop(*pm, jtu.tree_unflatten(treedef, lv))

    out = jax.lax.map(one, (tmap(blocks, per_member), mapped))
    return tmap(lambda v: v.reshape((nb * c,) + v.shape[2:])[:B], out)


_SHARED = object()  # the in_axes of a leaf of `args` that every member shares


def _leaf_axes(args, args_axes, treedef):
    """The ``jax.vmap`` in_axes of every leaf of `args` (the prefix `args_axes` broadcast to the
    leaves; ``_SHARED`` for None)."""
    full = jtu.tree_map(
        lambda ax, sub: jtu.tree_map(lambda _: _SHARED if ax is None else ax, sub),
        args_axes,
        args,
        is_leaf=lambda x: x is None,
    )
    axes = treedef.flatten_up_to(full)
    if any(ax is not _SHARED and not isinstance(ax, (int, np.integer)) for ax in axes):
        raise ValueError(f"`args_axes` must give an int or None per leaf of `args`, got {args_axes!r}.")
    return axes


def _packing(y0):
    """(B, n) flattened initial states, and ravel/unravel of one member's state pytree."""
    _, unravel = ravel_pytree(tmap(lambda x: x[0], y0))
    ravel = lambda tree: ravel_pytree(tree)[0]  # noqa: E731
    return jax.vmap(ravel)(y0), ravel, unravel


def _check_concrete(t0, t1, ts, max_steps):
    try:
        a, b, s = (np.asarray(v) for v in (t0, t1, ts))
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return
    if np.any(b < a):
        raise ValueError("`t1` must be ≥ `t0` for every member.")
    if s.shape[1] and (
        np.any(np.diff(s, axis=1) < 0) or np.any(s < a[:, None]) or np.any(s > b[:, None])
    ):
        raise ValueError("`ts` must be non-decreasing and lie within [t0, t1].")


def _initial_carry(y0, t0, seg0, ts, B, dtype):
    S = ts.shape[1]
    ones = jnp.ones((B,), dtype)
    zeros_i = jnp.zeros((B,), jnp.int32)
    finite = _all_finite(y0, B)
    return _Carry(
        tprev=t0,
        tnext=t0,
        y=_where(finite, y0, tmap(jnp.zeros_like, y0)),
        f0=tmap(jnp.zeros_like, y0),
        init=jnp.ones((B,), bool),
        seg=seg0,
        inv_err=ones,
        inv_err2=ones,
        at_dtmin=jnp.zeros((B,), bool),
        save_idx=zeros_i,
        status=jnp.where(finite, _RUNNING, NONFINITE).astype(jnp.int32),
        num_steps=zeros_i,
        num_accepted=zeros_i,
        seg_steps=zeros_i,
        ys=tmap(lambda x: jnp.zeros((B, S + 1) + x.shape[1:], x.dtype), y0),
    )


def _make_body(
    F, F_stage, R, args, method, ctrl, norm_b, dt0, targets, ts, max_steps, kind, B, solver
):
    a, b, be, c, fsal = method.a, method.b, method.b_error, method.c, method.fsal
    s = len(b)
    first = 1 if fsal else 0
    rows = jnp.arange(B)
    S = ts.shape[1]


    def scale_of(y):
        return tmap(lambda u: ctrl.atol + jnp.abs(u) * ctrl.rtol, y)

    def body(cr: _Carry) -> _Carry:
        running = cr.status == _RUNNING
        init = running & cr.init
        stepping = running & ~cr.init
        tprev, tnext, y = cr.tprev, cr.tnext, cr.y
        dt = tnext - tprev  # 0 for initialising and finished members
        end = _pick(targets.end, cr.seg)
        # -- stages; an initialising member uses the first two evaluations for the initial step
        # selection
        fs = [cr.f0] if fsal else []
        ks = [tmap(lambda v: _scale_member(dt, v), cr.f0)] if fsal else []
        h0 = g0 = None
        for i in range(first, s):
            yi = _axpy(y, a[i, :i], ks)
            ti = jnp.where(c[i] == 1.0, tnext, tprev + c[i] * dt)
            if i == first + 1 and dt0 is None:
                ti = jnp.where(init, tprev + h0, ti)
                probe = tmap(lambda u, g, h=h0: u + _scale_member(h, g), y, g0)
                yi = _where(init, probe, yi)
            fi, ki = F_stage(dt, ti, yi, args)
            if i == first:
                g0 = fi
                h0, d1 = _probe_step(y, g0, scale_of(y), norm_b)
            fs.append(fi)
            ks.append(ki)
        h_init = _initial_step(
            init, y, g0, fs[first + 1], h0, d1, dt0, scale_of, norm_b, method, ctrl
        )
        y1 = _axpy(y, b, ks)
        y_err = tmap(
            lambda e: jnp.where(jnp.isnan(e), jnp.inf, e), _axpy(tmap(jnp.zeros_like, y), be, ks)
        )
        keep, dt_next, inv_err, inv_err2, at_dtmin = _adapt(
            y, y1, y_err, dt, cr, ctrl, method, norm_b
        )
        # -- bookkeeping of stepping members
        acc = stepping & keep
        arrive = acc & (tnext == end)
        value = _pick(targets.value, cr.seg)
        is_final = _pick(targets.final, cr.seg)
        do_reset = _pick(targets.reset, cr.seg)
        nt0 = jnp.minimum(jnp.where(keep, tnext, tprev), end)
        nt1 = _clip_to_end(nt0, nt0 + dt_next, end, _pick(targets.floor, cr.seg), keep)
        limit = jnp.where(arrive, value - targets.tol, tnext)
        ys, save_idx = _save(cr, acc, limit, tprev, tnext, y, y1, ks, ts, rows, S, solver, kind)
        # (members that do not arrive reset their own state, finite, not a rejected candidate: the
        # result is dropped either way, but a candidate outside the reset's domain would make its
        # partial derivatives, times the zero cotangent, NaN)
        y_arr = _arrival(
            _pick(targets.motion, cr.seg), value, do_reset, arrive, _where(arrive, y1, y),
            fs[-1] if fsal else None, args, F=F, R=R,
        )
        y_new = _where(arrive, y_arr, _where(acc, y1, y))
        f0_new = fs[-1] if fsal else cr.f0
        f0_new = _where(acc & ~arrive, f0_new, cr.f0)
        # -- members that start a segment now (initialised this iteration) or next (arrived)
        t_start = jnp.where(arrive, value, nt0)
        tn_step = jnp.where(arrive, value, nt1)
        tn_init = jnp.minimum(tprev + h_init, end)
        new_init = (cr.init & ~init) | (arrive & ~is_final)
        tprev_new = jnp.where(init, tprev, jnp.where(stepping, t_start, tprev))
        tnext_new = jnp.where(init, tn_init, jnp.where(stepping & ~arrive, tn_step, tprev_new))
        f0_new = _where(init, g0, f0_new) if fsal else f0_new
        one = jnp.ones((B,), tprev.dtype)
        restart = init | arrive
        status = _new_status(
            cr, init, stepping, acc, arrive, is_final, y_new, g0, f0_new, nt0, nt1, max_steps, fsal,
            _all_finite(y1, B),
        )
        ok = status != NONFINITE
        return _Carry(
            tprev=tprev_new,
            tnext=jnp.where(status == _RUNNING, tnext_new, tprev_new),
            y=_where(ok, y_new, tmap(jnp.zeros_like, y_new)),
            f0=_where(ok, f0_new, tmap(jnp.zeros_like, f0_new)),
            init=new_init,
            seg=cr.seg + (arrive & ~is_final).astype(jnp.int32),
            inv_err=jnp.where(restart, one, jnp.where(stepping, inv_err, cr.inv_err)),
            inv_err2=jnp.where(restart, one, jnp.where(stepping, inv_err2, cr.inv_err2)),
            at_dtmin=jnp.where(restart, False, jnp.where(stepping, at_dtmin, cr.at_dtmin)),
            save_idx=save_idx,
            status=status,
            num_steps=cr.num_steps + stepping.astype(jnp.int32),
            seg_steps=jnp.where(arrive, 0, cr.seg_steps + stepping.astype(jnp.int32)),
            num_accepted=cr.num_accepted + acc.astype(jnp.int32),
            ys=ys,
        )

    return body


@eqx.filter_custom_jvp
def _arrival(d, tau, do_reset, arrive, y1, f_minus, args, *, F, R):
    """The state with which a member leaves a segment end τ: ``reset(τ, y⁻)`` where τ is a reset
    time, y⁻ itself at a jump time of the vector field.

    Its derivative includes the motion of τ: the steps do not move with τ, so a shift δτ of τ is
    the jump condition y⁺ + δτ·(∂reset/∂t + ∂reset/∂y f⁻ − f⁺), with f⁻ = f(τ⁻, y⁻) the vector
    field that ends the segment and f⁺ = f(τ, y⁺) the one that starts the next; `d` (value 0)
    carries δτ.  The two evaluations of f run only where the derivative is taken (a custom JVP:
    the forward pass does not pay for them), and only when τ has a derivative.  The loop calls it
    for every member at every iteration; the coefficients f⁻, f⁺ and ∂reset/∂t are used where
    `arrive` only, and set to 0 elsewhere and where they are not finite (a member in mid-segment,
    reset there, may leave the domain of f: its 0 · NaN would turn reverse mode's cotangent of τ
    into NaN)."""
    del d, f_minus, F, arrive
    return _act(tau, do_reset, y1, args, R)


def _act(tau, do_reset, y1, args, R):
    return y1 if R is None else _where(do_reset, R(tau, y1, args), y1)


@_arrival.def_jvp
def _arrival_jvp(primals, tangents, *, F, R):
    _, tau, do_reset, arrive, y1, f_minus, args = primals
    t_d, _, _, _, t_y1, _, t_args = tangents
    act = lambda y_, a_: _act(tau, do_reset, y_, a_, R)
    if t_y1 is None:
        t_y1 = tmap(jnp.zeros_like, y1)
    if t_d is None:
        return eqx.filter_jvp(act, (y1, args), (t_y1, t_args))

    def coefficient(pred, v):  # a primal coefficient of δτ: used where `pred`, finite, else 0
        return tmap(lambda u: _where(pred, jnp.where(jnp.isfinite(u), u, 0.0), jnp.zeros_like(u)), v)

    if f_minus is None:
        f_minus = F(_prevbefore(tau), y1, args)
    f_minus = coefficient(arrive, f_minus)
    moved = tmap(lambda t_, g: t_ + _scale_member(t_d, g), t_y1, f_minus)
    out, t_out = eqx.filter_jvp(act, (y1, args), (moved, t_args))
    if R is not None:  # ∂reset/∂t
        _, r_t = jax.jvp(lambda s: R(s, y1, args), (tau,), (jnp.ones_like(tau),))
        r_t = coefficient(arrive & do_reset, r_t)
        t_out = tmap(lambda t_, g: t_ + _scale_member(t_d, g), t_out, r_t)
    # f⁺ of a reset read one float below τ, as f⁻ (the same field unless a plant jump falls on τ: then
    # the derivative from below); at a jump time (no reset) f⁺ is the field after the jump
    f_plus = coefficient(arrive, F(jnp.where(do_reset, _prevbefore(tau), tau), out, args))
    return out, tmap(lambda t_, g: t_ - _scale_member(t_d, g), t_out, f_plus)


def _probe_step(y, g0, scale, norm_b):
    """h0 of diffrax's initial step selection (from f(t0, y0)), and d1."""
    d0 = norm_b(tmap(lambda u, s_: u / s_, y, scale))
    d1 = norm_b(tmap(lambda u, s_: u / s_, g0, scale))
    small = (d0 < 1e-5) | (d1 < 1e-5)
    h0 = jnp.where(small, 1e-6, 0.01 * (d0 / jnp.where(small, 1.0, d1)))
    return jax.lax.stop_gradient(h0), d1


def _initial_step(init, y, g0, g1, h0, d1, dt0, scale_of, norm_b, method, ctrl):
    """First step of a segment: dt0, or diffrax's selection from f(t0, y0) and f(t0 + h0, y0 + h0
    f0)."""
    if dt0 is None:
        scale = scale_of(y)
        d2 = norm_b(tmap(lambda u, v, s_: (u - v) / s_, g1, g0, scale)) / h0
        max_d = jnp.maximum(d1, d2)
        h1 = jnp.where(
            max_d <= 1e-15,
            jnp.maximum(1e-6, h0 * 1e-3),
            (0.01 / jnp.where(max_d <= 1e-15, 1.0, max_d)) ** (1 / method.order),
        )
        h = jax.lax.stop_gradient(jnp.minimum(100 * h0, h1))
    else:
        h = dt0
    if ctrl.dtmax is not None:
        h = jnp.minimum(h, ctrl.dtmax)
    if ctrl.dtmin is not None:
        h = jnp.maximum(h, ctrl.dtmin)
    return jnp.where(init, h, 0.0)


def _adapt(y, y1, y_err, dt, cr, ctrl, method, norm_b):
    """diffrax.PIDController.adapt_step_size, member-wise: (keep, next dt, ε history, at_dtmin)."""

    def scaled(u0, u1, e):
        nan = jnp.any(jnp.isnan(u1).reshape(u1.shape[0], -1), axis=1)
        u1 = jnp.where(nan.reshape(nan.shape + (1,) * (u1.ndim - 1)), u0, u1)
        return e / (ctrl.atol + jnp.maximum(jnp.abs(u0), jnp.abs(u1)) * ctrl.rtol)

    err = norm_b(tmap(scaled, y, y1, y_err))
    keep = err < 1
    if ctrl.dtmin is not None:
        keep = keep | cr.at_dtmin
    inv = jax.lax.stop_gradient(1 / err)
    q = method.order
    zero = lambda v: isinstance(v, (int, float)) and v == 0
    c1 = (ctrl.icoeff + ctrl.pcoeff + ctrl.dcoeff) / q
    c2 = -(ctrl.pcoeff + 2 * ctrl.dcoeff) / q
    c3 = ctrl.dcoeff / q
    f1 = 1 if zero(c1) else inv**c1
    f2 = 1 if zero(c2) else cr.inv_err**c2
    f3 = 1 if zero(c3) else cr.inv_err2**c3
    factor = jnp.clip(
        ctrl.safety * f1 * f2 * f3,
        min=jnp.where(keep, 1.0, ctrl.factormin),
        max=jnp.where(keep, ctrl.factormax, ctrl.safety),
    )
    # an overflowing candidate has a NaN error (inf − inf): reject it like any other step, not with a NaN
    # step size that every later step inherits (see GuardedController)
    factor = jax.lax.stop_gradient(jnp.where(jnp.isnan(factor), ctrl.factormin, factor))
    dt_next = dt * factor
    inv = jnp.where((inv == 0) | jnp.isinf(inv), 1.0, inv)
    at_dtmin = cr.at_dtmin
    if ctrl.dtmax is not None:
        dt_next = jnp.minimum(dt_next, ctrl.dtmax)
    if ctrl.dtmin is not None:
        dt_next = jnp.where(at_dtmin & (factor == 1), ctrl.dtmin, dt_next)
        at_dtmin = dt_next <= ctrl.dtmin
        dt_next = jnp.maximum(dt_next, ctrl.dtmin)
    inv_err = jnp.where(keep, inv, cr.inv_err)
    inv_err2 = jnp.where(keep, cr.inv_err, cr.inv_err2)
    return keep, dt_next, inv_err, inv_err2, at_dtmin


def _clip_to_end(tprev, tnext, end, floor, keep):
    """diffrax's rounding of a step onto the end of the solve, at the end of the current segment."""
    clip = tnext > floor
    return jnp.where(clip, jnp.where(keep, end, tprev + 0.5 * (end - tprev)), tnext)


def _new_status(
    cr, init, stepping, acc, arrive, is_final, y_new, g0, f0_new, nt0, nt1, max_steps, fsal, y1_finite
):
    B = cr.status.shape[0]
    status = cr.status
    status = jnp.where(arrive & is_final, SUCCESS, status)
    bad = (acc & ~_all_finite(y_new, B)) | (init & ~_all_finite(g0, B))
    if fsal:
        bad = bad | (acc & ~arrive & ~_all_finite(f0_new, B))
    status = jnp.where(bad, NONFINITE, status)
    underflow = stepping & ~arrive & (nt1 <= nt0)
    # the step size underflowed on a candidate that is not finite: the solution left the domain of
    # the vector field (it diverged), not a tolerance too tight to meet
    status = jnp.where(underflow & ~y1_finite & (status == _RUNNING), NONFINITE, status)
    total, per_segment = max_steps
    out_of_steps = stepping & (cr.num_steps + 1 >= total)
    if per_segment is not None:  # the segment's solve ran out of steps before reaching its end
        out_of_steps = out_of_steps | (stepping & ~arrive & (cr.seg_steps + 1 >= per_segment))
    failed = (underflow | out_of_steps) & (status == _RUNNING)
    return jnp.where(failed, SOLVER_FAILED, status).astype(jnp.int32)


def _save(cr, acc, limit, tprev, tnext, y, y1, ks, ts, rows, S, solver, kind):
    """Write the dense interpolant at the save times in [tprev, limit) of every accepted step."""

    def pending(idx):
        s_ = _pick(ts, jnp.minimum(idx, S - 1))
        return acc & (idx < S) & (s_ < limit), s_

    def cond(sc):
        return jnp.any(pending(sc[0])[0])

    def body(sc):
        idx, ys = sc
        pend, s_ = pending(idx)
        w = jax.vmap(lambda a_, b_, t_: _interpolation_weights(solver, len(ks), a_, b_, t_))(
            tprev, tnext, s_
        )
        # (members with nothing to save: weights 0, so that the derivative in the save times and the
        # step's ends does not meet a rejected step's NaN stages)
        w = jnp.where(pend[:, None], w, jnp.zeros_like(w))
        val = _axpy_member(w, [y, y1, *ks])
        col = jnp.where(pend, idx, S)  # column S: a scratch column, discarded
        ys = tmap(
            lambda v, buf: buf.at[rows, col].set(v), val, ys
        )  # values first: buffers are nodes
        return idx + pend.astype(jnp.int32), ys

    idx, ys = eqxi.while_loop(
        cond, body, (cr.save_idx, cr.ys), max_steps=S, buffers=lambda sc: sc[1], kind=kind
    )
    return ys, idx


def _interpolation_weights(solver, n_stages, t0, t1, t):
    """The solver's dense interpolant on [t0, t1] at t is linear in (y0, y1, k_1, …, k_s): its
    coefficients, read off by interpolating the unit vectors.  (Combining the members' states with
    them needs no stacked copy of the stages, which XLA would otherwise build at every step.)"""
    eye = jnp.eye(2 + n_stages, dtype=jnp.result_type(t0, t1, t))
    return solver.interpolation_cls(t0=t0, t1=t1, y0=eye[0], y1=eye[1], k=eye[2:]).evaluate(t)


def _axpy_member(w, trees):
    """Σ_i w[:, i] · trees[i], member-wise (w: (B, n) coefficients)."""
    return tmap(lambda *xs: sum(_scale_member(w[:, i], x) for i, x in enumerate(xs)), *trees)


def _finish(cr: _Carry, ts, t1, unravel_saved, unravel_final) -> AdaptiveRKSolution:
    B, S = ts.shape
    status = jnp.where(cr.status == _RUNNING, SOLVER_FAILED, cr.status).astype(jnp.int32)
    ok = status == SUCCESS
    unsaved = jnp.arange(S)[None, :] >= cr.save_idx[:, None]

    def fill(buf, yf):
        buf = buf[:, :S]
        shape = (B, S) + (1,) * (buf.ndim - 2)
        tail = jnp.where(ok.reshape((B, 1) + (1,) * (buf.ndim - 2)), yf[:, None], jnp.nan)
        return jnp.where(unsaved.reshape(shape), tail, buf)

    ys = tmap(fill, cr.ys, cr.y)
    y1 = _where(ok, cr.y, tmap(lambda v: jnp.full_like(v, jnp.nan), cr.y))
    num_acc = cr.num_accepted
    return AdaptiveRKSolution(
        ts=ts,
        ys=unravel_saved(ys),
        t1=t1,
        y1=unravel_final(y1),
        status=status,
        num_steps=cr.num_steps,
        num_accepted_steps=num_acc,
        num_rejected_steps=cr.num_steps - num_acc,
    )
