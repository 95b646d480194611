"""Traced kernels saved across processes (``jax.export``): the part of a first call that the
compilation cache cannot save.

JAX's persistent compilation cache (:mod:`obsjax._cache`) saves XLA's compilation, but every process
still traces and lowers each kernel, and for a differentiated adaptive solve that is most of a warm
first call (the first step of ``tune`` spends seconds tracing ``jax.jacfwd`` through diffrax).  With
the trace cache on, the kernels of :func:`obsjax.tune` and :func:`obsjax.monte_carlo` are exported
once (``jax.export``: the lowered StableHLO program, serialized) and later processes read the program
back instead of tracing it; its compilation is then found in the compilation cache.

**When a saved program is reused.**  Only when everything that determines it is the same, hashed by
content (:mod:`obsjax.montecarlo._fingerprint`, the fingerprint that guards checkpoints): the
kernel's name, the shapes, dtypes and weak types of its array arguments, the pytree structure and
every static value (observer and plant classes with their static fields, loss and sampler functions
by bytecode, closures and the globals they read), the versions of Python, jax, jaxlib, NumPy, SciPy,
diffrax, equinox, lineax, optax and obsjax, a digest of obsjax's own source files (an edited
checkout is another program), the JAX settings that change a trace (float64, default precision,
dtype and rank promotion, the PRNG implementation and its options, NaN/Inf debugging: every setting
but those about caches, logging, dumps, transfers and profiling), equinox's error mode, the backend and its number of devices (a mesh by its axes and devices), and the kind of CPU (the
directory is the compilation cache's, one per kind).  Anything the fingerprint cannot hash by content (an object of a compiled
extension, a module outside the numerical libraries that a user function reads) makes the call fall
back to the ordinary ``eqx.filter_jit`` path, as does any failure to export, save or read a program.

**What it cannot see**: a change made at run time to a library function (a monkeypatch of obsjax,
diffrax or jax internals) is not in the fingerprint; nor is an edit of an editable install of a library
other than obsjax that keeps its version string (diffrax, equinox, ...: hashed by name and version),
a file a user function reads while it is traced (``np.loadtxt`` inside a sampler), a lookup through
``globals()[...]``, or flatten/unflatten functions registered for a user's pytree node.  That is why the cache is off by default for
library users and in the test suite; the ``obsjax`` command turns it on (its processes change
nothing at run time), and :func:`enable_trace_cache` turns it on for a user's process.
``OBSJAX_NO_TRACE_CACHE=1`` (or ``OBSJAX_NO_COMPILATION_CACHE=1``) turns it off everywhere.

Programs live in ``<compilation cache directory>/obsjax-traced/``, one file per kernel and
signature, written atomically; deleting the directory loses nothing but time.
"""

from __future__ import annotations

import functools
import hashlib
import os
import tempfile

import equinox as eqx
import jax
import numpy as np

#: environment variable that turns the trace cache off
OPT_OUT = "OBSJAX_NO_TRACE_CACHE"
#: subdirectory of the compilation cache directory
SUBDIR = "obsjax-traced"
#: bumped when the file format or the key changes (2: the key's fingerprint hashes a class reached through a
#: global, a closure cell or a base class by content, not as a bare reference)
FORMAT = 2
#: the oldest JAX whose programs, exported by one process and read back by another, run: with jax
#: 0.6.1, 0.6.2, 0.7.2, 0.8.0, 0.9.0 and 0.9.2 the first call of a program read back crashed the
#: process (SIGSEGV inside XLA), with 0.10.0 and 0.10.1 it computed the same numbers
MIN_JAX = (0, 10, 0)

_state = {"dir": None}
_memo: dict = {}  # in-process: signature -> callable on (dynamic leaves)
#: what happened to each kernel signature first seen in this process (for tests and benchmarks)
events: list[tuple[str, str]] = []

# JAX settings that cannot change a traced program (caches, logging, dumps, transfer guards, profiling,
# distributed set-up): every other setting enters the key, so that one added by a later JAX is covered.
_CONFIG_SKIP = (
    "cache", "log", "dump", "transfer_guard", "profil", "pgle", "traceback", "explain", "pprint",
    "cross_host", "distributed", "timeout", "visible_devices", "source_url", "verbose",
    "preemption", "recoverability", "thread_guard", "mock_", "debug_key_reuse",
)  # fmt: skip


