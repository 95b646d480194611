"""Lovass-Nagy observers for any observable pair: the design condition solved as a matrix ODE, the
{1}-inverse identities of the slides' background slide (and its two misprints).

Independent references: the defining identities of {1}-inverses and numpy's pinv; the matrix ODE
Ṫ = FT − TA + GC integrated by SciPy's solve_ivp (written here), with Ṫ by central differences for the
solvability condition; the error law z − T x = expm(F t)(z0 − T0 x0) with SciPy's expm; a closed form for a
scalar T that turns singular; central finite differences for gradients.
"""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate as si
import scipy.linalg as sl

import obsjax
from obsjax.design import (
    input_solvability_residual,
    lovass_nagy_T,
    lovass_nagy_T_ode,
    moore_penrose,
    one_inverse,
)

# ---------------------------------------------------------------------------------------------------
# the slides' background slide: AXA = A (printed "XAX = A") and (I − BB^{1}) (printed "(I − B^{1}B)")
# ---------------------------------------------------------------------------------------------------


def test_one_inverse_identity_holds_and_the_printed_one_does_not():
    rng = np.random.default_rng(4)
    for m, n, r in [(2, 3, 1), (3, 3, 2), (4, 2, 2)]:
        C = rng.normal(size=(m, r)) @ rng.normal(size=(r, n))
        X = np.asarray(one_inverse(C, Y=rng.normal(size=(n, m)), Z=rng.normal(size=(n, m))))
        np.testing.assert_allclose(C @ X @ C, C, atol=1e-10)  # A X A = A
    # the slides' own example: C^{1} = C⁺ = [[0, 0], [.5, .5]] satisfies CXC = C but not the printed XCX = C
    C = np.array([[0.0, 1.0], [0.0, 1.0]])
    X = np.asarray(moore_penrose(C))
    np.testing.assert_allclose(C @ X @ C, C, atol=1e-15)
    assert np.abs(X @ C @ X - C).max() > 0.4  # X C X = X (a {2}-inverse property), not C
    # for a non-square matrix the printed identity is not even defined
    C23 = np.ones((2, 3))
    X32 = np.asarray(moore_penrose(C23))
    with pytest.raises(ValueError):
        np.asarray(X32 @ C23 @ X32) - C23


def test_input_solvability_uses_B_B1_not_B1_B():
    rng = np.random.default_rng(1)
    B = rng.normal(size=(3, 1))
    v_in = B @ np.array([2.5])
    v_out = v_in + np.cross(B[:, 0], rng.normal(size=3))  # off range(B)
    np.testing.assert_allclose(input_solvability_residual(B, v_in), 0.0, atol=1e-13)
    u = np.linalg.pinv(B) @ v_in
    np.testing.assert_allclose(B @ u, v_in, atol=1e-13)  # u = B^{1} v solves B u = v
    r = np.asarray(input_solvability_residual(B, v_out))
    assert np.linalg.norm(r) > 0.1
    # the residual is the least-squares misfit of B u = v: no input reproduces v_out
    u_ls = np.linalg.lstsq(B, v_out, rcond=None)[0]
    np.testing.assert_allclose(np.linalg.norm(B @ u_ls - v_out), np.linalg.norm(r), rtol=1e-12)
    # zero-ness does not depend on the {1}-inverse (B X is a projector onto range B for every X)
    for _ in range(3):
        X = np.asarray(one_inverse(B, Y=rng.normal(size=(3, 1)).T, Z=rng.normal(size=(1, 3))))
        np.testing.assert_allclose(
            np.asarray(input_solvability_residual(B, v_in, X)), 0.0, atol=1e-12
        )
        assert np.linalg.norm(np.asarray(input_solvability_residual(B, v_out, X))) > 1e-3
    # the printed (I − B^{1}B) v: (1 × 1) times a 3-vector is undefined ...
    with pytest.raises(ValueError):
        (np.eye(1) - np.linalg.pinv(B) @ B) @ v_out
    # ... and for a square singular B it accepts a v that no input produces
    Bs = np.array([[1.0, 0.0], [1.0, 0.0]])
    v = np.array([1.0, 0.0])  # range(Bs) = span{(1, 1)}: v is not reachable
    np.testing.assert_allclose((np.eye(2) - np.linalg.pinv(Bs) @ Bs) @ v, 0.0, atol=1e-15)
    np.testing.assert_allclose(input_solvability_residual(Bs, v), [0.5, -0.5], atol=1e-15)


