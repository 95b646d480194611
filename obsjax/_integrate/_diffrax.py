"""The general back-end: one ``diffrax.diffeqsolve`` per segment of the schedule.

Any diffrax solver (explicit, implicit, an SDE solver for white measurement noise), adaptive steps with
:class:`GuardedController` (diffrax's PID controller with the early-stop and gradient guards of
``_status.py``) or constant steps, any adjoint.  Every solve carries :func:`divergence_event`, so a state that
becomes non-finite ends it at once (except under adjoints that do not support events, where it runs on to
the end with constant steps and the status comes from the saved values).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import diffrax
import jax

from .._checks import concrete_value
from ..systems._noise import WhiteNoise
from . import _segments, _system
from ._schedule import Schedule
from ._status import GuardedController, code_of, divergence_event

tmap = jax.tree_util.tree_map


@dataclasses.dataclass(frozen=True)
class Options:
    """How to integrate (what ``simulate`` resolved from its keyword arguments)."""

    solver: diffrax.AbstractSolver
    rtol: float
    atol: float
    dt0: float | None
    adaptive: bool
    max_steps: int | None
    adjoint: diffrax.AbstractAdjoint | None
    white_noise: WhiteNoise | None = None
    key: jax.Array | None = None
    span: tuple[float, float] | None = None  # concrete horizon (white noise needs it)
    study: bool = False


def terms_of(opt: Options, m: int):
    """The ODE term, or drift + white-noise diffusion driven by a virtual Brownian tree."""
    drift = _system.drift_in_study if opt.study else _system.drift
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


def steps_budget(opt: Options) -> int | None:
    """max_steps, raised for constant steps to cover the horizon (per segment it is then always enough)."""
    dt0 = concrete_value(opt.dt0) if opt.dt0 is not None else None
    if opt.max_steps is None or opt.adaptive or opt.span is None or dt0 is None:
        return opt.max_steps
    t0c, t1c = opt.span
    return max(opt.max_steps, int(math.ceil((t1c - t0c) / float(dt0))) + 16)


def _event_of(adjoint):
    if isinstance(adjoint, (diffrax.BacksolveAdjoint, diffrax.ImplicitAdjoint)):
        return None
    return divergence_event()


def integrate(args: _system.Args, state0, ts, sched: Schedule, opt: Options):
    """Integrate from `state0` = (x0, z0) over the schedule; returns ((xs, zs) at `ts`, status code)."""
    terms = terms_of(opt, args.plant.m)
    ctrl = controller_of(opt, sched.t0, sched.t1)
    event = _event_of(opt.adjoint)
    max_steps = steps_budget(opt)
    adjoint = {} if opt.adjoint is None else {"adjoint": opt.adjoint}

    def solve(s0, s1, state, save_ts):
        sol = diffrax.diffeqsolve(
            terms, opt.solver, s0, s1, opt.dt0, state, args=args,
            saveat=diffrax.SaveAt(ts=save_ts, t1=True), stepsize_controller=ctrl,
            max_steps=max_steps, throw=False, event=event, **adjoint,
        )
        saved = tmap(lambda a: a[:-1], sol.ys)
        return saved, code_of(sol.result), tmap(lambda a: a[-1], sol.ys)

    act = functools.partial(_act, args, sched.has_reset, sched.has_event)
    row = jax.eval_shape(lambda s: s, state0)
    saved, code, _ = _segments.integrate(solve, act, state0, ts, sched, row)
    return saved, code


def _act(args, has_reset, has_event, t, state, do_reset, do_event):
    return _system.act(args, t, state, do_reset, do_event, has_reset, has_event)
