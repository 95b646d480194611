"""The non-minimal adaptive observer with the plant output fed back (Hassan thesis, section 4.5.2)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import positive, require_finite, vector
from ._adaptive_common import (
    state_dimension,
    siso_signal,
    adapt_mask,
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
from ._minimal_adaptive import _positive_scalar


class NonMinimalAdaptiveState(eqx.Module):
    """State of :class:`NonMinimalAdaptiveObserver`: ŷ, the filters of y and u, and the estimates â, b̂."""

    yhat: jax.Array  # ()
    omega_y: jax.Array  # (n−1,) state of 1/R(s) driven by the plant output y
    omega_u: jax.Array  # (n−1,) state of 1/R(s) driven by u
    a: jax.Array  # (n,)  â: coefficients of −P(s)
    b: jax.Array  # (n,)  b̂: coefficients of Q(s)


class NonMinimalAdaptiveObserver(AbstractObserver):
    r"""Non-minimal adaptive observer with the plant output fed back (thesis section 4.5.2, (4.19),
    Figs. 4.4-4.5).

    The plant is SISO of order n with transfer function T_p(s) = Q_p(s)/R_p(s), deg Q_p ≤ n − 1, R_p monic of
    degree n.  **As printed:** with R(s) Hurwitz of degree n − 1 (monic; roots ``filter_poles``) and λ_0 > 0,

        R(s)(s + λ_0) + P_p(s) = R_p(s),   T_p = (Q_p/R) · (1/(s + λ_0)) / (1 + (P_p/R)/(s + λ_0)),

    so that (s + λ_0) y = Q_p/R u − P_p/R y: Fig. 4.4, with the *plant* output y in the feedback path
    (Fig. 4.5).  Adaptive law (4.19), with a rate Γ in place of the unit gain:

        â̇_i = −e_1 v⁽¹⁾_i,   b̂̇_i = −e_1 v⁽²⁾_i   (i = 1..n),   i.e. θ̇ = −Γ e_1 v,  θ = [â; b̂], v = [v⁽¹⁾; v⁽²⁾]

    (the OCR prints "â_i = −e_i v_i(1)": the dot of the derivative and the index 1 of the output error are lost).

    **Rebuilt** (Figs. 4.4-4.5 are not in the text): the regressors are the outputs of two identical filters
    1/R(s) (states ω⁽¹⁾, ω⁽²⁾ of dimension n − 1, zero at t0), v⁽¹⁾_i = s^{n−i}/R(s) y and
    v⁽²⁾_i = s^{n−i}/R(s) u; the model is

        ŷ̇ = −λ_0 ŷ + âᵀ v⁽¹⁾ + b̂ᵀ v⁽²⁾,   e_1 = ŷ − y,

    where b̂ estimates the coefficients of Q_p (b_i of s^{n−i}) and â those of −P_p (the feedback path of
    Fig. 4.4 enters with a minus sign, 1/(1 + ...)); with this sign the printed law (4.19) is the one for
    which the Lyapunov argument holds.  The plant obeys ẏ = −λ_0 y + aᵀv⁽¹⁾ + bᵀv⁽²⁾ + τ(t), τ a transient
    of the initial states of plant and filters that decays with the roots of R (τ ≡ 0 when the plant starts
    at rest), so ė_1 = −λ_0 e_1 + θ̃ᵀ v − τ
    (θ̃ = θ − θ*), and V = ½ e_1² + ½ θ̃ᵀ Γ⁻¹ θ̃ (:meth:`lyapunov`) has V̇ = −λ_0 e_1² − e_1 τ(t): the error
    system is (4.20)-(4.21)(ii) with A = −λ_0 and B(t) = −Γ^{1/2} v.

    **State estimate** (the thesis identifies the plant; the state is rebuilt from the same signals): x̂ is
    the state of the plant in the form (4.12), ẋ = [−α | Ā] x + b u, y = x_1 (:func:`obsjax.kreisselmeier_form`,
    α the coefficients of R̂_p = R(s)(s + λ_0) − Â(s)).  In that form x_j = U_j(s) y − V_j(s) u with
    U_j = s^{j−1} + α_1 s^{j−2} + ... + α_{j−1}, V_j = b_1 s^{j−2} + ... + b_{j−1}; dividing U_j R by R̂_p
    (quotient q_j, remainder r_j) and using R̂_p y = B̂ u gives x̂_j = [r_j y + (q_j B̂ − V_j R) u]/R(s), read off
    the filter states (:meth:`estimate`).  x̂_1 = y; x̂ → x as the parameters converge.  The filters start at
    rest, so only ``xhat0[0]`` is used (as ŷ(t0)).

    **Arguments:**

    - `n`: plant order (static).
    - `filter_poles`: the n − 1 roots of R(s) (stable; real or conjugate pairs); differentiable.
    - `lam0`: λ_0 > 0; differentiable.
    - `Gamma`: adaptation rate of θ = [â; b̂]: scalar, (2n,) diagonal or (2n, 2n) s.p.d.; a differentiable leaf.
    - `a0`, `b0`: initial â, b̂ in the law's own coordinates (default zeros; :meth:`matching_point` maps a plant
      in the form (4.12) to them).
    - `adapt`: optional 2n booleans, False for known parameters (held at a0/b0).

    ``parameters(z)`` returns the estimates (α̂, b̂) of the plant form (4.12), ``z.a``/``z.b`` the law's own.
    The field ``cache`` holds (R, (s + λ_0)R) coefficients computed by ``prepare`` once per solve.

    **Example:**::

        plant = obsjax.kreisselmeier_form(a=[2., 2.], b=[1., 1.])      # (s + 1)/(s² + 2s + 2)
        obs = obsjax.NonMinimalAdaptiveObserver(2, filter_poles=[-1.], lam0=1., Gamma=20.)
        u = obsjax.signals.multisine([1., 1.], [.7, 2.])
        traj = obsjax.simulate(plant, obs, jnp.ones(2), jnp.zeros(2), jnp.linspace(0., 300., 601), u=u)
        a_hat, b_hat = obs.parameters(traj.z)                          # → (2, 2) and (1, 1)
    """

    filter_poles: jax.Array
    lam0: jax.Array
    Gamma: jax.Array
    a0: jax.Array
    b0: jax.Array
    cache: tuple | None
    n: int = eqx.field(static=True)
    adapt: tuple[bool, ...] = eqx.field(static=True)

    def __init__(self, n, filter_poles, lam0, Gamma, *, a0=None, b0=None, adapt=None):
        n = state_dimension(n)
        if n < 1:
            raise ValueError(f"`n` (the plant order) must be >= 1, got {n}.")
        self.n = n
        self.filter_poles = check_stable_roots(
            jnp.zeros(0) if n == 1 and filter_poles is None else filter_poles, "filter_poles", n - 1
        )
        self.lam0 = _positive_scalar(lam0, "lam0")
        self.Gamma = gain_array(Gamma, "Gamma", 2 * n)
        self.a0 = jnp.zeros(n) if a0 is None else require_finite(vector(a0, "a0", n), "a0")
        self.b0 = jnp.zeros(n) if b0 is None else require_finite(vector(b0, "b0", n), "b0")
        self.adapt = adapt_mask(adapt, 2 * n)
        self.cache = None

    def prepare(self):
        """Guards that survive ``jit`` (``eqx.error_if``): Γ positive (definite), λ_0 > 0, Re(filter poles) < 0."""
        poles = traced_stable_roots(self.filter_poles, "filter_poles")
        new = eqx.tree_at(
            lambda o: (o.Gamma, o.lam0, o.filter_poles),
            self,
            (traced_positive(self.Gamma, "Gamma"), traced_positive(self.lam0, "lam0"), poles),
        )
        fresh = eqx.tree_at(lambda o: o.cache, new, None, is_leaf=lambda x: x is None)
        design = (fresh._rho(), fresh._base())  # once per solve, inside the differentiated graph
        return eqx.tree_at(lambda o: o.cache, new, design, is_leaf=lambda x: x is None)

    def check(self):
        check_gain(self.Gamma, "Gamma")
        positive(self.lam0, "lam0")
        check_stable_roots(self.filter_poles, "filter_poles", self.n - 1)
        return self

    def _rho(self):
        """Coefficients (ρ_1, ..., ρ_{n−1}) of R(s) = s^{n−1} + ρ_1 s^{n−2} + ... + ρ_{n−1}."""
        if self.cache is not None:
            return self.cache[0]
        return poly_from_roots(self.filter_poles)

    def _base(self):
        """Coefficients (c_1, ..., c_n) of (s + λ_0) R(s) = s^n + c_1 s^{n−1} + ... + c_n."""
        if self.cache is not None:
            return self.cache[1]
        return poly_from_roots(jnp.concatenate([-jnp.reshape(self.lam0, (1,)), self.filter_poles]))

    def matching_point(self, a, b):
        """(a*, b*) of the law for a plant (4.12) with parameters (a, b): a* = c − a, b* = b, where
        (s + λ_0) R(s) = s^n + c_1 s^{n−1} + ... + c_n (so that −P_p = (s + λ_0) R − R_p)."""
        return self._base() - jnp.asarray(a), jnp.asarray(b)

    def init(self, t0, xhat0, y0):
        n = self.n
        xhat0 = jnp.asarray(xhat0, dtype=float)
        if xhat0.shape != (n,):
            raise ValueError(f"`xhat0` must have shape ({n},), got {tuple(xhat0.shape)}.")
        zeros = jnp.zeros(n - 1)
        return NonMinimalAdaptiveState(xhat0[0], zeros, zeros, self.a0, self.b0)

    def vector_field(self, t, z: NonMinimalAdaptiveState, y, u):
        n = self.n
        y = siso_signal(y, "y", "NonMinimalAdaptiveObserver")
        u = siso_signal(u, "u", "NonMinimalAdaptiveObserver")
        rho = self._rho()
        v1 = filter_regressor(z.omega_y, y, rho)  # s^{n−i}/R y: the plant output fed back
        v2 = filter_regressor(z.omega_u, u, rho)
        e1 = z.yhat - y
        dyhat = -self.lam0 * z.yhat + z.a @ v1 + z.b @ v2  # Figs. 4.4-4.5
        dtheta = -e1 * masked_rate(self.Gamma, self.adapt, jnp.concatenate([v1, v2]))  # (4.19)
        return NonMinimalAdaptiveState(
            dyhat,
            filter_step(z.omega_y, y, rho),
            filter_step(z.omega_u, u, rho),
            dtheta[:n],
            dtheta[n:],
        )

    def estimate(self, t, z: NonMinimalAdaptiveState, y):
        y = siso_signal(y, "y", "NonMinimalAdaptiveObserver")
        rho = self._rho()
        alpha = self._base() - z.a
        Ry, Su = _state_map(alpha, z.b, rho)  # (n, n) and (n, n−1) ascending coefficients
        # P(s)/R(s) sig from the filter state: Σ_{k<r} p_k ω_{k+1} + p_r (sig − ρ_asc·ω)
        r = self.n - 1
        top_y = y - jnp.dot(rho[::-1], z.omega_y) if r > 0 else y
        return Ry[:, :r] @ z.omega_y + Ry[:, r] * top_y + Su @ z.omega_u

    def parameters(self, z: NonMinimalAdaptiveState):
        """Estimates (α̂, b̂) of the plant form (4.12): α̂ = c − â, b̂ (works on a trajectory too)."""
        return self._base() - z.a, z.b

    def output(self, z: NonMinimalAdaptiveState):
        """ŷ of the model (Figs. 4.4-4.5)."""
        return z.yhat

    def regressor(self, z: NonMinimalAdaptiveState, y, u):
        """v = [v⁽¹⁾; v⁽²⁾] of (4.19) (vectorised over a leading time axis)."""

        def one(zz, yy, uu):
            rho = self._rho()
            yy, uu = siso_signal(yy, "y", "NonMinimalAdaptiveObserver"), siso_signal(uu, "u", "NonMinimalAdaptiveObserver")
            return jnp.concatenate(
                [filter_regressor(zz.omega_y, yy, rho), filter_regressor(zz.omega_u, uu, rho)]
            )

        if z.a.ndim == 1:
            return one(z, y, u)
        return jax.vmap(one)(z, y, u)

    def lyapunov(self, z: NonMinimalAdaptiveState, y, a, b):
        """V = ½ e_1² + ½ θ̃ᵀ Γ⁻¹ θ̃ for a plant (4.12) with parameters (a, b) (vectorised over time)."""
        a_star, b_star = self.matching_point(a, b)
        e1 = z.yhat - jnp.asarray(y).reshape(z.yhat.shape)
        theta = jnp.concatenate([z.a - a_star, z.b - b_star], axis=-1)
        return 0.5 * e1**2 + 0.5 * quadratic_weight(self.Gamma, self.adapt, theta)


def _state_map(alpha, b, rho):
    """Numerators of x_j = [r_j(s) y + S_j(s) u]/R(s) for the plant (4.12) with parameters (α, b).

    Returns ascending coefficient arrays: r (n, n) (degree ≤ n − 1) and S (n, n − 1) (degree ≤ n − 2).
    U_j R = q_j R_p + r_j (R_p = s^n + α_1 s^{n−1} + ..., monic), S_j = q_j B − V_j R, truncated to its degree
    n − 2 (the higher coefficients cancel identically).
    """
    n = alpha.shape[0]
    R = jnp.concatenate([jnp.ones(1, rho.dtype), rho])  # descending, degree n − 1
    Rp = jnp.concatenate([jnp.ones(1, alpha.dtype), alpha])  # descending, degree n
    rows_r, rows_s = [], []
    for j in range(1, n + 1):
        U = jnp.concatenate([jnp.ones(1, alpha.dtype), alpha[: j - 1]])  # degree j − 1
        V = b[: j - 1]  # degree j − 2 (empty for j = 1)
        q, rem = _divmod_monic(jnp.convolve(U, R), Rp)
        S = _sub(
            jnp.convolve(q, b) if q.shape[0] else jnp.zeros(0),
            jnp.convolve(V, R) if V.shape[0] else jnp.zeros(0),
        )
        rows_r.append(_ascending(rem, n))
        rows_s.append(_ascending(S, n - 1))
    return jnp.stack(rows_r), jnp.stack(rows_s)


def _divmod_monic(num, den):
    """Quotient and remainder (descending coefficients) of num / den for a monic den."""
    m, k = num.shape[0] - 1, den.shape[0] - 1
    if m < k:
        return jnp.zeros(0, num.dtype), num
    rem = num
    q = []
    for i in range(m - k + 1):
        c = rem[i]
        q.append(c)
        rem = rem.at[i : i + k + 1].add(-c * den)
    return jnp.stack(q), rem[m - k + 1 :]


def _sub(p, q):
    """p − q for descending coefficient arrays of any lengths."""
    L = max(p.shape[0], q.shape[0])
    return jnp.pad(p, (L - p.shape[0], 0)) - jnp.pad(q, (L - q.shape[0], 0))


def _ascending(p, size):
    """The lowest ``size`` coefficients of a descending array, in ascending order (zero-padded)."""
    asc = p[::-1]
    if asc.shape[0] >= size:
        return asc[:size]
    return jnp.pad(asc, (0, size - asc.shape[0]))
