"""Streaming Monte-Carlo studies (``keep="summary"``): the sketch against exact quantiles, streaming
statistics against the in-memory study, resume, per-trajectory rows read back from disk."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import obsjax
from obsjax.montecarlo import LogHistogram

TINY = np.finfo(np.float64).tiny

# ẋ = x² blows up at t = 1/x0: trajectories with x0 > 1/2 fail on [0, 2], the others succeed; the
# observer x̂' = y − x̂ (L = 1 on the model ẋ = 0) then gives spread-out errors, some converging.
BLOWUP = obsjax.Nonlinear(lambda t, x, u: x**2, lambda t, x, u: x, n=1, m=1)
SCALAR_OBS = obsjax.Luenberger(obsjax.LTI([[0.0]], None, [[1.0]]), L=[[1.0]])
TS = np.linspace(0.0, 2.0, 11)
N, CHUNK = 200, 48  # 5 chunks, the last one padded


def x0_uniform(key):
    return jr.uniform(key, (1,), minval=0.0, maxval=0.8)


def xhat0_near(key, x0):
    return x0 + 0.3 * jr.normal(key, (1,))


def run(**kw):
    kw.setdefault("chunk_size", CHUNK)
    return obsjax.monte_carlo(BLOWUP, SCALAR_OBS, jr.PRNGKey(3), kw.pop("n", N), x0_sampler=x0_uniform,
                              xhat0_sampler=xhat0_near, ts=TS, progress=False,
                              simulate_kwargs={"max_steps": 2048}, **kw)  # fmt: skip


@pytest.fixture(scope="module")
def exact():
    return run()


# ---- the sketch -------------------------------------------------------------------------------------------


def _bound_holds(est, ref, rtol, floor=TINY):
    est, ref = np.asarray(est), np.asarray(ref)
    same_inf = np.isinf(est) & np.isinf(ref)
    with np.errstate(invalid="ignore"):
        err = np.where(same_inf, 0.0, np.abs(est - ref))
    return np.all(err <= rtol * np.abs(np.where(same_inf, 0.0, ref)) * (1 + 1e-12) + floor)


@pytest.mark.parametrize("rtol", [1e-3, 2e-2])
def test_sketch_quantiles_are_within_their_bound_of_exact_ones(rtol):
    rng = np.random.default_rng(0)
    x = np.exp(rng.normal(0.0, 6.0, size=(4001, 3)))  # 10 decades and more
    x[:40, 0] = 0.0
    x[:7, 1] = 1e-320  # subnormals count as zero
    x[-30:, 2] = np.inf  # a "lower" quantile may land on +inf
    h = LogHistogram(3, rtol)
    for part in np.array_split(x, 9):
        h.add(part)
    qs = np.linspace(0.0, 1.0, 401)
    lin = h.quantile(qs)
    ref = np.quantile(x[:, :2], qs, axis=0)
    assert _bound_holds(lin[:, :2], ref, rtol)
    assert _bound_holds(h.quantile(qs, "lower"), np.quantile(x, qs, axis=0, method="lower"), rtol)
    # the bound is tight enough to matter: the estimates are not the exact values
    assert np.max(np.abs(lin[:, :2] - ref) / np.maximum(ref, 1e-300)) > 0.1 * rtol
    for k in (1, 17, 400):
        top = np.mean(np.sort(x[:, 1])[-k:])
        assert abs(h.top_mean(k, column=1) - top) <= rtol * top
    assert np.array_equal(h.count, [4001, 4001, 4001])


def test_sketch_counts_do_not_depend_on_the_chunking():
    x = np.exp(np.random.default_rng(1).normal(0.0, 3.0, size=(1000, 2)))
    a, b = LogHistogram(2), LogHistogram(2)
    a.add(x)
    for part in np.array_split(x[::-1], 13):
        b.add(part)
    assert a.k0 == b.k0 and np.array_equal(a.counts, b.counts) and np.array_equal(a.zeros, b.zeros)


def test_a_sketch_that_folds_its_lowest_bins_states_its_floor():
    x = np.exp(np.random.default_rng(2).normal(0.0, 8.0, size=(3000, 1)))  # ~ 20 decades
    h = LogHistogram(1, 1e-3, max_bins=8000)  # ~ 7 decades at α = 1e-3: the largest are kept
    for part in np.array_split(x, 5):
        h.add(part)
    assert h.counts.shape[1] <= 8000 and h.floor > 0
    qs = np.linspace(0.0, 1.0, 301)
    assert _bound_holds(h.quantile(qs), np.quantile(x, qs, axis=0), 1e-3, floor=h.floor)
    # order statistics above the floor keep the relative bound alone
    ref = np.quantile(x, qs, axis=0, method="lower")
    above = ref[:, 0] > h.floor
    assert 5 < above.sum() < qs.size - 5
    assert _bound_holds(h.quantile(qs[above], "lower"), ref[above], 1e-3, floor=0.0)


def test_sketch_refuses_nan_and_negative_values():
    h = LogHistogram(1)
    with pytest.raises(ValueError, match="NaN or a negative"):
        h.add(np.array([[1.0], [np.nan]]))
    with pytest.raises(ValueError, match="NaN or a negative"):
        h.add(np.array([[-1.0]]))
    with pytest.raises(ValueError, match="relative accuracy"):
        LogHistogram(1, rtol=0.5)


# ---- streaming studies against the in-memory one ------------------------------------------------------------


def _assert_stream_matches(st, ex, rtol):
    assert st.keep == "summary" and st.sketch_rtol == rtol
    # exact statistics
    assert (st.n_done, st.n_failed, st.complete) == (ex.n_done, ex.n_failed, ex.complete)
    assert st.failure_fraction == ex.failure_fraction
    assert st.converged_fraction == ex.converged_fraction
    np.testing.assert_allclose(st.error_norm_mean, ex.error_norm_mean, rtol=1e-13)
    s, e = st.summary(), ex.summary()
    for key in ("n", "failed", "failure_fraction", "converged_fraction"):
        assert s[key] == e[key], key
    assert s["ise_mean"] == pytest.approx(e["ise_mean"], rel=1e-13)
    # sketched statistics: within their bound
    assert _bound_holds(st.bands, ex.bands, rtol)
    assert _bound_holds(st.band(0.33), ex.band(0.33), rtol)
    qs = (0.1, 0.5, 0.9, 0.99)
    assert _bound_holds(st.convergence_quantiles(qs), ex.convergence_quantiles(qs), rtol)
    for key in ("final_median", "final_p95", "conv_median", "conv_p95", "ise_cvar95"):
        assert _bound_holds(s[key], e[key], rtol), key


@pytest.mark.extended
def test_streaming_statistics_equal_the_in_memory_ones(exact):
    assert 0 < exact.n_failed < N and 0 < exact.converged_fraction < 1  # failures, both outcomes
    for rtol in (1e-3, 3e-2):
        _assert_stream_matches(run(keep="summary", sketch_rtol=rtol), exact, rtol)


def test_streaming_result_holds_no_per_trajectory_array(exact):
    st = run(keep="summary")
    for name in ("error_norm", "status", "convergence_time", "ise", "ok"):
        with pytest.raises(AttributeError, match=f"MonteCarloResult.{name} is not available.*keep='summary'"):
            getattr(st, name)
    with pytest.raises(ValueError, match="without `checkpoint`"):
        next(st.iter_chunks())
    arrays = [getattr(st, f.name) for f in dataclasses.fields(st)] + list(vars(st._stream).values())
    arrays += [vars(h)[k] for h in (st._stream.norms, st._stream.conv, st._stream.ise) for k in vars(h)]
    for a in arrays:
        if isinstance(a, np.ndarray):
            assert N not in a.shape and CHUNK not in a.shape, a.shape
    fig = st.plot()  # bands and the convergence-time histogram from the sketches
    assert len(fig.axes) == 2


def test_streaming_resumes_after_an_interruption_and_reads_rows_back(exact, tmp_path):
    ck = tmp_path / "ck"
    part = run(keep="summary", checkpoint=ck, max_chunks=2)
    assert not part.complete and part.n_done == 2 * CHUNK and part.n_computed == 2 * CHUNK
    resumed = run(keep="summary", checkpoint=ck)
    assert resumed.complete and resumed.n_computed == N - 2 * CHUNK
    _assert_stream_matches(resumed, exact, 1e-3)
    straight = run(keep="summary")
    np.testing.assert_array_equal(resumed.bands, straight.bands)  # integer counts: order-free
    # the per-trajectory rows are on disk: read back chunk by chunk, equal to the in-memory study
    starts, rows, status = zip(*resumed.iter_chunks())
    assert list(starts) == list(range(0, N, CHUNK))
    np.testing.assert_array_equal(np.concatenate(rows), exact.error_norm)
    np.testing.assert_array_equal(np.concatenate(status), exact.status)
    # the same checkpoint serves an in-memory study (the chunks do not depend on `keep`)
    loaded = run(checkpoint=ck)
    assert loaded.n_computed == 0
    np.testing.assert_array_equal(loaded.error_norm, exact.error_norm)


def test_streaming_arguments_are_checked():
    with pytest.raises(ValueError, match="`keep` must be 'all' or 'summary'"):
        run(n=4, keep="rows")
    with pytest.raises(ValueError, match="`sketch_rtol`"):
        run(n=4, keep="summary", sketch_rtol=0.0)


def test_in_memory_result_reads_its_chunks_back(exact, tmp_path):
    res = run(n=60, chunk_size=32, checkpoint=tmp_path / "ck")
    starts, rows, status = zip(*res.iter_chunks())
    assert starts == (0, 32)
    np.testing.assert_array_equal(np.concatenate(rows), res.error_norm)
    np.testing.assert_array_equal(np.concatenate(status), res.status)
    np.testing.assert_allclose(res.error_norm_mean, np.mean(res.error_norm[res.ok], axis=0), rtol=1e-15)
    with open(tmp_path / "ck" / "chunk_000001.npz", "r+b") as fh:  # damage after the study ran
        fh.seek(40)
        fh.write(b"\x00" * 8)
    with pytest.raises(ValueError, match="cannot be read back"):
        list(res.iter_chunks())


def test_a_study_without_successes_streams_nan_statistics():
    st = obsjax.monte_carlo(BLOWUP, SCALAR_OBS, jr.PRNGKey(0), 8, x0_sampler=lambda k: jnp.ones(1) * 2.0,
                            xhat0_sampler=np.zeros(1), ts=TS, progress=False, chunk_size=8,
                            keep="summary", simulate_kwargs={"max_steps": 2048})  # fmt: skip
    assert st.n_failed == 8 and st.failure_fraction == 1.0
    assert np.all(np.isnan(st.bands)) and np.all(np.isnan(st.error_norm_mean))
    s = st.summary()
    assert np.isnan(s["final_median"]) and np.isnan(s["ise_mean"]) and np.isnan(s["conv_median"])


# ---- several processes: the loaded chunks are broadcast one at a time and folded by every process ----------

_WORKER = r"""
import hashlib, json, os, sys
import jax
jax.distributed.initialize(coordinator_address="127.0.0.1:" + sys.argv[1], num_processes=2,
                           process_id=int(sys.argv[2]), initialization_timeout=120)
