"""How accurately a gain places the poles: eigenvalues of A − LC to extended precision.

``numpy.linalg.eigvals(A - L @ C)`` is backward stable, so its eigenvalue k is off by about
ε·κ_k·‖A − LC‖ (κ_k the eigenvalue's condition number), plus what forming A − LC in float64 rounds.
For a placed observer with κ_k ~ 10⁶ that is ~10⁻⁸ relative: the float64 measurement can no longer
tell a gain that places its poles to 10⁻¹⁰ from one that misses them by 10⁻⁷.  Here the float64
eigenpairs are refined by Newton's method on the bordered system

    [A − LC − λI   −x] [δx]   [−r]
    [    e_jᵀ       0] [δλ] = [ 0],     r = (A − LC)x − λx,

with A − LC, the iterates x, λ and the residual r carried in double-double arithmetic (pairs of float64,
about 32 significant digits, by error-free transformations: Dekker's product and Knuth's sum) from the
float64 entries of A, L and C taken as exact, and the corrections solved in float64: mixed-precision
iterative refinement, which converges to the eigenvalues of the exact A − LC to about ε²·κ_k·‖A − LC‖
(ε² ≈ 1.2e-32).  The same on every platform (no long double needed).
"""

from __future__ import annotations

import warnings

import numpy as np

# ------------------------------------------------------------------ double-double arithmetic (numpy)
# A value is a pair (hi, lo) of float64 arrays with |lo| ≤ ulp(hi)/2; the operations below are exact
# transformations (Dekker 1971, Knuth TAOCP 2) followed by a renormalisation, as in the QD library.
_SPLIT = 134217729.0  # 2**27 + 1


def _split(a):
    c = _SPLIT * a
    hi = c - (c - a)
    return hi, a - hi


def _two_sum(a, b):
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


def _quick_two_sum(a, b):
    s = a + b
    return s, b - (s - a)


def _two_prod(a, b):
    p = a * b
    ah, al = _split(a)
    bh, bl = _split(b)
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


def _dd_add(a, b):
    s, e = _two_sum(a[0], b[0])
    t, f = _two_sum(a[1], b[1])
    s, e = _quick_two_sum(s, e + t)
    return _quick_two_sum(s, e + f)


def _dd_mul(a, b):
    p, e = _two_prod(a[0], b[0])
    return _quick_two_sum(p, e + (a[0] * b[1] + a[1] * b[0]))


def _dd_neg(a):
    return (-a[0], -a[1])


def _cdd_mul(a, b):
    """Complex double-double product; a complex value is (re, im), each a double-double pair."""
    (ar, ai), (br, bi) = a, b
    return (
        _dd_add(_dd_mul(ar, br), _dd_neg(_dd_mul(ai, bi))),
        _dd_add(_dd_mul(ar, bi), _dd_mul(ai, br)),
    )


def _cdd(z):
    """A complex float64 array as a complex double-double (exact)."""
    z = np.asarray(z, complex)
    return ((z.real.copy(), np.zeros(z.shape)), (z.imag.copy(), np.zeros(z.shape)))


def _cdd_add(a, b):
    return (_dd_add(a[0], b[0]), _dd_add(a[1], b[1]))


def _cdd_value(a):
    return (a[0][0] + a[0][1]) + 1j * (a[1][0] + a[1][1])


def _real_matrix(x, name: str) -> np.ndarray:
    """A finite real float64 array (complex input is refused, not cast)."""
    arr = np.asarray(x)
    if np.iscomplexobj(arr):
        raise ValueError(f"`{name}` must be real, got dtype {arr.dtype}.")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"`{name}` must be finite.")
    return arr


def _solve_or_nan(B, r):
    try:
        return np.linalg.solve(B, r)
    except np.linalg.LinAlgError:
        return np.full(r.shape, np.nan + 0j)


