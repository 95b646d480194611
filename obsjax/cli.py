"""The ``obsjax`` command: ``obsjax demo``, ``obsjax reproduce <document>|--all``, ``obsjax bench``."""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import subprocess
import sys
import time
import traceback

# Document aliases -> modules of obsjax/_reproduce (each exposing ``reproduce(outdir) -> list[str]``).
ALIASES: dict[str, tuple[str, ...]] = {
    "chen-yen": ("chen_yen",),
    "chenyen": ("chen_yen",),
    "hassan": ("luenberger", "adaptive"),
    "thesis": ("luenberger", "adaptive"),
    "lovass-nagy": ("lovass_nagy",),
    "chaisanguanmitt": ("lovass_nagy",),
    "huang-zhu": ("huang_zhu",),
    "tlo": ("huang_zhu",),
    "byrski-fuksa": ("byrski_fuksa",),
}
#: the order of ``--all`` for the documents' modules (others found in obsjax/_reproduce follow)
DOCUMENT_MODULES = (
    "chen_yen",
    "luenberger",
    "adaptive",
    "lovass_nagy",
    "huang_zhu",
    "byrski_fuksa",
)


# ----------------------------------------------------------------------------------------------------------
# reproduce
# ----------------------------------------------------------------------------------------------------------


def available_reproductions() -> list[str]:
    """Module names present in obsjax/_reproduce."""
    from . import _reproduce

    return sorted(
        m.name for m in pkgutil.iter_modules(_reproduce.__path__) if not m.name.startswith("_")
    )


def resolve_document(name: str) -> tuple[str, ...]:
    """Alias or module name -> module names (ValueError for an unknown name)."""
    key = name.strip().lower().replace("_", "-").replace(" ", "-")
    if key in ALIASES:
        return ALIASES[key]
    mod = name.strip().lower().replace("-", "_")
    known = set(DOCUMENT_MODULES) | set(available_reproductions())
    if mod in known:
        return (mod,)
    raise ValueError(
        f"unknown document {name!r}: use one of {', '.join(sorted(ALIASES))}, "
        f"a module name ({', '.join(sorted(known))}) or --all."
    )


def run_reproductions(modules, outdir: str) -> int:
    present = set(available_reproductions())
    failures = 0
    for mod in modules:
        if mod not in present:
            print(
                f"[skip] {mod}: obsjax/_reproduce/{mod}.py is not present in this installation (not merged yet)."
            )
            continue
        target = os.path.join(outdir, mod)
        t0 = time.perf_counter()
        try:
            module = importlib.import_module(f"obsjax._reproduce.{mod}")
            paths = module.reproduce(target)
        except Exception:
            failures += 1
            print(f"[fail] {mod}:")
            traceback.print_exc()
            continue
        print(f"[ok]   {mod}: {len(paths)} figure(s) in {time.perf_counter() - t0:.1f} s")
        for p in paths:
            print(f"         {p}")
    return 1 if failures else 0


# ----------------------------------------------------------------------------------------------------------
# demo
# ----------------------------------------------------------------------------------------------------------

DEMO_NOISE_SIGMA = 0.05
DEMO_NOISE_DT = 0.05
DEMO_DT0 = 0.0125  # fixed Tsit5 step: a quarter of the noise grid
DEMO_X0_SCALE = 3.0


def demo_x0(key):
    """Initial plant state of the demo's studies: x(0) ~ N(0, 3² I)."""
    import jax.random as jr

    return DEMO_X0_SCALE * jr.normal(key, (2,))


def demo_xhat0(key):
    """Initial estimate x̂(0) = 0 (the observer knows nothing)."""
    import jax.numpy as jnp

    return jnp.zeros(2)


