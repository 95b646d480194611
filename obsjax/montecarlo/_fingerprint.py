"""A content fingerprint of everything that determines a study's result (its checkpoints' key).

A checkpoint may only be reused by the study that wrote it.  Names are not enough: two samplers
called ``x0_sampler`` that differ by a constant in a closure, two LTV plants whose ``A(t)`` differ,
or two noise models that differ by a static grid spacing give different results.
:func:`fingerprint` therefore hashes the *content* of the objects, recursively:

- arrays by dtype, shape and bytes; numbers, strings, tuples, lists, dicts and sets by value;
- dataclasses (every ``eqx.Module``: plants, observers, noise models, diffrax solvers) field by
  field, static fields included, plus the code of the methods of user-defined classes;
- user-defined classes wherever they are reached (the class of an instance, a global or closure value
  that is a class, a base class) by name and by their attributes and methods, recursively; a class met
  again (one that refers to itself, or mutually recursive classes) is a reference to its first visit;
- user functions by their bytecode (constants, names, nested functions), their closure values, their
  default arguments and the values of the globals they read, recursively, including the attributes
  they may read from a user's module (a settings module read as ``cfg.SCALE`` or
  ``getattr(cfg, "SCALE")``: those named in the function's code, as names or string constants);
- what a user function reads from the process: the environment variables its code names as string
  constants (``os.environ["SCALE"]``, ``os.getenv("SCALE")``; a computed name is not seen), the state
  of a ``random.Random`` (``getstate()``), of the ``random`` module's hidden generator when the code
  calls one of its functions, and of NumPy's legacy global ``RandomState`` (``np.random.normal``);
- the JAX settings that change the random draws or the precision (``jax_threefry_partitionable``,
  the PRNG implementation, ``jax_enable_x64``), in the header beside the versions;
- functions, classes and modules of the numerical libraries (jax, numpy, scipy, diffrax, equinox,
  optax, lineax, obsjax, ...) by qualified name (their versions enter the header), but their
  closures by value, so ``jax.jit(f)`` and closures made by library factories are still hashed by
  content.

What cannot be hashed this way (an object of a compiled extension without a dataclass, ``__dict__``
or slots, such as ``numpy.random.Generator``, or a traced array) is reported with its path; the
caller refuses to checkpoint unless the user names the study with an explicit ``study_id``.
"""

from __future__ import annotations

import collections
import dataclasses
import enum
import functools
import hashlib
import itertools
import importlib.metadata
import os
import random as _pyrandom
import struct
import sys
import types

import jax
import jax.random as jr
import numpy as np

FORMAT = 2  # checkpoint format: content fingerprints and per-file checksums
#: Revision of what the integrators compute from the same inputs, in the header: a study checkpointed
#: before a change of the results (not only of their rounding) is another study.  2: the schedule's time
#: tolerance relative to the horizon, max_steps per segment in the masked loop, a reset on a plant jump
#: as one target there.  3: the Kalman–Bucy filter and the least-squares observer subtract an LTI
#: model's feedthrough D u; switching_ltv_example keeps switching after its declared horizon; the
#: padding of stacked recorded experiments (cubic hold, spacing).  4: fixed steps keep a plant jump
#: where the plant switches (and cut the interval around one within the tolerance of t0 or t1); an
#: overflowing candidate step is rejected instead of leaving a NaN step size; the Lovass-Nagy and min-max
#: checks are relative (a T accepted or refused differently), min-max estimates are solved on scaled ψ.
RESULTS_REVISION = 4

# Top-level packages hashed by name (their version is part of the fingerprint header).
_LIBRARIES = frozenset(
    {
        "jax", "jaxlib", "numpy", "scipy", "diffrax", "equinox", "lineax", "optax", "optimistix",
        "jaxtyping", "obsjax", "builtins", "math", "cmath", "operator", "functools", "itertools",
        "typing", "collections", "abc", "dataclasses", "enum", "numbers", "_operator", "_functools",
        "inspect",
    }
)  # fmt: skip
_VERSIONED = (
    "jax",
    "jaxlib",
    "numpy",
    "scipy",
    "diffrax",
    "equinox",
    "lineax",
    "optax",
    "optimistix",
    "jaxtyping",
    "obsjax",
)  # fmt: skip  (every third-party package in _LIBRARIES: hashed by name, so versioned)
# Class attributes that are machinery, not behaviour (the instance's fields carry the state).
_CLASS_SKIP = frozenset(
    {
        "__module__", "__qualname__", "__doc__", "__dict__", "__weakref__", "__annotations__",
        "__dataclass_fields__", "__dataclass_params__", "__match_args__", "__abstractmethods__",
        "_abc_impl", "__abstractvars__", "__abstractclassvars__", "__slots__", "__orig_bases__",
        "__parameters__", "__static_attributes__", "__firstlineno__", "__init__", "__post_init__",
        "__check_init__", "__repr__", "__eq__", "__hash__", "__init_subclass__", "__new__",
        "__setattr__", "__delattr__", "__getstate__", "__setstate__", "__reduce__", "__annotate__",
    }
)  # fmt: skip