import jax.numpy as jnp, jax.random as jr, numpy as np
import obsjax

plant = obsjax.LTI([[-2.0, 1.0], [0.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]])
obs = obsjax.Luenberger.from_poles(plant, [-2.0, -3.0])
def x0s(k):
    return jr.normal(k, (2,))
def xh0(k):
    return jnp.zeros(2)
kw = dict(x0_sampler=x0s, xhat0_sampler=xh0, ts=np.linspace(0.0, 2.0, 9), chunk_size=32,
          progress=False, keep="summary", simulate_kwargs={"adaptive": False, "dt0": 0.1})
ck = os.path.join(sys.argv[3], "ck_p%d" % jax.process_index())
part = obsjax.monte_carlo(plant, obs, jr.PRNGKey(5), 100, checkpoint=ck, max_chunks=2, **kw)
res = obsjax.monte_carlo(plant, obs, jr.PRNGKey(5), 100, checkpoint=ck, **kw)
out = dict(part=part.n_done, computed=res.n_computed, n_done=res.n_done, bands=res.bands.tolist(),
           mean=res.error_norm_mean.tolist(), k0=res._stream.norms.k0,
           counts=hashlib.sha256(res._stream.norms.counts.tobytes()).hexdigest(),
           written=os.path.isdir(ck))
