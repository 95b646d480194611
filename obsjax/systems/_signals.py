"""Input signals u(t)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import real_array, require_finite


class Multisine(eqx.Module):
    """u_j(t) = Σ_k a_jk sin(ω_jk t + φ_jk): a sum of sinusoids per input channel.

    A signal with ≥ n distinct frequencies (2n spectral lines) is sufficiently rich for the
    identification of an n-th order plant (thesis ch. 5-6, persistent excitation).
    """

    amplitudes: jax.Array
    frequencies: jax.Array
    phases: jax.Array

    def __call__(self, t):
        return jnp.sum(self.amplitudes * jnp.sin(self.frequencies * t + self.phases), axis=-1)


def multisine(amplitudes, frequencies, phases=None) -> Multisine:
    """A multisine input.

    **Arguments:**

    - `amplitudes`: (k,) for one input, or (p, k) for p inputs with k sinusoids each.
    - `frequencies`: angular frequencies ω (rad/s), same shape as `amplitudes`.
    - `phases`: φ, same shape (zeros when ``None``).

    All three must be real and finite (a ``ValueError`` names the argument otherwise).

    **Returns:** a callable ``u(t)`` of shape (p,) (p = 1 for 1-D amplitudes), vmappable and differentiable.

    **Example:** ``u = obsjax.signals.multisine([1., .5, .2], [.7, 1.9, 3.1])``
    """
    a = require_finite(real_array(amplitudes, "amplitudes"), "amplitudes")
    w = require_finite(real_array(frequencies, "frequencies"), "frequencies")
    if a.ndim == 0:
        a = a.reshape(1)
    if w.ndim == 0:
        w = w.reshape(1)
    if a.shape != w.shape:
        raise ValueError(
            f"`frequencies` must have the shape of `amplitudes` {tuple(a.shape)}, got {tuple(w.shape)}."
        )
    given = tuple(a.shape)  # the shape phases must have (a scalar amplitude counts as (1,))
    if a.ndim == 1:
        a, w = a[None], w[None]
    if a.ndim != 2:
        raise ValueError(f"`amplitudes` must be (k,) or (p, k), got shape {tuple(a.shape)}.")
    if phases is None:
        ph = jnp.zeros_like(a)
    else:
        ph = require_finite(real_array(phases, "phases"), "phases")
        if ph.ndim == 0:
            ph = ph.reshape(1)
        if tuple(ph.shape) != given:  # a transposed (p, k) array has the right size but not the shape
            raise ValueError(
                f"`phases` must have the shape of `amplitudes` {given}, got {tuple(ph.shape)}."
            )
        ph = ph.reshape(a.shape)
    return Multisine(a, w, ph)


class Constant(eqx.Module):
    """u(t) = value (a step applied at t0)."""

    value: jax.Array

    def __call__(self, t):
        return self.value


def constant(value) -> Constant:
    """A constant input of shape (p,)."""
    return Constant(jnp.atleast_1d(require_finite(real_array(value, "value"), "value")))
