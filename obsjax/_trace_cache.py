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
#: bumped when the file format or the key changes
FORMAT = 1

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


def enable_trace_cache(path: str | os.PathLike | None = None) -> str | None:
    """Save the traced kernels of ``tune`` and ``monte_carlo`` across processes (``jax.export``).

    Turns on the compilation cache too (:func:`obsjax.enable_compilation_cache`), whose directory
    holds the programs, under ``obsjax-traced/``.  A later process that calls the same kernel on
    the same kind of arguments reads the program instead of tracing it (see this module's
    documentation for what must match, and what a monkeypatch can hide).  Off by default for
    library users; the ``obsjax`` command turns it on.

    **Returns:** the directory of saved programs, or ``None`` when opted out
    (``OBSJAX_NO_TRACE_CACHE=1`` or ``OBSJAX_NO_COMPILATION_CACHE=1``).
    """
    from ._cache import enable_compilation_cache

    if _opted_out():
        return None
    base = enable_compilation_cache(path)
    if base is None:
        return None
    d = os.path.join(base, SUBDIR)
    os.makedirs(d, exist_ok=True)
    _state["dir"] = d
    return d


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


def filter_jit(fn):
    """``eqx.filter_jit(fn)`` whose traced program is saved across processes when the trace cache is
    on (:func:`enable_trace_cache`); exactly ``eqx.filter_jit(fn)`` when it is off.  `fn` must be a
    module-level function returning a tuple of arrays (or a tuple of tuples of arrays)."""
    jitted = eqx.filter_jit(fn)
    name = f"{fn.__module__}.{fn.__qualname__}"

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
        try:
            sig = (name, dtree, stree, tuple(sleaves), avals, env, d)
            hash(sig)
        except TypeError:
            return jitted(*args)
        fast = _memo.get(sig)
        if fast is None:
            fast = _load_or_export(name, fn, jitted, dtree, static, leaves, avals, env, d)
            _memo[sig] = fast
        if fast is jitted:
            return jitted(*args)
        return fast(*leaves)

    call.__wrapped__ = fn
    return call


def _one_device(exp):
    """The call of a one-device program: every argument committed to one device first (jit compiles
    anew when committed and uncommitted arguments alternate, as they do between tune's steps, on a
    process with several devices)."""
    run = jax.jit(exp.call)

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


def _load_or_export(name, fn, jitted, dtree, static, leaves, avals, env, d):
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
    return _one_device(exp) if exp.nr_devices == 1 else jax.jit(exp.call)