# Attributes of a wrapper (functools.update_wrapper's) that are not behaviour.
_WRAPPER_SKIP = frozenset(
    {"__wrapped__", "__doc__", "__name__", "__qualname__", "__module__", "__annotations__",
     "__type_params__", "__dict__", "__signature__"}
)  # fmt: skip


#: Names through which a function reads the process environment (``os.environ[...]``,
#: ``os.environ.get``, ``os.getenv``): the variables its code names as string constants are hashed
#: by value (a computed variable name is not seen).
_ENV_READERS = frozenset({"environ", "environb", "getenv", "getenvb"})


_STORES = ("STORE_FAST", "STORE_NAME", "STORE_DEREF", "STORE_GLOBAL")


def _bound_to(owner) -> frozenset:
    """The names of a module's functions that are methods of `owner` (a hidden generator)."""
    mods = (_pyrandom, np.random)
    return frozenset(k for m in mods for k, v in vars(m).items() if getattr(v, "__self__", None) is owner)


#: The names of the functions that draw from the ``random`` module's and NumPy's hidden generators:
#: a function whose code names none of them is not scanned.
_GENERATOR_FUNCTIONS = _bound_to(getattr(_pyrandom, "_inst", None)) | _bound_to(
    getattr(np.random.mtrand, "_rand", None)
)


def _hidden_generators(fn: types.FunctionType) -> set[str]:
    """Which hidden global generators a function's code draws from: ``"random"`` for the ``random``
    module's functions (``random.gauss(...)``, ``rnd.random()`` after ``import random as rnd``, also
    inside the function), ``"numpy"`` for NumPy's legacy ``np.random.normal(...)``.  Read from the
    bytecode: a module loaded as a global, closure value or local import, then the attributes loaded
    from it, resolved; a method of the user's own ``random.Random`` (``rng.random()``) is not one."""
    import dis

    glb = fn.__globals__
    cells = {}
    for name, cell in zip(fn.__code__.co_freevars, fn.__closure__ or ()):
        try:
            cells[name] = cell.cell_contents
        except ValueError:
            pass
    found: set[str] = set()

    def scan(co):
        local_mods: dict[str, object] = {}
        cur = None
        pending_import = pending_full = None  # ``import a.b`` binds a; ``from a.b import c`` reads a.b
        for ins in dis.get_instructions(co):
            op, arg = ins.opname, ins.argval
            if op == "IMPORT_NAME":
                pending_import = sys.modules.get(str(arg).split(".")[0])
                pending_full = sys.modules.get(str(arg))
                cur = None
                continue
            if op == "IMPORT_FROM":  # ``from numpy import random as r``, ``import numpy.random as r``
                pending_import = None if pending_full is None else getattr(pending_full, str(arg), None)
                cur = None
                continue
            if op in _STORES and pending_import is not None:
                local_mods[arg] = pending_import
                pending_import = None  # (pending_full stays for the next name of a ``from`` import)
                cur = None
                continue
            pending_import = None
            if op not in _STORES:
                pending_full = None
            if op in ("LOAD_GLOBAL", "LOAD_NAME"):
                cur = glb.get(arg)
            elif op in ("LOAD_DEREF", "LOAD_CLOSURE"):
                cur = cells.get(arg, local_mods.get(arg))
            elif op in ("LOAD_FAST", "LOAD_FAST_CHECK"):
                cur = local_mods.get(arg)
            elif op in ("LOAD_ATTR", "LOAD_METHOD") and isinstance(cur, types.ModuleType):
                cur = getattr(cur, str(arg), None)
            else:
                cur = None
                continue
            owner = getattr(cur, "__self__", None)
            if owner is not None and owner is getattr(_pyrandom, "_inst", None):
                found.add("random")
            elif owner is not None and owner is getattr(np.random.mtrand, "_rand", None):
                found.add("numpy")
            if not isinstance(cur, types.ModuleType):
                cur = None
        for c in co.co_consts:
            if isinstance(c, types.CodeType):
                scan(c)

    scan(fn.__code__)
    return found


