"""The door of :func:`obsjax.simulate` and :func:`obsjax.simulate_batch`: every argument checked once.

Eagerly (before tracing) a bad argument raises ``ValueError`` naming it, what was expected and what was
found; values that are traced (inside ``jit``) are checked with ``eqx.error_if`` (the save times, dt0) or
surface as the trajectory's status (a NaN x0 or gain: ``NONFINITE``).  Shapes are checked across the plant,
the observer, x0, x̂0, ``u``, ``controller`` and the noise with ``jax.eval_shape`` (nothing is computed).
"""

from __future__ import annotations

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value, real_array, static_value
from ..observers._base import AbstractObserver
from ..systems._noise import BandLimitedNoise, WhiteNoise
from ..systems._plants import AbstractSystem
from . import _schedule
from ._diffrax import Options


def check_plant(plant):
    if not isinstance(plant, AbstractSystem):
        raise ValueError(f"`plant` must be an obsjax plant (LTI, LTV, Nonlinear), got {type(plant).__name__}.")


def check_observer(observer):
    if not isinstance(observer, AbstractObserver):
        raise ValueError(f"`observer` must be an obsjax observer, got {type(observer).__name__}.")


def check_noise(noise):
    if noise is not None and not isinstance(noise, (WhiteNoise, BandLimitedNoise)):
        raise ValueError(
            "`noise` must be an obsjax noise model (obsjax.noise.WhiteNoise or BandLimitedNoise) or None, "
            f"got {type(noise).__name__}."
        )


def check_types(plant, observer, noise):
    """The types of the plant, the observer and the noise (``simulate``, ``simulate_batch``, ``tune``,
    ``monte_carlo``)."""
    check_plant(plant)
    check_observer(observer)
    check_noise(noise)


def concrete_times(ts):
    """The save times as a float64 NumPy array when they are constants, else ``None`` (traced by jit, or by an
    eager ``jax.grad``/``jvp`` in the save times: a NumPy grid would drop that derivative)."""
    v = static_value(ts)
    if v is None or np.iscomplexobj(v):
        return None
    return np.asarray(v, dtype=np.float64)


def check_ts_values(v: np.ndarray) -> None:
    """Concrete save times: finite and strictly increasing (``ValueError`` naming the first offender)."""
    if not np.all(np.isfinite(v)):
        raise ValueError(f"`ts` must hold finite times, got {v[~np.isfinite(v)][:3].tolist()}.")
    bad = np.flatnonzero(np.diff(v) <= 0)
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"`ts` must be strictly increasing, got ts[{i}] = {v[i]} followed by ts[{i + 1}] = {v[i + 1]}."
        )


def check_ts(ts):
    """Save times: real, 1-D, at least 2, finite and strictly increasing (eagerly, and under jit)."""
    v = concrete_times(ts)
    ts = real_array(ts, "ts")
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"`ts` must be a 1-D array of at least 2 save times, got shape {tuple(ts.shape)}.")
    if v is not None:
        check_ts_values(v)
        return ts
    ts = eqx.error_if(
        ts,
        ~jnp.all(jnp.isfinite(ts)),
        "`ts` must hold finite save times (a NaN or an infinite time reached a traced `ts`).",
    )
    return eqx.error_if(
        ts,
        ~jnp.all(jnp.diff(ts) > 0),
        "`ts` must be strictly increasing (finite save times, each after the previous): obsjax never "
        "integrates backwards.",
    )


def check_span(observer, ts_np):
    """The observer after its own check of the simulated span [ts[0], ts[-1]]
    (:meth:`AbstractObserver.check_span`), when the save times are concrete."""
    if ts_np is None or not len(ts_np):
        return observer
    return observer.check_span(float(ts_np[0]), float(ts_np[-1]))


def check_state(x, name, shape_text, ndim):
    arr = real_array(x, name)
    if arr.ndim != ndim:
        raise ValueError(f"`{name}` must have shape {shape_text}, got {tuple(arr.shape)}.")
    return arr


