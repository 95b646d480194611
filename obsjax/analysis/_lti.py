"""Observability of LTI pairs: the observability matrix, and every rank decision of the package.

All rank decisions about a pair (A, C) -- observability, the observability indices of thesis §3.2, the
Jordan structure that pole placement can give, the order ν − 1 of a functional observer -- are made by one
mechanism, :func:`observability_staircase`: an orthogonal staircase (observability Hessenberg) form of
the *balanced* pair, computed by a block Arnoldi sweep in the lexicographic order of thesis §3.2, steps
(a)-(e).  Its decisions compare a new direction with the direction it came from (relative thresholds), on
the pair scaled to unit norm, so they do not change when A → cA (a change of time unit) or C → dC (a
change of output unit), nor under a diagonal change of state units: the balancing (:func:`log_scaling`)
brings every nonzero entry as close to magnitude 1 as diagonal scalings allow, which is defined for
integrators and constant biases too (states whose row of A is zero, which a norm balancing leaves in the
unit they were given).

The independence test itself is :func:`lexicographic_step` (a residual outside the directions kept,
against a relative threshold); the LTV side (the indices and strong observability of Huang & Zhu's
canonical form, the TLO, the TLC) runs the same step on the rows [C; 𝓛C; …], and checks that must run
under ``jit`` use its traced twin :func:`relative_residuals`.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import equinox as eqx

from .._checks import concrete_value, real_array

#: Default relative tolerance of the rank decisions (see :func:`observability_staircase`).
DEFAULT_TOL = 1e-9


def _pair(A, C):
    A = real_array(A, "A")  # a complex A or C: refused, not silently cast to its real part
    C = real_array(C, "C")
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

    **Example:** ``obsv([[0., 1.], [0., 0.]], [[1., 0.]])`` → [[1, 0], [0, 1]].
    """
    A, C = _pair(A, C)
    av, cv = concrete_value(A), concrete_value(C)
    checked = av is not None and cv is not None
    if checked and not (np.all(np.isfinite(av)) and np.all(np.isfinite(cv))):
        raise ValueError("obsv: `A` and `C` must be finite, got a NaN or an infinity.")
    n = A.shape[0]
    blocks = [C]
    for _ in range(n - 1):
        blocks.append(blocks[-1] @ A)
    O = jnp.concatenate(blocks, axis=0)
    if not checked:  # on the result, which depends on A and C whatever n (A alone is unused when n = 1)
        O = eqx.error_if(O, ~(jnp.all(jnp.isfinite(A)) & jnp.all(jnp.isfinite(C))),
                         "obsv: `A` and `C` must be finite.")
    return O


def _obsv_np(A, C) -> np.ndarray:
    """Observability matrix in NumPy (for checks on concrete values)."""
    A = np.asarray(A, dtype=float)
    C = np.atleast_2d(np.asarray(C, dtype=float))
    blocks = [C]
    for _ in range(A.shape[0] - 1):
        blocks.append(blocks[-1] @ A)
    return np.concatenate(blocks, axis=0)


def _concrete_pair(A, C, who: str) -> tuple[np.ndarray, np.ndarray]:
    _pair(A, C)
    try:
        A = np.asarray(A, dtype=float)
        C = np.atleast_2d(np.asarray(C, dtype=float))
    except Exception:  # noqa: BLE001  (a tracer)
        raise ValueError(
            f"{who} decides ranks on concrete values: `A` and `C` must not be traced (call it outside "
            "`jit`, or on the model's concrete matrices)."
        ) from None
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(C))):
        raise ValueError(f"{who}: `A` and `C` must be finite, got a NaN or an infinity.")
    return A, C


def _unit(M: np.ndarray) -> np.ndarray:
    s = np.linalg.norm(M, 2) if M.size else 0.0
    return M / s if s > 0 else M


def _xp(*arrays):
    """numpy for concrete NumPy inputs, jax.numpy otherwise."""
    return np if all(isinstance(a, (np.ndarray, np.generic, float, int, list, tuple)) for a in arrays) else jnp