#: Python's standard library, hashed by name too (its version is the header's Python version): a user
#: function that imports ``sys``, ``os`` or ``warnings`` must not walk ``sys.modules`` or ``os.environ``
_STDLIB = frozenset(getattr(sys, "stdlib_module_names", ()))


def _is_library(module_name) -> bool:
    """A module hashed by name: the numerical libraries, the standard library, and any package installed
    in site-packages (beartype, pytest, ...: installed code, not a user's; walking its module graph from
    a function that imports it cost seconds per call).  A user's own modules (and editable installs)
    live elsewhere and are hashed by content."""
    if not isinstance(module_name, str):
        return False
    top = module_name.split(".")[0]
    return top in _LIBRARIES or top in _STDLIB or _installed(top)


_INSTALLED: dict = {}


def _installed(top: str) -> bool:
    """Whether the imported top-level package `top` lives in site-packages (cached once imported)."""
    if top in _INSTALLED:
        return _INSTALLED[top]
    mod = sys.modules.get(top)
    f = getattr(mod, "__file__", None)
    if not f:
        return False
    _INSTALLED[top] = _in_site_packages(f)
    return _INSTALLED[top]


def _in_site_packages(f: str) -> bool:
    import os
    import site
    import sysconfig

    roots = set()
    for r in [*getattr(site, "getsitepackages", list)(), site.getusersitepackages(),
              sysconfig.get_paths().get("purelib"), sysconfig.get_paths().get("platlib")]:  # fmt: skip
        if r:
            roots.add(os.path.realpath(r))
    path = os.path.realpath(f)
    return any(path.startswith(r + os.sep) for r in roots)


def _version(pkg: str) -> str:
    try:
        return importlib.metadata.version(pkg)
    except importlib.metadata.PackageNotFoundError:
        mod = sys.modules.get(pkg)
        return str(getattr(mod, "__version__", "?"))


#: JAX settings that change what a study computes from the same inputs: the random bits drawn from a key
#: (``jax_threefry_partitionable`` changes every draw of ``jax.random``; the PRNG implementation) and the
#: precision.
_CONFIG_FLAGS = ("jax_threefry_partitionable", "jax_default_prng_impl", "jax_enable_x64")


def header() -> str:
    """Python and library versions, and the JAX settings of :data:`_CONFIG_FLAGS`: a result computed by
    other versions or under other settings is another study."""
    py = f"python{sys.version_info.major}.{sys.version_info.minor}"
    flags = [f"{f}={getattr(jax.config, f, '?')}" for f in _CONFIG_FLAGS]
    return ";".join(
        [f"format{FORMAT}", f"results{RESULTS_REVISION}", py]
        + [f"{p}={_version(p)}" for p in _VERSIONED]
        + flags
    )


def _canonical_node_data(data):
    """A pytree node's auxiliary data in an order that does not change between processes.

    equinox 0.13.0 keeps a module's wrapper fields (``__doc__``, ``__name__``, ``__qualname__``, ...) as
    name–value pairs in the iteration order of a set of strings, which Python's string hashing changes
    from process to process: the same structure would fingerprint differently in every process (the
    trace cache never found a saved program there).  The pairs are sorted by name.  Later equinox
    versions keep no such field; other node data is left as it is."""
    wf = getattr(data, "wrapper_fields", None)
    if (
        type(data).__module__.startswith("equinox")
        and dataclasses.is_dataclass(data)
        and isinstance(wf, tuple)
        and all(isinstance(kv, tuple) and len(kv) == 2 and isinstance(kv[0], str) for kv in wf)
    ):
        return dataclasses.replace(data, wrapper_fields=tuple(sorted(wf, key=lambda kv: kv[0])))
    return data


_TUPLEGETTER = type(collections.namedtuple("_T", "a").a)
#: attributes of a class that only describe its layout (the accessor of a slot, of a named tuple's field)
_LAYOUT_DESCRIPTORS = (types.MemberDescriptorType, types.GetSetDescriptorType, _TUPLEGETTER)