def demo(
    outdir: str = "obsjax-demo", n: int = 10_000, steps: int = 20, batch: int = 8, seed: int = 0
) -> dict:
    """Chen & Yen's example end to end: the paper's figures, gradient tuning of γ·p0 and T under measurement
    noise, and a Monte-Carlo comparison of the paper's and the tuned gains.  Returns the numbers printed."""
    t_all = time.perf_counter()
    import jax
    import jax.numpy as jnp
    import jax.random as jr
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    import optax

    import obsjax
    from obsjax.montecarlo import comparison_table, noisy_batch

    os.makedirs(outdir, exist_ok=True)
    figures = []
    key = jr.PRNGKey(seed)
    k_tune_x0, k_tune_noise, k_mc = jr.split(key, 3)
    plant = obsjax.chen_yen_example()
    paper = obsjax.LeastSquaresReset(plant, gamma=20.0, p0=0.1, T=0.25)

    # 1. The paper's simulations (Figs. 1 and 2): x(0) = 0, x̂(0) = [5, -5].
    t0 = time.perf_counter()
    ts = np.linspace(0.0, 10.0, 201)
    # Independent SciPy references (solve_ivp, rtol 1e-10, the Riccati form (15) of P, segment by segment).
    from obsjax._reproduce.references import CHEN_YEN_ERROR_NORM

    ref = {T: tuple(CHEN_YEN_ERROR_NORM[(20.0, 0.1, T)].values()) for T in (0.25, 2.0)}
    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    print(
        "Chen & Yen example, γ = 20, p0 = 0.1, x̂(0) = [5, -5]  (‖x̃(t)‖; SciPy reference in brackets)"
    )
    import equinox as eqx

    @eqx.filter_jit
    def paper_run(
        obs,
    ):  # one compilation for both periods (T is a traced leaf; 40 segments cover T ≥ 0.25)
        return obsjax.simulate(
            plant, obs, jnp.zeros(2), jnp.array([5.0, -5.0]), ts, max_segments=40
        ).error_norm

    for T, r in ref.items():
        en = np.asarray(paper_run(obsjax.LeastSquaresReset(plant, 20.0, 0.1, T)))
        vals = [en[np.argmin(np.abs(ts - t))] for t in (1, 2, 5, 10)]
        print(
            f"  T = {T:<5}"
            + "".join(f"  t={t:>2}: {v:.4g} [{w:.4g}]" for t, v, w in zip((1, 2, 5, 10), vals, r))
        )
        ax.semilogy(ts, en, label=f"T = {T}")
    ax.set_xlabel("t")
    ax.set_ylabel("‖x̃(t)‖")
    ax.set_title("Chen & Yen, Figs. 1-2: γ = 20, p0 = 0.1")
    ax.legend()
    fig.tight_layout()
    figures.append(os.path.join(outdir, "paper_figures.png"))
    fig.savefig(figures[-1], dpi=110)
    plt.close(fig)
    t_paper = time.perf_counter() - t0

    # 2. Tune γ (hence γ·p0, p0 fixed) and T by gradient descent on the mean ISE over a batch of initial
    #    conditions, each with its own band-limited measurement-noise realisation.
    t0 = time.perf_counter()
    ts_s = np.linspace(0.0, 10.0, 41)
    ts_tune = ts_s[:25]  # tune on [0, 6]: the transient, at 60 % of the cost
    noise = obsjax.noise.BandLimitedNoise(DEMO_NOISE_SIGMA, dt=DEMO_NOISE_DT)
    x0s = jax.vmap(demo_x0)(jr.split(k_tune_x0, batch))
    xhat0s = jnp.zeros((batch, 2))
    plants = noisy_batch(plant, noise, k_tune_noise, batch, ts_tune[0], ts_tune[-1])
    fixed = {"adaptive": False, "dt0": DEMO_DT0}
    tuned = obsjax.tune(
        paper,
        plants,
        where=lambda o: (o.gamma, o.T),
        loss=obsjax.losses.ise,
        x0s=x0s,
        xhat0s=xhat0s,
        ts=ts_tune,
        optimizer=optax.adam(0.15),
        steps=steps,
        plant_batched=True,
        simulate_kwargs=fixed,
        progress=True,
    )
    best = tuned.observer
    hist = tuned.history
    t_tune = time.perf_counter() - t0
    print(
        f"\nTuned on [0, 6] over {batch} initial conditions with noise σ = {DEMO_NOISE_SIGMA} ({steps} Adam steps, "
        f"{t_tune:.1f} s): γ·p0 {20 * 0.1:.3g} -> {float(best.gamma * best.p0):.3g}, T 0.25 -> {float(best.T):.3g}, "
        f"mean ISE {hist['loss'][0]:.4g} -> {hist['loss'][hist['best_step']]:.4g}"
    )
    fig, ax = plt.subplots(1, 3, figsize=(11, 3.2))
    ax[0].semilogy(hist["loss"])
    ax[0].set_title("mean ISE on [0, 6] over the batch")
    ax[1].plot(hist["params"][0] * float(paper.p0))
    ax[1].set_title("γ·p0")
    ax[2].plot(hist["params"][1])
    ax[2].set_title("T")
    for a in ax:
        a.set_xlabel("Adam step")
    fig.tight_layout()
    figures.append(os.path.join(outdir, "tuning.png"))
    fig.savefig(figures[-1], dpi=110)
    plt.close(fig)

    # 3. Monte-Carlo study: n trajectories, random x(0), independent noise, paper's against tuned gains.
    t0 = time.perf_counter()
    results = {}
    for label, obs in (
        ("paper (γ·p0 = 2, T = 0.25)", paper),
        (f"tuned (γ·p0 = {float(best.gamma * best.p0):.3g}, T = {float(best.T):.3g})", best),
    ):
        results[label] = obsjax.monte_carlo(
            plant,
            obs,
            k_mc,
            n,
            x0_sampler=demo_x0,
            xhat0_sampler=demo_xhat0,
            ts=ts_s,
            noise=noise,
            chunk_size=min(n, 2500),
            simulate_kwargs=fixed,
            progress=True,
        )
    t_mc = time.perf_counter() - t0
    print(
        f"\nMonte-Carlo study: {n} trajectories each, x(0) ~ N(0, {DEMO_X0_SCALE:g}² I), x̂(0) = 0, "
        f"band-limited noise σ = {DEMO_NOISE_SIGMA} ({t_mc:.1f} s, common random numbers)"
    )
    print(comparison_table(results))
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for i, (label, res) in enumerate(results.items()):
        res.plot(axes=axes, label=label, color=f"C{i}")
    axes[0].set_title(f"‖x̃(t)‖: median, 25-75 % and 5-95 % bands (N = {n})")
    axes[1].set_title("convergence time (‖x̃‖ ≤ 5 % of ‖x̃(0)‖ thereafter)")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    figures.append(os.path.join(outdir, "monte_carlo.png"))
    fig.savefig(figures[-1], dpi=110)
    plt.close(fig)

    total = time.perf_counter() - t_all
    print(f"\nFigures: {', '.join(figures)}")
    print(
        f"Total {total:.1f} s (paper figures {t_paper:.1f} s, tuning {t_tune:.1f} s, Monte Carlo {t_mc:.1f} s)"
    )
    return {
        "results": results,
        "tuned": best,
        "history": hist,
        "figures": figures,
        "seconds": total,
        "seconds_parts": {"paper": t_paper, "tune": t_tune, "monte_carlo": t_mc},
    }


