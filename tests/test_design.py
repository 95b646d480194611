"""Pole placement, Sylvester equations and observability indices against independent references."""

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

import obsjax
from obsjax.design import observability_indices, place, sylvester

A28 = np.array([[-2.0, 1.0], [0.0, -1.0]])
B28 = np.array([[0.0], [1.0]])
C28 = np.array([[1.0, 0.0]])


def test_example_2_8_gain():
    """Thesis example (2.8): poles {-3, -3} give G = [3, 4] and A - GC = [[-5, 1], [-4, -1]]."""
    L = place(A28, C28, [-3.0, -3.0])
    np.testing.assert_allclose(L, [[3.0], [4.0]], atol=1e-12)
    np.testing.assert_allclose(A28 - L @ C28, [[-5.0, 1.0], [-4.0, -1.0]], atol=1e-12)


def test_reduced_order_example_gain():
    """Reduced-order observer of (2.8) with pole -3: G = 2 (A22 - G A12 = -1 - G)."""
    obs = obsjax.ReducedOrder.from_poles(obsjax.LTI(A28, B28, C28), [-3.0])
    np.testing.assert_allclose(obs.gain, [[2.0]], atol=1e-12)


def test_sylvester_section_3_2():
    """Thesis (3.3): T [[-2, 1], [0, -2]] + 3 T = [1, 0] gives T = [1, -1]."""
    T = sylvester([[-2.0, 1.0], [0.0, -2.0]], [[-3.0]], [[1.0, 0.0]])
    np.testing.assert_allclose(T, [[1.0, -1.0]], atol=1e-12)


def test_sylvester_against_scipy():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((4, 4))
    F = rng.standard_normal((3, 3)) - 5 * np.eye(3)
    H = rng.standard_normal((3, 4))
    T = np.asarray(sylvester(A, F, H))
    # T A - F T = H  <=>  (-F) T + T A = H
    np.testing.assert_allclose(T, scipy.linalg.solve_sylvester(-F, A, H), rtol=1e-10, atol=1e-12)


def _random_system(seed, n, m):
    rng = np.random.default_rng(seed)
    return rng.standard_normal((n, n)), rng.standard_normal((m, n))


def _poles(seed, n):
    rng = np.random.default_rng(seed + 7)
    poles = []
    while len(poles) < n:
        if n - len(poles) >= 2 and rng.random() < 0.4:
            re, im = -rng.uniform(0.5, 4.0), rng.uniform(0.2, 3.0)
            poles += [re + 1j * im, re - 1j * im]
        else:
            poles.append(-rng.uniform(0.5, 4.0))
    return np.array(poles)


def _match(a, b):
    """Max relative distance between two multisets of eigenvalues (greedy matching)."""
    b = list(b)
    worst = 0.0
    for x in a:
        d = [abs(x - y) for y in b]
        k = int(np.argmin(d))
        worst = max(worst, d[k] / max(1.0, abs(x)))
        b.pop(k)
    return worst


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), n=st.integers(1, 5), m=st.integers(1, 3))
def test_place_random_systems_property_and_control(seed, n, m):
    """eig(A - LC) = requested poles on random observable systems, and python-control agrees."""
    m = min(m, n)
    A, C = _random_system(seed, n, m)
    O = np.asarray(obsjax.analysis.obsv(A, C))
    assume(np.linalg.cond(O[: max(n, 1) * m]) < 1e5)
    poles = _poles(seed, n)
    assume(np.min(np.abs(poles[:, None] - poles[None, :]) + 10 * np.eye(n)) > 0.1)
    L = np.asarray(place(A, C, poles))
    assert L.shape == (n, m) and np.isrealobj(L)
    eig = np.linalg.eigvals(A - L @ C)
    # conditioning of the closed-loop eigenproblem decides what "match" can mean
    _, V = np.linalg.eig(A - L @ C)
    kappa = np.linalg.cond(V)
    assume(kappa < 1e4)
    assert _match(eig, poles) < 1e-8 * kappa
    K = control.place(A.T, C.T, poles)
    eig_ctrl = np.linalg.eigvals(A - K.T @ C)
    assert _match(eig, eig_ctrl) < 1e-6 * kappa


