"""Input validation shared by the whole package (names the matrix, the expected and the found shape)."""

from __future__ import annotations

import contextlib
import threading

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

try:  # jax >= 0.6
    from jax.extend.core import concrete_or_error as _concrete_or_error
except ImportError:  # pragma: no cover
    _concrete_or_error = jax.core.concrete_or_error


def host_array(x):
    """``x`` as a NumPy array when it is a host value (a Python number, a NumPy array or scalar, a list of
    numbers), else ``None`` (a JAX array, a tracer, anything NumPy reads only as an object)."""
    if isinstance(x, (jax.Array, jax.core.Tracer)):
        return None
    try:
        h = np.asarray(x)
    except Exception:  # noqa: BLE001  (e.g. a list holding tracers)
        return None
    if h.dtype.kind not in "biufc" or h.dtype.itemsize > (16 if h.dtype.kind == "c" else 8):
        return None  # (not a JAX dtype, e.g. np.longdouble: left to jnp.asarray and its message)
    return h


def device_array(x, dtype=None) -> jax.Array:
    """``jnp.asarray(x, dtype)``, with host values converted by NumPy first.

    On jax 0.10 ``jnp.asarray`` of a host value (a Python number or list, a NumPy array) and a change of
    dtype compile a small program, once per shape and dtype in each process: tens of milliseconds each on
    a CPU, a sizeable share of a script's first call.  Here host values are converted by NumPy and moved
    by ``jax.device_put``, which compiles nothing.  JAX arrays and tracers take ``jnp.asarray`` itself.
    The result is strongly typed (a Python float gives float64 under x64, not a weakly typed float).

    The host value is copied first, as ``jnp.asarray`` copies: on the CPU ``jax.device_put`` may keep the
    NumPy buffer itself (no copy), and the caller's array, changed afterwards, would change the JAX array
    (a plant built in a loop that edits one matrix in place got the last matrix three times)."""
    h = host_array(x)
    if h is None:
        return jnp.asarray(x, dtype=dtype)
    return _to_device(h, dtype)


def _to_device(h: np.ndarray, dtype=None) -> jax.Array:
    """A fresh copy of the host array `h` (in `dtype`) on the default device (see :func:`device_array`)."""
    return jax.device_put(np.array(h, dtype=dtype, copy=True))


def as_float_array(x, name: str) -> jax.Array:
    """Convert to a floating JAX array, naming ``name`` on failure.

    Integers and narrower floats (float16, float32) become the default float (float64 under x64, which
    importing obsjax turns on), so a float32 input never meets a float64 state inside a solve; complex input is
    returned as is (callers that need real values use :func:`real_array`); booleans are refused.  Host values
    (Python numbers, lists, NumPy arrays) are converted by NumPy (:func:`device_array`).
    """
    h = host_array(x)
    if h is not None:
        if h.dtype == np.bool_:
            x = h  # refused below, with the message
        else:
            default = np.dtype(jnp.result_type(float))
            widen = h.dtype.kind in "biu" or (h.dtype.kind == "f" and h.dtype.itemsize < default.itemsize)
            return _to_device(h, default if widen else None)  # a copy (see device_array)
    try:
        arr = jnp.asarray(x)
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"`{name}` must be array-like, got {type(x).__name__}: {e}") from None
    if arr.dtype == jnp.bool_:
        # a mask passed where numbers belong (True/False read as 1/0 gave a result without a word)
        raise ValueError(f"`{name}` must hold numbers, got booleans (dtype bool) of shape {tuple(arr.shape)}.")
    if jnp.issubdtype(arr.dtype, jnp.complexfloating):
        return arr
    default = jnp.result_type(float)
    if not jnp.issubdtype(arr.dtype, jnp.floating) or arr.dtype.itemsize < jnp.dtype(default).itemsize:
        arr = arr.astype(default)
    return arr


def real_array(x, name: str) -> jax.Array:
    """:func:`as_float_array` that refuses complex values (a plant, a state, a time are real)."""
    arr = as_float_array(x, name)
    if jnp.issubdtype(arr.dtype, jnp.complexfloating):
        raise ValueError(f"`{name}` must be real, got an array of dtype {arr.dtype}.")
    return arr


