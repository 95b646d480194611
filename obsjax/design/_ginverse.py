"""Matrix {1}-inverses and the Lovass-Nagy design of T(t) (Chaisanguanmitt, slides on generalized inverses).

A {1}-inverse X of a matrix C (size m × n) is any n × m matrix with C X C = C.  The Moore–Penrose inverse C⁺
is one; all of them are

    X = C⁺ + (I − C⁺C) Y + Z (I − CC⁺),        Y, Z arbitrary n × m.

(Given a {1}-inverse X, take Y = X − C⁺ and Z = C⁺C(X − C⁺): the formula returns X.)

The Lovass-Nagy observers need G with G C = M for a given M (slides, full-state (9), reduced (12)).  The
equation is solvable iff M (I − XC) = 0, and then G = M X.  Note that I − XC is a projector onto null(C)
for *every* {1}-inverse X, so the solvability condition does not depend on the choice of X; the choice only
selects which of the (then many) solutions G is used.  :func:`solvability_residual` computes M (I − XC).

:func:`lovass_nagy_T` solves the design condition for the unspecified entries of T(t): the user gives the
block S(t) = T(t) N on the null space of C (N an orthonormal basis of null(C)), and the rest of T is
found algebraically.  See its docstring for the derivation.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array, concrete_value, matrix


def moore_penrose(C) -> jax.Array:
    """Moore–Penrose inverse C⁺ of an (m, n) matrix: the {1,2,3,4}-inverse.

    **Arguments:**

    - `C`: (m, n) matrix.

    **Returns:** the (n, m) matrix C⁺ (``jnp.linalg.pinv``, differentiable where the rank is constant).

    **Example:** the slides' C = A12 = [[0, 1], [0, 1]] gives C⁺ = [[0, 0], [0.5, 0.5]], the C^{1} they
    chose::

        obsjax.design.moore_penrose([[0., 1.], [0., 1.]])
    """
    C = matrix(C, "C", (None, None))
    return jnp.linalg.pinv(C)


def one_inverse(C, Y=None, Z=None) -> jax.Array:
    """A {1}-inverse of C from the general family (slides, "The mathematical background").

        X = C⁺ + (I − C⁺C) Y + Z (I − CC⁺),     so that  C X C = C,

    which parametrises every {1}-inverse of C.  ``Y = Z = None`` gives the Moore–Penrose choice C⁺.

    **Arguments:**

    - `C`: (m, n) matrix.
    - `Y`, `Z`: optional (n, m) free parameters.

    **Returns:** the (n, m) matrix X.

    **Example:**

        C = jnp.array([[0., 1.], [0., 1.]])
        X = obsjax.design.one_inverse(C, Y=jnp.ones((2, 2)))
        assert jnp.allclose(C @ X @ C, C)
    """
    C = matrix(C, "C", (None, None))
    m, n = C.shape
    Cp = jnp.linalg.pinv(C)
    X = Cp
    if Y is not None:
        Y = matrix(Y, "Y", (n, m))
        X = X + (jnp.eye(n, dtype=C.dtype) - Cp @ C) @ Y
    if Z is not None:
        Z = matrix(Z, "Z", (n, m))
        X = X + Z @ (jnp.eye(m, dtype=C.dtype) - C @ Cp)
    return X


def is_one_inverse(X, C, rtol: float = 1e-9) -> bool:
    """True when ‖C X C − C‖ ≤ rtol · max(1, ‖C‖) (Frobenius norms; concrete inputs)."""
    C = matrix(C, "C", (None, None))
    X = matrix(X, "X", (C.shape[1], C.shape[0]))
    err = float(jnp.linalg.norm(C @ X @ C - C))
    return err <= rtol * max(1.0, float(jnp.linalg.norm(C)))


def solvability_residual(M, C, C1=None) -> jax.Array:
    """Residual M (I − C^{1} C) of the equation G C = M (slides, step 3 of the Lovass-Nagy procedure).

    G C = M has a solution G iff the residual is zero; then G = M C^{1}.  The residual is the same for
    every {1}-inverse C^{1} (I − C^{1}C projects onto null(C)).

    **Arguments:** `M` (q, n); `C` (m, n); `C1` (n, m) a {1}-inverse of C (Moore–Penrose when ``None``).

    **Returns:** the (q, n) residual.
    """
    C = matrix(C, "C", (None, None))
    m, n = C.shape
    M = matrix(M, "M", (None, n))
    C1 = jnp.linalg.pinv(C) if C1 is None else matrix(C1, "C1", (n, m))
    return M @ (jnp.eye(n, dtype=M.dtype) - C1 @ C)


def null_space_basis(C, rtol: float | None = None) -> np.ndarray:
    """Orthonormal basis N (n, k) of null(C) for a concrete (m, n) matrix, each column's largest-magnitude
    entry made positive (so that e.g. null([[0, 1], [0, 1]]) = [[1], [0]])."""
    Cn = concrete_value(matrix(C, "C", (None, None)))
    if Cn is None:
        raise ValueError("`C` must be concrete (not traced) to compute its null-space basis.")
    m, n = Cn.shape
    _u, s, vt = np.linalg.svd(Cn)
    tol = (rtol if rtol is not None else max(m, n) * np.finfo(float).eps) * (
        s[0] if s.size else 0.0
    )
    rank = int(np.sum(s > tol))
    N = vt[rank:].T.copy()
    for j in range(N.shape[1]):
        i = int(np.argmax(np.abs(N[:, j])))
        if N[i, j] < 0:
            N[:, j] = -N[:, j]
    return N


def _as_time_fn(A, name):
    if callable(A):
        return A
    A = as_float_array(A, name)
    return lambda t: A


class LovassNagyT(eqx.Module):
    """T(t) = S(t) Nᵀ + Q(t) K(t)⁺, the completion built by :func:`lovass_nagy_T` (call it with t)."""

    A: Callable
    F: jax.Array
    S: Callable
    N: jax.Array

    def _S(self, t):
        s = jnp.asarray(self.S(t))
        return s.reshape(s.shape[0], -1)

    def K(self, t):
        """K(t) = (I − NNᵀ) Ā(t) N, which must have full column rank k."""
        N = self.N
        P = jnp.eye(N.shape[0], dtype=N.dtype) - N @ N.T
        return P @ jnp.asarray(self.A(t)) @ N

    def __call__(self, t):
        t = jnp.asarray(t, dtype=self.N.dtype)
        N = self.N
        S = self._S(t)
        Sdot = jax.jacfwd(self._S)(t)
        K = self.K(t)
        Q = self.F @ S - Sdot - S @ (N.T @ jnp.asarray(self.A(t)) @ N)
        # R = Q K⁺ with K⁺ = (KᵀK)⁻¹Kᵀ (K has full column rank): smooth in t, so Ṫ and T̈ exist.
        R = jnp.linalg.solve(K.T @ K, Q.T).T @ K.T
        return S @ N.T + R


def lovass_nagy_T(A, C, F, S, *, N=None, t0: float = 0.0) -> LovassNagyT:
    """Solve the Lovass-Nagy condition for the unspecified entries of T(t).

    The design equation (slides, full-state (9); reduced form derived in
    :class:`obsjax.GeneralizedInverseReduced`) is

        M(t) := Ṫ + T Ā − F T = G C,     solvable iff  M (I − C^{1} C) = 0,

    with Ā = A (full-state, T n × n) or Ā = A22 and C = A12 (reduced order, T (n−m) × (n−m)).  Let N (k
    columns) be an orthonormal basis of null(C) (C constant), so that I − C^{1}C and NNᵀ have the same
    null space and the condition reads M N = 0.  Write T = S Nᵀ + R with S = T N (the entries of T the
    user specifies, any twice-differentiable functions of t) and R N = 0.  Since Ṫ N = Ṡ,

        M N = Ṡ + S NᵀĀN + R K − F S,     K := (I − NNᵀ) Ā N,

    so M N = 0 is the linear equation R K = Q := F S − Ṡ − S NᵀĀN.  When K(t) has full column rank k
    (checked at t0), R = Q K⁺ solves it exactly, and R N = 0 holds because the rows of K⁺ lie in
    range(I − NNᵀ).  No integration is needed; det T ≠ 0 (step 4) is then a condition on the choice of S,
    checked by the observers over their horizon.

    For the slides' 4th-order example (C = A12 = [[0, 1], [0, 1]], N = e1, F = −5 I, Ā = A22 =
    [[−5, 0], [−4/β, 0]]) this gives T = [S, β Ṡ / 4]: the first column of T is free, the second follows.

    **Arguments:**

    - `A`: Ā as an (q', q') matrix or a callable of t (A(t) for the full-state observer, A22(t) for the
      reduced one).
    - `C`: the constant measurement matrix of the design (C, or A12 for the reduced observer).
    - `F`: (q, q) observer matrix (a leaf: T follows F when F is differentiated).
    - `S`: callable t -> (q, k) (or (q,) when k = 1), the free block T(t) N; it must be differentiable
      twice (Ṫ uses Ṡ, and the reduced observer needs Ġ, hence T̈).
    - `N`: optional basis of null(C) (orthonormal columns); default :func:`null_space_basis`.
    - `t0`: time at which the rank of K is checked.

    **Returns:** a callable module ``T(t)`` (its leaves include F).

    **Example:** the slides' reduced-order example::

        beta = lambda t: 0.4 * jnp.cos(0.3 * t) - 0.5
        A22 = lambda t: jnp.array([[-5.0, 0.0], [-4.0 / beta(t), 0.0]])
        T = obsjax.design.lovass_nagy_T(A22, [[0., 1.], [0., 1.]], -5 * jnp.eye(2),
                                        lambda t: jnp.stack([jnp.cos(t), jnp.sin(t)]))
    """
    C = matrix(C, "C", (None, None))
    n_ = C.shape[1]
    A_fn = _as_time_fn(A, "A")
    A0 = jnp.asarray(A_fn(jnp.asarray(t0)))
    if A0.shape != (n_, n_):
        raise ValueError(
            f"`A` must be ({n_}, {n_}) to match `C` of shape {tuple(C.shape)}, got {A0.shape}."
        )
    if N is None:
        N = null_space_basis(C)
    N = matrix(N, "N", (n_, None))
    k = N.shape[1]
    if k == 0:
        raise ValueError(
            "`C` has full column rank: null(C) = {0}, every T satisfies the condition."
        )
    Nc = concrete_value(N)
    Cc = concrete_value(C)
    if Nc is not None and Cc is not None:
        if np.linalg.norm(Cc @ Nc) > 1e-9 * max(1.0, np.linalg.norm(Cc)):
            raise ValueError(f"`N` must span null(C): ‖C N‖ = {np.linalg.norm(Cc @ Nc):.3e}.")
        if np.linalg.norm(Nc.T @ Nc - np.eye(k)) > 1e-9:
            raise ValueError("`N` must have orthonormal columns (NᵀN = I).")
    F = as_float_array(F, "F")
    S0 = jnp.asarray(S(jnp.asarray(t0)))
    q = S0.shape[0]
    S0 = S0.reshape(q, -1)
    if S0.shape[1] != k:
        raise ValueError(
            f"`S(t)` must return ({q}, {k}) (k = dim null(C) = {k}), got {tuple(S0.shape)}."
        )
    F = matrix(F, "F", (q, q))
    if q != n_:
        raise ValueError(f"`S(t)` must have {n_} rows (T is square, {n_} × {n_}), got {q}.")
    T = LovassNagyT(A=A_fn, F=F, S=S, N=N)
    Kc = concrete_value(T.K(jnp.asarray(t0)))
    if Kc is not None:
        sv = np.linalg.svd(Kc, compute_uv=False)
        if sv.size < k or sv[-1] <= 1e-10 * max(1.0, np.abs(Kc).max()):
            raise ValueError(
                f"K = (I − NNᵀ)·A·N must have full column rank {k} at t = {t0} for the algebraic "
                f"completion of T, found singular values {sv.tolist()}; choose other free entries "
                f"(another N) or solve the condition as a differential equation."
            )
    return T
