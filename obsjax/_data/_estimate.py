"""Run an observer on recorded measurements: :func:`estimate`, a driver of the segmented integration core."""

from __future__ import annotations

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value, real_array, without_diffrax_save_time_checks
from .._config import require_x64
from .._integrate import _diffrax, _schedule, _segments
from .._integrate._status import NONFINITE, SOLVER_FAILED, SUCCESS, code_of, is_finite
from .._integrate._validate import check_options, check_span, concrete_times, plain_int
from ..montecarlo._fingerprint import content_key
from ..observers._base import AbstractObserver
from ._measurements import Measurements, hermite_coefficients

tmap = jax.tree_util.tree_map


class Estimate(eqx.Module):
    """An observer run on recorded data, one row per save time (the samples by default).

    - `ts`: (T,) save times.
    - `xhat`: (T, n) estimate x̂(t), right-continuous (after the update at a sample, as in
      :class:`obsjax.Trajectory`).
    - `yhat`: (T, m) predicted output ŷ(t) = h(t, x̂⁻(t), u(t)) from the observer's model, x̂⁻ the
      estimate *before* a discrete update at t (the one-step prediction of a sampled-data filter; equal to
      x̂ for a continuous observer); ``None`` when the observer has no output model (adaptive observers,
      functional observers).
    - `innovation`: (T, m) y(t) − ŷ(t), the held measurement minus the prediction (at the samples: the
      sample itself); ``None`` with `yhat`.
    - `z`: the observer state pytree, each leaf with a leading axis T.
    - `status`: int, 0 success, 1 solver failure (max_steps), 2 non-finite values (see :func:`estimate`).
    - `valid`: (T,) bool, False at padding of a stacked batch (:meth:`obsjax.Measurements.stack`).
    - `state_error`: (T, q) x̂[:, x_index] − x_ref when the data carry validation states (at the samples),
      else ``None``.
    """

    ts: jax.Array
    xhat: jax.Array
    yhat: jax.Array | None
    innovation: jax.Array | None
    z: object
    status: jax.Array
    valid: jax.Array
    state_error: jax.Array | None


class _Hold(eqx.Module):
    """The held signal [y; u] on each sampling interval, evaluated from the interval's index k."""

    ts: jax.Array
    values: jax.Array
    coeffs: tuple | None
    kind: str = eqx.field(static=True)

    @classmethod
    def of(cls, data: Measurements):
        v = jnp.concatenate([data.y, data.u], axis=-1)
        coeffs = hermite_coefficients(data.ts, v) if data.hold == "cubic" else None
        return cls(data.ts, v, coeffs, data.hold)

    def __call__(self, t, k):
        K = self.ts.shape[0]
        if self.kind == "zoh":
            return self.values[jnp.clip(k, 0, K - 1)]
        j = jnp.clip(k, 0, K - 2)
        s = t - self.ts[j]
        if self.kind == "linear":
            return self.values[j] + s * (self.values[j + 1] - self.values[j]) / (self.ts[j + 1] - self.ts[j])
        d, c, b, a = self.coeffs
        return a[j] + s * (b[j] + s * (c[j] + s * d[j]))


def _output_map(observer):
    """The observer model's output map h(t, x, u), or None when ŷ is not defined from x̂."""
    model = getattr(observer, "model", None)
    if model is None or not callable(getattr(model, "h", None)):
        return None
    if type(observer).target is not AbstractObserver.target:  # it estimates a functional of x
        return None
    return model.h


def _check_dimensions(observer, data: Measurements, xhat0):
    model = getattr(observer, "model", None)
    for dim, name, what in (("m", "m", "outputs"), ("p", "p", "inputs")):
        want = getattr(model, dim, None)
        if isinstance(want, (int, np.integer)) and want != getattr(data, dim):
            fix = " (pass `u` to obsjax.Measurements)" if dim == "p" and data.p == 0 else ""
            raise ValueError(
                f"`data` has {name} = {getattr(data, dim)} {what} but the observer's model has {name} = {want}{fix}."
            )
    n = getattr(model, "n", None)
    if isinstance(n, (int, np.integer)) and xhat0.shape != (n,):
        raise ValueError(f"`xhat0` must have shape ({n},) (the observer's state dimension), got {tuple(xhat0.shape)}.")
    if data.x_index is not None and isinstance(n, (int, np.integer)) and max(data.x_index) >= n:
        raise ValueError(f"`data.x_index` = {data.x_index} names a state beyond n = {n}.")


