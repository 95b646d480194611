"""Continuous–discrete Kalman filter: a continuous-time model, measurements at instants."""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value
from .._linalg import spd_solve
from ._base import AbstractObserver, feedthrough
from ._kalman_bucy import _spd
from ._least_squares import _check_model
from .._integrate import _schedule
from ._validation import is_concrete, traced_spd


class ContinuousDiscreteKalmanState(NamedTuple):
    """State of :class:`ContinuousDiscreteKalman`: the mean `xhat` (n,) and the covariance `P` (n, n)."""

    xhat: jax.Array
    P: jax.Array


def _times(times):
    if times is None:
        return None
    v = np.asarray(times, dtype=float).reshape(-1)
    if v.size == 0 or not np.all(np.isfinite(v)) or np.any(np.diff(v) <= 0):
        raise ValueError(f"`times` (the sampling instants) must be finite and strictly increasing, got {v.tolist()}.")
    return tuple(float(t) for t in v)


def _period(period):
    if period is None:
        return None
    v = concrete_value(period)
    if v is None or np.ndim(v) != 0:
        raise ValueError(f"`period` must be a concrete scalar (it sets the number of updates), got {period!r}.")
    v = float(v)
    if not (v > 0 and math.isfinite(v)):
        raise ValueError(f"`period` (the sampling interval) must be finite and > 0, got {v}.")
    return v


