"""Observer gain design: pole placement, Sylvester equations, observability indices."""

from __future__ import annotations

import functools
import warnings
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array, concrete_value, device_array, host_array, require_finite, static_value
from .._config import require_x64
from ..analysis._lti import _pair, balancing, observability_staircase, require_observable
from ._poles import (
    CLUSTER_RTOL,
    REAL_RTOL,
    PoleStructure,
    blocks_of,
    default_structure,
    jordan_summary,
    pole_structure,
)
from ._robust import _MAXITER, after, make_layout, robust_gain

#: Default bound on the a-posteriori relative eigenvalue error of a placed gain.
PLACE_RTOL = 1e-6


def as_design_matrix(x, name: str) -> jax.Array:
    """A real matrix in float64 (float32 and integer inputs are promoted: designs run in float64)."""
    arr = as_float_array(x, name)
    if jnp.issubdtype(arr.dtype, jnp.complexfloating):
        raise ValueError(f"`{name}` must be real, got dtype {arr.dtype}.")
    return arr.astype(jnp.float64)


def design_pair(A, C, who: str):
    """(A, C) validated, promoted to float64; raises under OBSJAX_NO_X64 rather than design in float32."""
    require_x64(who)
    A, C = _pair(A, C)
    A, C = as_design_matrix(A, "A"), as_design_matrix(C, "C")
    if A.shape[0] == 0:
        raise ValueError(f"{who}: `A` has no states (shape {tuple(A.shape)}): nothing to observe.")
    if C.shape[0] > A.shape[0]:
        raise ValueError(
            f"`C` has m = {C.shape[0]} rows for n = {A.shape[0]} states: at most n independent outputs."
        )
    return A, C


def pole_vector(poles, n: int, who: str = "place") -> jax.Array:
    """The poles as a vector of length n (float64 or complex128)."""
    h = host_array(poles)
    if h is not None and h.dtype != np.bool_ and h.ndim <= 1 and h.size == n:
        # host poles (the usual case): converted by NumPy, no program compiled
        h = h.reshape(n)
        return device_array(h, dtype=np.complex128 if np.iscomplexobj(h) else np.float64)
    try:
        p = jnp.asarray(poles)
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"`poles` must be array-like, got {type(poles).__name__}: {e}") from None
    if p.dtype == jnp.bool_:
        raise ValueError(f"{who}: `poles` must be numbers, got booleans {np.asarray(p).tolist()}.")
    if p.ndim == 0:
        p = p.reshape(1)
    if p.ndim != 1 or p.shape[0] != n:
        got = p.shape[0] if p.ndim == 1 else p.shape
        raise ValueError(f"{who}: `poles` must hold exactly n = {n} observer poles, got {got}.")
    if jnp.issubdtype(p.dtype, jnp.complexfloating):
        return p.astype(jnp.complex128)
    return p.astype(jnp.float64)


def resolve_structure(poles, structure: PoleStructure | None, n: int) -> PoleStructure:
    """The pole pattern: read from concrete poles, given, or (traced real poles) n distinct reals."""
    v = concrete_value(poles)
    if v is not None:
        found = pole_structure(v)
        if structure is not None and structure != found:
            raise ValueError(
                f"`structure` {structure} does not match the pattern of `poles` {found}."
            )
        return found
    if structure is not None:
        if not isinstance(structure, PoleStructure) or structure.n != n:
            raise ValueError(
                f"`structure` must be a PoleStructure of n = {n} poles (obsjax.design.pole_structure)."
            )
        return structure
    if jnp.issubdtype(poles.dtype, jnp.complexfloating):
        raise ValueError(
            "Traced complex `poles`: their pattern (which are conjugate pairs, which repeat) cannot be "
            "read under jit; pass `structure=obsjax.design.pole_structure(example_poles)`."
        )
    return default_structure(n)


class Pattern(NamedTuple):
    """A pole pattern and its Jordan chains as arrays of length n (data, so that patterns share one
    compiled program): per pole its cluster id `pc`, a reference copy `ref`, whether it is real, the
    member with Im > 0 of a pair (`up`) and its conjugate's position (`partner`); per row of T its
    cluster id `rc` and whether that cluster is defective (`rdef`)."""

    pc: jax.Array
    ref: jax.Array
    real: jax.Array
    up: jax.Array
    partner: jax.Array
    rc: jax.Array
    rdef: jax.Array


