"""The minimal adaptive observer of Carroll–Lindorff and Kudva–Narendra (Hassan thesis, section 4.5.1)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array, concrete_value, positive, require_finite, vector
from ._adaptive_common import (
    state_dimension,
    siso_signal,
    adapt_mask,
    auxiliary_matrices,
    check_gain,
    check_stable_roots,
    filter_regressor,
    filter_step,
    gain_array,
    masked_rate,
    poly_from_roots,
    quadratic_weight,
    traced_positive,
    traced_stable_roots,
)
from ._base import AbstractObserver
from ._kreisselmeier import observer_form


class MinimalAdaptiveState(eqx.Module):
    """State of :class:`MinimalAdaptiveObserver`: x̂ of (4.14), â, b̂, and the filters of x_1 and u."""

    xhat: jax.Array  # (n,)
    a: jax.Array  # (n,)   â
    b: jax.Array  # (n,)   b̂
    omega_y: jax.Array  # (n−1,) state of 1/D(s) driven by x_1 = y
    omega_u: jax.Array  # (n−1,) state of 1/D(s) driven by u


class MinimalAdaptiveObserver(AbstractObserver):
    r"""Minimal adaptive observer (thesis section 4.5.1, (4.12)-(4.18); Carroll–Lindorff, Kudva–Narendra).

    Plant (4.12), single input and output, order n, with a, b ∈ Rⁿ unknown:

        ẋ = [−a | Ā] x + b u,   y = x_1 = hᵀx,   Ā = [I_{n−1}; 0],  h = e_1,

    i.e. y = (b_1 s^{n−1} + ... + b_n)/(s^n + a_1 s^{n−1} + ... + a_n) u (:func:`obsjax.kreisselmeier_form`
    builds it).  The thesis leaves the known n × (n−1) matrix Ā general; it is taken in this observable
    canonical form, to which every observable SISO plant can be brought.

    **Implemented as printed** (with the unit rate of (4.17)-(4.18) replaced by a gain Γ):

    - (4.13)-(4.14): K = [−k | Ā],  x̂̇ = K x̂ + (k − â) x_1 + b̂ u + w⁽¹⁾ + w⁽²⁾ (the printed "k x̂" is K x̂);
    - (4.15): with e = x̂ − x, φ = a − â, ψ = b̂ − b, θ = [φ | ψ], Z = [x_1, u]:  ė = K e + θ Z + w,
      ε_1 = hᵀ e (ε_1 = x̂_1 − y);
    - (4.16)-(4.18): θ̇ = −Γ ε_1 v, v = [v⁽¹⁾; v⁽²⁾] (θ as the 2n-vector [φ; ψ]), i.e. â̇ = −φ̇ and b̂̇ = ψ̇.

    **Rebuilt** (the text names but does not print v, w, d; "v(t) = G(pPZ(t))", "w = w(θ, V)" and the
    garbled second system of the proposition are read as v = G(p) Z, w = w(θ̇, filter states),
    ε̇ = K ε + d θᵀ v):

    - the filters of Fig. 4.3, two identical (n−1)-th order systems 1/D(s),
      D(s) = s^{n−1} + δ_1 s^{n−2} + ... + δ_{n−1} with the roots ``filter_poles``, driven by x_1 and u
      (states ω⁽¹⁾, ω⁽²⁾, zero at t0); the regressors are v⁽¹⁾_i = s^{n−i}/D(s) x_1 and
      v⁽²⁾_i = s^{n−i}/D(s) u (i = 1..n);
    - the gain k: det(sI − K) = (s + λ) D(s) (``lam`` = λ), and d = (1, δ_1, ..., δ_{n−1}), so that
      hᵀ(sI − K)⁻¹ d = D(s)/((s + λ) D(s)) = 1/(s + λ), strictly positive real, as error model 2 (4.16)
      requires;
    - the auxiliary signals w⁽¹⁾ = Σ_i φ̇_i C_i ω⁽¹⁾, w⁽²⁾ = Σ_i ψ̇_i C_i ω⁽²⁾, with the constant matrices C_i
      of :func:`auxiliary_matrices` (K C_i − C_i F = d E_i, C_i g = e_i − δ_{i1} d for the filter (F, g) and
      v_i = E_i ω + δ_{i1} sig).  Then ρ = Σ_i (φ_i C_i ω⁽¹⁾ + ψ_i C_i ω⁽²⁾) has ρ_1 ≡ 0, and ε = e − ρ obeys
      ε̇ = K ε + d θᵀ v exactly (the proposition: both systems have the output ε_1).

    Lyapunov argument: since K d = −λ d, ε̇_1 = −λ ε_1 + θᵀ v + η(t), where η = hᵀKε + λ ε_1 decays with
    the modes of K and vanishes identically when e(0) = 0.  With V = ½ ε_1² + ½ θᵀ Γ⁻¹ θ
    (:meth:`lyapunov`), V̇ = −λ ε_1² + ε_1 η: V is non-increasing whenever x̂(0) = x(0).  (ε_1, θ) is the
    second class of (4.21) with A = −λ and B = −Γ^{1/2} v, so the parameters converge uniformly when v is
    sufficiently rich (:func:`obsjax.analysis.morgan_narendra`): n distinct frequencies in u when all 2n
    parameters are unknown.  With the same filters (D = R, λ = λ_0), matching initial estimates
    (:meth:`NonMinimalAdaptiveObserver.matching_point`) and a plant at rest, x(0) = x̂(0) = 0, this law and
    :class:`obsjax.NonMinimalAdaptiveObserver` produce the same parameter estimates.  From another
    x(0) = x̂(0) they differ: the non-minimal observer's filters start at zero, which is the plant's
    filtered state only when x(0) = 0 (its initial-condition terms decay with the filters' modes).

    **Arguments:**

    - `n`: plant order (static).
    - `filter_poles`: the n − 1 roots of D(s) (stable; real or conjugate pairs); differentiable.
    - `lam`: λ > 0, the remaining eigenvalue −λ of K; differentiable.
    - `Gamma`: adaptation rate of θ (2n parameters, â then b̂): a scalar, a (2n,) diagonal or a (2n, 2n)
      symmetric positive definite matrix; a differentiable leaf.
    - `a0`, `b0`: initial estimates â(t0), b̂(t0) (default zeros).
    - `adapt`: optional 2n booleans, False for parameters that are known: they stay at a0/b0 (the rate is
      restricted to the unknown ones, M Γ M).

    ``parameters(z)`` returns (â, b̂).  The field ``cache`` holds the design (k, K, d, δ, C_i) that
    ``prepare`` computes once per solve (``None`` otherwise).

    **Example:**::

        plant = obsjax.kreisselmeier_form(a=[2., 2.], b=[1., 1.])      # (s + 1)/(s² + 2s + 2)
        obs = obsjax.MinimalAdaptiveObserver(2, filter_poles=[-1.], lam=1., Gamma=20.)
        u = obsjax.signals.multisine([1., 1.], [.7, 2.])
        traj = obsjax.simulate(plant, obs, jnp.ones(2), jnp.ones(2), jnp.linspace(0., 300., 601), u=u)
        a_hat, b_hat = obs.parameters(traj.z)                          # → (2, 2) and (1, 1)
    """

    filter_poles: jax.Array
    lam: jax.Array
    Gamma: jax.Array
    a0: jax.Array
    b0: jax.Array
    cache: tuple | None
    n: int = eqx.field(static=True)
    adapt: tuple[bool, ...] = eqx.field(static=True)

    def __init__(self, n, filter_poles, lam, Gamma, *, a0=None, b0=None, adapt=None):
        n = state_dimension(n)
        if n < 1:
            raise ValueError(f"`n` (the plant order) must be >= 1, got {n}.")
        self.n = n
        self.filter_poles = check_stable_roots(
            jnp.zeros(0) if n == 1 and filter_poles is None else filter_poles, "filter_poles", n - 1
        )
        self.lam = _positive_scalar(lam, "lam")
        self.Gamma = gain_array(Gamma, "Gamma", 2 * n)
        self.a0 = jnp.zeros(n) if a0 is None else require_finite(vector(a0, "a0", n), "a0")
        self.b0 = jnp.zeros(n) if b0 is None else require_finite(vector(b0, "b0", n), "b0")
        self.adapt = adapt_mask(adapt, 2 * n)
        self.cache = None

    def prepare(self):
        """Guards that survive ``jit`` (``eqx.error_if``): Γ positive (definite), λ > 0, Re(filter poles) < 0."""
        poles = traced_stable_roots(self.filter_poles, "filter_poles")
        new = eqx.tree_at(
            lambda o: (o.Gamma, o.lam, o.filter_poles),
            self,
            (traced_positive(self.Gamma, "Gamma"), traced_positive(self.lam, "lam"), poles),
        )
        # the design (k, K, d, δ, C_i) once per solve, inside the differentiated graph
        design = eqx.tree_at(lambda o: o.cache, new, None, is_leaf=lambda x: x is None)._design()
        return eqx.tree_at(lambda o: o.cache, new, design, is_leaf=lambda x: x is None)

    def check(self):
        check_gain(self.Gamma, "Gamma")
        positive(self.lam, "lam")
        check_stable_roots(self.filter_poles, "filter_poles", self.n - 1)
        return self

    def design(self):
        """(k, K, d, δ): det(sI − K) = (s + λ) D(s), K = [−k | Ā], d = (1, δ), D(s) = s^{n−1} + Σ δ_j s^{n−1−j}."""
        return self._design()[:4]

    def _design(self):
        """(k, K, d, δ, C): the design, cached by ``prepare`` (computed afresh when it has not run)."""
        if self.cache is not None:
            return self.cache
        delta = poly_from_roots(self.filter_poles)
        k = poly_from_roots(jnp.concatenate([-jnp.reshape(self.lam, (1,)), self.filter_poles]))
        d = jnp.concatenate([jnp.ones(1, delta.dtype), delta])
        return k, observer_form(k), d, delta, auxiliary_matrices(d)

    def init(self, t0, xhat0, y0):
        n = self.n
        xhat0 = jnp.asarray(xhat0, dtype=float)
        if xhat0.shape != (n,):
            raise ValueError(f"`xhat0` must have shape ({n},), got {tuple(xhat0.shape)}.")
        zeros = jnp.zeros(n - 1)
        return MinimalAdaptiveState(xhat0, self.a0, self.b0, zeros, zeros)

    def vector_field(self, t, z: MinimalAdaptiveState, y, u):
        n = self.n
        x1 = siso_signal(y, "y", "MinimalAdaptiveObserver")
        u = siso_signal(u, "u", "MinimalAdaptiveObserver")
        k, K, _, delta, C = self._design()
        v = jnp.concatenate(
            [filter_regressor(z.omega_y, x1, delta), filter_regressor(z.omega_u, u, delta)]
        )
        eps1 = z.xhat[0] - x1  # ε_1 = hᵀ e
        dtheta = -eps1 * masked_rate(self.Gamma, self.adapt, v)  # (4.18)
        dphi, dpsi = dtheta[:n], dtheta[n:]
        w = jnp.einsum("i,imj,j->m", dphi, C, z.omega_y) + jnp.einsum(
            "i,imj,j->m", dpsi, C, z.omega_u
        )  # w⁽¹⁾ + w⁽²⁾
        dxhat = K @ z.xhat + (k - z.a) * x1 + z.b * u + w  # (4.14)
        return MinimalAdaptiveState(
            dxhat,
            -dphi,  # φ = a − â
            dpsi,  # ψ = b̂ − b
            filter_step(z.omega_y, x1, delta),
            filter_step(z.omega_u, u, delta),
        )

    def estimate(self, t, z: MinimalAdaptiveState, y):
        return z.xhat

    def parameters(self, z: MinimalAdaptiveState):
        """Current (â, b̂), the estimates of (a, b) of (4.12) (works on a trajectory too)."""
        return z.a, z.b

    def regressor(self, z: MinimalAdaptiveState, y, u):
        """v = [v⁽¹⁾; v⁽²⁾] of (4.18) (vectorised over a leading time axis)."""

        def one(zz, yy, uu):
            delta = self.design()[3]
            yy, uu = siso_signal(yy, "y", "MinimalAdaptiveObserver"), siso_signal(uu, "u", "MinimalAdaptiveObserver")
            return jnp.concatenate(
                [filter_regressor(zz.omega_y, yy, delta), filter_regressor(zz.omega_u, uu, delta)]
            )

        if z.xhat.ndim == 1:
            return one(z, y, u)
        return jax.vmap(one)(z, y, u)

    def lyapunov(self, z: MinimalAdaptiveState, y, a, b):
        """V = ½ ε_1² + ½ θᵀ Γ⁻¹ θ for the true (a, b), θ = [a − â; b̂ − b] (vectorised over time)."""
        eps1 = z.xhat[..., 0] - jnp.asarray(y).reshape(z.xhat.shape[:-1])
        theta = jnp.concatenate([jnp.asarray(a) - z.a, z.b - jnp.asarray(b)], axis=-1)
        return 0.5 * eps1**2 + 0.5 * quadratic_weight(self.Gamma, self.adapt, theta)


def _positive_scalar(x, name):
    arr = as_float_array(x, name)
    if arr.ndim != 0:
        raise ValueError(f"`{name}` must be a scalar, got shape {tuple(arr.shape)}.")
    positive(arr, name)
    v = concrete_value(arr)
    if v is not None and not np.isfinite(v):
        raise ValueError(f"`{name}` must be finite, got {v.tolist()}.")
    return arr
