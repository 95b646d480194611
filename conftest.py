"""pytest configuration for the whole repository (tests/ and the notebooks run by nbmake).

JAX's persistent compilation cache is NOT turned on for the test run by default: two CI runs aborted
(SIGABRT) with jaxlib 0.10.2, once inside ``executable.serialize()``; the cause was that release's
YNNPACK fusions (now excluded, see obsjax/_config.py), and the cache stays opt-in until proven on a
supported release.  ``OBSJAX_TEST_COMPILATION_CACHE=1`` turns it
on for a local run (and, through the environment, for the notebook kernels that nbmake starts).
"""

import os

from obsjax._cache import cache_environment, enable_compilation_cache

if os.environ.get("OBSJAX_TEST_COMPILATION_CACHE", "").strip().lower() in ("1", "true", "yes"):
    _CACHE_DIR = enable_compilation_cache()
    if _CACHE_DIR is not None:
        os.environ.update(cache_environment(_CACHE_DIR))