def make_pattern(structure: PoleStructure, blocks) -> Pattern:
    n = structure.n
    pc, ref, partner = np.zeros(n, np.int32), np.zeros(n, np.int32), np.arange(n, dtype=np.int32)
    real, up = np.zeros(n, bool), np.zeros(n, bool)
    for c, (kind, u, d) in enumerate(structure.clusters):
        pc[list(u)], ref[list(u)] = c, u[0]
        if kind == 1:
            real[list(u)] = True
        else:
            pc[list(d)], ref[list(d)] = c, d[0]
            up[list(u)] = True
            partner[list(u)], partner[list(d)] = d, u
    rc, rdef = np.zeros(n, np.int32), np.zeros(n, bool)
    r = 0
    for b in blocks:
        rc[r : r + b.kind * b.length] = b.cluster
        r += b.kind * b.length
    for b in blocks:
        if b.length > 1:
            rdef[rc == b.cluster] = True
    return Pattern(*(device_array(a) for a in (pc, ref, real, up, partner, rc, rdef)))


def _pattern_flags(pr, pi, pat: Pattern):
    """(non-finite, not conjugate-closed, real pole with an imaginary part, copies apart)."""
    nonfinite = ~(jnp.all(jnp.isfinite(pr)) & jnp.all(jnp.isfinite(pi)))
    mag = jnp.abs(pr + 1j * pi)
    copies = jnp.any(jnp.abs(pr - pr[pat.ref]) + jnp.abs(pi - pi[pat.ref]) > CLUSTER_RTOL * mag)
    imag = jnp.any(pat.real & (jnp.abs(pi) > REAL_RTOL * mag))
    conj = jnp.any(
        pat.up
        & (
            (pi <= 0)
            | (jnp.abs(pr[pat.partner] - pr) + jnp.abs(pi[pat.partner] + pi) > CLUSTER_RTOL * mag)
        )
    )
    return nonfinite, conj, imag, copies


def _check_pattern(pr, pi, pat: Pattern, who: str):
    """The pole values against their declared pattern, under jit (eqx.error_if naming the poles)."""
    nonfinite, conj, imag, copies = _pattern_flags(pr, pi, pat)
    pr = eqx.error_if(pr, nonfinite, f"{who}: `poles` must be finite (a NaN or an infinity was passed).")
    pr = eqx.error_if(
        pr,
        conj,
        f"{who}: `poles` must be closed under conjugation: a complex pole lacks its conjugate at the "
        "position the structure declares.",
    )
    pr = eqx.error_if(pr, imag, f"{who}: a pole declared real by the structure has an imaginary part.")
    pr = eqx.error_if(
        pr,
        copies,
        f"{who}: the copies of a repeated pole (declared by the structure) are no longer equal; give "
        "distinct poles their own structure entries.",
    )
    return pr, pi


def cluster_values(pat: Pattern, pr, pi):
    """The requested value of each cluster id (mean of its copies, the member with Im ≥ 0), length n."""
    n = pr.shape[0]
    w = jnp.where(pat.real | pat.up, 1.0, 0.0)
    tot = jax.ops.segment_sum(w * (pr + 1j * pi), pat.pc, num_segments=n)
    cnt = jax.ops.segment_sum(w, pat.pc, num_segments=n)
    return tot / jnp.where(cnt > 0, cnt, 1.0)


def warn_jordan(structure, blocks, pr, pi, m, kron, who, stacklevel=4):
    """Warn (at design time) about poles assigned with Jordan chains: such gains are sensitive."""
    if not any(b.length > 1 for b in blocks):
        return
    vals = concrete_value(pr), concrete_value(pi)
    names = (
        jordan_summary(structure, blocks, vals[0] + 1j * vals[1])
        if vals[0] is not None and vals[1] is not None
        else ["(traced values)"]
    )
    why = f"observability indices {tuple(kron)}" if kron is not None else "the pattern of the poles"
    warnings.warn(
        f"{who}: poles {', '.join(names)} cannot all have independent eigenvectors with m = {m} "
        f"output(s) and {why}; they are assigned with Jordan chains.  Such a gain is sensitive: an "
        "eigenvalue of a Jordan block of size s moves by about ε^(1/s) under a perturbation ε of A, "
        "C or L.",
        stacklevel=stacklevel,
    )


