"""Measurement noise, a first-class option of :func:`obsjax.simulate`.

Two models, both keyed (reproducible from a PRNG key) and vmappable over keys:

- :class:`WhiteNoise`: y_meas dt = y dt + σ dW.  The joint plant-observer system becomes an SDE

      d(x, z) = f(x, z, y) dt + (0, ∂ż/∂y · diag σ) dW,

  solved with diffrax (a ``ControlTerm`` driven by a ``VirtualBrownianTree``).  The diffusion is the
  Jacobian of the observer's vector field with respect to y, exact for every observer affine in y
  (all linear and least-squares observers); for a nonlinear dependence it is the Itô linearisation.
  The reported ``y`` is the noise-free output (white noise has no pointwise value).
- :class:`BandLimitedNoise`: seeded Gaussian samples of standard deviation σ on a grid of spacing ``dt``,
  linearly interpolated (a zero-order-free, band-limited signal with bandwidth ~ 1/(2 dt)); an ODE, so
  any solver applies.  The reported ``y`` includes the noise.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

from .._checks import concrete_value, real_array, require_finite


def _sigma(sigma):
    """σ: a real scalar or vector of finite, non-negative intensities (checked eagerly when known, else the
    sign with ``eqx.error_if``)."""
    if isinstance(sigma, bool) or getattr(sigma, "dtype", None) == bool or (
        isinstance(sigma, (list, tuple)) and any(isinstance(v, bool) for v in sigma)
    ):
        raise ValueError(f"`sigma` must be a real intensity (a scalar or an (m,) vector), got a boolean {sigma!r}.")
    arr = real_array(sigma, "sigma")
    if arr.ndim > 1:
        raise ValueError(
            f"`sigma` must be a scalar or a vector (m,) (one intensity per output), got shape {tuple(arr.shape)}."
        )
    require_finite(arr, "sigma")
    v = concrete_value(arr)
    if v is not None and np.any(v < 0):
        raise ValueError(f"`sigma` must be ≥ 0, got {v.tolist()}.")
    if v is None:  # traced: checked under jit (a NaN σ is left to the trajectory's status, per member)
        arr = eqx.error_if(arr, jnp.any(arr < 0), "`sigma` must be ≥ 0 (a noise intensity).")
    return arr


class AbstractNoise(eqx.Module):
    pass


class WhiteNoise(AbstractNoise):
    """White measurement noise of intensity σ (per output, or one scalar for all).

    `sigma`: a scalar or an (m,) vector, finite and ≥ 0; :func:`obsjax.simulate` checks its length against
    the plant's m.
    """

    sigma: jax.Array

    def __init__(self, sigma):
        self.sigma = _sigma(sigma)


class BandLimitedNoise(AbstractNoise):
    """Band-limited measurement noise: N(0, σ²) samples every ``dt``, linearly interpolated.

    `sigma`: a scalar or an (m,) vector, finite and ≥ 0; `dt` > 0 finite.

    The path is continuous and piecewise linear: its kinks at the nodes are not breakpoints of the solve,
    so adaptive solves of a noisy trajectory reach about 100·rtol rather than rtol (see
    :mod:`obsjax.noise`).
    """

    sigma: jax.Array
    dt: float = eqx.field(static=True)

    def __init__(self, sigma, dt=0.01):
        self.sigma = _sigma(sigma)
        if isinstance(dt, bool):
            raise ValueError(f"`dt` of BandLimitedNoise must be a real number > 0, got {dt!r}.")
        try:
            dt = float(dt)
        except (TypeError, ValueError):
            raise ValueError(f"`dt` of BandLimitedNoise must be a real number > 0, got {dt!r}.") from None
        if not (dt > 0 and math.isfinite(dt)):
            raise ValueError(f"`dt` of BandLimitedNoise must be finite and > 0, got {dt}.")
        self.dt = dt


class SampledNoise(eqx.Module):
    """A realised band-limited noise path v(t) (internal)."""

    t0: jax.Array
    dt: float = eqx.field(static=True)
    values: jax.Array  # (K, m)

    def __call__(self, t):
        s = (t - self.t0) / self.dt
        k = jnp.clip(jnp.floor(s).astype(jnp.int32), 0, self.values.shape[0] - 2)
        w = jnp.clip(s - k, 0.0, 1.0)
        return (1 - w) * self.values[k] + w * self.values[k + 1]


def realise_band_limited(noise: BandLimitedNoise, key, t0, t1, m: int) -> SampledNoise:
    span = float(t1) - float(t0)
    k = int(math.ceil(span / noise.dt)) + 2
    sigma = jnp.broadcast_to(noise.sigma, (m,))
    vals = sigma * jr.normal(key, (k, m))
    return SampledNoise(jnp.asarray(t0), noise.dt, vals)