def test_input_solvability_bad_shape():
    with pytest.raises(ValueError, match="`v` must have shape"):
        input_solvability_residual(np.ones((3, 1)), np.ones(2))


# ---------------------------------------------------------------------------------------------------
# plants of our own: 3 states / 1 output and 4 states / 2 outputs, both with time-varying A and C
# ---------------------------------------------------------------------------------------------------


def A3(t):
    return jnp.array(
        [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0 - 0.5 * jnp.sin(t), -2.0 - jnp.sin(0.7 * t), -1.0]]
    )


def C3(t):
    return jnp.array([[1.0, 0.2 * jnp.cos(t), 0.0]])


def B3(t):
    return jnp.array([[0.0], [0.0], [1.0]])


F3 = jnp.array(
    [[-3.0, 1.0, 0.0], [0.0, -4.0, 1.0], [0.0, 0.0, -5.0]]
)  # upper triangular, free entries 1
G3 = jnp.ones((3, 1))


def A4(t):
    return jnp.array(
        [
            [0.0, 1.0, 0.0, 0.0],
            [-2.0 - 0.5 * jnp.sin(t), -0.3, 0.4, 0.0],
            [0.0, 0.0, 0.0, 1.0],
            [0.3, 0.0, -1.0 - 0.3 * jnp.cos(t), -0.2],
        ]
    )


def C4(t):
    return jnp.array([[1.0, 0.0, 0.1 * jnp.sin(t), 0.0], [0.0, 0.0, 1.0, 0.0]])


def B4(t):
    return jnp.array([[0.0], [1.0], [0.0], [0.5]])