def plain_int(v):
    """A NumPy integer as a Python int, anything else unchanged (checked where it is used): step and
    segment counts are static (they size the solver's buffers), and a NumPy scalar would be traced as an
    array inside a ``jit``."""
    return int(v) if isinstance(v, np.integer) else v


def plain_int_kwargs(kwargs: dict) -> dict:
    """`kwargs` with its ``max_steps`` and ``max_segments`` through :func:`plain_int`."""
    return {k: plain_int(v) if k in ("max_steps", "max_segments") else v for k, v in kwargs.items()}


def check_options(rtol, atol, dt0, adaptive, max_steps, noise):
    for name, v in (("rtol", rtol), ("atol", atol)):
        if isinstance(v, (str, bytes, bool)) or v is None:
            raise ValueError(f"`{name}` must be a finite number > 0, got {v!r}.")
        if np.ndim(v) != 0:
            # the joint state (plant, observer) has no one layout for per-component tolerances, and the
            # back-ends broadcast an array against different leaves
            raise ValueError(
                f"`{name}` must be a scalar (one tolerance for every component of the plant's and the "
                f"observer's states; `atol` is in the units of the states), got shape {np.shape(v)}."
            )
        c = concrete_value(v)
        if c is not None and not np.issubdtype(np.asarray(c).dtype, np.number):
            raise ValueError(f"`{name}` must be a finite number > 0, got {v!r}.")
        if c is not None and np.iscomplexobj(c):
            raise ValueError(f"`{name}` must be real, got {v!r}.")
        if c is not None and not (np.all(np.isfinite(c)) and np.all(c > 0)):
            raise ValueError(f"`{name}` must be finite and > 0, got {c}.")
    if max_steps is not None and (
        isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1
    ):
        raise ValueError(f"`max_steps` must be a positive integer or None, got {max_steps!r}.")
    if not adaptive and dt0 is None and not isinstance(noise, WhiteNoise):
        raise ValueError("`dt0` is required for fixed steps (adaptive=False).")
    if dt0 is None:
        return None
    c = concrete_value(dt0)
    if c is not None:
        if not (np.ndim(c) == 0 and np.isfinite(c) and c > 0):
            raise ValueError(f"`dt0` (the initial or fixed step) must be a finite scalar > 0, got {c}.")
        return float(c)
    dt0 = jnp.asarray(dt0, dtype=jnp.result_type(float))
    return eqx.error_if(dt0, ~(jnp.isfinite(dt0) & (dt0 > 0)), "`dt0` must be finite and > 0.")


def _shape(fn, what):
    try:
        return jax.eval_shape(fn)
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"{what} failed: {type(e).__name__}: {e}") from None


def estimate_dim(observer):
    """The length of x̂0 the observer takes (its model's n, or its own `n`), or ``None`` where it does not
    say (checked then by ``observer.init``'s shape)."""
    model = getattr(observer, "model", None)
    n_obs = model.n if isinstance(model, AbstractSystem) else getattr(observer, "n", None)
    return int(n_obs) if isinstance(n_obs, (int, np.integer)) and not isinstance(n_obs, bool) else None


def check_keys_need_noise(noise, key, name):
    """A PRNG key given without a noise model draws nothing: refused, so that a study meant to be noisy
    does not run noise-free without a word."""
    if noise is None and key is not None:
        raise ValueError(
            f"`{name}` is given but `noise` is None: nothing would be drawn from it, and the result would be "
            f"noise-free. Pass the noise model (`noise=obsjax.noise.WhiteNoise(...)` or BandLimitedNoise) "
            f"or leave `{name}` out."
        )


