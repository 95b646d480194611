"""The ``obsjax`` command: ``obsjax demo``, ``obsjax reproduce <document>|--all``, ``obsjax bench``,
``obsjax --version``."""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import subprocess
import sys
import textwrap
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
    "data": ("recorded_data",),
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


#: modules of obsjax/_reproduce that hold data, not a document's reproduction
NOT_DOCUMENTS = ("references",)


def available_reproductions() -> list[str]:
    """Document modules present in obsjax/_reproduce."""
    from . import _reproduce

    return sorted(
        m.name
        for m in pkgutil.iter_modules(_reproduce.__path__)
        if not m.name.startswith("_") and m.name not in NOT_DOCUMENTS
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


def _title(module) -> str:
    doc = (module.__doc__ or "").strip()
    return doc.splitlines()[0].rstrip(".") if doc else module.__name__


def run_reproductions(modules, outdir: str, values: bool = True) -> int:
    """Run each document module's ``reproduce(outdir/<module>)``, announcing every figure as it is written,
    then print its ``paper_values()`` as a table (the document's value, obsjax's value, the relative
    difference) and a summary line.  Returns 1 if a module failed or a value is out of tolerance, else 0."""
    import jax

    from ._reproduce._report import announce_figures, format_table, summary_line

    present = set(available_reproductions())
    todo = []
    for mod in modules:
        if mod in present:
            todo.append(mod)
        else:
            print(
                f"[skip] {mod}: obsjax/_reproduce/{mod}.py is not present in this installation (not merged yet)."
            )
    failures, all_rows, t_all = [], [], time.perf_counter()
    for i, mod in enumerate(todo, 1):
        t0 = time.perf_counter()
        try:
            module = importlib.import_module(f"obsjax._reproduce.{mod}")
            print(f"[{i}/{len(todo)}] {mod}: {_title(module)}", flush=True)
            if not hasattr(module, "reproduce"):
                raise TypeError(f"obsjax/_reproduce/{mod}.py defines no `reproduce(outdir)`.")
            with announce_figures():
                paths = module.reproduce(os.path.join(outdir, mod))
            print(f"    {len(paths)} figure(s) in {time.perf_counter() - t0:.1f} s", flush=True)
            if values and hasattr(module, "paper_values"):
                print("    the document's values against obsjax's:", flush=True)
                rows = module.paper_values()
                print("\n".join("    " + line for line in format_table(rows).splitlines()))
                print(f"    {mod}: {summary_line(rows)}", flush=True)
                all_rows += rows
        except Exception:
            failures.append(mod)
            print(f"[fail] {mod}:")
            traceback.print_exc()
        finally:
            # each document compiles its own programs; XLA:CPU keeps every executable's code in memory
            # mappings of its own, so drop them between documents (a long process can otherwise reach
            # the kernel's vm.max_map_count, after which XLA's allocations fail)
            jax.clear_caches()
    if todo:
        done = len(todo) - len(failures)
        line = f"Summary: {done} of {len(todo)} document module(s) reproduced"
        if failures:
            line += f" (failed: {', '.join(failures)})"
        if values:
            line += f"; {summary_line(all_rows)}"
        print(f"{line}; {time.perf_counter() - t_all:.0f} s in all.")
    return 1 if failures or any(not r.within for r in all_rows) else 0


# ----------------------------------------------------------------------------------------------------------
# demo
# ----------------------------------------------------------------------------------------------------------

DEMO_NOISE_SIGMA = 0.05
DEMO_NOISE_DT = 0.05
DEMO_DT0 = 0.025  # fixed Tsit5 step: half the noise grid (its kinks fall on steps' ends)
#: fixed Tsit5 step of the paper's runs (Figs. 1-2): within 5.3e-6 (relative) of a tight adaptive solve (rtol
#: 1e-11) at every one of the 1001 save times for T = 0.25 and T = 2, closer than the default adaptive solve
#: (1.2e-5 at T = 2; C(t)'s √t makes the first steps converge at order 1.5 only), and its program compiles in
#: 2.3 s instead of 4.0 s
DEMO_PAPER_DT0 = 0.0025
DEMO_X0_SCALE = 3.0
DEMO_TUNE_RTOL = 1e-3  # tune stops once 3 accepted steps lower the mean ISE by less than 0.1 %
DEMO_TUNE_PATIENCE = 3


def demo_x0(key):
    """Initial plant state of the demo's studies: x(0) ~ N(0, 3² I)."""
    import jax.random as jr

    return DEMO_X0_SCALE * jr.normal(key, (2,))


def demo_xhat0(key):
    """Initial estimate x̂(0) = 0 (the observer knows nothing)."""
    import jax.numpy as jnp

    return jnp.zeros(2)


def monte_carlo_figure(results: dict, path: str) -> str:
    """The demo's Monte-Carlo figure: ‖x̃(t)‖ median and 5-95 % band per observer (log scale), and the
    distributions of the convergence times (same bins for every observer, medians marked)."""
    import matplotlib.pyplot as plt
    import numpy as np

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(12, 4.4))
    cts = {
        k: r.convergence_time[r.ok & np.isfinite(r.convergence_time)] for k, r in results.items()
    }
    finite = np.concatenate(list(cts.values()) or [np.zeros(0)])
    hi = float(finite.max()) if finite.size and finite.max() > 0 else 1.0
    bins = np.linspace(0.0, hi, 61)
    for i, (label, res) in enumerate(results.items()):
        c, qs = f"C{i}", list(res.quantiles)
        ax0.fill_between(
            res.ts,
            res.band(0.05),
            res.band(0.95),
            color=c,
            alpha=0.2,
            lw=0,
            label=f"{label}: 5–95 %",
        )
        ax0.plot(
            res.ts,
            res.bands[qs.index(0.5)] if 0.5 in qs else res.band(0.5),
            color=c,
            lw=1.8,
            label=f"{label}: median",
        )
        ax1.hist(
            cts[label],
            bins=bins,
            histtype="stepfilled",
            alpha=0.35,
            color=c,
            label=f"{label}; not converged by t = {res.ts[-1]:g} s: {1 - res.converged_fraction:.1%}",
        )
        if cts[label].size:
            med = float(np.median(cts[label]))
            ax1.axvline(med, color=c, ls="--", lw=1.2, label=f"median {med:.2f} s")
    n = max(r.n_done for r in results.values())
    ax0.set_yscale("log")
    ax0.set_xlabel("time t (s)")
    ax0.set_ylabel(r"estimation error $\|\tilde x(t)\|$")
    failed = " and ".join(str(r.n_failed) for r in results.values())
    ax0.set_title(f"{n} trajectories per observer (failed solves: {failed})", fontsize=10)
    ax0.grid(True, which="both", alpha=0.3)
    ax0.legend(fontsize=8, loc="lower left")
    res0 = next(iter(results.values()))
    thr = (
        f"{res0.conv_tol:.0%} of " + r"$\|\tilde x(0)\|$"
        if res0.conv_relative
        else f"{res0.conv_tol:g}"
    )
    ax1.set_xlabel("convergence time (s): " + r"$\|\tilde x\|$" + f" ≤ {thr} from then on")
    ax1.set_ylabel("trajectories per bin")
    ax1.set_title("convergence times", fontsize=10)
    ax1.grid(True, alpha=0.3)
    ax1.set_ylim(0.0, 1.5 * ax1.get_ylim()[1])  # room for the legend above the bars
    ax1.legend(fontsize=8, loc="upper center")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _paper_error_norm(plant, obs, ts):
    """‖x̃(t)‖ of the demo's paper run (x(0) = 0, x̂(0) = [5, −5]) and its status, `ts` a tuple."""
    import jax.numpy as jnp
    import numpy as np

    import obsjax

    traj = obsjax.simulate(
        plant, obs, jnp.zeros(2), jnp.array([5.0, -5.0]), np.asarray(ts), max_segments=40,
        throw=False, adaptive=False, dt0=DEMO_PAPER_DT0,
    )  # fmt: skip
    return traj.error_norm, traj.status


