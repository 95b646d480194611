"""pytest configuration for the whole repository (tests/ and the notebooks run by nbmake).

JAX's persistent compilation cache is NOT turned on for the test run by default: in one CI run,
XLA:CPU aborted the whole process (SIGABRT inside ``executable.serialize()``, jaxlib 0.10.2) while
writing a cache entry, which no Python code can catch.  ``OBSJAX_TEST_COMPILATION_CACHE=1`` turns it
on for a local run (and, through the environment, for the notebook kernels that nbmake starts).
"""

import os

from obsjax._cache import cache_environment, enable_compilation_cache

if os.environ.get("OBSJAX_TEST_COMPILATION_CACHE", "").strip().lower() in ("1", "true", "yes"):
    _CACHE_DIR = enable_compilation_cache()
    if _CACHE_DIR is not None:
        os.environ.update(cache_environment(_CACHE_DIR))
