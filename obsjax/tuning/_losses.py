"""Losses on a simulated trajectory (each returns a scalar; :func:`obsjax.tune` averages over a batch)."""

from __future__ import annotations

import math
from fractions import Fraction

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value, real_array, scalar_value


def _trapz(f, ts):
    return jnp.sum(0.5 * (f[1:] + f[:-1]) * jnp.diff(ts))


def ise(traj) -> jnp.ndarray:
    """Integral of squared error ∫ ‖x̃(t)‖² dt (trapezoid on the save grid)."""
    return _trapz(jnp.sum(traj.error**2, axis=-1), traj.ts)


def _norm(error):
    """‖x̃‖ per save time, exact for every value (no absolute smoothing constant, so the states' units do
    not matter; scaled by max |x̃_i| first, so that errors of 1e-200 or 1e200 neither underflow nor
    overflow, and inf for an infinite error); its derivative at x̃ = 0 is taken as 0 (where the norm has
    none)."""
    scale = jax.lax.stop_gradient(jnp.max(jnp.abs(error), axis=-1))  # ‖x̃‖ = s ‖x̃/s‖ for any s > 0
    pos = scale > 0
    big = jnp.isinf(scale)
    safe = jnp.where(pos & ~big, scale, 1.0)
    sq = jnp.sum((error / safe[..., None]) ** 2, axis=-1)
    nrm = safe * jnp.sqrt(jnp.where(pos, sq, 1.0))
    return jnp.where(big, jnp.inf, jnp.where(pos, nrm, 0.0))


def itae(traj) -> jnp.ndarray:
    """Integral of time-weighted absolute error ∫ (t − t0) ‖x̃(t)‖ dt (trapezoid on the save grid; the
    derivative of ‖x̃‖ at x̃ = 0 is taken as 0)."""
    return _trapz((traj.ts - traj.ts[0]) * _norm(traj.error), traj.ts)


def terminal(traj) -> jnp.ndarray:
    """Squared terminal error ‖x̃(t_end)‖²."""
    return jnp.sum(traj.error[-1] ** 2)


def peak(traj, sharpness: float | jax.Array = 50.0) -> jnp.ndarray:
    """Peak error max_t ‖x̃(t)‖ over the save times, as a smooth maximum so that its gradient spreads over
    near-maximal times: the log-sum-exp M + (M/s) log Σ_k exp(s (‖x̃(t_k)‖ − M)/M), M = max_k ‖x̃(t_k)‖,
    s = `sharpness` (> 0; relative to M, so the states' units do not matter).

    It is never below the maximum and at most M (1 + ln K / s) for K save times: the excess is (M/s) ln k
    when k save times share the maximum (an isolated peak adds nothing), so it grows with the density of
    the save grid where the error is flat near its peak (a constant error over 1001 save times gives
    1.138 M at s = 50).  Raise `sharpness` for a value closer to the maximum (and a gradient concentrated
    on fewer times).
    """
    sv = scalar_value(sharpness)
    if sv is not None and not (np.ndim(sv) == 0 and np.isrealobj(sv) and np.isfinite(sv) and sv > 0):
        raise ValueError(f"`sharpness` must be a positive finite scalar, got {np.asarray(sv).tolist()}.")
    if sv is None:  # traced: checked under jit
        sharpness = eqx.error_if(
            sharpness, ~(jnp.isfinite(sharpness) & (sharpness > 0)), "`sharpness` must be a positive finite scalar."
        )
    # the peak is homogeneous of degree 1 in x̃: computed on x̃ / S, S = max |x̃_i| (no derivative), and
    # multiplied by S, so that errors of 1e-200 or 1e200 neither underflow nor overflow (nor their gradients)
    err = traj.error
    S = jax.lax.stop_gradient(jnp.max(jnp.abs(err)))
    safe = jnp.where(jnp.isfinite(S) & (S > 0), S, 1.0)
    nrm = _norm(err / safe)
    top = jnp.max(nrm)
    ratio = nrm / jnp.where(top > 0, top, 1.0)  # in [0, 1]; all 0 for a zero error (then the peak is 0)
    smooth = top * (1.0 + jnp.log(jnp.sum(jnp.exp(sharpness * (ratio - 1.0)))) / sharpness)
    return jnp.where(jnp.isinf(S), jnp.inf, safe * smooth)  # an infinite error: an infinite peak, not NaN


def _valid_mean(values, valid):
    """Mean over the valid rows; NaN when there is none (a mean of nothing is not a zero loss)."""
    w = valid.astype(values.dtype)
    count = jnp.sum(w)
    return jnp.where(count > 0, jnp.sum(w * values) / jnp.maximum(count, 1.0), jnp.nan)