def demo(
    outdir: str = "obsjax-demo", n: int = 10_000, steps: int = 40, batch: int = 8, seed: int = 0
) -> dict:
    """Chen & Yen's example end to end: the paper's figures, gradient tuning of γ·p0 and T under measurement
    noise, and a Monte-Carlo comparison of the paper's and the tuned gains.  Returns the numbers printed."""
    for name, value in (("n", n), ("steps", steps), ("batch", batch)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"`{name}` must be a positive integer, got {value!r}.")
    if os.path.exists(outdir) and not os.path.isdir(outdir):
        raise ValueError(f"`outdir` {outdir!r} is a file, not a directory.")
    t_all = time.perf_counter()
    import jax
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

    # 1. The paper's simulations (Figs. 1 and 2): x(0) = 0, x̂(0) = [5, -5], on a dense save grid.
    t0 = time.perf_counter()
    ts = np.linspace(0.0, 10.0, 1001)
    # Independent SciPy references (solve_ivp, rtol 1e-10, the Riccati form (15) of P, segment by segment).
    from obsjax._reproduce.references import CHEN_YEN_ERROR_NORM

    ref = {T: tuple(CHEN_YEN_ERROR_NORM[(20.0, 0.1, T)].values()) for T in (0.25, 2.0)}
    t_ref = tuple(CHEN_YEN_ERROR_NORM[(20.0, 0.1, 0.25)])
    fig, ax = plt.subplots(figsize=(6.5, 4.0))
    print(
        "Chen & Yen example, γ = 20, p0 = 0.1, x̂(0) = [5, -5]  (‖x̃(t)‖; SciPy reference in brackets)"
    )
    from ._checks import device_array, runtime_checks_as_nan
    from ._trace_cache import filter_jit

    paper_kernel = filter_jit(_paper_error_norm, fast_compile=True)  # traced program saved across processes

    def paper_run(
        obs,
    ):  # one compilation for both periods (T is a traced leaf; 40 segments cover T ≥ 0.25)
        with (
            runtime_checks_as_nan()
        ):  # no host callback: the program is cached (status checked below)
            en, status = paper_kernel(plant, obs, tuple(float(t) for t in ts))
        if int(status) != 0:
            raise RuntimeError(f"the paper's simulation failed (status {int(status)})")
        return en

    for i, (T, r) in enumerate(ref.items()):
        en = np.asarray(paper_run(obsjax.LeastSquaresReset(plant, 20.0, 0.1, T)))
        vals = [en[np.argmin(np.abs(ts - t))] for t in (1, 2, 5, 10)]
        print(
            f"  T = {T:<5}"
            + "".join(f"  t={t:>2}: {v:.4g} [{w:.4g}]" for t, v, w in zip((1, 2, 5, 10), vals, r))
        )
        ax.semilogy(
            ts, en, color=f"C{i}", label=f"obsjax, T = {T:g} s ({'Fig. 1' if i == 0 else 'Fig. 2'})"
        )
    for i, r in enumerate(ref.values()):
        ax.semilogy(
            t_ref,
            r,
            "o",
            color="k",
            mfc="none",
            ms=7,
            label="independent SciPy solution" if i == 0 else None,
        )
    ax.set_xlabel("time t (s)")
    ax.set_ylabel(r"estimation error $\|\tilde x(t)\| = \|\hat x(t) - x(t)\|$")
    ax.set_title("Chen & Yen (1999), Figs. 1–2: γ = 20, p$_0$ = 0.1", fontsize=11)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=9)
    fig.tight_layout()
    figures.append(os.path.join(outdir, "paper_figures.png"))
    fig.savefig(figures[-1], dpi=120)
    plt.close(fig)
    t_paper = time.perf_counter() - t0

    # 2. Tune γ (hence γ·p0, p0 fixed) and T by gradient descent on the mean ISE over a batch of initial
    #    conditions, each with its own band-limited measurement-noise realisation, until the loss stops
    #    improving (tune's stopping rule; `steps` is only a bound).
    t0 = time.perf_counter()
    # on [0, 6.1] (the transient, at 60 % of the cost), 0.244 s apart: off the multiples of T = 0.25,
    # where the loss has kinks in T (tune would warn)
    ts_tune = np.linspace(0.0, 6.1, 26)
    noise = obsjax.noise.BandLimitedNoise(DEMO_NOISE_SIGMA, dt=DEMO_NOISE_DT)
    x0s = jax.vmap(demo_x0)(jr.split(k_tune_x0, batch))
    xhat0s = device_array(np.zeros((batch, 2)))
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
        rtol=DEMO_TUNE_RTOL,
        patience=DEMO_TUNE_PATIENCE,
        plant_batched=True,
        simulate_kwargs=fixed,
        progress=True,
    )
    best = tuned.observer
    hist = tuned.history
    t_tune = time.perf_counter() - t0
    print(
        f"\nTuned on [0, 6.1] over {batch} initial conditions with noise σ = {DEMO_NOISE_SIGMA} "
        f"({tuned.steps_taken} evaluations, {'converged' if tuned.converged else tuned.stop_reason}, "
        f"{t_tune:.1f} s): γ·p0 {20 * 0.1:.3g} -> {float(best.gamma) * float(best.p0):.3g}, T 0.25 -> {float(best.T):.3g}, "
        f"mean ISE {hist['loss'][0]:.4g} -> {hist['loss'][hist['best_step']]:.4g}"
    )
    fig, ax = plt.subplots(1, 3, figsize=(12, 3.6))
    steps_taken = np.arange(len(hist["loss"]))
    from matplotlib.ticker import MaxNLocator

    loss = np.asarray(hist["loss"])
    ax[0].plot(steps_taken, loss, "o-", ms=3, label="mean ISE")
    if loss.max() > 10 * loss.min() > 0:
        ax[0].set_yscale("log")
    ax[0].axvline(hist["best_step"], color="k", ls=":", lw=1, label="lowest loss (observer kept)")
    ax[0].set_ylabel(r"mean ISE $\int_0^{6.1} \|\tilde x\|^2\,dt$ (s)")
    ax[0].set_title(f"loss over {batch} noisy initial conditions", fontsize=10)
    ax[0].legend(fontsize=8)
    ax[1].plot(steps_taken, hist["params"][0] * float(paper.p0), "o-", ms=3)
    ax[1].set_ylabel(r"$\gamma\,p_0$ (1/s)")
    ax[1].set_title("adaptation gain", fontsize=10)
    ax[2].plot(steps_taken, hist["params"][1], "o-", ms=3)
    ax[2].set_ylabel("reset period T (s)")
    ax[2].set_title("covariance reset period", fontsize=10)
    for a in ax:
        a.set_xlabel("Adam step")
        a.xaxis.set_major_locator(MaxNLocator(integer=True))
        a.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    figures.append(os.path.join(outdir, "tuning.png"))
    fig.savefig(figures[-1], dpi=120)
    plt.close(fig)

    # 3. Monte-Carlo study: n trajectories, random x(0), independent noise, paper's against tuned gains,
    #    saved every 0.025 s (smooth bands, convergence times resolved to 0.025 s).
    t0 = time.perf_counter()
    ts_mc = np.linspace(0.0, 10.0, 401)
    # Both studies hold the reset segments of the shorter period, so that they run one compiled program
    # (each would otherwise hold exactly its own period's count and compile its own).
    from ._simulate import num_segments

    mc_kwargs = {**fixed, "max_segments": max(num_segments(o.T, ts_mc[0], ts_mc[-1]) for o in (paper, best))}
    results = {}
    for label, obs in (
        ("paper (γ·p0 = 2, T = 0.25)", paper),
        (f"tuned (γ·p0 = {float(best.gamma) * float(best.p0):.3g}, T = {float(best.T):.3g})", best),
    ):
        results[label] = obsjax.monte_carlo(
            plant,
            obs,
            k_mc,
            n,
            x0_sampler=demo_x0,
            xhat0_sampler=demo_xhat0,
            ts=ts_mc,
            noise=noise,
            chunk_size=min(n, 2500),
            simulate_kwargs=mc_kwargs,
            progress=True,
        )
    t_mc = time.perf_counter() - t0
    print(
        f"\nMonte-Carlo study: {n} trajectories each, x(0) ~ N(0, {DEMO_X0_SCALE:g}² I), x̂(0) = 0, "
        f"band-limited noise σ = {DEMO_NOISE_SIGMA} ({t_mc:.1f} s on {len(jax.devices())} "
        f"{jax.default_backend().upper()} device(s), common random numbers)"
    )
    print(comparison_table(results))
    figures.append(os.path.join(outdir, "monte_carlo.png"))
    monte_carlo_figure(results, figures[-1])

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