def _check_save_times(ts, data: Measurements):
    if ts is None:
        return data.ts, concrete_times(data.ts), True
    ts_np = concrete_times(ts)
    from .._integrate._validate import check_ts

    ts = check_ts(ts)
    lo, hi = data.ts[0], data.ts[-1]
    lv, hv = concrete_value(lo), concrete_value(hi)
    if ts_np is not None and lv is not None:
        if ts_np[0] < float(lv) or ts_np[-1] > float(hv):
            raise ValueError(
                f"`ts` must lie within the data's sample times [{float(lv)}, {float(hv)}], got "
                f"[{ts_np[0]}, {ts_np[-1]}]: obsjax does not extrapolate measurements."
            )
    else:
        ts = eqx.error_if(ts, (ts[0] < lo) | (ts[-1] > hi), "`ts` must lie within the data's sample times.")
    return ts, ts_np, False


def estimate(
    observer,
    data,
    xhat0,
    *,
    ts=None,
    solver: diffrax.AbstractSolver | None = None,
    rtol=1e-6,
    atol=1e-8,
    dt0=None,
    adaptive: bool = True,
    max_steps: int | np.integer | None = 4096,
    max_segments: int | np.integer | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    throw: bool = True,
) -> Estimate:
    """Run an observer on recorded measurements: the continuous-time law between samples, driven by the
    held measurement, and the discrete update at each sample.

        ż = observer.vector_field(t, z, y_h(t), u_h(t))   on [t_k, t_{k+1}),
        z(t_k⁺) = observer.update(t_k, reset(z(t_k⁻)), y_k, u_k),      x̂ = observer.estimate(t, z, y_h),

    with y_h, u_h the hold of the samples (:class:`obsjax.Measurements`: zero-order, linear or cubic).
    For a continuous observer (Luenberger, Kalman–Bucy, the least-squares observer with its resets) the
    update is the identity and the data enter through the hold; for a sampled-data filter
    (:class:`obsjax.observers.ContinuousDiscreteKalman`) they enter through the update.

    Like :func:`obsjax.simulate`, the horizon is cut at every breakpoint (here: every sample, and the
    observer's reset instants t0 + kT) and one solve runs per segment in a ``lax.scan``, so no solve steps
    across a kink of the hold or a jump of the state.  On noise-free samples of an LTI plant, the estimate
    agrees with ``simulate`` of the same plant and observer up to the interpolation error of the hold
    (first order in the sampling interval for ``"zoh"``, second for ``"linear"``, third for ``"cubic"``).

    Updates happen at the data's samples (an observer's own ``event_times``, e.g. a sampling period meant
    for ``simulate``, is not used: recorded data define the measurement instants), except at samples whose
    ``mask`` is False (padding).

    **Arguments:**

    - `observer`: any :class:`obsjax.AbstractObserver`.
    - `data`: an :class:`obsjax.Measurements`; a stacked batch (:meth:`obsjax.Measurements.stack`) is
      mapped with ``eqx.filter_vmap`` (then `xhat0` may be (n,) or (batch, n)).
    - `xhat0`: the initial estimate x̂(ts[0]).
    - `ts`: save times within the data's span (default: the sample times, the cheapest: one saved row
      per segment).
    - `solver`, `rtol`, `atol`, `dt0`, `adaptive`, `max_steps`, `max_segments`, `adjoint`: as for
      :func:`obsjax.simulate` (`max_steps` per segment; `max_segments` for a reset observer whose period
      or data are traced, e.g. under ``vmap`` over experiments).
    - `throw`: raise on solver failure or non-finite values (``eqx.error_if``, also under ``jit``);
      ``False`` returns the status instead.

    **Returns:** an :class:`obsjax.Estimate` (ts, xhat, yhat, innovation, z, status, valid, state_error).

    jit-, vmap- (over experiments: a stacked batch; over initial estimates: ``jax.vmap`` over `xhat0`) and
    grad-compatible (gradients with respect to every gain flow through the solves).

    **Example:**::

        data = obsjax.Measurements.from_csv("run.csv", t="t", y=["theta"], u=["volts"])
        obs = obsjax.Luenberger.from_poles(model, [-20.0, -25.0, -30.0])
        est = obsjax.estimate(obs, data, jnp.zeros(3))
        est.xhat[:, 1]   # the velocity estimate
    """
    require_x64("obsjax.estimate")
    if not isinstance(observer, AbstractObserver):
        raise ValueError(f"`observer` must be an obsjax observer, got {type(observer).__name__}.")
    if not isinstance(data, Measurements):
        raise ValueError(f"`data` must be an obsjax.Measurements, got {type(data).__name__}.")
    kwargs = dict(ts=ts, solver=solver, rtol=rtol, atol=atol, dt0=dt0, adaptive=adaptive,
                  max_steps=plain_int(max_steps), max_segments=plain_int(max_segments), adjoint=adjoint,
                  throw=throw)
    if data.batched:
        xhat0 = real_array(xhat0, "xhat0")
        B = data.ts.shape[0]
        if xhat0.ndim == 2 and xhat0.shape[0] != B:
            raise ValueError(f"`xhat0` must be (n,) or ({B}, n) for a batch of {B} experiments, got {tuple(xhat0.shape)}.")
        axis = 0 if xhat0.ndim == 2 else None
        return eqx.filter_vmap(lambda d, x: estimate(observer, d, x, **kwargs), in_axes=(0, axis))(data, xhat0)
    return _estimate_one(observer, data, xhat0, **kwargs)


