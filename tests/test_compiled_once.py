"""simulate and simulate_batch compile a problem once: a second call that changes only array values (initial
states, gains, plant matrices) runs the compiled program (it took 1–5 s per call for a problem with resets,
which compiled its segment loop again each time), and gives the numbers of a first call."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import obsjax
from obsjax import _integrate
from obsjax._integrate import _compiled

CY = obsjax.chen_yen_example()
TS = np.linspace(0.0, 2.0, 21)


@pytest.fixture
def traces(monkeypatch):
    """The number of times the back-ends are traced (each trace of a program calls them once)."""
    count = {"single": 0, "batch": 0}
    single, batch, masked = _integrate.integrate, _integrate.integrate_batch, _integrate._masked.integrate

    def spy_single(*a, **k):
        count["single"] += 1
        return single(*a, **k)

    def spy_batch(*a, **k):
        count["batch"] += 1
        return batch(*a, **k)

    def spy_masked(*a, **k):
        count["batch"] += 1
        return masked(*a, **k)

    monkeypatch.setattr(_integrate, "integrate", spy_single)
    monkeypatch.setattr(_integrate, "integrate_batch", spy_batch)
    monkeypatch.setattr(_integrate._masked, "integrate", spy_masked)
    _compiled.clear()
    yield count
    _compiled.clear()


def _ls(gamma=20.0):
    return obsjax.LeastSquaresReset(CY, gamma=jnp.asarray(gamma), p0=0.1, T=0.25)


@pytest.mark.parametrize("kw", [{}, {"adaptive": False, "dt0": 0.01}], ids=["adaptive", "fixed"])
def test_a_second_simulate_with_new_values_is_not_traced_again(traces, kw):
    a = obsjax.simulate(CY, _ls(), jnp.array([1.0, 2.0]), jnp.zeros(2), TS, **kw)
    assert traces["single"] == 1
    b = obsjax.simulate(CY, _ls(30.0), jnp.array([-1.0, 0.5]), jnp.array([0.3, 0.0]), TS, **kw)
    assert traces["single"] == 1  # the same structure: the compiled program ran
    _compiled.clear()
    ref = obsjax.simulate(CY, _ls(30.0), jnp.array([-1.0, 0.5]), jnp.array([0.3, 0.0]), TS, **kw)
    assert traces["single"] == 2
    np.testing.assert_array_equal(b.error, ref.error)
    assert not np.allclose(a.error, b.error)


def test_another_save_grid_or_period_is_another_program(traces):
    obsjax.simulate(CY, _ls(), jnp.ones(2), jnp.zeros(2), TS)
    got = obsjax.simulate(CY, _ls(), jnp.ones(2), jnp.zeros(2), TS + 0.05)  # the resets fall elsewhere
    assert traces["single"] == 2
    obs = obsjax.LeastSquaresReset(CY, gamma=20.0, p0=0.1, T=0.3)
    other = obsjax.simulate(CY, obs, jnp.ones(2), jnp.zeros(2), TS + 0.05)
    assert traces["single"] == 3
    assert float(jnp.max(jnp.abs(got.error - other.error))) > 1e-6  # not the program of T = 0.25


@pytest.mark.parametrize("lockstep", [False, True], ids=["masked", "lockstep"])
def test_a_second_batch_with_new_values_is_not_traced_again(traces, lockstep):
    x0s = jnp.array([[1.0, 2.0], [0.5, -1.0]])
    tight = dict(rtol=1e-10, atol=1e-12)
    obsjax.simulate_batch(CY, _ls(), x0s, jnp.zeros((2, 2)), TS, lockstep=lockstep, **tight)
    assert traces["batch"] == 1
    got = obsjax.simulate_batch(CY, _ls(25.0), -x0s, jnp.ones((2, 2)), TS, lockstep=lockstep, **tight)
    assert traces["batch"] == 1
    for i in range(2):  # member by member (lock step shares its steps: equal to the tolerance)
        one = obsjax.simulate(CY, _ls(25.0), -x0s[i], jnp.ones(2), TS, **tight)
        np.testing.assert_allclose(got.error[i], one.error, atol=1e-8)
