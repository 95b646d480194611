"""Benchmark (n): the programs JAX lowers on a script's first run, and what they cost.

Every JAX operation run eagerly (outside ``jit``) compiles a program of its own on its first call in a
process, and on jax 0.10 so does ``jnp.asarray`` of a Python number, a list or a NumPy array: tens of
milliseconds each on a CPU, lowered again in every process even when the compiled code comes from the
persistent cache.  This benchmark runs three workloads in fresh processes and counts, with
``jax.monitoring``'s compilation events (public API: one event per program lowered, with its name and
duration), every program lowered, the time spent lowering them and the time in XLA's compiler (or reading
the cache):

1. README's first example (``Luenberger.from_poles``, ``simulate`` with a multisine input, ``error_norm``);
2. README's tour (Chen & Yen's ``simulate`` with 40 resets, ten ``tune`` steps with noise, a 2000-trajectory
   ``monte_carlo``);
3. ``obsjax demo`` (its second run, the compilation cache warm: the run that benchmark (h) times).

Programs are split into *small* ones (lowered and compiled in under 0.4 s together: single operations,
checks, conversions, random draws) and the rest (the solver kernels; in the demo's second run the kernels
come from the cache in less than that and count as small too, so there the two columns are the same).  The snippets are read from
README.md, so they stay in step with it.  ``--python PATH --label NAME`` adds a column run with another
interpreter (e.g. the virtual environment of an earlier commit), so that both are measured in one run on
one machine.

Usage: ``python benchmarks/n_eager_programs.py [--python /old/venv/bin/python --label before]``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile

import _common as C

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SMALL_S = 0.4

CHILD = r"""
import json, sys, time, runpy, collections
import jax
LOWER = "/jax/core/compile/jaxpr_to_mlir_module_duration"
COMPILE = "/jax/core/compile/backend_compile_duration"
rec = collections.defaultdict(lambda: [0, 0.0, 0.0])  # name -> [count, lowering s, compile s]
order = []
def listener(event, duration, **kw):
    name = str(kw.get("fun_name", "?"))
    if event == LOWER:
        rec[name][0] += 1
        rec[name][1] += duration
        order.append([name, duration, 0.0])
    elif event == COMPILE:
        rec[name][2] += duration
        if order and order[-1][0] == name:
            order[-1][2] += duration
jax.monitoring.register_event_duration_secs_listener(listener)
kind, target, out = sys.argv[1], sys.argv[2], sys.argv[3]
t0 = time.perf_counter()
if kind == "script":
    runpy.run_path(target, run_name="__main__")
else:
    from obsjax.cli import main
    sys.argv = ["obsjax", "demo", "--out", target]
    main()
wall = time.perf_counter() - t0
json.dump({"wall": wall, "programs": order}, open(out, "w"))
"""


def _snippets():
    text = open(os.path.join(ROOT, "README.md"), encoding="utf-8").read()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    return {"README's first example": blocks[0], "README's tour": blocks[1]}


def _run(python, kind, target, env):
    with tempfile.TemporaryDirectory() as d:
        out = os.path.join(d, "out.json")
        child = os.path.join(d, "child.py")
        with open(child, "w") as f:
            f.write(CHILD)
        r = subprocess.run([python, child, kind, target, out], env=env, capture_output=True, text=True,
                           cwd=d, timeout=900)  # fmt: skip
        if r.returncode != 0:
            raise RuntimeError(f"{kind} {target} failed:\n{r.stderr[-3000:]}")
        return json.load(open(out))


def measure(python, workloads):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env.update({"JAX_PLATFORMS": "cpu", "MPLBACKEND": "Agg", "TF_CPP_MIN_LOG_LEVEL": "3"})
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        cache = os.path.join(tmp, "cache")
        for label, kind, target in workloads:
            e = dict(env)
            if kind == "demo":  # first run fills the cache; the second is measured
                e["OBSJAX_COMPILATION_CACHE_DIR"] = cache
                _run(python, kind, os.path.join(tmp, "demo"), e)
                got = _run(python, kind, os.path.join(tmp, "demo"), e)
            else:
                e["OBSJAX_NO_COMPILATION_CACHE"] = "1"
                path = os.path.join(tmp, re.sub(r"\W+", "_", label) + ".py")
                with open(path, "w") as f:
                    f.write(target)
                got = _run(python, "script", path, e)
            progs = got["programs"]
            small = [p for p in progs if p[1] + p[2] < SMALL_S]
            names: dict = {}
            for n, lo, co in small:
                names[n] = names.get(n, 0) + 1
            rows[label] = {
                "wall": got["wall"], "n": len(progs), "t": sum(p[1] + p[2] for p in progs),
                "n_small": len(small), "t_small": sum(p[1] + p[2] for p in small),
                "lower_small": sum(p[1] for p in small),
                "top": sorted(names.items(), key=lambda kv: -kv[1])[:8],
            }  # fmt: skip
            print(f"{label}: {rows[label]['n_small']} small programs, {rows[label]['t_small']:.2f} s; "
                  f"{rows[label]['n']} in all; wall {rows[label]['wall']:.1f} s", flush=True)  # fmt: skip
    return rows


def main(python_other=None, label_other=None):
    snips = _snippets()
    workloads = [(k, "script", v) for k, v in snips.items()] + [
        ("`obsjax demo`, second run (cache warm)", "demo", None)
    ]
    columns = [("this code", sys.executable)]
    if python_other:
        columns.append((label_other or "other", python_other))
    load = C.Load()
    results = {}
    for name, py in columns:
        results[name] = measure(py, workloads)
    lines = [
        __doc__.split("\n\n", 1)[1].split("Usage:")[0].strip(),
        "",
        "Each cell: small programs (their lowering and compilation time) / all programs (all their time); the "
        "process's wall time of the workload.  The first two workloads run with the compilation cache off "
        "(`OBSJAX_NO_COMPILATION_CACHE=1`); the demo's second run reads its programs from the cache its first "
        "run filled.",
        "",
        "| workload | " + " | ".join(n for n, _ in columns) + " |",
        "|---|" + "---|" * len(columns),
    ]
    for label, _, _ in workloads:
        cells = []
        for name, _ in columns:
            r = results[name][label]
            cells.append(
                f"{r['n_small']} small ({r['t_small']:.2f} s, of which lowering {r['lower_small']:.2f} s) / "
                f"{r['n']} in all ({r['t']:.2f} s); wall {r['wall']:.1f} s"
            )
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", "The small programs most often lowered (name: count):", ""]
    for name, _ in columns:
        for label, _, _ in workloads:
            top = ", ".join(f"`{n}`: {c}" for n, c in results[name][label]["top"])
            lines.append(f"- {name}, {label}: {top or 'none'}")
    C.write_result(
        "n_eager_programs", "Benchmark (n): programs lowered on a script's first run", "\n".join(lines),
        load=load,
    )  # fmt: skip
    return results

if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("--python", default=None, help="another interpreter to measure beside this one")
    p.add_argument("--label", default=None, help="its column's name")
    a = p.parse_args()
    main(a.python, a.label)
