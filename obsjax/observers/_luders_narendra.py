"""Lüders–Narendra adaptive observer and identifier (Hassan thesis, chapter 5)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import as_float_array, vector
from ._adaptive_common import siso_signal, state_dimension
from ._base import AbstractObserver
from ._validation import positive_scalar, require_finite


def luders_narendra_form(a, b, lambdas):
    """The plant of the canonical form (5.2) as an :class:`obsjax.LTI`, for parameters a, b and known Λ = diag(−λ_2, ..., −λ_n).

        A = [[a_1, 1, ..., 1], [a_2, −λ_2, 0, ...], ..., [a_n, 0, ..., −λ_n]],  B = b,  C = e_1ᵀ.

    ``lambdas`` may have length n (λ_1 is then ignored: it is the observer's own gain) or n − 1.
    """
    a = as_float_array(a, "a")
    b = as_float_array(b, "b")
    n = a.shape[0]
    if a.ndim != 1 or b.shape != (n,):
        raise ValueError(
            f"`a` and `b` must be vectors of the same length n, got {tuple(a.shape)} and {tuple(b.shape)}."
        )
    lam = as_float_array(lambdas, "lambdas").reshape(-1)
    if lam.shape[0] == n:
        lam = lam[1:]
    if lam.shape[0] != n - 1:
        raise ValueError(f"`lambdas` must have length {n} or {n - 1}, got {lam.shape[0]}.")
    require_finite(a, "a")
    require_finite(b, "b")
    if lam.shape[0]:
        positive_scalar(lam, "lambdas", " (the stable Λ of the form (5.2), as LudersNarendra requires)")
    A = jnp.zeros((n, n)).at[:, 0].set(a).at[0, 1:].set(1.0)
    A = A.at[jnp.arange(1, n), jnp.arange(1, n)].set(-lam)
    from ..systems._plants import LTI

    return LTI(A, b.reshape(n, 1), jnp.eye(1, n))


class LudersNarendraState(eqx.Module):
    """State of :class:`LudersNarendra`: x̂ of (5.3), α, β, and the filters v, s of (5.6)."""

    xhat: jax.Array  # (n,)
    alpha: jax.Array  # (n,)
    beta: jax.Array  # (n,)
    v: jax.Array  # (n−1,)  v̇_i = −λ_i v_i + x_1   (5.6a)
    s: jax.Array  # (n−1,)  ṡ_i = −λ_i s_i + u     (5.6b)


class LudersNarendra(AbstractObserver):
    r"""Lüders–Narendra adaptive observer and identifier (thesis chapter 5, (5.2)-(5.12)).

    The SISO plant of order n is written in the canonical form (5.2) with known
    Λ = diag(−λ_2, ..., −λ_n) and unknown a, b ∈ Rⁿ:

        ẋ_1 = a_1 x_1 + x_2 + ... + x_n + b_1 u,   ẋ_i = a_i x_1 − λ_i x_i + b_i u  (i ≥ 2),   y = x_1.

    Implemented equations (the OCR of (5.3)-(5.12) is garbled; these are the laws for which the
    Lyapunov argument (5.11)-(5.14) holds, and they agree with every legible line of the text):

    - model (5.3): x̂̇_1 = α_1 x_1 + Σ_{i≥2} x̂_i + β_1 u − λ_1 (x̂_1 − x_1),
      x̂̇_i = α_i x_1 − λ_i x̂_i + β_i u + w_i  (i = 2..n);
    - filters (5.6): v̇_i = −λ_i v_i + x_1, ṡ_i = −λ_i s_i + u (i = 2..n), v(0) = s(0) = 0, so that
      v_i = [p + λ_i]⁻¹ x_1 and s_i = [p + λ_i]⁻¹ u;
    - stabilising signals (5.5) w_i = v_i φ̇_i + s_i ψ̇_i, which with the laws below is (5.7):
      w_i = −(c_i v_i² + d_i s_i²) e_1;
    - adaptive laws (5.12): α̇_1 = −c_1 e_1 x_1, β̇_1 = −d_1 e_1 u, α̇_i = −c_i e_1 v_i, β̇_i = −d_i e_1 s_i,
      with e_1 = x̂_1 − x_1 = x̂_1 − y.

    With (5.5) the unmeasured errors integrate to (5.9): e_i = v_i φ_i + s_i ψ_i + e^{−λ_i t} e_i(0)
    (φ = α − a, ψ = β − b), and the Lyapunov function (5.11)
    V = ½ e_1² + ½ Σ (φ_i²/c_i + ψ_i²/d_i) obeys (5.13) V̇ = −λ_1 e_1² + e_1 f(t),
    f(t) = Σ_{i≥2} e^{−λ_i t} e_i(0): it is non-increasing whenever x̂_i(0) = x_i(0) for i ≥ 2.

    **Arguments:**

    - `n`: plant order (static).
    - `lambdas`: (λ_1, ..., λ_n), all > 0: λ_1 the observer's output-injection gain, λ_2..λ_n the known
      Λ of (5.2) (they must equal the plant's).  Differentiable leaves.
    - `c`, `d`: adaptation rates (c_1..c_n) and (d_1..d_n) of (5.12), > 0 (scalars are broadcast).
    - `a0`, `b0`: initial estimates α(0), β(0) (default zeros).

    ``parameters(z)`` returns (α, β), the estimates of (a, b) of (5.2).

    **Example:**::

        plant = obsjax.luders_narendra_form(a=[-1., -1.], b=[1., -1.], lambdas=[1., .5])
        obs = obsjax.LudersNarendra(2, lambdas=[1., .5], c=[28., 21.], d=[5., 5.])
        u = obsjax.signals.multisine([1., 1.], [.5, 3.])
        traj = obsjax.simulate(plant, obs, jnp.ones(2), jnp.array([0., 1.]), jnp.linspace(0., 200., 401), u=u)
        alpha, beta = obs.parameters(traj.z)           # → (-1, -1) and (1, -1)
    """

    lambdas: jax.Array
    c: jax.Array
    d: jax.Array
    a0: jax.Array
    b0: jax.Array
    n: int = eqx.field(static=True)

    def __init__(self, n, lambdas, c, d, *, a0=None, b0=None):
        n = state_dimension(n)
        if n < 1:
            raise ValueError(f"`n` (the plant order) must be >= 1, got {n}.")
        self.n = n
        self.lambdas = vector(lambdas, "lambdas", n)
        positive_scalar(self.lambdas, "lambdas")
        self.c = _rates(c, "c", n)
        self.d = _rates(d, "d", n)
        self.a0 = jnp.zeros(n) if a0 is None else require_finite(vector(a0, "a0", n), "a0")
        self.b0 = jnp.zeros(n) if b0 is None else require_finite(vector(b0, "b0", n), "b0")

    def prepare(self):
        """Guards that survive ``jit`` (``eqx.error_if``): λ_i, c_i, d_i finite and > 0."""
        return eqx.tree_at(
            lambda o: (o.lambdas, o.c, o.d),
            self,
            (
                positive_scalar(self.lambdas, "lambdas"),
                positive_scalar(self.c, "c"),
                positive_scalar(self.d, "d"),
            ),
        )

    def check(self):
        positive_scalar(self.lambdas, "lambdas")
        positive_scalar(self.c, "c")
        positive_scalar(self.d, "d")
        return self

    def init(self, t0, xhat0, y0):
        n = self.n
        xhat0 = jnp.asarray(xhat0, dtype=float)
        if xhat0.shape != (n,):
            raise ValueError(f"`xhat0` must have shape ({n},), got {tuple(xhat0.shape)}.")
        zeros = jnp.zeros(n - 1)
        return LudersNarendraState(xhat0, self.a0, self.b0, zeros, zeros)

    def vector_field(self, t, z: LudersNarendraState, y, u):
        x1 = siso_signal(y, "y", "LudersNarendra")
        u = siso_signal(u, "u", "LudersNarendra")
        lam1, lam = self.lambdas[0], self.lambdas[1:]
        c1, cb = self.c[0], self.c[1:]
        d1, db = self.d[0], self.d[1:]
        e1 = z.xhat[0] - x1
        w = -(cb * z.v**2 + db * z.s**2) * e1  # (5.7)
        dx1 = z.alpha[0] * x1 + jnp.sum(z.xhat[1:]) + z.beta[0] * u - lam1 * e1  # (5.3), row 1
        dxi = z.alpha[1:] * x1 - lam * z.xhat[1:] + z.beta[1:] * u + w  # (5.3), rows 2..n
        dv = -lam * z.v + x1  # (5.6a)
        ds = -lam * z.s + u  # (5.6b)
        dalpha = -e1 * jnp.concatenate([(c1 * x1)[None], cb * z.v])  # (5.12)
        dbeta = -e1 * jnp.concatenate([(d1 * u)[None], db * z.s])  # (5.12)
        return LudersNarendraState(jnp.concatenate([dx1[None], dxi]), dalpha, dbeta, dv, ds)

    def estimate(self, t, z: LudersNarendraState, y):
        return z.xhat

    def parameters(self, z: LudersNarendraState):
        """Current (α, β): the estimates of (a, b) of (5.2) (works on a trajectory too)."""
        return z.alpha, z.beta

    def lyapunov(self, z: LudersNarendraState, y, a, b):
        """V of (5.11) for the true (a, b): ½ e_1² + ½ Σ (φ_i²/c_i + ψ_i²/d_i) (vectorised over time)."""
        e1 = z.xhat[..., 0] - jnp.asarray(y).reshape(z.xhat.shape[:-1])
        phi = z.alpha - jnp.asarray(a)
        psi = z.beta - jnp.asarray(b)
        return 0.5 * e1**2 + 0.5 * jnp.sum(phi**2 / self.c + psi**2 / self.d, axis=-1)


def _rates(x, name, n):
    arr = as_float_array(x, name)
    if arr.ndim == 0:
        arr = jnp.full((n,), arr)
    arr = vector(arr, name, n)
    positive_scalar(arr, name)  # finite and > 0, elementwise
    return arr