class _Hasher:
    """Feeds a canonical, length-prefixed encoding of an object graph into SHA-256."""

    def __init__(self, strict_modules: bool = False):
        self.strict_modules = strict_modules
        self.h = hashlib.sha256()
        self.memo: dict[int, int] = {}
        self.keep: list = []  # keeps visited objects alive, so that their ids are not reused
        self.opaque: list[str] = []
        self.traced = False  # a traced array was met (its value is not known here)

    def put(self, tag: str, data: bytes | str = b"") -> None:
        if isinstance(data, str):
            data = data.encode()
        tag_b = tag.encode()
        self.h.update(struct.pack("<I", len(tag_b)) + tag_b + struct.pack("<Q", len(data)) + data)

    def _seen(self, obj) -> bool:
        i = self.memo.get(id(obj))
        if i is not None:
            self.put("ref", str(i))
            return True
        self.memo[id(obj)] = len(self.memo)
        self.keep.append(obj)
        return False

    # ---------------------------------------------------------------------------------------------
    def visit(self, obj, path: str) -> None:
        if obj is None or isinstance(obj, (bool, int, float, complex, str, bytes)):
            self.put(type(obj).__name__, repr(obj) if not isinstance(obj, bytes) else obj)
            return
        if isinstance(obj, (np.ndarray, np.generic)):
            self._array(np.asarray(obj), path)
            return
        if isinstance(obj, jax.Array):
            self._jax_array(obj, path)
            return
        if isinstance(obj, (np.dtype, type(Ellipsis))):
            self.put(type(obj).__name__, str(obj))
            return
        if isinstance(obj, type):
            # before the memo: _class memoises the class itself (and writes "ref" for a class seen
            # before, which ends the walk of a class that refers to itself); marked seen here, it was
            # hashed as a bare "ref" to itself, without its name or attributes
            self._class(obj, path)
            return
        if self._seen(obj):
            return
        if isinstance(obj, (tuple, list)):
            self.put(type(obj).__name__, str(len(obj)))
            for i, v in enumerate(obj):
                self.visit(v, f"{path}[{i}]")
            return
        if isinstance(obj, (dict, types.MappingProxyType)):
            self._dict(dict(obj), path)
            return
        if isinstance(obj, jax.tree_util.PyTreeDef):
            self._treedef(obj, path)
            return
        if isinstance(obj, jax.sharding.Mesh):
            self._mesh(obj, path)
            return
        if type(obj) is object:  # a sentinel
            self.put("object")
            return
        if isinstance(obj, (set, frozenset)):
            self._set(obj, path)
            return
        if isinstance(obj, types.ModuleType):
            if self.strict_modules and not _is_library(obj.__name__):
                self.opaque.append(f"{path} (module {obj.__name__}, not hashed by content)")
            self.put("module", obj.__name__)
            return
        if isinstance(obj, types.CodeType):
            self._code(obj, path)
            return
        if isinstance(obj, types.FunctionType):
            self._function(obj, path)
            return
        if isinstance(obj, types.MethodType):
            self.put("method", obj.__func__.__qualname__)
            self.visit(obj.__func__, f"{path}.__func__")
            self.visit(obj.__self__, f"{path}.__self__")
            return
        if isinstance(obj, (types.BuiltinFunctionType, types.BuiltinMethodType, np.ufunc)):
            self._builtin(obj, path)
            return
        if isinstance(obj, functools.partial):
            self.put("partial")
            self.visit(obj.func, f"{path}.func")
            self.visit(obj.args, f"{path}.args")
            self.visit(obj.keywords, f"{path}.keywords")
            return
        if isinstance(obj, _pyrandom.Random):
            self._pyrandom_state(obj, path)
            return
        if isinstance(obj, enum.Enum):
            self.put("enum", f"{type(obj).__module__}.{type(obj).__qualname__}.{obj.name}")
            return
        if dataclasses.is_dataclass(obj):
            self._class(type(obj), f"{path}.<class>")
            names = set()
            for f in dataclasses.fields(obj):
                names.add(f.name)
                self.put("field", f.name)
                self.visit(getattr(obj, f.name, None), f"{path}.{f.name}")
            # attributes outside the fields (set after construction, or by __post_init__)
            extra = {k: v for k, v in getattr(obj, "__dict__", {}).items() if k not in names}
            for c in type(obj).__mro__:
                for sl in getattr(c, "__slots__", ()):
                    if (
                        sl not in names
                        and sl not in ("__dict__", "__weakref__")
                        and hasattr(obj, sl)
                    ):
                        extra[sl] = getattr(obj, sl)
            if extra:
                self.put("extra")
                self._dict(extra, f"{path}.<attributes>")
            return
        if callable(obj) and hasattr(obj, "__wrapped__"):  # jax.jit, functools.wraps, custom_jvp
            self.put("wrapper", type(obj).__qualname__)
            self.visit(obj.__wrapped__, f"{path}.__wrapped__")
            # the wrapper's own state too: a custom_jvp's jvp rule, a custom_vjp's fwd and bwd
            extra = {
                k: v for k, v in getattr(obj, "__dict__", {}).items() if k not in _WRAPPER_SKIP
            }
            if extra:
                self._dict(extra, f"{path}.<wrapper state>")
            return
        self._instance(obj, path)

    # ---------------------------------------------------------------------------------------------
    def _array(self, a: np.ndarray, path: str) -> None:
        if a.dtype == object:
            self.opaque.append(f"{path} (an array of Python objects)")
            return
        self.put("array", f"{a.dtype.str}{a.shape}")
        self.put("bytes", np.ascontiguousarray(a).tobytes())

    def _jax_array(self, a, path: str) -> None:
        if isinstance(a, jax.core.Tracer):
            self.traced = True
            self.opaque.append(f"{path} (a traced array: call monte_carlo outside jit)")
            return
        if getattr(a, "weak_type", False):  # promotes like a Python scalar: another computation
            self.put("weak_type")
        if jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key):
            self.put("prng_key", str(jr.key_impl(a)))
            a = jr.key_data(a)
        try:
            self._array(np.asarray(a), path)
        except Exception as e:  # noqa: BLE001  (e.g. an array not addressable from this process)
            self.opaque.append(f"{path} (a jax.Array that cannot be read: {type(e).__name__})")

    def _dict(self, d: dict, path: str) -> None:
        self.put("dict", str(len(d)))
        items = list(d.items())
        if all(isinstance(k, (str, int, float)) for k in d):
            items.sort(key=lambda kv: (type(kv[0]).__name__, repr(kv[0])))
        for k, v in items:
            self.visit(k, f"{path}.<key>")
            self.visit(v, f"{path}[{k!r}]")

    def _treedef(self, td, path: str) -> None:
        """A pytree structure node by node: node types and auxiliary data (static fields), by
        content."""
        self.put("treedef", str(td.num_leaves))
        node = td.node_data()
        if node is None:
            self.put("leaf")
            return
        self.visit(node[0], f"{path}.<node type>")
        self.visit(_canonical_node_data(node[1]), f"{path}.<node data>")
        for i, child in enumerate(td.children()):
            self.visit(child, f"{path}.<child {i}>")

    def _mesh(self, mesh, path: str) -> None:
        """A device mesh by its axes and its devices (platform, kind, id, process), in mesh order."""
        self.put("mesh", repr(tuple(mesh.axis_names)) + repr(tuple(mesh.devices.shape)))
        for d in mesh.devices.flat:
            self.put("device", f"{d.platform}|{d.device_kind}|{d.id}|{d.process_index}")
        self.put("axis_types", repr(getattr(mesh, "axis_types", None)))

    def _set(self, s, path: str) -> None:
        digests = []
        for v in s:
            sub = _Hasher(self.strict_modules)
            sub.visit(v, path)
            self.opaque.extend(sub.opaque)
            digests.append(sub.h.hexdigest())
        self.put(type(s).__name__, ",".join(sorted(digests)))

    def _code(self, co: types.CodeType, path: str) -> None:
        if self.strict_modules:
            # a module imported inside the function is read by name only, like a global module
            import dis

            for ins in dis.get_instructions(co):
                if ins.opname == "IMPORT_NAME" and not _is_library(str(ins.argval)):
                    self.opaque.append(
                        f"{path} (imports module {ins.argval}, not hashed by content)"
                    )
        self.put("code", co.co_code)
        self.put(
            "code-meta",
            f"{co.co_argcount},{co.co_posonlyargcount},{co.co_kwonlyargcount},{co.co_flags}|"
            f"{co.co_names}|{co.co_varnames}|{co.co_freevars}|{co.co_cellvars}",
        )
        for i, c in enumerate(co.co_consts):
            self.visit(c, f"{path}.<const {i}>")

    def _function(self, fn: types.FunctionType, path: str) -> None:
        self.put("function", f"{fn.__module__}.{fn.__qualname__}")
        names = _global_names(fn.__code__)
        if not _is_library(fn.__module__):
            self._code(fn.__code__, path)
            if fn.__dict__:  # attributes set on the function (f.scale = ...)
                self._dict(dict(fn.__dict__), f"{path}.__dict__")
            glb = fn.__globals__
            for name in sorted(names):
                if name in glb:
                    self.put("global", name)
                    self._read(glb[name], names, f"{path}.<global {name}>")
            # modules the function imports when it runs (``import cfg`` or ``from cfg import X`` in its
            # body): their attributes that the code names, as for a module read as a global
            for mod_name in _imported_modules(fn.__code__, fn.__globals__.get("__package__")):
                self.put("import", mod_name)
                if _is_library(mod_name):
                    continue
                mod = sys.modules.get(mod_name)
                if mod is None:
                    try:
                        mod = importlib.import_module(mod_name)
                    except Exception:  # noqa: BLE001 - it fails when the function runs, if ever
                        self.opaque.append(f"{path} (imports module {mod_name}, which cannot be found)")
                        continue
                self._module_attributes(mod, names, f"{path}.<import {mod_name}>", set())
            self._process_state(fn, names, path)
        self.visit(fn.__defaults__, f"{path}.__defaults__")
        self.visit(fn.__kwdefaults__, f"{path}.__kwdefaults__")
        for name, cell in zip(fn.__code__.co_freevars, fn.__closure__ or ()):
            self.put("cell", name)
            try:
                value = cell.cell_contents
            except ValueError:  # an empty cell
                self.put("empty-cell")
                continue
            self._read(value, names, f"{path}.<closure {name}>")

    def _pyrandom_state(self, rng, path: str) -> None:
        """A ``random.Random`` by its class and its generator's state (``getstate()``: the Mersenne
        Twister's words live in C, not in ``__dict__``); a generator without a state
        (``random.SystemRandom``) cannot be hashed by content."""
        cls = type(rng)
        try:
            state = rng.getstate()
        except (NotImplementedError, AttributeError, TypeError):
            self.opaque.append(f"{path} ({cls.__module__}.{cls.__qualname__}, a generator without a state)")
            self.put("opaque", f"{cls.__module__}.{cls.__qualname__}")
            return
        self._class(cls, f"{path}.<class>")
        self.put("random-state")
        self.visit(state, f"{path}.<state>")
        if getattr(rng, "__dict__", None):
            self.visit(dict(vars(rng)), f"{path}.__dict__")

    def _process_state(self, fn: types.FunctionType, names: set, path: str) -> None:
        """What a function may read from the process rather than from its code and values: the
        environment variables its code names (``os.environ["SCALE"]``, ``os.getenv("SCALE")``), the
        state of the ``random`` module's hidden generator when it calls one of its functions
        (``random.gauss``), and NumPy's global ``RandomState`` when it calls a legacy ``np.random``
        function (``np.random.normal``).  (Such a function imported by name, ``from random import
        gauss``, is a bound method of the hidden generator and is hashed with its state anyway.)"""
        if names & _ENV_READERS:
            for key in sorted(_string_constants(fn.__code__)):
                self.put("env", f"{key}\0{os.environ.get(key)!r}")
        hidden = _hidden_generators(fn) if names & _GENERATOR_FUNCTIONS else set()
        if "random" in hidden:
            self.put("random-module")
            self._pyrandom_state(_pyrandom._inst, f"{path}.<random module's generator>")
        if "numpy" in hidden:
            self.put("numpy-global-random")
            self.visit(np.random.get_state(), f"{path}.<numpy's global RandomState>")

    def _read(self, value, names: set, path: str) -> None:
        """A value a function reads (a global or a closure cell), and, for a module, the attributes of
        it that the function's code names."""
        self.visit(value, path)
        if isinstance(value, types.ModuleType):
            self._module_attributes(value, names, path, set())

    def _module_attributes(self, mod: types.ModuleType, names: set, path: str, seen: set) -> None:
        """The attributes of a user's module (a settings module, ``cfg.SCALE``) that a function may read:
        those named in its code (``co_names`` holds both global and attribute names), by content.  A
        module is otherwise hashed by its name only, and a changed setting would go unnoticed."""
        if _is_library(mod.__name__) or id(mod) in seen:
            return
        seen.add(id(mod))
        space = vars(mod)
        for attr in sorted(names):
            if attr.startswith("__") or attr not in space:
                continue
            value = space[attr]
            self.put("module-attr", f"{mod.__name__}.{attr}")
            self.visit(value, f"{path}.{attr}")
            if isinstance(value, types.ModuleType):
                self._module_attributes(value, names, f"{path}.{attr}", seen)

    def _builtin(self, fn, path: str) -> None:
        mod = getattr(fn, "__module__", None)
        self.put("builtin", f"{mod}.{getattr(fn, '__qualname__', getattr(fn, '__name__', '?'))}")
        owner = getattr(fn, "__self__", None)
        if owner is not None and not isinstance(owner, types.ModuleType):
            self.visit(owner, f"{path}.__self__")  # a bound method of a C object: its state matters

    def _class(self, cls: type, path: str) -> None:
        name = f"{cls.__module__}.{cls.__qualname__}"
        if self._seen(cls):
            return
        self.put("class", name)
        if _is_library(cls.__module__):
            return
        for base in cls.__bases__:
            self.visit(base, f"{path}.<base {base.__qualname__}>")
        for key in sorted(vars(cls)):
            if key in _CLASS_SKIP:
                continue
            value = vars(cls)[key]
            self.put("attr", key)
            if isinstance(value, (staticmethod, classmethod)):
                value = value.__func__
            elif isinstance(value, property):
                value = (value.fget, value.fset)
            elif isinstance(value, functools.cached_property):
                value = value.func  # (not its lock)
            elif isinstance(value, _LAYOUT_DESCRIPTORS):
                # a slot's or a named tuple's field accessor: the class's layout, named by the key
                # (a named tuple's accessor also by its index)
                layout = value.__reduce__()[1][0] if isinstance(value, _TUPLEGETTER) else ""
                self.put("descriptor", f"{type(value).__name__}{layout}")
                continue
            self.visit(value, f"{name}.{key}")

    def _instance(self, obj, path: str) -> None:
        cls = type(obj)
        state = getattr(obj, "__dict__", None)
        slots = [s for c in cls.__mro__ for s in getattr(c, "__slots__", ())]
        if state is None and not slots:
            self.opaque.append(f"{path} ({cls.__module__}.{cls.__qualname__})")
            self.put("opaque", f"{cls.__module__}.{cls.__qualname__}")
            return
        self._class(cls, f"{path}.<class>")
        if state is not None:
            self.visit(dict(state), f"{path}.__dict__")
        for s in slots:
            if s not in ("__dict__", "__weakref__") and hasattr(obj, s):
                self.put("slot", s)
                self.visit(getattr(obj, s), f"{path}.{s}")


