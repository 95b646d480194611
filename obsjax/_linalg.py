"""Small dense linear algebra written with elementwise operations.

XLA on the CPU lowers a batched ``jnp.linalg.solve`` (under ``jax.vmap``) to one LAPACK call per matrix; for the
2 × 2 … 8 × 8 matrices that observer vector fields solve at every stage of every step, that call costs several
times the rest of the vector field.  An unrolled Cholesky factorisation of a small symmetric positive definite
matrix is a few dozen fused elementwise operations instead, vectorises across the batch, and differentiates like
any other arithmetic.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl

#: Largest order solved by the unrolled factorisation; larger systems go to LAPACK (``cho_factor``).
UNROLL_MAX = 8


def spd_solve(A: jax.Array, B: jax.Array) -> jax.Array:
    """Solve A X = B for a symmetric positive definite A (n × n), B of shape (n,) or (n, k).

    A = L Lᵀ (Cholesky, only the lower triangle of A is read), then L Y = B and Lᵀ X = Y by substitution.
    For n ≤ ``UNROLL_MAX`` the factorisation and both substitutions are unrolled into elementwise operations
    (see the module docstring); above that, ``jax.scipy.linalg.cho_factor`` / ``cho_solve``.  A matrix that is
    not positive definite gives non-finite values (a square root of a non-positive pivot), which
    :func:`obsjax.simulate` reports as status 2.

    The derivative of the unrolled solve is that of X = A⁻¹ B written with the same factor,
    dX = A⁻¹ (dB − dA X), where dA is the symmetric matrix whose lower triangle is that of the tangent
    of A (the triangle the factorisation reads): two substitutions per tangent instead of
    differentiating the factorisation (fewer operations in forward and reverse mode alike).
    """
    n = A.shape[-1]
    if A.shape != (n, n) or B.shape[0] != n or B.ndim not in (1, 2):
        raise ValueError(f"spd_solve: expected A (n, n) and B (n,) or (n, k), got {A.shape} and {B.shape}.")
    if n > UNROLL_MAX:
        return jsl.cho_solve(jsl.cho_factor(A, lower=True), B)
    return _spd_solve_unrolled(A, B)


def _cholesky(A):
    """The lower Cholesky factor of A (n × n, lower triangle read) as nested lists of scalars."""
    n = A.shape[-1]
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        d = A[j, j] - sum((L[j][k] ** 2 for k in range(j)), start=jnp.zeros((), A.dtype))
        L[j][j] = jnp.sqrt(d)
        for i in range(j + 1, n):
            s = A[i, j] - sum((L[i][k] * L[j][k] for k in range(j)), start=jnp.zeros((), A.dtype))
            L[i][j] = s / L[j][j]
    return L


def _substitute(L, B):
    """X with L Lᵀ X = B, by forward then backward substitution."""
    n = len(L)
    ys = []
    for i in range(n):
        ys.append((B[i] - sum((L[i][k] * ys[k] for k in range(i)), start=jnp.zeros_like(B[i]))) / L[i][i])
    xs = [None] * n
    for i in reversed(range(n)):
        r = sum((L[k][i] * xs[k] for k in range(i + 1, n)), start=jnp.zeros_like(B[i]))
        xs[i] = (ys[i] - r) / L[i][i]
    return jnp.stack(xs)


@jax.custom_jvp
def _spd_solve_unrolled(A, B):
    return _substitute(_cholesky(A), B)


@_spd_solve_unrolled.defjvp
def _spd_solve_unrolled_jvp(primals, tangents):
    A, B = primals
    dA, dB = tangents
    L = _cholesky(A)
    X = _substitute(L, B)
    lower = jnp.tril(dA)
    dA_sym = lower + jnp.tril(dA, -1).T  # the factorisation reads the lower triangle only
    return X, _substitute(L, dB - dA_sym @ X)
