"""simulate and simulate_batch compile a problem once: a second call that changes only array values (initial
states, gains, plant matrices) runs the compiled program (it took 1–5 s per call for a problem with resets,
which compiled its segment loop again each time), and gives the numbers of a first call."""

from __future__ import annotations

import jax
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


@pytest.mark.extended
def test_another_save_grid_or_period_is_another_program(traces):
    obsjax.simulate(CY, _ls(), jnp.ones(2), jnp.zeros(2), TS)
    got = obsjax.simulate(CY, _ls(), jnp.ones(2), jnp.zeros(2), TS + 0.05)  # the resets fall elsewhere
    assert traces["single"] == 2
    obs = obsjax.LeastSquaresReset(CY, gamma=20.0, p0=0.1, T=0.3)
    other = obsjax.simulate(CY, obs, jnp.ones(2), jnp.zeros(2), TS + 0.05)
    assert traces["single"] == 3
    assert float(jnp.max(jnp.abs(got.error - other.error))) > 1e-6  # not the program of T = 0.25


@pytest.mark.extended
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


# ------------------------------------------------------------------- eager differentiation (jax.grad, no jit)


def _ise_of_gamma(gamma):
    tr = obsjax.simulate(CY, _ls(gamma), jnp.array([1.0, -1.0]), jnp.array([5.0, -5.0]), TS, rtol=1e-10,
                         atol=1e-12)
    return obsjax.losses.ise(tr)


@pytest.mark.extended
def test_an_eager_gradient_is_compiled_once_and_equals_central_differences(traces):
    """jax.grad without jit differentiates the compiled program: a second gradient at another gain runs the
    programs JAX derived for the first (8.0 s per call on the Chen & Yen example with 40 resets before,
    88 ms now: benchmark (l)), and the values are those of central differences (against jit(grad): the
    next test)."""
    g1 = float(jax.grad(_ise_of_gamma)(20.0))
    assert traces["single"] == 1
    g2 = float(jax.grad(_ise_of_gamma)(27.0))
    assert traces["single"] == 1  # not traced again
    for gamma, g in ((20.0, g1), (27.0, g2)):
        h = 1e-4  # eager calls of the same structure: the kept forward program
        fd = (float(_ise_of_gamma(gamma + h)) - float(_ise_of_gamma(gamma - h))) / (2 * h)
        assert g == pytest.approx(fd, rel=1e-5)
    assert traces["single"] == 1
    assert g1 != pytest.approx(g2, rel=1e-3)


@pytest.mark.parametrize(
    "how", ["simulate"] + [pytest.param(h, marks=pytest.mark.extended) for h in ("lockstep", "masked")]
)
@pytest.mark.extended
def test_a_gradient_through_a_plant_function_that_closes_over_the_parameter(how):
    """The parameter reaches the solve only through a closure (an LTV plant's A(t) built inside the loss).
    JAX refused this gradient, eagerly and under jit ("differentiation of a custom_vjp function with respect
    to a closed-over value": the zero-gradient guard of rejected steps is a custom_vjp); the closed-over
    values are now explicit arguments of the guard.  Each call is a new function, hence a new program (the
    closed-over value is not frozen into a program kept for a later call).  The eager and the jitted
    derivatives agree, and equal central differences."""
    x0s = jnp.array([[1.0, 0.0], [0.3, -0.5]])

    def cost(a):
        plant = obsjax.LTV(lambda t: jnp.array([[0.0, 1.0], [-a, -0.4]]), lambda t: jnp.array([[1.0, 0.0]]))
        obs = obsjax.LeastSquaresReset(plant, gamma=5.0, p0=1.0, T=0.5)
        kw = dict(rtol=1e-10, atol=1e-12)
        if how == "simulate":
            tr = obsjax.simulate(plant, obs, x0s[0], jnp.zeros(2), TS, **kw)
        else:
            tr = obsjax.simulate_batch(plant, obs, x0s, jnp.zeros((2, 2)), TS, lockstep=how == "lockstep",
                                       **kw)
        return jnp.sum(tr.x ** 2) + jnp.sum(tr.error ** 2)

    a, h = 1.5, 1e-5
    g = float(jax.jit(jax.grad(cost))(a))
    f = jax.jit(cost)
    assert g == pytest.approx((float(f(a + h)) - float(f(a - h))) / (2 * h), rel=1e-5)
    if how == "simulate":
        assert float(jax.grad(cost)(a)) == pytest.approx(g, rel=1e-9)


_A0, _C0 = jnp.array([[0.0, 1.0], [-2.0, -0.3]]), jnp.array([[1.0, 0.0]])
_LUEN = obsjax.Luenberger(obsjax.LTI(_A0, C=_C0), L=jnp.array([[3.0], [2.0]]))
_TS4 = jnp.linspace(0.0, 2.0, 5)


@pytest.mark.extended
def test_a_global_that_holds_a_tracer_is_not_served_a_program_of_another_tracer():
    """A plant function reads a global that the loss sets to the parameter, twice per loss with other
    values.  Both solves had one key (a traced value was left out of the content digest), so the second
    ran the program traced with the first tracer: value −12.574 and derivative −0.642 for −11.893 and
    5.364, eagerly and under jit (or an UnexpectedTracerError on a later call).  A traced value now makes
    the key unique."""
    P = {"a": 0.0}
    plant = obsjax.LTV(lambda t: _A0 + P["a"] * jnp.array([[0.0, 0.0], [jnp.sin(t), 0.0]]), lambda t: _C0)

    def loss(a):
        P["a"] = a
        s1 = jnp.sum(obsjax.simulate(plant, _LUEN, jnp.array([1.0, 0.0]), jnp.zeros(2), _TS4, adaptive=False,
                                     dt0=0.01).x[-1])
        P["a"] = 2 * a
        s2 = jnp.sum(obsjax.simulate(plant, _LUEN, jnp.array([1.0, 0.0]), jnp.zeros(2), _TS4, adaptive=False,
                                     dt0=0.01).x[-1])
        return s1 + 10 * s2

    a, h = 0.7, 1e-5
    plain = float(loss(a))
    fd = (float(loss(a + h)) - float(loss(a - h))) / (2 * h)
    for vg in (jax.value_and_grad(loss), jax.jit(jax.value_and_grad(loss))):
        for _ in range(2):  # a second eager call once the first trace has ended
            v, g = vg(a)
            assert float(v) == pytest.approx(plain, rel=1e-12)
            assert float(g) == pytest.approx(fd, rel=1e-6)


@pytest.mark.extended
def test_a_plant_function_that_closes_over_a_traced_integer():
    """An integer traced by jit (or vmap) that the plant function reads, with a gradient in another
    parameter: the zero-gradient guard of rejected steps kept it as a constant of its custom_vjp, and
    jit(grad) failed ("No constant handler for type DynamicJaxprTracer").  Equal to the eager values."""
    def loss(a, n):
        plant = obsjax.LTV(lambda t: _A0 + a * (n % 2 + 1) * jnp.array([[0.0, 0.0], [jnp.sin(t), 0.0]]),
                           lambda t: _C0)
        tr = obsjax.simulate(plant, _LUEN, jnp.array([1.0, 0.0]), jnp.zeros(2), _TS4, rtol=1e-10, atol=1e-12)
        return jnp.sum(tr.error**2) + jnp.sum(tr.x[-1])

    jitted = jax.jit(jax.grad(loss))
    assert float(jitted(0.7, 1)) == pytest.approx(float(jax.grad(loss)(0.7, 1)), rel=1e-10)
    assert float(jitted(0.7, 0)) != pytest.approx(float(jitted(0.7, 1)), rel=1e-3)  # n is read
