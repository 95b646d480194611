"""Continuous identification of a constant vector from αᵀ(t) K = b(t) (Hassan thesis, section 4.2)."""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from ._adaptive_common import check_gain, gain_array, solve_gain, traced_positive, state_dimension
from ._base import AbstractObserver


class LeastSquaresIdentifierState(eqx.Module):
    """State of :class:`LeastSquaresIdentifier`: the estimate K̂."""

    K: jax.Array  # (n,)


class LeastSquaresIdentifier(AbstractObserver):
    r"""Continuous identification law of the thesis's section 4.2, (4.1)-(4.2).

    The algebraic equation (4.1) αᵀ(t) K = b(t) holds for t ≥ t0 with α(t) ∈ R^{n×m} (Rⁿ when m = 1) and
    b(t) ∈ R^m bounded and piecewise continuous, and K ∈ Rⁿ constant and unknown.  **As printed** (approach
    (b) of the text), with a rate Γ in place of its unit gain:

        K̂̇ = −Γ [α(t) αᵀ(t) K̂ − α(t) b(t)]      (4.2)

    the steepest descent of the squared equation error ½‖αᵀK̂ − b‖² (Γ = 1 is the printed law; the text's
    "least-squares" law is this gradient form, it carries no covariance matrix).  The error
    K̃ = K̂ − K obeys K̃̇ = −Γ α αᵀ K̃, the first class of (4.21) with B = Γ^{1/2} α: V = ½ K̃ᵀΓ⁻¹K̃ has
    V̇ = −‖αᵀK̃‖² ≤ 0 (:meth:`lyapunov`), and K̂ → K uniformly and exponentially if and only if α is
    persistently exciting (:func:`obsjax.analysis.morgan_narendra` gives the richness constants, the
    worst-case rate over its windows and a rate guaranteed by the gramians alone).  When α is not, wᵀΓ⁻¹K̃ stays constant for every direction w with αᵀ(t) w ≡ 0 (d/dt wᵀΓ⁻¹K̃ = −(αᵀw)(αᵀK̃) = 0; the component wᵀK̃ itself is constant only for a scalar Γ).

    In ``obsjax.simulate`` the unknown K is the state of the plant ẋ = 0, y = αᵀ(t, u) x
    (:meth:`plant` builds it), the measurement y is b(t), and ``Trajectory.error`` is K̂ − K.

    **Arguments:**

    - `n`: dimension of K (static).
    - `regressor`: a callable ``regressor(t, u)`` returning α(t): shape (n,) for a scalar equation, (n, m) for
      m equations; it may use the input u (pass ``u=`` to ``simulate``) or ignore it.
    - `Gamma`: adaptation rate, a scalar, an (n,) diagonal or an (n, n) symmetric positive definite matrix
      (a differentiable leaf).

    ``init`` takes K̂(t0) from ``xhat0``.

    **Example:**::

        alpha = lambda t, u: jnp.array([1.0, jnp.sin(t), jnp.cos(2 * t)])
        ident = obsjax.LeastSquaresIdentifier(3, alpha, Gamma=1.0)
        K = jnp.array([1.0, -2.0, 0.5])
        traj = obsjax.simulate(ident.plant(), ident, K, jnp.zeros(3), jnp.linspace(0., 60., 601))
        traj.error_norm[-1]                                             # ‖K̂ − K‖ ≈ 7e-6

    A larger Γ is not always faster: for ẋ = −Γααᵀx the fast directions settle on the instantaneous null space
    of αᵀ and the slow ones then move at a rate that falls with Γ (here Γ = 2 and 5 are slower than Γ = 1).
    """

    regressor: Callable
    Gamma: jax.Array
    n: int = eqx.field(static=True)

    def __init__(self, n, regressor, Gamma=1.0):
        n = state_dimension(n)
        if n < 1:
            raise ValueError(f"`n` (the dimension of K) must be >= 1, got {n}.")
        if not callable(regressor):
            raise ValueError(  # noqa: TRY004 (bad input is a ValueError throughout obsjax)
                f"`regressor` must be a callable (t, u) -> α(t) of shape ({n},) or ({n}, m), "
                f"got {type(regressor).__name__}."
            )
        self.n = n
        self.regressor = regressor
        self.Gamma = gain_array(Gamma, "Gamma", n)

    def alpha(self, t, u):
        """α(t) as an (n, m) matrix, its shape checked."""
        a = jnp.asarray(self.regressor(t, u))
        if jnp.issubdtype(a.dtype, jnp.complexfloating):
            raise ValueError(f"`regressor(t, u)` must return real values, got dtype {a.dtype}.")
        if a.ndim == 1:
            a = a[:, None]
        if a.ndim != 2 or a.shape[0] != self.n:
            raise ValueError(
                f"`regressor(t, u)` must return an array of shape ({self.n},) or ({self.n}, m), "
                f"got {tuple(a.shape)}."
            )
        return a

    def plant(self, p: int = 0):
        """The plant ẋ = 0, y = αᵀ(t, u) x whose constant state is K (p inputs, default none)."""
        from ..systems._plants import Nonlinear

        p = int(p)
        m = jax.eval_shape(lambda t, u: self.alpha(t, u), 0.0, jnp.zeros(p)).shape[1]
        return Nonlinear(_ConstantState(), _RegressorOutput(self), self.n, m, p)

    def prepare(self):
        """Guard that survives ``jit`` (``eqx.error_if``): Γ positive (definite)."""
        return eqx.tree_at(lambda o: o.Gamma, self, traced_positive(self.Gamma, "Gamma"))

    def check(self):
        check_gain(self.Gamma, "Gamma")
        return self

    def init(self, t0, xhat0, y0):
        xhat0 = jnp.asarray(xhat0, dtype=float)
        if xhat0.shape != (self.n,):
            raise ValueError(
                f"`xhat0` (K̂(t0)) must have shape ({self.n},), got {tuple(xhat0.shape)}."
            )
        return LeastSquaresIdentifierState(xhat0)

    def vector_field(self, t, z: LeastSquaresIdentifierState, y, u):
        alpha = self.alpha(t, u)
        y = jnp.asarray(y)
        if y.size != alpha.shape[1]:
            raise ValueError(
                f"LeastSquaresIdentifier: the measurement has {y.size} output(s) but `regressor(t, u)` has "
                f"m = {alpha.shape[1]} column(s) (y = αᵀK): the data and the regressor must agree."
            )
        b = y.reshape(alpha.shape[1])
        grad = alpha @ (alpha.T @ z.K - b)
        G = jnp.asarray(self.Gamma)
        dK = G @ grad if G.ndim == 2 else G * grad  # (4.2)
        return LeastSquaresIdentifierState(-dK)

    def estimate(self, t, z: LeastSquaresIdentifierState, y):
        return z.K

    def lyapunov(self, z: LeastSquaresIdentifierState, K):
        """V = ½ K̃ᵀ Γ⁻¹ K̃, K̃ = K̂ − K (vectorised over a leading time axis)."""
        Kt = z.K - jnp.asarray(K)
        if Kt.ndim == 1:
            return 0.5 * Kt @ solve_gain(self.Gamma, Kt)
        return 0.5 * jnp.sum(Kt * jax.vmap(lambda k: solve_gain(self.Gamma, k))(Kt), axis=-1)


class _ConstantState(eqx.Module):
    """ẋ = 0: the unknown K of (4.1) as a plant state."""

    def __call__(self, t, x, u):
        return jnp.zeros_like(x)


class _RegressorOutput(eqx.Module):
    """y = αᵀ(t, u) x = b(t) of (4.1) (a module, so that regressors with array leaves share compilations)."""

    identifier: LeastSquaresIdentifier

    def __call__(self, t, x, u):
        return self.identifier.alpha(t, u).T @ x
