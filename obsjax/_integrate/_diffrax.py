"""The general back-end: one ``diffrax.diffeqsolve`` per segment of the schedule.

Any diffrax solver (explicit, implicit, an SDE solver for white measurement noise), adaptive steps with
:class:`GuardedController` (diffrax's PID controller with the early-stop and gradient guards of
``_status.py``: a state that becomes non-finite ends the solve within a few steps) or constant steps, any
adjoint.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import concrete_value, without_diffrax_save_time_checks
from ..systems._noise import WhiteNoise
from . import _segments, _system
from ._schedule import Schedule
from ._status import GuardedController, code_of, finite_gradient_call

tmap = jax.tree_util.tree_map


@dataclasses.dataclass(frozen=True)
class Options:
    """How to integrate (what ``simulate`` resolved from its keyword arguments)."""

    solver: diffrax.AbstractSolver
    rtol: float | jax.Array
    atol: float | jax.Array
    dt0: float | jax.Array | None
    adaptive: bool
    max_steps: int | None
    adjoint: diffrax.AbstractAdjoint | None
    white_noise: WhiteNoise | None = None
    key: jax.Array | None = None
    span: tuple[float, float] | None = None  # concrete horizon (white noise needs it)


def terms_of(opt: Options, m: int):
    """The ODE term, or drift + white-noise diffusion driven by a virtual Brownian tree."""
    drift = _system.for_check_mode(_system.drift)
    if opt.white_noise is None:
        return diffrax.ODETerm(drift)
    t0c, t1c = opt.span
    bm = diffrax.VirtualBrownianTree(t0c, t1c, tol=opt.dt0 / 2, shape=(m,), key=opt.key)
    return diffrax.MultiTerm(
        diffrax.ODETerm(drift), _system.MeasurementNoiseTerm(opt.white_noise.sigma, bm)
    )


def controller_of(opt: Options, t0, t1):
    if opt.adaptive:
        return GuardedController(opt.rtol, opt.atol, t0, t1)
    return diffrax.ConstantStepSize()


class SaveTimeStepSize(diffrax.AbstractStepSizeController):
    """Steps of ``dt0`` that also end at every save time (white measurement noise).

    Between two steps diffrax's dense output of an SDE solve is the straight line between the steps' ends;
    at a save time inside a step that line's variance is below the path's (by up to a quarter of a step's
    increment at mid-step), so the statistics at the save times would depend on the save grid.  A step that
    would pass a save time ends at it instead, and the next one starts there; the Brownian path is sampled
    there exactly (the virtual Brownian tree's bridge), so every saved value is a state of the scheme.
    `save_ts` is sorted; entries at or before the current step's end are passed over.
    """

    save_ts: jax.Array

    def wrap(self, direction):
        return self

    def _next(self, t, proposal):
        ts = self.save_ts
        i = jnp.searchsorted(ts, t, side="right")
        nxt = jnp.where(i < ts.shape[0], ts[jnp.minimum(i, ts.shape[0] - 1)], jnp.inf)
        return jnp.minimum(proposal, nxt)

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        del terms, t1, y0, args, func, error_order
        if dt0 is None:
            raise ValueError("white measurement noise needs a step `dt0`.")
        return self._next(t0, t0 + dt0), jnp.asarray(dt0, jnp.result_type(t0, dt0))

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        del t0, y0, y1_candidate, args, y_error, error_order
        dt = controller_state
        return True, t1, self._next(t1, t1 + dt), False, dt, diffrax.RESULTS.successful


def steps_budget(opt: Options) -> int | None:
    """max_steps, raised for constant steps to cover the horizon (per segment it is then always enough)."""
    dt0 = concrete_value(opt.dt0) if opt.dt0 is not None else None
    if opt.max_steps is None or opt.adaptive or opt.span is None or dt0 is None:
        return opt.max_steps
    t0c, t1c = opt.span
    return max(opt.max_steps, math.ceil((t1c - t0c) / float(dt0)) + 16)


def _finite_gradient_step(solver, terms, t0, t1, y0, args, solver_state, made_jump, both_modes=False):
    """``solver.step`` whose reverse-mode derivative is zero when the step's output is not finite.

    An adaptive solve rejects a step whose candidate is not finite (a stage left the domain of the vector
    field, typically a step across an undeclared discontinuity); its cotangent is zero, but the step's own
    partial derivatives are NaN there and 0 × NaN poisons the whole gradient.  The gradient of such a step is
    defined as zero instead (per trajectory, also under ``vmap``); finite steps are untouched.
    """
    diff, rest = eqx.partition((terms, t0, t1, y0, args, solver_state, made_jump), eqx.is_inexact_array)
    arrs, static = eqx.partition(rest, eqx.is_array)

    def run(d, a):
        terms_, t0_, t1_, y0_, args_, state_, jump_ = eqx.combine(d, a, static)
        y1, err, dense, state1, _ = solver.step(terms_, t0_, t1_, y0_, args_, state_, jump_)
        return y1, err, dense, state1

    y1, err, dense, state1 = finite_gradient_call(run, diff, arrs, both_modes=both_modes)
    return y1, err, dense, state1, diffrax.RESULTS.successful


class FiniteGradientSolver(diffrax.AbstractWrappedSolver):
    """An explicit Runge–Kutta solver whose non-finite (rejected) steps contribute a zero gradient
    (:func:`_finite_gradient_step`); everything else is the wrapped solver's.  ``both_modes``: a
    ``custom_jvp`` (for ``diffrax.DirectAdjoint``, which allows forward mode too) instead of a
    ``custom_vjp``."""

    solver: diffrax.AbstractSolver
    both_modes: bool = eqx.field(static=True, default=False)

    @property
    def term_structure(self):
        return self.solver.term_structure

    @property
    def scan_kind(self):  # read by DirectAdjoint (isinstance checks pass through to the wrapped solver)
        return getattr(self.solver, "scan_kind", None)

    @property
    def interpolation_cls(self):
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    def order(self, terms):
        return self.solver.order(terms)

    def strong_order(self, terms):
        return self.solver.strong_order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

    def init(self, terms, t0, t1, y0, args):
        return self.solver.init(terms, t0, t1, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        return _finite_gradient_step(
            self.solver, terms, t0, t1, y0, args, solver_state, made_jump, both_modes=self.both_modes
        )

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)


def solver_of(opt: Options):
    """The solver, wrapped by :class:`FiniteGradientSolver` when it is an explicit Runge–Kutta method
    differentiated in reverse mode by the default adjoint (a ``custom_vjp``, which has no forward mode)
    or by ``diffrax.DirectAdjoint`` (both modes: a ``custom_jvp``)."""
    adj = opt.adjoint
    reverse = adj is None or type(adj) is diffrax.RecursiveCheckpointAdjoint
    direct = type(adj) is diffrax.DirectAdjoint
    if (reverse or direct) and isinstance(opt.solver, diffrax.AbstractERK) and opt.white_noise is None:
        solver = opt.solver
        if direct and solver.scan_kind is None:  # what DirectAdjoint sets, which it cannot set on the wrapper
            solver = eqx.tree_at(lambda s: s.scan_kind, solver, "bounded", is_leaf=lambda v: v is None)
        return FiniteGradientSolver(solver, both_modes=direct)
    return opt.solver


def integrate(args: _system.Args, state0, ts, sched: Schedule, opt: Options):
    """Integrate from `state0` = (x0, z0) over the schedule; returns ((xs, zs) at `ts`, status code)."""
    terms = terms_of(opt, args.plant.m)
    solver = solver_of(opt)
    ctrl = controller_of(opt, sched.t0, sched.t1)
    max_steps = steps_budget(opt)
    if opt.white_noise is not None and max_steps is not None:
        max_steps += int(ts.shape[0])  # a step more per save time (SaveTimeStepSize)
    adjoint = {} if opt.adjoint is None else {"adjoint": opt.adjoint}

    def solve(s0, s1, state, save_ts):
        c = ctrl if opt.white_noise is None else SaveTimeStepSize(jax.lax.stop_gradient(save_ts))
        with without_diffrax_save_time_checks():  # save_ts lie in [s0, s1], nondecreasing (``_segments``)
            sol = diffrax.diffeqsolve(
                terms, solver, s0, s1, opt.dt0, state, args=args,
                saveat=diffrax.SaveAt(ts=save_ts, t1=True), stepsize_controller=c,
                max_steps=max_steps, throw=False, **adjoint,
            )
        saved = tmap(lambda a: a[:-1], sol.ys)
        return saved, code_of(sol.result), tmap(lambda a: a[-1], sol.ys)

    act = functools.partial(_act, args, sched.has_reset, sched.has_event)
    row = jax.eval_shape(lambda s: s, state0)
    if opt.white_noise is not None and sched.concrete is None:
        sched = dataclasses.replace(sched, times=no_derivative_under_white_noise(sched.times))
    # an ODE: traced breakpoints (a tuned T) move by the jump condition, not by moving the solves' steps
    f = _system.for_check_mode(_system.drift)
    drift = None if opt.white_noise is not None else (lambda t, s: f(t, s, args))
    saved, code, _ = _segments.integrate(solve, act, state0, ts, sched, row, drift=drift)
    return saved, code


WHITE_NOISE_TIMES = (
    "the reset instants or event times of the observer (a reset period T, an event time) cannot be "
    "differentiated under white measurement noise: the measurement enters the estimate as a Brownian "
    "increment, and moving a reset or an event by δT changes the estimate by O(√δT) on each path, so the "
    "pathwise loss has no derivative in them. Use BandLimitedNoise (a piecewise-linear noise path, through "
    "which dJ/dT is exact to the tolerance), or hold T fixed (jax.lax.stop_gradient, or tune the other gains)."
)


@jax.custom_jvp
def no_derivative_under_white_noise(times):
    """The breakpoint times, unchanged; differentiating them raises ``ValueError(WHITE_NOISE_TIMES)``
    at trace time (without this, diffrax raises an opaque error about t0)."""
    return times


@no_derivative_under_white_noise.defjvp
def _no_derivative_jvp(primals, tangents):
    raise ValueError(WHITE_NOISE_TIMES)


def _act(args, has_reset, has_event, t, state, do_reset, do_event):
    return _system.act(args, t, state, do_reset, do_event, has_reset, has_event)
