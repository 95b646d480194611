"""Integration back-ends of :func:`obsjax.simulate` and :func:`obsjax.simulate_batch`.

``simulate`` validates its arguments (``_validate.py``), builds the schedule of breakpoints
(``_schedule.py``: reset instants, plant jumps, observer events) and hands the loop to one back-end:

- ``_diffrax.py``: the general back-end, one ``diffrax.diffeqsolve`` per segment (any solver, adaptive or
  constant steps, white noise as an SDE, any adjoint), with the early-stop guards of ``_status.py``;
- ``_fixed_step.py``: fixed steps of an explicit Runge–Kutta method, a direct ``lax.scan`` over the Butcher
  tableau, on a grid through the save times and breakpoints (built before tracing, or inside the trace when
  the breakpoints are traced, e.g. a tuned reset period);
- ``_lockstep.py``: a batch as one adaptive ODE (``simulate_batch``), with failure isolation;
- ``_masked.py``: a batch whose members each take their own adaptive steps (``simulate_batch(lockstep=False)``
  and ``monte_carlo``'s default kernel) on the masked explicit Runge–Kutta loop of ``_adaptive_rk.py``.

``_segments.py`` is the segmented scan the diffrax and lock-step back-ends share; ``_system.py`` the joint
plant–observer vector field and the jumps at breakpoints.  A new back-end is one file with one entry point
``integrate(args, state0, ...) -> ((xs, zs), code)`` and one branch in :func:`integrate` below.

Reuse for other drivers (recorded data): ``_schedule.build(ts, ts_np, T, n_reset, jumps, event_times)``
takes any ``event_times(t0, t1)`` callable (e.g. the sample times of a data set), and
``_segments.integrate(solve, act, carry0, ts, schedule, row)`` runs any per-segment ``solve`` and any jump
``act``, so a driver whose "plant" is interpolated data only supplies those two functions.
"""

from __future__ import annotations

import numpy as np

from . import _diffrax, _fixed_step, _lockstep, _schedule
from ._system import Args
from ._validate import Plan


def integrate(args: Args, state0, plan: Plan):
    """One trajectory: choose the back-end and run it.  Returns ((xs, zs) at the save times, status code)."""
    opt, sched = plan.opt, plan.sched
    if opt.white_noise is None and not opt.adaptive:
        tab = _fixed_step.tableau_of(opt.solver)
        if tab is not None and plan.ts_np is not None:
            tol = _schedule.horizon_tolerance(plan.ts_np)
            edges = _fixed_step.edge_jumps(plan.ts_np, getattr(args.plant, "jump_ts", None), tol)
            g = _fixed_step.grid(plan.ts_np, opt.dt0, sched.concrete, tol, edges)
            if g is not None:
                return _fixed_step.integrate(args, state0, sched, g, tab)
            dt0 = _fixed_step.concrete_value(opt.dt0)
            if dt0 is not None and sched.concrete is None:  # traced breakpoints (a tuned T)
                return _fixed_step.integrate_traced(
                    args, state0, sched, plan.ts_np, float(np.asarray(dt0).reshape(())), tab, tol, edges
                )
    # One trajectory: diffrax.  (Batches with independent adaptive steps go to ``_masked.py`` from
    # ``simulate_batch``, where the batch is visible.)
    return _diffrax.integrate(args, state0, plan.ts, sched, opt)


def integrate_batch(args_b: Args, state0_b, plan: Plan):
    """A batch in lock step (adaptive steps only).  Returns ((xs, zs) as (B, T, ...), codes (B,))."""
    return _lockstep.integrate(args_b, state0_b, plan.ts, plan.sched, plan.opt)