@functools.partial(jax.jit, static_argnames=("m", "depth", "maxiter"))
def _robust_core(lay, pat, A, C, pr, pi, d, e, *, m, depth, maxiter):
    """Checks, placement and a-posteriori error in one program (one compilation per (n, m, depth)).

    The placement runs on the pair in balanced units, (D⁻¹ A D, E C D) with the scalings of
    :func:`obsjax.analysis._lti.balancing`, and L = D L_b E: A − LC = D (A_b − L_b C_b) D⁻¹ has the
    same eigenvalues, and the gain does not depend on the units of the states or outputs (the design of
    (S A S⁻¹, Λ C S⁻¹) is S L Λ⁻¹).  Without it the eigenvector criterion would be measured in whatever
    units the states were given in: a state in µ-units and another in M-units made a well-posed MIMO
    placement fail its a-posteriori check.  ``d``, ``e`` come from :func:`_scalings`: computed in NumPy
    for concrete A and C, traced (a differentiable function of A and C for a fixed zero pattern, so the
    derivative of L is that of the whole design) when they are traced."""
    pr, pi = _check_pattern(pr, pi, pat, "place")
    Ab = A * (d[None, :] / d[:, None])
    Cb = C * e[:, None] * d[None, :]
    Lb, T, F = robust_gain(m, depth, maxiter, lay, Ab, Cb, pr, pi)
    err, kappa = _error_estimate(Ab, Cb, Lb, T, F, pat.rc, pat.rdef, cluster_values(pat, pr, pi))
    return d[:, None] * Lb * e[None, :], err, kappa


def _scalings(A, C):
    """The balancing (d, e) of the pair (:func:`obsjax.analysis._lti.balancing`): in NumPy when A and C
    are concrete (no compilation), traced otherwise (the same operations, so the same gain)."""
    Av, Cv = static_value(A), static_value(C)
    if Av is not None and Cv is not None:
        d, e = balancing(np.asarray(Av, dtype=float), np.asarray(Cv, dtype=float))
        return device_array(d), device_array(e)
    return balancing(A, C)


def _real_form(structure: PoleStructure, pr, pi):
    """F (n × n, real) with the requested spectrum in pole order: λ on the diagonal for a real pole, and
    for a pair a ± ib at positions (u, d) the block [[a, b], [−b, a]] on rows and columns (u, d); with the
    cluster id of each row and each cluster's value (Im ≥ 0) for :func:`_error_estimate`."""
    n = structure.n
    F = jnp.diag(pr)
    rc = np.zeros(n, np.int32)
    ups, dns = [], []
    for k, (kind, up, dn) in enumerate(structure.clusters):
        rc[list(up) + list(dn)] = k
        if kind == 2:
            ups += list(up)
            dns += list(dn)
    if ups:
        u, d = np.asarray(ups), np.asarray(dns)
        F = F.at[u, d].set(pi[u]).at[d, u].set(-pi[u])
    first = np.array([c[1][0] for c in structure.clusters])
    lam = jnp.zeros(n, complex).at[: len(first)].set(pr[first] + 1j * jnp.abs(pi[first]))
    return F, jnp.asarray(rc), lam


@functools.partial(jax.jit, static_argnums=0)
def _square_core(structure: PoleStructure, A, C, pr, pi):
    """m = n (C invertible): L = (A − F) C⁻¹ gives A − LC = F exactly, the real form of the poles, whose
    eigenvector matrix is orthogonal-block (T = I, perfectly conditioned).  Any T would do (the robust
    criterion is flat there), so this fixed choice also makes L a smooth function of the poles, whose
    derivative is that of the formula (the iterative minimiser's choice among equals is not)."""
    F, rc, lam = _real_form(structure, pr, pi)
    L = jnp.linalg.solve(C.T, (A - F).T).T
    n = A.shape[0]
    err, kappa = _error_estimate(A, C, L, jnp.eye(n, dtype=A.dtype), F, rc, jnp.zeros(n, bool), lam)
    return L, err, kappa