def _closed_loop_dd(A, C, L):
    """A − L C as a double-double matrix (every product L_iq·C_qj exact, the sums to ~ε²)."""
    n = A.shape[0]
    acc = (np.zeros((n, n)), np.zeros((n, n)))
    for q in range(C.shape[0]):
        acc = _dd_add(acc, _two_prod(L[:, q : q + 1], C[q : q + 1, :]))
    return _dd_add((A, np.zeros_like(A)), _dd_neg(acc))


def _residual(M, X, lam):
    """(M X − X diag(λ)) in complex double-double: M real double-double (n, n), the columns of X (n, K)
    the eigenvectors, λ (K,) the eigenvalues."""
    n, K = M[0].shape[0], X[0][0].shape[1]
    (xr, xi) = X
    zero = (np.zeros((n, K)), np.zeros((n, K)))
    yr, yi = zero, zero
    for j in range(n):  # Y += M[:, j] X[j, :], a column of M at a time
        Mj = (M[0][:, j : j + 1], M[1][:, j : j + 1])
        yr = _dd_add(yr, _dd_mul(Mj, (xr[0][j : j + 1], xr[1][j : j + 1])))
        yi = _dd_add(yi, _dd_mul(Mj, (xi[0][j : j + 1], xi[1][j : j + 1])))
    lx = _cdd_mul(lam, X)
    return _cdd_add((yr, yi), (_dd_neg(lx[0]), _dd_neg(lx[1])))


