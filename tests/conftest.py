import os

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.hookimpl(trylast=True)  # after pytest-xdist's, see the repository's conftest.py
def pytest_configure(config):
    """float64 and obsjax imported before the test modules, in each process that runs tests (not in the
    pytest-xdist process that only hands them to its workers)."""
    if config.pluginmanager.has_plugin("dsession"):
        return
    import jax

    jax.config.update("jax_enable_x64", True)
    import obsjax  # noqa: F401
