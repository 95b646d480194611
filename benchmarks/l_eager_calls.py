"""Benchmark (l): eager calls of ``simulate`` and ``simulate_batch`` on the same problem, with new values.

A user (or a test) calls ``obsjax.simulate(plant, obs, x0, xhat0, ts)`` eagerly, again and again, with other
initial states or gains of the same structure.  ``simulate`` runs its solve as one compiled program kept per
problem structure (``obsjax/_integrate/_compiled.py``); before, an eager call ran the back-end's loops as
separate primitives, and a problem with resets, observer updates or a batch compiled its loop again on every
call.  Both are measured in one run: "kept" is ``simulate`` as it is, "compiled again" calls the back-end
directly (``_compiled.call`` replaced by ``fn(*args)``, the behaviour before).  Each case runs in a fresh
process (first call: tracing and compilation, the compilation cache off); then CALLS calls with new initial
states (and a new gain where the observer has an array gain), median and best reported.

The last two cases differentiate eagerly (``jax.grad`` without ``jit``): the compiled program is then
differentiated as a whole and JAX keeps the derivative programs, where before the backward pass ran as
separate primitives and compiled its loop again on every call.

Usage: ``python benchmarks/l_eager_calls.py``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import _common as C

CALLS = 5


def case_luenberger():
    import jax.numpy as jnp

    import obsjax

    p = obsjax.LTI([[-2.0, 1.0], [0.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]])
    ts = jnp.linspace(0.0, 5.0, 51)

    def call(i):
        obs = obsjax.Luenberger(p, L=jnp.array([[4.0 + i], [3.0]]))
        return obsjax.simulate(p, obs, jnp.array([1.0 + i, -1.0]), jnp.zeros(2), ts).x

    return call


def _least_squares_case(**kw):
    def case():
        import jax.numpy as jnp

        import obsjax

        p = obsjax.chen_yen_example()
        ts = jnp.linspace(0.0, 10.0, 81)

        def call(i):
            obs = obsjax.LeastSquaresReset(p, gamma=jnp.asarray(20.0 + i), p0=0.1, T=0.25)
            return obsjax.simulate(p, obs, jnp.array([1.0 + i, -1.0]), jnp.zeros(2), ts, **kw).x

        return call

    return case


def case_cd_kalman():
    import jax.numpy as jnp

    import obsjax

    p = obsjax.LTI([[0.0, 1.0], [-2.0, -0.5]], [[0.0], [1.0]], [[1.0, 0.0]])
    ts = jnp.linspace(0.0, 5.0, 51)

    def call(i):
        obs = obsjax.ContinuousDiscreteKalman(p, jnp.eye(2) * (0.1 + i), [[0.01]], jnp.eye(2), period=0.1)
        return obsjax.simulate(p, obs, jnp.array([1.0 + i, -1.0]), jnp.zeros(2), ts).x

    return call


def _batch_case(lockstep):
    def case():
        import jax.numpy as jnp

        import obsjax

        p = obsjax.chen_yen_example()
        ts = jnp.linspace(0.0, 10.0, 81)
        x0s = jnp.stack([jnp.linspace(-1.0, 1.0, 64), jnp.linspace(2.0, -2.0, 64)], axis=1)

        def call(i):
            obs = obsjax.LeastSquaresReset(p, gamma=jnp.asarray(20.0 + i), p0=0.1, T=0.25)
            return obsjax.simulate_batch(p, obs, x0s * (1 + i), jnp.zeros((64, 2)), ts, lockstep=lockstep).x

        return call

    return case


def _gradient_case(lockstep=None):
    """jax.grad without jit, in the gain γ: of the ISE of one trajectory (lockstep None), or of Σ‖x̃‖² over a
    batch of 64."""

    def case():
        import jax
        import jax.numpy as jnp

        import obsjax

        p = obsjax.chen_yen_example()
        ts = jnp.linspace(0.0, 10.0, 81)
        x0s = jnp.stack([jnp.linspace(-1.0, 1.0, 64), jnp.linspace(2.0, -2.0, 64)], axis=1)

        def loss(gamma, scale):
            obs = obsjax.LeastSquaresReset(p, gamma=gamma, p0=0.1, T=0.25)
            if lockstep is None:
                return obsjax.losses.ise(obsjax.simulate(p, obs, x0s[0] * scale, jnp.zeros(2), ts))
            tb = obsjax.simulate_batch(p, obs, x0s * scale, jnp.zeros((64, 2)), ts, lockstep=lockstep)
            return jnp.sum(tb.error**2)

        def call(i):
            return jax.grad(loss)(jnp.asarray(20.0 + i), 1.0 + i)

        return call

    return case


CASES = {
    "Luenberger (no breakpoint), simulate": case_luenberger,
    "LeastSquaresReset (40 resets), simulate": _least_squares_case(),
    "LeastSquaresReset, fixed steps h = 0.0125, simulate": _least_squares_case(adaptive=False, dt0=0.0125),
    "ContinuousDiscreteKalman (50 updates), simulate": case_cd_kalman,
    "LeastSquaresReset, simulate_batch of 64 (own steps)": _batch_case(False),
    "LeastSquaresReset, simulate_batch of 64 (lock step)": _batch_case(True),
    "LeastSquaresReset (40 resets), jax.grad (no jit) of the ISE in γ": _gradient_case(),
    "LeastSquaresReset, jax.grad (no jit) in γ over a simulate_batch of 64 (lock step)": _gradient_case(True),
}


def _child(name, mode):
    import jax

    import obsjax  # noqa: F401
    from obsjax._integrate import _compiled

    if mode == "compiled again":
        _compiled.call = lambda fn, *args: fn(*args)
    call = CASES[name]()
    t0 = time.perf_counter()
    jax.block_until_ready(call(0))
    first = time.perf_counter() - t0
    times = []
    for i in range(1, CALLS + 1):
        t0 = time.perf_counter()
        jax.block_until_ready(call(i))
        times.append(time.perf_counter() - t0)
    times.sort()
    print(json.dumps({"first": first, "best": times[0], "median": times[len(times) // 2]}))


def main():
    if len(sys.argv) == 4 and sys.argv[1] == "--child":
        _child(sys.argv[2], sys.argv[3])
        return
    load = C.Load()
    env = dict(__import__("os").environ, OBSJAX_NO_COMPILATION_CACHE="1")
    rows = []
    for name in CASES:
        res = {}
        for mode in ("kept", "compiled again"):
            out = subprocess.run(
                [sys.executable, __file__, "--child", name, mode], capture_output=True, text=True, env=env,
                timeout=1200,
            )
            if out.returncode != 0:
                raise RuntimeError(out.stderr[-3000:])
            res[mode] = json.loads(out.stdout.strip().splitlines()[-1])
        k, a = res["kept"], res["compiled again"]
        rows.append(
            f"| {name} | {k['first']:.2f} s | {k['median'] * 1e3:.1f} ms ({k['best'] * 1e3:.1f} ms) | "
            f"{a['first']:.2f} s | {a['median'] * 1e3:.1f} ms ({a['best'] * 1e3:.1f} ms) | "
            f"**{a['median'] / k['median']:.0f}×** |"
        )
        print(rows[-1], flush=True)
    body = "\n".join(
        [
            __doc__.split("Usage:")[0].split("\n", 1)[1].strip(),
            "",
            "| problem | kept: first call | kept: later call, median (best) | compiled again: first call | "
            "compiled again: later call, median (best) | later call, compiled again / kept |",
            "|---|---|---|---|---|---|",
            *rows,
        ]
    )
    C.write_result("l_eager_calls", "Benchmark (l): eager calls on the same problem with new values", body, load)


if __name__ == "__main__":
    main()