def _estimate_one(observer, data, xhat0, *, ts, solver, rtol, atol, dt0, adaptive, max_steps, max_segments,
                  adjoint, throw):
    """Validate (eagerly), then run the compiled driver :func:`_run` (one compilation per problem structure)."""
    xhat0 = real_array(xhat0, "xhat0")
    if xhat0.ndim != 1:
        raise ValueError(f"`xhat0` must be a vector (n̂,), got shape {tuple(xhat0.shape)}.")
    dt0 = check_options(rtol, atol, dt0, adaptive, max_steps, None)
    save_ts, ts_np, at_samples = _check_save_times(ts, data)
    observer = observer.prepare()
    observer = check_span(observer, ts_np)
    _check_dimensions(observer, data, xhat0)
    if solver is not None and not isinstance(solver, diffrax.AbstractSolver):
        raise ValueError(f"`solver` must be a diffrax solver, got {type(solver).__name__}.")
    pick = getattr(observer, "recommended_solver", None)
    solver = solver if solver is not None else (pick(ts_np) if pick is not None else diffrax.Tsit5())
    T = observer.reset_period
    n_reset = 1 if T is None else _schedule.reset_segments(T, save_ts, ts_np, max_segments)
    window = 1 if at_samples else _window(observer, data, save_ts, ts_np, n_reset)
    # the observer's content (functions with the globals they read) keys the compiled driver, which would
    # otherwise find the program traced before by the identity of the observer's functions
    data = _checked_samples(data)
    static = (solver, bool(adaptive), max_steps, adjoint, n_reset, window, at_samples, content_key(observer))
    # the checks of `throw` are attached outside the compiled driver (as in simulate): a program with a
    # host callback is not written to the persistent compilation cache, and throw=True/False share one
    return _raise_if(_run(observer, data, xhat0, save_ts, rtol, atol, dt0, static), throw)