def _config_items() -> tuple:
    try:
        names = sorted(jax.config.values)
    except AttributeError:  # pragma: no cover - an older JAX: the settings known to change a trace
        names = [
            "jax_enable_x64", "jax_default_matmul_precision", "jax_numpy_dtype_promotion",
            "jax_numpy_rank_promotion", "jax_default_prng_impl", "jax_debug_nans", "jax_debug_infs",
            "jax_threefry_partitionable", "jax_random_seed_offset", "jax_high_dynamic_range_gumbel",
            "jax_softmax_custom_jvp", "jax_enable_custom_prng", "jax_legacy_prng_key",
        ]  # fmt: skip
    out = []
    for k in names:
        if any(p in k for p in _CONFIG_SKIP):
            continue
        try:
            out.append((k, repr(getattr(jax.config, k))))  # getattr: context-manager overrides too
        except Exception:  # noqa: BLE001
            out.append((k, "?"))
    return tuple(out)


def _opted_out() -> bool:
    from ._cache import _opted_out as compilation_opted_out

    flag = os.environ.get(OPT_OUT, "").strip().lower() not in ("", "0", "false", "no")
    return flag or compilation_opted_out()


def enable_trace_cache(
    path: str | os.PathLike | None = None, *, min_compile_time_secs: float | None = None
) -> str | None:
    """Save the traced kernels of ``tune`` and ``monte_carlo`` across processes (``jax.export``).

    Turns on the compilation cache too (:func:`obsjax.enable_compilation_cache`), whose directory
    holds the programs, under ``obsjax-traced/``.  On some x86 CPUs every program read back logs a
    harmless error line (``Target machine feature +prefer-no-gather is not supported``): that
    function's documentation says why it is harmless and how to silence it.  A later process that calls the same kernel on
    the same kind of arguments reads the program instead of tracing it (see this module's
    documentation for what must match, and what a monkeypatch can hide).  Off by default for
    library users; the ``obsjax`` command turns it on.

    `min_compile_time_secs` is passed on to :func:`obsjax.enable_compilation_cache` (``None``: its
    default).

    **Returns:** the directory of saved programs, or ``None`` when opted out
    (``OBSJAX_NO_TRACE_CACHE=1`` or ``OBSJAX_NO_COMPILATION_CACHE=1``) or when the installed JAX is
    older than ``MIN_JAX`` (0.10.0): with older versions a program read back by another process
    crashed it, so the trace cache stays off there (with a warning) and only the compilation cache is
    turned on.
    """
    from ._cache import MIN_COMPILE_TIME_SECS, enable_compilation_cache

    if _opted_out():
        return None
    if min_compile_time_secs is None:
        min_compile_time_secs = MIN_COMPILE_TIME_SECS
    base = enable_compilation_cache(path, min_compile_time_secs=min_compile_time_secs)
    if base is None:
        return None
    if not supported():
        import warnings

        warnings.warn(
            f"obsjax's trace cache needs jax >= {'.'.join(map(str, MIN_JAX))} (a program read back "
            f"from it crashed the process with older versions); jax {jax.__version__} is installed, so "
            "kernels are traced in every process (the compilation cache is on).",
            RuntimeWarning,
            stacklevel=2,
        )
        return None
    d = os.path.join(base, SUBDIR)
    os.makedirs(d, exist_ok=True)
    _state["dir"] = d
    return d


def supported() -> bool:
    """Whether the installed JAX is one the trace cache is used with (``MIN_JAX`` or newer)."""
    parts = []
    for p in jax.__version__.split(".")[:3]:
        digits = "".join(c for c in p if c.isdigit())
        parts.append(int(digits) if digits else 0)
    return tuple(parts) >= MIN_JAX


def disable_trace_cache() -> None:
    """Stop reading and writing saved traces in this process (the compilation cache stays on)."""
    _state["dir"] = None
    _memo.clear()


def trace_cache_dir() -> str | None:
    """The directory of saved programs in use, or ``None`` when the trace cache is off."""
    return _state["dir"] if not _opted_out() else None


