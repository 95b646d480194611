"""Observability of LTI pairs."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array


def _pair(A, C):
    A = as_float_array(A, "A")
    C = as_float_array(C, "C")
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"`A` must be a square (n, n) matrix, got shape {tuple(A.shape)}.")
    if C.ndim == 1:
        C = C[None, :]
    if C.ndim != 2 or C.shape[1] != A.shape[0]:
        raise ValueError(f"`C` must have shape (m, {A.shape[0]}), got {tuple(C.shape)}.")
    return A, C


def obsv(A, C) -> jax.Array:
    """Observability matrix O = [C; CA; …; CA^{n−1}] of shape (n·m, n) (thesis section 3.2).

    Differentiable in A and C.
    """
    A, C = _pair(A, C)
    n = A.shape[0]
    blocks = [C]
    for _ in range(n - 1):
        blocks.append(blocks[-1] @ A)
    return jnp.concatenate(blocks, axis=0)


def _obsv_np(A, C) -> np.ndarray:
    """Observability matrix in NumPy (for checks on concrete values, also while tracing)."""
    A = np.asarray(A, dtype=float)
    C = np.atleast_2d(np.asarray(C, dtype=float))
    blocks = [C]
    for _ in range(A.shape[0] - 1):
        blocks.append(blocks[-1] @ A)
    return np.concatenate(blocks, axis=0)


def is_observable(A, C, tol: float | None = None) -> bool:
    """True when rank obsv(A, C) = n (checked on concrete values with an SVD rank test).

    The default tolerance is ``max(shape) · eps · σ_max`` on the observability matrix scaled column-wise.
    """
    _pair(A, C)
    O = _obsv_np(A, C)
    n = O.shape[1]
    s = np.linalg.svd(O, compute_uv=False)
    if s[0] == 0:
        return False
    tol = max(O.shape) * np.finfo(float).eps * s[0] * 10 if tol is None else tol
    return int(np.sum(s > tol)) == n
