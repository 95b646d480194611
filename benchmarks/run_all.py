"""Run the benchmarks (a)-(e), (g), (h) and (m) (a two-process study on localhost), each in its own process,
each writing benchmarks/results/<name>.md.

Usage: ``python benchmarks/run_all.py [a b c d e g h i m] [--large N]`` (``obsjax bench`` calls this).  ``--large N`` also
runs the N-trajectory sharded study of (d) (10⁶ takes a few minutes on 2 cores with the lock-step kernel).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
BENCHMARKS = {
    "a": "a_chen_yen_throughput.py",
    "b": "b_gradient_cost.py",
    "c": "c_compile_time.py",
    "d": "d_sharding.py",
    "e": "e_lti_python_control.py",
    "f": "f_placement.py",
    "f2": "f_placement_estimate.py",
    "m": "multihost_local.py",
    "g": "g_numba_dopri5.py",
    "h": "h_first_call.py",
    "i": "i_recorded_data.py",
    "j": "j_forward_gradient.py",
    "k": "k_plant_uncertainty.py",
    "l": "l_eager_calls.py",
    "n": "n_eager_programs.py",
    "s": "s_streaming_study.py",
}


def main(argv):
    large = None
    if "--large" in argv:
        i = argv.index("--large")
        large = argv[i + 1]
        argv = argv[:i] + argv[i + 2 :]
    names = argv or list(BENCHMARKS)
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        print(f"unknown benchmark(s) {unknown}; choose from {list(BENCHMARKS)}")
        return 2
    env = dict(os.environ)
    root = os.path.dirname(HERE)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    status = 0
    for n in names:
        cmd = [sys.executable, os.path.join(HERE, BENCHMARKS[n])]
        if n == "d" and large:
            cmd += ["--n", str(large)]
        print(f"== ({n}) {BENCHMARKS[n]}", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.call(cmd, cwd=HERE, env=env)
        print(f"== ({n}) finished in {time.perf_counter() - t0:.0f} s, exit code {rc}", flush=True)
        status |= rc
    return status


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