def _imported_modules(co: types.CodeType, package) -> list[str]:
    """The absolute names of the modules that a function's code (nested functions included) imports:
    ``import a.b`` gives ``a`` and ``a.b``; a relative import is resolved against `package`."""
    import dis
    import importlib.util

    out: list[str] = []
    ins = list(dis.get_instructions(co))
    for i, op in enumerate(ins):
        if op.opname != "IMPORT_NAME":
            continue
        name = str(op.argval)
        level = ins[i - 2].argval if i >= 2 and ins[i - 2].opname == "LOAD_CONST" else 0
        if isinstance(level, int) and level > 0:
            try:
                name = importlib.util.resolve_name("." * level + name, package)
            except (ImportError, ValueError, TypeError):
                continue
        parts = name.split(".") if name else []
        out += [".".join(parts[: k + 1]) for k in range(len(parts))]
        fromlist = ins[i - 1].argval if i >= 1 and ins[i - 1].opname == "LOAD_CONST" else None
        # ``from pkg import sub``: sub may be a module of its own
        for sub in fromlist or ():
            if isinstance(sub, str) and sub != "*" and _is_submodule(name, sub):
                out.append(f"{name}.{sub}")
    for c in co.co_consts:
        if isinstance(c, types.CodeType):
            out += _imported_modules(c, package)
    return sorted(set(out))


