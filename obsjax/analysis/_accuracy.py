"""How accurately a gain places the poles: eigenvalues of A − LC to extended precision.

``numpy.linalg.eigvals(A - L @ C)`` is backward stable, so its eigenvalue k is off by about
ε·κ_k·‖A − LC‖ (κ_k the eigenvalue's condition number), plus what forming A − LC in float64 rounds.
For a placed observer with κ_k ~ 10⁶ that is ~10⁻⁸ relative: the float64 measurement can no longer
tell a gain that places its poles to 10⁻¹⁰ from one that misses them by 10⁻⁷.  Here the float64
eigenpairs are refined by Newton's method on the bordered system

    [A − LC − λI   −x] [δx]   [−r]
    [    e_jᵀ       0] [δλ] = [ 0],     r = (A − LC)x − λx,

with the residual r formed in long double from the float64 entries of A, L and C (taken as exact) and
the corrections solved in float64: mixed-precision iterative refinement, which converges to the
eigenvalues of the exact A − LC to about ε_ld·κ_k·‖A − LC‖ (ε_ld ≈ 1.1e-19 with x86's 80-bit long
double, about 2000× below float64's rounding).
"""

from __future__ import annotations

import numpy as np


def _extended() -> bool:
    return bool(np.finfo(np.longdouble).eps < 1e-18)


def _real_matrix(x, name: str) -> np.ndarray:
    """A finite real float64 array (complex input is refused, not cast)."""
    arr = np.asarray(x)
    if np.iscomplexobj(arr):
        raise ValueError(f"`{name}` must be real, got dtype {arr.dtype}.")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"`{name}` must be finite.")
    return arr


def closed_loop_eigvals(A, C, L, *, iters: int = 5, return_accuracy: bool = False):
    """Eigenvalues of A − L C for the float64 gain as stored, to extended precision.

    The float64 eigenpairs of A − LC are refined by Newton's method on the bordered eigenproblem
    ``[(A − LC − λI)  −x; e_jᵀ  0][δx; δλ] = [−r; 0]`` with the residual ``r = (A − LC)x − λx`` formed in
    long double from the entries of A, L and C taken as exact (mixed-precision iterative refinement).
    The result is the spectrum of the exact A − LC to about ε_ld·κ_k·‖A − LC‖, where
    ``numpy.linalg.eigvals(A - L @ C)`` is off by about ε·κ_k·‖A − LC‖ (ε_ld/ε ≈ 1/2000 with an
    80-bit long double): use it to measure how well a gain places its poles when the eigenvalues are
    ill-conditioned (see :func:`placement_error`).

    NumPy on the host (not traceable): a checking tool, not a design step.

    **Arguments:** `A` (n, n), `C` (m, n), `L` (n, m), real.  `iters`: Newton steps (each step gains
    about 1/(ε·κ(bordered matrix)) in accuracy; 5 is ample for κ up to 10¹²).

    **Returns:** the n eigenvalues (complex128, in the order of ``numpy.linalg.eig``); with
    ``return_accuracy=True`` also the estimated absolute accuracy of each (the largest Newton
    correction after the second step: the rounding noise the refinement settled at).

    **Raises** ``ValueError`` for shapes that do not fit and for non-finite entries;
    ``RuntimeError`` where NumPy's long double is not wider than float64 (e.g. macOS on arm64), so no
    refinement is possible, or where the refinement makes no progress or two eigenvalues run together
    (a cluster or a Jordan block, whose eigenvalues are only as accurate as their sensitivity allows).

    **Example:**

    ```python
    import numpy as np, obsjax

    A, C = np.array([[-2.0, 1.0], [0.0, -1.0]]), np.array([[1.0, 0.0]])
    L = np.asarray(obsjax.design.place(A, C, [-3.0, -4.0]))
    obsjax.analysis.closed_loop_eigvals(A, C, L)  # -3, -4 to ~1e-19
    ```
    """
    if not (isinstance(iters, int) and iters >= 3):
        raise ValueError(f"`iters` must be an integer >= 3 (the accuracy is read from steps 3 on), got {iters!r}.")
    A, C, L = (_real_matrix(x, name) for x, name in ((A, "A"), (C, "C"), (L, "L")))
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"`A` must be square (n, n), got shape {A.shape}.")
    n = A.shape[0]
    if C.ndim != 2 or C.shape[1] != n:
        raise ValueError(f"`C` must be (m, {n}), got shape {C.shape}.")
    if L.shape != (n, C.shape[0]):
        raise ValueError(f"`L` must be ({n}, {C.shape[0]}), got shape {L.shape}.")
    if not _extended():
        raise RuntimeError(
            "closed_loop_eigvals: numpy.longdouble is not wider than float64 on this platform "
            f"(eps {np.finfo(np.longdouble).eps:.1e}); no extended-precision residual is available."
        )
    ld = np.longdouble
    M = A.astype(ld) - L.astype(ld) @ C.astype(ld)  # each product of two doubles exact to ε_ld
    Mc = M.astype(np.clongdouble)
    M64 = A - L @ C
    w, V = np.linalg.eig(M64)
    scale = max(float(np.linalg.norm(M64)), np.finfo(float).tiny)
    out = np.empty(n, np.clongdouble)
    acc = np.empty(n)
    for k in range(n):
        j = int(np.argmax(np.abs(V[:, k])))
        x = (V[:, k] / V[j, k]).astype(np.clongdouble)
        lam = np.clongdouble(w[k])
        B = np.zeros((n + 1, n + 1), complex)
        B[n, j] = 1.0
        steps = []
        for _ in range(iters):
            r = Mc @ x - lam * x
            B[:n, :n] = M64 - complex(lam) * np.eye(n)
            B[:n, n] = -x.astype(complex)
            try:
                d = np.linalg.solve(B, np.concatenate([-r.astype(complex), [0.0]]))
            except np.linalg.LinAlgError:  # exactly singular: a multiple eigenvalue
                d = np.full(n + 1, np.nan)
            x = x + d[:n].astype(np.clongdouble)
            lam = lam + np.clongdouble(d[n])
            steps.append(abs(d[n]))
        # after two steps the corrections are rounding noise: their size is the accuracy of the refined
        # value.  No progress at all from the float64 value (above its rounding level) means divergence.
        noise = max(steps[2:])
        acc[k] = noise
        if not np.isfinite(noise) or noise > max(0.5 * steps[0], 1e-13 * scale):
            raise RuntimeError(
                f"closed_loop_eigvals: the refinement of eigenvalue {complex(w[k]):.6g} did not settle "
                f"(corrections {steps[0]:.1e} then up to {noise:.1e}); it is too close to another "
                "eigenvalue to be refined."
            )
        out[k] = lam
    refined = out.astype(complex)
    gaps = np.where(np.eye(n, dtype=bool), np.inf, np.abs(refined[:, None] - refined[None, :]))
    moved = np.abs(refined - w)
    if n > 1 and np.any(gaps.min(axis=1) <= 2.0 * moved):
        raise RuntimeError(
            "closed_loop_eigvals: two refined eigenvalues ran together (a cluster or a Jordan block); "
            "their float64 values are as accurate as they can be."
        )
    return (refined, acc) if return_accuracy else refined


