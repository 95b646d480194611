"""Helpers shared by the adaptive observers (gain matrices, Lyapunov equation, observer-form matrices)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value, real_array
from ._validation import equilibrated, spd_ok
from ._validation import spd_violation


def gain_array(x, name: str, size: int) -> jnp.ndarray:
    """Validate an adaptation gain given as a scalar, a (size,) vector (diagonal) or a (size, size) matrix.

    Scalars and vectors must be > 0; a matrix must be symmetric positive definite (checked when concrete).
    """
    arr = real_array(x, name)  # a complex gain made V complex and failed deep inside the solver
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
        # relative tests, on v as given or on the equilibrated D⁻¹ v D⁻¹ (D = diag(√v_ii), see spd_ok):
        # neither an absolute floor (an asymmetric gain of size 1e-13 passed) nor the units decide
        if bool(spd_ok(v, False, np)):
            return
        w, _ = equilibrated(v, np)
        if not np.max(np.abs(w - w.T), initial=0.0) <= 1e-10 * np.max(np.abs(w), initial=0.0):
            raise ValueError(f"`{name}` must be a symmetric matrix, got {v.tolist()}.")
        raw = np.linalg.eigvalsh(0.5 * (v + v.T))
        raise ValueError(f"`{name}` must be positive definite, got eigenvalues {raw.tolist()}.")


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


def _poly_coefficients(roots) -> jnp.ndarray:
    """Coefficients (c1, ..., cn) of Π (s − r_i) (complex for complex roots)."""
    roots = jnp.asarray(roots)
    coeffs = jnp.ones((1,), dtype=jnp.result_type(roots.dtype, jnp.float64))
    for k in range(roots.shape[0]):
        coeffs = jnp.concatenate([coeffs, jnp.zeros((1,), coeffs.dtype)]) - roots[
            k
        ] * jnp.concatenate([jnp.zeros((1,), coeffs.dtype), coeffs])
    return coeffs[1:]


def poly_from_roots(roots) -> jnp.ndarray:
    """Real coefficients (c1, ..., cn) of Π (s − r_i) = s^n + c1 s^{n−1} + ... + cn."""
    return jnp.real(_poly_coefficients(roots))


def state_dimension(n, name: str = "n", minimum: int = 1, what: str = "") -> int:
    """A dimension given as an integer ≥ `minimum` (a Python or NumPy integer, or an integral float such
    as 3.0); ``ValueError`` for 2.7, True, "3" (``int()`` truncated or parsed them)."""
    if not isinstance(n, (bool, np.bool_, str)) and hasattr(n, "shape") and np.ndim(n) == 0:
        v = concrete_value(n)  # a 0-d NumPy or JAX array holding the order
        if v is not None and np.asarray(v).dtype.kind in "iuf":
            n = np.asarray(v).item()
    ok = not isinstance(n, (bool, np.bool_)) and isinstance(n, (int, float, np.integer, np.floating))
    if not (ok and np.isfinite(n) and float(n) == int(n) and int(n) >= minimum):
        raise ValueError(f"`{name}`{what} must be an integer >= {minimum}, got {n!r}.")
    return int(n)


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
            # relative to the poles' magnitude, so the verdict does not depend on the time unit
            if not np.allclose(a, b, rtol=0.0, atol=1e-9 * np.max(np.abs(v))):
                raise ValueError(
                    f"`{name}` must come in complex-conjugate pairs (a real polynomial), got {v.tolist()}."
                )
    return arr


def traced_positive(arr, name: str):
    """``eqx.error_if`` guard (survives jit) that a scalar/vector gain is finite and > 0, or a matrix gain
    finite, symmetric (to 1e-10 relative) and positive definite (``spd_violation``): the Lyapunov
    arguments of the adaptive laws need Γ = Γᵀ > 0, and a traced Γ that is not is otherwise used as it is."""
    import equinox as eqx

    arr = jnp.asarray(arr)
    if arr.ndim <= 1:
        bad, what = jnp.any(~jnp.isfinite(arr) | ~(arr > 0)), "finite and > 0"
    else:
        bad, what = spd_violation(arr, semi=False), "finite, symmetric and positive definite"
    return eqx.error_if(arr, bad, f"`{name}` must be {what}.")


def traced_stable_roots(roots, name: str):
    """``eqx.error_if`` guard (survives jit) that eigenvalues are finite, in the open left half-plane and,
    when complex, closed under conjugation: the real polynomial Π(s − r_i) is formed from them, and for a
    set that is not closed its real part has other roots (−1 ± j, −1 + 2j gave s² + 2s − 1, a root at
    +0.41).  The test is |Im c_k| ≤ 1e-8 · e_k(|r|), e_k the bound of |c_k|, so it does not depend on the
    time unit."""
    import equinox as eqx

    r = jnp.asarray(roots)
    bad = jnp.any(~jnp.isfinite(r)) | jnp.any(~(jnp.real(r) < 0))
    if jnp.iscomplexobj(r) and r.shape[0] > 0:
        c = _poly_coefficients(r)
        bound = jnp.real(_poly_coefficients(-jnp.abs(r)))
        bad = bad | jnp.any(jnp.abs(jnp.imag(c)) > 1e-8 * bound)
    return eqx.error_if(
        r, bad, f"`{name}` must be finite, in the open left half-plane (Re < 0) and closed under conjugation."
    )


# --------------------------------------------------------------------------- chapter 4, section 4.5
def filter_step(omega, sig, delta) -> jnp.ndarray:
    """d/dt of the state ω of the filter 1/D(s), D(s) = s^r + δ_1 s^{r−1} + ... + δ_r, driven by ``sig``.

    Controllable companion form: ω_j = s^{j−1}/D(s) sig (j = 1..r), so ω̇_j = ω_{j+1} and
    ω̇_r = s^r/D sig = sig − Σ_j δ_{r+1−j} ω_j.  ``delta`` holds (δ_1, ..., δ_r).
    """
    if omega.shape[0] == 0:
        return omega
    top = sig - jnp.dot(delta[::-1], omega)
    return jnp.concatenate([omega[1:], top[None]])


def filter_regressor(omega, sig, delta) -> jnp.ndarray:
    """The n = r + 1 filtered signals v_i = s^{n−i}/D(s) sig, i = 1..n, from the filter state ω.

    v_1 = s^r/D sig = sig − Σ_j δ_{r+1−j} ω_j (a direct term of ``sig``), v_i = ω_{n+1−i} for i ≥ 2.
    """
    sig = jnp.asarray(sig)
    if omega.shape[0] == 0:
        return sig[None]
    first = sig - jnp.dot(delta[::-1], omega)
    return jnp.concatenate([first[None], omega[::-1]])


def auxiliary_matrices(d) -> jnp.ndarray:
    """Matrices C_i (n × (n−1)) of the minimal adaptive observer's auxiliary signals, stacked as C[i].

    With K = [−k | Ā] in observer form and d = (1, δ_1, ..., δ_{n−1}) the coefficients of the monic D(s),
    C_i ω is the zero-state response r⁽ⁱ⁾ of ṙ = K r + e_i sig − d v_i (v_i = s^{n−i}/D sig, ω the state of
    1/D(s) driven by sig).  Its first component vanishes identically (hᵀ(sI − K)⁻¹(e_i D − d s^{n−i}) = 0
    when det(sI − K) = (s + λ) D(s)), and the remaining rows follow from (sI − K) q = x, x = e_i D − d s^{n−i}:
    q_1 = 0, q_2 = −x_1, q_{m+1} = s q_m − x_m, each q_m of degree ≤ n − 2, so r⁽ⁱ⁾ = C_i ω with C_i[m, j] the
    coefficient of s^{j−1} in q_m.  Polynomials here are ascending coefficient arrays of length n.
    """
    d = jnp.asarray(d)
    n = d.shape[0]
    r = n - 1
    dasc = d[::-1]  # D(s) ascending: δ_{n−1}, ..., δ_1, 1
    mats = []
    for i in range(n):
        x = -jnp.outer(d, jnp.eye(n, dtype=d.dtype)[n - 1 - i])  # row m: −d_m s^{n−1−i}
        x = x.at[i].add(dasc)  # + δ_{mi} D(s)
        rows = [jnp.zeros(n, d.dtype)]
        for m in range(1, n):
            shifted = jnp.concatenate([jnp.zeros(1, d.dtype), rows[-1][:-1]])  # s · q_m
            rows.append(shifted - x[m - 1])
        mats.append(jnp.stack(rows)[:, :r])
    return jnp.stack(mats)


def adapt_mask(adapt, size: int) -> tuple[bool, ...]:
    """Validate the static mask of adapted (unknown) parameters; ``None`` adapts all of them."""
    if adapt is None:
        return (True,) * size
    mask = tuple(bool(v) for v in np.asarray(adapt, dtype=bool).reshape(-1))
    if len(mask) != size:
        raise ValueError(f"`adapt` must hold {size} booleans (one per parameter), got {len(mask)}.")
    if not any(mask):
        raise ValueError("`adapt` must mark at least one parameter as unknown (True).")
    return mask


def masked_rate(Gamma, mask, v) -> jnp.ndarray:
    """M Γ M v with M = diag(mask): the rate restricted to the unknown parameters (Γ_uu is s.p.d. when Γ is)."""
    m = jnp.asarray(mask, dtype=v.dtype)
    return m * apply_gain(Gamma, m * v)


def quadratic_weight(Gamma, mask, theta) -> jnp.ndarray:
    """θ_uᵀ Γ_uu⁻¹ θ_u over the unknown parameters (vectorised over leading axes of θ)."""
    idx = np.flatnonzero(np.asarray(mask))
    th = theta[..., idx]
    G = jnp.asarray(Gamma)
    if G.ndim == 0:
        return jnp.sum(th**2, axis=-1) / G
    if G.ndim == 1:
        return jnp.sum(th**2 / G[idx], axis=-1)
    Guu = G[np.ix_(idx, idx)]
    sol = jnp.linalg.solve(Guu, jnp.moveaxis(th, -1, 0).reshape(idx.size, -1))
    return jnp.sum(th * sol.T.reshape(th.shape), axis=-1)


def siso_signal(v, name: str, who: str) -> jax.Array:
    """The scalar of a single-input single-output observer's signal `name` (y or u).

    Hassan's plant forms (4.12), (5.1) and (6.1) have one input and one output (y = x₁); a plant with
    several was accepted before and every channel but the first silently dropped (status 0, wrong
    parameter estimates).  Shapes are static, so this refuses eagerly, also under ``jit``."""
    v = jnp.asarray(v)
    if v.size != 1:
        raise ValueError(
            f"{who} is single-input single-output (the plant forms (4.12), (5.1), (6.1)): `{name}` must have "
            f"one entry, got shape {tuple(v.shape)}; the plant has {v.size} "
            f"{'outputs' if name == 'y' else 'inputs'}."
        )
    return v.reshape(())
