"""Benchmark (s): a Monte-Carlo study larger than memory: ``monte_carlo(..., keep="summary")`` with host
memory bounded by a chunk, the per-trajectory results on disk (the checkpoint's chunk files).

Plant and observer: ẋ = A x, A = [[−2, 1], [0, −1]], y = x₁, a Luenberger observer with poles (−2, −3) on
the exact model, x(0) ~ N(0, I), x̂(0) = 0; fixed-step Tsit5 (h = 0.1) on [0, 2], 21 save times; chunks of
65536 trajectories.  Each study runs in a fresh process under ``/usr/bin/time -v`` (peak resident memory of
the whole process, JAX and compilation included; ``resource.getrusage`` reported beside it):

- streaming (``keep="summary"``, checkpointed) for N = 10⁵, 10⁶ and, unless ``--max-n`` says otherwise,
  10⁷: target peak ≤ 1.5 GB, and flat in N;
- in memory (``keep="all"``) for N = 10⁵ and 10⁶, for contrast (N × 21 floats and their copies).

Independent check of the statistics: on the exact model the error is x̃(t) = −exp(F t) x(0), F = A − LC,
Gaussian with covariance Σ(t) = exp(F t) exp(F t)ᵀ; with Σ's eigenvalues λ₁, λ₂, E‖x̃(t)‖ and the median of
‖x̃(t)‖ are one-dimensional integrals (polar coordinates), evaluated with SciPy.  The streamed mean and
median band must agree within 4 standard errors (plus the sketch's relative accuracy for the median).

Usage: ``python benchmarks/s_streaming_study.py [--max-n 10000000]``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile

import _common as C

CHUNK = 65536
TS = (0.0, 2.0, 21)
POLES = (-2.0, -3.0)


def x0_sampler(key):
    import jax.random as jr

    return jr.normal(key, (2,))


def xhat0_sampler(key):
    import jax.numpy as jnp

    return jnp.zeros(2)


def problem():
    import obsjax

    plant = obsjax.LTI([[-2.0, 1.0], [0.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]])
    return plant, obsjax.Luenberger.from_poles(plant, list(POLES))


def child(n, keep, ckpt):
    """One study in this (fresh) process; prints a JSON line."""
    import resource
    import time

    import diffrax
    import jax.random as jr
    import numpy as np

    import obsjax

    plant, obs = problem()
    ts = np.linspace(*TS)
    t0 = time.perf_counter()
    res = obsjax.monte_carlo(
        plant, obs, jr.PRNGKey(0), n, x0_sampler=x0_sampler, xhat0_sampler=xhat0_sampler, ts=ts,
        chunk_size=CHUNK, progress=False, keep=keep, checkpoint=ckpt,
        simulate_kwargs={"solver": diffrax.Tsit5(), "adaptive": False, "dt0": 0.1},
    )  # fmt: skip
    wall = time.perf_counter() - t0
    out = {
        "n": n, "keep": keep, "wall": wall, "compute": res.elapsed, "n_done": res.n_done,
        "failed": res.n_failed, "maxrss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
        "mean": res.error_norm_mean.tolist(), "median": res.band(0.5).tolist(),
        "summary": res.summary(),
        "disk": sum(os.path.getsize(os.path.join(ckpt, f)) for f in os.listdir(ckpt)) if ckpt else 0,
    }  # fmt: skip
    print("RESULT " + json.dumps(out), flush=True)


def _polar(lam, x=None):
    """For x̃ ~ N(0, diag(lam)): E‖x̃‖, or (x given) P(‖x̃‖ ≤ x) and the density of ‖x̃‖ at x, by
    polar coordinates (‖x̃‖ = r·sqrt(ρ(θ)), r ~ Rayleigh(1), θ ~ U(0, 2π), independent)."""
    import numpy as np
    import scipy.integrate as si

    def rho(th):
        return lam[0] * np.cos(th) ** 2 + lam[1] * np.sin(th) ** 2

    def avg(f):
        return si.quad(f, 0.0, 2 * np.pi)[0] / (2 * np.pi)

    if x is None:
        return np.sqrt(np.pi / 2) * avg(lambda th: np.sqrt(rho(th)))
    cdf = avg(lambda th: 1 - np.exp(-(x**2) / (2 * rho(th))))
    pdf = avg(lambda th: x / rho(th) * np.exp(-(x**2) / (2 * rho(th))))
    return cdf, pdf


def exact_stats(ts):
    """E‖x̃(t)‖, the std of ‖x̃(t)‖, its median and its density at the median, for x̃(t) = −exp(Ft) x0,
    x0 ~ N(0, I)."""
    import numpy as np
    import scipy.linalg as sl
    import scipy.optimize as so

    _, obs = problem()
    F = np.asarray(obs.observer_matrix)
    mean, std, med, dens = [], [], [], []
    for t in ts:
        E = sl.expm(F * t)
        lam = np.linalg.eigvalsh(E @ E.T)
        m = _polar(lam)
        second = lam.sum()  # E‖x̃‖² = trace Σ
        mean.append(m)
        std.append(np.sqrt(second - m**2))
        med.append(so.brentq(lambda x, lam=lam: _polar(lam, x)[0] - 0.5, 1e-12, 10 * np.sqrt(second)))
        dens.append(_polar(lam, med[-1])[1])
    return np.array(mean), np.array(std), np.array(med), np.array(dens)


def run_child(n, keep, workdir):
    ckpt = os.path.join(workdir, f"ckpt_{keep}_{n}") if keep == "summary" else None
    env = dict(os.environ)
    env["PYTHONPATH"] = C.ROOT + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    cmd = ["/usr/bin/time", "-v", sys.executable, os.path.abspath(__file__), "--child", str(n), keep]
    if ckpt:
        cmd.append(ckpt)
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=os.path.dirname(__file__),
                       check=False)
    if p.returncode != 0:
        raise RuntimeError(f"child {n} {keep} failed:\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}")
    out = json.loads(next(ln for ln in p.stdout.splitlines() if ln.startswith("RESULT "))[7:])
    out["time_v_maxrss_kb"] = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", p.stderr).group(1))
    out["cpu_user"] = float(re.search(r"User time \(seconds\): ([\d.]+)", p.stderr).group(1))
    out["cpu_sys"] = float(re.search(r"System time \(seconds\): ([\d.]+)", p.stderr).group(1))
    if ckpt:
        shutil.rmtree(ckpt, ignore_errors=True)
    return out


def main(max_n):
    load = C.Load()
    import numpy as np

    runs = []
    workdir = tempfile.mkdtemp(prefix="obsjax_stream_")
    try:
        plan = [(n, "summary") for n in (10**5, 10**6, 10**7) if n <= max_n]
        plan += [(n, "all") for n in (10**5, 10**6) if n <= max_n]
        for n, keep in plan:
            r = run_child(n, keep, workdir)
            runs.append(r)
            print(f"N = {n:.0e} keep={keep}: wall {r['wall']:.1f} s, peak RSS "
                  f"{r['time_v_maxrss_kb'] / 2**20:.2f} GiB", flush=True)  # fmt: skip
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    ts = np.linspace(*TS)
    mean, std, med, dens = exact_stats(ts)
    big = max((r for r in runs if r["keep"] == "summary"), key=lambda r: r["n"])
    se = std / np.sqrt(big["n_done"])
    z_mean = np.max(np.abs(np.asarray(big["mean"]) - mean) / se)
    # the sample median's standard error is 1 / (2 f(m) sqrt(N)), f the density at the median m
    se_med = 1.0 / (2 * dens * np.sqrt(big["n_done"]))
    dev_med = np.abs(np.asarray(big["median"]) - med)
    z_med = np.max((dev_med - 1e-3 * med) / se_med)  # after the sketch's relative accuracy α
    rel_med = np.max(dev_med / med)
    stream = [r for r in runs if r["keep"] == "summary"]
    peaks = [r["time_v_maxrss_kb"] / 2**20 for r in stream]
    flat = max(peaks) - min(peaks)

    def row(r):
        gib = r["time_v_maxrss_kb"] / 2**20
        target = C.verdict(gib, 1.5, "lower") if r["keep"] == "summary" else "(contrast)"
        return (f"| {r['n']:.0e} | `{r['keep']}` | {r['wall']:.1f} s | {r['compute']:.1f} s | "
                f"{r['n_done'] / r['compute']:.3g} /s | {r['cpu_user'] + r['cpu_sys']:.0f} s | "
                f"**{gib:.2f} GiB** ({r['maxrss_kb'] / 2**20:.2f}) | {target} | "
                f"{r['disk'] / 2**30:.2f} GiB |")  # fmt: skip

    table = "\n".join(row(r) for r in runs)
    body = f"""