def _error_estimate(A, C, L, T, F, rc, defective, lam):
    """A-posteriori relative error of the placed eigenvalues.

    With X = T⁻¹ and M = T X (= I up to rounding), G = M⁻¹ T (A X − L (C X)) is similar to A − LC (by X)
    and Δ = G − F.  The closed loop is never formed: rounding the product L·C would perturb ill-conditioned
    eigenvalues by more than the gain does (the observer itself evaluates A x̂ + L(y − C x̂)).  For a
    cluster of rows R sharing a requested value λ (F normal on it), the eigenvalues move by about ‖Δ_RR‖
    (first order; Bauer-Fike on the block), plus the rounding of Δ_RR, bounded entrywise by
    4ε·|T|(|A||X| + |L||CX| + |A X − L C X|), plus the second-order coupling Σ_{i∈R, j∉R} |Δ_ij||Δ_ji| /
    |λ_i − λ_j| (with the rounding added to |Δ|), all doubled; if ‖Δ‖ (with its rounding) reaches a quarter of the gap
    between requested values, it is used instead.  For a defective (Jordan) cluster, ‖Δ_RR‖ is the
    backward error (the gain places the Jordan structure for a matrix that close).  Each error is relative
    to max(|λ|, 10⁻³·max_k|λ_k|) (‖A‖_F if every pole is 0).  Returns (largest relative error, Frobenius condition number of
    T)."""
    T, L = jax.lax.stop_gradient(T), jax.lax.stop_gradient(L)
    T = after(L, T)  # one batched factorisation at a time (see `_robust.after`)
    n = A.shape[0]
    ncl = n  # cluster ids < n; unused ids are ignored below
    Ti = jnp.linalg.inv(T)
    CX = C @ Ti
    Z = A @ Ti - L @ CX
    D = jnp.linalg.solve(T @ Ti, T @ Z) - F
    eps = jnp.finfo(A.dtype).eps
    rnd = 4.0 * eps * (jnp.abs(T) @ (jnp.abs(A) @ jnp.abs(Ti) + jnp.abs(L) @ jnp.abs(CX) + jnp.abs(Z)))
    same = rc[:, None] == rc[None, :]

    def per_cluster(E):
        return jnp.sqrt(jax.ops.segment_sum(jnp.sum(jnp.where(same, E**2, 0.0), axis=1), rc, num_segments=ncl))

    dc, rc_rnd = per_cluster(D), per_cluster(rnd)
    used = jax.ops.segment_sum(jnp.ones(n), rc, num_segments=ncl) > 0
    defective = jax.ops.segment_max(defective.astype(jnp.int32), rc, num_segments=ncl) > 0
    lam = jax.lax.stop_gradient(lam)
    # second order: the coupling of row i to the other clusters moves λ by Σ_j Δ_ij Δ_ji / (λ_i − λ_j)
    E = jnp.abs(D) + rnd
    lr = lam[rc]
    grow = jnp.where(same, jnp.inf, jnp.abs(lr[:, None] - lr[None, :]))
    second = jax.ops.segment_sum(jnp.sum(E * E.T / grow, axis=1), rc, num_segments=ncl)
    # twice the first- and second-order terms: the higher orders (and the rounding of Δ itself) are
    # covered with a margin; measured against 60-digit eigenvalues the first-order term alone can be
    # the exact error to 4 digits (a badly scaled A), and an estimate must not fall below it
    est = jnp.where(defective, dc, 2.0 * (dc + rc_rnd + second))
    # the floor of the relative error: 10⁻³·max|λ_k| (‖A‖_F only when every pole is 0), as in
    # analysis.placement_error -- not ‖A‖_F, which a change of state units moves arbitrarily
    lmax = jnp.max(jnp.where(used, jnp.abs(lam), 0.0))
    big = jnp.where(lmax > 0, lmax, jnp.linalg.norm(A))
    pairs = used[:, None] & used[None, :] & ~jnp.eye(ncl, dtype=bool)
    gap = jnp.where(pairs, jnp.abs(lam[:, None] - lam[None, :]), jnp.inf)
    dn = jnp.linalg.norm(D) + jnp.linalg.norm(rnd)
    est = jnp.where(dn >= 0.25 * jnp.min(gap), jnp.maximum(est, dn), est)
    rel = est / jnp.maximum(jnp.abs(lam), 1e-3 * jnp.where(big > 0, big, 1.0))
    kappa = jnp.linalg.norm(T) * jnp.linalg.norm(Ti)  # Frobenius condition number of T
    return jnp.max(jnp.where(used, rel, 0.0)), kappa


def _sanitize_poles(pr, pi, structure: PoleStructure):
    """Traced poles that are not all finite are replaced, for the computation only, by a finite vector of
    the same structure (cluster k at −(k + 1), pairs ± i); returns (pr, pi, finite) with `finite` the
    traced flag (``None`` for concrete poles, which are checked by the caller)."""
    if concrete_value(pr) is not None and concrete_value(pi) is not None:
        return pr, pi, None
    fr, fi = np.zeros(structure.n), np.zeros(structure.n)
    for k, (kind, up, dn) in enumerate(structure.clusters):
        fr[list(up) + list(dn)] = -(k + 1.0)
        if kind == 2:
            fi[list(up)], fi[list(dn)] = 1.0, -1.0
    finite = jnp.all(jnp.isfinite(pr)) & jnp.all(jnp.isfinite(pi))
    return jnp.where(finite, pr, fr), jnp.where(finite, pi, fi), finite


