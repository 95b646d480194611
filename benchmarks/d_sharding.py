"""Benchmark (d): ``monte_carlo`` sharded over 2 host devices against 1, and a 10⁶-trajectory study.

The script re-runs itself with ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` (the CPU split into two
XLA devices).  Chen & Yen example, adaptive Tsit5 (rtol 1e-6), x(0) ~ N(0, I), x̂(0) = [5, -5], save grid of
11 points on [0, 10] (coarse: the host keeps N × 11 floats).

1. 4096 trajectories in one chunk, devices = 1 and devices = 2 (after a warm-up study that compiles the same
   kernel), with the default kernel (independent steps) and with ``lockstep=True``: throughput ratio (target ≥ 1.4×).
2. With ``--n N`` (e.g. 1000000): N trajectories in chunks of 4096 on 2 devices (lock step): throughput
   against the 4096-batch rate (target within 20 %), and the peak resident memory of the process; written to
   ``results/d_sharding_large.md`` (part 1 alone, the default ``--n 0``, writes ``results/d_sharding.md``).

Usage: ``python benchmarks/d_sharding.py [--n 1000000]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import _common as C


def x0_sampler(key):
    import jax.random as jr

    return jr.normal(key, (2,))


def xhat0_sampler(key):
    import jax.numpy as jnp

    return jnp.array([5.0, -5.0])


def child(n_big, chunk):
    import resource
    import time

    import jax
    import jax.random as jr
    import numpy as np

    import obsjax

    assert len(jax.devices()) == 2, jax.devices()
    plant, obs = C.chen_yen()
    ts = np.linspace(0.0, 10.0, 11)
    kw = dict(
        x0_sampler=x0_sampler, xhat0_sampler=xhat0_sampler, ts=ts, chunk_size=chunk, progress=False
    )
    out = {}
    for mode in ("vmap", "lock"):
        for d in (1, 2):
            mkw = dict(kw, devices=d, lockstep=mode == "lock")
            t0 = time.perf_counter()
            obsjax.monte_carlo(plant, obs, jr.PRNGKey(1), chunk, **mkw)  # warm-up: compiles the kernel
            out[f"compile_{mode}_{d}"] = time.perf_counter() - t0
            best, best_cpu = None, None
            for rep in range(3):
                c0 = time.process_time()
                r = obsjax.monte_carlo(plant, obs, jr.PRNGKey(2 + rep), chunk, **mkw)
                cpu = time.process_time() - c0
                if best is None or r.elapsed < best.elapsed:
                    best, best_cpu = r, cpu
            out[f"tput_{mode}_{d}"] = best.throughput
            out[f"cores_{mode}_{d}"] = best_cpu / best.elapsed
            out[f"fail_{mode}_{d}"] = best.n_failed
            print(f"{mode} devices={d}: {best.throughput:.0f} traj/s", file=sys.stderr, flush=True)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if n_big:
        t0 = time.perf_counter()
        # resumable: the study can be stopped (e.g. while other benchmarks run) and continued from here
        ckpt = os.environ.get("OBSJAX_BENCH_CHECKPOINT")
        big = obsjax.monte_carlo(
            plant, obs, jr.PRNGKey(9), n_big, devices=2, checkpoint=ckpt, lockstep=True,
            **{**kw, "progress": True},
        )
        out["big_computed_here"] = big.n_computed
        out["big_n"] = n_big
        out["big_wall"] = time.perf_counter() - t0
        out["big_tput"] = big.throughput
        out["big_failed"] = big.n_failed
        out["big_summary"] = {k: float(v) for k, v in big.summary().items()}
    out["rss_before_big_mib"] = rss0
    out["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps(out))


def main(n_big=0, chunk=4096):
    load = C.Load()
    env = dict(os.environ)
    env["XLA_FLAGS"] = (
        env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    ).strip()
    env["JAX_PLATFORMS"] = "cpu"
    proc = subprocess.run(
        [sys.executable, __file__, "--child", "--n", str(n_big), "--chunk", str(chunk)],
        env=env,
        stdout=subprocess.PIPE,
        text=True,
        cwd=C.ROOT,
    )  # stderr: progress bar
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        raise SystemExit("d_sharding: the child process failed")
    r = json.loads(lines[-1])
    sv = r["tput_vmap_2"] / r["tput_vmap_1"]
    sl = r["tput_lock_2"] / r["tput_lock_1"]
    body = f"""