@functools.lru_cache(maxsize=1)
def source_digest() -> str:
    """SHA-256 of obsjax's own Python source files (relative path and bytes, in sorted order)."""
    root = os.path.dirname(os.path.abspath(__file__))
    h = hashlib.sha256()
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if d != "__pycache__")
        for name in sorted(filenames):
            if name.endswith(".py"):
                p = os.path.join(dirpath, name)
                h.update(os.path.relpath(p, root).encode() + b"\0")
                with open(p, "rb") as f:
                    h.update(f.read())
                h.update(b"\0")
    return h.hexdigest()


def _environment() -> tuple:
    """Settings outside the arguments that change what a trace produces."""
    try:
        import equinox._errors as E

        eqx_mode = str(E.EQX_ON_ERROR)
    except (ImportError, AttributeError):
        eqx_mode = os.environ.get("EQX_ON_ERROR", "?")
    return (_config_items(), eqx_mode, jax.default_backend(), len(jax.devices()))


def _aval(x):
    a = jax.typeof(x) if isinstance(x, jax.Array) else None
    weak = bool(getattr(a, "weak_type", False))
    return (tuple(np.shape(x)), str(np.result_type(x) if a is None else a.dtype), weak)


#: XLA:CPU options for the solver kernels of ``tune``, ``monte_carlo`` and the demo's paper runs: the
#: elemental IR emitters instead of the MLIR fusion emitters.  A differentiated or batched solve lowers to a
#: few hundred small fusions, and the fusion emitters take longer over each: on jaxlib 0.10.1 the demo's
#: tune kernel (jacfwd of 8 scenarios, Tsit5) compiled in 4.2 s instead of 6.5 s, its Monte-Carlo kernel
#: in 5.2 s instead of 6.5 s, with the same results and the same run time
#: (benchmarks/results/h_first_call.md compares first calls with and without).
FAST_COMPILE_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
#: environment variable: "1" compiles the kernels with XLA's default options
DEFAULT_COMPILE_ENV = "OBSJAX_DEFAULT_XLA_OPTIONS"
_fast_options: dict = {}


def fast_compile_options() -> dict:
    """:data:`FAST_COMPILE_OPTIONS` where the backend is the CPU and this jaxlib knows them, else ``{}``
    (probed once per process by compiling a trivial program; a jaxlib without the option refuses it with
    "No such compile option").  ``OBSJAX_DEFAULT_XLA_OPTIONS=1`` gives ``{}``."""
    if os.environ.get(DEFAULT_COMPILE_ENV, "").strip().lower() not in ("", "0", "false", "no"):
        return {}
    backend = jax.default_backend()
    if backend not in _fast_options:
        opts = {}
        if backend == "cpu":
            try:
                jax.jit(lambda x: x + 1, compiler_options=FAST_COMPILE_OPTIONS).lower(
                    np.float32(0)
                ).compile()
                opts = dict(FAST_COMPILE_OPTIONS)
            except Exception:  # noqa: BLE001 - an unknown option (another jaxlib): the defaults
                opts = {}
        _fast_options[backend] = opts
    return _fast_options[backend]


