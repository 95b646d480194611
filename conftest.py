"""pytest configuration for the whole repository (tests/ and the notebooks run by nbmake)."""

import os

from obsjax._cache import cache_environment, enable_compilation_cache

# JAX's persistent compilation cache for the test run (OBSJAX_NO_COMPILATION_CACHE=1 turns it off),
# also for the notebook kernels that nbmake starts: they inherit these variables and JAX reads them
# on import.
_CACHE_DIR = enable_compilation_cache()
if _CACHE_DIR is not None:
    os.environ.update(cache_environment(_CACHE_DIR))
