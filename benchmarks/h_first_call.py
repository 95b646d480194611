"""Benchmark (h): time to first result in fresh processes, with and without JAX's persistent
compilation cache.

Each workload runs in three fresh processes: with the cache turned off
(``OBSJAX_NO_COMPILATION_CACHE=1``), with the cache on and its directory just emptied (the first run
after installation), and again with the directory the previous run filled (the second run).
Workloads:

- ``obsjax demo`` (the command line turns the cache on itself);
- the first ``tune`` step of the README example (``steps=1``: compilation plus one gradient step; fixed steps
  as in the README, and the same problem with adaptive steps and 16 scenarios, the masked kernel);
- the first chunk of a Monte-Carlo study (the README's study with ``n = chunk_size = 2500``);
- the first adaptive ``simulate`` of the Chen & Yen example (40 reset segments).

The library workloads call ``obsjax.enable_compilation_cache()`` when the cache is on.  Each
process's wall time and CPU time (user + system, all threads) are recorded; the workload's own
section is timed inside the process (after imports).  The cache directory is a fresh temporary one
(``OBSJAX_COMPILATION_CACHE_DIR``).

With the trace cache (``obsjax.enable_trace_cache()``, on in the command) the library workloads run
twice more, cold and warm, and the demo once more with it turned off on the warm cache.

Usage: ``python benchmarks/h_first_call.py [--only demo,tune,tune-adaptive,mc,simulate] [--demo-n 10000]``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time

import _common as C

# Each workload script: imports (their time is reported apart), the cache as the row says, the Chen & Yen
# plant and the paper's observer; the tune scripts end by timing `tune(..., steps=1)`.
_PREAMBLE = r"""
import json, os, time
t_start = time.perf_counter()
import jax, jax.numpy as jnp, optax, obsjax
if os.environ.get("OBSJAX_H_TRACES") == "1":
    obsjax.enable_trace_cache()  # the compilation cache and the saved traces
elif os.environ.get("OBSJAX_NO_COMPILATION_CACHE") != "1":
    obsjax.enable_compilation_cache()
plant = obsjax.chen_yen_example()
obs = obsjax.LeastSquaresReset(plant, gamma=20.0, p0=0.1, T=0.25)
"""
_TUNE_END = r"""
jax.block_until_ready(res.observer)
print("RESULT", json.dumps({"section": time.perf_counter() - t0, "import": t0 - t_start}))
"""

# The README's tune example as it stands (fixed Tsit5 steps, 8 noisy scenarios, (γ, T) tuned).
_TUNE = _PREAMBLE + r"""
noise = obsjax.noise.BandLimitedNoise(0.05, dt=0.05)
fixed = dict(adaptive=False, dt0=0.0125)
x0s = 3 * jax.random.normal(jax.random.PRNGKey(0), (8, 2))
t0 = time.perf_counter()
res = obsjax.tune(obs, plant, where=lambda o: (o.gamma, o.T), loss=obsjax.losses.ise, x0s=x0s,
                  xhat0s=jnp.zeros((8, 2)), ts=jnp.linspace(0., 5.9, 61), optimizer=optax.adam(0.1),
                  steps=1, noise=noise, key=jax.random.PRNGKey(1), simulate_kwargs=fixed,
                  progress=False)
""" + _TUNE_END

# The example as it was before it moved to fixed steps: adaptive steps (the masked kernel), 16 scenarios.
_TUNE_ADAPTIVE = _PREAMBLE + r"""
x0s = jax.random.normal(jax.random.PRNGKey(0), (16, 2)); xh0s = jnp.zeros((16, 2))
t0 = time.perf_counter()
res = obsjax.tune(obs, plant, where=lambda o: (o.gamma, o.T), loss=obsjax.losses.ise, x0s=x0s,
                  xhat0s=xh0s, ts=jnp.linspace(0., 6., 61), optimizer=optax.adam(0.05), steps=1,
                  noise=obsjax.noise.BandLimitedNoise(0.05, dt=0.02), key=jax.random.PRNGKey(1),
                  progress=False)
""" + _TUNE_END

_MC = _PREAMBLE + r"""
t0 = time.perf_counter()
mc = obsjax.monte_carlo(plant, obs, jax.random.PRNGKey(2), 2500,
                        x0_sampler=lambda k: 3 * jax.random.normal(k, (2,)),
                        xhat0_sampler=lambda k: jnp.zeros(2), ts=jnp.linspace(0., 10., 41),
                        chunk_size=2500, progress=False)
print("RESULT", json.dumps({"section": time.perf_counter() - t0, "import": t0 - t_start,
                            "failed": int(mc.n_failed)}))