def placement_error(A, C, L, poles, *, return_accuracy: bool = False):
    """Largest relative distance max_k |λ̂_k − λ_k| / max(|λ_k|, s) between the eigenvalues λ̂ of
    A − LC (:func:`closed_loop_eigvals`, extended precision) and the requested ``poles`` (matched
    greedily, each requested pole to its nearest unused eigenvalue), s = 10⁻³·max_k |λ_k| (10⁻³·‖A‖_F
    when every pole is 0): a pole at or near the origin is measured against the size of the
    spectrum, not divided by zero.

    This is the error of the gain itself; ``numpy.linalg.eigvals`` adds its own rounding
    ε·κ_k·‖A − LC‖/|λ_k|, which for ill-conditioned placements exceeds the gain's error.

    **Returns:** the error (float); with ``return_accuracy=True`` also the accuracy of that figure
    (max_k of the refined eigenvalue's accuracy over |λ_k|).  Where the refinement cannot settle
    (a gain so far off that eigenvalues run together, a Jordan block) the float64 eigenvalues are used
    and the accuracy is ``inf``.

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
    worst, unsure = 0.0, 0.0
    # a pole at (or near) the origin is measured against the size of the problem, as `place` does
    top = float(np.max(np.abs(p), initial=0.0))
    floor = 1e-3 * (top if top > 0 else float(np.linalg.norm(np.asarray(A, float))))
    for q in p:
        d = np.abs(np.asarray(eig) - q)
        k = int(np.argmin(d))
        size = max(abs(q), floor, np.finfo(float).tiny)
        worst = max(worst, float(d[k] / size))
        unsure = max(unsure, float(acc[k] / size))
        eig.pop(k)
        acc.pop(k)
    return (worst, unsure) if return_accuracy else worst