A study whose per-trajectory results do not fit in memory: `monte_carlo(..., keep="summary")` folds each
chunk into streaming statistics (exact counts and sums; quantiles from relative-accuracy logarithmic
histograms, α = 10⁻³) and drops it; the per-trajectory rows go to the checkpoint's chunk files on disk.

Plant ẋ = A x, A = [[−2, 1], [0, −1]], y = x₁; Luenberger observer, poles (−2, −3), on the exact model;
x(0) ~ N(0, I), x̂(0) = 0; fixed-step Tsit5, h = 0.1, on [0, 2], 21 save times; chunks of {CHUNK}; one
fresh process per study, peak resident memory of the whole process by `/usr/bin/time -v` (in parentheses:
`resource.getrusage` in the process; JAX, XLA compilation and the Python interpreter included).

| N | keep | wall (process) | computing | throughput | CPU (user + sys) | peak RSS | target ≤ 1.5 GB | on disk |
|---|---|---|---|---|---|---|---|---|
{table}

Peak RSS of the streaming studies: {', '.join(f'{p:.2f}' for p in peaks)} GiB for N =
{', '.join(f'{r["n"]:.0e}' for r in stream)}: spread {flat * 1024:.0f} MiB (flat in N: the memory is the
process, the compiled kernel, one chunk and the sketches).  The in-memory studies keep N × 21 floats and
their per-row statistics, and grow with N.

Check against the closed form (N = {big['n']:.0e}): ‖x̃(t)‖ of x̃(t) = −exp(F t) x(0) has mean
E‖x̃(t)‖ and median from one-dimensional integrals (SciPy).  Largest deviation of the streamed mean over the
21 save times: **{z_mean:.2f} standard errors** (must be < 4); of the streamed median band (a sketch,
α = 10⁻³): {rel_med:.2e} relative, **{z_med:.2f} standard errors of the sample median** beyond the sketch's
α·m (must be < 4).  Failed trajectories: {big['failed']}.
"""
    if max_n < 10**7:
        body += f"""
This run stopped at N = {max_n:.0e} (`--max-n`); the 10⁷ study was not run here.
"""
    C.write_result("s_streaming_study", "Benchmark (s): a study larger than memory", body, load)
    ok = z_mean < 4 and z_med < 4 and big["failed"] == 0
    return 0 if ok else 1


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(int(sys.argv[2]), sys.argv[3], sys.argv[4] if len(sys.argv) > 4 else None)
        sys.exit(0)
    ap = argparse.ArgumentParser()
    ap.add_argument("--max-n", type=int, default=10**7)
    a = ap.parse_args()
    sys.exit(main(a.max_n))