# ----------------------------------------------------------------------------------------------------------
# bench
# ----------------------------------------------------------------------------------------------------------


def _benchmarks_dir(given: str | None):
    if given:
        return given
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    cand = os.path.join(here, "benchmarks")
    if os.path.isfile(os.path.join(cand, "run_all.py")):
        return cand
    cand = os.path.join(os.getcwd(), "benchmarks")
    if os.path.isfile(os.path.join(cand, "run_all.py")):
        return cand
    return None


def bench(names, bench_dir=None) -> int:
    d = _benchmarks_dir(bench_dir)
    if d is None:
        print(
            "obsjax bench: no benchmarks/run_all.py found (the benchmarks live in the source checkout, not "
            "in the installed package); run it from the repository root or pass --dir."
        )
        return 2
    return subprocess.call([sys.executable, os.path.join(d, "run_all.py"), *names])


# ----------------------------------------------------------------------------------------------------------
# entry point
# ----------------------------------------------------------------------------------------------------------


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="obsjax", description="Differentiable, batched state observers."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    p_demo = sub.add_parser(
        "demo", help="Chen & Yen example: simulate, tune under noise, Monte-Carlo compare"
    )
    p_demo.add_argument(
        "--out", default="obsjax-demo", help="figure directory (default ./obsjax-demo)"
    )
    p_demo.add_argument("-n", type=int, default=10_000, help="Monte-Carlo trajectories per study")
    p_demo.add_argument("--steps", type=int, default=20, help="Adam steps of the tuning")
    p_demo.add_argument(
        "--batch", type=int, default=8, help="initial conditions in the tuning batch"
    )
    p_demo.add_argument("--seed", type=int, default=0)
    p_rep = sub.add_parser("reproduce", help="write a document's examples and figures")
    p_rep.add_argument(
        "documents", nargs="*", help="chen-yen, hassan, lovass-nagy, huang-zhu, byrski-fuksa, ..."
    )
    p_rep.add_argument("--all", action="store_true", help="every document")
    p_rep.add_argument("--out", default="obsjax-reproduce", help="output directory")
    p_rep.add_argument("--list", action="store_true", help="list the available reproductions")
    p_bench = sub.add_parser("bench", help="run the benchmarks (benchmarks/run_all.py)")
    p_bench.add_argument("names", nargs="*", help="a b c d e m (default: all)")
    p_bench.add_argument("--dir", default=None, help="the benchmarks directory")
    args = parser.parse_args(argv)
    # JAX's persistent compilation cache for this process (OBSJAX_NO_COMPILATION_CACHE=1 opts out).
    from ._cache import enable_compilation_cache

    enable_compilation_cache()

    if args.command == "demo":
        demo(args.out, n=args.n, steps=args.steps, batch=args.batch, seed=args.seed)
        return 0
    if args.command == "reproduce":
        if args.list:
            present = available_reproductions()
            print("available:", ", ".join(present) or "(none)")
            print(
                "aliases:",
                ", ".join(f"{k} -> {'/'.join(v)}" for k, v in ALIASES.items() if not k.isdigit()),
            )
            return 0
        if args.all:
            extra = [m for m in available_reproductions() if m not in DOCUMENT_MODULES]
            modules = list(DOCUMENT_MODULES) + extra
        elif args.documents:
            modules = []
            for doc in args.documents:
                try:
                    modules += [m for m in resolve_document(doc) if m not in modules]
                except ValueError as e:
                    parser.error(str(e))
        else:
            parser.error("name a document (e.g. `obsjax reproduce chen-yen`) or pass --all")
        return run_reproductions(modules, args.out)
    if args.command == "bench":
        return bench(args.names, args.dir)
    return 2


if __name__ == "__main__":
    sys.exit(main())