"""


# The first adaptive `simulate` of the same example (40 reset segments on [0, 10]): one eager call, the
# library's own compiled program (before, diffrax's checks of the save times made it a program JAX
# never writes to the cache).
_SIMULATE = _PREAMBLE + r"""
t0 = time.perf_counter()
tr = obsjax.simulate(plant, obs, jnp.array([1.0, -1.0]), jnp.array([5.0, -5.0]), jnp.linspace(0., 10., 41))
jax.block_until_ready(tr.error)
print("RESULT", json.dumps({"section": time.perf_counter() - t0, "import": t0 - t_start}))
"""


def _run(cmd, env, cwd):
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    out = subprocess.run(
        cmd, env=env, cwd=cwd, check=False, capture_output=True, text=True, timeout=3600
    )
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if out.returncode != 0:
        raise RuntimeError(f"{cmd[:3]} failed:\n{out.stdout[-2000:]}\n{out.stderr[-3000:]}")
    info = {}
    for line in out.stdout.splitlines():
        if line.startswith("RESULT "):
            info = json.loads(line[7:])
        if line.startswith("Total ") and " s (" in line:  # the demo's own summary line
            info["section"] = float(line.split()[1])
            info["demo_line"] = line.strip()
    return wall, cpu, info


def _cache_size(d):
    files = [os.path.join(d, f) for f in os.listdir(d)] if os.path.isdir(d) else []
    entries = [f for f in files if f.endswith("-cache")]
    return len(entries), sum(os.path.getsize(f) for f in files) / 2**20


def main(only=("demo", "tune", "tune-adaptive", "mc", "simulate"), demo_n=10_000):
    load = C.Load()
    work = tempfile.mkdtemp(prefix="obsjax-h-")
    base = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT"))
        # a user's installation keeps the modules' bytecode (pip compiles it, or the first import of an
        # editable install writes it): without this, a shell that sets PYTHONDONTWRITEBYTECODE would
        # make every process compile obsjax's sources again
        and k != "PYTHONDONTWRITEBYTECODE"
    }
    base["PYTHONPATH"] = C.ROOT + (
        os.pathsep + base["PYTHONPATH"] if base.get("PYTHONPATH") else ""
    )
    base["JAX_PLATFORMS"] = base.get("JAX_PLATFORMS", "cpu")
    base["MPLBACKEND"] = "Agg"
    workloads = {
        "demo": [  # as the `obsjax` command runs it (its entry point, obsjax.cli:main)
            sys.executable,
            "-c",
            "import sys; from obsjax.cli import main; sys.exit(main())",
            "demo",
            "--out",
            os.path.join(work, "demo"),
            "-n",
            str(demo_n),
        ],
        "tune": [sys.executable, "-c", _TUNE],
        "tune-adaptive": [sys.executable, "-c", _TUNE_ADAPTIVE],
        "mc": [sys.executable, "-c", _MC],
        "simulate": [sys.executable, "-c", _SIMULATE],
    }
    rows = []
    try:
        for name in only:
            cache = os.path.join(work, f"cache-{name}")
            for mode in _MODES[name]:
                env = dict(base)
                for k in (
                    "OBSJAX_NO_COMPILATION_CACHE",
                    "OBSJAX_NO_TRACE_CACHE",
                    "OBSJAX_H_TRACES",
                    "OBSJAX_DEFAULT_XLA_OPTIONS",
                ):
                    env.pop(k, None)
                if mode.endswith("default XLA options"):
                    env["OBSJAX_DEFAULT_XLA_OPTIONS"] = "1"
                env["OBSJAX_COMPILATION_CACHE_DIR"] = cache
                if mode.startswith("off"):
                    env["OBSJAX_NO_COMPILATION_CACHE"] = "1"
                elif mode.startswith("cold"):
                    shutil.rmtree(cache, ignore_errors=True)
                if mode.endswith("traces off"):
                    env["OBSJAX_NO_TRACE_CACHE"] = "1"
                elif mode.endswith("+ traces"):
                    env["OBSJAX_H_TRACES"] = "1"
                wall, cpu, info = _run(workloads[name], env, work)
                n, mib = _cache_size(cache)
                rows.append((name, mode, wall, cpu, info, n, mib))
                print(
                    f"{name:5s} {mode:5s} process {wall:7.1f} s wall {cpu:7.1f} s CPU; section "
                    f"{info.get('section', float('nan')):7.1f} s; cache {n} entries {mib:.1f} MiB",
                    flush=True,
                )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    C.write_result(
        "h_first_call",
        "Benchmark (h): time to first result in fresh processes",
        _report(rows, demo_n),
        load,
        script="h_first_call",
    )


# The command turns the trace cache on itself ("traces off": OBSJAX_NO_TRACE_CACHE=1 on the filled
# cache); the library workloads run as a user's script that turns on the compilation cache only, and
# again with obsjax.enable_trace_cache() ("+ traces").
_MODES = {
    "demo": (
        "off", "cold", "warm", "cold, traces off", "warm, traces off", "cold, default XLA options",
    ),
    "tune": ("off", "off, default XLA options", "cold", "warm", "cold + traces", "warm + traces"),
    "tune-adaptive": (
        "off", "off, default XLA options", "cold", "warm", "cold + traces", "warm + traces",
    ),
    "mc": ("off", "off, default XLA options", "cold", "warm", "cold + traces", "warm + traces"),
    "simulate": ("off", "off, default XLA options", "cold", "warm"),
}  # fmt: skip
_TARGETS = {
    ("demo", "cold"): 30.0,
    ("demo", "warm"): 12.0,
    ("tune", "warm"): 5.0,
    ("mc", "warm"): 4.0,
    ("tune", "warm + traces"): 5.0,
    ("tune-adaptive", "warm"): 5.0,
    ("tune-adaptive", "warm + traces"): 5.0,
    ("mc", "warm + traces"): 4.0,
}
_WHAT = {
    "demo": "`obsjax demo` (whole process; section = the demo's own total)",
    "tune": "first `tune` step of the README example, fixed steps (section: the `tune(..., steps=1)` call)",
    "tune-adaptive": "first `tune` step, the README's earlier example: adaptive steps, 16 scenarios, noise dt 0.02 (section: as above)",
    "mc": "first Monte-Carlo chunk, 2500 trajectories (section: the `monte_carlo` call)",
    "simulate": "first adaptive `simulate` of the example (40 resets; section: the `simulate` call)",
}


_NOTES = """
What the cache can and cannot save: JAX writes a compiled program to the cache only if it carries
no host callback (`eqx.error_if`'s checks are). The `throw=True` checks of `simulate` run outside
its compiled program, and obsjax's solves trace diffrax without its two checks of the save times
(which they satisfy by construction), so the eager `simulate` and `simulate_batch` programs are cached
unless an observer checks a gain inside its vector field; `tune`'s kernel and the Monte-Carlo kernels
are traced with the checks as NaN (no callbacks: a check that fires rejects the tuning step, or fails
the trajectory) and are cached. Tracing and lowering are
not saved by the compilation cache; with `obsjax.enable_trace_cache()` (which the `obsjax` command
turns on) the traced programs of `tune`'s and `monte_carlo`'s kernels are saved too (`jax.export`),
and a warm process reads them instead of tracing (rows "+ traces"; the demo's "traces off" rows run
the command with `OBSJAX_NO_TRACE_CACHE=1` on a cache of their own, emptied before the cold one: an
exported program compiles to other cache entries than the same kernel traced directly). The demo also shards its Monte-Carlo studies
over one XLA CPU device per core (`OBSJAX_DEMO_DEVICES`), in every row.

On a shared machine the process CPU time (all threads, compilation included) is the steadier
figure; the wall times above include waiting for the cores. Whether the machine was quiet: see
"What else was running" below.

Targets (issue: time to first result, on a quiet 2-core machine): `obsjax demo` ≤ 30 s on its
first run and ≤ 12 s on its second, the first `tune` step ≤ 5 s, the first Monte-Carlo chunk
≤ 4 s (the last two judged on the warm runs, the cache filled by an earlier process: with the
compilation cache alone, and with the saved traces as well).
"""


def _report(rows, demo_n):
    intro = (
        "Each row is a fresh process. *off*: `OBSJAX_NO_COMPILATION_CACHE=1`; *cold*: cache on, "
        "directory just emptied (first run after installation); *warm*: cache on, filled by the "
        "cold run (second run); *+ traces*: the script calls `obsjax.enable_trace_cache()` instead "
        "of `obsjax.enable_compilation_cache()`; *traces off*: `OBSJAX_NO_TRACE_CACHE=1`; "
        "*default XLA options*: `OBSJAX_DEFAULT_XLA_OPTIONS=1`, the kernels compiled with XLA's default "
        "CPU emitters (every other row: the elemental emitters, `xla_cpu_use_fusion_emitters=False`). "
        f"The demo runs with `-n {demo_n}`, through the `obsjax` command's entry point "
        "(`obsjax.cli:main`). The processes keep Python's bytecode files, as an installation does "
        "(`PYTHONDONTWRITEBYTECODE` is dropped from their environment)."
    )
    header = (
        "| workload | cache | process wall | process CPU | section wall | cache entries | target |"
    )
    lines = [
        intro,
        "",
        header,
        "|---|---|---|---|---|---|---|",
    ]
    for name, mode, wall, cpu, info, n, mib in rows:
        target = _TARGETS.get((name, mode))
        sec = info.get("section", float("nan"))
        measured = wall if name == "demo" else sec
        verdict = ""
        if target is not None:
            verdict = f"≤ {target:g} s: " + C.verdict(measured, target, "lower")
        lines.append(
            f"| {_WHAT[name]} | {mode} | {wall:.1f} s | {cpu:.1f} s | {sec:.1f} s | "
            f"{n} ({mib:.1f} MiB) | {verdict} |"
        )
    demo = [r for r in rows if r[0] == "demo" and "demo_line" in r[4]]
    if demo:
        lines += ["", "The demo's own summary lines:", ""]
        lines += [f"- {r[1]}: `{r[4]['demo_line']}`" for r in demo]
    paragraphs = [" ".join(p.split("\n")) for p in _NOTES.strip().split("\n\n")]
    for p in paragraphs:
        lines += ["", p]
    return "\n".join(lines)


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("--only", default="demo,tune,tune-adaptive,mc,simulate")
    p.add_argument("--demo-n", type=int, default=10_000)
    a = p.parse_args()
    sys.exit(main(tuple(a.only.split(",")), a.demo_n))
