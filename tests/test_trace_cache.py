"""Traced kernels saved across processes (obsjax/_trace_cache.py): a second process reads the program
the first exported and computes the same numbers as a process without the cache; anything that changes
the program changes the key; what cannot be hashed, a call inside a transformation and the opt-out all
fall back to the ordinary trace."""

import json
import os
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from obsjax import _cache, _trace_cache

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# the tests of programs read back by another process, on the JAX versions the cache is used with
needs_supported_jax = pytest.mark.skipif(
    not _trace_cache.supported(), reason=f"the trace cache is off with jax < {_trace_cache.MIN_JAX}"
)

# A small Monte-Carlo study and two tune steps, with the trace cache in the directory argv[1] (or off
# when argv[1] is "off").
_RUN = r"""
import json, sys
import jax, jax.numpy as jnp, numpy as np, optax
import obsjax
from obsjax import _trace_cache

if sys.argv[1] != "off":
    _trace_cache.enable_trace_cache(sys.argv[1])
SCALE = float(sys.argv[2])
plant = obsjax.LTI([[-2., 1.], [0., -1.]], [[0.], [1.]], [[1., 0.]])
obs = obsjax.Luenberger.from_poles(plant, [-3., -4.])
ts = np.linspace(0., 1., 6)
mc = obsjax.monte_carlo(plant, obs, jax.random.PRNGKey(0), 8,
                        x0_sampler=lambda k: SCALE * jax.random.normal(k, (2,)),
                        xhat0_sampler=lambda k: jnp.zeros(2), ts=ts, chunk_size=8, progress=False,
                        simulate_kwargs={"adaptive": False, "dt0": 0.05})
x0s = jnp.array([[1., -1.], [0.5, 2.]])
res = obsjax.tune(obs, plant, where=lambda o: o.poles, loss=obsjax.losses.ise, x0s=SCALE * x0s,
                  xhat0s=jnp.zeros((2, 2)), ts=ts, optimizer=optax.adam(0.05), steps=2,
                  simulate_kwargs={"adaptive": False, "dt0": 0.05}, progress=False)
print(json.dumps({"events": _trace_cache.events,
                  "error_norm": np.asarray(mc.error_norm).ravel().tolist(),
                  "loss": [float(v) for v in res.history["loss"]],
                  "poles": np.asarray(res.observer.poles).real.tolist()}))
"""