F4 = jnp.diag(jnp.array([-3.0, -4.0, -5.0, -6.0])).at[0, 1].set(0.5)
G4 = jnp.array([[1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [1.0, -1.0]])

PLANTS = {3: (A3, C3, B3, F3, G3), 4: (A4, C4, B4, F4, G4)}
TS = jnp.linspace(0.0, 6.0, 61)


def u_in(t):
    return jnp.array([jnp.sin(2.0 * t) + 0.3])


def scipy_T(A, C, F, G, T0, ts):
    """Ṫ = F T − T A + G C by SciPy (numpy callables), dense output."""
    A_, C_ = (lambda t: np.asarray(A(t))), (lambda t: np.asarray(C(t)))
    F_, G_ = np.asarray(F), np.asarray(G)
    n = F_.shape[0]

    def rhs(t, v):
        T = v.reshape(n, n)
        return (F_ @ T - T @ A_(t) + G_ @ C_(t)).ravel()

    return si.solve_ivp(
        rhs,
        (ts[0], ts[-1]),
        np.asarray(T0).ravel(),
        rtol=1e-12,
        atol=1e-13,
        method="DOP853",
        dense_output=True,
    )


def test_algebraic_completion_fails_for_3_states_1_output():
    """The reason for the ODE route: rank((I − NNᵀ) A N) = 1 < dim null C = 2."""
    with pytest.raises(ValueError, match="full column rank 2"):
        lovass_nagy_T(A3, jnp.array([[1.0, 0.0, 0.0]]), F3, lambda t: jnp.ones((3, 2)))


@pytest.mark.parametrize("n", [3, 4])
@pytest.mark.extended
def test_T_ode_matches_scipy_and_satisfies_the_solvability_condition(n):
    A, C, _, F, G = PLANTS[n]
    ts = np.linspace(0.0, 4.0, 41)
    flow = lovass_nagy_T_ode(A, C, F, G, ts)
    sol = scipy_T(A, C, F, G, flow.T[0], ts)
    Ts = np.stack([sol.sol(t).reshape(n, n) for t in ts])
    np.testing.assert_allclose(flow.T, Ts, atol=1e-8 * np.abs(Ts).max())
    # T(0) is the frozen Sylvester solution T A(0) − F T = G C(0)
    T0 = Ts[0]
    np.testing.assert_allclose(T0 @ A(0.0) - F @ T0, G @ C(0.0), atol=1e-10)
    # the slides' condition (Ṫ + T A − F T)(I − C⁺C) = 0 with Ṫ by central differences of SciPy's T
    h = 1e-4
    for t in (0.7, 2.3, 3.9):
        Td = (sol.sol(t + h) - sol.sol(t - h)).reshape(n, n) / (2 * h)
        T = sol.sol(t).reshape(n, n)
        M = Td + T @ np.asarray(A(t)) - np.asarray(F) @ T
        Cn = np.asarray(C(t))
        P = np.eye(n) - np.linalg.pinv(Cn) @ Cn
        assert np.abs(M @ P).max() < 1e-6 * np.abs(M).max()
        assert np.abs(M).max() > 1e-2  # not trivially zero
    assert float(flow.rcond.min()) > 1e-3


@functools.cache
def _runner(n):
    A, C, B, _F, _G = PLANTS[n]
    plant = obsjax.LTV(A, C, B)

    @eqx.filter_jit
    def run(obs, x0, xhat0):
        return obsjax.simulate(plant, obs, x0, xhat0, TS, u=u_in, rtol=1e-11, atol=1e-12)

    return plant, run


@pytest.mark.parametrize("n", [3, 4])
@pytest.mark.extended
def test_error_law_z_minus_Tx_is_exp_Ft(n):
    """The defining property (7): z − T x = e^{F(t−t0)}(z0 − T0 x0), to 1e-8, and x̂ → x."""
    A, C, _B, F, G = PLANTS[n]
    plant, run = _runner(n)
    obs = obsjax.GeneralizedInverseODE(plant, F, G, horizon=(0.0, 6.0))
    x0 = jnp.linspace(1.0, -1.0, n)
    tr = run(obs, x0, jnp.zeros(n))
    z, T = tr.z
    e = np.asarray(z - jnp.einsum("tij,tj->ti", T, tr.x))
    e0 = e[0]
    pred = np.stack([sl.expm(np.asarray(F) * float(t)) @ e0 for t in TS])
    assert np.abs(e0).max() > 0.1
    np.testing.assert_allclose(e, pred, atol=1e-8)
    # T in the observer state is the solution of the matrix ODE (SciPy)
    sol = scipy_T(A, C, F, G, T[0], np.asarray(TS))
    np.testing.assert_allclose(T[-1], sol.sol(6.0).reshape(n, n), atol=1e-8 * np.abs(T).max())
    assert float(tr.error_norm[-1]) < 1e-8 * float(tr.error_norm[0]) * 1e3
    assert float(tr.error_norm[-1]) < 1e-6


@pytest.mark.extended
def test_singular_T_is_refused_and_named():
    """Scalar case: Ṫ = −T + 1 from T0 = −1 gives T = 1 − 2e^{−t}, singular at t = ln 2."""
    plant = obsjax.LTV(lambda t: jnp.zeros((1, 1)), lambda t: jnp.ones((1, 1)))
    with pytest.raises(ValueError, match=r"changes sign between t = 0\.69 and t = 0\.7"):
        obsjax.GeneralizedInverseODE(plant, [[-1.0]], [[1.0]], T0=[[-1.0]], horizon=(0.0, 2.0))
    with pytest.raises(ValueError, match=r"σ_min\(T\)/σ_max\(T\) = 0.000e\+00 .* at t = 0\b"):
        lovass_nagy_T_ode(
            A3, C3, F3, G3, np.linspace(0, 1, 5), T0=jnp.zeros((3, 3)).at[0, 0].set(1.0)
        )
    # the same with T0 = +1 stays invertible
    obsjax.GeneralizedInverseODE(plant, [[-1.0]], [[1.0]], T0=[[1.0]], horizon=(0.0, 2.0))


def test_bad_inputs():
    plant = obsjax.LTV(A3, C3, B3)
    with pytest.raises(ValueError, match="left half-plane"):
        obsjax.GeneralizedInverseODE(plant, jnp.eye(3), G3)
    with pytest.raises(ValueError, match=r"`G` must have shape \(3, 1\)"):
        obsjax.GeneralizedInverseODE(plant, F3, jnp.ones((3, 2)))
    with pytest.raises(ValueError, match=r"`T0` must have shape \(3, 3\)"):
        obsjax.GeneralizedInverseODE(plant, F3, G3, T0=jnp.eye(2))
    with pytest.raises(ValueError, match=r"`G\(t\)` must return shape \(3, 1\)"):
        obsjax.GeneralizedInverseODE(plant, F3, lambda t: jnp.ones((1, 3)))


@pytest.mark.extended
def test_gradient_wrt_G_and_F_matches_finite_differences():
    """d/dG and d/dF (entry above the diagonal, a free entry of step 1) of Σ‖x̂ − x‖² through simulate."""
    plant = obsjax.LTV(A3, C3, B3)
    ts = jnp.linspace(0.0, 2.0, 21)
    x0 = jnp.array([1.0, -0.5, 0.3])

    T0 = obsjax.design.frozen_T0(
        A3(0.0), C3(0.0), F3, G3
    )  # fixed: x̂ = T⁻¹z is invariant to scaling G

    @jax.jit
    def loss(g, f01):
        obs = obsjax.GeneralizedInverseODE(plant, F3.at[0, 1].set(f01), g, T0=T0)
        tr = obsjax.simulate(
            plant,
            obs,
            x0,
            jnp.zeros(3),
            ts,
            u=u_in,
            solver=diffrax.Heun(),
            dt0=0.01,
            adaptive=False,
        )
        return jnp.sum(tr.error**2)

    g0, f0 = jnp.array([[1.3], [0.6], [-0.4]]), 1.0
    dg, df = jax.grad(loss, argnums=(0, 1))(g0, f0)
    h = 1e-5
    for i in range(3):
        e = jnp.zeros((3, 1)).at[i, 0].set(h)
        fd = (loss(g0 + e, f0) - loss(g0 - e, f0)) / (2 * h)
        np.testing.assert_allclose(dg[i, 0], fd, rtol=1e-5, atol=1e-6 * float(jnp.abs(dg).max()))
    fd = (loss(g0, f0 + h) - loss(g0, f0 - h)) / (2 * h)
    np.testing.assert_allclose(df, fd, rtol=1e-5, atol=1e-9)
    assert abs(float(df)) > 1e-4 and float(jnp.abs(dg).max()) > 1e-3


def test_equilibrated_rcond_is_invariant_to_the_state_units_and_zero_when_singular():
    from obsjax.design._ginverse import equilibrated_rcond

    rng = np.random.default_rng(4)
    T = rng.normal(size=(4, 4))
    r0 = float(equilibrated_rcond(T))
    for S in ([1e-4, 1.0, 1e4, 3.0], [1e6, 1e-6, 1.0, 1.0]):
        np.testing.assert_allclose(float(equilibrated_rcond(T / np.asarray(S)[None, :])), r0, rtol=1e-10)
        np.testing.assert_allclose(float(equilibrated_rcond(7.5 * T / np.asarray(S)[None, :])), r0, rtol=1e-10)
    sv = np.linalg.svd(T, compute_uv=False)
    assert r0 > 0 and abs(np.log10(r0 / (sv[-1] / sv[0]))) < 2  # the same order as the plain ratio here
    assert float(equilibrated_rcond(np.array([[1.0, 2.0], [2.0, 4.0]]))) < 1e-15
    np.testing.assert_allclose(equilibrated_rcond(np.stack([T, 2 * T])), [r0, r0], rtol=1e-12)  # batched


@pytest.mark.extended
def test_invertibility_verdict_does_not_depend_on_the_state_units():
    """σ_min/σ_max of T changes with the units of the state (T → T S⁻¹): in units 1e-4, 1, 1e4 a design with
    rcond 6e-3 read 1.5e-11 and was refused.  The test equilibrates T first; a singular T still reads 0."""
    from obsjax.design import lovass_nagy_T_ode

    A0 = lambda t: jnp.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -2.0 - jnp.sin(t), -1.0]])
    C0, F, G = np.array([[1.0, 0.0, 0.0]]), np.diag([-4.0, -5.0, -6.0]), np.ones((3, 1))
    ts = jnp.linspace(0.0, 5.0, 11)
    mins = []
    for S in ([1.0, 1.0, 1.0], [1e-4, 1.0, 1e4], [1e6, 1.0, 1e-6]):
        S = np.asarray(S)
        A = lambda t, S=S: jnp.asarray(S)[:, None] * A0(t) / jnp.asarray(S)[None, :]
        flow = lovass_nagy_T_ode(A, jnp.asarray(C0 / S[None, :]), jnp.asarray(F), jnp.asarray(G), ts)
        mins.append(float(np.min(flow.rcond)))
    np.testing.assert_allclose(mins, mins[0], rtol=1e-6)
    assert mins[0] > 1e-3