def log_scaling(A, C):
    """The diagonal scalings that bring every nonzero entry of (A, C) as close to magnitude 1 as possible.

    Curtis & Reid's log-magnitude scaling (A. R. Curtis and J. K. Reid, "On the automatic scaling of
    matrices for Gaussian elimination", J. Inst. Maths Applics 10, 1972), for a state-space pair: the
    state scaling d (n,), the output scaling e (m,) and the time scaling c minimise

        Σ_{A_ij ≠ 0} (log|c A_ij d_j / d_i|)² + Σ_{C_kj ≠ 0} (log|e_k C_kj d_j|)²,

    a linear least-squares problem in (log d, log e, log c), solved to its minimum-norm solution.  Its
    residual -- the log-magnitudes of the scaled entries c D⁻¹ A D and E C D -- is unique, so the scaled
    pair of (c' S A S⁻¹, Λ C S⁻¹) (S, Λ diagonal and invertible, c' > 0) is that of (A, C) up to the signs
    of S and Λ, to rounding: a change of time, output or state units does not change it.  Unlike a norm
    balancing (LAPACK's gebal, Osborne's iteration), it is defined for a state whose row or column of A is
    zero (an integrator, a constant bias), which a norm balancing leaves in whatever unit it was given.

    NumPy arrays give NumPy results (no compilation: the rank decisions run on concrete values); JAX
    arrays or tracers give a traced computation, differentiable where the zero pattern is fixed (the
    same operations).  Returns (d, e, c) with d normalised to geometric mean 1 (e compensating).

    **Example:** the bias state of ẋ = [[0, 1, 0], [−4, −0.4, 10⁻⁹], [0, 0, 0]] x, y = x_1 gets d_3 ≈ 10⁹
    (its coupling 10⁻⁹ is brought to about 1).
    """
    xp = _xp(A, C)
    A = xp.asarray(A)
    C = xp.atleast_2d(xp.asarray(C))
    n, m = A.shape[0], C.shape[0]
    dtype = xp.result_type(A.dtype, C.dtype, xp.float32)
    eye_n, eye_m = xp.eye(n, dtype=dtype), xp.eye(m, dtype=dtype)
    # design rows: A_ij -> (−e_i + e_j over δ, 0 over ε, 1 over τ); C_kj -> (e_j, e_k, 0)
    Ga = xp.concatenate(
        [
            (eye_n[None, :, :] - eye_n[:, None, :]).reshape(n * n, n),
            xp.zeros((n * n, m), dtype),
            xp.ones((n * n, 1), dtype),
        ],
        axis=1,
    )
    Gc = xp.concatenate(
        [
            xp.broadcast_to(eye_n[None, :, :], (m, n, n)).reshape(m * n, n),
            xp.broadcast_to(eye_m[:, None, :], (m, n, m)).reshape(m * n, m),
            xp.zeros((m * n, 1), dtype),
        ],
        axis=1,
    )
    G = xp.concatenate([Ga, Gc], axis=0)
    v = xp.concatenate([A.reshape(-1), C.reshape(-1)]).astype(dtype)
    w = (v != 0).astype(dtype)
    b = xp.log(xp.abs(xp.where(v != 0, v, 1.0)))
    WG = w[:, None] * G
    x = -xp.linalg.pinv(WG, rcond=_PINV_RCOND * max(WG.shape)) @ (w * b) if WG.size else xp.zeros(n + m + 1)
    delta, eps, tau = x[:n], x[n : n + m], x[n + m]
    if n:  # d to geometric mean 1, e compensating: e_k C_kj d_j is unchanged
        mu = xp.mean(delta)
        delta, eps = delta - mu, eps + mu
    return xp.exp(delta), xp.exp(eps), xp.exp(tau)


#: relative cut-off (times the larger dimension) of the pseudo-inverse in :func:`log_scaling`
_PINV_RCOND = 10.0 * float(np.finfo(float).eps)

#: Sweeps of Osborne's iteration after the log-magnitude scaling (:func:`balancing`).
OSBORNE_SWEEPS = 24