print("RESULT " + json.dumps(out), flush=True)
"""


@pytest.mark.extended
def test_two_processes_stream_like_one(tmp_path):
    import hashlib
    import json
    import os
    import socket
    import subprocess
    import sys

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port = str(s.getsockname()[1])
    script = tmp_path / "worker.py"
    script.write_text(_WORKER)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=root)
    env["XLA_FLAGS"] = " ".join(
        f for f in env.get("XLA_FLAGS", "").split() if "force_host_platform_device_count" not in f
    )
    logs = [open(tmp_path / f"p{i}.log", "w") for i in range(2)]  # noqa: SIM115 (closed below)
    procs = [subprocess.Popen([sys.executable, str(script), port, str(i), str(tmp_path)], env=env,
                              stdout=logs[i], stderr=subprocess.STDOUT)
             for i in range(2)]  # fmt: skip
    outs = []
    try:
        for p in procs:
            p.wait(timeout=240)
    finally:
        for p in procs:  # only the processes started here
            if p.poll() is None:
                p.kill()
                p.wait()
        for log in logs:
            log.close()
    for i, p in enumerate(procs):
        text = (tmp_path / f"p{i}.log").read_text()
        assert p.returncode == 0, text[-3000:]
        outs.append(json.loads(next(ln for ln in text.splitlines() if ln.startswith("RESULT "))[7:]))
    # one process, the same study (the worker's definitions)
    plant = obsjax.LTI([[-2.0, 1.0], [0.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]])
    one = obsjax.monte_carlo(plant, obsjax.Luenberger.from_poles(plant, [-2.0, -3.0]), jr.PRNGKey(5), 100,
                             x0_sampler=lambda k: jr.normal(k, (2,)), xhat0_sampler=np.zeros(2),
                             ts=np.linspace(0.0, 2.0, 9), chunk_size=32, progress=False, keep="summary",
                             simulate_kwargs={"adaptive": False, "dt0": 0.1})  # fmt: skip
    for o in outs:
        assert o["part"] == 64 and o["computed"] == 36 and o["n_done"] == 100
        # every process folded every chunk exactly once: the same integer counts
        assert o["k0"] == one._stream.norms.k0
        assert o["counts"] == hashlib.sha256(one._stream.norms.counts.tobytes()).hexdigest()
        np.testing.assert_array_equal(o["bands"], one.bands)
        np.testing.assert_allclose(o["mean"], one.error_norm_mean, rtol=1e-13)
    assert [o["written"] for o in outs] == [True, False]  # process 0 alone holds the checkpoint