def require_finite(x, name: str):
    """``ValueError`` when the concrete value of `x` holds NaN or inf (naming `name` and the value);
    traced values pass (checked under ``jit`` by the caller's ``eqx.error_if``, e.g.
    ``observers._validation.traced_finite``, or by the trajectory's status)."""
    v = concrete_value(x)
    if v is not None and not np.all(np.isfinite(v)):
        raise ValueError(f"`{name}` must be finite (no NaN or inf), got {np.asarray(v).tolist()}.")
    return x


def matrix(x, name: str, shape: tuple[int | None, int | None]) -> jax.Array:
    """Validate a 2-D matrix of the given shape (``None`` = any); 1-D input is refused."""
    arr = as_float_array(x, name)
    if arr.ndim != 2:
        raise ValueError(
            f"`{name}` must be a 2-D matrix of shape {_fmt(shape)}, got an array with "
            f"{arr.ndim} dimension(s) and shape {tuple(arr.shape)}."
        )
    for k, (want, got) in enumerate(zip(shape, arr.shape)):
        if want is not None and want != got:
            raise ValueError(
                f"`{name}` must have shape {_fmt(shape)}, got {tuple(arr.shape)} "
                f"(dimension {k} is {got}, expected {want})."
            )
    return arr


def vector(x, name: str, size: int | None) -> jax.Array:
    arr = as_float_array(x, name)
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1:
        raise ValueError(
            f"`{name}` must be a vector of length {size if size is not None else 'k'}, "
            f"got shape {tuple(arr.shape)}."
        )
    if size is not None and arr.shape[0] != size:
        raise ValueError(f"`{name}` must have length {size}, got length {arr.shape[0]}.")
    return arr


def is_concrete(x) -> bool:
    """True when every leaf of ``x`` has a concrete value (not a jit tracer)."""
    leaves = jax.tree_util.tree_leaves(x)
    for leaf in leaves:
        if isinstance(leaf, jax.core.Tracer):
            try:
                _concrete_or_error(None, leaf)
            except Exception:  # noqa: BLE001
                return False
    return True


def concrete_value(x):
    """Concrete numpy value of ``x`` or ``None`` when it is traced (inside jit).

    Outside ``jit``, a leaf being differentiated (``jax.grad``/``jvp`` run eagerly) still has a concrete
    primal, and this returns it: right for checks and for sizes, wrong for anything the result must stay
    differentiable in (use :func:`static_value` there).
    """
    try:
        return np.asarray(_concrete_or_error(None, x))
    except Exception:  # noqa: BLE001
        return None


def scalar_value(x):
    """NumPy value of a Python or NumPy number, array or list of numbers as given (also under ``jit``,
    where ``jnp.asarray`` of a constant is traced), else :func:`concrete_value` of it (``None`` when
    traced)."""
    if isinstance(x, (bool, int, float, complex, np.generic, np.ndarray)):
        return np.asarray(x)
    if isinstance(x, (list, tuple)):
        try:
            v = np.asarray(x)
        except Exception:  # noqa: BLE001  (e.g. a list holding tracers)
            v = None
        if v is not None and v.dtype != object:
            return v
    return concrete_value(jnp.asarray(x))


def static_value(x):
    """NumPy value of ``x`` when it is a constant of the computation, ``None`` when any leaf is a JAX tracer.

    Unlike :func:`concrete_value`, a leaf traced by an eager ``jax.grad``/``jvp``/``vmap`` counts as traced:
    a quantity read here (a reset period, breakpoint instants) is frozen into NumPy, so its derivative would
    be lost silently.  Code that builds structure from such a value must take its traced path instead.
    """
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(x)):
        return None
    return concrete_value(x)


def positive(value, name: str):
    """Trace-time check that a gain is > 0 when its value is known; ``None`` passes."""
    v = concrete_value(value)
    if v is not None and not np.all(v > 0):
        raise ValueError(f"`{name}` must be > 0, got {v.tolist()}.")


def _fmt(shape) -> str:
    return "(" + ", ".join("k" if s is None else str(s) for s in shape) + ")"


#: runtime_checks_as_nan's state, shared by the threads of the process (equinox's mode is one per process)
_AS_NAN = {"depth": 0, "saved": None}
_AS_NAN_LOCK = threading.Lock()


