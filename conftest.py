"""pytest configuration for the whole repository (tests/ and the notebooks run by nbmake).

JAX's persistent compilation cache is on for the test run (the user cache directory, see
``obsjax._cache.default_cache_dir``; ``OBSJAX_NO_COMPILATION_CACHE=1`` turns it off), and through the
environment for the notebook kernels that nbmake starts.  Besides a second run, it serves the first:
a program dropped after a module (``_release_compiled_programs``) is read back, not compiled again,
when a later module compiles the same program.  (It was opt-in while two CI runs aborted
inside cache writes; the causes were the memory mappings that compiled programs accumulate and jaxlib
0.10.2's YNNPACK fusions, both dealt with, see obsjax/_config.py.)

What keeps the run short (the default tier on 2 cores with an empty cache went from 6:50 to 5:17-6:23 in
CI's conditions on 2026-12-07): every
program is compiled with XLA:CPU's elemental emitters (``XLA_FLAGS``, below), the process that only hands
tests to pytest-xdist's workers imports neither JAX nor obsjax, and a worker keeps its compiled programs
from one module to the next until it holds many memory mappings or much memory.
"""

import gc
import os
import re

import pytest

#: XLA:CPU's elemental emitters for every program the test run compiles (the library compiles tune's and
#: monte_carlo's kernels with them, obsjax._trace_cache.FAST_COMPILE_OPTIONS): most of the run is
#: compilation, which they do faster.  ``OBSJAX_DEFAULT_XLA_OPTIONS=1`` runs with XLA's defaults.
_FAST_XLA_FLAG = "--xla_cpu_use_fusion_emitters=false"