def filter_jit(fn=None, *, fast_compile: bool = False):
    """``eqx.filter_jit(fn)`` whose traced program is saved across processes when the trace cache is
    on (:func:`enable_trace_cache`); ``eqx.filter_jit(fn)`` (with the compile options below) when it is
    off.  `fn` must be a module-level function returning a tuple of arrays (or a tuple of tuples of arrays).

    `fast_compile`: compile with :func:`fast_compile_options` (decided at the first call, when the backend
    is known); the program computes the same operations, code-generated by XLA's other CPU emitter."""
    if fn is None:
        return functools.partial(filter_jit, fast_compile=fast_compile)
    name = f"{fn.__module__}.{fn.__qualname__}"
    made: dict = {}

    def options() -> dict:
        return fast_compile_options() if fast_compile else {}

    def jitted(*args):
        opts = options()
        key = tuple(sorted(opts.items()))
        if key not in made:
            made[key] = eqx.filter_jit(fn, compiler_options=opts) if opts else eqx.filter_jit(fn)
        return made[key](*args)

    @functools.wraps(fn)
    def call(*args):
        d = trace_cache_dir()
        if d is None or jax.process_count() > 1 or jax.config.jax_disable_jit:
            # off, several processes (each traces its own), or no compilation at all
            return jitted(*args)
        dyn, static = eqx.partition(args, eqx.is_array)
        leaves, dtree = jax.tree_util.tree_flatten(dyn)
        if any(isinstance(x, jax.core.Tracer) for x in leaves):  # inside a transformation
            return jitted(*args)
        backend = jax.default_backend()
        if any(
            isinstance(x, jax.Array) and any(dv.platform != backend for dv in x.sharding.device_set)
            for x in leaves
        ):  # arguments on another platform than the default one (a program is exported for that)
            return jitted(*args)
        sleaves, stree = jax.tree_util.tree_flatten(static)
        avals = tuple(_aval(x) for x in leaves)
        env = _environment()
        opts = options()
        try:
            sig = (name, dtree, stree, tuple(sleaves), avals, env, d, tuple(sorted(opts.items())))
            hash(sig)
        except TypeError:
            return jitted(*args)
        fast = _memo.get(sig)
        if fast is None:
            fast = _load_or_export(name, fn, jitted, dtree, static, leaves, avals, env, d, opts)
            _memo[sig] = fast
        if fast is jitted:
            return jitted(*args)
        return fast(*leaves)

    call.__wrapped__ = fn
    return call


def _one_device(exp, opts):
    """The call of a one-device program: every argument committed to one device first (jit compiles
    anew when committed and uncommitted arguments alternate, as they do between tune's steps, on a
    process with several devices)."""
    run = jax.jit(exp.call, compiler_options=opts) if opts else jax.jit(exp.call)

    def call(*leaves):
        dev = None
        for x in leaves:
            if isinstance(x, jax.Array) and getattr(x, "committed", False):
                dev = next(iter(x.sharding.device_set))
                break
        if dev is None:
            dev = jax.config.jax_default_device
            if not isinstance(dev, jax.Device):  # unset, or a platform name
                dev = jax.devices()[0]
        return run(*jax.device_put(list(leaves), dev))

    return call


def _key(name, dtree, static, avals, env) -> str | None:
    from .montecarlo._fingerprint import fingerprint

    fp, opaque = fingerprint(
        {
            "format": FORMAT,
            "kernel": name,
            "dynamic_structure": dtree,
            "static": static,
            "avals": avals,
            "environment": env,
            "obsjax_source": source_digest(),
        },
        strict_modules=True,
    )
    return None if opaque else fp


def _load_or_export(name, fn, jitted, dtree, static, leaves, avals, env, d, opts):
    from jax import export

    try:
        key = _key(name, dtree, static, avals, env)
    except Exception:  # noqa: BLE001 - the fingerprint failed: trace as usual
        key = None
    if key is None:
        events.append((name, "not hashable: traced"))
        return jitted
    path = os.path.join(d, f"{key}.bin")
    exp = None
    if os.path.exists(path):
        try:
            with open(path, "rb") as f:
                exp = export.deserialize(bytearray(f.read()))
            got = tuple((tuple(a.shape), str(a.dtype)) for a in exp.in_avals)
            if got != tuple((s, t) for s, t, _ in avals):
                exp = None
            else:
                events.append((name, "read"))
        except Exception:  # noqa: BLE001 - an unreadable file: export again
            exp = None
    if exp is None:

        def flat(*xs):
            return fn(*eqx.combine(jax.tree_util.tree_unflatten(dtree, xs), static))

        try:
            specs = [jax.ShapeDtypeStruct(s, np.dtype(t), weak_type=w) for (s, t, w) in avals]
            exp = export.export(jax.jit(flat))(*specs)
            data = exp.serialize()
            fd, tmp = tempfile.mkstemp(dir=d, suffix=".tmp")
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            os.replace(tmp, path)
            events.append((name, "exported"))
        except Exception as e:  # noqa: BLE001 - cannot export (a host callback, an extended dtype)
            events.append((name, f"not exported ({type(e).__name__}): traced"))
            return jitted
    if exp.nr_devices == 1:
        return _one_device(exp, opts)
    return jax.jit(exp.call, compiler_options=opts) if opts else jax.jit(exp.call)