#: the benchmarks of benchmarks/run_all.py, each with what it measures (benchmarks/README.md)
BENCHMARKS = {
    "a": "Chen & Yen example, 4096 initial conditions: throughput of adaptive (jax.vmap(simulate) and the "
    "lock-step simulate_batch) and fixed-step solves against a Python loop over SciPy solve_ivp and a "
    "hand-written lax.scan; accuracy",
    "b": "value_and_grad of the ISE with respect to (γ, p0, T) against the forward pass (cost ratio)",
    "c": "first-call compile time of a jitted simulate per observer family; no retrace when gains change",
    "d": "monte_carlo sharded over 2 host devices against 1 (independent-step and lock-step kernels); with "
    "--large N an N-trajectory study and its peak memory",
    "e": "LTI Luenberger observer: obsjax against python-control (place + input_output_response)",
    "f": "robust MIMO pole placement (n = 4, 10, 20, m = 2, 1000 pole sets, jit(vmap(place))) against a "
    "SciPy place_poles loop: eigenvalue-error distribution, gain ratio, time",
    "f2": "place's a-posteriori accuracy check on (f)'s pole sets: its estimate against the gain's exact "
    "(refined) error; refusals at rtol 1e-6; accepted gains that miss it",
    "g": "Chen & Yen batch (4096 trajectories, 40 resets, rtol 1e-6): the adaptive back-ends against a "
    "hand-written numba Dormand-Prince 5(4); throughput, accuracy, step counts (needs the `bench` extra)",
    "h": "time to first result in fresh processes: obsjax demo, the first tune step, the first Monte-Carlo "
    "chunk, with the compilation cache off, cold and warm",
    "i": "estimate with the continuous-discrete Kalman filter over 1e5 samples and vmapped over 1000 "
    "experiments against a NumPy/SciPy loop and filterpy (needs the `bench` extra)",
    "j": "one tune step in forward mode (jax.jacfwd through diffrax.ForwardMode) and in reverse mode "
    "against the forward pass; where the two modes cross",
    "k": "a batch of plants (model uncertainty) on the masked adaptive loop against jax.vmap(simulate): "
    "throughput, a monte_carlo study with a param_sampler, a tune step with plant_batched=True",
    "l": "later eager calls of simulate and simulate_batch and eager jax.grad (resets, observer updates, "
    "batches) against the first call, with and without the table of compiled programs, each in fresh processes",
    "n": "the programs JAX lowers on a script's first run (README's two examples, the demo's second run): "
    "small ones (eager operations, checks, conversions) against the solver kernels, count and time",
    "m": "monte_carlo in 2 jax.distributed processes on localhost against 1 process: agreement, resume "
    "from process 0's checkpoint, timings",
    "s": "a 1e7-trajectory monte_carlo(keep='summary') study in a fresh process: peak resident memory "
    "flat in N against keep='all', wall time, streamed statistics against the closed form",
}


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
    unknown = [
        n for n in names if n not in BENCHMARKS and not n.startswith("-") and not n.isdigit()
    ]
    if unknown:
        print(f"obsjax bench: unknown benchmark(s) {unknown}; choose from {', '.join(BENCHMARKS)}.")
        return 2
    return subprocess.call([sys.executable, os.path.join(d, "run_all.py"), *names])