def _finish(L, err, kappa, rtol: float, who: str, finite=None):
    """Raise (concrete) or stop at run time (eqx.error_if) when the gain is not finite or the
    a-posteriori eigenvalue error exceeds rtol.  Traced poles that are not finite (`finite` False, see
    :func:`_sanitize_poles`) give a NaN gain instead of the run-time error: the simulation's status
    says NONFINITE for that member of a batch (a NaN pole is a bad input of one trajectory, not a
    design on which the whole batch must stop), and ``simulate(throw=True)`` raises on it."""
    if finite is None and not any(isinstance(v, jax.core.Tracer) for v in (L, err, kappa)):
        # concrete: decided in NumPy (the same test; run eagerly, JAX compiles a program per operation).
        # np.asarray, not concrete_value: reading a result raises a check that fired inside the kernel,
        # where concrete_value would return None and lose its message.
        e, k = np.asarray(err), np.asarray(kappa)
        okv = np.all(np.isfinite(np.asarray(L))) & (e <= rtol)
    else:
        e, k = concrete_value(err), concrete_value(kappa)
        ok = jnp.all(jnp.isfinite(L)) & (err <= rtol)
        if finite is not None:
            L, ok = jnp.where(finite, L, jnp.nan), ok | ~finite
        okv = concrete_value(ok)
    if okv is not None:
        if not bool(okv) and not np.all(np.isfinite(np.asarray(concrete_value(L)))):
            raise ValueError(
                f"{who}: the computed gain is not finite (the eigenvector computation broke down; "
                f"a-posteriori error {float(e):.2e}, eigenvector condition number {float(k):.2e}).  No "
                "`rtol` accepts it: (A, C) is nearly unobservable, or the poles ask for an eigenstructure "
                "that cannot be computed in float64 (try distinct poles, or `method='canonical'`)."
            )
        if not bool(okv):
            raise ValueError(
                f"{who}: the computed gain does not place the poles to rtol = {rtol:.1e} (a-posteriori "
                f"relative eigenvalue error {float(e):.2e}, eigenvector condition number "
                f"{float(k):.2e}): (A, C) is nearly unobservable, or the poles ask for an eigenstructure "
                "too ill-conditioned to be placed in float64 (raise `rtol` to accept it)."
            )
        return L
    return eqx.error_if(
        L,
        ~ok,
        f"{who}: the computed gain does not place the poles to `rtol` (non-finite gain or a-posteriori "
        "eigenvalue error above rtol): (A, C) is nearly unobservable, the poles ask for an "
        "ill-conditioned eigenstructure, a repeated pole exceeds the number of outputs, or traced "
        "poles repeat without their pattern: under jit poles are taken as distinct unless "
        "`structure=obsjax.design.pole_structure(poles)` is given.",
    )


def place_real(
    A,
    C,
    pr,
    pi,
    structure: PoleStructure,
    *,
    method: str = "robust",
    tol: float | None = None,
    rtol: float = PLACE_RTOL,
    maxiter: int = _MAXITER,
    blocks=None,
    indices=None,
    warn: bool = True,
    who: str = "place",
    nan_for_nonfinite_poles: bool = False,
):
    """:func:`place` on validated float64 (A, C) and the real and imaginary parts of the poles
    (``blocks``: the Jordan chains decided earlier on the concrete model, see :func:`blocks_of`).

    ``nan_for_nonfinite_poles`` (the observers' gains): traced poles that are not finite give a NaN gain
    (the trajectory's status NONFINITE, per member under vmap) instead of the run-time error that
    :func:`place` raises."""
    n, m = A.shape[0], C.shape[0]
    Av, Cv = concrete_value(A), concrete_value(C)
    kron = None
    if Av is not None and Cv is not None and blocks is None and indices is None:
        st = require_observable(Av, Cv, tol, who, independent_outputs=True)
        kron = st.kronecker
    elif not (
        Av is not None and Cv is not None and np.all(np.isfinite(Av)) and np.all(np.isfinite(Cv))
    ):  # (concrete and finite: nothing to check, and the checks run eagerly would each compile)
        A = eqx.error_if(A, ~jnp.all(jnp.isfinite(A)), f"{who}: `A` must be finite.")
        C = eqx.error_if(C, ~jnp.all(jnp.isfinite(C)), f"{who}: `C` must be finite.")
    finite = None
    if nan_for_nonfinite_poles:
        pr, pi, finite = _sanitize_poles(pr, pi, structure)
    if method == "canonical":
        from ._canonical import canonical_gain

        pr, pi = _check_pattern(pr, pi, make_pattern(structure, ()), who)
        return canonical_gain(
            A, C, pr, pi, structure, tol=tol, rtol=rtol, who=who, indices=indices, finite=finite
        )
    if method != "robust":
        raise ValueError(f"`method` must be 'robust' or 'canonical', got {method!r}.")
    if m == n:
        pr, pi = _check_pattern(pr, pi, make_pattern(structure, ()), who)
        L, err, kappa = _square_core(structure, A, C, pr, pi)
        return _finish(L, err, kappa, rtol, who, finite)
    blocks = blocks_of(structure, m, kron) if blocks is None else blocks
    if warn:
        warn_jordan(structure, blocks, pr, pi, m, kron, who)
    lay, depth = make_layout(blocks, n)
    d, e = _scalings(A, C)
    L, err, kappa = _robust_core(
        lay, make_pattern(structure, blocks), A, C, pr, pi, d, e, m=m, depth=depth, maxiter=maxiter
    )
    return _finish(L, err, kappa, rtol, who, finite)


