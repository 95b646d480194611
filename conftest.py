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


try:  # property tests draw the same examples on every run: a CI result can be reproduced
    from hypothesis import settings as _hyp_settings

    _hyp_settings.register_profile("obsjax", derandomize=True, print_blob=True)
    _hyp_settings.load_profile("obsjax")
except ImportError:  # pragma: no cover - hypothesis is a test extra
    pass
