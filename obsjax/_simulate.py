"""Plant + observer -> one trajectory: the door (validation), then a back-end of ``obsjax/_integrate/``."""

from __future__ import annotations

from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _integrate
from ._config import require_x64
from ._integrate import _compiled, _validate
from ._integrate._schedule import MAX_RESET_SEGMENTS, num_segments
from ._integrate._status import NONFINITE, SOLVER_FAILED, SUCCESS, is_finite
from ._integrate._system import Args as _Args
from ._integrate._system import with_content as _with_content
from ._integrate._system import drift as _drift
from ._integrate._system import initial_state, signals
from ._integrate._validate import check_ts as _check_ts
from .systems._noise import AbstractNoise, BandLimitedNoise, realise_band_limited

# Also imported from here: the status codes, ``num_segments`` and ``_check_ts`` (monte_carlo, tune), ``_Args``
# and ``_drift`` (tests, benchmarks).
__all__ = [
    "MAX_RESET_SEGMENTS", "NONFINITE", "SOLVER_FAILED", "SUCCESS", "Trajectory", "_Args", "_check_ts",
    "_drift", "num_segments", "simulate",
]


class Trajectory(eqx.Module):
    """A simulated plant-observer trajectory, one row per entry of ``ts``.

    - `ts`: (T,) save times.
    - `x`: (T, n) true plant state.
    - `xhat`: (T, n) estimate x̂.
    - `y`: (T, m) measurement (with band-limited noise included; noise-free under white noise).
    - `error`: (T, n) estimation error x̃ = x̂ − x (Chen & Yen's sign).
    - `z`: observer state pytree, each leaf with a leading axis of length T.
    - `status`: int, 0 success, 1 solver failure (max_steps reached), 2 non-finite values
      (the trajectory diverged, a value overflowed or an input was NaN); see ``throw``.  Rows after a solve
      stopped early (status 1 or 2) are not meaningful: with ``throw=True`` every other field carries the
      check of the status (reading any of them raises), with ``throw=False`` read the status first.
    """

    ts: jax.Array
    x: jax.Array
    xhat: jax.Array
    y: jax.Array
    error: jax.Array
    z: object
    status: jax.Array

    @property
    def error_norm(self) -> jax.Array:
        """‖x̃(t)‖ at each save time, shape (T,).

        Scaled by the largest component before squaring, so errors of 1e-200 (or 1e200) neither underflow
        to 0 nor overflow to inf; the scale is held out of the derivative, which is exact for a norm
        (‖e‖ = s‖e/s‖ for any s > 0)."""
        return _error_norm(self.error)


@jax.jit
def _error_norm(e):
    """‖e‖ over the last axis, scaled (see :attr:`Trajectory.error_norm`): one compiled program, where the
    property read eagerly ran eight operations, each compiling its own program on its first call in a
    process (inlined under an outer ``jit``, differentiated and vmapped as its operations are)."""
    s = jax.lax.stop_gradient(jnp.max(jnp.abs(e), axis=-1, keepdims=True))
    s = jnp.where((s > 0) & jnp.isfinite(s), s, 1.0)
    return s[..., 0] * jnp.linalg.norm(e / s, axis=-1)


