"""Benchmark (e): LTI Luenberger observer, obsjax against python-control on the same batch.

Thesis example (2.8): A = [[-2, 1], [0, -1]], B = [0, 1]ᵀ, C = [1, 0], observer poles {-3, -4}, input
u(t) = sin t + 0.5 sin 3t, x(0) ~ N(0, I), x̂(0) = 0, [0, 10] with 101 save points.

- python-control: ``control.place`` on the dual pair for L, then ``control.input_output_response`` of the
  plant-observer system [x; x̂] per trajectory (a Python loop; SciPy RK45 inside, rtol 1e-6, atol 1e-8 passed
  through ``solve_ivp_kwargs``).
- obsjax: ``Luenberger.from_poles`` and one ``jax.jit(jax.vmap(simulate))`` over the batch (Tsit5, rtol 1e-6).

Both are checked against the closed form x̃(t) = exp((A − LC) t) x̃(0).

Usage: ``python benchmarks/e_lti_python_control.py [--batch 4096] [--loop 64]``.
"""

from __future__ import annotations

import argparse
import time

import _common as C


def main(batch=4096, n_loop=64, repeat=3):
    load = C.Load()
    import control as ct
    import jax
    import numpy as np
    import scipy.linalg

    import obsjax

    A = np.array([[-2.0, 1.0], [0.0, -1.0]])
    B = np.array([[0.0], [1.0]])
    Cm = np.array([[1.0, 0.0]])
    poles = [-3.0, -4.0]
    ts = np.linspace(0.0, 10.0, 101)
    rng = np.random.default_rng(0)
    x0s = rng.normal(size=(batch, 2))
    xh0s = np.zeros((batch, 2))

    # python-control
    t0 = time.perf_counter()
    L_ct = ct.place(A.T, Cm.T, poles).T
    Aaug = np.block([[A, np.zeros((2, 2))], [L_ct @ Cm, A - L_ct @ Cm]])
    sys_aug = ct.ss(Aaug, np.vstack([B, B]), np.hstack([-np.eye(2), np.eye(2)]), np.zeros((2, 1)))
    U = np.sin(ts) + 0.5 * np.sin(3 * ts)
    err_ct = []
    for i in range(n_loop):
        resp = ct.input_output_response(
            sys_aug,
            ts,
            U,
            np.concatenate([x0s[i], xh0s[i]]),
            solve_ivp_kwargs={"rtol": 1e-6, "atol": 1e-8},
        )
        err_ct.append(np.linalg.norm(resp.outputs, axis=0))
    t_ct = time.perf_counter() - t0
    tput_ct = n_loop / t_ct

    # obsjax
    plant = obsjax.LTI(A, B, Cm)
    obs = obsjax.Luenberger.from_poles(plant, poles)
    u = obsjax.signals.multisine([1.0, 0.5], [1.0, 3.0])

    @jax.jit
    def run(x0s, xh0s):
        return jax.vmap(
            lambda x, xh: obsjax.simulate(plant, obs, x, xh, ts, u=u, throw=False).error_norm
        )(x0s, xh0s)

    first, best, med = C.timeit(run, x0s, xh0s, repeat=repeat)
    tput_oj = batch / best
    out = np.asarray(run(x0s, xh0s))

    # closed form
    L_oj = np.asarray(obs.gain)
    F = A - L_oj @ Cm
    ref = np.stack(
        [
            [np.linalg.norm(scipy.linalg.expm(F * t) @ (xh0s[i] - x0s[i])) for t in ts]
            for i in range(n_loop)
        ]
    )
    scale = np.linalg.norm(x0s[:n_loop], axis=1)[:, None]
    acc_ct = float(np.max(np.abs(np.stack(err_ct) - ref) / scale))
    acc_oj = float(np.max(np.abs(out[:n_loop] - ref) / scale))
    ratio = tput_oj / tput_ct
    body = f"""
Thesis example (2.8) with observer poles {{-3, -4}} (python-control's `place` refuses a repeated pole of
multiplicity above rank C), input u = sin t + 0.5 sin 3t, x(0) ~ N(0, I), x̂(0) = 0, 101 save points on
[0, 10].  Gains: python-control L = {L_ct.ravel().round(6).tolist()}, obsjax L = {L_oj.ravel().round(6).tolist()}.

| method | trajectories/s | ratio |
|---|---|---|
| python-control `place` + `input_output_response` loop ({n_loop} trajectories, RK45 rtol 1e-6) | {tput_ct:.1f} | 1 |
| obsjax `jit(vmap(simulate))`, batch {batch} (Tsit5 rtol 1e-6; best {best:.3f} s, median {med:.3f} s) | {tput_oj:.0f} | **{ratio:.0f}×** |

obsjax first call (trace + compile + run): {first:.1f} s.

Accuracy against the closed form ‖exp((A − LC)t) x̃(0)‖ (max over the grid, relative to ‖x̃(0)‖, {n_loop}
trajectories): python-control {acc_ct:.1e}, obsjax {acc_oj:.1e}.
"""
    C.write_result(
        "e_lti_python_control",
        "Benchmark (e): LTI Luenberger, obsjax against python-control",
        body,
        load,
    )
    return ratio


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--batch", type=int, default=4096)
    ap.add_argument("--loop", type=int, default=64)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    main(a.batch, a.loop, a.repeat)