# ----------------------------------------------------------------------------------------------------------
# entry point
# ----------------------------------------------------------------------------------------------------------


def _positive_int(text: str) -> int:
    """argparse type: an integer ≥ 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def main(argv=None) -> int:
    from . import __version__

    parser = argparse.ArgumentParser(
        prog="obsjax", description="Differentiable, batched state observers."
    )
    parser.add_argument("--version", action="version", version=f"obsjax {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    p_demo = sub.add_parser(
        "demo", help="Chen & Yen example: simulate, tune under noise, Monte-Carlo compare"
    )
    p_demo.add_argument(
        "--out", default="obsjax-demo", help="figure directory (default ./obsjax-demo)"
    )
    p_demo.add_argument("-n", type=_positive_int, default=10_000, help="Monte-Carlo trajectories per study")
    p_demo.add_argument(
        "--steps",
        type=_positive_int,
        default=40,
        help="most evaluations of the tuning (it stops once converged)",
    )
    p_demo.add_argument(
        "--batch", type=_positive_int, default=8, help="initial conditions in the tuning batch"
    )
    p_demo.add_argument("--seed", type=int, default=0)
    p_rep = sub.add_parser("reproduce", help="write a document's examples and figures")
    p_rep.add_argument(
        "documents",
        nargs="*",
        help="chen-yen, hassan, lovass-nagy, huang-zhu, byrski-fuksa, data, ...",
    )
    p_rep.add_argument("--all", action="store_true", help="every document")
    p_rep.add_argument("--out", default="obsjax-reproduce", help="output directory")
    p_rep.add_argument("--list", action="store_true", help="list the available reproductions")
    p_rep.add_argument(
        "--no-values",
        dest="values",
        action="store_false",
        help="figures only: skip the table of the document's values against obsjax's",
    )
    listing = "\n".join(
        textwrap.fill(f"{k}  {v}", width=96, initial_indent="  ", subsequent_indent="     ")
        for k, v in BENCHMARKS.items()
    )
    p_bench = sub.add_parser(
        "bench",
        help="run the benchmarks (benchmarks/run_all.py)",
        description=textwrap.fill(
            "Run benchmarks, each in its own process; each writes its table to benchmarks/results/ "
            "(numbers, targets, machine, versions, load).  Needs the source checkout "
            "(benchmarks/ is not part of the installed package).",
            width=96,
        ),
        epilog=f"benchmarks:\n{listing}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p_bench.add_argument(
        "names", nargs="*", metavar="name", help=f"{' '.join(BENCHMARKS)} (default: all; see below)"
    )
    p_bench.add_argument(
        "--large", metavar="N", default=None, help="(d) also runs an N-trajectory study"
    )
    p_bench.add_argument("--dir", default=None, help="the benchmarks directory")
    args = parser.parse_args(argv)
    # JAX's persistent compilation cache, on unless OBSJAX_NO_COMPILATION_CACHE=1 (see obsjax/_cache.py),
    # and the traced kernels of tune and monte_carlo saved beside it, on unless OBSJAX_NO_TRACE_CACHE=1
    # (obsjax/_trace_cache.py); jaxlib's harmless complaint at every executable read back on some CPUs
    # is dropped from stderr
    import contextlib

    import jax

    from . import _trace_cache
    from ._cache import enable_compilation_cache, quiet_benign_cache_log

    min_before = jax.config.jax_persistent_cache_min_compile_time_secs
    on = enable_compilation_cache(min_compile_time_secs=CLI_MIN_COMPILE_TIME_SECS) is not None
    before = _trace_cache._state["dir"]
    if on:
        _trace_cache.enable_trace_cache(min_compile_time_secs=CLI_MIN_COMPILE_TIME_SECS)
    try:
        with quiet_benign_cache_log() if on else contextlib.nullcontext():
            return _run(parser, args)
    finally:
        if before is None:  # main() called from a process that had it off (a test, a notebook)
            _trace_cache.disable_trace_cache()
        jax.config.update("jax_persistent_cache_min_compile_time_secs", min_before)


#: the command writes every program it compiles to the cache, however quickly it compiled: the
#: demo's dozens of small programs (random draws, the optimiser's update, array stacking) each
#: compile in 10-300 ms, 1.8 s together, which a second run would otherwise spend again
CLI_MIN_COMPILE_TIME_SECS = 0.0


#: environment variable: the number of XLA host devices the demo's process uses (default: one per core)
DEMO_DEVICES_ENV = "OBSJAX_DEMO_DEVICES"


def host_devices_for_demo() -> int | None:
    """Give the demo's process one XLA CPU device per core, so that its Monte-Carlo studies are sharded
    across the cores (``monte_carlo`` splits each chunk over ``jax.devices()``; the result does not
    depend on the number of devices).  Only where JAX's CPU backend has not started yet and
    ``XLA_FLAGS`` does not set the device count already; ``OBSJAX_DEMO_DEVICES=1`` keeps one device.
    Returns the count set, or ``None`` when nothing was changed."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" in flags:
        return None
    try:
        from jax._src import xla_bridge

        if xla_bridge._backends:  # JAX has started: too late to change its devices
            return None
    except (ImportError, AttributeError):
        return None
    given = os.environ.get(DEMO_DEVICES_ENV, "").strip()
    if given:
        n = int(given)
    else:
        n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    n = max(1, int(n or 1))
    if n == 1:
        return None
    os.environ["XLA_FLAGS"] = (flags + f" --xla_force_host_platform_device_count={n}").strip()
    return n


def _run(parser, args) -> int:
    if args.command == "demo":
        if os.path.exists(args.out) and not os.path.isdir(args.out):
            parser.error(f"--out {args.out!r} is a file, not a directory")
        host_devices_for_demo()
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
        return run_reproductions(modules, args.out, values=args.values)
    if args.command == "bench":
        names = list(args.names) + (["--large", args.large] if args.large else [])
        return bench(names, args.dir)
    return 2


if __name__ == "__main__":
    sys.exit(main())