def simulate(
    plant,
    observer,
    x0,
    xhat0,
    ts,
    *,
    u: Callable | None = None,
    controller: Callable | None = None,
    noise: AbstractNoise | None = None,
    key=None,
    solver: diffrax.AbstractSolver | None = None,
    rtol: float | jax.Array = 1e-6,
    atol: float | jax.Array = 1e-8,
    dt0: float | jax.Array | None = None,
    adaptive: bool = True,
    max_steps: int | np.integer | None = 16384,
    max_segments: int | np.integer | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    throw: bool = True,
) -> Trajectory:
    """Simulate the true plant and an observer together, integrating the joint state (x, z).

        ẋ = f(t, x, u),   y = h(t, x, u) + v,   ż = observer.vector_field(t, z, y, u),
        x̂ = observer.estimate(t, z, y),   u = u(t) + controller(t, x̂).

    The observer carries its own model of the plant; ``plant`` is the truth, so model mismatch is free.

    **Segments.**  The horizon is cut at every breakpoint: the observer's resets t0 + kT (Chen & Yen's
    covariance reset; T itself a differentiable leaf), the plant's declared ``jump_ts`` and the observer's
    ``event_times`` (discrete updates of a sampled-data observer, ``observer.update``).  A ``lax.scan`` runs
    one solve per segment and applies the reset, then the update, at its start, so no solve ever steps
    across a discontinuity and gradients with respect to T are those of smooth solves.  A save time at a
    breakpoint sees the state after it; "at" is to the schedule's time tolerance, 1e-9 of the horizon
    (plus 4 ulp of the times), and a concrete save time that is within it before a reset or an update but
    not at the instant to rounding is refused (``ValueError``), since it would show the state after the
    jump.  A plant switch that is *not* declared is stepped over by the
    adaptive solver (accurate to the tolerances, at the price of rejected steps); its gradients stay finite
    (a rejected step whose stages left the domain of the vector field contributes zero) but are not
    accurate: the discrete solution is not differentiable where a step straddles the switch.  Declare known
    switches.

    **Back-ends** (``obsjax/_integrate/``): fixed steps of an explicit Runge–Kutta solver with concrete save
    times and ``dt0`` run as a direct ``lax.scan`` over the Butcher tableau (the breakpoints may be traced,
    as with a tuned reset period T: the same grid is then built inside the trace); everything else runs one
    ``diffrax.diffeqsolve`` per segment.

    **Status.**  0 success; 1 the solver did not reach the end of the horizon (``max_steps``, an implicit
    solver's failed Newton iteration); 2 non-finite: the plant state, observer state, estimate, measurement
    or error became NaN/inf or a sum of their squares (Σ‖x̃‖² included) overflowed, including a NaN initial
    state or gain.  A diverging solve stops as soon as its state is no longer finite (it does not burn
    ``max_steps``).

    **Arguments:**

    - `plant`: the true system (:class:`obsjax.LTI`, :class:`obsjax.LTV`, :class:`obsjax.Nonlinear`).
    - `observer`: any :class:`obsjax.AbstractObserver`.
    - `x0`, `xhat0`: initial plant state (n,) and initial estimate (the observer's state dimension).
    - `ts`: (T,) strictly increasing save times; the solve runs from ``ts[0]`` to ``ts[-1]`` (checked
      eagerly, and with ``eqx.error_if`` when traced: obsjax never integrates backwards).
    - `u`: open-loop input, a callable t -> (p,), zero when ``None``.
    - `controller`: output feedback ``controller(t, x̂) -> (p,)`` (closes the loop through the estimate).
    - `noise`: :class:`obsjax.noise.WhiteNoise` (an SDE; fixed steps, Euler–Maruyama by default, ``dt0``
      defaulting to span/2000; a step that would pass a save time ends at it, so every saved value is a
      state of the scheme, never an interpolant between two steps, whose variance would be too small)
      or :class:`obsjax.noise.BandLimitedNoise`; needs ``key``.  Under white
      noise the reset instants and event times of the observer cannot be differentiated (the pathwise
      solution is not differentiable in them); a derivative in them raises ``ValueError``.
    - `key`: the PRNG key the noise is drawn from; only with `noise` (a key without it is refused, so a run
      meant to be noisy never runs noise-free without a word).
    - `solver`: a diffrax solver.  Default: the observer's ``recommended_solver(ts)`` when it has one (the
      high-gain :class:`obsjax.TrajectoryLinearization` returns the implicit ``Kvaerno5`` when
      max|ρ̄|·ω/ε makes the problem stiff), else ``Tsit5``.
    - `rtol`, `atol`: tolerances of the adaptive PID controller, scalars > 0: each component of the joint
      state (plant and observer) must meet |error| ≤ atol + rtol·|value| per step.  `atol` is in the
      units of the states, so scale it with them: with every state around 1e-6 (a unit 10⁶ times
      larger) the default 1e-8 is a 1 % tolerance, and status 0 means solved to *that* tolerance (with
      states around 1e-7, x̃ was 12 % off).  States in mixed units are integrated accurately as long as
      the components that matter are well above `atol`.
    - `dt0`, `adaptive`: ``adaptive=False`` with ``dt0`` > 0 gives fixed steps.  With an explicit Runge–Kutta
      solver and concrete ``ts`` and ``dt0``, fixed steps bypass ``diffeqsolve``: a ``lax.scan`` over the
      solver's Butcher tableau on a grid through every save time and breakpoint, each interval cut into
      ⌈Δ/dt0⌉ equal steps (an interval ending at a plant jump ends, stages included, one float before it).
      The derivative with respect to a moving breakpoint (a reset period T) is that of the exact
      solution to the method's order, not of the fixed-step map itself: with a low-order solver
      (Heun, dt0 = 0.02) it can differ from a finite difference of the fixed-step loss by 5–20 %, a gap
      that closes as dt0 shrinks (it was at rounding for Tsit5 on smooth data; with noise held between
      samples the fixed-step loss has kinks in T, and its one-sided differences scatter about the
      derivative returned).
    - `max_steps`: per solve (per segment), a positive integer.
    - `adjoint`: how diffrax differentiates each solve (default ``RecursiveCheckpointAdjoint()``, with
      log₂(max_steps) checkpoints); e.g. ``RecursiveCheckpointAdjoint(checkpoints=max_steps)`` stores every
      step of a short fixed-step segment and skips recomputation in reverse mode.  Forward mode
      (``jax.jvp``, ``jax.jacfwd``) through an adaptive solve needs ``adjoint=diffrax.ForwardMode()``: the
      default adjoint is a ``custom_vjp``, which JAX cannot differentiate forwards (``obsjax.tune`` passes
      it itself when it chooses forward mode).  Unused by the direct fixed-step path (a ``lax.scan``,
      differentiated by JAX in either mode).
    - `max_segments`: number of reset segments, needed only when the reset period is traced under ``jit``
      (a T passed into the jitted function or computed from traced values; a constant T, also one written
      as a literal inside the jitted function, is counted: ceil((t1 − t0) / T)); must satisfy
      max_segments·T ≥ t1 − t0.  At
      most ``MAX_RESET_SEGMENTS`` (100 000) reset segments are integrated: a shorter period is refused.
    - `throw`: raise on solver failure or non-finite values (the check is attached to every array of the
      trajectory, so it fires under ``jit`` whichever field is read); ``False`` returns ``status`` instead, so
      a failing member of a vmapped batch does not poison the rest.

    **Returns:** a :class:`obsjax.Trajectory`.

    **Example:**::

        plant = obsjax.LTI([[-2., 1.], [0., -1.]], [[0.], [1.]], [[1., 0.]])
        obs = obsjax.Luenberger.from_poles(plant, [-3., -3.])
        traj = obsjax.simulate(plant, obs, jnp.array([1., 1.]), jnp.zeros(2), jnp.linspace(0, 5, 51))
    """
    require_x64("obsjax.simulate")
    max_steps, max_segments = _validate.plain_int(max_steps), _validate.plain_int(max_segments)
    _validate.check_types(plant, observer, noise)
    if noise is not None and key is None:
        raise ValueError("`key` is required when `noise` is given (the noise is drawn from it).")
    _validate.check_keys_need_noise(noise, key, "key")
    ts_np = _validate.concrete_times(ts)
    ts = _validate.check_ts(ts)
    x0 = _validate.check_state(x0, "x0", f"({plant.n},) (the plant's state)", 1)
    xhat0 = _validate.check_state(xhat0, "xhat0", "(n̂,) (a vector)", 1)
    dt0 = _validate.check_options(rtol, atol, dt0, adaptive, max_steps, noise)
    observer = observer.prepare()
    observer = _validate.check_span(observer, ts_np)
    # (t0 for shapes only: NumPy's where the times are concrete, as indexing `ts` eagerly compiles a program)
    t0_shape = ts[0] if ts_np is None else ts_np[0]
    _validate.check_dimensions(plant, observer, x0, xhat0, t0_shape, u, controller, noise)
    plan = _validate.plan(
        plant, observer, ts, ts_np, noise=noise, key=key, solver=solver, rtol=rtol, atol=atol, dt0=dt0,
        adaptive=adaptive, max_steps=max_steps, max_segments=max_segments, adjoint=adjoint,
    )
    path = None
    if isinstance(noise, BandLimitedNoise):
        t0c, t1c = _validate.concrete_span(ts_np)
        path = realise_band_limited(noise, key, t0c, t1c, plant.m)
    args = _with_content(plant, observer, u, controller, path)
    state0 = initial_state(args, ts[0], x0, xhat0)
    traj = _compiled.call(_solve, args, state0, plan, ts)  # compiled once per problem structure
    return _raise_if(traj, throw, "obsjax.simulate", traj.status)