@contextlib.contextmanager
def runtime_checks_as_nan():
    """Trace with equinox's runtime checks (``eqx.error_if``, also inside diffrax) as NaN instead of a host
    callback that raises.

    Inside a study every trajectory runs with ``throw=False``, so a check that fires should mark that
    trajectory failed (non-finite: status 2, counted), not abort the study; in ``tune``'s kernel it makes
    the loss NaN, so the step is rejected.  Without host callbacks a program can be written to JAX's
    persistent compilation cache (JAX does not write one that carries them).  It also matters for speed: on the
    CPU runtime, a multi-device program that contains host callbacks (even in branches never taken, as
    diffrax's checks of ``SaveAt.ts`` are) runs its device partitions one after another; without them the
    shards of a ``shard_map`` run in parallel (benchmarks/results/d_sharding.md).  equinox reads its error
    mode when a check is traced, from ``equinox._errors``; a fresh jitted check function avoids reusing one
    traced in raise mode.  If equinox's internals differ, this does nothing.

    equinox's mode is one per process, so the context is counted across threads: the first to enter
    switches the mode, the last to leave restores it (two threads inside it at once, e.g. studies run
    from two threads, never restore it under each other).  While any thread is inside,
    checks traced by every thread are NaN checks.
    """
    try:
        import equinox._errors as E

        E.EQX_ON_ERROR, E.branched_error_if_impl_jit  # noqa: B018 - both must exist
    except (ImportError, AttributeError):
        yield
        return
    with _AS_NAN_LOCK:
        if _AS_NAN["depth"] == 0:
            _AS_NAN["saved"] = (E.EQX_ON_ERROR, E.branched_error_if_impl_jit)
            impl = E.branched_error_if_impl

            def as_nan(x, pred, index, msgs, *, on_error):  # a new function: a new jit cache
                return impl(x, pred, index, msgs, on_error="nan" if on_error == "default" else on_error)

            E.EQX_ON_ERROR = "nan"
            E.branched_error_if_impl_jit = eqx.filter_jit(as_nan)
        _AS_NAN["depth"] += 1
    try:
        yield
    finally:
        with _AS_NAN_LOCK:
            _AS_NAN["depth"] -= 1
            if _AS_NAN["depth"] == 0:
                E.EQX_ON_ERROR, E.branched_error_if_impl_jit = _AS_NAN["saved"]
                _AS_NAN["saved"] = None


#: diffrax's runtime checks of ``SaveAt.ts`` (``diffeqsolve``), which the solves of ``obsjax._integrate``
#: satisfy by construction: their save times are the validated save times (nondecreasing; decreasing traced
#: times are refused by obsjax's own check), clipped onto each segment's [start, end]
DIFFRAX_SAVE_TIME_CHECKS = frozenset(
    {"saveat.ts must be increasing or decreasing.", "saveat.ts must lie between t0 and t1."}
)
_SKIP = threading.local()
_SKIP_STATE = {"installed": None}


def _skipping_dispatch(original):
    def dispatch(x, pred, index, msgs, *, on_error):
        if getattr(_SKIP, "depth", 0) and set(msgs) <= DIFFRAX_SAVE_TIME_CHECKS:
            return x
        return original(x, pred, index, msgs, on_error=on_error)

    return dispatch


@contextlib.contextmanager
def without_diffrax_save_time_checks():
    """Trace ``diffrax.diffeqsolve`` without its two checks of ``SaveAt.ts`` (:data:`DIFFRAX_SAVE_TIME_CHECKS`),
    in this thread only.

    diffrax traces them as ``eqx.error_if`` checks, host callbacks whatever ``throw`` is, and JAX writes no
    program that carries a host callback to its persistent compilation cache: an adaptive ``simulate`` compiled
    in every process, cache or not.  The solves of ``obsjax._integrate`` pass save times that satisfy both
    checks by construction, so inside this context those two checks (identified by their messages) are left
    out; every other check, obsjax's own included, is traced as before.  equinox looks its check function up in
    ``equinox._errors`` at each check: a dispatcher is put there once (first use; it passes every call on to
    the function it replaced unless this thread is inside the context and the check is one of the two).  If
    equinox's internals differ, or :func:`runtime_checks_as_nan` (whose checks carry no callback anyway) holds
    that slot, this does nothing.
    """
    try:
        import equinox._errors as E

        current = E.branched_error_if_impl_jit
    except (ImportError, AttributeError):
        yield
        return
    with _AS_NAN_LOCK:
        if _AS_NAN["depth"] == 0 and current is not _SKIP_STATE["installed"]:
            _SKIP_STATE["installed"] = E.branched_error_if_impl_jit = _skipping_dispatch(current)
    _SKIP.depth = getattr(_SKIP, "depth", 0) + 1
    try:
        yield
    finally:
        _SKIP.depth -= 1
