"""Continuous-time extended Kalman–Bucy filter (the baseline the TLO is compared with, Huang & Zhu §I)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import concrete_value, real_array, vector
from .._linalg import spd_solve
from ..systems._plants import AbstractSystem
from ._base import AbstractObserver
from ._validation import check_covariance_value, is_concrete, require_finite, traced_spd


def _covariance(x, name: str, size: int, *, definite: bool) -> jax.Array:
    """A scalar (× I), a vector (diagonal) or a symmetric (size, size) matrix, PSD (or PD if `definite`)."""
    a = real_array(x, name)
    if a.ndim == 0:
        a = a * jnp.eye(size)
    elif a.ndim == 1:
        if a.shape[0] != size:
            raise ValueError(f"`{name}` as a diagonal must have length {size}, got {a.shape[0]}.")
        a = jnp.diag(a)
    if a.shape != (size, size):
        raise ValueError(
            f"`{name}` must be a scalar, a length-{size} diagonal or a ({size}, {size}) matrix, got shape {tuple(a.shape)}."
        )
    require_finite(a, name)
    v = concrete_value(a)
    if v is not None:
        check_covariance_value(v, name, semi=not definite)
    return a


class ExtendedKalman(AbstractObserver):
    """Continuous-time extended Kalman–Bucy filter.

        x̂˙ = f(t, x̂, u) + P Hᵀ R⁻¹ (y − h(t, x̂, u)),
        Ṗ  = F P + P Fᵀ + Q − P Hᵀ R⁻¹ H P,      F = ∂f/∂x (t, x̂, u),  H = ∂h/∂x (t, x̂, u),

    with Jacobians by ``jax.jacfwd`` (the EKF the TLO paper compares with, its refs. [6], [7], [9]).  For a
    linear model this is the Kalman–Bucy filter and P(t) tends to the solution of the filter Riccati
    equation.  The observer state is (x̂, P).

    **Arguments:**

    - `model`: the filter's model of the plant (:class:`obsjax.Nonlinear`, or any obsjax plant).
    - `Q`: process-noise intensity, (n, n) symmetric PSD (a scalar means q·I, a vector a diagonal).
    - `R`: measurement-noise intensity, (m, m) symmetric positive definite (same conventions).
    - `P0`: initial covariance, (n, n) symmetric PSD (same conventions).

    **Example:**

        ekf = obsjax.ExtendedKalman(model, Q=0.1, R=0.01, P0=1.0)
        traj = obsjax.simulate(plant, ekf, x0, xhat0, ts)
    """

    model: AbstractSystem
    Q: jax.Array
    R: jax.Array
    P0: jax.Array

    def __init__(self, model, Q, R, P0):
        if not isinstance(model, AbstractSystem):
            raise ValueError(f"`model` must be an obsjax plant, got {type(model).__name__}.")
        self.model = model
        self.Q = _covariance(Q, "Q", model.n, definite=False)
        self.R = _covariance(R, "R", model.m, definite=True)
        self.P0 = _covariance(P0, "P0", model.n, definite=False)

    def check(self) -> ExtendedKalman:
        """Q and P0 finite symmetric PSD, R finite symmetric positive definite: ``ValueError`` for
        concrete values, ``eqx.error_if`` (survives jit) for traced ones."""
        if is_concrete(self.Q, self.R, self.P0):
            _covariance(self.Q, "Q", self.model.n, definite=False)
            _covariance(self.R, "R", self.model.m, definite=True)
            _covariance(self.P0, "P0", self.model.n, definite=False)
            return self
        who = "ExtendedKalman's"
        Q = traced_spd(self.Q, "Q", semi=True, what=f" ({who} process-noise intensity)")
        R = traced_spd(self.R, "R", semi=False, what=f" ({who} measurement-noise intensity)")
        P0 = traced_spd(self.P0, "P0", semi=True, what=f" ({who} initial covariance)")
        return eqx.tree_at(lambda o: (o.Q, o.R, o.P0), self, (Q, R, P0))

    def prepare(self) -> ExtendedKalman:
        return self.check()

    def init(self, t0, xhat0, y0):
        # symmetrised, so that the derivative in P0 is symmetric (as KalmanBucy.init)
        return (vector(xhat0, "xhat0", self.model.n), 0.5 * (self.P0 + self.P0.T))

    def gain(self, t, z, u):
        """The Kalman gain P Hᵀ R⁻¹, shape (n, m)."""
        xh, P = z
        H = jax.jacfwd(self.model.h, argnums=1)(t, xh, u)
        return spd_solve(0.5 * (self.R + self.R.T), H @ P).T

    def vector_field(self, t, z, y, u):
        xh, P = z
        f, h = self.model.f, self.model.h
        F = jax.jacfwd(f, argnums=1)(t, xh, u)
        H = jax.jacfwd(h, argnums=1)(t, xh, u)
        RinvHP = spd_solve(0.5 * (self.R + self.R.T), H @ P)  # R⁻¹ H P, (m, n)
        dx = f(t, xh, u) + RinvHP.T @ (y - h(t, xh, u))
        dP = F @ P + P @ F.T + self.Q - (H @ P).T @ RinvHP
        return dx, 0.5 * (dP + dP.T)

    def estimate(self, t, z, y):
        return z[0]
