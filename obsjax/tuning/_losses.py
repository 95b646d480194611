"""Losses on a simulated trajectory (each returns a scalar; :func:`obsjax.tune` averages over a batch)."""

from __future__ import annotations

import math

import jax.numpy as jnp


def _trapz(f, ts):
    return jnp.sum(0.5 * (f[1:] + f[:-1]) * jnp.diff(ts))


def ise(traj) -> jnp.ndarray:
    """Integral of squared error ∫ ‖x̃(t)‖² dt (trapezoid on the save grid)."""
    return _trapz(jnp.sum(traj.error**2, axis=-1), traj.ts)


def itae(traj) -> jnp.ndarray:
    """Integral of time-weighted absolute error ∫ (t − t0) ‖x̃(t)‖ dt (a smooth norm: √(‖x̃‖² + 1e-24))."""
    nrm = jnp.sqrt(jnp.sum(traj.error**2, axis=-1) + 1e-24)
    return _trapz((traj.ts - traj.ts[0]) * nrm, traj.ts)


def terminal(traj) -> jnp.ndarray:
    """Squared terminal error ‖x̃(t_end)‖²."""
    return jnp.sum(traj.error[-1] ** 2)


def peak(traj, sharpness: float = 50.0) -> jnp.ndarray:
    """Peak error max_t ‖x̃(t)‖, as a smooth maximum (log-sum-exp with the given sharpness, relative to
    the largest value) so that its gradient spreads over near-maximal times."""
    nrm = jnp.sqrt(jnp.sum(traj.error**2, axis=-1) + 1e-24)
    top = jnp.max(nrm)
    scale = sharpness / jnp.maximum(top, 1e-12)
    return top + jnp.log(jnp.mean(jnp.exp(scale * (nrm - top)))) / scale + jnp.log(nrm.shape[0]) / scale


def _valid_mean(values, valid):
    """Mean over the valid rows; NaN when there is none (a mean of nothing is not a zero loss)."""
    w = valid.astype(values.dtype)
    count = jnp.sum(w)
    return jnp.where(count > 0, jnp.sum(w * values) / jnp.maximum(count, 1.0), jnp.nan)


def output_error(est, integral: bool = False, weight=None) -> jnp.ndarray:
    """Output prediction error of an :class:`obsjax.Estimate` on recorded data.

    Default: the mean over the valid samples of ‖y_k − ŷ_k‖², ŷ_k = h(t_k, x̂⁻_k, u_k) the prediction
    before the update at t_k (for a sampled-data filter the one-step prediction error, whose minimisation
    is the prediction-error method of system identification, Ljung, *System Identification: Theory for the
    User*, 2nd ed., Prentice Hall, 1999, §7.2); padding (``est.valid`` False) is ignored, so experiments of
    different lengths batch.  ``integral=True``: ∫ ‖y − ŷ‖² dt by the trapezoid rule over the save grid
    (intervals with both ends valid only).  `weight`: optional (m,) weights w_i of ‖e‖² = Σ w_i e_i² (e.g. 1/σ_i² to put outputs
    in different units on one scale).  An estimate without a valid sample (for the integral: without an interval whose two ends are
    valid) gives NaN, never a zero loss.
    """
    if est.innovation is None:
        raise ValueError(
            "`output_error` needs the predicted output ŷ, but this estimate has none (the observer has no "
            "output model: an adaptive or functional observer); use `state_error` with validation states."
        )
    w_out = 1.0 if weight is None else jnp.asarray(weight)
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


def tail_count(alpha: float, n: int) -> int:
    """k = ⌈(1 − α) n⌉ (at least 1): how many of n equally weighted losses the CVaR at level α averages
    (the worst k).  The product is rounded before the ceiling: 1 − 0.95 is not exact in binary, and
    (1 − 0.95)·20 = 1.0000000000000009 would otherwise average the worst 2 of 20 instead of the worst 1."""
    x = (1.0 - float(alpha)) * int(n)
    return max(1, int(math.ceil(x - 1e-9 * max(1.0, x))))