def closed_loop_eigvals(A, C, L, *, iters: int = 6, return_accuracy: bool = False):
    """Eigenvalues of A − L C for the float64 gain as stored, to extended precision.

    The float64 eigenpairs of A − LC are refined by Newton's method on the bordered eigenproblem
    ``[(A − LC − λI)  −x; e_jᵀ  0][δx; δλ] = [−r; 0]`` with the matrix A − LC, the iterates and the
    residual ``r = (A − LC)x − λx`` in double-double arithmetic (about 32 digits) from the entries of
    A, L and C taken as exact, and the corrections solved in float64 (mixed-precision iterative
    refinement).  The result is the spectrum of the exact A − LC to about ε²·κ_k·‖A − LC‖, where
    ``numpy.linalg.eigvals(A - L @ C)`` is off by about ε·κ_k·‖A − LC‖: use it to measure how well a
    gain places its poles when the eigenvalues are ill-conditioned (see :func:`placement_error`).

    NumPy on the host (not traceable): a checking tool, not a design step.

    **Arguments:** `A` (n, n), `C` (m, n), `L` (n, m), real.  `iters`: Newton steps (each step gains
    about 1/(ε·κ(bordered matrix)) in accuracy; 6 is ample for κ up to 10¹²).

    **Returns:** the n eigenvalues (complex128, in the order of ``numpy.linalg.eig``); with
    ``return_accuracy=True`` also the estimated absolute accuracy of each (the larger of the last two
    Newton corrections: the rounding noise the refinement settled at, or, where it is still
    converging, a bound on what is left).

    **Raises** ``ValueError`` for shapes that do not fit and for non-finite entries; ``RuntimeError``
    where the refinement makes no progress or two eigenvalues run together (a cluster or a Jordan block,
    whose eigenvalues are only as accurate as their sensitivity allows).

    **Example:**

    ```python
    import numpy as np, obsjax

    A, C = np.array([[-2.0, 1.0], [0.0, -1.0]]), np.array([[1.0, 0.0]])
    L = np.asarray(obsjax.design.place(A, C, [-3.0, -4.0]))
    obsjax.analysis.closed_loop_eigvals(A, C, L)  # -3, -4 to ~1e-30
    ```
    """
    if not (isinstance(iters, int) and iters >= 3):
        raise ValueError(f"`iters` must be an integer >= 3 (the accuracy is read from the last steps), got {iters!r}.")
    A, C, L = (_real_matrix(x, name) for x, name in ((A, "A"), (C, "C"), (L, "L")))
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"`A` must be square (n, n), got shape {A.shape}.")
    n = A.shape[0]
    if C.ndim == 1 and C.shape[0] == n:  # one output given as a vector (as `place` accepts it)
        C = C[None, :]
        if L.ndim == 1 and L.shape[0] == n:
            L = L[:, None]
    if C.ndim != 2 or C.shape[1] != n:
        raise ValueError(f"`C` must be (m, {n}), got shape {C.shape}.")
    if L.shape != (n, C.shape[0]):
        raise ValueError(f"`L` must be ({n}, {C.shape[0]}), got shape {L.shape}.")
    M = _closed_loop_dd(A, C, L)
    M64 = M[0] + M[1]
    w, V = np.linalg.eig(M64)
    scale = max(float(np.linalg.norm(M64)), np.finfo(float).tiny)
    js = np.argmax(np.abs(V), axis=0)
    cols = np.arange(n)
    X = _cdd(V / V[js, cols])  # every eigenpair refined at once: column k, normalised at row js[k]
    lam = _cdd(w)
    B = np.zeros((n, n + 1, n + 1), complex)
    B[cols, n, js] = 1.0
    steps = []
    for _ in range(iters):
        R = _cdd_value(_residual(M, X, lam))  # (n, K)
        B[:, :n, :n] = M64[None] - _cdd_value(lam)[:, None, None] * np.eye(n)
        B[:, :n, n] = -_cdd_value(X).T
        rhs = np.concatenate([-R.T, np.zeros((n, 1))], axis=1)
        with np.errstate(all="ignore"):
            try:
                d = np.linalg.solve(B, rhs[..., None])[..., 0]
            except np.linalg.LinAlgError:  # exactly singular: a multiple eigenvalue
                d = np.stack([_solve_or_nan(Bk, rk) for Bk, rk in zip(B, rhs)])
        X = _cdd_add(X, _cdd(d[:, :n].T))
        lam = _cdd_add(lam, _cdd(d[:, n]))
        steps.append(np.abs(d[:, n]))
    steps = np.asarray(steps)  # (iters, K)
    # the last corrections are rounding noise once converged (and bound what is left otherwise):
    # their size is the accuracy of the refined value.  No progress at all from the float64 value
    # (above its rounding level) means divergence.
    acc = np.max(steps[-2:], axis=0)
    bad = ~np.isfinite(acc) | (acc > np.maximum(0.5 * steps[0], 1e-13 * scale))
    if np.any(bad):
        k = int(np.argmax(bad))
        raise RuntimeError(
            f"closed_loop_eigvals: the refinement of eigenvalue {complex(w[k]):.6g} did not settle "
            f"(corrections {steps[0, k]:.1e} then up to {acc[k]:.1e}); it is too close to another "
            "eigenvalue to be refined."
        )
    refined = _cdd_value(lam)
    gaps = np.where(np.eye(n, dtype=bool), np.inf, np.abs(refined[:, None] - refined[None, :]))
    moved = np.abs(refined - w)
    if n > 1 and np.any(gaps.min(axis=1) <= 2.0 * moved):
        raise RuntimeError(
            "closed_loop_eigvals: two refined eigenvalues ran together (a cluster or a Jordan block); "
            "their float64 values are as accurate as they can be."
        )
    return (refined, acc) if return_accuracy else refined


