"""The multi-output observable canonical form of thesis §3.2 (Theorem 1, (3.1c), Figs. 3.2-3.3), and the
observer designed on it as m single-output observers (Fig. 3.4).

With the lexicographic selection (a)-(e) of §3.2 the rows c_j A^i, i < ν_j, are independent and

    c_k A^{ν_k} = Σ_j Σ_i α_ij(k) c_j A^i,      α_ij(k) = 0 for i > ν_k, and for i = ν_k when j > k  (3.1c)

(the thesis writes it for the columns (Aᵀ)^i h_j with H = Cᵀ).  Subsystem k of Fig. 3.3 is a chain of ν_k
integrators driven by the outputs: with y = Cx,

    ż_{k,1} = Σ_j α_0j(k) y_j,     ż_{k,l} = z_{k,l−1} + Σ_j α_{l−1,j}(k) y_j  (l = 2 … ν_k),
    ȳ_k := z_{k,ν_k} = y_k − Σ_{j<k} α_{ν_k,j}(k) y_j,

so z = P x with the rows q_{k,ν_k} = c_k − Σ_{j<k} α_{ν_k,j}(k) c_j and q_{k,l−1} = q_{k,l} A − Σ_j
α_{l−1,j}(k) c_j; in these coordinates A_z = S + Γ C_z (S: ones on the sub-diagonal of each block, Γ the
α's), C_z = R E (E picks the last state of each block, R is unit lower triangular): "the subsystems are
coupled to each other only through their outputs", and y = R ȳ.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value
from ..analysis._lti import balance_pair, require_observable
from ._place import _finish, design_pair
from ._poles import PoleStructure


class ObservableCanonicalForm(NamedTuple):
    """The multi-output canonical form of thesis §3.2 (see :func:`observable_canonical_form`).

    - `P` (n, n): z = P x, the states of the subsystems block by block (z_{k,1} … z_{k,ν_k}).
    - `A` (n, n) = P A P⁻¹ = S + Γ C_z;  `C` (m, n) = C P⁻¹ = R E.
    - `indices`: (ν_1, …, ν_m).
    - `alpha`: tuple of m arrays, ``alpha[k]`` of shape (ν_k + 1, m) with ``alpha[k][i, j]`` = α_ij(k) of (3.1c).
    - `R` (m, m): unit lower triangular, y = R ȳ with ȳ_k = z_{k,ν_k} (the subsystem outputs of Fig. 3.3).
    - `Gamma` (n, m): ``Gamma[(k, l), j]`` = α_{l−1,j}(k), the output injections of Fig. 3.3.
    """

    P: jax.Array
    A: jax.Array
    C: jax.Array
    indices: tuple[int, ...]
    alpha: tuple[jax.Array, ...]
    R: jax.Array
    Gamma: jax.Array


def _selected(indices) -> list[tuple[int, int]]:
    """(i, j) of the rows c_j A^i kept by the search, in lexicographic order (power first)."""
    return [(i, j) for i in range(max(indices)) for j in range(len(indices)) if i < indices[j]]


def _form(A, C, indices, scale):
    """The canonical form for static `indices`; `scale` = (D, sA) makes the α solve well scaled."""
    m = C.shape[0]
    d, sA = scale
    An = (A * (d[None, :] / d[:, None])) / sA  # D⁻¹ A D / sA (similarity and time scaling)
    Cn = C * d[None, :]
    powers = [Cn]
    for _ in range(max(indices)):
        powers.append(powers[-1] @ An)
    sel = _selected(indices)
    O = jnp.stack([powers[i][j] for i, j in sel])  # (n, n), independent rows
    alphas = []
    for k in range(m):
        nu = indices[k]
        coef = jnp.linalg.solve(O.T, powers[nu][k])  # c_k A^ν_k in terms of the selected rows
        ak = jnp.zeros((nu + 1, m), A.dtype)
        for (i, j), c in zip(sel, coef):
            keep = i < nu or (i == nu and j < k)  # (3.1c): later rows have zero coefficients
            if keep:
                ak = ak.at[i, j].set(c * sA ** (nu - i))  # back to the units of A
        alphas.append(ak)
    rows = []
    for k in range(m):
        nu, ak = indices[k], alphas[k]
        q = C[k] - ak[nu, :k] @ C[:k]
        block = [q]
        for l in range(nu, 1, -1):  # q_{k,l−1} = q_{k,l} A − Σ_j α_{l−1,j}(k) c_j
            q = q @ A - ak[l - 1] @ C
            block.append(q)
        rows.extend(block[::-1])
    P = jnp.stack(rows)
    Atil = jnp.zeros((m, m), A.dtype)
    for k in range(m):
        Atil = Atil.at[k, :k].set(alphas[k][indices[k], :k])
    R = jnp.linalg.inv(jnp.eye(m, dtype=A.dtype) - Atil)
    Gamma = jnp.concatenate([alphas[k][: indices[k]] for k in range(m)], axis=0)
    # C P⁻¹ = R E and P A P⁻¹ = S + Γ C P⁻¹ exactly (module docstring): from the structure, not from P⁻¹,
    # whose rows differ in scale by powers of ‖A‖ (after a change of time or output units the products
    # with P⁻¹ lost every digit of the structural zeros and ones)
    S, E = _shift_and_pick(indices, A.dtype)
    Cz = R @ E
    return ObservableCanonicalForm(P, S + Gamma @ Cz, Cz, tuple(indices), tuple(alphas), R, Gamma)


def _shift_and_pick(indices, dtype):
    """S (n, n): ones on the sub-diagonal of each block (ż_{k,l} ∋ z_{k,l−1}); E (m, n): the last state
    of each block."""
    n, m = sum(indices), len(indices)
    S, E = np.zeros((n, n)), np.zeros((m, n))
    off = 0
    for k, nu in enumerate(indices):
        for i in range(1, nu):
            S[off + i, off + i - 1] = 1.0
        E[k, off + nu - 1] = 1.0
        off += nu
    return jnp.asarray(S, dtype), jnp.asarray(E, dtype)


def _indices_and_scale(A, C, tol, who):
    Av, Cv = concrete_value(A), concrete_value(C)
    if Av is None or Cv is None:
        raise ValueError(
            f"{who}: the observability indices are static: call it with concrete `A` and `C` "
            "(outside jit), or pass `indices`."
        )
    st = require_observable(Av, Cv, tol, who)
    if min(st.indices) < 1:
        raise ValueError(
            f"{who}: every output must contribute (indices {st.indices}); the rows of `C` are "
            "linearly dependent -- remove the redundant outputs."
        )
    _, _, d = balance_pair(Av, Cv)
    sA = max(np.linalg.norm(Av * (d[None, :] / d[:, None]), 2), np.finfo(float).tiny)
    return st.indices, (jnp.asarray(d), float(sA))


#: Under jit, the largest relative residual ‖P A − A_z P‖ / (‖P‖ (‖A‖ + ‖A_z‖)) a form is accepted with
#: (with the right indices it is at the rounding level times the conditioning of P; wrong indices
#: whose rows are independent leave a residual of order one).
_FORM_RTOL = 1e-6


def observable_canonical_form(A, C, *, tol: float | None = None, indices=None) -> ObservableCanonicalForm:
    """The multi-output observable canonical form of thesis §3.2, Theorem 1 ((3.1c), Figs. 3.2-3.3).

    The observability indices ν_k come from the lexicographic search (a)-(e) (decided on the staircase
    form, :func:`obsjax.analysis.observability_staircase`); the α_ij(k) of (3.1c) express c_k A^{ν_k}
    through the rows kept before it; the coordinates z = P x make the system m single-output
    subsystems (orders ν_k, Σ ν_k = n) coupled only through their outputs:

        ż_{k,1} = Σ_j α_0j(k) y_j,   ż_{k,l} = z_{k,l−1} + Σ_j α_{l−1,j}(k) y_j,
        z_{k,ν_k} = y_k − Σ_{j<k} α_{ν_k,j}(k) y_j,

    i.e. P A P⁻¹ = S + Γ C P⁻¹ and C P⁻¹ = R E (module docstring).  Differentiable in A and C (for fixed
    indices).  For m = 1 it is the observable companion form (python-control's ``observable_form``
    with the states in reverse order).

    **Arguments:** `A` (n, n), `C` (m, n) (concrete unless `indices` is given); `tol`: tolerance of the
    rank decisions; `indices`: the ν_k (to call it under ``jit``).

    **Returns:** an :class:`ObservableCanonicalForm` (P, A, C, indices, alpha, R, Gamma).

    **Example:** the fourth-order example of §3.2 (x1, x3 measured) has ν = (2, 2)::

        cf = observable_canonical_form(A4, [[1, 0, 0, 0], [0, 0, 1, 0]])
        cf.indices, cf.alpha[0]   # (2, 2), the α_ij(1)
    """
    A, C = design_pair(A, C, "observable_canonical_form")
    if indices is None:
        indices, scale = _indices_and_scale(A, C, tol, "observable_canonical_form")
    else:
        indices = tuple(int(v) for v in indices)
        if len(indices) != C.shape[0] or min(indices) < 1 or sum(indices) != A.shape[0]:
            raise ValueError(
                f"`indices` must be {C.shape[0]} positive integers summing to n = {A.shape[0]}, "
                f"got {indices}."
            )
        scale = (jnp.ones(A.shape[0]), 1.0)
        if concrete_value(A) is not None and concrete_value(C) is not None:
            true, _ = _indices_and_scale(A, C, tol, "observable_canonical_form")
            if tuple(true) != indices:
                raise ValueError(
                    f"`indices` must be the observability indices of (A, C), which are {tuple(true)}, "
                    f"got {indices}: with others the rows of P are dependent (P singular)."
                )
    cf = _form(A, C, indices, scale)
    if concrete_value(A) is None or concrete_value(C) is None:  # traced: indices that do not fit give NaN
        # indices that do not fit give NaN (P singular) or, when the rows they pick are independent
        # but are not the lexicographic ones, a form whose coefficients drop terms: P A ≠ A_z P
        res = jnp.linalg.norm(cf.P @ A - cf.A @ cf.P) / (
            jnp.linalg.norm(cf.P) * (jnp.linalg.norm(A) + jnp.linalg.norm(cf.A)) + jnp.finfo(A.dtype).tiny
        )
        bad = ~(jnp.all(jnp.isfinite(cf.P)) & jnp.all(jnp.isfinite(cf.A)) & (res <= _FORM_RTOL))
        msg = (
            "observable_canonical_form: `indices` are not the observability indices of the pair (A, C) "
            "(the transformation P is singular, or P A ≠ A_z P: the form does not describe the pair)."
        )
        # on every matrix of the form, so that the check is not dead code of a field left unread
        cf = cf._replace(**{k: eqx.error_if(getattr(cf, k), bad, msg) for k in ("P", "A", "C", "R", "Gamma")})
    return cf


def assign_subsystems(structure: PoleStructure, indices) -> list[list[int]]:
    """Positions of the poles given to each subsystem (orders ν_k): conjugate pairs first, each to the
    first subsystem with two free places, then the real poles in order."""
    free = list(indices)
    out: list[list[int]] = [[] for _ in indices]
    units = [(2, [u, d]) for kind, up, dn in structure.clusters if kind == 2 for u, d in zip(up, dn)]
    units += [(1, [i]) for kind, idx, _ in structure.clusters if kind == 1 for i in idx]
    for size, pos in units:
        k = next((k for k in range(len(free)) if free[k] >= size), None)
        if k is None:
            raise ValueError(
                f"method='canonical': a conjugate pair cannot be split between subsystems of orders "
                f"{tuple(indices)}; choose real poles for the first-order subsystems or use "
                "method='robust'."
            )
        out[k].extend(pos)
        free[k] -= size
    return out


def _warn_repeated_in_block(structure: PoleStructure, groups, pr, pi, who):
    """A companion block is non-derogatory: a root repeated s times within one subsystem is a Jordan
    block of size s, whose eigenvalues move by about ε^(1/s) under a perturbation ε.  Warn (at trace
    time), as the robust method does for its Jordan chains."""
    cid = {}
    for c, (kind, up, dn) in enumerate(structure.clusters):
        for i in up:
            cid[i] = c
    worst = []
    for k, pos in enumerate(groups):
        counts: dict[int, int] = {}
        for i in pos:
            if i in cid:  # a real pole, or the Im > 0 member of a pair
                counts[cid[i]] = counts.get(cid[i], 0) + 1
        worst += [(k, c, s) for c, s in counts.items() if s > 1]
    if not worst:
        return
    vr, vi = concrete_value(pr), concrete_value(pi)

    def name(c):
        i = structure.clusters[c][1][0]
        return f"{complex(vr[i], vi[i]):.4g}" if vr is not None and vi is not None else f"cluster {c}"

    what = ", ".join(f"{name(c)} ×{s} in subsystem {k + 1}" for k, c, s in worst)
    warnings.warn(
        f"{who}: method='canonical' gives repeated poles ({what}) to one companion block, i.e. a Jordan "
        "block: such a gain is sensitive (an eigenvalue of a Jordan block of size s moves by about ε^(1/s) "
        "under a perturbation ε of A, C or L), and the accuracy check then bounds only the backward error. "
        "method='robust' assigns up to m copies of a pole with independent eigenvectors.",
        stacklevel=4,
    )


def canonical_gain(A, C, pr, pi, structure: PoleStructure, *, tol, rtol, who, indices=None, finite=None):
    """Gain of the canonical design (Fig. 3.4): in z = P x each subsystem k gets the observer-companion
    error dynamics S_k − g_k e_{ν_k}ᵀ with the characteristic polynomial of its poles, i.e.
    L_z = Γ + G_b R⁻¹ and L = P⁻¹ L_z."""
    if indices is None:
        indices, scale = _indices_and_scale(A, C, tol, who)
    else:
        scale = (jnp.ones(A.shape[0]), 1.0)
    cf = _form(A, C, tuple(indices), scale)
    n, m = A.shape[0], C.shape[0]
    groups = assign_subsystems(structure, indices)
    _warn_repeated_in_block(structure, groups, pr, pi, who)
    Gb = jnp.zeros((n, m), A.dtype)
    Fc = jnp.zeros((n, n), A.dtype)
    start = 0
    for k, pos in enumerate(groups):
        nu = indices[k]
        coeffs = jnp.ones((1,), jnp.complex128)
        for i in pos:
            coeffs = jnp.convolve(coeffs, jnp.stack([jnp.ones((), jnp.complex128), -(pr[i] + 1j * pi[i])]))
        g = jnp.real(coeffs[1:])[::-1]  # s^ν + a_1 s^{ν−1} + … + a_ν  →  g = (a_ν, …, a_1)
        Gb = Gb.at[start : start + nu, k].set(g)
        Fc = Fc.at[start : start + nu, start + nu - 1].set(-g)
        if nu > 1:
            Fc = Fc.at[start + 1 : start + nu, start : start + nu - 1].add(jnp.eye(nu - 1))
        start += nu
    Lz = cf.Gamma + Gb @ jnp.linalg.inv(cf.R)
    L = jnp.linalg.solve(cf.P, Lz)
    err, kappa = _companion_error_estimate(A, C, L, cf.P, Fc, indices, groups, structure, pr, pi)
    return _finish(L, err, kappa, rtol, who, finite)


def _value_ids(structure: PoleStructure) -> np.ndarray:
    """An id per position of the pole vector, equal for positions holding the same value."""
    ids = np.zeros(structure.n, np.int64)
    for c, (kind, up, dn) in enumerate(structure.clusters):
        ids[list(up)] = 2 * c
        if kind == 2:
            ids[list(dn)] = 2 * c + 1
    return ids


def _companion_error_estimate(A, C, L, P, F, indices, groups, structure, pr, pi):
    """A-posteriori relative error of the eigenvalues placed by the canonical design.

    In z = P x the requested closed loop is F, block diagonal with the observer-companion blocks
    F_k = S_k − g_k e_νᵀ whose characteristic polynomials p_k carry the requested poles.  For a root λ of
    p_k that is simple in p_k, the left and right eigenvectors of F_k are w = (1, λ, …, λ^{ν−1}) and v with
    v_ν = 1, v_{i−1} = λ v_i + g_i (the quotient p_k(s)/(s − λ)), wᵀv = p_k′(λ).  In the original
    coordinates x = P⁻¹v and yᵀ = wᵀP are approximate eigenvectors of A − LC; with the residual
    r = A x − L(C x) − λx the eigenvalue moves by (first order, Wilkinson)

        ( |yᵀ r| + 4ε·|y|ᵀ(|A||x| + |L||Cx| + |λ||x|) ) / |yᵀ x|,

    the second term bounding the rounding of the residual.  The residual is formed without the matrix
    A − LC: rounding the product L·C perturbs the roots by more than the gain itself does (the closed loop
    of the observer is also evaluated as A x̂ + L(y − C x̂)).  A companion design loses accuracy through the
    sensitivity of a polynomial's roots to its coefficients (poles −1, …, −12 in one block: exact error
    2.4e-5 for a random n = 12), and this estimate carries it (within 10-100× of the exact error in the
    tests, never below it); the backward error of a block alone does not.  A root repeated within p_k is a
    Jordan chain: its error is the backward error ‖Δ_k‖ of the block, Δ = P(A − LC)P⁻¹ − F (row and column
    block k), as for the robust method's defective clusters.  Each error is relative to
    max(|λ|, 10⁻³·max_k|λ_k|) (‖A‖_F if every pole is 0).  Returns (largest relative error, Frobenius condition number of P)."""
    P, L = jax.lax.stop_gradient(P), jax.lax.stop_gradient(L)
    pr, pi = jax.lax.stop_gradient(pr), jax.lax.stop_gradient(pi)
    Pi = jnp.linalg.inv(P)
    D = (P @ (A - L @ C)) @ Pi - F
    eps = jnp.finfo(A.dtype).eps
    tiny = jnp.finfo(A.dtype).tiny
    lam_all = pr + 1j * pi
    lmax = jnp.max(jnp.abs(lam_all))  # the floor as in _place._error_estimate (not ‖A‖_F: units)
    big = jnp.where(lmax > 0, lmax, jnp.linalg.norm(A))
    floor = 1e-3 * jnp.where(big > 0, big, 1.0)
    ids = _value_ids(structure)
    worst = jnp.zeros((), A.dtype)
    start = 0
    for k, pos in enumerate(groups):
        nu = indices[k]
        sl = slice(start, start + nu)
        pos = np.asarray(pos)
        lam = lam_all[pos].astype(jnp.complex128)  # (r,) the poles of block k
        repeated = np.array([np.sum(ids[pos] == ids[i]) > 1 for i in pos])
        if np.any(repeated):
            dk = jnp.sqrt(jnp.sum(D[sl, :] ** 2) + jnp.sum(D[:, sl] ** 2) - jnp.sum(D[sl, sl] ** 2))
        else:
            dk = jnp.zeros((), A.dtype)
        g = -F[sl, start + nu - 1]
        cols = [jnp.ones_like(lam)]  # right eigenvectors of F_k: v_ν = 1, v_{i−1} = λ v_i + g_i
        for i in range(nu - 1, 0, -1):
            cols.append(lam * cols[-1] + g[i])
        V = jnp.stack(cols[::-1], axis=0)  # (ν, r)
        W = lam[None, :] ** jnp.arange(nu)[:, None]  # (ν, r) left eigenvectors
        X = Pi[:, sl] @ V  # (n, r)
        Y = W.T @ P[sl, :]  # (r, n)
        # the residual of A − LC without forming it: rounding L·C would perturb the (ill-conditioned)
        # roots by more than the gain does
        CX = C @ X
        R = A @ X - L @ CX - X * lam[None, :]
        Ya = jnp.abs(Y).T  # (n, r)
        size = jnp.abs(A) @ jnp.abs(X) + jnp.abs(L) @ jnp.abs(CX) + jnp.abs(X) * jnp.abs(lam)[None, :]
        yx = jnp.abs(jnp.sum(Y.T * X, axis=0))
        yx = jnp.where(yx > 0, yx, tiny)
        simple_est = (jnp.abs(jnp.sum(Y.T * R, axis=0)) + 4 * eps * jnp.sum(Ya * size, axis=0)) / yx
        est = jnp.where(jnp.asarray(repeated), dk, simple_est)
        rel = est / jnp.maximum(jnp.abs(lam), floor)
        worst = jnp.maximum(worst, jnp.max(rel))
        start += nu
    kappa = jnp.linalg.norm(P) * jnp.linalg.norm(Pi)
    return worst, kappa
