"""The eager programs of simulate, simulate_batch and estimate are compiled with the library's XLA:CPU
options (obsjax._trace_cache.fast_compile_options: the elemental emitters, as tune's and monte_carlo's
kernels); inside an outer jit they are traced into the outer program, which takes none of their options
(JAX refuses compile options on a nested jit)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import obsjax
from obsjax import _trace_cache
from obsjax._data import _estimate
from obsjax._integrate import _compiled

PLANT = obsjax.LTI([[-2.0, 1.0], [0.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]])
OBS = obsjax.Luenberger.from_poles(PLANT, [-3.0, -4.0])
X0, XH0 = jnp.array([1.0, -1.0]), jnp.zeros(2)
TS = np.linspace(0.0, 2.0, 11)
DATA = obsjax.Measurements(TS, np.exp(-TS)[:, None], np.sin(TS)[:, None])
#: an option XLA does not know: a program compiled with it is refused, and the error names it
BOGUS = {"xla_obsjax_no_such_option": True}


def _forget_programs():
    _compiled.clear()
    _estimate._drivers.clear()


@pytest.fixture
def options(monkeypatch):
    """Set the options the entry points compile with (a dict), starting from empty tables of programs."""
    _forget_programs()

    def use(opts):
        monkeypatch.setattr(_compiled, "fast_compile_options", lambda: opts)
        monkeypatch.setattr(_estimate, "fast_compile_options", lambda: opts)

    yield use
    _forget_programs()


_CALLS = {
    "simulate": lambda x0: obsjax.simulate(PLANT, OBS, x0, XH0, TS).xhat,
    "simulate_batch": lambda x0: obsjax.simulate_batch(
        PLANT, OBS, jnp.stack([x0, -x0]), jnp.zeros((2, 2)), TS
    ).xhat,
    "estimate": lambda x0: obsjax.estimate(OBS, DATA, x0).xhat,
}


@pytest.mark.parametrize("name", list(_CALLS))
def test_the_eager_program_is_compiled_with_the_library_options(options, name):
    options(BOGUS)
    with pytest.raises(Exception, match="xla_obsjax_no_such_option|No such compile option"):
        _CALLS[name](X0)


@pytest.mark.parametrize("name", list(_CALLS))
def test_inside_an_outer_jit_the_outer_program_takes_no_options_of_theirs(options, name):
    options(BOGUS)
    out = jax.jit(_CALLS[name])(X0)
    assert np.all(np.isfinite(np.asarray(out)))


@pytest.mark.parametrize("name", list(_CALLS))
def test_an_eager_gradient_compiles_without_options(options, name):
    """Under eager ``jax.grad`` JAX traces the program again inside its differentiation, where options on a
    jit are refused as nested: the program is compiled without them."""
    options(BOGUS)
    g = jax.grad(lambda x0: jnp.sum(_CALLS[name](x0) ** 2))(X0)
    assert g.shape == (2,) and np.all(np.isfinite(np.asarray(g)))


@pytest.mark.parametrize("name", list(_CALLS))
def test_the_library_options_give_the_numbers_of_xla_defaults(options, name):
    fast = _trace_cache.fast_compile_options()
    if not fast:
        pytest.skip("this jaxlib does not know the elemental-emitter option (the defaults are used)")
    options(fast)
    a = np.asarray(_CALLS[name](X0))
    _forget_programs()
    options({})
    b = np.asarray(_CALLS[name](X0))
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