def _solve(args: _Args, state0, plan, ts) -> Trajectory:
    """The back-end's solve and the trajectory at the save times (one program, see ``_compiled``)."""
    (xs, zs), code = _integrate.integrate(args, state0, plan)
    # a non-finite initial state is NONFINITE whatever the solver made of it (an implicit solver or a
    # gain's own guard may stop it otherwise, and the code must not depend on jit: eager read 2, jit 1)
    code = jnp.where(is_finite(state0), code, NONFINITE).astype(jnp.int32)
    return trajectory(args, ts, xs, zs, code)


def trajectory(args: _Args, ts, xs, zs, code) -> Trajectory:
    """Outputs at the save times and the status (see :class:`Trajectory`)."""

    def outputs(t, x, z):
        _, y, xhat = signals(args, t, x, z)
        return y, xhat

    y, xhat = jax.vmap(outputs)(ts, xs, zs)
    error = xhat - jax.vmap(args.observer.target)(ts, xs)
    finite = is_finite((xs, xhat, y)) & is_finite(error) & is_finite(zs)
    status = jnp.where(code != SUCCESS, code, jnp.where(finite, SUCCESS, NONFINITE)).astype(jnp.int32)
    return Trajectory(ts=ts, x=xs, xhat=xhat, y=y, error=error, z=zs, status=status)


def _raise_if(traj: Trajectory, throw: bool, who: str, status) -> Trajectory:
    """With `throw`, every array of the trajectory (x, x̂, y, x̃, z) carries the check of its status, so a
    computation that reads any of them (under ``jit`` too) raises on a failed trajectory."""
    if not throw:
        return traj
    fields = (traj.x, traj.xhat, traj.y, traj.error, traj.z)
    fields = eqx.error_if(
        fields,
        jnp.any(status == SOLVER_FAILED),
        f"{who}: the solver did not reach the end of the horizon (max_steps reached, or an implicit "
        "solver failed). Raise `max_steps`, loosen `rtol`/`atol`, or use an implicit solver for a stiff observer; "
        "pass throw=False to get a per-trajectory status instead.",
    )
    fields = eqx.error_if(
        fields,
        jnp.any(status == NONFINITE),
        f"{who}: the trajectory diverged or contains non-finite values (the plant or the observer diverged, "
        "a value overflowed, or an initial state or gain is NaN/inf). Pass throw=False to get a "
        "per-trajectory status instead.",
    )
    x, xhat, y, error, z = fields
    return Trajectory(ts=traj.ts, x=x, xhat=xhat, y=y, error=error, z=z, status=traj.status)
