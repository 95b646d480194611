"""Kreisselmeier's parametrised adaptive observer (Hassan thesis, chapter 6) with its three adaptation laws."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array, vector
from ._adaptive_common import (
    state_dimension,
    siso_signal,
    apply_gain,
    check_gain,
    check_stable_roots,
    gain_array,
    gain_matrix,
    poly_from_roots,
    traced_positive,
    traced_stable_roots,
)
from ._base import AbstractObserver
from ._validation import positive_scalar, require_finite, traced_finite

_SCHEMES = ("gradient", "generalized", "integral")


def observer_form(coeffs) -> jnp.ndarray:
    """The observable canonical matrix of (6.2)/(6.4): first column −coeffs, ones on the superdiagonal.

    ``observer_form(a)`` is the plant's A of (6.2); ``observer_form(f)`` is the observer's F of (6.4).
    """
    coeffs = jnp.asarray(coeffs)
    n = coeffs.shape[0]
    return jnp.eye(n, k=1, dtype=coeffs.dtype).at[:, 0].set(-coeffs)


def resolvent_numerators(F, f) -> jnp.ndarray:
    """The matrices T_i of (6.9): (sI − F)⁻¹ e_i = T_i (sI − Fᵀ)⁻¹ e_1, stacked as T[i] (shape (n, n, n)).

    By (6.8), (sI − Fᵀ)⁻¹ e_1 = [s^{n−1}, ..., s, 1]ᵀ / det(sI − F) for F in the form (6.4), so column k
    of T_i holds the coefficient of s^{n−1−k} in adj(sI − F) e_i.  With det(sI − F) = s^n + f_1 s^{n−1}
    + ... + f_n the Faddeev–LeVerrier recursion adj(sI − F) = Σ_k s^{n−1−k} B_k, B_0 = I,
    B_k = F B_{k−1} + f_k I gives T_i[:, k] = B_k e_i.
    """
    n = F.shape[0]
    Bs = [jnp.eye(n, dtype=F.dtype)]
    for k in range(1, n):
        Bs.append(F @ Bs[-1] + f[k - 1] * jnp.eye(n, dtype=F.dtype))
    B = jnp.stack(Bs)  # (k, row, i)
    return jnp.transpose(B, (2, 1, 0))  # T[i, row, k] = B_k[row, i]


class KreisselmeierState(eqx.Module):
    """State of :class:`Kreisselmeier`: filters (6.10a-b), e^{F t} x̂0, parameters p = [g; h] and the
    scheme's memory (Lion's filter states for ``"generalized"``, R and r of (6.24) for ``"integral"``)."""

    eta1: jax.Array  # (n,)   η1 of (6.10a)
    eta2: jax.Array  # (n,)   η2 of (6.10b)
    free: jax.Array  # (n,)   exp(F t) x̂0
    p: jax.Array  # (2n,)  [g; h]
    W: jax.Array | None  # (2n, 2n−1) Lion filter states of Z   (generalized)
    omega: jax.Array | None  # (2n−1,) Lion filter state of y − cᵀe^{Ft}x̂0 (generalized)
    R: jax.Array | None  # (2n, 2n)  (6.24a)  (integral)
    r: jax.Array | None  # (2n,)     (6.24b)  (integral)


class Kreisselmeier(AbstractObserver):
    r"""Kreisselmeier's adaptive observer with exponential rate of convergence (thesis chapter 6).

    The plant is single-input single-output of known order n, in the observable canonical form (6.2)

        ẋ = A x + b u,  y = cᵀ x,  A = [−a | I_{n−1}; 0],  c = e_1,

    with a, b ∈ Rⁿ unknown.  The observer matrix F of (6.4) has the chosen eigenvalues ``poles`` and first
    column −f; the matching point of the Luenberger observer (6.3) is p* = [g*; h*] with g* = f − a,
    h* = b (6.5).  Implemented equations:

    - filters (6.10a-b): η̇₁ = Fᵀ η₁ + e₁ y,  η̇₂ = Fᵀ η₂ + e₁ u,  η(0) = 0;  Z = [η₁; η₂];
    - state estimate (6.15a) through (6.10c): x̂ = Σ_i T_i (g_i η₁ + h_i η₂) + e^{Ft} x̂0, with T_i of (6.9)
      (:func:`resolvent_numerators`); output ŷ = Zᵀ p + cᵀ e^{Ft} x̂0 (6.15b);
    - ``scheme="gradient"``, (6.16): ṗ = −G Z (ŷ − y), the steepest descent of (ŷ − y)².  (The OCR prints
      y − ŷ; with that sign the law ascends the criterion, so the descent sign of the text is used.)
    - ``scheme="generalized"``, Lion's generalised error (6.18)-(6.19): ṗ = −G 𝒵 Q (𝒵ᵀ p − Y) with
      𝒵 = [Z, Ż, ..., Z^{(2n−1)}] and Y = [y_c, ẏ_c, ..., y_c^{(2n−1)}], y_c = y − cᵀe^{Ft}x̂0 (so
      𝒵ᵀp − Y is the generalised output error Ŷ − Y of (6.18a)).  It is realised without differentiating
      any signal by Lion's state-variable filters: Z and y_c are first passed through the stable filter
      1/L(s), L(s) = (s + ℓ)^{2n−1} (``filter_pole`` ℓ), whose 2n−1 states are the filtered derivatives
      s^k/L Z, k = 0..2n−2, and s^{2n−1}/L Z = Z − Σ l_k s^k/L Z.  Because y = Zᵀ p* + cᵀ e^{Ft} x0 is
      linear time-invariant in (y, Z), the filtered signals satisfy it too up to exponentially vanishing
      transients, so 𝒵ᵀ(p − p*) is the generalised error of (6.18) for the filtered pair.
    - ``scheme="integral"``, (6.20)-(6.24): ṗ = −G (R p + r), Ṙ = −q R + Z Zᵀ, ṙ = −q r + Z (cᵀe^{Ft}x̂0 − y),
      R(0) = 0, r(0) = 0: the gradient of the exponentially weighted criterion (6.20) with memory q.

    With u sufficiently rich (n distinct frequencies), Z is persistently exciting (6.17) and p → p*,
    x̂ → x exponentially.

    **Arguments:**

    - `n`: plant order (static).
    - `poles`: the n eigenvalues of F (stable; real, or complex-conjugate pairs).
    - `G`: adaptation gain: a scalar, a (2n,) diagonal, or a (2n, 2n) symmetric positive definite matrix
      (a differentiable leaf).
    - `scheme`: ``"gradient"`` (6.16), ``"generalized"`` (6.19) or ``"integral"`` (6.23).
    - `q`: memory of the integral scheme (> 0, differentiable; required for ``"integral"``, refused otherwise).
    - `Q`: weighting of the generalised error (``"generalized"``): scalar, (2n,) or (2n, 2n); default 1.
    - `filter_pole`: ℓ > 0 of Lion's filter (``"generalized"``); default 1.
    - `a0`, `b0`: initial parameter estimates in the form (6.2) (default zeros).

    **Returns:** ``parameters(z)`` gives the current (â, b̂) of (6.2): â = f − g, b̂ = h.

    The components of Z differ in size by orders of magnitude, so a diagonal G normalised by the mean of
    Z Zᵀ (:func:`mean_regressor_covariance`) converges far faster than a scalar one;
    :meth:`averaged_rate` predicts the resulting exponential rate.

    **Example:**::

        plant = obsjax.kreisselmeier_form(a=[2., 2.], b=[1., 1.])   # (s + 1)/(s² + 2s + 2)
        G = 2.0 / np.diag(mean_regressor_covariance([2., 2.], [1., 1.], [-2., -2.], [1., 1.], [.7, 2.]))
        obs = obsjax.Kreisselmeier(2, poles=[-2., -2.], G=G, scheme="integral", q=0.2)
        u = obsjax.signals.multisine([1., 1.], [.7, 2.])
        traj = obsjax.simulate(plant, obs, jnp.ones(2), jnp.zeros(2), jnp.linspace(0., 100., 201), u=u)
        a_hat, b_hat = obs.parameters(traj.z)          # (T, n) each; → (2, 2) and (1, 1)
    """

    poles: jax.Array
    G: jax.Array
    q: jax.Array | None
    Q: jax.Array
    filter_pole: jax.Array
    a0: jax.Array
    b0: jax.Array
    n: int = eqx.field(static=True)
    scheme: str = eqx.field(static=True)

    def __init__(
        self,
        n,
        poles,
        G,
        scheme: str = "gradient",
        q=None,
        *,
        Q=None,
        filter_pole=None,
        a0=None,
        b0=None,
    ):
        n = state_dimension(n, what=" (the plant order)")
        if scheme not in _SCHEMES:
            raise ValueError(f"`scheme` must be one of {_SCHEMES}, got {scheme!r}.")
        self.n = n
        self.scheme = scheme
        self.poles = check_stable_roots(poles, "poles", n)
        self.G = gain_array(G, "G", 2 * n)
        if scheme == "integral":
            if q is None:
                raise ValueError(
                    "`q` (the memory of the integral scheme (6.20)) is required for scheme='integral'."
                )
            q = as_float_array(q, "q")
            if q.ndim != 0:
                raise ValueError(f"`q` must be a scalar, got shape {tuple(q.shape)}.")
            positive_scalar(q, "q", " (the memory of the integral scheme)")
            self.q = q
        else:
            if q is not None:
                raise ValueError(
                    f"`q` is the memory of scheme='integral'; it is unused by scheme={scheme!r}."
                )
            self.q = None
        self.Q = gain_array(1.0 if Q is None else Q, "Q", 2 * n)
        fp = as_float_array(1.0 if filter_pole is None else filter_pole, "filter_pole")
        if fp.ndim != 0:
            raise ValueError(f"`filter_pole` must be a scalar, got shape {tuple(fp.shape)}.")
        positive_scalar(fp, "filter_pole", " (Lion's filter pole ℓ)")
        self.filter_pole = fp
        self.a0 = jnp.zeros(n) if a0 is None else require_finite(vector(a0, "a0", n), "a0")
        self.b0 = jnp.zeros(n) if b0 is None else require_finite(vector(b0, "b0", n), "b0")

    # ------------------------------------------------------------------ design
    def _design(self):
        f = poly_from_roots(self.poles)
        F = observer_form(f)
        T = resolvent_numerators(F, f)
        return f, F, T

    def _lion(self):
        """Companion matrix of L(s) = (s + ℓ)^{2n−1} (controllable form, last row −l) and l."""
        k = 2 * self.n - 1
        ell = self.filter_pole
        l_desc = poly_from_roots(-ell * jnp.ones(k))  # l_{k−1}, ..., l_0 (descending)
        l_asc = l_desc[::-1]  # l_0, ..., l_{k−1}
        Ac = jnp.eye(k, k=1).at[-1, :].set(-l_asc)
        return Ac, l_asc

    def prepare(self):
        """Guards that survive ``jit`` (``eqx.error_if``): G, Q > 0, q > 0, ℓ > 0, Re(poles) < 0,
        all finite."""
        G = traced_finite(traced_positive(self.G, "G"), "G")
        Q = traced_finite(traced_positive(self.Q, "Q"), "Q")
        new = eqx.tree_at(lambda o: (o.G, o.Q), self, (G, Q))
        new = eqx.tree_at(
            lambda o: o.filter_pole, new, positive_scalar(self.filter_pole, "filter_pole")
        )
        if self.q is not None:
            new = eqx.tree_at(lambda o: o.q, new, positive_scalar(self.q, "q"))
        poles = traced_stable_roots(self.poles, "poles")
        return eqx.tree_at(lambda o: o.poles, new, poles)

    def check(self):
        check_gain(self.G, "G")
        check_gain(self.Q, "Q")
        if self.q is not None:
            positive_scalar(self.q, "q")
        positive_scalar(self.filter_pole, "filter_pole")
        check_stable_roots(self.poles, "poles", self.n)
        return self

    # ------------------------------------------------------------------ protocol
    def init(self, t0, xhat0, y0):
        n = self.n
        f, _, _ = self._design()
        xhat0 = jnp.asarray(xhat0, dtype=float)
        if xhat0.shape != (n,):
            raise ValueError(f"`xhat0` must have shape ({n},), got {tuple(xhat0.shape)}.")
        p0 = jnp.concatenate([f - self.a0, self.b0])  # (6.5) applied to the initial guess
        zeros = jnp.zeros(n)
        W = omega = R = r = None
        if self.scheme == "generalized":
            W = jnp.zeros((2 * n, 2 * n - 1))
            omega = jnp.zeros(2 * n - 1)
        elif self.scheme == "integral":
            R = jnp.zeros((2 * n, 2 * n))
            r = jnp.zeros(2 * n)
        return KreisselmeierState(zeros, zeros, xhat0, p0, W, omega, R, r)

    def vector_field(self, t, z: KreisselmeierState, y, u):
        n = self.n
        _, F, _ = self._design()
        y = siso_signal(y, "y", "Kreisselmeier")
        u = siso_signal(u, "u", "Kreisselmeier")
        e1 = jnp.zeros(n).at[0].set(1.0)
        deta1 = F.T @ z.eta1 + e1 * y  # (6.10a)
        deta2 = F.T @ z.eta2 + e1 * u  # (6.10b)
        dfree = F @ z.free  # d/dt e^{Ft} x̂0
        Z = jnp.concatenate([z.eta1, z.eta2])
        yc = y - z.free[0]  # y − cᵀ e^{Ft} x̂0
        dW = domega = dR = dr = None
        if self.scheme == "gradient":
            err = Z @ z.p - yc  # ŷ − y (6.15b)
            dp = -apply_gain(self.G, Z * err)  # (6.16)
        elif self.scheme == "generalized":
            Ac, l = self._lion()
            k = 2 * n - 1
            elast = jnp.zeros(k).at[-1].set(1.0)
            dW = z.W @ Ac.T + jnp.outer(Z, elast)
            domega = Ac @ z.omega + elast * yc
            Zf = jnp.concatenate([z.W, (Z - z.W @ l)[:, None]], axis=1)  # 𝒵 (filtered), (2n, 2n)
            Yf = jnp.concatenate([z.omega, (yc - l @ z.omega)[None]])  # Y (filtered), (2n,)
            E = Zf.T @ z.p - Yf  # generalised output error (6.18)
            dp = -apply_gain(self.G, Zf @ apply_gain(self.Q, E))  # (6.19)
        else:
            dR = -self.q * z.R + jnp.outer(Z, Z)  # (6.24a)
            dr = -self.q * z.r + Z * (z.free[0] - y)  # (6.24b)
            dp = -apply_gain(self.G, z.R @ z.p + z.r)  # (6.23)
        return KreisselmeierState(deta1, deta2, dfree, dp, dW, domega, dR, dr)

    def estimate(self, t, z: KreisselmeierState, y):
        n = self.n
        _, _, T = self._design()
        g, h = z.p[:n], z.p[n:]
        # (6.15a) with ξ_i = T_i η₁, ξ_{n+i} = T_i η₂ (6.10c)
        return (
            jnp.einsum("irk,k,i->r", T, z.eta1, g) + jnp.einsum("irk,k,i->r", T, z.eta2, h) + z.free
        )

    def output(self, z: KreisselmeierState):
        """ŷ = Zᵀ p + cᵀ e^{Ft} x̂0 (6.15b)."""
        return jnp.concatenate([z.eta1, z.eta2]) @ z.p + z.free[..., 0]

    def parameters(self, z: KreisselmeierState):
        """Current estimates (â, b̂) of the plant form (6.2): â = f − g, b̂ = h (inverse of (6.5)).

        Works on a single state or on a trajectory (leading time axis)."""
        n = self.n
        f, _, _ = self._design()
        p = z.p
        return f - p[..., :n], p[..., n:]

    def matching_point(self, a, b):
        """p* = [f − a; b] of (6.5) for a plant (a, b) in the form (6.2)."""
        f, _, _ = self._design()
        return jnp.concatenate([f - jnp.asarray(a), jnp.asarray(b)])

    def averaged_rate(self, a, b, amplitudes, frequencies):
        """Predicted exponential rate of ‖p − p*‖ by averaging, for a multisine input (NumPy, no simulation).

        For small gains the parameter error obeys ṗ ≈ −G M̄ (p − p*) with M̄ = R̄ (gradient, (6.16)),
        M̄ = Σ_{k,l} Q_kl avg(s^k/L Z (s^l/L Z)ᴴ) (generalised, (6.19)), or M̄ = R̄/q (integral, (6.23),
        once R(t) of (6.24a) has reached its mean R̄/q); the slowest rate is λ_min(G M̄).
        R̄ is :func:`mean_regressor_covariance`.
        """
        n = self.n
        poles = np.asarray(self.poles)
        G = np.asarray(gain_matrix(self.G, 2 * n))
        if self.scheme == "generalized":
            Qm = np.asarray(gain_matrix(self.Q, 2 * n))
            ell = float(self.filter_pole)

            def weight(w):
                v = np.array([(1j * w) ** k for k in range(2 * n)]) / (1j * w + ell) ** (2 * n - 1)
                return complex(v @ Qm @ v.conj())

            M = mean_regressor_covariance(a, b, poles, amplitudes, frequencies, weight)
        else:
            M = mean_regressor_covariance(a, b, poles, amplitudes, frequencies)
            if self.scheme == "integral":
                M = M / float(self.q)
        return float(np.min(np.real(np.linalg.eigvals(G @ M))))

    def regressor(self, z: KreisselmeierState):
        """Z = [η₁; η₂] (the regressor of (6.13))."""
        return jnp.concatenate([z.eta1, z.eta2], axis=-1)


def kreisselmeier_form(a, b):
    """The plant of (6.2) as an :class:`obsjax.LTI`: A = [−a | I_{n−1}; 0], B = b, C = e_1ᵀ.

    Its transfer function is (b_1 s^{n−1} + ... + b_n) / (s^n + a_1 s^{n−1} + ... + a_n).
    """
    from ..systems._plants import LTI

    a = as_float_array(a, "a")
    b = as_float_array(b, "b")
    if a.ndim != 1 or b.shape != a.shape:
        raise ValueError(
            f"`a` and `b` must be vectors of the same length n, got {tuple(a.shape)} and {tuple(b.shape)}."
        )
    n = a.shape[0]
    require_finite(a, "a")
    require_finite(b, "b")
    return LTI(observer_form(a), b.reshape(n, 1), jnp.eye(1, n))


def mean_regressor_covariance(a, b, poles, amplitudes, frequencies, weight=None):
    """Time average of Z Zᵀ (the excitation of (6.17)) for u = Σ A_k sin(ω_k t + φ_k), by the frequency response.

    Z = [η₁; η₂] = H(s) u with H = [[s^{n−1}, ..., 1] N(s)/(D(s) d(s)); [s^{n−1}, ..., 1]/d(s)], N/D the
    plant's transfer function of (6.2) and d(s) = det(sI − F); in steady state
    R̄ = Σ_k (A_k²/2) Re(H(jω_k) H(jω_k)ᴴ) (distinct ω_k).  ``weight(ω)`` (a complex factor per frequency, applied before the real part)
    gives the average of filtered regressors.  Computed with NumPy, independently of the simulation.
    """
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    n = a.shape[0]
    D = np.r_[1.0, a]
    d = np.real(np.poly(np.asarray(poles)))
    R = np.zeros((2 * n, 2 * n))
    for A, w in zip(np.ravel(amplitudes), np.ravel(frequencies)):
        s = 1j * w
        basis = np.array([s ** (n - 1 - k) for k in range(n)]) / np.polyval(d, s)
        H = np.r_[basis * np.polyval(b, s) / np.polyval(D, s), basis]
        wt = 1.0 if weight is None else weight(w)
        R += A**2 / 2 * np.real(wt * np.outer(H, H.conj()))
    return R