def _is_submodule(package: str, name: str) -> bool:
    """Whether ``package.name`` is a module (``from package import name`` then imports it)."""
    import importlib.util

    full = f"{package}.{name}"
    if full in sys.modules:
        return True
    if _is_library(package):
        return False
    try:
        return importlib.util.find_spec(full) is not None
    except (ImportError, ValueError, AttributeError):
        return False


def _global_names(co: types.CodeType) -> set[str]:
    """The names a function's code may read: its global and attribute names (``co_names``), and the
    string constants that are identifiers, which is how ``getattr(cfg, "SCALE")``,
    ``vars(cfg)["SCALE"]`` and ``globals()["SCALE"]`` name what they read (a name that is a constant
    but no global or attribute is simply not found)."""
    names = set(co.co_names)
    for c in co.co_consts:
        if isinstance(c, types.CodeType):
            names |= _global_names(c)
        elif isinstance(c, str) and c.isidentifier():
            names.add(c)
    return names


def _string_constants(co: types.CodeType) -> set[str]:
    """Every string constant of a function's code, nested functions included."""
    out = set()
    for c in co.co_consts:
        if isinstance(c, types.CodeType):
            out |= _string_constants(c)
        elif isinstance(c, str):
            out.add(c)
    return out


def fingerprint(parts: dict, *, strict_modules: bool = False) -> tuple[str, list[str]]:
    """SHA-256 hex digest of the version header and the named parts, and the list of paths that
    could not be hashed by content (empty when the fingerprint covers everything).

    `strict_modules`: also report a module outside the numerical libraries (one a user function
    reads as a global, e.g. ``mymodule.helper``) as not hashed by content, since only its name is
    hashed; the trace cache sets it."""
    h = _Hasher(strict_modules)
    h.put("header", header())
    with _deep_recursion():
        for name in sorted(parts):
            h.put("part", name)
            try:
                h.visit(parts[name], name)
            except RecursionError:  # an object graph nested beyond any limit: not hashed by content
                h.opaque.append(f"{name} (an object graph nested too deeply to hash)")
    return h.h.hexdigest(), h.opaque


