"""Kudva–Narendra identification with all states accessible, and the error models 1 and 2
(Hassan thesis, section 4.3-4.4)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value, matrix
from ._adaptive_common import check_gain, gain_array, lyapunov, solve_gain, traced_positive, state_dimension
from ._base import AbstractObserver
from ._validation import require_finite, spd_violation, traced_finite


def _stable_matrix(K, name, n):
    K = require_finite(matrix(K, name, (n, n)), name)
    v = concrete_value(K)
    if v is not None:
        ev = np.linalg.eigvals(v)
        if not np.all(ev.real < 0):
            raise ValueError(
                f"`{name}` must be a stable (Hurwitz) matrix, got eigenvalues {ev.tolist()}."
            )
    return K


def _spd(Q, name, n):
    Q = matrix(Q, name, (n, n))
    check_gain(Q, name)
    return Q


class KudvaNarendraState(eqx.Module):
    """State of :class:`KudvaNarendra`: model state x_m and the adjustable A_m, B_m of (4.4)."""

    xm: jax.Array  # (n,)
    Am: jax.Array  # (n, n)
    Bm: jax.Array  # (n, m)


class KudvaNarendra(AbstractObserver):
    r"""Kudva–Narendra identifier of a MIMO plant with all states accessible (thesis section 4.3).

    Plant (4.3): ẋ_p = A_p x_p + B_p u with A_p (n×n), B_p (n×m) unknown and y = x_p measured.
    Implemented equations:

    - model (4.4): ẋ_m = K x_m + (A_m − K) x_p + B_m u, K stable;
    - laws (4.6)-(4.7): Ȧ_m = −Γ₁⁻¹ P e x_pᵀ, Ḃ_m = −Γ₂⁻¹ P e uᵀ, e = x_m − x_p, with P the solution of
      Kᵀ P + P K = −Q.

    The state error obeys (4.5) ė = K e + φ x_p + ψ u (φ = A_m − A_p, ψ = B_m − B_p), which is error model 1
    (4.8) with θᵀ = [φ, ψ], V = [x_p; u]; with V = ½[eᵀPe + tr(φᵀΓ₁φ + ψᵀΓ₂ψ)] the laws give
    V̇ = −½ eᵀ Q e ≤ 0 (the text writes −eᵀQe, i.e. without the ½ of its own V).

    **Units.**  The law Ȧ_m = −Γ₁⁻¹ P e x_pᵀ weighs the columns of A_m by x_p, with no weight of its own
    on them: the observer is the same under a change of units only when every state shares one scale
    (x' = s x, with K unchanged and Γ₁, Γ₂, Q scaled consistently).  With states in units spread over
    1e-4 … 1e4 no choice of Γ₁ reproduces it, and the adaptation becomes stiff (a simulation ran into
    max_steps, status 1): give the states comparable units.

    **Arguments:**

    - `n`: number of states (all measured).
    - `m`: number of inputs (the thesis's r; the plant's ``p``).
    - `K`: (n, n) stable model matrix.
    - `Gamma1`: (n, n) s.p.d. (or scalar / (n,) diagonal) weight of φ; the rate of A_m is Γ₁⁻¹.
    - `Gamma2`: the same for ψ; the rate of B_m is Γ₂⁻¹.
    - `Q`: (n, n) s.p.d. matrix of the Lyapunov equation.
    - `A0`, `B0`: initial A_m, B_m (default zeros).

    All of K, Gamma1, Gamma2, Q are differentiable leaves.  ``parameters(z)`` returns (A_m, B_m).

    **Example:**::

        obs = obsjax.KudvaNarendra(2, 1, K=-2 * jnp.eye(2), Gamma1=0.2, Gamma2=0.2, Q=jnp.eye(2))
        plant = obsjax.LTI(Ap, Bp, jnp.eye(2))         # all states measured
        traj = obsjax.simulate(plant, obs, x0, x0, ts, u=u)
    """

    K: jax.Array
    Gamma1: jax.Array
    Gamma2: jax.Array
    Q: jax.Array
    A0: jax.Array
    B0: jax.Array
    n: int = eqx.field(static=True)
    m: int = eqx.field(static=True)

    def __init__(self, n, m, K, Gamma1, Gamma2, Q, *, A0=None, B0=None):
        n, m = state_dimension(n), state_dimension(m, "m", minimum=0)
        if n < 1 or m < 0:
            raise ValueError(f"`n` must be >= 1 and `m` >= 0, got n={n}, m={m}.")
        self.n, self.m = n, m
        self.K = _stable_matrix(K, "K", n)
        self.Gamma1 = gain_array(Gamma1, "Gamma1", n)
        self.Gamma2 = gain_array(Gamma2, "Gamma2", n)
        self.Q = _spd(Q, "Q", n)
        A0 = jnp.zeros((n, n)) if A0 is None else matrix(A0, "A0", (n, n))
        B0 = jnp.zeros((n, m)) if B0 is None else matrix(B0, "B0", (n, m))
        self.A0, self.B0 = require_finite(A0, "A0"), require_finite(B0, "B0")

    def prepare(self):
        """Guards that survive ``jit`` (``eqx.error_if``): Γ₁, Γ₂, Q positive (definite), K
        Hurwitz, all finite."""
        # K is Hurwitz iff the solution P of KᵀP + PK = −Q (Q > 0) is positive definite (GPU-friendly test).
        K = traced_finite(self.K, "K")
        P = lyapunov(K, self.Q)
        K = eqx.error_if(K, spd_violation(P, semi=False), "`K` must be stable (Hurwitz).")  # equilibrated
        return eqx.tree_at(
            lambda o: (o.K, o.Gamma1, o.Gamma2, o.Q),
            self,
            (
                K,
                traced_finite(traced_positive(self.Gamma1, "Gamma1"), "Gamma1"),
                traced_finite(traced_positive(self.Gamma2, "Gamma2"), "Gamma2"),
                traced_finite(traced_positive(self.Q, "Q"), "Q"),
            ),
        )

    def check(self):
        _stable_matrix(self.K, "K", self.n)
        check_gain(self.Gamma1, "Gamma1")
        check_gain(self.Gamma2, "Gamma2")
        check_gain(self.Q, "Q")
        return self

    @property
    def P(self):
        """P with Kᵀ P + P K = −Q."""
        return lyapunov(self.K, self.Q)

    def init(self, t0, xhat0, y0):
        xhat0 = jnp.asarray(xhat0, dtype=float)
        if xhat0.shape != (self.n,):
            raise ValueError(f"`xhat0` must have shape ({self.n},), got {tuple(xhat0.shape)}.")
        return KudvaNarendraState(xhat0, self.A0, self.B0)

    def vector_field(self, t, z: KudvaNarendraState, y, u):
        xp = jnp.asarray(y).reshape(self.n)
        u = jnp.asarray(u).reshape(self.m)
        e = z.xm - xp
        Pe = self.P @ e
        dxm = self.K @ z.xm + (z.Am - self.K) @ xp + z.Bm @ u  # (4.4)
        dAm = -solve_gain(self.Gamma1, jnp.outer(Pe, xp))  # (4.6)
        dBm = -solve_gain(self.Gamma2, jnp.outer(Pe, u))  # (4.7)
        return KudvaNarendraState(dxm, dAm, dBm)

    def estimate(self, t, z: KudvaNarendraState, y):
        return z.xm

    def parameters(self, z: KudvaNarendraState):
        """Current (A_m, B_m), the estimates of (A_p, B_p)."""
        return z.Am, z.Bm

    def lyapunov(self, z: KudvaNarendraState, xp, Ap, Bp):
        """V = ½[eᵀPe + tr(φᵀΓ₁φ + ψᵀΓ₂ψ)] of section 4.3 (vectorised over a leading time axis)."""
        e = z.xm - xp
        phi = z.Am - Ap
        psi = z.Bm - Bp
        P = self.P
        quad = jnp.einsum("...i,ij,...j->...", e, P, e)
        t1 = jnp.sum(phi * _left(self.Gamma1, phi), axis=(-2, -1))
        t2 = jnp.sum(psi * _left(self.Gamma2, psi), axis=(-2, -1))
        return 0.5 * (quad + t1 + t2)


def _left(Gamma, X):
    """Γ X for a batch of matrices X (..., n, k)."""
    Gamma = jnp.asarray(Gamma)
    if Gamma.ndim == 0:
        return Gamma * X
    if Gamma.ndim == 1:
        return Gamma[:, None] * X
    return jnp.einsum("ij,...jk->...ik", Gamma, X)


class ErrorModel1(eqx.Module):
    r"""Error model 1 (4.8)-(4.9): all error states accessible.

        ė = K e + θᵀ V(t),   θ̇ᵀ = −Γ⁻¹ P e Vᵀ,   Kᵀ P + P K = −Q,

    e ∈ Rⁿ, θᵀ (n×s), V(t) ∈ Rˢ.  With W = ½[eᵀPe + tr(θΓθᵀ)], Ẇ = −½ eᵀQe.  ``vector_field(t, (e, θᵀ), V)``.

    **Arguments:** `K` (n, n) stable, `Gamma` (scalar / (n,) / (n, n) s.p.d.), `Q` (n, n) s.p.d.
    """

    K: jax.Array
    Gamma: jax.Array
    Q: jax.Array

    def __init__(self, K, Gamma, Q):
        K = matrix(K, "K", (None, None))
        n = K.shape[0]
        self.K = _stable_matrix(K, "K", n)
        self.Gamma = gain_array(Gamma, "Gamma", n)
        self.Q = _spd(Q, "Q", n)

    def vector_field(self, t, state, V):
        e, thetaT = state
        P = lyapunov(self.K, self.Q)
        de = self.K @ e + thetaT @ V  # (4.8)
        dthetaT = -solve_gain(self.Gamma, jnp.outer(P @ e, V))  # (4.9)
        return de, dthetaT

    def lyapunov(self, state):
        e, thetaT = state
        P = lyapunov(self.K, self.Q)
        return 0.5 * (
            jnp.einsum("...i,ij,...j->...", e, P, e)
            + jnp.sum(thetaT * _left(self.Gamma, thetaT), axis=(-2, -1))
        )


class ErrorModel2(eqx.Module):
    r"""Error model 2 (4.10)-(4.11): only the output η of the error is accessible.

        ε̇ = K ε + D θᵀ V(t),   η = H ε,   θ̇ᵀ = −Γ⁻¹ η Vᵀ.

    The law is stable when H = Dᵀ P with Kᵀ P + P K = −Q (H(sI − K)⁻¹D strictly positive real): then
    W = ½[εᵀPε + tr(θΓθᵀ)] has Ẇ = −½ εᵀQε.  ``H=None`` builds H = Dᵀ P; a given H is checked against it.

    **Arguments:** `K` (n, n) stable, `D` (n, k), `Gamma` (scalar / (k,) / (k, k) s.p.d.), `Q` (n, n) s.p.d.,
    `H` (k, n) or ``None``.
    """

    K: jax.Array
    D: jax.Array
    H: jax.Array
    Gamma: jax.Array
    Q: jax.Array

    def __init__(self, K, D, Gamma, Q, H=None):
        K = matrix(K, "K", (None, None))
        n = K.shape[0]
        self.K = _stable_matrix(K, "K", n)
        self.D = matrix(D, "D", (n, None))
        k = self.D.shape[1]
        self.Gamma = gain_array(Gamma, "Gamma", k)
        self.Q = _spd(Q, "Q", n)
        P = lyapunov(self.K, self.Q)
        if H is None:
            self.H = self.D.T @ P
        else:
            H = matrix(H, "H", (k, n))
            hv, pv = concrete_value(H), concrete_value(self.D.T @ P)
            if hv is not None and pv is not None and not np.allclose(hv, pv, rtol=1e-8, atol=1e-10):
                raise ValueError(
                    "`H` must equal Dᵀ P (P solving Kᵀ P + P K = −Q) for the law (4.11) to be stable "
                    f"(H(sI − K)⁻¹D strictly positive real); expected {pv.tolist()}, got {hv.tolist()}."
                )
            self.H = H

    def vector_field(self, t, state, V):
        eps, thetaT = state
        eta = self.H @ eps
        de = self.K @ eps + self.D @ (thetaT @ V)  # (4.10)
        dthetaT = -solve_gain(self.Gamma, jnp.outer(eta, V))  # (4.11)
        return de, dthetaT

    def lyapunov(self, state):
        eps, thetaT = state
        P = lyapunov(self.K, self.Q)
        return 0.5 * (
            jnp.einsum("...i,ij,...j->...", eps, P, eps)
            + jnp.sum(thetaT * _left(self.Gamma, thetaT), axis=(-2, -1))
        )
