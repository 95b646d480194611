"""Observer gain design: pole placement, Sylvester equations, observability indices."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array, concrete_value
from ..analysis._lti import _obsv_np, _pair, is_observable, obsv


def _check_poles(poles, n):
    poles = jnp.asarray(poles)
    if poles.ndim == 0:
        poles = poles.reshape(1)
    if poles.ndim != 1 or poles.shape[0] != n:
        raise ValueError(
            f"`poles` must hold exactly n = {n} observer poles, got {poles.shape[0] if poles.ndim == 1 else poles.shape}."
        )
    v = concrete_value(poles)
    if v is not None and np.iscomplexobj(v):
        # complex poles must come with their conjugates
        remaining = list(v)
        while remaining:
            p = remaining.pop(0)
            if abs(p.imag) <= 1e-12 * max(1.0, abs(p)):
                continue
            dist = [abs(q - np.conj(p)) for q in remaining]
            if not dist or min(dist) > 1e-9 * max(1.0, abs(p)):
                raise ValueError(
                    f"`poles` must be closed under conjugation for a real gain: {p} has no conjugate {np.conj(p)}."
                )
            remaining.pop(int(np.argmin(dist)))
    if v is not None and not np.all(np.isfinite(v)):
        raise ValueError(f"`poles` must be finite, got {v.tolist()}.")
    return poles


def _charpoly(poles):
    """Real coefficients [1, c1, …, cn] of Π (s − p_i), differentiable in the poles."""
    coeffs = jnp.ones((1,), dtype=poles.dtype)
    for i in range(poles.shape[0]):
        coeffs = jnp.convolve(coeffs, jnp.stack([jnp.ones((), poles.dtype), -poles[i]]))
    return jnp.real(coeffs)


def _ackermann(A, c, coeffs):
    """Gain l (n,) with eig(A − l c) having characteristic polynomial ``coeffs`` (SISO, Ackermann).

        l = φ(A) · O⁻¹ · e_n,   O = [c; cA; …; cA^{n−1}],   φ(s) = s^n + c1 s^{n−1} + … + cn.
    """
    n = A.shape[0]
    O = obsv(A, c[None, :])
    eye = jnp.eye(n, dtype=A.dtype)
    phi = coeffs[0] * eye
    for k in range(1, n + 1):  # Horner: φ(A) = ((A + c1 I) A + c2 I) A + …
        phi = phi @ A + coeffs[k] * eye
    en = jnp.zeros((n,), A.dtype).at[-1].set(1.0)
    return phi @ jnp.linalg.solve(O, en)


def _cyclic_candidates(n, m):
    """Deterministic (L0, v) candidates for the MIMO reduction; the first is (0, equal weights)."""
    rng = np.random.default_rng(20261121)
    out = [(np.zeros((n, m)), np.ones(m) / np.sqrt(m))]
    for _ in range(6):
        v = rng.standard_normal(m)
        out.append((np.zeros((n, m)), v / np.linalg.norm(v)))
    for _ in range(6):
        v = rng.standard_normal(m)
        out.append((rng.standard_normal((n, m)), v / np.linalg.norm(v)))
    return out


def choose_reduction(A, C) -> int:
    """Index of the best-conditioned single-output reduction (L0, v) of a concrete MIMO pair (A, C).

    Store it (as :class:`obsjax.Luenberger` does) to keep the same reduction when A, C are later traced.
    """
    A = np.asarray(A, dtype=float)
    C = np.asarray(C, dtype=float)
    n, m = A.shape[0], C.shape[0]
    if m == 1:
        return 0
    scale = max(1.0, float(np.linalg.norm(A)))
    best = None
    for idx, (L0, v) in enumerate(_cyclic_candidates(n, m)):
        Ak = A - (L0 * scale) @ C
        O = _obsv_np(Ak, (v @ C)[None, :])
        with np.errstate(all="ignore"):
            cond = np.linalg.cond(O)
        if not np.isfinite(cond):
            continue
        if best is None or cond < best[0] * 0.5:  # prefer earlier (simpler) candidates
            best = (cond, idx)
    if best is None:
        raise ValueError("place: no single-output reduction of (A, C) is observable; check (A, C).")
    return best[1]


def place(A, C, poles, *, reduction: int | None = None) -> jax.Array:
    """Observer gain L (n, m) such that eig(A − L C) = ``poles`` (thesis Lemma 1, (2.7)).

    The identity observer (2.7) ż = (A − LC) z + L y + B u then has the requested dynamics.

    - Single output (m = 1): Ackermann's formula l = φ(A)·O⁻¹·e_n with O = obsv(A, c) and φ the
      requested characteristic polynomial.
    - Several outputs: the MIMO problem is reduced to a single-output one (the cyclic design): with a fixed
      pre-gain L0 making A − L0C cyclic and a fixed output combination v making (A − L0C, vᵀC) observable,
      L = L0 + l vᵀ where l places the poles of (A − L0C, vᵀC) by Ackermann.  L0 and v are chosen once per
      design from a fixed deterministic list (the best-conditioned candidate when A and C are concrete; the
      first, L0 = 0, under ``jit``), then held constant, so L is an exact, differentiable function of A, C
      and the poles.  Well-conditioned problems give eig(A − LC) to ~1e-10 relative; the gain differs from
      python-control's robust (Kautsky–Nichols) choice but has the same eigenvalues.

    Differentiable with respect to A, C and the poles (real or conjugate-closed complex).

    **Raises** ``ValueError`` for a non-square A, mismatched C, a wrong number of poles, complex poles
    without their conjugates, or an unobservable pair (checked when A and C are concrete).

    **Example:** thesis example (2.8), poles {−3, −3}: ``place([[-2, 1], [0, -1]], [[1, 0]], [-3, -3])``
    gives L = [[3], [4]].
    """
    A, C = _pair(A, C)
    n, m = A.shape[0], C.shape[0]
    poles = _check_poles(poles, n)
    Av, Cv = concrete_value(A), concrete_value(C)
    if Av is not None and Cv is not None and not is_observable(Av, Cv):
        raise ValueError(
            f"(A, C) is not observable: rank obsv(A, C) = {np.linalg.matrix_rank(_obsv_np(Av, Cv))} < n = {n}; "
            "the observer poles cannot be placed arbitrarily (thesis Lemma 1)."
        )
    if jnp.iscomplexobj(poles):
        poles_c = poles
    else:
        poles_c = poles.astype(A.dtype)
    coeffs = _charpoly(poles_c).astype(A.dtype)
    if m == 1:
        return _ackermann(A, C[0], coeffs)[:, None]

    if reduction is None:
        reduction = choose_reduction(Av, Cv) if (Av is not None and Cv is not None) else 0
    L0, v = _cyclic_candidates(n, m)[reduction]
    L0 = jnp.asarray(L0, A.dtype) * jnp.maximum(1.0, jnp.linalg.norm(A))
    v = jnp.asarray(v, A.dtype)
    Ak = A - L0 @ C
    l = _ackermann(Ak, v @ C, coeffs)
    return L0 + jnp.outer(l, v)


def sylvester(A, F, H) -> jax.Array:
    """Solve T A − F T = H for T (thesis Theorem 1, (2.2)-(2.4)).

    Unique when A and F have no common eigenvalue.  Solved through the Kronecker form
    (Aᵀ ⊗ I − I ⊗ F) vec(T) = vec(H); differentiable in A, F and H.

    **Arguments:** `A` (n, n), `F` (q, q), `H` (q, n).  **Returns:** T (q, n).

    **Example:** thesis (3.3): ``sylvester([[-2, 1], [0, -2]], [[-3]], [[1, 0]])`` → [[1, −1]].
    """
    A = as_float_array(A, "A")
    F = as_float_array(F, "F")
    H = as_float_array(H, "H")
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"`A` must be square (n, n), got {tuple(A.shape)}.")
    if F.ndim != 2 or F.shape[0] != F.shape[1]:
        raise ValueError(f"`F` must be square (q, q), got {tuple(F.shape)}.")
    n, q = A.shape[0], F.shape[0]
    if H.shape != (q, n):
        raise ValueError(f"`H` must have shape ({q}, {n}), got {tuple(H.shape)}.")
    Av, Fv = concrete_value(A), concrete_value(F)
    if Av is not None and Fv is not None:
        ea, ef = np.linalg.eigvals(Av), np.linalg.eigvals(Fv)
        gap = np.min(np.abs(ea[:, None] - ef[None, :]))
        if gap < 1e-10 * max(1.0, np.max(np.abs(ea)), np.max(np.abs(ef))):
            raise ValueError(
                f"`A` and `F` share an eigenvalue (closest pair {gap:.2e} apart): T A − F T = H has no unique solution."
            )
    K = jnp.kron(A.T, jnp.eye(q, dtype=A.dtype)) - jnp.kron(jnp.eye(n, dtype=A.dtype), F)
    vecT = jnp.linalg.solve(K, H.T.reshape(-1))  # column-major vec
    return vecT.reshape(n, q).T


def observability_indices(A, C, tol: float | None = None) -> tuple[int, ...]:
    """Observability indices ν_1 … ν_m by the column selection (a)-(e) of thesis section 3.2.

    With H = Cᵀ (so y = Hᵀx), the columns h_1 … h_m, Aᵀh_1 … Aᵀh_m, (Aᵀ)²h_1, … are tested one by one in
    that order; a column dependent on those kept is dropped, and with it every later power of the same
    h_j (step (e)).  ν_k is the number of columns kept for output k; Σ ν_k = n for an observable pair and
    max ν_k is the observability index ν.

    **Raises** ``ValueError`` when the pair is not observable.
    """
    _pair(A, C)
    A = np.asarray(A, dtype=float)
    C = np.atleast_2d(np.asarray(C, dtype=float))
    n, m = A.shape[0], C.shape[0]
    H = C.T
    kept = []
    nu = [0] * m
    alive = [True] * m
    cols = [H[:, j].copy() for j in range(m)]
    scale = max(1.0, np.linalg.norm(A), np.linalg.norm(C))
    tol = (1e-9 * scale) if tol is None else tol
    for _ in range(n):
        for j in range(m):
            if not alive[j] or len(kept) == n:
                continue
            cand = np.column_stack(kept + [cols[j]])
            s = np.linalg.svd(cand, compute_uv=False)
            if s[-1] > tol * max(1.0, s[0]):
                kept.append(cols[j])
                nu[j] += 1
            else:
                alive[j] = False
            cols[j] = A.T @ cols[j]
    if len(kept) < n:
        raise ValueError(
            f"(A, C) is not observable: the column selection found {len(kept)} < n = {n} independent columns."
        )
    return tuple(nu)
