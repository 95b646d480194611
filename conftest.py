"""pytest configuration for the whole repository (tests/ and the notebooks run by nbmake).

JAX's persistent compilation cache is NOT turned on for the test run by default: two CI runs aborted
(SIGABRT), once inside ``executable.serialize()``.  The causes were the memory mappings that compiled
programs accumulate (see ``_release_compiled_programs``) and jaxlib 0.10.2's YNNPACK fusions (now
excluded, see obsjax/_config.py); the cache stays opt-in until proven through a whole run.
``OBSJAX_TEST_COMPILATION_CACHE=1`` turns it on for a local run (and, through the environment, for the
notebook kernels that nbmake starts).
"""

import gc
import os

import jax
import pytest

from obsjax._cache import cache_environment, enable_compilation_cache

if os.environ.get("OBSJAX_TEST_COMPILATION_CACHE", "").strip().lower() in ("1", "true", "yes"):
    _CACHE_DIR = enable_compilation_cache()
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
