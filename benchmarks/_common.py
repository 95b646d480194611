"""Shared helpers of the benchmarks: timing as diffrax's benchmarking advice says, machine and version info,
the Chen & Yen problem, and the result-file writer.

Timing rules (diffrax docs, "How to benchmark"): everything inside one ``jax.jit``; a warm-up call (compile)
before timing; ``jax.block_until_ready`` on the outputs; float64 (``import obsjax`` enables it); problems of
at least 100 ms (batches are sized so that one call takes that long; calls are repeated and the minimum is
reported, the least disturbed by other processes).
"""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

#: where the tables go; ``OBSJAX_BENCH_RESULTS`` redirects them (the smoke tests write to a temporary folder)
RESULTS = os.environ.get("OBSJAX_BENCH_RESULTS") or os.path.join(ROOT, "benchmarks", "results")


def timeit(fn, *args, repeat=5, min_time=0.1, max_time=None, return_output=False):
    """(first-call seconds, best steady-state seconds, median) of ``fn(*args)`` with block_until_ready.

    The steady-state call is repeated until it has run ``repeat`` times and at least ``min_time`` in total,
    or, with ``max_time``, until the calls have taken ``max_time`` in total (at least one call).  With
    ``return_output=True`` the first call's output and the number of steady-state calls are appended.
    """
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    times = []
    while len(times) < repeat or sum(times) < min_time:
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
        if len(times) > 200 or (max_time is not None and sum(times) >= max_time):
            break
    times.sort()
    result = (first, times[0], times[len(times) // 2])
    return (*result, out, len(times)) if return_output else result


def machine() -> dict:
    info = {
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "cpus": os.cpu_count(),
    }
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    info["cpu"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        with open("/proc/meminfo") as fh:
            info["memory"] = fh.readline().split(":", 1)[1].strip()
    except OSError:
        pass
    info["loadavg"] = " ".join(f"{x:.2f}" for x in os.getloadavg())
    return info


def versions() -> dict:
    import importlib

    out = {}
    for mod in ("jax", "jaxlib", "diffrax", "equinox", "optax", "numpy", "scipy", "control"):
        try:
            out[mod] = importlib.import_module(mod).__version__
        except Exception:
            out[mod] = "n/a"
    try:
        import jax

        out["jax backend"] = f"{jax.default_backend()} ({len(jax.devices())} device(s))"
        import obsjax  # noqa: F401  (enables float64, as in every measuring process)

        out["x64"] = str(jax.config.jax_enable_x64)
    except Exception:
        pass
    return out


def other_processes(limit=8) -> list[str]:
    """The busiest other processes right now (what else was running during the measurement)."""
    try:
        out = subprocess.run(
            ["ps", "-eo", "pid,pcpu,etime,args", "--sort=-pcpu"],
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.splitlines()
    except Exception:
        return []
    me = os.getpid()
    rows = []
    for line in out[1:]:
        parts = line.split(None, 3)
        if len(parts) < 4 or int(parts[0]) == me or float(parts[1]) < 5.0:
            continue
        rows.append(f"pid {parts[0]}, {parts[1]} % CPU: {parts[3][:110]}")
        if len(rows) >= limit:
            break
    return rows


class Load:
    """Records load averages and the busiest processes at the start and the end of a benchmark."""

    def __init__(self):
        self.start = (os.getloadavg(), other_processes())

    def finish(self):
        self.end = (os.getloadavg(), other_processes())
        return self

    def markdown(self) -> str:
        lines = ["## What else was running", ""]
        for when, (la, procs) in (("start", self.start), ("end", self.end)):
            lines.append(
                f"- at the {when}: load average {la[0]:.2f} / {la[1]:.2f} / {la[2]:.2f} "
                f"(1 / 5 / 15 min) on {os.cpu_count()} CPUs"
            )
            for p in procs:
                lines.append(f"  - {p}")
            if not procs:
                lines.append("  - no other process above 5 % CPU")
        return "\n".join(lines)


def write_result(name: str, title: str, body: str, load: Load | None = None, script: str | None = None) -> str:
    """Write ``results/<name>.md``.  Run on an accelerator (JAX's default back-end not the CPU), the
    table goes beside the CPU one, to ``<name>_gpu.md``, its title naming the device."""
    import jax

    script = script or name
    if jax.default_backend() != "cpu" and not name.endswith("_gpu"):
        name += "_gpu"
        title += f" — {jax.default_backend().upper()} ({jax.devices()[0].device_kind})"
    os.makedirs(RESULTS, exist_ok=True)
    path = os.path.join(RESULTS, f"{name}.md")
    m, v = machine(), versions()
    parts = [
        f"# {title}",
        "",
        f"Run {datetime.datetime.now().strftime('%Y-%m-%d %H:%M:%S')} by `benchmarks/{script}.py`.",
        "",
        body.strip(),
        "",
        "## Machine",
        "",
        *[f"- {k}: {val}" for k, val in m.items()],
        "",
        "## Versions",
        "",
        *[f"- {k}: {val}" for k, val in v.items()],
        "",
    ]
    if load is not None:
        parts += [load.finish().markdown(), ""]
    with open(path, "w") as fh:
        fh.write("\n".join(parts))
    print(f"wrote {path}")
    return path


def verdict(value: float, target: float, better: str) -> str:
    """'met' or 'missed by …' for a target (better = 'higher' or 'lower')."""
    if better == "higher":
        ok = value >= target
        gap = target / value if value > 0 else float("inf")
        return (
            "**met**"
            if ok
            else f"**missed** by a factor {gap:.2f} (need {target:g}, got {value:.3g})"
        )
    ok = value <= target
    gap = value / target
    return (
        "**met**"
        if ok
        else f"**missed** by a factor {gap:.2f} (need ≤ {target:g}, got {value:.3g})"
    )


# ------------------------------------------------------------------------------------------------ Chen & Yen

GAMMA, P0, T_RESET = 20.0, 0.1, 0.25
T1 = 10.0


def chen_yen():
    import obsjax

    plant = obsjax.chen_yen_example()
    return plant, obsjax.LeastSquaresReset(plant, GAMMA, P0, T_RESET)


def chen_yen_batch(batch, seed=0):
    """x(0) ~ N(0, I), x̂(0) = [5, -5] (the paper's estimate) for a batch."""
    import numpy as np

    rng = np.random.default_rng(seed)
    x0s = rng.normal(size=(batch, 2))
    xh0s = np.tile([5.0, -5.0], (batch, 1))
    return x0s, xh0s


def scipy_chen_yen(x0, xh0, ts, rtol=1e-6, atol=1e-8, T=T_RESET, gamma=GAMMA, p0=P0):
    """The plant and the least-squares observer (8), (11), (13), (15) with SciPy's RK45, segment by segment
    (what a user writes without obsjax).  Returns ‖x̃(t)‖ at ``ts``."""
    import numpy as np
    from scipy.integrate import solve_ivp

    def A(t):
        c, s = np.cos(t), np.sin(t)
        return np.array([[-1 + 1.5 * c * c, 1 - 1.5 * s * c], [-1 + 1.5 * s * c, -1 + 1.5 * s * s]])

    def C(t):
        r = np.sqrt(t)
        return np.array([[np.cos(r) + np.sin(r), 3 * np.cos(r) ** 2]])

    def f(t, s):
        x, xh = s[:2], s[2:4]
        Phi, P = s[4:8].reshape(2, 2), s[8:].reshape(2, 2)
        At, Ct = A(t), C(t)
        w = Phi.T @ Ct.T
        L = gamma * Phi @ P @ w
        dxh = At @ xh + L @ (Ct @ x - Ct @ xh)
        return np.concatenate([At @ x, dxh, (At @ Phi).ravel(), (-gamma * P @ w @ w.T @ P).ravel()])

    out = np.empty(len(ts))
    x, xh = np.asarray(x0, float), np.asarray(xh0, float)
    nseg = int(np.ceil((ts[-1] - ts[0]) / T - 1e-9))
    for k in range(nseg):
        a, b = ts[0] + k * T, min(ts[0] + (k + 1) * T, ts[-1])
        if k == nseg - 1:
            b = ts[-1]
        sel = [i for i, t in enumerate(ts) if (a <= t < b) or (k == nseg - 1 and t == b)]
        s0 = np.concatenate([x, xh, np.eye(2).ravel(), p0 * np.eye(2).ravel()])
        sol = solve_ivp(f, (a, b), s0, method="RK45", rtol=rtol, atol=atol, dense_output=True)
        for i in sel:
            s = sol.sol(ts[i])
            out[i] = np.linalg.norm(s[2:4] - s[:2])
        x, xh = sol.y[:2, -1], sol.y[2:4, -1]
    return out
