"""Matrix {1}-inverses and the Lovass-Nagy design of T(t) (Chaisanguanmitt, slides on generalized inverses).

A {1}-inverse X of a matrix C (size m × n) is any n × m matrix with C X C = C.  The Moore–Penrose inverse C⁺
is one; all of them are

    X = C⁺ + (I − C⁺C) Y + Z (I − CC⁺),        Y, Z arbitrary n × m.

(Given a {1}-inverse X, take Y = X − C⁺ and Z = C⁺C(X − C⁺): the formula returns X.)

**Two misprints on the slides' background slide.**  They define a {1}-inverse by "XAX = A"; the defining
identity is A X A = A (X A X = X defines a {2}-inverse, and X A X = A is not even dimensionally consistent for
a non-square A).  They state that ẋ = A x + B u can be solved for u iff "(I − B^{1}B)(ẋ − A x) = 0"; the
correct condition is (I − B B^{1})(ẋ − A x) = 0 (B B^{1} is the n × n projector onto range(B); B^{1}B is
p × p and cannot multiply the n-vector ẋ − A x unless p = n).  :func:`input_solvability_residual` computes
the corrected residual; the tests check both identities and that the printed forms fail.

The Lovass-Nagy observers need G with G C = M for a given M (slides, full-state (9), reduced (12)).  The
equation is solvable iff M (I − XC) = 0, and then G = M X.  Note that I − XC is a projector onto null(C)
for *every* {1}-inverse X, so the solvability condition does not depend on the choice of X; the choice only
selects which of the (then many) solutions G is used.  :func:`solvability_residual` computes M (I − XC).

:func:`lovass_nagy_T` solves the design condition for the unspecified entries of T(t): the user gives the
block S(t) = T(t) N on the null space of C (N an orthonormal basis of null(C)), and the rest of T is
found algebraically.  See its docstring for the derivation.  That completion needs
rank((I − NNᵀ)ĀN) = dim null(C), which fails e.g. for a full-state observer of a 3-state, 1-output plant.

:func:`lovass_nagy_T_ode` takes the procedure's other route, valid for every pair: the condition
M (I − C^{1}C) = 0 says exactly that M = G C for some G (take G = M C^{1}), so every admissible T(t) solves
the matrix differential equation Ṫ = F T − T A + G(t) C(t) for some free G(t), and conversely.  The free
entries (G, F's entries above the diagonal, T(t0)) are then chosen to keep det T ≠ 0 (step 4), which is
checked on the horizon.  :class:`obsjax.GeneralizedInverseODE` integrates this equation together with the
observer.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg
import numpy as np

from .._checks import as_float_array, concrete_value, matrix, real_array
from ..analysis._lti import DEFAULT_TOL, relative_residuals


def _gmatrix(x, name, shape=(None, None)):
    """A real, non-empty matrix of the given shape; a concrete NaN or infinity is refused by name (under
    ``jit`` the result's status is the caller's: these functions return NaN for it, as pinv)."""
    arr = matrix(real_array(x, name), name, shape)
    if 0 in arr.shape:
        raise ValueError(f"`{name}` must not be empty, got shape {tuple(arr.shape)}.")
    v = concrete_value(arr)
    if v is not None and not np.all(np.isfinite(v)):
        raise ValueError(f"`{name}` must be finite (no NaN or inf), got {v.tolist()}.")
    return arr


def _check_one_inverse(X, C, name, what):
    """A ValueError when a concrete X (a user's {1}-inverse) is not a {1}-inverse of C."""
    if concrete_value(X) is not None and concrete_value(C) is not None and not is_one_inverse(X, C):
        raise ValueError(
            f"`{name}` is not a {{1}}-inverse of `{what}` ({what} {name} {what} ≠ {what}): the residual would be "
            f"that of another equation; pass a {{1}}-inverse (obsjax.design.one_inverse) or None (Moore–Penrose)."
        )


def moore_penrose(C) -> jax.Array:
    """Moore–Penrose inverse C⁺ of an (m, n) matrix: the {1,2,3,4}-inverse.

    **Arguments:**

    - `C`: (m, n) matrix.

    **Returns:** the (n, m) matrix C⁺ (``jnp.linalg.pinv``, differentiable where the rank is constant).

    **Example:** the slides' C = A12 = [[0, 1], [0, 1]] gives C⁺ = [[0, 0], [0.5, 0.5]], the C^{1} they
    chose::

        obsjax.design.moore_penrose([[0., 1.], [0., 1.]])
    """
    C = _gmatrix(C, "C")
    return jnp.linalg.pinv(C)


def one_inverse(C, Y=None, Z=None) -> jax.Array:
    """A {1}-inverse of C from the general family (slides, "The mathematical background").

        X = C⁺ + (I − C⁺C) Y + Z (I − CC⁺),     so that  C X C = C,

    which parametrises every {1}-inverse of C.  ``Y = Z = None`` gives the Moore–Penrose choice C⁺.
    (The slides print the defining identity as "X A X = A", a misprint for A X A = A.)

    **Arguments:**

    - `C`: (m, n) matrix.
    - `Y`, `Z`: optional (n, m) free parameters.

    **Returns:** the (n, m) matrix X.

    **Example:**

        C = jnp.array([[0., 1.], [0., 1.]])
        X = obsjax.design.one_inverse(C, Y=jnp.ones((2, 2)))
        assert jnp.allclose(C @ X @ C, C)
    """
    C = _gmatrix(C, "C")
    m, n = C.shape
    Cp = jnp.linalg.pinv(C)
    X = Cp
    if Y is not None:
        Y = _gmatrix(Y, "Y", (n, m))
        X = X + (jnp.eye(n, dtype=C.dtype) - Cp @ C) @ Y
    if Z is not None:
        Z = _gmatrix(Z, "Z", (n, m))
        X = X + Z @ (jnp.eye(m, dtype=C.dtype) - C @ Cp)
    return X


def is_one_inverse(X, C, rtol: float = 1e-9) -> bool:
    """True when ‖C X C − C‖ ≤ rtol · ‖C‖ + 4 (m + n) ε ‖C‖² ‖X‖ (Frobenius norms; concrete inputs).

    Relative to ‖C‖ (the test does not depend on C's units: a {1}-inverse of s C is X / s), with the
    rounding of the product C X C (of order ε ‖C‖² ‖X‖) allowed for at machine precision only: a large
    X does not loosen the test (with rtol · ‖C‖² ‖X‖, X = diag(1, 1e4) passed for C = diag(1, 1e-6),
    whose only {1}-inverse is diag(1, 1e6)).  Every X is a {1}-inverse of C = 0."""
    C = matrix(C, "C", (None, None))
    X = matrix(X, "X", (C.shape[1], C.shape[0]))
    err = float(jnp.linalg.norm(C @ X @ C - C))
    nc, nx = float(jnp.linalg.norm(C)), float(jnp.linalg.norm(X))
    if not np.isfinite(err):
        return False
    eps = float(np.finfo(np.asarray(C).dtype).eps)
    return err <= rtol * nc + 4 * sum(C.shape) * eps * nc * nc * nx


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
    if C1 is None:
        C1 = jnp.linalg.pinv(C)
    else:
        C1 = _gmatrix(C1, "C1", (n, m))
        _check_one_inverse(C1, C, "C1", "C")
    return M @ (jnp.eye(n, dtype=M.dtype) - C1 @ C)


def input_solvability_residual(B, v, B1=None) -> jax.Array:
    """Residual (I − B B^{1}) v of the equation B u = v (slides, background slide, corrected).

    For ẋ = A x + B u the input is recovered from v = ẋ − A x iff (I − B B^{1}) v = 0, and then u = B^{1} v
    is a solution (B B^{1} projects onto range(B) for every {1}-inverse B^{1}).  The slides print the
    condition as (I − B^{1}B)(ẋ − A x) = 0, which multiplies the n-vector v by a p × p matrix: a misprint.

    **Arguments:** `B` (n, p); `v` (n,) or (n, k); `B1` (p, n) a {1}-inverse of B (Moore–Penrose if ``None``).

    **Returns:** the residual, shaped like `v`.

    **Example:**

        B = jnp.array([[1.], [0.], [1.]])
        input_solvability_residual(B, B @ jnp.array([2.]))     # zeros: u = 2 recovers v
        input_solvability_residual(B, jnp.array([1., 0., 0.]))  # [0.5, 0, −0.5]: v ∉ range(B)
    """
    B = matrix(B, "B", (None, None))
    n, p = B.shape
    v = as_float_array(v, "v")
    if v.ndim not in (1, 2) or v.shape[0] != n:
        raise ValueError(f"`v` must have shape ({n},) or ({n}, k) to match `B` {tuple(B.shape)}, got {tuple(v.shape)}.")
    if B1 is None:
        B1 = jnp.linalg.pinv(B)
    else:
        B1 = _gmatrix(B1, "B1", (p, n))
        _check_one_inverse(B1, B, "B1", "B")
    return v - B @ (B1 @ v)


def null_space_basis(C, rtol: float | None = None) -> np.ndarray:
    """Orthonormal basis N (n, k) of null(C) for a concrete (m, n) matrix, each column's largest-magnitude
    entry made positive (so that e.g. null([[0, 1], [0, 1]]) = [[1], [0]]).

    A singular value counts as zero when it is at most rtol·σ₁, by default rtol = 10·max(m, n)·ε: the
    cut-off of :func:`moore_penrose` (``jnp.linalg.pinv``), so that the two agree on the rank of C and
    C⁺C = I − N Nᵀ."""
    Cn = concrete_value(_gmatrix(C, "C"))
    if Cn is None:
        raise ValueError("`C` must be concrete (not traced) to compute its null-space basis.")
    m, n = Cn.shape
    _u, s, vt = np.linalg.svd(Cn)
    tol = (rtol if rtol is not None else 10 * max(m, n) * np.finfo(float).eps) * (
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
        # R = Q K⁺ with K⁺ = R_K⁻¹ Q_Kᵀ from a thin QR of K (K has full column rank): smooth in t, so Ṫ
        # and T̈ exist.  The normal equations (KᵀK)⁻¹Kᵀ square cond(K): with states in units 1e4 and 1e-4
        # (cond K 1e8) they broke the design condition by 6-15 %.
        QK, RK = jnp.linalg.qr(K, mode="reduced")
        R = jax.scipy.linalg.solve_triangular(RK, Q.T, trans="T", lower=False).T @ QK.T
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
        # relative to ‖C‖ (an absolute floor let any N pass for C in small output units)
        if np.linalg.norm(Cc @ Nc) > 1e-9 * np.linalg.norm(Cc):
            raise ValueError(
                f"`N` must span null(C): ‖C N‖ = {np.linalg.norm(Cc @ Nc):.3e} against ‖C‖ = "
                f"{np.linalg.norm(Cc):.3e}."
            )
        dim = null_space_basis(Cc).shape[1]
        if k != dim:
            raise ValueError(
                f"`N` must span null(C), of dimension {dim} (n − rank C), got {k} column(s)."
            )
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
        # the package's rank mechanism: each column's residual outside the columns before it, relative
        # to ‖Ā‖ (K = (I − NNᵀ)ĀN has columns of norm ≤ ‖Ā‖), so the decision ignores the time unit
        a_norm = float(np.linalg.norm(np.asarray(A0), 2))
        res = np.asarray(relative_residuals(Kc.T, np.full(k, a_norm))) if Kc.shape[0] >= k else [0.0]
        if not np.min(res) > DEFAULT_TOL:
            raise ValueError(
                f"K = (I − NNᵀ)·A·N must have full column rank {k} at t = {t0} for the algebraic "
                f"completion of T; the smallest residual of a column outside those before it is "
                f"{np.min(res):.2e} relative to ‖A‖ (≤ {DEFAULT_TOL:.0e}); choose other free entries "
                f"(another N) or solve the condition as a differential equation "
                f"(obsjax.design.lovass_nagy_T_ode, obsjax.GeneralizedInverseODE)."
            )
    return T


# --------------------------------------------------------------------------------------------------
# The design condition as a matrix differential equation (any observable pair)
# --------------------------------------------------------------------------------------------------


def _time_matrix(X, name: str, shape: tuple[int | None, int | None]) -> Callable:
    """t ↦ X(t) from a constant matrix or a callable (shape checked at t = 0)."""
    if callable(X):
        out = jax.eval_shape(X, jnp.asarray(0.0))
        if len(out.shape) != 2 or any(w is not None and w != g for w, g in zip(shape, out.shape)):
            raise ValueError(f"`{name}(t)` must return a matrix of shape {shape}, got {tuple(out.shape)}.")
        return lambda t: jnp.asarray(X(t))
    Xc = matrix(X, name, shape)
    return lambda t: Xc


def lovass_nagy_rhs(A, C, F, G) -> Callable:
    """The vector field T ↦ Ṫ = F T − T A(t) + G(t) C(t) of the design condition (slides (9)).

    Every solution satisfies Ṫ + T A − F T = G C, hence the solvability condition
    (Ṫ + T A − F T)(I − C^{1} C) = G C (I − C^{1} C) = 0 for every {1}-inverse C^{1}; conversely every T that
    satisfies the condition solves this equation with G = (Ṫ + T A − F T) C^{1}.

    **Arguments:** `A`, `C`, `G`: constant matrices or callables of t; `F` (n, n) constant.

    **Returns:** ``rhs(t, T)``.
    """
    F = matrix(F, "F", (None, None))
    q = F.shape[0]
    A_fn = A if callable(A) else _time_matrix(A, "A", (None, None))
    C_fn = C if callable(C) else _time_matrix(C, "C", (None, None))
    G_fn = G if callable(G) else _time_matrix(G, "G", (q, None))

    def rhs(t, T):
        return F @ T - T @ jnp.asarray(A_fn(t)) + jnp.asarray(G_fn(t)) @ jnp.asarray(C_fn(t))

    return rhs


def frozen_T0(A0, C0, F, G0) -> jax.Array:
    """T(t0) on the frozen-coefficient steady state: T A(t0) − F T = G(t0) C(t0) (a Sylvester equation).

    For constant (A, C, G) this is the equilibrium of Ṫ = F T − T A + G C, invertible when (A, C) is
    observable, (F, G) controllable and eig F ∩ eig A = ∅ (the Luenberger/Sylvester theorem); starting T
    there avoids the transient e^{F(t−t0)} T(t0) Φ(t0, t).  Differentiable in all arguments.

    **Arguments:** `A0` (n, n), `C0` (m, n), `F` (q, q), `G0` (q, m).  **Returns:** T0 (q, n).
    """
    from ._place import sylvester

    A0 = matrix(A0, "A(t0)", (None, None))
    C0 = matrix(C0, "C(t0)", (None, A0.shape[0]))
    F = matrix(F, "F", (None, None))
    G0 = matrix(G0, "G(t0)", (F.shape[0], C0.shape[0]))
    return sylvester(A0, F, G0 @ C0)


class LovassNagyTFlow(NamedTuple):
    """T(t) of :func:`lovass_nagy_T_ode` on the requested times: `ts` (K,), `T` (K, n, n), `rcond` (K,) the
    reciprocal condition number σ_min(T)/σ_max(T), `det` (K,) det T."""

    ts: jax.Array
    T: jax.Array
    rcond: jax.Array
    det: jax.Array


def equilibrated_rcond(T) -> jax.Array:
    """σ_min/σ_max of T (…, n, n) after scaling its columns, then its rows, to unit norm: 0 exactly when T
    is singular, and unchanged by a change of the state's units (T → T S⁻¹, S diagonal: the columns) and
    by a common scale of T.  Without the scaling, states in units 1e-4, 1 and 1e4 turned an rcond of 1e-3
    into 1.5e-11 and a valid design was refused."""
    T = jnp.asarray(T)

    def unit(v, axis):
        nrm = jnp.linalg.norm(v, axis=axis, keepdims=True)
        return v / jnp.where(nrm > 0, nrm, 1.0)

    Te = unit(unit(T, -2), -1)
    sv = jnp.linalg.svd(Te, compute_uv=False)
    return jnp.where(sv[..., 0] > 0, sv[..., -1] / jnp.where(sv[..., 0] > 0, sv[..., 0], 1.0), 0.0)


def check_invertible_on(ts, rcond, det, rcond_min: float, what: str) -> None:
    """Raise ``ValueError`` when T(t) is singular on the grid: σ_min/σ_max ≤ rcond_min (of the equilibrated
    T, :func:`equilibrated_rcond`: invariant to the units of the state and to a scale of T),
    a non-finite value, or a sign change of det T between two samples (T singular in between)."""
    ts, rcond, det = (concrete_value(jnp.asarray(v)) for v in (ts, rcond, det))
    if ts is None or rcond is None or det is None:
        return  # traced: the observer's estimate turns non-finite instead (status 2)
    bad = ~np.isfinite(rcond) | ~np.isfinite(det) | (rcond <= rcond_min)
    if bad.any():
        k = int(np.argmax(bad))
        raise ValueError(
            f"{what}: `T` must stay invertible (det T ≠ 0, step 4): σ_min(T)/σ_max(T) = {rcond[k]:.3e} "
            f"(≤ rcond_min = {rcond_min:.1e}) at t = {ts[k]:.6g}.  Choose other free entries: G, the "
            f"entries of F above its diagonal, or T(t0); a faster F keeps T near its frozen Sylvester value."
        )
    flips = np.nonzero(np.sign(det[:-1]) * np.sign(det[1:]) < 0)[0]
    if flips.size:
        j = int(flips[0])
        raise ValueError(
            f"{what}: `T` must stay invertible (det T ≠ 0, step 4): det T changes sign between "
            f"t = {ts[j]:.6g} and t = {ts[j + 1]:.6g} ({det[j]:.3e} → {det[j + 1]:.3e})."
        )


def lovass_nagy_T_ode(
    A, C, F, G, ts, *, T0=None, rtol: float = 1e-10, atol: float = 1e-12, rcond_min: float = 1e-10
) -> LovassNagyTFlow:
    """T(t) for any pair (A(t), C(t)) by integrating the Lovass-Nagy condition as a matrix ODE.

    The design equation (slides (9)) Ṫ + T A − F T = G C is solvable for G iff
    (Ṫ + T A − F T)(I − C^{1} C) = 0 (step 3).  Its solutions are exactly the solutions of

        Ṫ = F T − T A(t) + G(t) C(t),      T(t0) = T0,

    for a free G(t) (q × m): the condition is then satisfied identically, for constant or time-varying C,
    whatever the rank of (I − NNᵀ)ĀN (which the algebraic completion :func:`lovass_nagy_T` needs).  The
    free entries (G, F above its diagonal, T0; slides, steps 1, 2 and 4) must keep det T ≠ 0; this is
    checked on `ts` with a scale-invariant test (σ_min/σ_max of T, and sign changes of det T).  The solution
    is T(t) = e^{F(t−t0)} T0 Φ(t0, t) + ∫_{t0}^{t} e^{F(t−s)} G C(s) Φ(s, t) ds: with F faster than A its first
    term dies out and T follows the frozen Sylvester solution (:func:`frozen_T0`, the default T0), invertible
    for an observable (A, C) and a controllable (F, G).

    For the reduced observer use Ā = A22 and C = A12.  :class:`obsjax.GeneralizedInverseODE` integrates the
    same equation jointly with the observer, so that z − T x = e^{F(t−t0)}(z0 − T0 x0) holds to the solver's
    tolerance; this function gives T on a grid, for design and inspection.

    **Arguments:**

    - `A`, `C`: constant matrices or callables of t (Ā (n, n) and C (m, n)).
    - `F`: (q, q) constant observer matrix (q = n for a full-state observer).
    - `G`: (q, m) constant or a callable of t: the free gain.
    - `ts`: (K,) increasing times; the integration runs from ts[0].
    - `T0`: T(ts[0]); default :func:`frozen_T0` at ts[0].
    - `rtol`, `atol`: tolerances of the integration (diffrax ``Tsit5``).
    - `rcond_min`: smallest admissible σ_min(T)/σ_max(T).

    **Returns:** a :class:`LovassNagyTFlow` (ts, T, rcond, det).

    **Example:** a 3-state, 1-output LTV plant, for which :func:`lovass_nagy_T` has no completion::

        A = lambda t: jnp.array([[0., 1., 0.], [0., 0., 1.], [-1., -2. - jnp.sin(t), -1.]])
        C = jnp.array([[1., 0., 0.]])
        flow = lovass_nagy_T_ode(A, C, jnp.diag(jnp.array([-4., -5., -6.])), jnp.ones((3, 1)),
                                 jnp.linspace(0., 5., 51))
        flow.rcond.min()     # > 0: T(t) invertible on [0, 5]
    """
    import diffrax

    F = matrix(F, "F", (None, None))
    if F.shape[0] != F.shape[1]:
        raise ValueError(f"`F` must be square, got {tuple(F.shape)}.")
    q = F.shape[0]
    A_fn = _time_matrix(A, "A", (None, None))
    n = jax.eval_shape(A_fn, jnp.asarray(0.0)).shape[0]
    C_fn = _time_matrix(C, "C", (None, n))
    m = jax.eval_shape(C_fn, jnp.asarray(0.0)).shape[0]
    G_fn = _time_matrix(G, "G", (q, m))
    ts = as_float_array(ts, "ts")
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"`ts` must be a 1-D array of at least 2 times, got shape {tuple(ts.shape)}.")
    tsc = concrete_value(ts)
    if tsc is not None and not np.all(np.diff(tsc) > 0):
        raise ValueError("`ts` must be strictly increasing.")
    t0 = ts[0]
    if T0 is None:
        T0 = frozen_T0(A_fn(t0), C_fn(t0), F, G_fn(t0))
    T0 = matrix(T0, "T0", (q, n))
    rhs = lovass_nagy_rhs(A_fn, C_fn, F, G_fn)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, T, args: rhs(t, T)),
        diffrax.Tsit5(),
        t0,
        ts[-1],
        None,
        T0,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        max_steps=100_000,
    )
    Ts = sol.ys
    if q != n:
        return LovassNagyTFlow(ts, Ts, jnp.full(ts.shape, jnp.nan), jnp.full(ts.shape, jnp.nan))
    rcond = equilibrated_rcond(Ts)
    det = jnp.linalg.det(Ts)
    check_invertible_on(ts, rcond, det, rcond_min, "lovass_nagy_T_ode")
    return LovassNagyTFlow(ts, Ts, rcond, det)