def _checked_samples(data: Measurements) -> Measurements:
    """The sample times, the breakpoints of the driver's schedule, must be finite and non-decreasing.  A
    Measurements checks them when it is made; they are checked again here, eagerly (NumPy) when concrete
    and with ``eqx.error_if`` outside the compiled driver when traced, so that the driver carries no host
    callback (a program with one is not written to the persistent compilation cache) and a Measurements
    whose times were replaced after construction (``eqx.tree_at``) is still refused."""
    msg = "obsjax.estimate: `data.ts` must hold finite, non-decreasing sample times"
    v = concrete_value(data.ts)
    if v is not None:
        v = np.asarray(v, dtype=np.float64)
        if not np.all(np.isfinite(v)) or np.any(np.diff(v) < 0):
            raise ValueError(f"{msg}, got {v.tolist() if v.size <= 8 else v}.")
        return data
    ts = eqx.error_if(data.ts, jnp.any(jnp.diff(data.ts) < 0) | jnp.any(~jnp.isfinite(data.ts)), f"{msg}.")
    return eqx.tree_at(lambda d: d.ts, data, ts)


def _window(observer, data, save_ts, ts_np, n_reset):
    """The largest number of save times in one segment, from the concrete schedule (else len(ts))."""
    if ts_np is None or concrete_value(data.ts) is None:
        return int(save_ts.shape[0])
    sched = _schedule.build(save_ts, ts_np, observer.reset_period, n_reset, None, lambda t0, t1: np.asarray(data.ts))
    return sched.window


@eqx.filter_jit
def _run(observer, data, xhat0, save_ts, rtol, atol, dt0, static):
    """The driver: breakpoints at every sample (and reset), one solve per segment, the outputs."""
    solver, adaptive, max_steps, adjoint, n_reset, window, at_samples, content = static
    opt = _diffrax.Options(solver=solver, rtol=rtol, atol=atol, dt0=dt0, adaptive=adaptive, max_steps=max_steps,
                           adjoint=adjoint)
    # every sample is an event breakpoint; the observer's resets are merged in; the save window is known
    # from the structure (one save time per segment at the samples), also when the samples are traced
    sched = _schedule.build(save_ts, None, observer.reset_period, n_reset, None, lambda t0, t1: data.ts,
                            events_checked=True)  # the samples: checked by _checked_samples
    sched = dataclasses.replace(sched, window=window)
    hold = _Hold.of(data)
    t0 = save_ts[0]
    tol = _schedule.tolerance_of(t0, save_ts[-1])
    k0 = jnp.searchsorted(data.ts, t0 - tol, side="left").astype(jnp.int32) - 1
    y0u0 = hold(t0, jnp.maximum(k0, 0))
    z0 = observer.init(t0, xhat0, y0u0[: data.m])
    drift = None
    if sched.has_reset:
        # the reset instants move with T: their derivative through the jump condition at each reset
        # (as in simulate), not through the ends of the solves.  A reset on a sample instant is a
        # zero-length segment between the two breakpoints, whose solve carries no derivative of its
        # ends: the term −δτ f⁺ of the flow after the reset was lost there (d/dT of the wrong sign)
        def drift(t, carry):
            z, k, zm = carry
            return (_vector_field(t, z, (observer, hold, k, data.m, content)), k,
                    tmap(jnp.zeros_like, zm))

    saved, code, _ = _segments.integrate(
        _solver_fn(observer, hold, opt, sched, data.m, content), _act_fn(observer, data, sched), (z0, k0, z0), save_ts,
        sched, jax.eval_shape(lambda: (z0, z0, k0)), drift=drift,
    )
    return _assemble(observer, data, hold, save_ts, saved, code, at_samples)


def _vector_field(t, z, args):
    # everything the field reads comes in through `args` (a closure over the observer's gains would hide
    # them from the custom derivative of the solver's steps)
    observer, hold, k, m, _ = args  # _: the content digest, a key of diffeqsolve's compilation
    v = hold(t, k)
    return observer.vector_field(t, z, v[:m], v[m:])


