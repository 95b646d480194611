"""One compiled program per problem structure for the eager entry points (``simulate``, ``simulate_batch``).

``simulate`` validates its arguments and builds its schedule in Python, then runs a back-end.  Called
eagerly, a back-end whose loop is a ``lax.scan`` over segments (resets, observer updates, plant jumps) or
the batch loops of ``_lockstep.py`` and ``_masked.py`` ran as separate primitives, and JAX compiled the loop
again on every call (its body is a new function each time): 1–5 s per call of the same problem, where a
problem without breakpoints (one ``diffeqsolve``, which diffrax compiles once) took 25 ms.

:func:`call` runs ``fn(*args)`` as one ``jax.jit`` program kept in a small table keyed by what tracing reads
besides the JAX arrays: the tree structure (with the static fields of plants and observers, and the content
digest of :class:`obsjax._integrate._system.Args`, which covers the globals that user functions read), the
Python scalars, the NumPy arrays by value (the concrete save times and breakpoints, which the fixed-step grid
and the schedule are built from) and the functions by identity.  JAX arrays, tracers included, are the
program's arguments.  A second call that differs only in array values (initial states, gains, plant
matrices) runs the compiled program.  The integration core's dataclasses (``Plan``, ``Schedule``,
``Options``) are walked field by field.

Eager differentiation (``jax.grad``, ``jax.value_and_grad`` or ``jax.jvp`` without ``jit``: tracers whose
innermost primal value is concrete) goes through the table too.  JAX then differentiates the compiled
program as a whole and keeps the programs it derives, so a second gradient of the same problem at other
values runs them: on the Chen & Yen example with 40 resets, 8.0 s per eager gradient before (the backward
pass ran as separate primitives and compiled its loop again) and 88 ms for a later one now (benchmark
(l)).  Inside an outer ``jit`` or ``vmap`` (any other tracer among the arguments) ``fn`` is traced there, as before: the
outer program compiles it once, constants of the outer trace stay constants, checks on them fold away, and
a study's kernel carries no host callback.
"""

from __future__ import annotations

import collections
import dataclasses
import threading

import equinox as eqx
import jax
import numpy as np
from jax._src.interpreters import ad as _ad

#: compiled programs kept (least recently used dropped first)
MAX_ENTRIES = 64

_table: collections.OrderedDict = collections.OrderedDict()
_lock = threading.Lock()


@jax.tree_util.register_pytree_node_class
class _Fields:
    """A dataclass of the integration core (not a pytree itself) as a pytree node: its fields are children,
    its class and field names the node's static data."""

    def __init__(self, cls, names, values):
        self.cls, self.names, self.values = cls, names, values

    def tree_flatten(self):
        return self.values, (self.cls, self.names)

    @classmethod
    def tree_unflatten(cls, aux, values):
        return cls(aux[0], aux[1], tuple(values))


def _is_core_dataclass(x) -> bool:
    return dataclasses.is_dataclass(x) and not isinstance(x, (type, eqx.Module))


def _to_tree(x):
    if _is_core_dataclass(x):
        names = tuple(f.name for f in dataclasses.fields(x))
        return _Fields(type(x), names, tuple(_to_tree(getattr(x, n)) for n in names))
    if type(x) is tuple:
        return tuple(_to_tree(v) for v in x)
    return x


def _from_tree(x):
    if isinstance(x, _Fields):
        return x.cls(**{n: _from_tree(v) for n, v in zip(x.names, x.values)})
    if type(x) is tuple:
        return tuple(_from_tree(v) for v in x)
    return x


class _Uncacheable(Exception):
    pass


def _static_key(leaf):
    """A hashable key of a leaf that tracing reads as a constant (equal keys: the same program)."""
    if isinstance(leaf, (np.ndarray, np.generic)):
        a = np.asarray(leaf)
        if a.dtype == object:
            raise _Uncacheable
        return ("nd", a.dtype.str, a.shape, a.tobytes())
    if isinstance(leaf, bool) or isinstance(leaf, int) or isinstance(leaf, str):
        return (type(leaf), leaf)
    if isinstance(leaf, float):
        return (float, leaf.hex())  # -0.0 and 0.0 are other constants; NaN equals itself here
    if isinstance(leaf, complex):
        return (complex, leaf.real.hex(), leaf.imag.hex())
    try:
        hash(leaf)
    except TypeError:
        raise _Uncacheable from None
    return ("obj", leaf)


#: the tracers of eager differentiation (``jax.grad``/``jax.jvp`` outside any ``jit``): their primal values
#: are concrete, and the compiled program is differentiated as a whole (JAX keeps its derivative programs too)
_AD_TRACERS = tuple(
    t for t in (getattr(_ad, "JVPTracer", None), getattr(_ad, "LinearizeTracer", None)) if t is not None
)


def _eager_or_eager_ad(leaf) -> bool:
    """True for a leaf that is not a tracer, or a tracer of eager differentiation (nested ones included)
    whose innermost primal is concrete; False under ``jit``, ``vmap`` and other traces."""
    while isinstance(leaf, jax.core.Tracer):
        if type(leaf) not in _AD_TRACERS:
            return False
        leaf = leaf.primal
    return True


def call(fn, *args):
    """``fn(*args)``, compiled once per structure (module docstring).  `fn` must be a module-level function
    (its identity is part of the key).  Arguments that cannot be keyed (an unhashable leaf) run ``fn``
    directly, as before."""
    leaves, treedef = jax.tree_util.tree_flatten(_to_tree(args))
    if not all(_eager_or_eager_ad(v) for v in leaves):
        # inside an outer jit/vmap: traced there, as before (constants of the outer trace stay constants,
        # so checks on them fold away and a study's kernel carries no host callback)
        return fn(*args)
    dynamic = tuple(isinstance(v, jax.Array) for v in leaves)
    try:
        key = (fn, treedef, dynamic, tuple(None if d else _static_key(v) for v, d in zip(leaves, dynamic)))
        hash(key)
    except (_Uncacheable, TypeError):
        return fn(*args)
    with _lock:
        program = _table.get(key)
        if program is not None:
            _table.move_to_end(key)
    if program is None:
        static = [None if d else v for v, d in zip(leaves, dynamic)]

        def program_fn(dyn):
            it = iter(dyn)
            full = [next(it) if d else s for s, d in zip(static, dynamic)]
            return fn(*_from_tree(jax.tree_util.tree_unflatten(treedef, full)))

        program = jax.jit(program_fn)
        with _lock:
            _table[key] = program
            while len(_table) > MAX_ENTRIES:
                _table.popitem(last=False)
    return program([v for v, d in zip(leaves, dynamic) if d])


def clear() -> None:
    """Forget the compiled programs of :func:`call` (JAX's own caches keep what they keep)."""
    with _lock:
        _table.clear()