def _bottleneck_matching(cost):
    """The assignment (row i → column match[i]) of a square cost matrix whose largest cost is smallest
    (binary search over the costs, a perfect bipartite matching at each threshold)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import maximum_bipartite_matching

    n = cost.shape[0]
    if n == 0:
        return np.zeros(0, int)
    levels = np.unique(cost)
    lo, hi = 0, levels.size - 1
    best = None
    while lo <= hi:
        mid = (lo + hi) // 2
        graph = csr_matrix((cost <= levels[mid]).astype(np.int8))
        m = maximum_bipartite_matching(graph, perm_type="column")
        if np.all(m >= 0):
            best, hi = m, mid - 1
        else:
            lo = mid + 1
    return np.asarray(best, int)


def placement_error(A, C, L, poles, *, return_accuracy: bool = False):
    """Largest relative distance max_k |λ̂_k − λ_k| / max(|λ_k|, s) between the eigenvalues λ̂ of
    A − LC (:func:`closed_loop_eigvals`, extended precision) and the requested ``poles``, over the best
    one-to-one matching (the one whose largest relative distance is smallest: a greedy nearest-first
    matching can pair a pole with a far eigenvalue and overstate the error), s = 10⁻³·max_k |λ_k| (10⁻³·‖A‖_F
    when every pole is 0): a pole at or near the origin is measured against the size of the
    spectrum, not divided by zero.

    This is the error of the gain itself; ``numpy.linalg.eigvals`` adds its own rounding
    ε·κ_k·‖A − LC‖/|λ_k|, which for ill-conditioned placements exceeds the gain's error.

    **Returns:** the error (float); with ``return_accuracy=True`` also the accuracy of that figure
    (max_k of the refined eigenvalue's accuracy over |λ_k|).  Where the refinement cannot settle
    (a gain so far off that eigenvalues run together, a Jordan block) the float64 eigenvalues are used
    and the accuracy is ``inf``.

    **Warns** ``RuntimeWarning`` when the figure is returned alone (``return_accuracy=False``) and its
    accuracy is not well below it (larger than a tenth of the error and than 10⁻¹⁴): the float64
    fallback above, or a refinement that settled coarsely.  The figure is then no better than that
    accuracy; ``return_accuracy=True`` returns both and does not warn.

    **Example:** ``placement_error(A, C, obsjax.design.place(A, C, poles), poles)`` ≈ 1e-15 for a
    well-conditioned placement.
    """
    try:
        eig, acc = closed_loop_eigvals(A, C, L, return_accuracy=True)
    except RuntimeError:
        eig = np.linalg.eigvals(np.asarray(A, float) - np.asarray(L, float) @ np.asarray(C, float))
        acc = np.full(eig.shape, np.inf)
    eig, acc = list(eig), list(acc)
    p = np.asarray(poles, complex).reshape(-1)
    if p.shape[0] != len(eig):
        raise ValueError(f"`poles` must hold n = {len(eig)} values, got {p.shape[0]}.")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"`poles` must be finite, got {p.tolist()}.")
    # a pole at (or near) the origin is measured against the size of the problem, as `place` does
    top = float(np.max(np.abs(p), initial=0.0))
    floor = 1e-3 * (top if top > 0 else float(np.linalg.norm(np.asarray(A, float))))
    size = np.maximum(np.maximum(np.abs(p), floor), np.finfo(float).tiny)
    eig_a, acc_a = np.asarray(eig), np.asarray(acc, float)
    cost = np.abs(eig_a[None, :] - p[:, None]) / size[:, None]  # (pole, eigenvalue)
    match = _bottleneck_matching(cost)
    rows = np.arange(p.shape[0])
    worst = float(np.max(cost[rows, match], initial=0.0))
    unsure = float(np.max(acc_a[match] / size, initial=0.0))
    if not return_accuracy and not unsure <= max(0.1 * worst, 1e-14):
        how = (
            "the eigenvalues of A − LC could not be refined (they run together: a cluster or a Jordan "
            "block), so float64 eigenvalues were used"
            if unsure == np.inf
            else "the refined eigenvalues settled only to this accuracy"
        )
        warnings.warn(
            f"placement_error: the error {worst:.2e} is known only to within {unsure:.1e} relative ({how}); "
            "return_accuracy=True returns the figure with its accuracy.",
            RuntimeWarning,
            stacklevel=2,
        )
    return (worst, unsure) if return_accuracy else worst
