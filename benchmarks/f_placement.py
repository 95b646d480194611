"""Benchmark (f): robust MIMO observer pole placement, obsjax against SciPy (and SLICOT when available).

For n = 4, 10, 20 states and m = 2 outputs: one random pair (A, C) (standard normal entries, fixed seed)
and 1000 pole sets with one pattern (a quarter of the poles in conjugate pairs, the rest real; real parts
uniform in [-4, -0.5], imaginary parts in [0.2, 3]).

- obsjax: ``jax.jit(jax.vmap(lambda p: obsjax.design.place(A, C, p, structure=...)))`` over the 1000 sets.
- SciPy: a Python loop of ``scipy.signal.place_poles`` (Tits-Yang, its default, maxiter 30) on the dual pair
  (Aᵀ, Cᵀ); L = Kᵀ.
- SLICOT SB01BD through python-control's ``place_varga`` (loop), when slycot is installed.

Reported per n: the distribution of the relative eigenvalue error max_k |λ̂_k − λ_k| / |λ_k| (eigenvalues of
the exact A − LC refined in double-double arithmetic by ``obsjax.analysis.placement_error``, and, for
comparison, by float64 ``numpy.linalg.eigvals``; matched greedily), how often each method reaches 1e-8, how often
obsjax misses 1e-8 where SciPy reaches it (target: never), the ratio ‖L_obsjax‖ / ‖L_SciPy‖ (target ≤ 2),
how many sets obsjax's a-posteriori check would refuse at its default rtol 1e-6, and the time for the
1000 sets (first call with compilation, then best and median of 3 further calls, fewer once 5 minutes are spent).

Usage: ``python benchmarks/f_placement.py [--sets 1000] [--ns 4 10 20]``.
"""

from __future__ import annotations

import argparse
import time
import warnings

import _common as C


def _match(eig, poles):
    import numpy as np

    rest = list(eig)
    worst = 0.0
    for p in poles:
        d = np.abs(np.asarray(rest) - p)
        k = int(np.argmin(d))
        worst = max(worst, d[k] / abs(p))
        rest.pop(k)
    return worst


def _pole_sets(rng, n, sets):
    import numpy as np

    npairs = n // 4
    nreal = n - 2 * npairs
    re = -rng.uniform(0.5, 4.0, (sets, npairs + nreal))
    im = rng.uniform(0.2, 3.0, (sets, npairs))
    pairs = re[:, :npairs] + 1j * im
    out = np.concatenate([np.stack([pairs, pairs.conj()], axis=2).reshape(sets, 2 * npairs), re[:, npairs:]], axis=1)
    return out


def pair_and_sets(n, sets, m=2, seed=0):
    """The benchmark's observable random pair (A, C) for n and its pole sets (fixed seeds)."""
    import numpy as np

    import obsjax

    rng = np.random.default_rng(seed + n)
    while True:
        A, Cm = rng.standard_normal((n, n)), rng.standard_normal((m, n))
        if obsjax.analysis.is_observable(A, Cm):
            break
    return A, Cm, _pole_sets(rng, n, sets)


def _finite_max(x):
    import numpy as np

    x = np.asarray(x)
    return float(np.max(x[np.isfinite(x)])) if np.any(np.isfinite(x)) else float("nan")


def _quantiles(x):
    import numpy as np

    x = np.asarray(x)
    return np.median(x), np.quantile(x, 0.9), np.quantile(x, 0.99), np.max(x)


