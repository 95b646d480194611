"""The jaxlib guard: the installed jax computes the pattern that jaxlib 0.10.2 got wrong, and importing
obsjax warns about a known-bad release.

jaxlib 0.10.2's XLA:CPU YNNPACK fusions returned a wrong last row for a jitted vmap of a matrix-vector
product followed by a sum of squares over 16,385 rows (268,435,456 exact; 266,342,400 computed, float64),
and aborted whole test runs from a worker thread.  Every observer's right-hand side is this pattern under
``simulate_batch`` / ``monte_carlo``.
"""

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import obsjax  # noqa: F401  (float64)
from obsjax._config import BAD_CPU_JAXLIB, YNN_OFF_FLAG, JaxlibWarning, _ynn_disabled, check_jaxlib


@pytest.mark.parametrize("n", [16_385, 40_000])
def test_vmapped_matvec_reduction_is_exact_under_jit(n):
    i = np.arange(n, dtype=np.float64)
    x = np.stack((i, np.zeros_like(i), np.zeros_like(i)), axis=1)
    a = np.eye(3)

    def f(x):
        return jax.vmap(lambda row: jnp.sum((a @ row) ** 2))(x)

    exact = i**2  # integers below 2**53: exact in float64
    np.testing.assert_array_equal(np.asarray(jax.jit(f)(jnp.asarray(x))), exact)
    np.testing.assert_array_equal(np.asarray(f(jnp.asarray(x))), exact)


def test_a_bad_release_warns_and_the_flag_or_another_release_does_not():
    bad = BAD_CPU_JAXLIB[0]
    with pytest.warns(JaxlibWarning, match=rf"jaxlib {bad}.*wrong values.*XLA_FLAGS"):
        msg = check_jaxlib(bad, "")
    assert "pip install" in msg
    assert check_jaxlib(bad, f"--xla_force_host_platform_device_count=2 {YNN_OFF_FLAG}") is None
    assert check_jaxlib("0.10.1", "") is None


def test_the_installed_release_is_not_a_bad_one_or_is_guarded():
    # The test environment itself: pyproject.toml excludes the bad releases; an environment that has one
    # anyway must have the fusions turned off, or the suite's numbers are not evidence.
    import jaxlib

    assert jaxlib.__version__ not in BAD_CPU_JAXLIB or _ynn_disabled(os.environ.get("XLA_FLAGS", ""))


def test_import_warns_in_a_process_that_reports_a_bad_release():
    code = (
        "import warnings, jaxlib\n"
        f"jaxlib.__version__ = {BAD_CPU_JAXLIB[0]!r}\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    warnings.simplefilter('always')\n"
        "    import obsjax\n"
        "print(sum(issubclass(x.category, obsjax.JaxlibWarning) for x in w))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "1"
