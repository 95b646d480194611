"""JAX's persistent compilation cache: off on import, on by one call, filled by one process and read
by the next, opted out by an environment variable, turned on by the command line and for the test
run."""

import json
import os
import subprocess
import sys

import jax
import pytest

import obsjax
from obsjax import _cache

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_CLEAN = (
    "JAX_COMPILATION_CACHE_DIR",
    "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS",
    _cache.OPT_OUT,
    _cache.DIR_ENV,
)

# A small Monte-Carlo study: its kernel is traced without host callbacks, so JAX may write it to the
# cache.
_STUDY = r"""
import json, sys, time
import jax, jax.numpy as jnp, numpy as np
import obsjax

events = []
jax.monitoring.register_event_listener(lambda ev, **kw: events.append(ev))
path = obsjax.enable_compilation_cache(sys.argv[1], min_compile_time_secs=0.0)
plant = obsjax.LTI([[-2., 1.], [0., -1.]], [[0.], [1.]], [[1., 0.]])
obs = obsjax.Luenberger.from_poles(plant, [-3., -3.])
t0 = time.perf_counter()
res = obsjax.monte_carlo(plant, obs, jax.random.PRNGKey(0), 8, x0_sampler=lambda k:
jax.random.normal(k, (2,)),
                         xhat0_sampler=lambda k: jnp.zeros(2), ts=np.linspace(0., 1., 5),
                         chunk_size=8, progress=False)
print(json.dumps({"path": path, "seconds": time.perf_counter() - t0,
                  "hits": events.count("/jax/compilation_cache/cache_hits"),
                  "misses": events.count("/jax/compilation_cache/cache_misses"),
                  "error_norm": np.asarray(res.error_norm).ravel().tolist()}))
"""


def _env(**extra):
    env = {k: v for k, v in os.environ.items() if k not in _CLEAN}
    env["PYTHONPATH"] = ROOT + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.update(extra)
    return env