def test_place_mimo_repeated_eigenvalues_non_cyclic():
    """A = 0 (non-cyclic) with two outputs still gets its poles (the cyclic pre-gain at work)."""
    A = np.zeros((2, 2))
    C = np.eye(2)
    L = np.asarray(place(A, C, [-1.0, -2.0]))
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(A - L @ C).real), [-2.0, -1.0], atol=1e-10)


@pytest.mark.parametrize("m", [1, 2])
def test_place_gradient_matches_finite_differences(m):
    A, C = _random_system(3, 3, m)
    poles = jnp.array([-1.0, -2.0, -3.5])
    red = obsjax.design.choose_reduction(A, C)
    w = jnp.asarray(np.random.default_rng(1).standard_normal((3, m)))

    def f(A, C, poles):
        return jnp.sum(w * place(A, C, poles, reduction=red))

    gA, gC, gp = jax.grad(f, argnums=(0, 1, 2))(jnp.asarray(A), jnp.asarray(C), poles)
    h = 1e-6
    for arg, g in ((0, gA), (1, gC), (2, gp)):
        base = [jnp.asarray(A), jnp.asarray(C), poles]
        flat = np.asarray(base[arg]).ravel()
        fd = np.zeros_like(flat)
        for i in range(flat.size):
            up, dn = flat.copy(), flat.copy()
            up[i] += h
            dn[i] -= h
            bu, bd = list(base), list(base)
            bu[arg] = jnp.asarray(up.reshape(base[arg].shape))
            bd[arg] = jnp.asarray(dn.reshape(base[arg].shape))
            fd[i] = (f(*bu) - f(*bd)) / (2 * h)
        np.testing.assert_allclose(np.asarray(g).ravel(), fd, rtol=1e-5, atol=1e-6)


def test_observability_indices_example_and_definition():
    A = np.array([[-2, 1, 0, 0], [0, -2, 1, 0], [0, 0, -1, 1], [1, 0, 0, -3.0]])
    C = np.array([[1, 0, 0, 0], [0, 0, 1, 0.0]])
    assert observability_indices(A, C) == (2, 2)
    rng = np.random.default_rng(5)
    for _ in range(20):
        n, m = rng.integers(2, 7), rng.integers(1, 4)
        A, C = rng.standard_normal((n, n)), rng.standard_normal((m, n))
        nu = observability_indices(A, C)
        assert sum(nu) == n
        # independent definition: the observability index is the least k with rank [C; CA; ...; CA^{k-1}] = n
        O = np.asarray(obsjax.analysis.obsv(A, C))
        k = next(k for k in range(1, n + 1) if np.linalg.matrix_rank(O[: k * m]) == n)
        assert max(nu) == k


# ---------------------------------------------------------------- bad input: one test per ValueError
def test_place_unobservable_pair():
    with pytest.raises(ValueError, match="not observable"):
        place([[1.0, 0.0], [0.0, 2.0]], [[1.0, 0.0]], [-1.0, -2.0])


def test_place_wrong_number_of_poles():
    with pytest.raises(ValueError, match="exactly n = 2"):
        place(A28, C28, [-1.0, -2.0, -3.0])


def test_place_complex_without_conjugate():
    with pytest.raises(ValueError, match="conjugat"):
        place(A28, C28, [-1.0 + 1j, -2.0])


def test_place_nonsquare_A():
    with pytest.raises(ValueError, match="`A` must be a square"):
        place(np.ones((2, 3)), C28, [-1.0, -2.0])


def test_place_C_wrong_columns():
    with pytest.raises(ValueError, match="`C` must have shape"):
        place(A28, np.ones((1, 3)), [-1.0, -2.0])


def test_sylvester_common_eigenvalue():
    with pytest.raises(ValueError, match="share an eigenvalue"):
        sylvester(A28, [[-2.0]], [[1.0, 0.0]])


def test_observability_indices_unobservable():
    with pytest.raises(ValueError, match="not observable"):
        observability_indices([[1.0, 0.0], [0.0, 2.0]], [[1.0, 0.0]])