def run(n, sets, m=2, seed=0):
    import jax
    import jax.numpy as jnp
    import numpy as np
    import scipy.signal

    import obsjax
    from obsjax.design._place import _robust_core, _scalings, make_pattern
    from obsjax.design._poles import blocks_of
    from obsjax.design._robust import make_layout

    A, Cm, P = pair_and_sets(n, sets, m, seed)
    st = obsjax.design.pole_structure(P[0])
    f = jax.jit(jax.vmap(lambda p: obsjax.design.place(A, Cm, p, structure=st, rtol=np.inf)))
    # the first call's gains are the ones measured; then 3 steady-state calls (more below 0.5 s in
    # all), fewer once 5 minutes are spent (one call takes ~5 min at n = 20 on a 2-core machine)
    first, best, med, L, calls = C.timeit(
        f, jnp.asarray(P), repeat=3, min_time=0.5, max_time=300.0, return_output=True
    )
    L = np.asarray(L)
    # the a-posteriori estimate that place checks against rtol (1e-6 by default)
    kron = obsjax.analysis.observability_staircase(A, Cm).kronecker
    blocks = blocks_of(st, m, kron)
    lay, depth = make_layout(blocks, n)
    pat = make_pattern(st, blocks)
    d, e = _scalings(A, Cm)  # the balancing place designs on (as place does)
    est = jax.jit(
        jax.vmap(lambda pr, pi: _robust_core(lay, pat, A, Cm, pr, pi, d, e, m=m, depth=depth, maxiter=60)[1])
    )(jnp.asarray(P.real), jnp.asarray(P.imag))
    refused = int(np.sum(~(np.asarray(est) <= 1e-6)))

    t0 = time.perf_counter()
    Ls = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for p in P:
            Ls.append(scipy.signal.place_poles(A.T, Cm.T, p).gain_matrix.T)
    t_scipy = time.perf_counter() - t0
    Ls = np.stack(Ls)

    varga = None
    try:
        import control  # noqa: F401
        import slycot  # noqa: F401

        t0 = time.perf_counter()
        Lv = np.stack([np.asarray(control.place_varga(A.T, Cm.T, p)).T for p in P])
        varga = (time.perf_counter() - t0, Lv)
    except ImportError:
        pass

    def errors(Lx):
        return np.array([_match(np.linalg.eigvals(A - l @ Cm), p) for l, p in zip(Lx, P)])

    def exact(Lx):  # (error, its accuracy) of the exact A − LC, refined in extended precision
        return np.array([obsjax.analysis.placement_error(A, Cm, l, p, return_accuracy=True) for l, p in zip(Lx, P)])

    e_ours, e_scipy = errors(L), errors(Ls)
    (x_ours, a_ours), (x_scipy, a_scipy) = exact(L).T, exact(Ls).T
    ratio = np.linalg.norm(L, axis=(1, 2)) / np.linalg.norm(Ls, axis=(1, 2))
    row = dict(
        n=n,
        e_ours=_quantiles(e_ours),
        e_scipy=_quantiles(e_scipy),
        reach_ours=float(np.mean(e_ours <= 1e-8)),
        reach_scipy=float(np.mean(e_scipy <= 1e-8)),
        missed=int(np.sum((e_scipy <= 1e-8) & (e_ours > 1e-8))),
        x_ours=_quantiles(x_ours),
        x_scipy=_quantiles(x_scipy),
        x_reach_ours=float(np.mean(x_ours <= 1e-8)),
        x_reach_scipy=float(np.mean(x_scipy <= 1e-8)),
        x_missed=int(np.sum((x_scipy <= 1e-8) & (x_ours > 1e-8))),
        x_missed_sets=[(int(k), float(x_ours[k]), float(x_scipy[k])) for k in np.where((x_scipy <= 1e-8) & (x_ours > 1e-8))[0]],
        x_acc=(_finite_max(a_ours), _finite_max(a_scipy)),
        x_fallback=(int(np.sum(~np.isfinite(a_ours))), int(np.sum(~np.isfinite(a_scipy)))),
        x_close=int(np.sum((np.abs(x_ours - 1e-8) <= a_ours) | (np.abs(x_scipy - 1e-8) <= a_scipy))),
        ratio=(np.median(ratio), np.max(ratio)),
        refused=refused,
        nonfinite=int(np.sum(~np.all(np.isfinite(L), axis=(1, 2)))),
        first=first,
        calls=calls,
        best=best,
        med=med,
        t_scipy=t_scipy,
    )
    if varga is not None:
        e_v = errors(varga[1])
        row["varga"] = (varga[0], _quantiles(e_v), float(np.mean(e_v <= 1e-8)))
        row["ratio_varga"] = np.median(np.linalg.norm(L, axis=(1, 2)) / np.linalg.norm(varga[1], axis=(1, 2)))
    return row