def _python(code, *args, **env):
    out = subprocess.run(
        [sys.executable, "-c", code, *args],
        check=False,
        capture_output=True,
        text=True,
        env=_env(**env),
        timeout=600,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout.strip().splitlines()[-1]


def test_import_does_not_turn_the_cache_on():
    line = _python("import jax, obsjax; print(jax.config.jax_compilation_cache_dir)")
    assert line == "None"


@pytest.mark.extended
def test_a_second_process_reads_what_the_first_wrote(tmp_path):
    d = str(tmp_path / "cache")
    first = json.loads(_python(_STUDY, d))
    assert first["path"] == d and first["hits"] == 0 and first["misses"] >= 1
    entries = [f for f in os.listdir(d) if f.endswith("-cache")]
    assert any("chunk_kernel" in f for f in entries), (
        entries
    )  # the study's kernel itself was written
    second = json.loads(_python(_STUDY, d))
    assert second["hits"] >= 1 and second["misses"] < first["misses"], (first, second)
    assert (
        second["error_norm"] == first["error_norm"]
    )  # the executable read back computes the same numbers


# The eager solves are written and read back: adaptive and fixed-step `simulate`, the lock-step and the
# masked batch, and `estimate` on recorded data.  Three of them solve with diffrax, whose checks of the
# save times are host callbacks (JAX writes no program that has one): they compiled in every process
# before obsjax's solves left those two checks out (and `estimate` traced its `throw` checks into its
# program).
_SOLVES = r"""
import json, os, sys
import jax, jax.numpy as jnp, numpy as np
import obsjax

events = []
jax.monitoring.register_event_listener(lambda ev, **kw: events.append(ev))
obsjax.enable_compilation_cache(sys.argv[1], min_compile_time_secs=0.0)
plant = obsjax.LTI([[0., 1.], [-2., -3.]], [[0.], [1.]], [[1., 0.]])
obs = obsjax.Luenberger(plant, L=np.array([[5.], [3.]]))
ts = jnp.linspace(0., 1., 5)
u = lambda t: jnp.ones(1)
fixed = obsjax.simulate(plant, obs, jnp.ones(2), jnp.zeros(2), ts, u=u, adaptive=False, dt0=0.01)
masked = obsjax.simulate_batch(plant, obs, jnp.ones((3, 2)), jnp.zeros((3, 2)), ts, u=u, lockstep=False)
adaptive = obsjax.simulate(plant, obs, jnp.ones(2), jnp.zeros(2), ts, u=u)
lockstep = obsjax.simulate_batch(plant, obs, jnp.ones((3, 2)), jnp.zeros((3, 2)), ts, u=u)
data = obsjax.Measurements(ts, adaptive.y, jnp.ones((5, 1)), hold="linear")
recorded = obsjax.estimate(obs, data, jnp.zeros(2))
print(json.dumps({"hits": events.count("/jax/compilation_cache/cache_hits"),
                  "programs": sorted(f for f in os.listdir(sys.argv[1]) if "program_fn" in f or "jit__run" in f),
                  "values": [np.asarray(r.xhat).tolist() for r in (fixed, masked, adaptive, lockstep, recorded)]}))
"""


@pytest.mark.extended
def test_every_eager_solve_is_read_back_by_a_second_process(tmp_path):
    d = str(tmp_path / "cache")
    first = json.loads(_python(_SOLVES, d))
    assert len(first["programs"]) == 5, first["programs"]  # the five solves' programs were written
    second = json.loads(_python(_SOLVES, d))
    assert second["programs"] == first["programs"]  # nothing compiled anew for them
    assert second["hits"] >= 5, second["hits"]
    assert second["values"] == first["values"]


def test_opt_out(tmp_path, monkeypatch):
    d = tmp_path / "never"
    monkeypatch.setenv(_cache.OPT_OUT, "1")
    before = jax.config.jax_compilation_cache_dir
    assert obsjax.enable_compilation_cache(d) is None
    assert not d.exists() and jax.config.jax_compilation_cache_dir == before
    line = _python(
        "import jax; from obsjax import cli; cli.main(['reproduce', '--list']); "
        "print(jax.config.jax_compilation_cache_dir)",
        **{_cache.OPT_OUT: "1", _cache.DIR_ENV: str(d)},
    )
    assert line == "None" and not d.exists()  # the command respects the opt-out


def test_the_command_line_turns_it_on_by_default(tmp_path):
    d = str(tmp_path / "cli")
    code = (
        "import jax; from obsjax import cli; cli.main(['reproduce', '--list']); "
        "print(jax.config.jax_compilation_cache_dir)"
    )
    line = _python(code, **{_cache.DIR_ENV: d})
    assert line == d and os.path.isdir(d)


def test_the_command_writes_every_program_and_restores_the_threshold(tmp_path):
    """While the command runs, a program that compiles in a few milliseconds is written too (the demo's
    random draws and optimiser updates); a process that called ``cli.main`` gets its threshold back."""
    d = str(tmp_path / "cli-small")
    code = (
        "import os, jax, jax.numpy as jnp; from obsjax import cli; "
        "run = cli._run; seen = []; "
        "cli._run = lambda p, a: (seen.append(jax.config.jax_persistent_cache_min_compile_time_secs), "
        "jax.jit(lambda x: jnp.sin(x) * 3.0 + 1.0)(jnp.arange(3.0)).block_until_ready(), run(p, a))[2]; "
        "before = jax.config.jax_persistent_cache_min_compile_time_secs; "
        "cli.main(['reproduce', '--list']); "
        "print(before, seen[0], jax.config.jax_persistent_cache_min_compile_time_secs, "
        f"sum(len(fs) for _, _, fs in os.walk({d!r})))"
    )
    before, during, after, files = _python(code, **{_cache.DIR_ENV: d}).split()
    assert float(during) == 0.0 and float(after) == float(before)
    assert int(files) >= 1  # the tiny program's executable is in the cache


def test_default_directory(tmp_path, monkeypatch):
    monkeypatch.delenv(_cache.DIR_ENV, raising=False)
    if sys.platform.startswith("linux"):
        monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
        assert _cache.default_cache_dir() == str(
            tmp_path / "obsjax" / "jax-compilation-cache" / _cache.host_tag()
        )
    monkeypatch.setenv(_cache.DIR_ENV, str(tmp_path / "mine"))
    assert _cache.default_cache_dir() == str(tmp_path / "mine")


def test_bad_threshold():
    with pytest.raises(ValueError, match="min_compile_time_secs"):
        obsjax.enable_compilation_cache(min_compile_time_secs=-1.0)


def test_the_test_run_and_its_kernels_use_it():
    if _cache._opted_out() or not jax.config.jax_enable_compilation_cache:
        pytest.skip("the test run opted out of the compilation cache")
    d = jax.config.jax_compilation_cache_dir
    assert d and os.path.isdir(d) and os.environ["JAX_COMPILATION_CACHE_DIR"] == d
    # a child process (a notebook kernel started by nbmake) inherits the directory
    child = subprocess.run(
        [sys.executable, "-c", "import jax; print(jax.config.jax_compilation_cache_dir)"],
        check=False,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert child.stdout.strip() == d


_CPU = "processor\t: {i}\nvendor_id\t: AuthenticAMD\ncpu family\t: 25\nmodel\t\t: 17\nflags\t\t: {flags}\n\n"


def test_one_directory_per_kind_of_cpu():
    """The default directory's last component names the CPU's instruction set: two machines that
    differ in one feature flag never share compiled code, and the order of the flags does not
    matter."""
    a = _cache.host_tag(_CPU.format(i=0, flags="fpu sse2 avx2 avx512f") * 2)
    b = _cache.host_tag(_CPU.format(i=0, flags="fpu sse2 avx2"))
    c = _cache.host_tag(_CPU.format(i=0, flags="avx512f avx2 sse2 fpu"))
    assert a != b and a == c
    assert _cache.host_tag(_CPU.format(i=0, flags="fpu").replace("25", "23")) != _cache.host_tag(
        _CPU.format(i=0, flags="fpu")
    )  # another CPU family
    import re

    assert re.fullmatch(r"[\w.-]+-[0-9a-f]{12}", a)
    assert _cache.host_tag() == _cache.host_tag()  # stable within a machine


_FILTER = r"""
import os, sys
from obsjax._cache import quiet_benign_cache_log
benign = (b"E1123 09:06:28.463150   23527 cpu_aot_loader.cc:195] Loading XLA:CPU AOT result. Target "
          b"machine feature +%s is not  supported on the host machine. Machine type used for XLA:CPU "
          b"compilation doesn't match the machine type for execution. This could lead to execution "
          b"errors such as SIGILL.\n")
with quiet_benign_cache_log():
    os.write(2, b"first\n")
    os.write(2, benign % b"prefer-no-gather")
    os.write(2, b"\rprogress 1/2")
    os.write(2, b"\rprogress 2/2\n")
    os.write(2, benign % b"avx512fp16")  # a real instruction-set extension: kept
    os.write(2, benign[:40])  # a benign line written in two pieces
    os.write(2, benign[40:] % b"prefer-no-scatter")
    print("from python", file=sys.stderr)
    os.system("echo from a child >&2")
    os.write(2, b"last, no newline")
print("done", file=sys.stderr)
"""


def test_the_command_drops_only_the_benign_loader_complaint():
    out = subprocess.run(
        [sys.executable, "-c", _FILTER], check=True, capture_output=True, env=_env(), timeout=120
    )
    err = out.stderr.decode()
    assert "prefer-no-gather" not in err and "prefer-no-scatter" not in err, err
    assert "+avx512fp16 is not" in err  # a line about a real feature still reaches the user
    order = ["first\n", "\rprogress 1/2\rprogress 2/2\n", "avx512fp16", "from python\n",
             "from a child\n", "last, no newline", "done\n"]  # fmt: skip
    pos = [err.index(s) for s in order]
    assert pos == sorted(pos), err


def test_import_leaves_scipy_unloaded():
    """SciPy (0.4 s of every process's start) is imported where a function needs it, not by ``import obsjax``."""
    line = _python("import sys, obsjax; print(sorted(m for m in sys.modules if m.split('.')[0] == 'scipy'))")
    assert line == "[]"


def test_only_diffrax_save_time_checks_are_left_out_and_only_inside_the_context():
    """obsjax's solves trace diffrax without its two checks of SaveAt.ts (host callbacks, which keep a program
    out of the cache); every other check, and the same two in other threads or outside, still raise."""
    import threading

    import equinox as eqx

    from obsjax._checks import DIFFRAX_SAVE_TIME_CHECKS, without_diffrax_save_time_checks

    msg = sorted(DIFFRAX_SAVE_TIME_CHECKS)[0]
    x = jax.numpy.asarray(-1.0)
    elsewhere = []
    with without_diffrax_save_time_checks():
        assert float(jax.jit(lambda v: eqx.error_if(v, v < 0, msg))(x)) == -1.0
        with pytest.raises(Exception, match="another check"):
            jax.jit(lambda v: eqx.error_if(v, v < 0, "another check"))(x)

        def other_thread():
            try:
                jax.jit(lambda v: eqx.error_if(v, v < 0, msg))(x)
            except Exception as e:  # noqa: BLE001 - the check's error, whatever equinox wraps it in
                elsewhere.append(str(e))

        t = threading.Thread(target=other_thread)
        t.start()
        t.join()
    assert elsewhere and msg in elsewhere[0]  # another thread keeps the check
    with pytest.raises(Exception, match="saveat"):
        jax.jit(lambda v: eqx.error_if(v, v < 0, msg))(x)  # and so does this thread, outside