def _jaxlib_knows(flag_name: str) -> bool:
    """Whether the installed jaxlib's XLA has the option `flag_name` (its name is in the shared libraries):
    an unknown flag in ``XLA_FLAGS`` aborts the process.  Looked up without importing JAX."""
    import importlib.util
    import mmap

    spec = importlib.util.find_spec("jaxlib")
    if spec is None or not spec.submodule_search_locations:
        return False
    needle = flag_name.encode()
    for where in spec.submodule_search_locations:
        for entry in os.scandir(where):
            if entry.name.endswith(".so") and entry.is_file():
                try:
                    with open(entry.path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
                        if m.find(needle) >= 0:
                            return True
                except (OSError, ValueError):
                    continue
    return False


def _use_fast_xla_emitters():
    """Add :data:`_FAST_XLA_FLAG` to ``XLA_FLAGS`` (read when JAX starts its backend, so before any test
    module runs; the worker processes and notebook kernels inherit it) unless opted out, already set either
    way, or unknown to this jaxlib."""
    if os.environ.get("OBSJAX_DEFAULT_XLA_OPTIONS", "").strip().lower() not in ("", "0", "false", "no"):
        return
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_use_fusion_emitters" in flags or not _jaxlib_knows("xla_cpu_use_fusion_emitters"):
        return
    os.environ["XLA_FLAGS"] = f"{flags} {_FAST_XLA_FLAG}".strip()


_use_fast_xla_emitters()


def _runs_tests_here(config) -> bool:
    """False in the process of pytest-xdist that hands the tests to worker processes (``-n auto``, the
    default, see pyproject.toml): it imports no test module, so it need not import JAX and obsjax."""
    return not config.pluginmanager.has_plugin("dsession")


@pytest.hookimpl(trylast=True)  # after pytest-xdist's own, which registers "dsession" when it distributes
def pytest_configure(config):
    """Turn on the compilation cache in each process that runs tests (the worker processes, or this one
    under ``-n 0``), before the test modules are imported.  The process that only distributes the tests
    skips it, and with it the import of JAX and obsjax (about 8 s under jaxtyping's import hook, spent
    before any worker starts)."""
    if not _runs_tests_here(config):
        return
    from obsjax._cache import cache_environment, enable_compilation_cache

    cache_dir = enable_compilation_cache()  # None when opted out
    if cache_dir is not None:
        os.environ.update(cache_environment(cache_dir))


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after a test module once the process holds more than
    :data:`_MAX_MAPPINGS` memory mappings or :data:`_MAX_RESIDENT` bytes of resident memory.

    Every XLA:CPU executable keeps its JIT-compiled code in memory mappings of its own; a single pytest
    process that compiles the whole suite's programs grows by about 30,000 mappings in five minutes and
    crosses the kernel's ``vm.max_map_count`` (65,530 by default) about half way through, after which
    XLA's allocations fail and the process dies by SIGABRT or SIGSEGV wherever it happens to be.  Clearing
    the caches keeps the count well below that.  They were cleared after every module before; keeping
    them while the process is small lets a later module reuse what an earlier one traced and compiled
    (the eager operations of NumPy-like code, the same example problems): 37 s less CPU in the default
    tier, whose worker processes then peaked at 2.0 GB instead of 1.2 GB.
    """
    yield
    if not _crowded():
        return
    import jax

    jax.clear_caches()
    gc.collect()
    _return_freed_memory()


#: memory mappings above which the compiled programs are dropped (a quarter of the kernel's default limit)
_MAX_MAPPINGS = 16_000
#: resident memory above which they are dropped (the default tier's target is 3 GB a process)
_MAX_RESIDENT = 1.75 * 2**30


def _crowded() -> bool:
    """Whether this process holds more than :data:`_MAX_MAPPINGS` mappings or :data:`_MAX_RESIDENT`
    bytes (Linux's ``/proc/self``; elsewhere always, as before)."""
    try:
        with open("/proc/self/maps", "rb") as f:
            n = sum(1 for _ in f)
        with open("/proc/self/statm") as f:
            rss = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return True
    return n > _MAX_MAPPINGS or rss > _MAX_RESIDENT


def _return_freed_memory():
    """Hand the heap that the dropped programs and arrays freed back to the kernel (glibc's
    ``malloc_trim``).  Freed memory otherwise stays in the allocator's arenas and counts as resident:
    after a module such as tests/test_pd_spectrum.py a worker held 675 MB, 342 MB after the trim.  A
    no-op where the C library has no ``malloc_trim``.
    """
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # pragma: no cover - not glibc
        pass


# The largest worker process peaks at about 3.1-3.4 GB of resident memory on the full suite (XLA's
# compiled programs of one test module at a time, see _release_compiled_programs); four GiB a worker
# keeps a small machine out of swap.
_WORKER_BYTES = 4 * 2**30


def _available_memory():
    try:
        with open("/proc/meminfo") as f:
            m = re.search(r"^MemAvailable:\s+(\d+) kB", f.read(), re.M)
        return int(m.group(1)) * 1024 if m else None
    except OSError:
        return None


@pytest.hookimpl(wrapper=True)
def pytest_xdist_auto_num_workers(config):
    """How many worker processes ``-n auto`` (the default, see pyproject.toml) starts: pytest-xdist's own
    count (one per CPU core, or ``PYTEST_XDIST_AUTO_NUM_WORKERS=k``), capped at one per 4 GiB of
    available memory, at least one.

    The test run is mostly XLA tracing and compilation, one program at a time per process, so a second
    process on a second core shortens its wall time.  ``-n 0`` runs in this process alone (no workers),
    e.g. under a debugger.
    """
    count = yield
    mem = _available_memory()
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS") or mem is None:
        return count
    return max(1, min(count, mem // _WORKER_BYTES))


try:  # property tests draw the same examples on every run: a CI result can be reproduced
    from hypothesis import settings as _hyp_settings

    _hyp_settings.register_profile("obsjax", derandomize=True, print_blob=True)
    _hyp_settings.load_profile("obsjax")
except ImportError:  # pragma: no cover - hypothesis is a test extra
    pass


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """The notebooks (run by nbmake) belong to the ``extended`` tier: each takes one to two minutes, most
    of it compiling, so the default run leaves them to ``python -m pytest -m extended`` (CI runs both).
    This runs before pytest's own ``-m`` selection, so the marker is seen by it.
    """
    for item in items:
        if item.path.suffix == ".ipynb":
            item.add_marker(pytest.mark.extended)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """End the run's report with its largest resident memory, so that a CI log shows it beside pytest's
    wall time: the largest of this process and the worker processes it has waited for (and theirs: the
    notebook kernels), from ``getrusage`` (Linux reports kilobytes).
    """
    if hasattr(config, "workerinput"):  # a pytest-xdist worker: the controller reports
        return
    try:
        import resource
    except ImportError:  # pragma: no cover - not POSIX
        return
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    terminalreporter.write_line(
        f"largest resident memory of one process: {max(own, children) / 1e6:.2f} GB "
        f"(this process {own / 1e6:.2f} GB, its finished worker processes {children / 1e6:.2f} GB)"
    )