def main(sets=1000, ns=(4, 10, 20)):
    load = C.Load()
    rows = [run(n, sets) for n in ns]
    load.finish()

    def q(x):
        return " / ".join(f"{v:.1e}" for v in x)

    lines = [
        f"One random pair (A, C) per n (m = 2), {sets} pole sets (a quarter of the poles in conjugate pairs).",
        "Relative eigenvalue error max_k |λ̂_k − λ_k|/|λ_k| of A − LC: median / 90 % / 99 % / max.",
        "",
        "**The gain's own error** (the issue's target): λ̂ are the eigenvalues of the exact A − LC for the float64",
        "gain as returned, by `obsjax.analysis.placement_error` (float64 eigenpairs refined by Newton's method with",
        "double-double residuals; checked against integer matrices of known spectrum and against 40-digit mpmath",
        "eigenvalues in tests/test_accuracy.py).",
        "",
        "| n | obsjax error | SciPy (Tits-Yang) error | reach 1e-8: obsjax / SciPy | obsjax > 1e-8 where SciPy ≤ 1e-8 | sets within the refinement's accuracy of 1e-8 | worst accuracy of the refined errors: obsjax / SciPy | not refinable (float64 used): obsjax / SciPy |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['n']} | {q(r['x_ours'])} | {q(r['x_scipy'])} | {r['x_reach_ours']:.1%} / {r['x_reach_scipy']:.1%} "
            f"| **{r['x_missed']}** | {r['x_close']} | {r['x_acc'][0]:.1e} / {r['x_acc'][1]:.1e} "
            f"| {r['x_fallback'][0]} / {r['x_fallback'][1]} |"
        )
    lines += [
        "",
        "A gain whose closed-loop eigenvalues cannot be refined one by one (they run together: a gain far off) is",
        "measured in float64 and counted in the last column; its accuracy is then infinite, so it also counts as",
        "within the refinement's accuracy of 1e-8.",
    ]
    for r in rows:
        for k, eo, es in r["x_missed_sets"]:
            lines.append(f"\n- n = {r['n']}, set {k}: obsjax {eo:.2e}, SciPy {es:.2e}.")
    lines += [
        "",
        "**As float64 `numpy.linalg.eigvals(A - L @ C)` sees it** (the measurement of the earlier tables): its own",
        "rounding ε·κ_k·‖A − LC‖/|λ_k| is about 1e-7 for the κ_k ~ 1e6-1e8 of these placements at n = 10, 20, so at",
        "the 1e-8 line it decides by rounding, not by the gain (e.g. a gain placing its poles to 9e-11 reads 1.0e-8).",
        "Kept for comparison, with the gain-size ratio and the refusals of obsjax's own a-posteriori check:",
        "",
        "| n | obsjax error | SciPy (Tits-Yang) error | reach 1e-8: obsjax / SciPy | obsjax > 1e-8 where SciPy ≤ 1e-8 | ‖L‖ obsjax / SciPy: median, max | refused at rtol 1e-6 | non-finite |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['n']} | {q(r['e_ours'])} | {q(r['e_scipy'])} | {r['reach_ours']:.1%} / {r['reach_scipy']:.1%} "
            f"| {r['missed']} | {r['ratio'][0]:.2f}, {r['ratio'][1]:.2f} | {r['refused']} | {r['nonfinite']} |"
        )
    lines += [
        "",
        f"Time for the {sets} sets (steady state: 3 calls after the first, more while they take under 0.5 s in all, fewer once 5 minutes are spent):",
        "",
        "| n | obsjax `jit(vmap(place))` first call (compile) | obsjax best / median (calls) | SciPy loop | speed-up |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['n']} | {r['first']:.2f} s | {r['best']:.3f} s / {r['med']:.3f} s ({r['calls']}) | {r['t_scipy']:.2f} s "
            f"| **{r['t_scipy'] / r['best']:.1f}×** |"
        )
    if all("varga" in r for r in rows):
        lines += [
            "",
            "SLICOT SB01BD (python-control `place_varga`, a Schur method that does not minimise the eigenvector "
            "conditioning), same sets:",
            "",
            "| n | error median / 90 % / 99 % / max | reach 1e-8 | ‖L‖ obsjax / SB01BD (median) | loop time |",
            "|---|---|---|---|---|",
        ]
        for r in rows:
            t, e, reach = r["varga"]
            lines.append(f"| {r['n']} | {q(e)} | {reach:.1%} | {r['ratio_varga']:.2f} | {t:.2f} s |")
    else:
        lines += ["", "SLICOT SB01BD: slycot is not installed here, comparison skipped."]
    body = "\n".join(lines)
    print(body)
    return C.write_result("f_placement", "Benchmark (f): robust MIMO pole placement against SciPy", body, load)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", type=int, default=1000)
    ap.add_argument("--ns", type=int, nargs="+", default=[4, 10, 20])
    a = ap.parse_args()
    main(a.sets, tuple(a.ns))
