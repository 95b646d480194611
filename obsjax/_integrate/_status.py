"""Status codes of a trajectory, and the guards that let a solve stop early instead of burning ``max_steps``.

``Trajectory.status``:

- ``SUCCESS`` (0): the solve reached the end of the horizon and every saved x, z, x̂, y is finite, and so is
  Σ‖x̃‖² over the save grid (an error norm that overflows is not a success).
- ``SOLVER_FAILED`` (1): the solver did not reach the end of the horizon with finite values: ``max_steps``
  reached, or an implicit solver's Newton iteration failed.
- ``NONFINITE`` (2): the plant or observer state, the estimate, the measurement or the error became
  non-finite or overflowed (including a NaN initial state or gain), i.e. the trajectory diverged.

Every back-end (``_diffrax.py``, ``_fixed_step.py``, ``_lockstep.py``, ``_adaptive_rk.py``) and every study
(``monte_carlo``, ``tune``) uses these codes.

Early stop.  A solve whose state becomes non-finite would make diffrax reject every further step (its error
estimate is NaN) until ``max_steps``.  :class:`GuardedController` prevents that.  It rejects a non-finite
candidate like any other (a too-long step may leave the domain of the vector field; "non-finite" means Σ y²
is NaN/inf, which includes an overflowing norm), but the step size never goes below a floor of 64 ulp of the
horizon's end, max(|t0|, |t1|), and a step at the floor is accepted whatever its error, as diffrax's
``dtmin`` does.  If that step's candidate is not finite (a NaN gain, a state overflowing) the controller ends
the solve with ``RESULTS.dt_min_reached``, mapped to ``NONFINITE``: a few dozen steps instead of
``max_steps``.  A solve that starts from a non-finite state (a NaN x0, or the state carried from an earlier
segment that diverged) starts at the floor and ends after one step.  A finite-time escape of the solution,
or a stiffness an explicit solver cannot follow, is stepped through at the floor until it overflows
(``NONFINITE``) or ``max_steps`` is reached; a tolerance below the rounding error of the state
(rtol ≈ 1e-13) costs a few steps at the floor instead of a failure.  (The guard lives in the controller, not
in a diffrax ``Event``: it costs a few scalar operations per step and works under every adjoint.)  With
constant steps (no controller) a non-finite solve runs to its end and the status comes from the saved
values.

Gradients.  :class:`GuardedController` stops the gradient of the proposed step size: the time grid moves
with the start of the solve (and of each segment) but does not depend on the state, so the derivative is
that of a fixed grid, the consistent discretisation of the true sensitivity (the solution's derivative does
not depend on the step choice).  A rejected step whose stages left the domain of the vector field would still
poison reverse-mode derivatives (its cotangent is zero, its partial derivatives NaN); every adaptive back-end
gives such steps a zero gradient (:func:`finite_gradient_call`: the step in ``_diffrax.py``, the members' vector
field in ``_lockstep.py``, the stages in ``_adaptive_rk.py``).
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

SUCCESS = 0
SOLVER_FAILED = 1
NONFINITE = 2

# The smallest step: this many ulp of max(|t0|, |t1|) of the horizon.
COLLAPSE_ULPS = 64.0


def sum_of_squares(tree):
    """Σ of squares over every leaf (inf when it overflows, NaN when a value is NaN)."""
    leaves = jax.tree_util.tree_leaves(tree)
    return sum(jnp.sum(jnp.square(leaf)) for leaf in leaves)


def is_finite(tree):
    """True when Σ y² over the pytree is finite: no NaN/inf and no overflow of the squared norm."""
    return jnp.isfinite(sum_of_squares(tree))


def finite_gradient_call(run, d, a, *, inputs_too: bool = False, both_modes: bool = False):
    """``run(d, a)``, whose reverse-mode derivative is zero where its output (with ``inputs_too``: or its
    floating inputs ``d``) is not finite; under ``vmap``, member by member.  ``d`` holds the floating arrays,
    ``a`` the other arrays (float0 cotangents).

    Such a result is rejected or replaced afterwards and its cotangent is zero, but its partial derivatives
    are NaN there, and 0 × NaN poisons the whole gradient.  Values that ``run`` closes over and that may
    carry a derivative (a plant's ``A(t)``, an input ``u(t)`` or a nonlinear plant function that reads a
    parameter being differentiated) are made explicit arguments first (closure conversion), because a
    ``custom_vjp`` cannot differentiate closed-over values: JAX refused such a gradient with
    "Detected differentiation of a custom_vjp function with respect to a closed-over value".

    ``both_modes``: a ``custom_jvp`` instead of a ``custom_vjp``, for loops that must allow forward mode
    as well (``diffrax.DirectAdjoint``).  Its rule masks the input tangents as well as the output tangents
    where the result is not finite: forward mode then carries no NaN tangent out, and in reverse mode the
    transpose of the input mask zeroes the NaN that J^T·0 produces inside (J's entries being NaN there).
    It linearises ``run`` in the rule, so it costs what a jvp costs, in both modes.
    """
    closed, out_shape = jax.make_jaxpr(run, return_shape=True)(d, a)
    jaxpr, consts = closed.jaxpr, list(closed.consts)
    # 1: a floating tracer (may carry a derivative); 2: another tracer (an integer one under jit or vmap,
    # float0 cotangent); 0: a concrete constant, kept in the jaxpr
    kind = [(1 if is_floating(c) else 2) if isinstance(c, jax.core.Tracer) else 0 for c in consts]
    out_tree = jax.tree_util.tree_structure(out_shape)

    def converted(dd, aa, hf, hi):
        it = {1: iter(hf), 2: iter(hi)}
        cs = [c if k == 0 else next(it[k]) for c, k in zip(consts, kind)]
        out = jax.core.eval_jaxpr(jaxpr, cs, *jax.tree_util.tree_leaves((dd, aa)))
        return jax.tree_util.tree_unflatten(out_tree, out)

    @jax.custom_vjp
    def call(dd, aa, hf, hi):
        return converted(dd, aa, hf, hi)

    def fwd(dd, aa, hf, hi):
        out, vjp = jax.vjp(lambda x, h: converted(x, aa, h, hi), dd, hf)
        ok = is_finite(eqx.filter(out, eqx.is_inexact_array))
        if inputs_too:
            ok = ok & is_finite(dd)
        return out, (vjp, ok, aa, hi)

    def bwd(res, ct):
        vjp, ok, aa, hi = res
        g, gh = vjp(ct)
        mask = lambda v: jnp.where(ok, v, jnp.zeros_like(v))  # noqa: E731
        float0 = lambda v: np.zeros(np.shape(v), jax.dtypes.float0)  # noqa: E731
        tm = jax.tree_util.tree_map
        return tm(mask, g), tm(float0, aa), [mask(v) for v in gh], [float0(v) for v in hi]

    call.defvjp(fwd, bwd)
    pick = lambda k: [c for c, kk in zip(consts, kind) if kk == k]  # noqa: E731
    if both_modes:
        return _finite_tangent_call(converted, inputs_too)(d, a, pick(1), pick(2))
    return call(d, a, pick(1), pick(2))


def _finite_tangent_call(converted, inputs_too):
    """The ``custom_jvp`` of :func:`finite_gradient_call` (``both_modes``)."""

    @jax.custom_jvp
    def call(dd, aa, hf, hi):
        return converted(dd, aa, hf, hi)

    def rule(primals, tangents):
        dd, aa, hf, hi = primals
        tdd, _, thf, _ = tangents
        out, lin = jax.linearize(lambda x, h: converted(x, aa, h, hi), dd, list(hf))
        ok = is_finite(eqx.filter(out, eqx.is_inexact_array))
        if inputs_too:
            ok = ok & is_finite(dd)

        def mask(v):
            if not is_floating(v):
                return v
            return jnp.where(ok, v, jnp.zeros_like(v))

        tm = jax.tree_util.tree_map
        tout = lin(tm(mask, tdd), [mask(v) for v in thf])
        return out, tm(mask, tout)

    call.defjvp(rule)
    return call


def finite_gradient(fn, *args, both_modes: bool = False):
    """``fn(*args)``, whose reverse-mode derivative is zero when its floating inputs or its output are not
    finite (under ``vmap``: per member): a stage of a Runge–Kutta step evaluated outside the domain of the
    vector field.  Non-floating arrays travel as a second argument (float0 cotangents), everything else is
    closed over (closed-over tracers: see :func:`finite_gradient_call`).  A ``custom_vjp``: reverse mode
    only, unless ``both_modes`` (a ``custom_jvp``, see :func:`finite_gradient_call`)."""
    diff, rest = eqx.partition(args, eqx.is_inexact_array)
    arrs, static = eqx.partition(rest, eqx.is_array)

    def run(d, a):
        return fn(*eqx.combine(d, a, static))

    return finite_gradient_call(run, diff, arrs, inputs_too=True, both_modes=both_modes)


def is_floating(v) -> bool:
    """Whether an array leaf is floating (real or complex): what a jump condition's motion may move."""
    return jnp.issubdtype(jnp.result_type(v), jnp.inexact)


def finite_or_zero(tree):
    """`tree` with non-finite values of its floating leaves set to 0 (other leaves unchanged): the
    coefficient of a zero-valued motion (a jump condition's δτ f) must not turn it into NaN; the solve
    reports a non-finite state itself."""

    def one(v):
        return jnp.where(jnp.isfinite(v), v, jnp.zeros((), jnp.result_type(v))) if is_floating(v) else v

    return jax.tree_util.tree_map(one, tree)


def code_of(result):
    """diffrax ``RESULTS`` → SUCCESS / SOLVER_FAILED / NONFINITE (``dt_min_reached`` is the stop of
    :class:`GuardedController` on a non-finite state; its inner PID controller has no ``dtmin``)."""
    ok = result == diffrax.RESULTS.successful
    diverged = result == diffrax.RESULTS.dt_min_reached
    return jnp.where(ok, SUCCESS, jnp.where(diverged, NONFINITE, SOLVER_FAILED)).astype(jnp.int32)


def first_failure(code, new):
    """Combine segment codes: the first non-zero code wins."""
    return jnp.where(code == SUCCESS, new, code)


class GuardedController(diffrax.AbstractAdaptiveStepSizeController):
    """diffrax's ``PIDController`` with two guards (see the module docstring): steps never go below
    ``dt_floor``, a step at the floor is accepted and ends the solve (``RESULTS.dt_min_reached``) when its
    candidate is not finite; and the proposed step size carries no gradient."""

    inner: diffrax.PIDController
    dt_floor: jax.Array

    def __init__(self, rtol, atol, t0, t1, norm=None):
        kw = {} if norm is None else {"norm": norm}
        self.inner = diffrax.PIDController(rtol=rtol, atol=atol, **kw)
        scale = jnp.maximum(jnp.abs(t0), jnp.abs(t1))
        self.dt_floor = jax.lax.stop_gradient(COLLAPSE_ULPS * jnp.finfo(jnp.result_type(scale)).eps * scale)

    @property
    def rtol(self):
        return self.inner.rtol

    @property
    def atol(self):
        return self.inner.atol

    @property
    def norm(self):
        return self.inner.norm

    def wrap(self, direction):
        return eqx.tree_at(lambda c: c.inner, self, self.inner.wrap(direction))

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        # (diffrax's PID init already stops the gradient of its initial step: t0 + dt0 moves with t0)
        tnext, state = self.inner.init(terms, t0, t1, y0, dt0, args, func, error_order)
        # a non-finite vector field at t0 gives a NaN first step: start small, the guard below takes over;
        # a non-finite initial state starts at the floor (its first step ends the solve)
        ok = jnp.isfinite(tnext) & (tnext > t0)
        tnext = jnp.where(ok, tnext, t0 + jax.lax.stop_gradient(1e-6 * (t1 - t0)))
        return jnp.where(is_finite(y0), tnext, t0 + self.dt_floor), state

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        pid_keep, next_t0, next_t1, jump, state, result = self.inner.adapt_step_size(
            t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state
        )
        keep = pid_keep
        # A candidate that overflows has a NaN error estimate (inf − inf): the PID factor, and so the next
        # step, came out NaN, and every later step with it, until max_steps (a solvable problem reported as
        # a solver failure).  It is a rejection like any other: shrink by factormin.
        shrunk = next_t0 + jax.lax.stop_gradient(self.inner.factormin * (t1 - t0))
        next_t1 = jnp.where(jnp.isfinite(next_t1), next_t1, shrunk)
        dt = jax.lax.stop_gradient(next_t1 - next_t0)
        # A step already at the floor is accepted whatever its error (diffrax's ``dtmin``): a finite one lets
        # the solve go on, a non-finite one (the state is kept, so later segments start from it) ends it.
        # t1 = t0 + dt_floor is rounded to a float: the step taken, t1 − t0, can exceed the floor by up to an
        # ulp of t1 (a step from just below 0.5 ends in the binade above).  A strict comparison would then
        # reject a non-finite floor step, propose the floor again, and repeat until max_steps (status 1
        # instead of 2).
        slack = 2 * ulp(jnp.maximum(jnp.abs(t0), jnp.abs(t1)))
        at_floor = jax.lax.stop_gradient(t1 - t0) <= self.dt_floor + slack
        finite = is_finite(y1_candidate)
        keep = (keep & finite) | at_floor
        next_t0 = jnp.where(at_floor, t1, next_t0)
        # a floor step the PID controller accepted proposes its next step as usual (it may grow again); one
        # it rejected proposed a step from t0, so the next starts at t1 with the floor.  (Forcing the floor
        # after every floor step kept a solve there for good: at clock times of 1.7e12 the floor is 0.024,
        # the first step 0.01, and one interval of 100 took 4137 floor steps into max_steps.)
        low = (at_floor & ~pid_keep) | (dt < self.dt_floor)
        next_t1 = jnp.where(low, next_t0 + self.dt_floor, next_t1)
        result = diffrax.RESULTS.where(at_floor & ~finite, diffrax.RESULTS.dt_min_reached, result)
        return keep, next_t0, frozen(next_t1, next_t0), jump, state, result


def ulp(x):
    """The spacing of floats at |x| (no derivative)."""
    x = jax.lax.stop_gradient(x)
    return jnp.nextafter(x, jnp.array(jnp.inf, x.dtype)) - x


def frozen(t_next, t_start):
    """``t_next`` (bit for bit) whose derivative is that of ``t_start``: the step length carries no gradient."""
    return t_next - (t_next - jax.lax.stop_gradient(t_next)) + (t_start - jax.lax.stop_gradient(t_start))