Chen & Yen example (adaptive Tsit5, rtol 1e-6, 40 reset segments), x(0) ~ N(0, I), x̂(0) = [5, -5], 11 save
points on [0, 10].  `obsjax.monte_carlo` with `jax.shard_map` over a 1-D mesh of host devices
(`--xla_force_host_platform_device_count=2` on this {os.cpu_count()}-CPU machine); each device integrates its
own slice of the chunk, so no collective runs inside the adaptive while loops.  Two kernels: independent
solves (the default: each device's slice one `simulate_batch(lockstep=False)`, the masked adaptive
Runge–Kutta loop, each trajectory its own steps) and `lockstep=True` (each device's slice one lock-step
`simulate_batch`).  Throughput =
trajectories ÷ wall time of the study after a warm-up study of the same shape (best of 3); cores = process
CPU time ÷ wall time of that study (2 means both cores busy).

| study | trajectories/s | cores used |
|---|---|---|
| {chunk} trajectories, independent, 1 device | {r["tput_vmap_1"]:.0f} | {r["cores_vmap_1"]:.2f} |
| {chunk} trajectories, independent, 2 devices (shard_map) | {r["tput_vmap_2"]:.0f} | {r["cores_vmap_2"]:.2f} |
| speed-up (independent) | **{sv:.2f}×** — target ≥ 1.4×: {C.verdict(sv, 1.4, "higher")} | |
| {chunk} trajectories, lock step, 1 device | {r["tput_lock_1"]:.0f} | {r["cores_lock_1"]:.2f} |
| {chunk} trajectories, lock step, 2 devices (shard_map) | {r["tput_lock_2"]:.0f} | {r["cores_lock_2"]:.2f} |
| speed-up (lock step) | **{sl:.2f}×** — target ≥ 1.4×: {C.verdict(sl, 1.4, "higher")} | |
"""
    if r.get("big_n"):
        keep = r["big_tput"] / r["tput_lock_2"]
        body = (
            body.rstrip("\n")
            + f"""
| {r["big_n"]:,} trajectories, lock step, 2 devices, chunks of {chunk} | {r["big_tput"]:.0f} ({r["big_computed_here"]:,} computed in the last call, {r["big_wall"]:.0f} s wall) | |
| large-study rate ÷ {chunk}-batch rate (lock step, 2 devices) | **{keep:.2f}** — target ≥ 0.8: {C.verdict(keep, 0.8, "higher")} | |

Peak resident memory of the process: {r["peak_rss_mib"]:.0f} MiB ({r["rss_before_big_mib"]:.0f} MiB before the
large study; the host keeps ‖x̃‖ on the 11-point grid, {r["big_n"] * 11 * 8 / 2**20:.0f} MiB for N = {r["big_n"]:,}).
Failures in the large study: {r["big_failed"]} (counted from the per-trajectory status).
"""
        )
    body += f"""
Compile (first study, trace + compile + run of one chunk): independent {r["compile_vmap_1"]:.1f} s on 1 device,
{r["compile_vmap_2"]:.1f} s on 2; lock step {r["compile_lock_1"]:.1f} s and {r["compile_lock_2"]:.1f} s.
"""
    if r.get("big_n"):
        C.write_result(
            "d_sharding_large",
            f"Benchmark (d): a {r['big_n']:,}-trajectory sharded study",
            body,
            load,
        )
    else:
        body += "\nThe large (10⁶-trajectory) study is run separately: see `d_sharding_large.md`.\n"
        C.write_result("d_sharding", "Benchmark (d): sharded Monte-Carlo studies", body, load)
    return r


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--child", action="store_true")
    ap.add_argument("--n", type=int, default=0)
    ap.add_argument("--chunk", type=int, default=4096)
    a = ap.parse_args()
    if a.child:
        child(a.n, a.chunk)
    else:
        main(a.n, a.chunk)