def place(
    A,
    C,
    poles,
    *,
    method: str = "robust",
    tol: float | None = None,
    rtol: float = PLACE_RTOL,
    structure: PoleStructure | None = None,
    maxiter: int = _MAXITER,
) -> jax.Array:
    """Observer gain L (n, m) with eig(A − L C) = ``poles`` (thesis Lemma 1, (2.7)).

    The identity observer (2.7) ż = (A − LC) z + L y + B u then has the requested dynamics.

    **Methods.**

    - ``"robust"`` (default, any m): the eigenvector method.  With F real block-diagonal holding the
      requested spectrum and T a real matrix of left eigenvectors, T A − F T = G C (thesis Theorem 1,
      (2.2)-(2.4)) and L = (A − T⁻¹FT) C⁺; each row of T lies in the m-dimensional space
      {t : t(A − λI) ∈ rowspace C} (an orthonormal basis from a QR factorisation of the PBH matrix
      [A − λI; C], as in Kautsky, Nichols & Van Dooren, Int. J. Control 41(5), 1985), chosen to minimise
      the Tits-Yang measure Σ log‖t_k‖ − log|det T| (Tits & Yang, IEEE TAC 41(10), 1996) by Newton's
      method: well-conditioned eigenvectors, hence a small gain and eigenvalues accurate to about
      ε·cond(T).  Single output: the eigenvectors are unique and the formula is exact.
    - ``"canonical"``: thesis §3.2: the multi-output canonical form (3.1c) splits the pair into m
      single-output subsystems of orders ν_1 … ν_m, coupled only through the outputs, and each gets its
      poles from the coefficients of its characteristic polynomial (Figs. 3.2-3.4); the poles are
      distributed over the subsystems in order, conjugate pairs kept together.  Exact, but its
      eigenvectors are those of companion matrices: ill-conditioned for large ν.

    **Repeated poles.**  A pole of multiplicity k ≤ m gets k independent eigenvectors where the
    observability indices allow it (Rosenbrock's majorisation); otherwise it is assigned with Jordan
    chains, with a warning: such a gain is sensitive -- an eigenvalue of a Jordan block of size s moves
    by about ε^{1/s} under a perturbation ε of A, C or L.

    **Trust.**  The result is checked a posteriori: with E = T(A − LC) − FT every eigenvalue of A − LC
    lies within ‖E T⁻¹‖ of a requested one (plus the rounding in forming E); a bound above ``rtol``
    times max(‖A‖, ‖F‖), or a non-finite gain, raises ``ValueError`` (``eqx.error_if`` under jit).
    Computed in float64, this estimate cannot fall below the rounding level ε·s_k·‖A − LC‖ (s_k the
    eigenvalue's condition number): it measures how far the eigenvalues move when A, C or L change at
    float64's rounding level, so a refusal may come where the exact eigenvalues of A − LC are closer
    (:func:`obsjax.analysis.placement_error` measures those); ``rtol=numpy.inf`` accepts such a gain.
    For poles placed with Jordan chains (a multiplicity above the number of outputs, always with a
    warning) the estimate bounds only the backward error, not the eigenvalues themselves: a defective
    eigenvalue of multiplicity k moves by about the k-th root of a perturbation, so an accepted 5-fold
    pole of a single-output design was 1.3e-3 (relative) from the requested one with the default
    ``rtol``; check such designs with :func:`obsjax.analysis.placement_error`.

    For m = n (as many outputs as states) the gain is L = (A − F) C⁻¹ with F the real block form of the
    poles, which is not invariant under a change of units when there are complex pairs: the eigenvalues
    are exact in any units, but the gain does not follow the units as described below.

    **Units.**  For m < n the design runs in balanced units (the diagonal scalings D, E of
    :func:`obsjax.analysis.observability_staircase`'s balancing) and returns L = D L_b E, so the gain
    follows a change of units: the pair (S A S⁻¹, Λ C S⁻¹), S and Λ positive diagonal, gets S L Λ⁻¹
    (to the minimiser's tolerance), and a state in micro-units beside one in mega-units is placed as
    well as in its natural units.

    **Rank decisions** (observability, indices, the Jordan structure) use
    :func:`obsjax.analysis.observability_staircase` with ``tol``; a nearly unobservable pair raises
    ``ValueError`` giving the PBH margin.  They run when A and C are concrete; under jit with traced A, C
    the a-posteriori check stands guard.

    **Arguments:**

    - `A` (n, n), `C` (m, n): float64 (float32 and integers are promoted; with ``OBSJAX_NO_X64=1`` the
      call raises rather than design in float32).
    - `poles`: n poles, real or complex (conjugate-closed).  Under ``jit`` with traced poles the pattern
      cannot be read: real poles are taken as distinct, complex ones need ``structure``.
    - `method`: ``"robust"`` or ``"canonical"``.
    - `tol`: relative tolerance of the rank decisions (default 1e-9).
    - `rtol`: bound on the a-posteriori relative eigenvalue error (default 1e-6).
    - `structure`: :func:`obsjax.design.pole_structure` of poles with the same pattern.
    - `maxiter`: Newton iterations of the robust method.

    **Returns:** L (n, m), float64, differentiable in A, C and the poles (the derivative of the
    minimiser, by implicit differentiation of its optimality condition); jit- and vmap-compatible.

    **Entries of A or C that are exactly zero.**  The robust method works in the balanced units of the
    pair (a log-magnitude fit over the *nonzero* entries), so where an entry is exactly 0 the gain is not
    differentiable in that entry: making it nonzero, however small, enters the fit (on a 4-state,
    2-output example the difference quotients drift by about 0.1 % per decade of the step and lie 1–2 %
    from the derivative returned).
    The derivative returned there is the one along perturbations that keep the zero pattern (exact for
    those); along a direction that fills zeros, compare with ``method="canonical"`` (smooth in every
    entry) or give the entry a nonzero value.  Derivatives in the poles are not affected.

    **Many outputs.**  When the Tits-Yang minimiser is not isolated (typically m > (n+1)/2 with
    distinct poles: the best-conditioned eigenvector matrices then form a family), the robust gain is
    an exact placement and as well conditioned as any, but it is one member of that family: which one
    depends on rounding, so it can differ between eager and ``jit`` calls or jump under a tiny change
    of the poles, and it has no derivative.  Differentiating it (``jax.grad``, ``jax.jvp``, ``tune``
    over the poles) raises; ``method="canonical"`` gives a unique, differentiable gain there.

    **Example:** thesis example (2.8), poles {−3, −3}: ``place([[-2, 1], [0, -1]], [[1, 0]], [-3, -3])``
    gives L = [[3], [4]] (a Jordan chain: one output, a double pole).
    """
    rtol_ok = True
    if not isinstance(rtol, jax.core.Tracer):  # a traced rtol is compared under jit as it is
        try:
            rtol_ok = float(rtol) > 0.0  # inf accepts every finite gain; NaN and negatives are refused
        except (TypeError, ValueError):
            rtol_ok = False
    if not rtol_ok:
        raise ValueError(f"place: `rtol` must be a positive number (or numpy.inf), got {rtol!r}.")
    if isinstance(maxiter, bool) or not isinstance(maxiter, (int, np.integer)) or maxiter < 1:
        raise ValueError(f"place: `maxiter` must be a positive integer, got {maxiter!r}.")
    A, C = design_pair(A, C, "place")
    n = A.shape[0]
    p = pole_vector(poles, n)
    structure = resolve_structure(p, structure, n)
    pr, pi = jnp.real(p).astype(jnp.float64), jnp.imag(p).astype(jnp.float64)
    return place_real(
        A, C, pr, pi, structure, method=method, tol=tol, rtol=rtol, maxiter=maxiter, who="place"
    )