class ContinuousDiscreteKalman(AbstractObserver):
    r"""Continuous–discrete Kalman filter (Jazwinski, *Stochastic Processes and Filtering Theory*,
    Academic Press, 1970, ch. 7; the update in Joseph's stabilised form, Bucy & Joseph, *Filtering for
    Stochastic Processes with Applications to Guidance*, Interscience, 1968).

    For the model ẋ = A(t)x + B(t)u + w, E[w(t) w(s)ᵀ] = Qw δ(t − s) (continuous white noise), measured
    at instants t_k as y_k = C x(t_k) + D u_k + v_k, E[v_k v_kᵀ] = Rv (a discrete covariance, per sample):

        between samples:   dx̂/dt = A x̂ + B u,      dP/dt = A P + P Aᵀ + Qw,
        at each sample:    S = C P⁻ Cᵀ + Rv,   K = P⁻ Cᵀ S⁻¹,
                           x̂⁺ = x̂⁻ + K (y_k − C x̂⁻ − D u_k),
                           P⁺ = (I − K C) P⁻ (I − K C)ᵀ + K Rv Kᵀ.

    With a zero-order-hold input and an exact propagation this is the discrete Kalman filter of the exactly
    discretised model, x_{k+1} = e^{Ah} x_k + ∫₀ʰ e^{Aτ} dτ B u_k + w_k with
    Cov w_k = ∫₀ʰ e^{Aτ} Qw e^{Aᵀτ} dτ (tests check it against that filter, discretised by the matrix
    exponential, to 1e-8).  The first update is at the first sample (x̂0, P0 is the prior at t0).

    In :func:`obsjax.estimate` the updates happen at the data's samples; in :func:`obsjax.simulate` every
    `period` from t0 (the plant sampled at 1/`period`) or at the given `times` (the reset mechanism's period T
    generalised to given event times), so `period` or `times` is needed there only.

    **Arguments:**

    - `model`: an :class:`obsjax.LTI` or :class:`obsjax.LTV` model (A(t), B(t), C(t), and D for an LTI).
    - `Qw`: (n, n) process-noise intensity, symmetric positive semidefinite (differentiable leaf).
    - `Rv`: (m, m) measurement-noise covariance per sample, symmetric positive definite (differentiable).
    - `P0`: (n, n) prior covariance at t0, symmetric positive definite (differentiable leaf).
    - `period`: sampling interval h > 0 for :func:`obsjax.simulate` (a concrete float: it sets the number of
      updates), or ``None``.
    - `times`: or the sampling instants themselves (irregular sampling in :func:`obsjax.simulate`), a
      strictly increasing sequence of floats; those outside the horizon are ignored.

    **Example:**::

        kf = obsjax.observers.ContinuousDiscreteKalman(model, Qw=1e-2 * jnp.eye(3), Rv=1e-4 * jnp.eye(1),
                                                       P0=jnp.eye(3), period=0.01)
        traj = obsjax.simulate(plant, kf, x0, xhat0, ts)      # sampled every 10 ms
        est = obsjax.estimate(kf, data, xhat0)                # updated at the recorded samples
    """

    model: eqx.Module
    Qw: jax.Array
    Rv: jax.Array
    P0: jax.Array
    period: float | None = eqx.field(static=True, default=None)
    times: tuple[float, ...] | None = eqx.field(static=True, default=None)

    def __init__(self, model, Qw, Rv, P0, period=None, times=None):
        _check_model(model)
        n, m = model.n, model.m
        self.model = model
        self.Qw = _spd(Qw, "Qw", n, semi=True)
        self.Rv = _spd(Rv, "Rv", m)
        self.P0 = _spd(P0, "P0", n)
        self.period = _period(period)
        self.times = _times(times)
        if period is not None and times is not None:
            raise ValueError("give `period` (regular sampling) or `times` (given instants), not both.")

    def check(self) -> ContinuousDiscreteKalman:
        """Qw finite symmetric PSD, Rv and P0 finite symmetric positive definite: ``ValueError`` for
        concrete values, ``eqx.error_if`` (survives jit) for traced ones."""
        n, m = self.model.n, self.model.m
        if is_concrete(self.Qw, self.Rv, self.P0):
            _spd(self.Qw, "Qw", n, semi=True)
            _spd(self.Rv, "Rv", m)
            _spd(self.P0, "P0", n)
            return self
        who = " (ContinuousDiscreteKalman's"
        Qw = traced_spd(self.Qw, "Qw", semi=True, what=f"{who} process-noise intensity)")
        Rv = traced_spd(self.Rv, "Rv", semi=False, what=f"{who} measurement-noise covariance)")
        P0 = traced_spd(self.P0, "P0", semi=False, what=f"{who} prior covariance)")
        return eqx.tree_at(lambda o: (o.Qw, o.Rv, o.P0), self, (Qw, Rv, P0))

    def prepare(self) -> ContinuousDiscreteKalman:
        return self.check()

    def init(self, t0, xhat0, y0):
        # symmetrised, so that the derivative in P0 is symmetric (as KalmanBucy.init)
        return ContinuousDiscreteKalmanState(jnp.asarray(xhat0), 0.5 * (self.P0 + self.P0.T))

    def vector_field(self, t, z, y, u):
        A = self.model.A_of(t)
        dx = A @ z.xhat
        if u is not None and self.model.p > 0:
            dx = dx + self.model.B_of(t) @ u
        dP = A @ z.P + z.P @ A.T + self.Qw
        return ContinuousDiscreteKalmanState(dx, 0.5 * (dP + dP.T))

    def gain(self, t, z):
        """Kalman gain K = P⁻ Cᵀ (C P⁻ Cᵀ + Rv)⁻¹ at a sample, shape (n, m)."""
        C = self.model.C_of(t)
        S = C @ z.P @ C.T + self.Rv
        return spd_solve(0.5 * (S + S.T), C @ z.P).T

    def update(self, t, z, y, u):
        """The measurement update at a sample (Joseph form of the covariance)."""
        C = self.model.C_of(t)
        K = self.gain(t, z)
        xhat = z.xhat + K @ (y - C @ z.xhat - feedthrough(self.model, u))
        IKC = jnp.eye(z.P.shape[0], dtype=z.P.dtype) - K @ C
        P = IKC @ z.P @ IKC.T + K @ self.Rv @ K.T
        return ContinuousDiscreteKalmanState(xhat, 0.5 * (P + P.T))

    def event_times(self, t0, t1):
        """The sampling instants t0 + k·period in [t0, t1], or the given `times` (for :func:`obsjax.simulate`)."""
        if self.times is not None:
            return np.asarray(self.times)
        if self.period is None:
            raise ValueError(
                "ContinuousDiscreteKalman needs `period` (the sampling interval) or `times` to run in obsjax.simulate; "
                "obsjax.estimate updates it at the recorded samples instead."
            )
        a, b = concrete_value(t0), concrete_value(t1)
        if a is None or b is None:
            raise ValueError(
                "ContinuousDiscreteKalman in obsjax.simulate needs concrete save times (the number of samples "
                "is fixed before tracing): close over `ts` instead of passing it traced."
            )
        a, b = float(a), float(b)
        # the schedule's own time tolerance (1e-9 of the horizon plus the rounding of the clock times):
        # with t0 a clock time (1.7e9 s), (t1 − t0)/period read 2.9999995 and the sample at t1 was lost
        tol = min(_schedule.tolerance(b - a, max(abs(a), abs(b))), 0.5 * self.period)  # < period: no repeat
        count = int(math.floor((b - a + tol) / self.period)) + 1
        return np.minimum(a + self.period * np.arange(count), b)  # the last one within tol of t1: at t1

    def estimate(self, t, z, y):
        return z.xhat
