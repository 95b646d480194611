"""Plant + observer -> one diffrax solve (segment by segment where the observer resets)."""

from __future__ import annotations

import math
from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

from . import _fixed_step
from ._checks import as_float_array, concrete_value
from ._config import require_x64
from .observers._base import AbstractObserver
from .systems._noise import AbstractNoise, BandLimitedNoise, WhiteNoise, realise_band_limited
from .systems._plants import AbstractSystem

# Status codes of a trajectory (``Trajectory.status``).
SUCCESS = 0
SOLVER_FAILED = 1  # diffrax did not reach t1 (max_steps, dt_min, ...)
NONFINITE = 2  # the solve finished but produced non-finite values


class Trajectory(eqx.Module):
    """A simulated plant-observer trajectory, one row per entry of ``ts``.

    - `ts`: (T,) save times.
    - `x`: (T, n) true plant state.
    - `xhat`: (T, n) estimate x̂.
    - `y`: (T, m) measurement (with band-limited noise included; noise-free under white noise).
    - `error`: (T, n) estimation error x̃ = x̂ − x (Chen & Yen's sign).
    - `z`: observer state pytree, each leaf with a leading axis of length T.
    - `status`: int, 0 success, 1 solver failure, 2 non-finite values (see ``throw``).
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
        """‖x̃(t)‖ at each save time, shape (T,)."""
        return jnp.linalg.norm(self.error, axis=-1)


class _Args(eqx.Module):
    plant: AbstractSystem
    observer: AbstractObserver
    u: Callable | None
    controller: Callable | None
    noise_path: Callable | None


def _zeros_input(plant):
    return jnp.zeros((plant.p,))


def _signals(args: _Args, t, x, z):
    """Inputs, measurement and estimate at time t (the algebraic part of the loop)."""
    plant, obs = args.plant, args.observer
    u_ol = _zeros_input(plant) if args.u is None else jnp.asarray(args.u(t)).reshape(plant.p)
    v = 0.0 if args.noise_path is None else args.noise_path(t)
    if args.controller is None:
        y = plant.h(t, x, u_ol) + v
        return u_ol, y, obs.estimate(t, z, y)
    # Output feedback: the estimate uses y at the open-loop input (exact when D = 0).
    y1 = plant.h(t, x, u_ol) + v
    xhat = obs.estimate(t, z, y1)
    u = u_ol + jnp.asarray(args.controller(t, xhat)).reshape(plant.p)
    y = plant.h(t, x, u) + v
    return u, y, obs.estimate(t, z, y)


def _drift(t, state, args: _Args):
    x, z = state
    u, y, _ = _signals(args, t, x, z)
    return args.plant.f(t, x, u), args.observer.vector_field(t, z, y, u)


def _drift_in_study(t, state, args):
    """The same vector field as ``_drift``, as a distinct function: diffrax caches the trace of
    ``diffeqsolve`` by its terms, so studies (``monte_carlo``, which traces its kernel with runtime checks as
    NaN) never reuse a trace made outside one, nor leave theirs to ``simulate``."""
    return _drift(t, state, args)


class _MeasurementNoiseTerm(diffrax.AbstractTerm):
    """Diffusion of white measurement noise: d(x, z) ⊃ (0, ∂ż/∂y · σ dW).

    ``vf_prod`` is a Jacobian-vector product of the observer's vector field in y (no Jacobian is formed).
    """

    sigma: jax.Array
    path: diffrax.AbstractPath

    def vf(self, t, state, args):
        x, z = state
        u, y, _ = _signals(args, t, x, z)
        jac = jax.jacfwd(lambda yy: args.observer.vector_field(t, z, yy, u))(y)
        s = jnp.broadcast_to(self.sigma, y.shape)
        return jnp.zeros(x.shape + y.shape, x.dtype), jax.tree_util.tree_map(lambda j: j * s, jac)

    def contr(self, t0, t1, **kwargs):
        return self.path.evaluate(t0, t1, **kwargs)

    def prod(self, vf, control):
        return jax.tree_util.tree_map(lambda j: j @ control, vf)

    def vf_prod(self, t, state, args, control):
        x, z = state
        u, y, _ = _signals(args, t, x, z)
        dy = jnp.broadcast_to(self.sigma, y.shape) * control
        _, dz = jax.jvp(lambda yy: args.observer.vector_field(t, z, yy, u), (y,), (dy,))
        return jnp.zeros_like(x), dz


def _check_ts(ts):
    ts = as_float_array(ts, "ts")
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"`ts` must be a 1-D array of at least 2 save times, got shape {tuple(ts.shape)}.")
    v = concrete_value(ts)
    if v is not None and not np.all(np.diff(v) > 0):
        raise ValueError("`ts` must be strictly increasing.")
    return ts


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
    rtol: float = 1e-6,
    atol: float = 1e-8,
    dt0: float | None = None,
    adaptive: bool = True,
    max_steps: int | None = 16384,
    max_segments: int | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    throw: bool = True,
    _study: bool = False,
) -> Trajectory:
    """Simulate the true plant and an observer together: one diffrax solve over the joint state (x, z).

        ẋ = f(t, x, u),   y = h(t, x, u) + v,   ż = observer.vector_field(t, z, y, u),
        x̂ = observer.estimate(t, z, y),   u = u(t) + controller(t, x̂).

    The observer carries its own model of the plant; ``plant`` is the truth, so model mismatch is free.
    Observers with a ``reset_period`` T (Chen & Yen's covariance reset) are integrated segment by segment,
    a ``lax.scan`` over [t0 + kT, t0 + (k+1)T] with one ``diffeqsolve`` each and ``observer.reset`` between,
    so gradients with respect to T itself are exact.  The plant's ``jump_ts`` are passed to diffrax's
    ``ClipStepSizeController``.

    **Arguments:**

    - `plant`: the true system (:class:`obsjax.LTI`, :class:`obsjax.LTV`, :class:`obsjax.Nonlinear`).
    - `observer`: any :class:`obsjax.AbstractObserver`.
    - `x0`, `xhat0`: initial plant state and initial estimate, shape (n,).
    - `ts`: (T,) strictly increasing save times; the solve runs from ``ts[0]`` to ``ts[-1]``.
    - `u`: open-loop input, a callable t -> (p,), zero when ``None``.
    - `controller`: output feedback ``controller(t, x̂) -> (p,)`` (closes the loop through the estimate).
    - `noise`: :class:`obsjax.noise.WhiteNoise` (an SDE; fixed steps, Euler–Maruyama by default, ``dt0``
      defaulting to span/2000) or :class:`obsjax.noise.BandLimitedNoise`; needs ``key``.
    - `solver`: a diffrax solver.  Default: the observer's ``recommended_solver(ts)`` when it has one (the
      high-gain :class:`obsjax.TrajectoryLinearization` returns the implicit ``Kvaerno5`` when
      max|ρ̄|·ω/ε makes the problem stiff), else ``Tsit5``.
    - `rtol`, `atol`: tolerances of the adaptive PID controller.
    - `dt0`, `adaptive`: ``adaptive=False`` with ``dt0`` gives fixed steps.  With an explicit Runge–Kutta
      solver and concrete ``ts`` (and reset period), fixed steps bypass ``diffeqsolve``: a ``lax.scan`` over
      the solver's Butcher tableau on a grid through every save time, reset instant and plant jump, each
      interval cut into ⌈Δ/dt0⌉ equal steps (see ``obsjax/_fixed_step.py``).
    - `max_steps`: per solve (per segment for resetting observers).
    - `adjoint`: how diffrax differentiates each solve (default ``RecursiveCheckpointAdjoint()``, with
      log₂(max_steps) checkpoints); e.g. ``RecursiveCheckpointAdjoint(checkpoints=max_steps)`` stores every
      step of a short fixed-step segment and skips recomputation in reverse mode.  Unused by the direct
      fixed-step path (a ``lax.scan``, differentiated by JAX).
    - `max_segments`: number of reset segments, needed only when the reset period is traced under ``jit``
      (outside ``jit`` it is computed as ceil((t1 − t0) / T)); must satisfy max_segments·T ≥ t1 − t0.
    - `throw`: raise on solver failure or non-finite values; ``False`` returns ``status`` instead, so a failing
      member of a vmapped batch does not poison the rest.

    **Returns:** a :class:`obsjax.Trajectory`.

    **Example:**::

        plant = obsjax.LTI([[-2., 1.], [0., -1.]], [[0.], [1.]], [[1., 0.]])
        obs = obsjax.Luenberger.from_poles(plant, [-3., -3.])
        traj = obsjax.simulate(plant, obs, jnp.array([1., 1.]), jnp.zeros(2), jnp.linspace(0, 5, 51))
    """
    require_x64("obsjax.simulate")
    if not isinstance(plant, AbstractSystem):
        raise ValueError(f"`plant` must be an obsjax plant (LTI, LTV, Nonlinear), got {type(plant).__name__}.")
    if not isinstance(observer, AbstractObserver):
        raise ValueError(f"`observer` must be an obsjax observer, got {type(observer).__name__}.")
    ts_np = concrete_value(ts)
    ts = _check_ts(ts)
    x0 = as_float_array(x0, "x0")
    if x0.shape != (plant.n,):
        raise ValueError(f"`x0` must have shape ({plant.n},) (the plant's state), got {tuple(x0.shape)}.")
    xhat0 = as_float_array(xhat0, "xhat0")
    if xhat0.ndim != 1:
        raise ValueError(f"`xhat0` must be a vector, got shape {tuple(xhat0.shape)}.")
    if noise is not None and key is None:
        raise ValueError("`key` is required when `noise` is given (the noise is drawn from it).")
    if not adaptive and dt0 is None and not isinstance(noise, WhiteNoise):
        raise ValueError("`dt0` is required for fixed steps (adaptive=False).")

    observer = observer.prepare()
    t0, t1 = ts[0], ts[-1]
    m = plant.m

    noise_path = None
    if isinstance(noise, BandLimitedNoise):
        t0c, t1c = _concrete_span(ts_np)
        noise_path = realise_band_limited(noise, key, t0c, t1c, m)
    elif noise is not None and not isinstance(noise, WhiteNoise):
        raise ValueError(f"`noise` must be WhiteNoise or BandLimitedNoise, got {type(noise).__name__}.")

    args = _Args(plant, observer, u, controller, noise_path)
    u0 = _zeros_input(plant) if u is None else jnp.asarray(u(t0)).reshape(plant.p)
    v0 = 0.0 if noise_path is None else noise_path(t0)
    z0 = observer.init(t0, xhat0, plant.h(t0, x0, u0) + v0)

    # Terms, solver, step-size control.
    drift = _drift_in_study if _study else _drift
    if isinstance(noise, WhiteNoise):
        t0c, t1c = _concrete_span(ts_np)
        span = t1c - t0c
        if dt0 is None:
            dt0 = span / 2000.0
        bm = diffrax.VirtualBrownianTree(t0c, t1c, tol=dt0 / 2, shape=(m,), key=key)
        terms = diffrax.MultiTerm(
            diffrax.ODETerm(drift), _MeasurementNoiseTerm(noise.sigma, bm)
        )
        solver = diffrax.Euler() if solver is None else solver
        adaptive = False
        if max_steps is not None:
            max_steps = max(max_steps, int(math.ceil(span / dt0)) + 16)
    else:
        terms = diffrax.ODETerm(drift)
        if solver is None:
            # Observers that know their own stiffness (the high-gain TLO) pick the solver.
            pick = getattr(observer, "recommended_solver", None)
            solver = pick(ts_np) if pick is not None else diffrax.Tsit5()

    jumps = plant.jumps
    if adaptive:
        ctrl = diffrax.PIDController(rtol=rtol, atol=atol)
    else:
        ctrl = diffrax.ConstantStepSize()
        if ts_np is not None and max_steps is not None:
            span_c = float(ts_np[-1] - ts_np[0])
            max_steps = max(max_steps, int(math.ceil(span_c / float(dt0))) + 16)
    if jumps is not None and adaptive:
        # (Fixed steps step onto the jumps in the direct path below; diffrax's ConstantStepSize cannot be
        # clipped, so a fixed-step SDE or a traced grid steps over them: first order across each jump.)
        ctrl = diffrax.ClipStepSizeController(ctrl, jump_ts=jumps)

    def solve(s0, s1, state, save_ts):
        sol = diffrax.diffeqsolve(
            terms,
            solver,
            s0,
            s1,
            dt0,
            state,
            args=args,
            saveat=diffrax.SaveAt(ts=save_ts, t1=True),
            stepsize_controller=ctrl,
            max_steps=max_steps,
            throw=False,
            **({} if adjoint is None else {"adjoint": adjoint}),
        )
        ok = sol.result == diffrax.RESULTS.successful
        return sol.ys, ok

    state0 = (x0, z0)
    T = observer.reset_period
    # Fixed steps of an explicit Runge-Kutta method on a grid known before tracing: a direct lax.scan over the
    # tableau (obsjax/_fixed_step.py), several times faster than diffrax's generic step on small states.
    direct = None
    if not adaptive and not isinstance(noise, WhiteNoise):
        tab = _fixed_step.tableau_of(solver)
        if tab is not None:
            g = _fixed_step.grid(ts_np if ts_np is not None else ts, dt0, T, jumps)
            if g is not None:
                direct = (tab, g)
    if direct is not None:
        tab, g = direct
        xs, zs = _fixed_step.integrate(
            _drift, args, state0, g, tab,
            reset=None if T is None else (lambda t, st: (st[0], observer.reset(t, st[1]))),
        )
        ok_all = jnp.asarray(True)
    elif T is None:
        ys, ok = solve(t0, t1, state0, ts)
        xs, zs = jax.tree_util.tree_map(lambda a: a[:-1], ys)
        ok_all = ok
    else:
        xs, zs, ok_all = _segmented(observer.reset, solve, state0, ts, T, max_segments, ts_np)

    # Algebraic outputs at the save times.
    def outputs(t, x, z):
        _, y, xhat = _signals(args, t, x, z)
        return y, xhat

    y_s, xhat_s = jax.vmap(outputs)(ts, xs, zs)
    error = xhat_s - jax.vmap(observer.target)(ts, xs)
    finite = jnp.all(jnp.isfinite(error)) & jnp.all(jnp.isfinite(y_s))
    status = jnp.where(ok_all, jnp.where(finite, SUCCESS, NONFINITE), SOLVER_FAILED).astype(jnp.int32)
    if throw:
        error = eqx.error_if(
            error,
            status == SOLVER_FAILED,
            "obsjax.simulate: the solver did not reach the end of the horizon (max_steps reached or step "
            "size underflow). Raise `max_steps`, loosen `rtol`/`atol`, or use an implicit solver for a stiff "
            "observer; pass throw=False to get a per-trajectory status instead.",
        )
        error = eqx.error_if(
            error,
            status == NONFINITE,
            "obsjax.simulate: the trajectory contains non-finite values (the plant or the observer diverged, "
            "or a gain is invalid). Pass throw=False to get a per-trajectory status instead.",
        )
    return Trajectory(ts=ts, x=xs, xhat=xhat_s, y=y_s, error=error, z=zs, status=status)


def _concrete_span(ts_np):
    if ts_np is None:
        raise ValueError(
            "`ts` must be concrete when `noise` is given (noise paths are drawn on a grid fixed before "
            "tracing): close over `ts` instead of passing it as a traced argument."
        )
    return float(ts_np[0]), float(ts_np[-1])


def num_segments(T, t0, t1) -> int | None:
    """ceil((t1 − t0)/T) for concrete values (a relative slack of 1e-9 absorbs rounding), else ``None``."""
    Tv, a, b = concrete_value(T), concrete_value(t0), concrete_value(t1)
    if Tv is None or a is None or b is None:
        return None
    Tv = float(np.asarray(Tv).reshape(()))
    if not Tv > 0:
        raise ValueError(f"the reset period `T` must be > 0, got {Tv}.")
    r = (float(b) - float(a)) / Tv
    return max(1, int(math.ceil(r - 1e-9 * max(1.0, r))))


def _segmented(reset, solve, state0, ts, T, max_segments, ts_np=None):
    t0, t1 = ts[0], ts[-1]
    n_seg = max_segments
    if n_seg is None and ts_np is not None:
        n_seg = num_segments(T, ts_np[0], ts_np[-1])
    if n_seg is None:
        raise ValueError(
            "The number of reset segments ceil((ts[-1] − ts[0]) / T) cannot be computed because the reset "
            "period T or the save times ts are traced (inside jit): pass `max_segments` (≥ (t1 − t0)/T) to "
            "obsjax.simulate."
        )
    T = jnp.asarray(T)
    T = eqx.error_if(
        T,
        (T <= 0) | (n_seg * T < (t1 - t0) * (1 - 1e-12)),
        "reset period T must be > 0 and max_segments·T must cover the horizon [ts[0], ts[-1]].",
    )
    # Index of the segment each save time belongs to (right-continuous at reset instants).
    seg_of = jnp.clip(jnp.floor((ts - t0) / T + 1e-9), 0, n_seg - 1).astype(jnp.int32)
    shapes = jax.eval_shape(lambda s: s, state0)
    buf0 = jax.tree_util.tree_map(lambda s: jnp.zeros((ts.shape[0],) + s.shape, s.dtype), shapes)

    def body(carry, k):
        state, buf, ok = carry
        # min(t0 + kT, t1), with a tie (horizon a multiple of T) resolved to the fixed t1: the end of the
        # horizon, like the save times, carries no T-derivative (jnp.minimum would split it 50/50).
        a0, a1 = t0 + k * T, t0 + (k + 1) * T
        s0 = jnp.where(a0 < t1, a0, t1)
        s1 = jnp.where(a1 < t1, a1, t1)
        s1 = jnp.where(k == n_seg - 1, t1, s1)
        x, z = state
        z = jax.lax.cond(k > 0, lambda zz: reset(s0, zz), lambda zz: zz, z)
        # Save times are fixed: they must not inherit a T-derivative from the clip (ties at reset instants).
        save_ts = jnp.clip(ts, jax.lax.stop_gradient(s0), jax.lax.stop_gradient(s1))
        ys, ok_k = solve(s0, s1, (x, z), save_ts)
        inside = seg_of == k
        buf = jax.tree_util.tree_map(
            lambda b, v: jnp.where(inside.reshape((-1,) + (1,) * (b.ndim - 1)), v[:-1], b), buf, ys
        )
        end = jax.tree_util.tree_map(lambda v: v[-1], ys)
        return (end, buf, ok & ok_k), None

    (_, buf, ok), _ = jax.lax.scan(body, (state0, buf0, jnp.asarray(True)), jnp.arange(n_seg))
    xs, zs = buf
    return xs, zs, ok
