"""The Luenberger family for LTI plants (Hassan thesis, chapters 2 and 3)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array, concrete_value, matrix, require_finite, vector
from ..analysis._lti import is_observable
from ..design._place import _check_poles, choose_reduction, observability_indices, place
from ..systems._plants import LTI
from ._base import AbstractObserver


def _require_lti(model, who):
    if not isinstance(model, LTI):
        raise ValueError(f"{who} needs an obsjax.LTI model, got {type(model).__name__}.")


class Luenberger(AbstractObserver):
    """Identity (full-order) observer, thesis (2.7):

        ż = (A − L C) z + L y + B u − L D u,      x̂ = z.

    The error x̃ = x̂ − x obeys dx̃/dt = (A − LC) x̃ (Theorem 1 with T = I).

    **Arguments:** `model` (an :class:`obsjax.LTI`, the observer's own model of the plant); `L` (n, m) gain.
    Use :meth:`from_poles` to design L by pole placement; the poles then are the differentiable leaf
    (``tune(..., where=lambda o: o.poles)``) and L is recomputed by :func:`obsjax.design.place` once per
    simulation.

    **Example:** thesis example (2.8)::

        plant = obsjax.LTI([[-2., 1.], [0., -1.]], [[0.], [1.]], [[1., 0.]])
        obs = obsjax.Luenberger.from_poles(plant, [-3., -3.])
        obs.gain   # [[3.], [4.]]
    """

    model: LTI
    L: jax.Array | None
    poles: jax.Array | None
    reduction: int = eqx.field(static=True, default=0)

    def __init__(self, model, L=None, poles=None, reduction=0):
        _require_lti(model, "Luenberger")
        if (L is None) == (poles is None):
            raise ValueError("Luenberger needs exactly one of `L` (a gain) or `poles` (use from_poles).")
        self.model = model
        self.L = None if L is None else require_finite(matrix(L, "L", (model.n, model.m)), "L")
        self.poles = None if poles is None else _check_poles(poles, model.n)
        self.reduction = int(reduction)

    @classmethod
    def from_poles(cls, model, poles) -> "Luenberger":
        """Observer with eig(A − LC) = ``poles`` (the poles are the tunable leaf)."""
        _require_lti(model, "Luenberger.from_poles")
        A, C = concrete_value(model.A), concrete_value(model.C)
        if A is not None and C is not None and not is_observable(A, C):
            raise ValueError("(A, C) of `model` is not observable: the observer poles cannot be placed.")
        red = choose_reduction(A, C) if (A is not None and C is not None) else 0
        return cls(model, poles=poles, reduction=red)

    @property
    def gain(self) -> jax.Array:
        """The gain L (computed from the poles when designed by placement)."""
        if self.L is not None:
            return self.L
        return place(self.model.A, self.model.C, self.poles, reduction=self.reduction)

    def prepare(self):
        if self.L is not None:
            return self
        return eqx.tree_at(lambda o: o.L, self, self.gain, is_leaf=lambda x: x is None)

    @property
    def observer_matrix(self) -> jax.Array:
        """F = A − L C."""
        return self.model.A - self.gain @ self.model.C

    def init(self, t0, xhat0, y0):
        return vector(xhat0, "xhat0", self.model.n)

    def vector_field(self, t, z, y, u):
        M = self.model
        L = self.gain
        return M.A @ z + M.B @ u + L @ (y - M.C @ z - M.D @ u)

    def estimate(self, t, z, y):
        return z


def _complement(C):
    """Rows D completing C to a nonsingular M = [C; D] (orthonormal basis of the null space of C)."""
    C = np.asarray(C)
    _, s, vt = np.linalg.svd(C)
    r = int(np.sum(s > 1e-12 * max(1.0, s[0])))
    if r < C.shape[0]:
        raise ValueError(f"`C` must have full row rank m = {C.shape[0]} for a reduced-order observer, got rank {r}.")
    return vt[r:]


class ReducedOrder(AbstractObserver):
    """Reduced-order observer of order n − m, thesis (2.13)-(2.16).

    With M = [C; D] nonsingular and x̄ = M x = [y; w], the plant reads
    ẏ = A11 y + A12 w + B1 u, ẇ = A21 y + A22 w + B2 u (2.13).  The observer (2.15)-(2.16) is

        ż = (A22 − G A12) z + [(A22 − G A12) G + A21 − G A11] y + (B2 − G B1) u,
        ŵ = z + G y,      x̂ = M⁻¹ [y; ŵ],

    so that ŵ − w obeys d/dt(ŵ − w) = (A22 − G A12)(ŵ − w) without differentiating y.

    **Arguments:** `model` (LTI with D = 0), `G` ((n−m), m) gain or `poles` (n − m of them), `Dc`
    ((n−m), n) rows completing C (an orthonormal null-space basis of C when ``None``).

    **Example:** the thesis plant (2.8) with pole −3 gives G = 2 (A22 − G A12 = −1 − G).
    """

    model: LTI
    G: jax.Array | None
    poles: jax.Array | None
    Dc: jax.Array

    def __init__(self, model, G=None, poles=None, Dc=None):
        _require_lti(model, "ReducedOrder")
        n, m = model.n, model.m
        if m >= n:
            raise ValueError(f"ReducedOrder needs fewer outputs than states, got m = {m}, n = {n}.")
        Dv = concrete_value(model.D)
        if Dv is not None and np.any(Dv != 0):
            raise ValueError("ReducedOrder needs a model without feedthrough (D = 0).")
        if (G is None) == (poles is None):
            raise ValueError("ReducedOrder needs exactly one of `G` (a gain) or `poles`.")
        if Dc is None:
            Cv = concrete_value(model.C)
            if Cv is None:
                raise ValueError("`Dc` must be given when the model's C is traced.")
            Dc = _complement(Cv)
        Dc = require_finite(matrix(Dc, "Dc", (n - m, n)), "Dc")
        Mv = concrete_value(jnp.concatenate([model.C, Dc]))
        if Mv is not None and abs(np.linalg.det(Mv)) < 1e-12:
            raise ValueError("M = [C; Dc] must be nonsingular: `Dc` does not complete `C`.")
        self.model, self.Dc = model, Dc
        self.G = None if G is None else require_finite(matrix(G, "G", (n - m, m)), "G")
        self.poles = None if poles is None else _check_poles(poles, n - m)

    @classmethod
    def from_poles(cls, model, poles, Dc=None) -> "ReducedOrder":
        """Reduced-order observer with eig(A22 − G A12) = ``poles`` (n − m poles)."""
        return cls(model, poles=poles, Dc=Dc)

    def _blocks(self):
        M = jnp.concatenate([self.model.C, self.Dc])
        Minv = jnp.linalg.inv(M)
        Ab = M @ self.model.A @ Minv
        Bb = M @ self.model.B
        m = self.model.m
        return M, Minv, Ab[:m, :m], Ab[:m, m:], Ab[m:, :m], Ab[m:, m:], Bb[:m], Bb[m:]

    @property
    def gain(self):
        if self.G is not None:
            return self.G
        _, _, _, A12, _, A22, _, _ = self._blocks()
        return place(A22, A12, self.poles)

    def prepare(self):
        if self.G is not None:
            return self
        return eqx.tree_at(lambda o: o.G, self, self.gain, is_leaf=lambda x: x is None)

    def init(self, t0, xhat0, y0):
        M, _, *_ = self._blocks()
        w0 = (M @ vector(xhat0, "xhat0", self.model.n))[self.model.m :]
        return w0 - self.gain @ y0

    def vector_field(self, t, z, y, u):
        _, _, A11, A12, A21, A22, B1, B2 = self._blocks()
        G = self.gain
        F = A22 - G @ A12
        return F @ z + (F @ G + A21 - G @ A11) @ y + (B2 - G @ B1) @ u

    def estimate(self, t, z, y):
        _, Minv, *_ = self._blocks()
        return Minv @ jnp.concatenate([y, z + self.gain @ y])


def _companion(coeffs):
    """Observer-companion matrix F (r, r) with characteristic polynomial coeffs = [1, c1, …, cr]."""
    r = coeffs.shape[0] - 1
    F = jnp.zeros((r, r), coeffs.dtype)
    if r > 1:
        F = F.at[1:, :-1].set(jnp.eye(r - 1, dtype=coeffs.dtype))
    return F.at[:, -1].set(-coeffs[1:][::-1])


class FunctionalObserver(AbstractObserver):
    """Observer of a single linear functional s = aᵀx with ν − 1 arbitrary poles (thesis §3.3, Theorem II).

    ν is the observability index (thesis §3.2).  The observer of order r = ν − 1 is

        ż = F z + G y + T B u,      ŝ = kᵀ z + eᵀ y,

    with T A − F T = G C (Theorem 1, (2.4)) and aᵀ = kᵀ T + eᵀ C, so that ŝ − s = kᵀ e^{Ft}(z(0) − T x(0)).
    F is the observer-companion matrix of the requested poles and k = e_r; the linear conditions are
    solved for (T, G, e) by least squares, and a residual above 1e-8 raises ``ValueError`` (the functional
    is not observable with that order).  When ν = 1 (r = 0) the functional is a static map of y.

    ``estimate`` returns ŝ (shape (1,)) and ``target(t, x) = aᵀx``, so ``Trajectory.error`` is ŝ − aᵀx.

    **Arguments:** `model` (LTI, D = 0), `a` (n,) the functional, `poles` (ν − 1 of them; default
    from_poles picks the order).  T, G, e are computed at construction from concrete values.
    """

    model: LTI
    a: jax.Array
    F: jax.Array
    T: jax.Array
    G: jax.Array
    k: jax.Array
    e: jax.Array

    def __init__(self, model, a, poles):
        _require_lti(model, "FunctionalObserver")
        A, B, C = (concrete_value(M) for M in (model.A, model.B, model.C))
        if A is None:
            raise ValueError("FunctionalObserver is designed from concrete model matrices (not under jit).")
        n, m = model.n, model.m
        a = require_finite(vector(a, "a", n), "a")
        nu = max(observability_indices(A, C))
        r = nu - 1
        poles = jnp.atleast_1d(jnp.asarray(poles))
        if poles.shape[0] != r:
            raise ValueError(
                f"`poles` must hold ν − 1 = {r} poles (observability index ν = {nu}), got {poles.shape[0]}."
            )
        from ..design._place import _charpoly

        if r > 0:
            _check_poles(poles, r)
            F = np.asarray(_companion(_charpoly(poles.astype(complex) if np.iscomplexobj(poles) else poles.astype(float))))
        else:
            F = np.zeros((0, 0))
        k = np.zeros(r)
        if r:
            k[-1] = 1.0
        # Unknowns: vec(T) (r n, row-major), vec(G) (r m), e (m).
        nT, nG = r * n, r * m
        rows, rhs = [], []
        # T A − F T − G C = 0 : entry (i, j)
        for i in range(r):
            for j in range(n):
                row = np.zeros(nT + nG + m)
                for l in range(n):
                    row[i * n + l] += A[l, j]
                for l in range(r):
                    row[l * n + j] -= F[i, l]
                for l in range(m):
                    row[nT + i * m + l] -= C[l, j]
                rows.append(row)
                rhs.append(0.0)
        # kᵀ T + eᵀ C = aᵀ
        av = np.asarray(a)
        for j in range(n):
            row = np.zeros(nT + nG + m)
            for i in range(r):
                row[i * n + j] += k[i]
            for l in range(m):
                row[nT + nG + l] += C[l, j]
            rows.append(row)
            rhs.append(av[j])
        Mx, b = np.array(rows), np.array(rhs)
        sol, *_ = np.linalg.lstsq(Mx, b, rcond=None)
        res = np.linalg.norm(Mx @ sol - b) / max(1.0, np.linalg.norm(b))
        if res > 1e-8:
            raise ValueError(
                f"The functional aᵀx cannot be observed with order ν − 1 = {r} and these poles "
                f"(residual {res:.2e} of TA − FT = GC, aᵀ = kᵀT + eᵀC)."
            )
        self.model = model
        self.a = a
        self.F = jnp.asarray(F)
        self.T = jnp.asarray(sol[:nT].reshape(r, n))
        self.G = jnp.asarray(sol[nT : nT + nG].reshape(r, m))
        self.k = jnp.asarray(k)
        self.e = jnp.asarray(sol[nT + nG :])

    @property
    def order(self) -> int:
        return self.F.shape[0]

    def init(self, t0, xhat0, y0):
        return self.T @ vector(xhat0, "xhat0", self.model.n)

    def vector_field(self, t, z, y, u):
        return self.F @ z + self.G @ y + self.T @ (self.model.B @ u)

    def estimate(self, t, z, y):
        return jnp.atleast_1d(self.k @ z + self.e @ y)

    def target(self, t, x):
        return jnp.atleast_1d(self.a @ x)