def check_dimensions(plant, observer, x0, xhat0, t0, u, controller, noise):
    """Shapes across plant, observer, x0, x̂0, u, controller and noise (x0, x̂0 of one member)."""
    n, m, p = plant.n, plant.m, plant.p
    if x0.shape != (n,):
        raise ValueError(f"`x0` must have shape ({n},) (the plant's state), got {tuple(x0.shape)}.")
    u0 = _check_input(u, t0, p)
    if noise is not None:
        s = jnp.shape(noise.sigma)
        if s not in ((), (m,)):  # (1,) for m > 1 is ambiguous: one output's intensity, or all?
            raise ValueError(
                f"`noise.sigma` must be a scalar or have shape ({m},) (one intensity per plant output), "
                f"got shape {s}."
            )
    model = getattr(observer, "model", None)
    if isinstance(model, AbstractSystem):
        if model.m != m:
            raise ValueError(
                f"`observer` expects m = {model.m} measurement(s) (its model's outputs) but `plant` has m = {m}."
            )
        if model.n != n:
            raise ValueError(f"`observer`'s model has n = {model.n} states but `plant` has n = {n}.")
    n_obs = estimate_dim(observer)
    if n_obs is not None and xhat0.shape != (n_obs,):
        raise ValueError(
            f"`xhat0` must have shape ({n_obs},) (the observer's state dimension), got {tuple(xhat0.shape)}."
        )
    y0 = _shape(lambda: plant.h(t0, x0, u0), "the plant's output `h(t, x, u)` at ts[0]")
    z0 = _shape(
        lambda: observer.init(t0, xhat0, jnp.zeros(y0.shape, y0.dtype)),
        f"`observer.init` with `xhat0` of shape {tuple(xhat0.shape)} and a measurement of shape ({m},)",
    )
    ybar = jnp.zeros(y0.shape, y0.dtype)
    zbar = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), z0)
    xh = _shape(lambda: observer.estimate(t0, zbar, ybar), "`observer.estimate`")
    tg = _shape(lambda: observer.target(t0, x0), "`observer.target` on the plant's state")
    if xh.shape != tg.shape:
        raise ValueError(
            f"`observer` estimates shape {xh.shape} but its target for the plant's state (n = {n}) has shape "
            f"{tg.shape}."
        )
    try:
        dz = jax.eval_shape(lambda: observer.vector_field(t0, zbar, ybar, jnp.zeros((p,))))
    except Exception as e:  # noqa: BLE001
        p_model = getattr(model, "p", None)
        if isinstance(p_model, (int, np.integer)) and p_model != p:
            raise ValueError(
                f"`observer` expects p = {p_model} input(s) (its model's inputs) but `plant` has p = {p}."
            ) from None
        raise ValueError(
            f"`observer.vector_field` with the plant's measurement (m = {m}) and input (p = {p}) failed: "
            f"{type(e).__name__}: {e}"
        ) from None
    if jax.tree_util.tree_structure(dz) != jax.tree_util.tree_structure(z0) or any(
        a.shape != b.shape for a, b in zip(jax.tree_util.tree_leaves(dz), jax.tree_util.tree_leaves(z0))
    ):
        raise ValueError("`observer.vector_field` must return the structure and shapes of the observer state.")
    fx = _shape(lambda: plant.f(t0, x0, jnp.zeros((p,))), "the plant's `f(t, x, u)`")
    if fx.shape != (n,):
        raise ValueError(f"the plant's `f(t, x, u)` must return shape ({n},), got {fx.shape}.")
    _check_controller(controller, t0, jnp.zeros(xh.shape, xh.dtype), p)


def _check_input(u, t0, p):
    if u is None:
        return jnp.zeros((p,))
    if not callable(u):
        raise ValueError(f"`u` must be a callable t -> (p,) input, got {type(u).__name__}.")
    out = _shape(lambda: jnp.asarray(u(t0)), "calling `u(t)` at ts[0]")
    if jnp.issubdtype(out.dtype, jnp.complexfloating):
        raise ValueError(f"`u(t)` must return real values, got dtype {out.dtype} at ts[0].")
    if int(np.prod(out.shape)) != p:
        raise ValueError(
            f"`u(t)` must return shape ({p},) (one value per plant input, p = {p}), got shape {out.shape}."
        )
    return jnp.zeros((p,))