def balancing(A, C):
    """The diagonal state and output scalings (d, e) of the balanced pair: the log-magnitude scaling of
    :func:`log_scaling`, then Osborne's norm balancing of the states from there.

    Osborne's iteration (E. E. Osborne, "On pre-conditioning of matrices", J. ACM 7, 1960; LAPACK's
    gebal) rescales each state so that the 2-norm of its row of D⁻¹AD (off the diagonal) equals that of
    its column of [D⁻¹AD; ECD], which is what keeps round-off in an eigenvector computation small.  For
    an irreducible pair its fixed point is unique up to a common factor, so it is that of a norm
    balancing from any start; a state whose row or column is zero (an integrator, a bias) has no such
    fixed point, and keeps the log-magnitude scale, which makes its couplings of order 1.  The result is
    a function of the log-magnitude-balanced pair, which does not depend on the units of time, states or
    outputs, so neither does this one.  A fixed number of sweeps (``OSBORNE_SWEEPS``); NumPy in, NumPy
    out (a Python loop), otherwise traced (``lax.fori_loop``: differentiable, reverse mode too).
    """
    xp = _xp(A, C)
    A = xp.asarray(A)
    C = xp.atleast_2d(xp.asarray(C))
    n = A.shape[0]
    d, e, c = log_scaling(A, C)
    if n == 0:
        return d, e
    off = c * A * (1.0 - xp.eye(n, dtype=A.dtype))  # in the time unit of the log-magnitude scaling
    Ce = C * e[:, None]
    idx = xp.arange(n)

    def norm(v):  # a 2-norm whose derivative is finite at 0 (the state is then skipped)
        ss = xp.sum(v * v)
        pos = ss > 0
        return xp.where(pos, xp.sqrt(xp.where(pos, ss, 1.0)), 0.0), pos

    def one(k, d):
        i = k % n
        di = xp.sum(xp.where(idx == i, d, 0.0))
        row, okr = norm(off[i] * d / di)
        col, okc = norm(xp.concatenate([off[:, i] * di / d, Ce[:, i] * di]))
        ok = okr & okc
        f = xp.sqrt(xp.where(ok, row, 1.0) / xp.where(ok, col, 1.0))
        return d * xp.where((idx == i) & ok, f, 1.0)

    if xp is np:
        for k in range(OSBORNE_SWEEPS * n):
            d = one(k, d)
    else:
        d = jax.lax.fori_loop(0, OSBORNE_SWEEPS * n, one, d)
    return d / xp.exp(xp.mean(xp.log(d))), e


#: A balancing that scales entries by more than this (max d / min d) is named in a warning: entries
#: that small relative to the others count as couplings (see :func:`observability_staircase`).
BALANCE_SPREAD_WARN = 1e10