def _charpoly(poles):
    """Real coefficients [1, c1, …, cn] of Π (s − p_i), differentiable in the poles."""
    coeffs = jnp.ones((1,), dtype=poles.dtype)
    for i in range(poles.shape[0]):
        coeffs = jnp.convolve(coeffs, jnp.stack([jnp.ones((), poles.dtype), -poles[i]]))
    return jnp.real(coeffs)


def sylvester(A, F, H) -> jax.Array:
    """Solve T A − F T = H for T (thesis Theorem 1, (2.2)-(2.4)).

    Unique when A and F have no common eigenvalue.  Solved through the Kronecker form
    (Aᵀ ⊗ I − I ⊗ F) vec(T) = vec(H); differentiable in A, F and H.  Concrete A and F that share an
    eigenvalue, and non-finite data, raise ``ValueError``; under ``jit`` a solution that is not finite
    raises at run time (``eqx.error_if``).

    **Arguments:** `A` (n, n), `F` (q, q), `H` (q, n).  **Returns:** T (q, n).

    **Example:** thesis (3.3): ``sylvester([[-2, 1], [0, -2]], [[-3]], [[1, 0]])`` → [[1, −1]].
    """
    require_x64("sylvester")
    A = as_design_matrix(A, "A")
    F = as_design_matrix(F, "F")
    H = as_design_matrix(H, "H")
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"`A` must be square (n, n), got {tuple(A.shape)}.")
    if F.ndim != 2 or F.shape[0] != F.shape[1]:
        raise ValueError(f"`F` must be square (q, q), got {tuple(F.shape)}.")
    n, q = A.shape[0], F.shape[0]
    if H.shape != (q, n):
        raise ValueError(f"`H` must have shape ({q}, {n}), got {tuple(H.shape)}.")
    for M, name in ((A, "A"), (F, "F"), (H, "H")):
        require_finite(M, name)
    Av, Fv = concrete_value(A), concrete_value(F)
    if Av is not None and Fv is not None:
        ea, ef = np.linalg.eigvals(Av), np.linalg.eigvals(Fv)
        gap = np.min(np.abs(ea[:, None] - ef[None, :]))
        if gap < 1e-10 * max(1e-300, np.max(np.abs(ea)), np.max(np.abs(ef))):
            raise ValueError(
                f"`A` and `F` share an eigenvalue (closest pair {gap:.2e} apart): T A − F T = H has "
                "no unique solution."
            )
    K = jnp.kron(A.T, jnp.eye(q, dtype=A.dtype)) - jnp.kron(jnp.eye(n, dtype=A.dtype), F)
    vecT = jnp.linalg.solve(K, H.T.reshape(-1))  # column-major vec
    # traced A or F (the eigenvalue test above needs concrete ones), or traced non-finite data: a
    # singular Kronecker matrix gives NaN or inf, refused at run time
    vecT = eqx.error_if(
        vecT,
        ~jnp.all(jnp.isfinite(vecT)),
        "sylvester: T A − F T = H has no unique finite solution (A and F share an eigenvalue, or A, F "
        "or H is not finite).",
    )
    return vecT.reshape(n, q).T