def _python(argv, env_extra, drop=()):
    """Run ``python -c`` with `argv` in a fresh process (obsjax from this checkout); its last line."""
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env["PYTHONPATH"] = ROOT + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.update(env_extra)
    out = subprocess.run(
        [sys.executable, "-c", *argv], check=False, capture_output=True, text=True, env=env,
        timeout=600,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout.strip().splitlines()[-1]


def _run(arg, scale=1.0, **env_extra):
    drop = (_cache.OPT_OUT, _trace_cache.OPT_OUT, _cache.DIR_ENV)
    return json.loads(_python([_RUN, arg, repr(scale)], env_extra, drop))


@pytest.mark.extended
@needs_supported_jax
def test_a_second_process_reads_the_programs_and_computes_the_same_numbers(tmp_path):
    d = str(tmp_path / "cache")
    first = _run(d)
    kinds = {e[1] for e in first["events"]}
    assert kinds == {"exported"}, first["events"]
    names = {e[0] for e in first["events"]}
    assert any("_chunk_kernel" in n for n in names) and any("_value_and_grad" in n for n in names)
    saved = os.listdir(os.path.join(d, _trace_cache.SUBDIR))
    assert len(saved) == len(first["events"]) and all(f.endswith(".bin") for f in saved)
    second = _run(d)
    assert {e[1] for e in second["events"]} == {"read"}, second["events"]
    plain = _run("off")
    assert plain["events"] == []
    for k in ("error_norm", "loss", "poles"):
        assert first[k] == plain[k] and second[k] == plain[k], k  # bit for bit
    # a closure constant of the sampler (and the scaled data) is another program: exported anew
    other = _run(d, scale=2.0)
    assert any(e[1] == "exported" and "_chunk_kernel" in e[0] for e in other["events"]), other[
        "events"
    ]
    assert other["error_norm"] != first["error_norm"]
    # the opt-out: nothing read or written
    off = _run(d, **{_trace_cache.OPT_OUT: "1"})
    assert off["events"] == [] and off["error_norm"] == plain["error_norm"]


def _kernel(a, b, cfg):
    return (a * cfg[0] + b,)


def test_the_key_changes_with_everything_that_changes_the_program():
    dtree = jax.tree_util.tree_structure((1, 2))
    avals = (((2,), "float64", False),)
    env = _trace_cache._environment()
    k = _trace_cache._key("f", dtree, (None, (3.0,)), avals, env)
    assert k is not None and k == _trace_cache._key("f", dtree, (None, (3.0,)), avals, env)
    assert k != _trace_cache._key("g", dtree, (None, (3.0,)), avals, env)  # another kernel
    assert k != _trace_cache._key("f", dtree, (None, (3.5,)), avals, env)  # a static value
    assert k != _trace_cache._key("f", dtree, (None, (3.0,)), (((3,), "float64", False),), env)
    assert k != _trace_cache._key("f", dtree, (None, (3.0,)), (((2,), "float32", False),), env)
    assert k != _trace_cache._key("f", dtree, (None, (3.0,)), (((2,), "float64", True),), env)
    assert k != _trace_cache._key("f", dtree, (None, (3.0,)), avals, env[:1] + ("nan",) + env[2:])

    def g(x, c=1.0):
        return x + c

    def h(x, c=2.0):
        return x + c

    assert _trace_cache._key("f", dtree, g, avals, env) != _trace_cache._key(
        "f", dtree, h, avals, env
    )


def test_the_key_covers_obsjax_source(monkeypatch):
    dtree = jax.tree_util.tree_structure((1,))
    avals = (((2,), "float64", False),)
    env = _trace_cache._environment()
    assert len(_trace_cache.source_digest()) == 64
    k = _trace_cache._key("f", dtree, None, avals, env)
    monkeypatch.setattr(_trace_cache, "source_digest", lambda: "an edited checkout")
    assert _trace_cache._key("f", dtree, None, avals, env) != k


def test_a_user_module_read_by_a_function_is_not_hashed_by_content():
    import types

    mod = types.ModuleType("someones_helpers")

    def f(x):
        return mod.scale * x

    globals()["mod"] = mod
    try:
        dtree = jax.tree_util.tree_structure((1,))
        key = _trace_cache._key(
            "f", dtree, f, (((2,), "float64", False),), _trace_cache._environment()
        )
        assert key is None  # cannot be saved: the call is traced as usual
    finally:
        del globals()["mod"]


def test_fallbacks_in_process(tmp_path, monkeypatch):
    monkeypatch.delenv(_trace_cache.OPT_OUT, raising=False)
    monkeypatch.delenv(_cache.OPT_OUT, raising=False)
    before = jax.config.jax_compilation_cache_dir
    kernel = _trace_cache.filter_jit(_kernel)
    try:
        _trace_cache._state["dir"] = str(tmp_path)
        n0 = len(_trace_cache.events)
        a, b = jnp.arange(3.0), jnp.ones(3)
        (out,) = kernel(a, b, (2.0,))
        np.testing.assert_array_equal(out, 2.0 * a + b)
        assert _trace_cache.events[n0:] == [(f"{__name__}._kernel", "exported")]
        _trace_cache._memo.clear()
        (out,) = kernel(a, b, (2.0,))
        assert _trace_cache.events[-1] == (f"{__name__}._kernel", "read")
        np.testing.assert_array_equal(out, 2.0 * a + b)
        # inside a transformation: the ordinary trace (jax.grad through it works)
        g = jax.grad(lambda x: kernel(x, b, (2.0,))[0].sum())(a)
        np.testing.assert_array_equal(g, 2.0 * np.ones(3))
        v = jax.vmap(lambda x: kernel(x, b, (3.0,))[0])(jnp.ones((4, 3)))
        np.testing.assert_array_equal(v, 4.0 * np.ones((4, 3)))
        # an unreadable saved program is exported again
        for f in os.listdir(tmp_path):
            (tmp_path / f).write_bytes(b"not a program")
        _trace_cache._memo.clear()
        (out,) = kernel(a, b, (2.0,))
        assert _trace_cache.events[-1][1] == "exported"
        np.testing.assert_array_equal(out, 2.0 * a + b)
        # off: exactly eqx.filter_jit
        _trace_cache.disable_trace_cache()
        n1 = len(_trace_cache.events)
        (out,) = kernel(a, b, (5.0,))
        assert len(_trace_cache.events) == n1
        np.testing.assert_array_equal(out, 5.0 * a + b)
    finally:
        _trace_cache.disable_trace_cache()
        assert jax.config.jax_compilation_cache_dir == before


def test_a_program_that_cannot_be_exported_is_traced():
    def with_callback(a, cfg):
        return (eqx.error_if(a, a < 0, "negative"),)

    kernel = _trace_cache.filter_jit(with_callback)
    try:
        import tempfile

        _trace_cache._state["dir"] = tempfile.mkdtemp()
        (out,) = kernel(jnp.ones(2), None)
        np.testing.assert_array_equal(out, np.ones(2))
        assert _trace_cache.events[-1][1].startswith("not exported")
        with pytest.raises(Exception, match="negative"):
            kernel(-jnp.ones(2), None)
    finally:
        _trace_cache.disable_trace_cache()


@needs_supported_jax
def test_the_command_line_turns_it_on_for_its_run_only_and_import_does_not():
    """On while the command runs; a process that called ``cli.main`` (a test, a notebook) has it off
    again afterwards."""
    assert _trace_cache._state["dir"] is None
    code = (
        "import obsjax; from obsjax import _trace_cache as t, cli; before = t.trace_cache_dir(); "
        "seen = []; run = cli._run; "
        "cli._run = lambda p, a: (seen.append(t.trace_cache_dir()), run(p, a))[1]; "
        "cli.main(['reproduce', '--list']); print(before, seen[0], t.trace_cache_dir())"
    )
    line = _python([code], {}, (_cache.OPT_OUT, _trace_cache.OPT_OUT))
    before, during, after = line.split()
    assert before == "None" and during.endswith(_trace_cache.SUBDIR) and after == "None"


@pytest.mark.extended
@needs_supported_jax
def test_a_sharded_study_is_saved_and_read_back(tmp_path):
    """Two host devices: the study's kernel (shard_map over a mesh) is exported, read back by the
    next process and computes what one device computes."""
    d = str(tmp_path / "cache")
    two = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    first = _run(d, **two)
    kernel = ["obsjax.montecarlo._montecarlo._chunk_kernel"]
    assert kernel + ["exported"] in first["events"], first["events"]
    second = _run(d, **two)
    assert kernel + ["read"] in second["events"], second["events"]
    one = _run("off")
    np.testing.assert_allclose(second["error_norm"], one["error_norm"], rtol=1e-12, atol=0)
    np.testing.assert_array_equal(first["error_norm"], second["error_norm"])


def _devices_after(env_extra):
    code = (
        "from obsjax import cli; r = cli.host_devices_for_demo(); import jax; "
        "print(r, len(jax.devices()))"
    )
    return _python([code], env_extra, ("XLA_FLAGS", "OBSJAX_DEMO_DEVICES"))


@pytest.mark.extended
def test_the_demo_uses_one_host_device_per_core_unless_told_otherwise():
    assert _devices_after({"OBSJAX_DEMO_DEVICES": "3"}) == "3 3"
    assert _devices_after({"OBSJAX_DEMO_DEVICES": "1"}) == "None 1"
    # a device count the user set is kept
    assert _devices_after({"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}) == "None 2"


# What an independent review of the first version found unhashed (each case made a second process
# read back a stale program): every one now changes the key, or makes the call fall back to tracing.
_DT = jax.tree_util.tree_structure((1,))
_AV = (((2,), "float64", False),)


def _k(static):
    return _trace_cache._key("f", _DT, static, _AV, _trace_cache._environment())


def _custom_jvp(scale):
    @jax.custom_jvp
    def sq(x):
        return x**2

    @sq.defjvp
    def sq_jvp(p, t):
        (x,), (dx,) = p, t
        return sq(x), scale * 2 * x * dx

    return sq


def _custom_vjp(scale):
    @jax.custom_vjp
    def f(x):
        return x

    f.defvjp(lambda x: (x, None), lambda _, g: (scale * g,))
    return f


def test_the_rules_of_custom_derivatives_are_in_the_key():
    assert _k(_custom_jvp(1.0)) != _k(_custom_jvp(-1.0))
    assert _k(_custom_vjp(1.0)) != _k(_custom_vjp(-1.0))


def test_attributes_outside_dataclass_fields_and_on_functions_are_in_the_key():
    import dataclasses

    @dataclasses.dataclass(eq=False)
    class Sampler:
        n: int = 2

        def __call__(self, k):
            return self.scale * jax.random.normal(k, (self.n,))

    a, b = Sampler(), Sampler()
    a.scale, b.scale = 1.0, 5.0
    assert _k(a) != _k(b)

    def f(k):
        return f.scale * k

    f.scale = 1.0
    k1 = _k(f)
    f.scale = 5.0
    assert _k(f) != k1


def test_a_module_imported_inside_a_function_is_not_hashed_by_content():
    def a_of_t(t):
        import someones_helpers  # noqa: F401  (never run: only its bytecode is read)

        return t

    def a_of_t_lib(t):
        import math

        return math.sin(t)

    assert _k(a_of_t) is None  # traced as usual
    assert _k(a_of_t_lib) is not None  # a numerical library is hashed by name and version


def test_the_weak_type_of_a_captured_array_is_in_the_key():
    weak, strong = jnp.asarray(1.1), jnp.asarray(1.1, dtype=jnp.float64)
    assert jax.typeof(weak).weak_type and not jax.typeof(strong).weak_type
    assert _k(lambda k, c=weak: c * k) != _k(lambda k, c=strong: c * k)


def test_every_jax_setting_that_can_change_a_trace_is_in_the_key():
    names = {k for k, _ in _trace_cache._environment()[0]}
    for k in ("jax_high_dynamic_range_gumbel", "jax_random_seed_offset", "jax_softmax_custom_jvp",
              "jax_enable_x64", "jax_threefry_partitionable", "jax_default_matmul_precision"):  # fmt: skip
        assert k in names, k
    before = _k(None)
    old = jax.config.jax_high_dynamic_range_gumbel
    try:
        jax.config.update("jax_high_dynamic_range_gumbel", not old)
        assert _k(None) != before
    finally:
        jax.config.update("jax_high_dynamic_range_gumbel", old)
    assert _k(None) == before


def test_the_versions_of_every_numerical_library_are_in_the_key():
    from obsjax.montecarlo import _fingerprint

    head = _fingerprint.header()
    assert f"results{_fingerprint.RESULTS_REVISION}" in head  # what the integrators compute
    for pkg in ("jax=", "jaxlib=", "diffrax=", "equinox=", "lineax=", "optax=", "optimistix=",
                "jaxtyping=", "obsjax="):  # fmt: skip
        assert pkg in head, pkg


def test_fast_compile_options_compile_the_same_program(monkeypatch):
    """A kernel compiled with XLA:CPU's elemental emitters (``fast_compile``) returns what the default
    compilation returns; the options are probed once, and a jaxlib that refuses them (or the opt-out)
    gives the defaults."""
    opts = _trace_cache.fast_compile_options()
    if jax.default_backend() == "cpu":
        assert opts in ({}, _trace_cache.FAST_COMPILE_OPTIONS)
    else:
        assert opts == {}
    monkeypatch.setenv(_trace_cache.DEFAULT_COMPILE_ENV, "1")
    assert _trace_cache.fast_compile_options() == {}
    monkeypatch.delenv(_trace_cache.DEFAULT_COMPILE_ENV)

    def kernel(x, n):
        def body(c, _):
            return jnp.sin(c) * 1.5 + jnp.cos(c[::-1]) * 0.25, c.sum()

        return jax.lax.scan(body, x, None, length=n)

    fast = _trace_cache.filter_jit(kernel, fast_compile=True)
    plain = _trace_cache.filter_jit(kernel)
    x = jnp.linspace(-1.0, 2.0, 7)
    a, b = fast(x, 50), plain(x, 50)
    for u, v in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_allclose(np.asarray(u), np.asarray(v), rtol=1e-13, atol=1e-13)
    # a jaxlib without the option: the probe refuses it and the kernel compiles with the defaults
    monkeypatch.setattr(_trace_cache, "FAST_COMPILE_OPTIONS", {"xla_no_such_option_here": True})
    monkeypatch.setattr(_trace_cache, "_fast_options", {})
    assert _trace_cache.fast_compile_options() == {}
    c = _trace_cache.filter_jit(kernel, fast_compile=True)(x, 50)
    np.testing.assert_allclose(np.asarray(c[0]), np.asarray(b[0]), rtol=0, atol=0)


def test_an_older_jax_leaves_the_trace_cache_off_with_a_warning(tmp_path, monkeypatch):
    """Below MIN_JAX (programs read back crashed another process) enable_trace_cache warns, returns
    None and leaves only the compilation cache on."""
    monkeypatch.delenv(_trace_cache.OPT_OUT, raising=False)
    monkeypatch.delenv(_cache.OPT_OUT, raising=False)
    monkeypatch.setattr(_trace_cache, "MIN_JAX", (99, 0, 0))
    # the directory and threshold in use (the suite's), so that nothing else changes
    before = jax.config.jax_compilation_cache_dir
    threshold = float(jax.config.jax_persistent_cache_min_compile_time_secs)
    path = before or str(tmp_path)
    try:
        assert not _trace_cache.supported()
        with pytest.warns(RuntimeWarning, match=r"trace cache needs jax >= 99\.0\.0"):
            assert _trace_cache.enable_trace_cache(path, min_compile_time_secs=threshold) is None
        assert _trace_cache.trace_cache_dir() is None
        assert jax.config.jax_compilation_cache_dir == os.path.abspath(path)
    finally:
        _trace_cache.disable_trace_cache()
        if before is None:
            jax.config.update("jax_compilation_cache_dir", None)


def test_the_order_of_an_equinox_modules_wrapper_fields_is_not_in_the_key():
    """equinox 0.13.0 keeps a module's wrapper fields (__doc__, __name__, ...) in a set's iteration order,
    which changes with every process's string hashing; the fingerprint sorts them (on equinox 0.13.0 a
    second process then found the first one's programs).  Here a stand-in of that node data, in two
    orders, gives one fingerprint; another value does not."""
    import dataclasses

    from obsjax.montecarlo._fingerprint import _canonical_node_data, fingerprint

    @dataclasses.dataclass(frozen=True)
    class FlattenedData:
        dynamic_field_names: tuple
        wrapper_fields: tuple

    FlattenedData.__module__ = "equinox._module._module"
    a = FlattenedData(("A",), (("__doc__", None), ("__name__", "f"), ("__qualname__", "f")))
    b = FlattenedData(("A",), (("__qualname__", "f"), ("__doc__", None), ("__name__", "f")))
    c = FlattenedData(("A",), (("__qualname__", "g"), ("__doc__", None), ("__name__", "f")))
    fp = lambda d: fingerprint({"x": _canonical_node_data(d)})[0]
    assert fp(a) == fp(b) != fp(c)
    # node data of other libraries is hashed as it is
    FlattenedData.__module__ = "mylib"
    assert fingerprint({"x": _canonical_node_data(a)})[0] != fingerprint({"x": _canonical_node_data(b)})[0]
