"""Losses on a simulated trajectory (each returns a scalar; :func:`obsjax.tune` averages over a batch)."""

from __future__ import annotations

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