def observability_indices(A, C, tol: float | None = None) -> tuple[int, ...]:
    """Observability indices ν_1 … ν_m by the column selection (a)-(e) of thesis section 3.2.

    With H = Cᵀ (so y = Hᵀx), the columns h_1 … h_m, Aᵀh_1 … Aᵀh_m, (Aᵀ)²h_1, … are tested one by one in
    that order; a column dependent on those kept is dropped, and with it every later power of the same
    h_j (step (e)).  ν_k is the number of columns kept for output k; Σ ν_k = n for an observable pair and
    max ν_k is the observability index ν.  The independence tests are those of the orthogonal staircase
    form of the balanced pair (:func:`obsjax.analysis.observability_staircase`), relative, so the indices
    do not change when A → cA or C → dC.

    **Arguments:** `A` (n, n), `C` (m, n) concrete; `tol`: relative tolerance (default 1e-9).

    **Returns:** (ν_1, …, ν_m).  **Raises** ``ValueError`` (with the PBH margin) when the pair is not
    observable.

    **Example:** ``observability_indices([[0, 1, 0], [0, 0, 0], [0, 0, 0]], [[1, 0, 0], [0, 0, 1]])``
    → (2, 1).
    """
    st = require_observable(A, C, tol, "observability_indices")
    return st.indices


__all__ = ["observability_indices", "observability_staircase", "place", "sylvester"]
