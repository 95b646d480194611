"""Helpers shared by the adaptive observers (gain matrices, Lyapunov equation, observer-form matrices)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array, concrete_value


def gain_array(x, name: str, size: int) -> jnp.ndarray:
    """Validate an adaptation gain given as a scalar, a (size,) vector (diagonal) or a (size, size) matrix.

    Scalars and vectors must be > 0; a matrix must be symmetric positive definite (checked when concrete).
    """
    arr = as_float_array(x, name)
    if arr.ndim == 0:
        pass
    elif arr.ndim == 1:
        if arr.shape[0] != size:
            raise ValueError(
                f"`{name}` must be a scalar, a ({size},) vector or a ({size}, {size}) matrix, "
                f"got a vector of length {arr.shape[0]}."
            )
    elif arr.ndim == 2:
        if arr.shape != (size, size):
            raise ValueError(
                f"`{name}` must be a scalar, a ({size},) vector or a ({size}, {size}) matrix, "
                f"got shape {tuple(arr.shape)}."
            )
    else:
        raise ValueError(
            f"`{name}` must be a scalar, vector or matrix, got shape {tuple(arr.shape)}."
        )
    check_gain(arr, name)
    return arr


def check_gain(arr, name: str) -> None:
    v = concrete_value(arr)
    if v is None:
        return
    if not np.all(np.isfinite(v)):
        raise ValueError(f"`{name}` must be finite, got {v.tolist()}.")
    if v.ndim < 2:
        if not np.all(v > 0):
            raise ValueError(f"`{name}` must be > 0 (an adaptation gain), got {v.tolist()}.")
    else:
        if not np.allclose(v, v.T, rtol=1e-10, atol=1e-12):
            raise ValueError(f"`{name}` must be a symmetric matrix, got {v.tolist()}.")
        ev = np.linalg.eigvalsh(0.5 * (v + v.T))
        if not np.all(ev > 0):
            raise ValueError(f"`{name}` must be positive definite, got eigenvalues {ev.tolist()}.")


def gain_matrix(arr, size: int) -> jnp.ndarray:
    """Scalar -> g I, vector -> diag(g), matrix -> itself."""
    arr = jnp.asarray(arr)
    if arr.ndim == 0:
        return arr * jnp.eye(size)
    if arr.ndim == 1:
        return jnp.diag(arr)
    return arr


def apply_gain(arr, v) -> jnp.ndarray:
    """G v for a scalar, diagonal-vector or matrix gain (no dense matrix for the first two)."""
    arr = jnp.asarray(arr)
    if arr.ndim == 0:
        return arr * v
    if arr.ndim == 1:
        return (arr[:, None] if v.ndim == 2 else arr) * v
    return arr @ v


def solve_gain(arr, v) -> jnp.ndarray:
    """Γ⁻¹ v for a scalar, diagonal-vector or matrix gain."""
    arr = jnp.asarray(arr)
    if arr.ndim == 0:
        return v / arr
    if arr.ndim == 1:
        return v / (arr[:, None] if v.ndim == 2 else arr)
    return jnp.linalg.solve(arr, v)


def lyapunov(K, Q) -> jnp.ndarray:
    """P with Kᵀ P + P K = −Q (dense Kronecker solve: small n, differentiable in K and Q)."""
    n = K.shape[0]
    eye = jnp.eye(n, dtype=K.dtype)
    # vec (row-major) of Kᵀ P + P K = (Kᵀ ⊗ I + I ⊗ Kᵀ) vec(P)
    M = jnp.kron(K.T, eye) + jnp.kron(eye, K.T)
    P = jnp.linalg.solve(M, -Q.reshape(-1)).reshape(n, n)
    return 0.5 * (P + P.T)


def poly_from_roots(roots) -> jnp.ndarray:
    """Real coefficients (c1, ..., cn) of Π (s − r_i) = s^n + c1 s^{n−1} + ... + cn."""
    roots = jnp.asarray(roots)
    coeffs = jnp.ones((1,), dtype=jnp.result_type(roots.dtype, jnp.float64))
    for k in range(roots.shape[0]):
        coeffs = jnp.concatenate([coeffs, jnp.zeros((1,), coeffs.dtype)]) - roots[
            k
        ] * jnp.concatenate([jnp.zeros((1,), coeffs.dtype), coeffs])
    return jnp.real(coeffs[1:])


def check_stable_roots(roots, name: str, size: int | None = None) -> jnp.ndarray:
    """Validate a set of eigenvalues: length, closed under conjugation, strictly in the left half-plane."""
    arr = jnp.asarray(roots)
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if not (
        jnp.issubdtype(arr.dtype, jnp.floating) or jnp.issubdtype(arr.dtype, jnp.complexfloating)
    ):
        arr = arr.astype(jnp.float64)
    if arr.ndim != 1 or (size is not None and arr.shape[0] != size):
        raise ValueError(
            f"`{name}` must be a vector of {size if size is not None else 'k'} eigenvalues, "
            f"got shape {tuple(arr.shape)}."
        )
    v = concrete_value(arr)
    if v is not None:
        v = np.asarray(v)
        if not np.all(np.isfinite(v)):
            raise ValueError(f"`{name}` must be finite, got {v.tolist()}.")
        if not np.all(np.real(v) < 0):
            raise ValueError(
                f"`{name}` must lie in the open left half-plane (Re < 0), got {v.tolist()}."
            )
        if np.iscomplexobj(v):
            a = np.sort_complex(v)
            b = np.sort_complex(np.conj(v))
            if not np.allclose(a, b, atol=1e-9):
                raise ValueError(
                    f"`{name}` must come in complex-conjugate pairs (a real polynomial), got {v.tolist()}."
                )
    return arr


def traced_positive(arr, name: str):
    """``eqx.error_if`` guard (survives jit) that a scalar/vector gain is > 0 or a matrix gain is s.p.d."""
    import equinox as eqx

    arr = jnp.asarray(arr)
    if arr.ndim <= 1:
        bad = jnp.any(~(arr > 0))
    else:
        bad = jnp.any(~(jnp.linalg.eigvalsh(0.5 * (arr + arr.T)) > 0))
    return eqx.error_if(arr, bad, f"`{name}` must be > 0 (positive definite for a matrix).")
