"""Time-varying Kalman-Bucy filter: the Riccati baseline of Chen & Yen's Remark 1."""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import concrete_value, matrix, real_array
from .._linalg import spd_solve
from ._base import AbstractObserver, feedthrough
from ._least_squares import _check_model
from ._validation import check_covariance_value, is_concrete, require_finite, traced_spd


class KalmanBucyState(NamedTuple):
    """State of :class:`KalmanBucy`: the estimate `xhat` (n,) and the error covariance `P` (n, n)."""

    xhat: jax.Array
    P: jax.Array


def _spd(x, name, size, *, semi=False):
    arr = require_finite(matrix(real_array(x, name), name, (size, size)), name)
    v = concrete_value(arr)
    if v is not None:
        check_covariance_value(v, name, semi=semi)
    return arr


class KalmanBucy(AbstractObserver):
    r"""Time-varying Kalman-Bucy filter (Kalman & Bucy 1961; Chen & Yen's ref. [1] and Remark 1).

    For the model ẋ = A(t)x + B(t)u + w, y = C(t)x + v with E[w wᵀ] = Qw δ, E[v vᵀ] = Rv δ:

        dx̂/dt = A x̂ + B u + L (y - C x̂ - D u),      L(t) = P Cᵀ Rv⁻¹,     (D: an LTI model's feedthrough)
        dP/dt = A P + P Aᵀ + Qw - P Cᵀ Rv⁻¹ C P,      P(t0) = P0   (differential Riccati equation).

    Unlike :class:`obsjax.LeastSquaresReset` the link between (Qw, Rv) and the decay rate of x̃ is not
    explicit in the time-varying case (the point of Chen & Yen's Remark 1).  The right-hand side of the
    Riccati equation is symmetrised at each evaluation so P stays symmetric to round-off; it stays
    positive definite because P0 > 0 and the equation preserves definiteness (Qw ⪰ 0).  The state has
    n + n² components against n + 2n² for the least-squares observer.

    **Arguments:**

    - `model`: an :class:`obsjax.LTV` or :class:`obsjax.LTI` model (A(t), B(t), C(t) read from it).
    - `Qw`: (n, n) process-noise intensity, symmetric positive semidefinite (differentiable leaf).
    - `Rv`: (m, m) measurement-noise intensity, symmetric positive definite (differentiable leaf).
    - `P0`: (n, n) initial covariance, symmetric positive definite (differentiable leaf).

    **Example:**

        plant = obsjax.chen_yen_example()
        kb = obsjax.KalmanBucy(plant, Qw=0.1 * jnp.eye(2), Rv=jnp.eye(1) * 1e-2, P0=jnp.eye(2))
    """

    model: eqx.Module
    Qw: jax.Array
    Rv: jax.Array
    P0: jax.Array

    def __init__(self, model, Qw, Rv, P0):
        _check_model(model)
        n, m = model.n, model.m
        self.model = model
        self.Qw = _spd(Qw, "Qw", n, semi=True)
        self.Rv = _spd(Rv, "Rv", m)
        self.P0 = _spd(P0, "P0", n)

    def check(self) -> KalmanBucy:
        """Qw finite symmetric PSD, Rv and P0 finite symmetric positive definite: ``ValueError`` for
        concrete values, ``eqx.error_if`` (survives jit) for traced ones."""
        n, m = self.model.n, self.model.m
        if is_concrete(self.Qw, self.Rv, self.P0):
            _spd(self.Qw, "Qw", n, semi=True)
            _spd(self.Rv, "Rv", m)
            _spd(self.P0, "P0", n)
            return self
        who = "KalmanBucy's"
        Qw = traced_spd(self.Qw, "Qw", semi=True, what=f" ({who} process-noise intensity)")
        Rv = traced_spd(self.Rv, "Rv", semi=False, what=f" ({who} measurement-noise intensity)")
        P0 = traced_spd(self.P0, "P0", semi=False, what=f" ({who} initial covariance)")
        return eqx.tree_at(lambda o: (o.Qw, o.Rv, o.P0), self, (Qw, Rv, P0))

    def prepare(self) -> KalmanBucy:
        return self.check()

    def init(self, t0, xhat0, y0):
        # symmetrised: the derivative in P0 is then that over symmetric matrices (P enters the gain as
        # C P, so the raw cotangent of P0 had an antisymmetric part and one tuning step broke symmetry)
        return KalmanBucyState(jnp.asarray(xhat0), 0.5 * (self.P0 + self.P0.T))

    def gain(self, t, z):
        """Kalman gain L(t) = P Cᵀ Rv⁻¹, shape (n, m)."""
        C = self.model.C_of(t)
        return spd_solve(0.5 * (self.Rv + self.Rv.T), C @ z.P).T

    def vector_field(self, t, z, y, u):
        A, C = self.model.A_of(t), self.model.C_of(t)
        L = self.gain(t, z)
        dxhat = A @ z.xhat + L @ (y - C @ z.xhat - feedthrough(self.model, u))
        if u is not None and self.model.p > 0:
            dxhat = dxhat + self.model.B_of(t) @ u
        dP = A @ z.P + z.P @ A.T + self.Qw - L @ (C @ z.P)
        return KalmanBucyState(dxhat, 0.5 * (dP + dP.T))

    def estimate(self, t, z, y):
        return z.xhat