#: the recursion limit while hashing: the walk recurses once per level of the object graph (a function,
#: the globals it reads, their attributes, ...), several frames per level, and more under a runtime
#: type checker; Python's default of 1000 was reached by the graph of a test session's functions
_HASH_RECURSION_LIMIT = 50_000


class _deep_recursion:
    """Raise the interpreter's recursion limit to :data:`_HASH_RECURSION_LIMIT` for the walk."""

    def __enter__(self):
        self.old = sys.getrecursionlimit()
        sys.setrecursionlimit(max(self.old, _HASH_RECURSION_LIMIT))

    def __exit__(self, *exc):
        sys.setrecursionlimit(self.old)
        return False


#: unique suffixes of the keys of trees that read a traced array (never equal to another key)
_TRACED_KEYS = itertools.count()


def content_key(tree) -> str:
    """A digest of what tracing ``tree`` reads besides its arrays, for an in-process compilation key.

    The non-array part of ``tree`` (the static fields of plants and observers, user functions with their
    bytecode, closures, defaults and the globals and settings-module attributes they read, arrays among
    those included) hashed as :func:`fingerprint` does, without the version header (one process has one
    set of versions).  ``jax.jit`` and ``eqx.filter_jit`` key a function argument by its identity, so a
    function that reads a global changed since the last call was served the program traced with the old
    value; a key that holds this digest is traced again instead.  A traced array among what the
    functions read (a closure or a global that holds a tracer of an enclosing ``jit`` or ``grad``) makes
    the key unique: its value is not known here, and a program traced with one tracer must not be served
    for another (it gave the numbers of the first, or an ``UnexpectedTracerError`` once that trace had
    ended).  What else cannot be hashed by content (an object of a compiled extension) is left out; a
    failure gives ``""`` (the identity key alone, as before)."""
    import equinox as eqx

    try:
        _, static = eqx.partition(tree, eqx.is_array)
        h = _Hasher(False)
        with _deep_recursion():
            h.visit(static, "static")
        if h.traced:
            return f"traced:{next(_TRACED_KEYS)}"
        return h.h.hexdigest()
    except Exception:  # noqa: BLE001 - an object the hasher cannot walk: keyed by identity as before
        return ""