def _output_weight(weight, m):
    """The (m,) output weights: real, finite, ≥ 0, not all 0 (a ValueError naming `weight`; traced values
    by ``eqx.error_if``).  A negative weight would make the loss reward that output's error."""
    w = real_array(weight, "weight")
    if w.shape != (m,):
        raise ValueError(f"`weight` must have shape ({m},) (one weight per output), got {tuple(w.shape)}.")
    wv = concrete_value(w)
    if wv is None:
        return eqx.error_if(
            w, ~(jnp.all(jnp.isfinite(w)) & jnp.all(w >= 0) & jnp.any(w > 0)),
            "`weight` must be finite and ≥ 0, with at least one weight > 0.",
        )
    if not (np.all(np.isfinite(wv)) and np.all(wv >= 0) and np.any(wv > 0)):
        raise ValueError(
            f"`weight` must be finite and ≥ 0, with at least one weight > 0 (a negative weight rewards that "
            f"output's error), got {wv.tolist()}."
        )
    return w


def output_error(est, integral: bool = False, weight=None) -> jnp.ndarray:
    """Output prediction error of an :class:`obsjax.Estimate` on recorded data.

    Default: the mean over the valid samples of ‖y_k − ŷ_k‖², ŷ_k = h(t_k, x̂⁻_k, u_k) the prediction
    before the update at t_k (for a sampled-data filter the one-step prediction error, whose minimisation
    is the prediction-error method of system identification, Ljung, *System Identification: Theory for the
    User*, 2nd ed., Prentice Hall, 1999, §7.2); padding (``est.valid`` False) is ignored, so experiments of
    different lengths batch.  ``integral=True``: ∫ ‖y − ŷ‖² dt by the trapezoid rule over the save grid
    (intervals with both ends valid only).  `weight`: optional (m,) weights w_i ≥ 0 (finite, not all 0) of
    ‖e‖² = Σ w_i e_i² (e.g. 1/σ_i² to put outputs in different units on one scale).  An estimate without a valid sample (for the integral: without an interval whose two ends are
    valid) gives NaN, never a zero loss.
    """
    if est.innovation is None:
        raise ValueError(
            "`output_error` needs the predicted output ŷ, but this estimate has none (the observer has no "
            "output model: an adaptive or functional observer); use `state_error` with validation states."
        )
    w_out = 1.0 if weight is None else _output_weight(weight, est.innovation.shape[-1])
    sq = jnp.sum(w_out * est.innovation**2, axis=-1)
    if integral:
        w = (est.valid[1:] & est.valid[:-1]).astype(sq.dtype)
        total = jnp.sum(w * 0.5 * (sq[1:] + sq[:-1]) * jnp.diff(est.ts))
        return jnp.where(jnp.any(w > 0), total, jnp.nan)  # no interval with both ends valid: NaN
    return _valid_mean(sq, est.valid)


def state_error(est) -> jnp.ndarray:
    """Mean over the valid samples of ‖x̂_k[x_index] − x_ref,k‖²: the error on the states that were measured
    for validation (``x_ref`` of :class:`obsjax.Measurements`)."""
    if est.state_error is None:
        raise ValueError(
            "`state_error` needs validation states: build the Measurements with `x_ref` and `x_index`, and "
            "save at the samples (ts=None)."
        )
    return _valid_mean(jnp.sum(est.state_error**2, axis=-1), est.valid)


def cvar_level(alpha) -> float:
    """The level α of ``("cvar", α)``: a real number in [0, 1) (``ValueError`` otherwise)."""
    try:
        v = None if isinstance(alpha, (bool, str)) else scalar_value(alpha)
    except Exception:  # noqa: BLE001  (not array-like)
        v = None
    if v is None or v.ndim != 0 or not (np.issubdtype(v.dtype, np.integer) or np.issubdtype(v.dtype, np.floating)):
        raise ValueError(
            f"CVaR level α must be a real number in [0, 1) (a static value, not traced), got {alpha!r}."
        )
    alpha = float(v)
    if not 0.0 <= alpha < 1.0:
        raise ValueError(f"CVaR level α must be in [0, 1), got {alpha}.")
    return alpha


def tail_count(alpha: float, n: int) -> int:
    """k = ⌈(1 − α) n⌉ (at least 1): how many of n equally weighted losses the CVaR at level α averages
    (the worst k).  α is taken as the shortest decimal that gives its float (0.95 as 19/20) and the product
    is computed exactly: in binary, (1 − 0.95)·20 = 1.0000000000000009 would average the worst 2 of 20
    instead of the worst 1, and no fixed rounding slack is right for every n."""
    x = (1 - Fraction(repr(float(alpha)))) * int(n)  # the decimal α as written: exact for any n
    return max(1, math.ceil(x))

