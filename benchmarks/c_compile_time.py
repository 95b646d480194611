"""Benchmark (c): first-call compile time of a jitted ``simulate`` for each observer family, and no retrace
when gain values change (``eqx.debug.assert_max_traces``).

Each family is measured in a fresh Python process (so no family profits from another's warm caches): the
first call of ``eqx.filter_jit(simulate)`` (trace + compile + run) minus a steady-state call is the compile
time; then the call is repeated with new gain values under ``assert_max_traces(max_traces=1)``.

Families not present on this branch are listed as not measured; add a factory to FAMILIES when a family lands.

Usage: ``python benchmarks/c_compile_time.py``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import _common as C


def _thesis_plant():
    import obsjax

    return obsjax.LTI([[-2.0, 1.0], [0.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]])


def _three_state():
    import obsjax

    A = [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -3.0, -3.0]]
    return obsjax.LTI(A, [[0.0], [0.0], [1.0]], [[1.0, 0.0, 0.0]])


def f_luenberger():
    import obsjax

    p = _thesis_plant()
    return p, obsjax.Luenberger.from_poles(p, [-3.0, -4.0]), lambda o: o.poles, None


def f_reduced():
    import obsjax

    p = _thesis_plant()
    return p, obsjax.ReducedOrder.from_poles(p, [-3.0], Dc=[[0.0, 1.0]]), lambda o: o.poles, None


def f_functional():
    import obsjax

    p = _three_state()
    return p, obsjax.FunctionalObserver(p, [1.0, 2.0, 0.5], [-4.0, -5.0]), None, None


def f_least_squares():
    import obsjax

    p = obsjax.chen_yen_example()
    return p, obsjax.LeastSquaresReset(p, 20.0, 0.1, 0.25), lambda o: (o.gamma, o.p0, o.T), 41


def f_kalman_bucy():
    import jax.numpy as jnp

    import obsjax

    p = obsjax.chen_yen_example()
    return p, obsjax.KalmanBucy(p, 0.1 * jnp.eye(2), jnp.eye(1), jnp.eye(2)), lambda o: o.Rv, None


def f_generalized_inverse_reduced():
    from obsjax._reproduce.lovass_nagy import reduced_example

    p, o = reduced_example()
    return p, o, None, None, 5.0


def f_finite_window():
    import obsjax

    model = obsjax.LTI(
        [[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[2.0, 0.0]]
    )  # Byrski & Fuksa (29)
    obs = obsjax.FiniteWindow(model, 1.0, n_chunks=10)  # reset period h = T / 10 = 0.1
    return model, obs, None, 101, 10.0


def f_kreisselmeier():
    import jax.numpy as jnp

    import obsjax
    from obsjax._reproduce.adaptive import KREISSELMEIER_2 as ex
    from obsjax._reproduce.adaptive import kreisselmeier_gain

    plant = obsjax.kreisselmeier_form(ex["a"], ex["b"])
    obs = obsjax.Kreisselmeier(
        2, ex["poles"], jnp.asarray(kreisselmeier_gain(ex, 2.0)), scheme="gradient"
    )
    u = obsjax.signals.multisine(ex["amplitudes"], ex["frequencies"])
    return plant, obs, None, None, 10.0, u


def f_tlo():
    import jax.numpy as jnp

    import obsjax
    from obsjax._reproduce.huang_zhu import van_der_pol

    plant, model = van_der_pol()
    obs = obsjax.TrajectoryLinearization(model, rho_bar=jnp.array([-1.0, -2.0]), omega=2.0, eps=0.5)
    return plant, obs, lambda o: o.eps, None, 10.0


FAMILIES = {
    "Luenberger": f_luenberger,
    "ReducedOrder": f_reduced,
    "FunctionalObserver": f_functional,
    "LeastSquaresReset": f_least_squares,
    "KalmanBucy": f_kalman_bucy,
    "GeneralizedInverseReduced": f_generalized_inverse_reduced,
    "FiniteWindow": f_finite_window,
    "Kreisselmeier": f_kreisselmeier,
    "TrajectoryLinearization": f_tlo,
}
#: documented families without a factory above (listed as not measured when present)
OTHERS = (
    "GeneralizedInverse",
    "KudvaNarendra",
    "LudersNarendra",
    "ExtendedKalman",
    "MinMaxLuenberger",
)


def measure(name):
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np

    import obsjax

    plant, obs, where, max_seg, *rest = FAMILIES[name]()
    n = plant.n
    ts = np.linspace(0.0, rest[0] if rest else 10.0, 101)
    u = rest[1] if len(rest) > 1 else None
    x0 = jnp.ones(n)
    xh0 = jnp.zeros(n)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def run(o, x0, xh0):
        return obsjax.simulate(plant, o, x0, xh0, ts, u=u, max_segments=max_seg).error

    t0 = time.perf_counter()
    jax.block_until_ready(run(obs, x0, xh0))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(run(obs, x0, xh0))
    steady = time.perf_counter() - t0
    retrace_ok = None
    if where is not None:
        leaves = where(obs)
        new = (
            tuple(1.1 * jnp.asarray(v) for v in leaves)
            if isinstance(leaves, tuple)
            else 1.1 * jnp.asarray(leaves)
        )
        obs2 = eqx.tree_at(where, obs, new)
        try:
            out2 = jax.block_until_ready(run(obs2, 2.0 * x0, xh0))
            retrace_ok = bool(np.all(np.isfinite(np.asarray(out2))))
        except RuntimeError as e:  # assert_max_traces raises on a second trace
            retrace_ok = False
            print("retrace:", e, file=sys.stderr)
    return {"first": first, "steady": steady, "compile": first - steady, "no_retrace": retrace_ok}


def main():
    load = C.Load()
    import obsjax

    rows = []
    for name in FAMILIES:
        if not hasattr(obsjax, name):
            rows.append((name, None))
            continue
        out = subprocess.run(
            [sys.executable, __file__, "--family", name],
            capture_output=True,
            text=True,
            cwd=C.ROOT,
            timeout=600,
        )
        line = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
        if out.returncode != 0 or not line:
            print(out.stderr[-2000:])
            rows.append(
                (name, {"error": out.stderr.strip().splitlines()[-1] if out.stderr else "failed"})
            )
            continue
        r = json.loads(line[-1])
        rows.append((name, r))
        print(name, r)
    lines = []
    worst = 0.0
    for name, r in rows:
        if r is None:
            lines.append(f"| {name} | not on this branch | | | |")
        elif "error" in r:
            lines.append(f"| {name} | error: {r['error'][:80]} | | | |")
        else:
            worst = max(worst, r["compile"])
            nr = {True: "no retrace", False: "**retraced**", None: "(no tunable leaf)"}[
                r["no_retrace"]
            ]
            lines.append(
                f"| {name} | {r['compile']:.2f} s | {r['first']:.2f} s | {r['steady'] * 1e3:.1f} ms | "
                f"{nr} · {C.verdict(r['compile'], 5.0, 'lower')} |"
            )
    others = [o for o in OTHERS if hasattr(obsjax, o)]
    body = f"""
`eqx.filter_jit(simulate)` of one trajectory on [0, 10] ([0, 5] for the slides' generalized-inverse example; 101 save points, adaptive Tsit5, rtol 1e-6), each
family in a fresh process.  Compile = first call (trace + compile + run) − a steady-state call.  Then the
gains selected for tuning are multiplied by 1.1 and x0 by 2, and the call is repeated under
`eqx.debug.assert_max_traces(max_traces=1)` (it raises on a second trace).

| family | compile | first call | steady call | gains changed; target compile ≤ 5 s |
|---|---|---|---|---|
{chr(10).join(lines)}

Worst compile time: {worst:.2f} s — {C.verdict(worst, 5.0, "lower")}.
{"Families present in obsjax but without a factory here (not measured): " + ", ".join(others) if others else ""}
"""
    C.write_result(
        "c_compile_time", "Benchmark (c): first-call compile time and retracing", body, load
    )
    return rows


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--family":
        print(json.dumps(measure(sys.argv[2])))
    else:
        main()