def _solver_fn(observer, hold, opt, sched, m, content):
    solver = _diffrax.solver_of(opt)
    # the guarded controller ends a diverging solve early (status NONFINITE), as in simulate
    ctrl = _diffrax.controller_of(opt, sched.t0, sched.t1)
    adjoint = {} if opt.adjoint is None else {"adjoint": opt.adjoint}

    term = diffrax.ODETerm(_vector_field)

    def solve(s0, s1, carry, save_ts):
        z, k, zm = carry
        with without_diffrax_save_time_checks():  # save_ts lie in [s0, s1], nondecreasing (``_segments``)
            sol = diffrax.diffeqsolve(
                term, solver, s0, s1, opt.dt0, z, args=(observer, hold, k, m, content),
                saveat=diffrax.SaveAt(ts=save_ts, t1=True), stepsize_controller=ctrl, max_steps=opt.max_steps,
                throw=False, **adjoint,
            )
        zs = tmap(lambda a: a[:-1], sol.ys)
        at_start = save_ts == jax.lax.stop_gradient(s0)
        prior = tmap(lambda a, b: jnp.where(at_start.reshape((-1,) + (1,) * (a.ndim - 1)), b[None], a), zs, zm)
        ks = jnp.broadcast_to(k, save_ts.shape)
        return (zs, prior, ks), code_of(sol.result), (tmap(lambda a: a[-1], sol.ys), k, zm)

    return solve


def _act_fn(observer, data, sched):
    K = data.K

    def act(t, carry, do_reset, do_event):
        z, k, _ = carry
        zm = z
        if sched.has_reset:
            z = jax.lax.cond(do_reset, lambda zz: observer.reset(t, zz), lambda zz: zz, z)
        if sched.has_event:
            k = k + do_event.astype(k.dtype)
            j = jnp.clip(k, 0, K - 1)
            upd = do_event & data.mask[j]
            z = jax.lax.cond(upd, lambda zz: observer.update(t, zz, data.y[j], data.u[j]), lambda zz: zz, z)
        return z, k, zm

    return act


def _assemble(observer, data, hold, ts, saved, code, at_samples) -> Estimate:
    zs, prior, ks = saved
    m = data.m
    v = jax.vmap(hold)(ts, ks)
    yh, uh = v[:, :m], v[:, m:]
    xhat = jax.vmap(observer.estimate)(ts, zs, yh)
    h = _output_map(observer)
    yhat = innovation = None
    if h is not None:
        xprior = jax.vmap(observer.estimate)(ts, prior, yh)
        yhat = jax.vmap(h)(ts, xprior, uh)
        innovation = yh - yhat
    valid = data.mask[jnp.clip(ks, 0, data.K - 1)]
    state_error = None
    if data.x_ref is not None and at_samples:
        state_error = xhat[:, jnp.asarray(data.x_index)] - data.x_ref
    finite = is_finite((xhat, zs)) & (True if yhat is None else is_finite(yhat))
    status = jnp.where(code != SUCCESS, code, jnp.where(finite, SUCCESS, NONFINITE)).astype(jnp.int32)
    return Estimate(ts, xhat, yhat, innovation, zs, status, valid, state_error)


def _raise_if(est: Estimate, throw: bool) -> Estimate:
    if not throw:
        return est
    xhat = eqx.error_if(
        est.xhat, est.status == SOLVER_FAILED,
        "obsjax.estimate: the solver did not reach the end of a sampling interval (max_steps reached, or an "
        "implicit solver failed). Raise `max_steps`, loosen `rtol`/`atol`, or pass throw=False to get the status.",
    )
    xhat = eqx.error_if(
        xhat, est.status == NONFINITE,
        "obsjax.estimate: the estimate diverged or contains non-finite values (an unstable observer, a gain "
        "or an initial estimate that is NaN/inf). Pass throw=False to get the status instead.",
    )
    return eqx.tree_at(lambda e: e.xhat, est, xhat)
