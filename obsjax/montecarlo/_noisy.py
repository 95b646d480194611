"""Band-limited measurement noise folded into the plant's output map (a realised path per trajectory).

``NoisyOutput(plant, path)`` is the plant with y = h(t, x, u) + v(t) for a realised noise path v, exactly what
:func:`obsjax.simulate` does with ``noise=BandLimitedNoise`` (``realise_band_limited`` draws the same path from
the same key), but with the path realised beforehand as array leaves.  A batch of such plants is one pytree
with a batch axis, so scenario sets that combine model uncertainty with given noise realisations can be tuned
with ``tune(..., plant_batched=True)`` (:func:`noisy_batch`), and the same realisations can be reused across
studies and tuning runs."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

from .._checks import device_array, static_value
from ..systems._noise import BandLimitedNoise, SampledNoise, realise_band_limited
from ..systems._plants import AbstractSystem


class NoisyOutput(AbstractSystem):
    """The plant ``plant`` measured through additive noise: y = h(t, x, u) + v(t).

    The path is piecewise linear with kinks every ``dt``: an adaptive solver spends many (rejected) steps
    on them (44 against 380 trajectories/s on Chen & Yen's example with dt = 0.05, declaring the kinks as
    jump times does not help), so noisy studies are best run with fixed steps aligned with the noise grid
    (``simulate_kwargs=dict(adaptive=False, dt0=dt/4)``: 2100 trajectories/s on the same problem).

    The wrapped plant is stored split into its array leaves and its static rest (callables of an LTV
    plant), so that a batch of these plants vmaps over arrays only.

    **Arguments:** `plant` (any obsjax plant); `path` (a realised noise path, callable t -> (m,)).
    """

    plant_arrays: object
    path: SampledNoise
    plant_static: object = eqx.field(static=True)

    def __init__(self, plant, path):
        if not isinstance(plant, AbstractSystem):
            raise ValueError(f"`plant` must be an obsjax plant, got {type(plant).__name__}.")
        self.plant_arrays, self.plant_static = eqx.partition(plant, eqx.is_array)
        self.path = path

    @property
    def plant(self) -> AbstractSystem:
        return eqx.combine(self.plant_arrays, self.plant_static)

    @property
    def n(self) -> int:
        return self.plant.n

    @property
    def m(self) -> int:
        return self.plant.m

    @property
    def p(self) -> int:
        return self.plant.p

    @property
    def jump_ts(self):
        return getattr(self.plant_static, "jump_ts", None)

    def f(self, t, x, u):
        return self.plant.f(t, x, u)

    def h(self, t, x, u):
        return self.plant.h(t, x, u) + self.path(t)


def with_noise(plant, noise, key, t0, t1) -> NoisyOutput:
    """One realisation (the path ``simulate(..., noise=noise, key=key)`` would draw on [t0, t1])."""
    if not isinstance(noise, BandLimitedNoise):
        raise ValueError(f"`noise` must be a BandLimitedNoise here, got {type(noise).__name__}.")
    return NoisyOutput(plant, realise_band_limited(noise, key, float(t0), float(t1), plant.m))


@eqx.filter_jit
def _standard_normals(key, batch, k, m):
    """``jr.normal(jr.split(key, batch)[b], (k, m))`` for b = 0 … batch − 1, stacked: one compiled
    program (drawn one by one, each eager JAX operation compiled a program of its own)."""
    return jax.vmap(lambda kk: jr.normal(kk, (k, m)))(jr.split(key, batch))


def _draw_paths(noise, key, batch, t0, t1, m) -> SampledNoise:
    """The paths ``realise_band_limited(noise, jr.split(key, batch)[b], t0, t1, m)``, stacked, bit for
    bit: the same standard normals, times σ on the host where σ and the draws are constants (one
    rounding, as JAX's); by JAX where either is traced (a traced key under ``jit``/``vmap``, σ being
    differentiated, even eagerly: its derivative is kept)."""
    k = int(math.ceil((float(t1) - float(t0)) / noise.dt)) + 2
    z = _standard_normals(key, batch, k, m)
    sigma = static_value(noise.sigma)
    if sigma is None or isinstance(z, jax.core.Tracer):
        values = jnp.broadcast_to(noise.sigma, (m,)) * z
    else:
        values = device_array(np.broadcast_to(sigma, (m,)) * np.asarray(z))
    t0s = device_array(np.full((batch,), float(t0)))
    return SampledNoise(t0s, noise.dt, values)


def noisy_batch(plant, noise, key, batch, t0, t1):
    """A batch of ``batch`` noisy plants (leading axis on every array leaf) for ``tune(plant_batched=True)``.

    The plant's own array leaves are broadcast along the batch; noise path b is drawn from
    ``jr.split(key, batch)[b]``.
    """
    if not isinstance(noise, BandLimitedNoise):
        raise ValueError(f"`noise` must be a BandLimitedNoise here, got {type(noise).__name__}.")
    if isinstance(batch, bool) or not isinstance(batch, (int, np.integer)) or batch < 1:
        raise ValueError(f"`batch` (the number of noisy plants) must be a positive integer, got {batch!r}.")
    a, b = float(t0), float(t1)
    if not (np.isfinite(a) and np.isfinite(b) and a < b):
        raise ValueError(f"`t0`, `t1` must be finite with t0 < t1, got t0 = {a}, t1 = {b}.")
    stacked = _draw_paths(noise, key, int(batch), a, b, plant.m)
    out = NoisyOutput(plant, stacked)
    arrays = jax.tree_util.tree_map(
        lambda a: jnp.broadcast_to(a, (batch,) + jnp.shape(a)), out.plant_arrays
    )
    return eqx.tree_at(lambda o: o.plant_arrays, out, arrays, is_leaf=lambda x: x is None)