def _check_controller(controller, t0, xhat, p):
    if controller is None:
        return
    if not callable(controller):
        raise ValueError(f"`controller` must be a callable (t, x̂) -> (p,), got {type(controller).__name__}.")
    if p == 0:
        raise ValueError("`controller` is given but `plant` has no inputs (p = 0).")
    out = _shape(lambda: jnp.asarray(controller(t0, xhat)), f"calling `controller(t, x̂)` with x̂ of shape {xhat.shape}")
    if jnp.issubdtype(out.dtype, jnp.complexfloating):
        raise ValueError(f"`controller(t, x̂)` must return real values, got dtype {out.dtype}.")
    if int(np.prod(out.shape)) != p:
        raise ValueError(
            f"`controller(t, x̂)` must return shape ({p},) (one value per plant input), got shape {out.shape}."
        )


def pick_solver(solver, observer, ts_np, noise):
    if solver is not None:
        if not isinstance(solver, diffrax.AbstractSolver):
            raise ValueError(f"`solver` must be a diffrax solver, got {type(solver).__name__}.")
        return solver
    if isinstance(noise, WhiteNoise):
        return diffrax.Euler()
    # Observers that know their own stiffness (the high-gain TLO) pick the solver.
    pick = getattr(observer, "recommended_solver", None)
    return pick(ts_np) if pick is not None else diffrax.Tsit5()


def concrete_span(ts_np):
    if ts_np is None:
        raise ValueError(
            "`ts` must be concrete when `noise` is given (noise paths are drawn on a grid fixed before "
            "tracing): close over `ts` instead of passing it as a traced argument."
        )
    return float(ts_np[0]), float(ts_np[-1])


@dataclasses.dataclass(frozen=True)
class Plan:
    """What every back-end needs: the resolved options and the schedule of breakpoints."""

    opt: Options
    sched: _schedule.Schedule
    ts: jax.Array
    ts_np: np.ndarray | None


def plan(plant, observer, ts, ts_np, *, noise, key, solver, rtol, atol, dt0, adaptive, max_steps,
         max_segments, adjoint) -> Plan:
    """Resolve the options (solver, white-noise SDE settings) and build the schedule."""
    span = None
    if isinstance(noise, WhiteNoise):
        span = concrete_span(ts_np)
        if dt0 is None:
            dt0 = (span[1] - span[0]) / 2000.0
        adaptive = False
    elif not adaptive and ts_np is not None:
        span = (float(ts_np[0]), float(ts_np[-1]))
    opt = Options(
        solver=pick_solver(solver, observer, ts_np, noise), rtol=rtol, atol=atol, dt0=dt0,
        adaptive=bool(adaptive), max_steps=max_steps, adjoint=adjoint,
        white_noise=noise if isinstance(noise, WhiteNoise) else None,
        key=key if isinstance(noise, WhiteNoise) else None, span=span,
    )
    T = observer.reset_period
    n_reset = 1 if T is None else _schedule.reset_segments(T, ts, ts_np, max_segments)
    sched = _schedule.build(ts, ts_np, T, n_reset, getattr(plant, "jump_ts", None), observer.event_times)
    if isinstance(noise, WhiteNoise) and sched.has_event:
        raise ValueError(
            f"{type(observer).__name__} updates its estimate from measurements at discrete instants, and "
            "white measurement noise (WhiteNoise) has no value at an instant: those updates would see the "
            "noise-free output. Use BandLimitedNoise(sigma, dt) (samples of variance sigma²; a "
            "ContinuousDiscreteKalman's Rv = sigma²) or recorded measurements (obsjax.estimate)."
        )
    return Plan(opt, sched, ts, ts_np)
