"""pytest configuration for the whole repository (tests/ and the notebooks run by nbmake).

JAX's persistent compilation cache is on for the test run (the user cache directory, see
``obsjax._cache.default_cache_dir``; ``OBSJAX_NO_COMPILATION_CACHE=1`` turns it off), and through the
environment for the notebook kernels that nbmake starts.  Besides a second run, it serves the first:
a program dropped after its module (``_release_compiled_programs``) is read back, not compiled again,
when a later module compiles the same program.  (It was opt-in while two CI runs aborted
inside cache writes; the causes were the memory mappings that compiled programs accumulate and jaxlib
0.10.2's YNNPACK fusions, both dealt with, see obsjax/_config.py.)
"""

import gc
import os
import re

import jax
import pytest

from obsjax._cache import cache_environment, enable_compilation_cache

_CACHE_DIR = enable_compilation_cache()  # None when opted out
if _CACHE_DIR is not None:
    os.environ.update(cache_environment(_CACHE_DIR))


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module.

    Every XLA:CPU executable keeps its JIT-compiled code in memory mappings of its own; a single pytest
    process that compiles the whole suite's programs grows by about 30,000 mappings in five minutes and
    crosses the kernel's ``vm.max_map_count`` (65,530 by default) about half way through, after which
    XLA's allocations fail and the process dies by SIGABRT or SIGSEGV wherever it happens to be.  Clearing
    the caches between modules keeps the count to what one module compiles.
    """
    yield
    jax.clear_caches()
    gc.collect()
    _return_freed_memory()


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