def balance_pair(A, C) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The balanced pair (A_b, C_b) = (D⁻¹ A D / ‖·‖, E C D / ‖·‖) and the diagonal D (as a vector).

    D and E are those of :func:`balancing`: the log-magnitude scaling of :func:`log_scaling` (every nonzero
    entry as close to magnitude 1 as a diagonal change of state and output units allows), then Osborne's
    norm balancing of the states where it has a fixed point.  Both results are scaled to
    unit 2-norm, so the balanced pair of (c S A S⁻¹, Λ C S⁻¹), with c > 0 (time unit), S and Λ diagonal
    and invertible (state and output units), is that of (A, C), up to the signs of S and Λ (an orthogonal
    similarity), to rounding.
    """
    A = np.asarray(A, dtype=float)
    C = np.atleast_2d(np.asarray(C, dtype=float))
    d, e = (np.asarray(z, dtype=float) for z in balancing(A, C))
    Ab = _unit(A * (d[None, :] / d[:, None]))
    Cb = _unit(C * e[:, None] * d[None, :])
    return Ab, Cb, d


def lexicographic_step(basis: list, cands: np.ndarray, alive: list, thresholds) -> np.ndarray:
    """One level of the lexicographic search of thesis §3.2, steps (a)-(e).

    The candidate rows ``cands[j]`` of the outputs still alive are taken in the order j = 1 … m; each is
    orthogonalised (twice, modified Gram-Schmidt) against the orthonormal rows in ``basis`` (those kept
    at earlier levels and earlier on this level) and kept -- appended, normalised, to ``basis`` -- when the
    residual exceeds ``thresholds[j]``; otherwise output j is dead for every later level (step (e)).

    Returns the residuals (m, n) (zero rows for outputs not kept).  Updates ``basis`` and ``alive``.
    This is the one place where the package decides a rank.
    """
    m, n = cands.shape
    res = np.zeros((m, n))
    for j in range(m):
        if not alive[j]:
            continue
        if len(basis) == n:
            alive[j] = False
            continue
        v = np.array(cands[j], dtype=float)
        if basis:
            Bm = np.asarray(basis)
            for _ in range(2):
                v = v - Bm.T @ (Bm @ v)
        nv = float(np.linalg.norm(v))
        if nv > thresholds[j] and nv > 0.0:
            basis.append(v / nv)
            res[j] = v
        else:
            alive[j] = False
    return res


def relative_residuals(rows, scales) -> jax.Array:
    """Traced twin of :func:`lexicographic_step`, for checks that run under ``jit``.

    For the rows of ``rows`` (r, n), r ≤ n, taken in order: the norm of each row's component outside the
    span of the rows before it -- the residual that :func:`lexicographic_step` compares with its
    threshold -- divided by ``scales`` (r,) (the scale its threshold is relative to).  The residuals
    are |R_kk| of a Householder QR factorisation of rowsᵀ; a zero scale gives 0.  Not differentiated
    (the decisions it feeds are not).

    **Example:** ``relative_residuals(jnp.array([[1., 0.], [1., 1e-6]]), jnp.ones(2))`` → [1, 1e-6].
    """
    rows = jax.lax.stop_gradient(jnp.asarray(rows))
    scales = jax.lax.stop_gradient(jnp.asarray(scales, dtype=rows.dtype))
    R = jnp.linalg.qr(rows.T, mode="r")
    res = jnp.abs(jnp.diagonal(R))
    ok = scales > 0
    return jnp.where(ok, res / jnp.where(ok, scales, 1.0), 0.0)


def gram_relative_residuals(M) -> jax.Array:
    """:func:`relative_residuals` of the vectors whose Gram matrix is M (symmetric positive
    semi-definite, n × n), each relative to its own norm √M_kk: with M = SᵀS, the residual of column k
    of S outside the columns before it.  Zero where M_kk = 0.  Invariant to a diagonal scaling of M (the
    units of the vectors)."""
    M = jax.lax.stop_gradient(jnp.asarray(M))
    M = 0.5 * (M + M.T)
    w, V = jnp.linalg.eigh(M)
    S = (V * jnp.sqrt(jnp.clip(w, 0.0, None))[None, :]) @ V.T  # symmetric square root
    return relative_residuals(S.T, jnp.sqrt(jnp.clip(jnp.diagonal(M), 0.0, None)))


class ObservabilityStaircase(NamedTuple):
    """The orthogonal staircase form of a pair (A, C), with its rank decisions.

    - `T` (n, n): z = T x; T = Q D⁻¹ with Q orthogonal (rows: the orthonormal directions found level by
      level, then an orthonormal basis of the unobservable part) and D the balancing.
    - `A` (n, n), `C` (m, n): T A T⁻¹ and C T⁻¹ (C T⁻¹ = [C_1, 0]; T A T⁻¹ is block Hessenberg: level k
      couples only to levels ≤ k + 1).
    - `blocks`: the level sizes r_1 ≥ r_2 ≥ … (r_k new directions at power k − 1 of A).
    - `indices`: the observability indices ν_1 … ν_m of thesis §3.2 (lexicographic, per output).
    - `kronecker`: the indices sorted in decreasing order (the conjugate partition of `blocks`).
    - `rank`: Σ r_k, the dimension of the observable subspace.
    - `margin`: the PBH margin min over eigenvalues λ of A_b of σ_min([A_b − λI; C_b]) of the balanced,
      unit-norm pair (0 for an unobservable pair; at most about 1).
    - `tol`: the relative tolerance used; `observable`: rank = n and margin > tol.
    """

    T: np.ndarray
    A: np.ndarray
    C: np.ndarray
    blocks: tuple[int, ...]
    indices: tuple[int, ...]
    kronecker: tuple[int, ...]
    rank: int
    margin: float
    tol: float
    observable: bool


def _margin(Ab: np.ndarray, Cb: np.ndarray) -> float:
    n = Ab.shape[0]
    if n == 0:
        return 1.0
    lams = np.linalg.eigvals(Ab)
    best = np.inf
    for lam in lams:
        M = np.concatenate([Ab - lam * np.eye(n), Cb.astype(complex)])
        best = min(best, float(np.linalg.svd(M, compute_uv=False)[-1]))
    return best


def pbh_margin(A, C) -> float:
    """PBH observability margin of (A, C): min over the eigenvalues λ of A of σ_min([A − λI; C]).

    Computed on the balanced pair scaled to unit norm (:func:`balance_pair`), so it is relative to ‖A‖,
    does not depend on the units of time, outputs or states, and lies in [0, about 1]; 0 means that an
    eigenvalue of A is unobservable (Popov-Belevitch-Hautus test).

    **Example:** ``pbh_margin([[1., 0.], [0., 1. + 1e-6]], [[1., 1.]])`` is about 1e-6.
    """
    A, C = _concrete_pair(A, C, "pbh_margin")
    Ab, Cb, _ = balance_pair(A, C)
    return _margin(Ab, Cb)


OUTPUT_SCALE_WARN = 1e-10  # a row of C this small relative to the largest one is named in a warning


def observability_staircase(A, C, *, tol: float | None = None) -> ObservabilityStaircase:
    """Orthogonal staircase (observability Hessenberg) form of the balanced pair, and its rank decisions.

    On the balanced, unit-norm pair (A_b, C_b) (:func:`balance_pair`) a block Arnoldi sweep builds
    orthonormal directions level by level in the order of thesis §3.2, steps (a)-(e): level 0 tests the
    rows c_1 … c_m of C_b, level k the rows w_j A_b where w_j is the new part that output j contributed at
    level k − 1.  A candidate is independent when its component outside the directions found so far
    exceeds ``tol`` times its parent's norm times ‖A_b‖ (``tol`` times the row's own norm at level 0).  In
    the new coordinates C is [C_1, 0] and A is block Hessenberg: the staircase form.

    Every threshold is relative, on a pair scaled to unit norm: the decisions do not change under
    A → cA, C → SC (S diagonal: the units of the outputs), nor under a diagonal change of state units.
    A row of C below 1e-10 of the largest therefore counts as a sensor like any other: a warning says so
    (round-off in a row cannot be told from a sensor in small units; zero it if it is round-off).

    **Arguments:** `A` (n, n), `C` (m, n): concrete arrays; `tol`: relative tolerance (default 1e-9).

    **Returns:** an :class:`ObservabilityStaircase` (transformation, staircase pair, level sizes, the
    per-output indices ν_k of §3.2, the sorted (Kronecker) indices, rank, PBH margin, observable).

    **Example:** a chain ẋ1 = x2 with a static third state, y = (x1, x3)::

        st = observability_staircase([[0, 1, 0], [0, 0, 0], [0, 0, 0.]], [[1, 0, 0], [0, 0, 1.]])
        st.indices, st.blocks   # (2, 1), (2, 1)
    """
    A, C = _concrete_pair(A, C, "observability_staircase")
    tol = DEFAULT_TOL if tol is None else float(tol)
    if not 0 < tol < 1:
        # a relative tolerance of 1 or more declares every direction negligible: the pair would be
        # reported unobservable whatever it is
        raise ValueError(f"`tol` (a relative rank tolerance) must be in (0, 1), got {tol}.")
    n, m = A.shape[0], C.shape[0]
    rows = np.linalg.norm(C, axis=1)
    if np.any((rows > 0) & (rows < OUTPUT_SCALE_WARN * rows.max())):
        i = int(np.argmin(np.where(rows > 0, rows, np.inf)))
        warnings.warn(
            f"observability_staircase: row {i} of C is {rows[i] / rows.max():.1e} of the largest row.  Each "
            "output is taken in its own unit (the decisions do not change under C → diag(s)·C), so this row "
            "counts as a sensor as much as any other; if it is round-off, set it to zero or remove it.",
            stacklevel=2,
        )
    Ab, Cb, d = balance_pair(A, C)
    if d.size and d.max() > BALANCE_SPREAD_WARN * d.min():
        warnings.warn(
            f"observability_staircase: balancing (A, C) rescales the states over a range of "
            f"{d.max() / d.min():.1e}.  The decisions do not depend on state units, so an entry of A or C "
            "that small relative to the others counts as a coupling like any other; if it is round-off, "
            "set it to zero.",
            stacklevel=2,
        )
    nA = np.linalg.norm(Ab, 2)
    basis: list = []
    alive = [True] * m
    nu = [0] * m
    blocks = []
    # level 0: an output is kept when it is independent of those before it, relative to its own norm (a
    # zero row is dropped)
    res = lexicographic_step(basis, Cb, alive, list(tol * np.linalg.norm(Cb, axis=1)))
    while True:
        kept = [j for j in range(m) if np.any(res[j])]
        if not kept:
            break
        blocks.append(len(kept))
        for j in kept:
            nu[j] += 1
        if len(basis) == n:
            break
        parents = np.linalg.norm(res, axis=1)
        res = lexicographic_step(basis, res @ Ab, alive, tol * nA * parents)
    r = len(basis)
    Q = np.asarray(basis).reshape(r, n)
    if r < n:  # complete with an orthonormal basis of the unobservable part
        _, _, vt = np.linalg.svd(Q) if r else (None, None, np.eye(n))
        Q = np.concatenate([Q, vt[r:]]) if r else np.eye(n)
    T = Q / d[None, :]
    Tinv = Q.T * d[:, None]
    margin = _margin(Ab, Cb)
    kron = tuple(sum(1 for b in blocks if b > i) for i in range(max(blocks) if blocks else 0))
    return ObservabilityStaircase(
        T=T,
        A=T @ A @ Tinv,
        C=C @ Tinv,
        blocks=tuple(blocks),
        indices=tuple(nu),
        kronecker=kron,
        rank=r,
        margin=float(margin),
        tol=tol,
        observable=bool(r == n and margin > tol),
    )


def is_observable(A, C, tol: float | None = None) -> bool:
    """True when (A, C) is observable by the rank decisions of :func:`observability_staircase`.

    The test runs on the balanced pair scaled to unit norm: the staircase must reach rank n and the PBH
    margin min_λ σ_min([A − λI; C]) must exceed ``tol`` (default 1e-9).  It does not depend on the units
    of time (A → cA), of the outputs (C → dC) or of the states (diagonal scaling).

    **Example:** ``is_observable([[0., 1.], [0., 0.]], [[1., 0.]])`` → True.
    """
    return observability_staircase(A, C, tol=tol).observable


def require_observable(
    A, C, tol: float | None, who: str, *, independent_outputs: bool = False
) -> ObservabilityStaircase:
    """The staircase of (A, C), or ``ValueError`` naming ``who``, the rank and the PBH margin; with
    ``independent_outputs`` also a ``ValueError`` when the rows of C are linearly dependent (the
    staircase's first block is smaller than m)."""
    st = observability_staircase(A, C, tol=tol)
    m = np.shape(C)[0]
    if independent_outputs and st.blocks and st.blocks[0] < m:
        raise ValueError(
            f"{who}: the rows of `C` are linearly dependent (rank {st.blocks[0]} < m = {m} at tol "
            f"{st.tol:.1e}); remove the redundant outputs."
        )
    if not st.observable:
        n = st.T.shape[0]
        why = (
            f"the staircase finds rank {st.rank} < n = {n}"
            if st.rank < n
            else f"the PBH margin is below tol = {st.tol:.1e}"
        )
        raise ValueError(
            f"{who}: (A, C) is not observable ({why}; PBH margin min_λ σ_min([A − λI; C]) = "
            f"{st.margin:.2e} relative to ‖A‖, on the balanced pair).  Observer poles cannot be placed "
            "for an unobservable (or nearly unobservable) pair (thesis Lemma 1)."
        )
    return st
