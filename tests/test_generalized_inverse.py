"""Lovass-Nagy {1}-inverses, T(t) design and generalized-inverse observers (slides 002).

Independent references: the defining property CXC = C and numpy's pinv; the closed form T = [S, βṠ/4]
of the slides' example (derived by hand); finite-difference Ṫ for the design condition; the exact error
law z − T w = expm(F t)(z0 − T0 w0) checked on a diffrax simulation of plant and observer written here
(and by obsjax.simulate) with scipy.linalg.expm; central finite differences for gradients.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import obsjax
from obsjax import LTV
from obsjax.design import lovass_nagy_T, moore_penrose, one_inverse, solvability_residual


# --- the slides' 4th-order example, transcribed independently ---------------------------------------
def alpha(t):
    return -0.4 * jnp.exp(jnp.sin(0.3 * t) - 0.5)


def beta(t):
    return 0.4 * jnp.cos(0.3 * t) - 0.5


def A_ex(t):
    return jnp.array(
        [
            [-10.0, -10.0 * alpha(t), 0.0, 1.0],
            [1.0, 0.0, 0.0, 1.0],
            [0.0, -1.0, -5.0, 0.0],
            [0.0, 0.0, -4.0 / beta(t), 0.0],
        ]
    )


B_ex = jnp.array([[1.0], [0.0], [0.0], [1.0]])
A12 = jnp.array([[0.0, 1.0], [0.0, 1.0]])
C1_slides = jnp.array([[0.0, 0.0], [0.5, 0.5]])
F5 = -5.0 * jnp.eye(2)


def S_ex(t):
    return jnp.stack([jnp.cos(t), jnp.sin(t)])


def reduced_plant():
    return LTV(
        lambda t: A_ex(t), lambda t: jnp.hstack([jnp.eye(2), jnp.zeros((2, 2))]), lambda t: B_ex
    )


def u_sin(t):
    return jnp.array([jnp.sin(2.0 * t)])


def simulate_pair(plant, vf_obs, x0, z0, ts, u, *, rtol=1e-10, atol=1e-12, dt=None):
    """Plant and observer integrated together (independent of obsjax.simulate)."""

    def vf(t, s, args):
        x, z = s
        uu = u(t)
        y = plant.h(t, x, uu)
        return plant.f(t, x, uu), vf_obs(t, z, y, uu)

    if dt is None:
        ctrl, dt0 = diffrax.PIDController(rtol=rtol, atol=atol), 1e-2
    else:
        ctrl, dt0 = diffrax.ConstantStepSize(), dt
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vf),
        diffrax.Tsit5(),
        ts[0],
        ts[-1],
        dt0,
        (x0, z0),
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=ctrl,
        max_steps=100_000,
    )
    return sol.ys


# --- {1}-inverses -----------------------------------------------------------------------------------
def test_moore_penrose_is_the_slides_choice_and_numpy_pinv():
    assert np.allclose(moore_penrose(A12), C1_slides)
    C = np.random.default_rng(0).normal(size=(3, 5))
    assert np.allclose(moore_penrose(C), np.linalg.pinv(C))


@pytest.mark.parametrize("shape,rank", [((2, 2), 1), ((3, 5), 2), ((4, 3), 3)])
def test_one_inverse_family(shape, rank):
    rng = np.random.default_rng(1)
    m, n = shape
    C = rng.normal(size=(m, rank)) @ rng.normal(size=(rank, n))
    for _ in range(3):
        Y, Z = rng.normal(size=(n, m)), rng.normal(size=(n, m))
        X = np.asarray(one_inverse(C, Y, Z))
        assert np.allclose(C @ X @ C, C, atol=1e-10)
        assert obsjax.design.is_one_inverse(X, C)
    # The family contains every {1}-inverse: recover a given one (Y = X − C⁺, Z = C⁺C(X − C⁺)).
    Cp = np.linalg.pinv(C)
    Xg = np.asarray(one_inverse(C, rng.normal(size=(n, m)), rng.normal(size=(n, m))))
    D = Xg - Cp
    assert np.allclose(one_inverse(C, D, Cp @ C @ D), Xg, atol=1e-10)
    if rank < min(m, n):
        assert not obsjax.design.is_one_inverse(rng.normal(size=(n, m)), C)


@pytest.mark.parametrize("scale", [1.0, 1e-6, 1e-10, 1e8])
def test_is_one_inverse_is_relative_to_C(scale):
    """The test was ‖CXC − C‖ ≤ rtol·max(1, ‖C‖): for C ~ 1e-10 (a sensor in other units) X = 0 passed
    with a 100 % relative residual.  Relative now: the {1}-inverses of s C are X / s at any scale."""
    C = scale * np.array([[1.0, 0.0, 2.0], [0.0, 1.0, 1.0]])
    assert not obsjax.design.is_one_inverse(np.zeros((3, 2)), C)
    assert obsjax.design.is_one_inverse(np.linalg.pinv(C), C)
    X = np.asarray(one_inverse(C, np.ones((3, 2)) / scale, np.ones((3, 2)) / scale))
    assert obsjax.design.is_one_inverse(X, C)
    assert not obsjax.design.is_one_inverse(X + 1e-3 / scale, C)
    assert obsjax.design.is_one_inverse(np.ones((3, 2)), np.zeros((2, 3)))  # every X, for C = 0


def test_solvability_residual_does_not_depend_on_the_one_inverse():
    """I − XC projects onto null(C) for every {1}-inverse X: solvability of GC = M is choice-free; the
    solution G = M X does depend on X, but all of them satisfy G C = M."""
    rng = np.random.default_rng(2)
    C = np.array([[0.0, 1.0], [0.0, 1.0]])
    M_good = rng.normal(size=(2, 1)) @ np.array([[0.0, 1.0]])  # rows in the row space of C
    M_bad = rng.normal(size=(2, 2))
    Gs = []
    for Y, Z in [(None, None), (rng.normal(size=(2, 2)), rng.normal(size=(2, 2)))]:
        X = one_inverse(C, Y, Z)
        assert np.allclose(solvability_residual(M_good, C, X), 0.0, atol=1e-12)
        assert np.linalg.norm(solvability_residual(M_bad, C, X)) > 1e-3
        G = M_good @ np.asarray(X)
        assert np.allclose(G @ C, M_good, atol=1e-12)
        Gs.append(G)
    assert np.linalg.norm(Gs[0] - Gs[1]) > 1e-3


def test_one_inverse_bad_shapes():
    with pytest.raises(ValueError, match="`Y` must have shape"):
        one_inverse(A12, Y=jnp.ones((3, 2)))


def test_one_inverse_bad_Z_shape():
    with pytest.raises(ValueError, match="`Z` must have shape"):
        one_inverse(A12, Z=jnp.ones((2, 3)))


# --- design of T -------------------------------------------------------------------------------------
def test_lovass_nagy_T_closed_form_for_the_slides_example():
    """By hand: with N = e1 and F = −5I the condition reads Ṫ_i1 = (4/β) T_i2, so T = [S, β Ṡ / 4]."""
    T = lovass_nagy_T(lambda t: A_ex(t)[2:, 2:], A12, F5, S_ex)
    for t in [0.0, 0.7, 3.1]:
        Sd = np.array([-np.sin(t), np.cos(t)])
        expected = np.column_stack([S_ex(t), float(beta(t)) / 4 * Sd])
        assert np.allclose(T(t), expected, atol=1e-12)


def test_lovass_nagy_T_condition_with_finite_difference_derivative():
    """M (I − C⁺C) = 0 with Ṫ from central differences (not the autodiff used inside)."""
    F = jnp.array([[-3.0, 1.0], [0.0, -4.0]])
    T = lovass_nagy_T(
        lambda t: A_ex(t)[2:, 2:], A12, F, lambda t: jnp.stack([1.0 + 0.2 * t, jnp.sin(t)])
    )
    h = 1e-5
    for t in [0.2, 1.3, 4.0]:
        Td = (np.asarray(T(t + h)) - np.asarray(T(t - h))) / (2 * h)
        M = Td + np.asarray(T(t)) @ np.asarray(A_ex(t)[2:, 2:]) - np.asarray(F) @ np.asarray(T(t))
        assert np.linalg.norm(solvability_residual(M, A12)) < 1e-7 * np.linalg.norm(M)
        assert np.linalg.norm(M) > 1e-2  # not trivially zero


def test_lovass_nagy_T_rank_deficient_K():
    """Full-state design with y = [x1, x2]: K = (I − NNᵀ) A N = A12 block has rank 1 < 2."""
    with pytest.raises(ValueError, match="K = .* full column rank 2"):
        lovass_nagy_T(
            A_ex,
            jnp.hstack([jnp.eye(2), jnp.zeros((2, 2))]),
            -jnp.eye(4),
            lambda t: jnp.ones((4, 2)),
        )


def test_lovass_nagy_T_bad_S_shape():
    with pytest.raises(ValueError, match=r"`S\(t\)` must return"):
        lovass_nagy_T(lambda t: A_ex(t)[2:, 2:], A12, F5, lambda t: jnp.ones((2, 2)))


# --- reduced-order observer ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def reduced_run():
    plant = reduced_plant()
    T = lovass_nagy_T(lambda t: A_ex(t)[2:, 2:], A12, F5, S_ex)
    obs = obsjax.GeneralizedInverseReduced(plant, F5, T, C1=C1_slides, horizon=(0.0, 5.0))
    x0 = jnp.array([-1.0, 2.0, -1.0, 2.0])  # y0 = [-1, 2], w0 = [-1, 2]
    z0 = jnp.array([2.0, -1.0])
    ts = jnp.linspace(0.0, 5.0, 51)
    # the slides give z0: choose x̂0 = [y0; T(0)⁻¹ z0] so that init gives z(0) = z0
    xhat0 = jnp.concatenate([x0[:2], jnp.linalg.solve(obs.T_of(0.0), z0)])
    sim = eqx.filter_jit(
        lambda o, x0, xh0: obsjax.simulate(plant, o, x0, xh0, ts, u=u_sin, rtol=1e-10, atol=1e-12)
    )
    traj = sim(obs, x0, xhat0)
    assert np.allclose(obs.z_of(0.0, traj.z[0], traj.y[0]), z0)
    return plant, obs, ts, traj.x, traj.z, z0, traj


@pytest.mark.extended
def test_reduced_defining_property_exact(reduced_run):
    """z − T w = expm(F t)(z0 − T0 w0) (with F = −5I: e^{−5t}), to solver tolerance, under an input."""
    _plant, obs, ts, xs, ps, z0, _traj = reduced_run
    zs = jax.jit(jax.vmap(obs.z_of))(ts, ps, xs[:, :2])
    Ts = jax.jit(jax.vmap(obs.T_of))(ts)
    e = np.asarray(zs - jnp.einsum("tij,tj->ti", Ts, xs[:, 2:]))
    e0 = np.asarray(z0 - obs.T_of(0.0) @ xs[0, 2:])
    pred = np.stack([scipy.linalg.expm(np.asarray(F5) * float(t)) @ e0 for t in ts])
    assert np.abs(e - pred).max() < 1e-7 * np.abs(e0).max()
    assert np.abs(e0).max() > 1.0


def test_reduced_reproduces_slides_convergence(reduced_run):
    """Slides: 'the simulation is run for 5 unit time and convergence is observed after 2.5'."""
    _plant, obs, ts, xs, ps, _z0, traj = reduced_run
    xhat = jax.jit(jax.vmap(obs.estimate))(ts, ps, xs[:, :2])
    assert np.allclose(traj.xhat, xhat)
    err = np.linalg.norm(np.asarray(traj.error), axis=1)
    assert np.allclose(xhat[:, :2], xs[:, :2])
    i25 = int(np.argmin(np.abs(np.asarray(ts) - 2.5)))
    assert err[0] > 10.0
    assert err[i25] < 1e-3 * err[0]
    assert np.all(err[i25:] < 1e-3 * err[0])


@pytest.mark.extended
def test_reduced_p_form_equals_form_with_ydot(reduced_run):
    """The differentiation-free p-form (run by obsjax.simulate) and ż = Fz + G(ẏ − A11y − B1u) + TA21y +
    TB2u with the plant's true ẏ (run by the harness here) give the same z."""
    plant, obs, ts, xs, ps, z0, _traj = reduced_run

    def vf_z(t, z, y, u, x):
        A11, _A12, A21, _A22, B1, B2 = obs.blocks(t)
        ydot = (plant.f(t, x, u))[:2]
        return (
            obs.F @ z + obs.G_of(t) @ (ydot - A11 @ y - B1 @ u) + obs.T_of(t) @ (A21 @ y + B2 @ u)
        )

    def vf(t, s, args):
        x, z = s
        uu = u_sin(t)
        return plant.f(t, x, uu), vf_z(t, z, x[:2], uu, x)

    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vf),
        diffrax.Tsit5(),
        0.0,
        5.0,
        1e-2,
        (xs[0], z0),
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-12),
    )
    zs = jax.jit(jax.vmap(obs.z_of))(ts, ps, xs[:, :2])
    assert np.abs(np.asarray(sol.ys[1] - zs)).max() < 1e-7


@pytest.mark.extended
def test_slides_reduced_form_violates_the_property(reduced_run):
    """The slides' final form (G from their (12) with the T·A21·C term, no T·A21·y, no Ġ·y) leaves a
    persistent bias in z − T w: the derivation matters for time-varying T."""
    plant, obs, ts, xs, _ps, z0, _traj = reduced_run

    def G_slides(t):
        _A11, A12_, A21, A22, _B1, _B2 = obs.blocks(t)
        T = obs.T_of(t)
        M = obs.Tdot_of(t) + T @ A22 + T @ A21 @ A12_ - obs.F @ T
        return M @ C1_slides

    def vf_slides(t, p, y, u):
        A11, _A12, _A21, _A22, B1, B2 = obs.blocks(t)
        G = G_slides(t)
        return obs.F @ (p + G @ y) - G @ A11 @ y - G @ B1 @ u + obs.T_of(t) @ B2 @ u

    p0 = z0 - G_slides(0.0) @ xs[0, :2]
    xs2, ps2 = simulate_pair(plant, vf_slides, xs[0], p0, ts, u_sin, rtol=1e-8, atol=1e-10)
    zs = ps2 + jnp.einsum("tij,tj->ti", jax.jit(jax.vmap(G_slides))(ts), xs2[:, :2])
    e = zs - jnp.einsum("tij,tj->ti", jax.jit(jax.vmap(obs.T_of))(ts), xs2[:, 2:])
    assert np.abs(np.asarray(e[-10:])).max() > 1e-2  # does not decay like e^{-5t} (≈ 1e-11 here)


# --- full-state observer ------------------------------------------------------------------------------
C_full = jnp.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])  # y = [x1, x3]
F_full = jnp.diag(jnp.array([-3.0, -4.0, -5.0, -6.0]))


def S_full(t):
    return jnp.array([[1.0, 0.0], [1.0, 0.2 * jnp.sin(t)], [0.0, 1.0], [0.3 * jnp.cos(t), 1.0]])


@pytest.mark.extended
def test_full_state_defining_property_and_convergence():
    plant = LTV(A_ex, lambda t: C_full, lambda t: B_ex)
    T = lovass_nagy_T(A_ex, C_full, F_full, S_full)
    obs = obsjax.GeneralizedInverse(plant, F_full, T, horizon=(0.0, 3.0))
    x0 = jnp.array([-1.0, 2.0, -1.0, 2.0])
    xhat0 = jnp.zeros(4)
    ts = jnp.linspace(0.0, 3.0, 31)
    z0 = obs.init(0.0, xhat0, C_full @ x0)
    xs, zs = simulate_pair(plant, obs.vector_field, x0, z0, ts, u_sin)
    e = np.asarray(zs - jnp.einsum("tij,tj->ti", jax.jit(jax.vmap(obs.T_of))(ts), xs))
    e0 = e[0]
    pred = np.stack([scipy.linalg.expm(np.asarray(F_full) * float(t)) @ e0 for t in ts])
    assert np.abs(e - pred).max() < 1e-7 * np.abs(e0).max()
    xhat = jax.jit(jax.vmap(obs.estimate))(ts, zs, zs)
    err = np.linalg.norm(np.asarray(xhat - xs), axis=1)
    assert err[-1] < 1e-2 * err[0]
    # G solves G C = Ṫ + TA − FT (the condition holds, so G C reproduces M exactly)
    for t in [0.3, 2.2]:
        assert np.allclose(obs.G_of(t) @ C_full, obs.M_of(t), atol=1e-9)


# --- bad input ----------------------------------------------------------------------------------------
def test_reduced_requires_partitioned_model():
    plant = LTV(A_ex, lambda t: C_full[:, ::-1], lambda t: B_ex)
    T = lovass_nagy_T(lambda t: A_ex(t)[2:, 2:], A12, F5, S_ex)
    with pytest.raises(ValueError, match=r"partitioned form x = \[y; w\]"):
        obsjax.GeneralizedInverseReduced(plant, F5, T)


def test_reduced_solvability_failure_names_residual_and_time():
    """T = I does not satisfy (Ṫ + T A22 − F T)(I − C⁺C) = 0 (its first column is [0, −4/β])."""
    with pytest.raises(ValueError, match=r"residual .* at t = 0"):
        obsjax.GeneralizedInverseReduced(
            reduced_plant(), F5, lambda t: jnp.eye(2), horizon=(0.0, 5.0)
        )


def test_reduced_singular_T_over_horizon():
    """S = [1, cos t] gives det T = (β/4)(−sin t), zero at t = π inside the horizon."""
    T = lovass_nagy_T(lambda t: A_ex(t)[2:, 2:], A12, F5, lambda t: jnp.stack([1.0, jnp.cos(t)]))
    with pytest.raises(ValueError, match=r"det T ≠ 0.*changes sign between t = 3\.1"):
        obsjax.GeneralizedInverseReduced(reduced_plant(), F5, T, horizon=(0.5, 5.0), num_checks=401)


def test_reduced_bad_F_shape():
    T = lovass_nagy_T(lambda t: A_ex(t)[2:, 2:], A12, F5, S_ex)
    with pytest.raises(ValueError, match="`F` must have shape"):
        obsjax.GeneralizedInverseReduced(reduced_plant(), -jnp.eye(3), T)


def test_reduced_bad_T_shape():
    with pytest.raises(ValueError, match=r"`T\(t\)` must return shape \(2, 2\)"):
        obsjax.GeneralizedInverseReduced(reduced_plant(), F5, lambda t: jnp.eye(3))


def test_full_bad_T_shape():
    plant = LTV(A_ex, lambda t: C_full, lambda t: B_ex)
    with pytest.raises(ValueError, match=r"`T\(t\)` must return shape \(4, 4\)"):
        obsjax.GeneralizedInverse(plant, F_full, lambda t: jnp.eye(2))


def test_full_solvability_failure():
    plant = LTV(A_ex, lambda t: C_full, lambda t: B_ex)
    with pytest.raises(ValueError, match="solvability condition fails"):
        obsjax.GeneralizedInverse(plant, F_full, lambda t: jnp.eye(4), horizon=(0.0, 1.0))


def test_unstable_F_is_refused_by_both_observers():
    """An F with an eigenvalue in the right half-plane was accepted (the reduced observer then reported
    status 0 while its error grew from 1 to 3e3); GeneralizedInverseODE refused it already."""
    plant = LTV(A_ex, lambda t: C_full, lambda t: B_ex)
    F_bad = jnp.diag(jnp.array([2.0, -4.0, -5.0, -6.0]))
    with pytest.raises(ValueError, match=r"`F` must have its eigenvalues in the open left half-plane"):
        obsjax.GeneralizedInverse(plant, F_bad, lambda t: jnp.eye(4))
    with pytest.raises(ValueError, match=r"`F` must have its eigenvalues in the open left half-plane"):
        obsjax.GeneralizedInverseReduced(reduced_plant(), jnp.diag(jnp.array([-5.0, 0.0])), lambda t: jnp.eye(2))


@pytest.mark.extended
def test_a_T_singular_inside_the_simulated_span_is_refused_without_a_horizon():
    """With ``horizon=None`` only t = 0 was checked: a T(t) whose determinant changes sign near t = 0.79
    (a design of the slides' procedure on a 4-state, 2-output plant) simulated over [0, 3] gave status 0
    and an estimate error of 4.4 for an initial error of 1.3.  Each simulation now checks its span."""
    def A4(t):
        return jnp.array([[0.0, 1.0, 0.0, 0.0], [-1.0 - 0.3 * jnp.sin(t), -0.2, 0.5, 0.0],
                          [0.0, 0.0, 0.0, 1.0], [0.4, 0.0, -2.0, -0.1 - 0.1 * jnp.cos(t)]])  # fmt: skip

    C4 = jnp.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    F4 = jnp.diag(jnp.array([-2.0, -3.0, -4.0, -5.0]))
    T4 = lovass_nagy_T(A4, C4, F4, lambda t: jnp.array([[1.0, 0.0], [0.2 * jnp.sin(t), 0.0], [0.0, 1.0], [0.0, 0.1 * jnp.cos(t)]]))
    plant = LTV(A4, lambda t: C4)
    obs = obsjax.GeneralizedInverse(plant, F4, T4)  # t = 0 is fine
    x0 = jnp.array([0.5, -1.0, 0.2, 0.7])
    short = obsjax.simulate(plant, obs, x0, jnp.zeros(4), jnp.linspace(0.0, 0.5, 6))
    assert int(short.status) == 0
    ts = np.linspace(0.0, 3.0, 31)
    with pytest.raises(ValueError, match=r"simulated span.*det T changes sign between t = 0\.78"):
        obsjax.simulate(plant, obs, x0, jnp.zeros(4), ts)
    with pytest.raises(Exception, match=r"simulated span.*`T` must be invertible"):  # under jit: eqx.error_if
        jax.jit(lambda x: obsjax.simulate(plant, obs, x, jnp.zeros(4), ts))(x0)
    with pytest.raises(ValueError, match=r"simulated span.*det T changes sign"):
        obsjax.simulate_batch(plant, obs, jnp.stack([x0, -x0]), jnp.zeros((2, 4)), np.linspace(0.0, 3.0, 31))


def test_bad_horizon():
    plant = LTV(A_ex, lambda t: C_full, lambda t: B_ex)
    T = lovass_nagy_T(A_ex, C_full, F_full, S_full)
    with pytest.raises(ValueError, match="`horizon` must be"):
        obsjax.GeneralizedInverse(plant, F_full, T, horizon=(1.0, 0.0))


# --- gradients with respect to F's eigenvalues ---------------------------------------------------------
def _reduced_loss(lams, t1=1.0, dt=0.02):
    plant = reduced_plant()
    F = jnp.diag(lams)
    T = lovass_nagy_T(lambda t: A_ex(t)[2:, 2:], A12, F, S_ex)
    obs = obsjax.GeneralizedInverseReduced(plant, F, T, C1=C1_slides)
    ts = jnp.linspace(0.0, t1, round(t1 / dt) + 1)
    x0 = jnp.array([-1.0, 2.0, -1.0, 2.0])
    p0 = obs.init(0.0, jnp.array([-1.0, 2.0, 0.5, 0.5]), x0[:2])
    xs, ps = simulate_pair(plant, obs.vector_field, x0, p0, ts, u_sin, dt=dt)
    err = jax.vmap(obs.estimate)(ts, ps, xs[:, :2]) - xs
    return jnp.sum(err[1:] ** 2) * dt


def _full_loss(lams, t1=1.0, dt=0.02):
    plant = LTV(A_ex, lambda t: C_full, lambda t: B_ex)
    F = jnp.diag(lams)
    T = lovass_nagy_T(A_ex, C_full, F, S_full)
    obs = obsjax.GeneralizedInverse(plant, F, T)
    ts = jnp.linspace(0.0, t1, round(t1 / dt) + 1)
    x0 = jnp.array([-1.0, 2.0, -1.0, 2.0])
    z0 = obs.init(0.0, jnp.zeros(4), C_full @ x0)
    xs, zs = simulate_pair(plant, obs.vector_field, x0, z0, ts, u_sin, dt=dt)
    err = jax.vmap(obs.estimate)(ts, zs, zs) - xs
    return jnp.sum(err[1:] ** 2) * dt


@pytest.mark.parametrize(
    "loss,lams",
    [(_reduced_loss, [-4.0, -6.0]), (_full_loss, [-2.0, -3.0, -4.0, -5.0])],
    ids=["reduced", "full"],
)
@pytest.mark.extended
def test_gradient_wrt_F_eigenvalues_matches_finite_differences(loss, lams):
    lams = jnp.array(lams)
    f = jax.jit(loss)
    g = np.asarray(jax.jit(jax.grad(loss))(lams))
    h = 1e-5
    fd = np.array(
        [(f(lams.at[i].add(h)) - f(lams.at[i].add(-h))) / (2 * h) for i in range(lams.size)]
    )
    assert np.allclose(g, fd, rtol=1e-5, atol=1e-8 * np.abs(fd).max())
    assert np.abs(g).max() > 1e-4


def test_lti_constant_T_places_eigenvalues_of_F():
    """LTI plant, constant S: T is constant and x̃̇ = (A − T⁻¹G C) x̃ with eig = eig(F) (numpy eig)."""
    plant = obsjax.LTI([[-2.0, 1.0], [0.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]])
    F = jnp.array([[-3.0, 1.0], [0.0, -4.0]])
    T = lovass_nagy_T(plant.A, plant.C, F, lambda t: jnp.array([0.3, 1.0]))
    obs = obsjax.GeneralizedInverse(plant, F, T, horizon=(0.0, 1.0), num_checks=5)
    L = np.linalg.solve(np.asarray(T(0.0)), np.asarray(obs.G_of(0.0)))
    eig = np.sort(np.linalg.eigvals(np.asarray(plant.A) - L @ np.asarray(plant.C)).real)
    assert np.allclose(eig, [-4.0, -3.0], atol=1e-10)
    assert np.allclose(obs.Tdot_of(0.5), 0.0)


# --- scale-invariant verdicts (review findings 1 and 4) -------------------------------------------------
class _Ac(eqx.Module):
    """A(t) of a 4-state, 2-output LTV plant in time units 1/c: c·A(c t) (c a leaf: one compilation)."""

    c: jax.Array

    def __call__(self, t):
        c = self.c
        return c * jnp.array(
            [
                [0.0, 1.0, 0.0, 0.0],
                [-2.0 - 0.5 * jnp.sin(c * t), -0.4, 0.3, 0.0],
                [0.0, 0.0, 0.0, 1.0],
                [0.2 * jnp.cos(0.7 * c * t), 0.0, -3.0, -0.2],
            ]
        )


class _Sc(eqx.Module):
    c: jax.Array

    def __call__(self, t):
        c = self.c
        return jnp.array(
            [[1.0, 0.2 * jnp.sin(c * t)], [0.0, 1.0], [0.3, 0.1 * jnp.cos(c * t)], [0.1, 0.5]]
        )


class _Perturbed(eqx.Module):
    """T(t)·(1 + δ E): a relative δ in the columns of T that the condition fixes."""

    T: eqx.Module
    delta: jax.Array

    def __call__(self, t):
        E = jnp.array([[0.0, 1.0, 0.0, 0.0], [0.0] * 4, [0.0, 0.0, 0.0, 1.0], [0.0] * 4])
        return self.T(t) * (1.0 + self.delta * E)


_C4 = jnp.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])


def _C4_of(t):
    return _C4


def _lti_tv_plant(c, delta):
    """The plant in time units 1/c (A → c·A(c t), F → c·F), with T from lovass_nagy_T perturbed by a
    relative `delta` (the reviewer's p22)."""
    c = jnp.asarray(c)
    A = _Ac(c)
    F = c * jnp.diag(jnp.array([-2.0, -3.0, -4.0, -5.0]))
    return LTV(A, _C4_of), F, _Perturbed(lovass_nagy_T(A, _C4, F, _Sc(c)), jnp.asarray(delta))


def test_solvability_verdict_does_not_depend_on_the_time_unit():
    """A T violating the condition by a relative 1e-3 was refused with c = 1 and 1e-3 but accepted with
    c = 1e-5 (the test was res/max(scale, 1) ≤ rtol: absolute once ‖Ṫ‖ + ‖TA‖ + ‖FT‖ ≪ 1), and the
    accepted observer's error stalled at 6.5e-5.  Now: refused in every time unit, eagerly and under
    jit; the exact T is accepted in every unit and its error follows T⁻¹ e^{Ft} T0 e0 (scipy expm)."""
    for c in (1.0, 1e-3, 1e-5):
        plant, F, T_bad = _lti_tv_plant(c, 1e-3)
        with pytest.raises(ValueError, match=r"solvability condition fails.*relative to"):
            obsjax.GeneralizedInverse(plant, F, T_bad, horizon=(0.0, 2.0 / c), num_checks=21)
        plant, F, T = _lti_tv_plant(c, 0.0)
        obsjax.GeneralizedInverse(plant, F, T, horizon=(0.0, 2.0 / c), num_checks=21)
    plant, F, T_bad = _lti_tv_plant(1e-5, 1e-3)
    with pytest.raises(
        (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError, ValueError),
        match="GeneralizedInverse: the Lovass-Nagy solvability condition",
    ):
        jax.block_until_ready(
            jax.jit(lambda F: obsjax.GeneralizedInverse(plant, F, T_bad, num_checks=5).F)(F)
        )


@pytest.mark.extended
def test_exact_design_converges_in_slow_time_units():
    """The design the scale-invariant test accepts at c = 1e-5 does what it claims: its error follows
    T⁻¹ e^{Ft} T0 e0 (scipy expm) over t ∈ [0, 2/c] (the violating T the old test accepted stalled)."""
    c = 1e-5
    plant, F, T = _lti_tv_plant(c, 0.0)
    obs = obsjax.GeneralizedInverse(plant, F, T)
    x0, xhat0 = np.array([1.0, 0.0, -1.0, 0.5]), np.zeros(4)
    ts = jnp.array([0.0, 1.0 / c, 2.0 / c])
    tr = obsjax.simulate(plant, obs, x0, xhat0, ts, rtol=1e-10, atol=1e-12)
    e0 = xhat0 - x0
    T0 = np.asarray(T(0.0))
    for t, err in zip(np.asarray(ts), np.asarray(tr.error)):
        pred = np.linalg.solve(np.asarray(T(t)), scipy.linalg.expm(np.asarray(F) * t) @ T0 @ e0)
        np.testing.assert_allclose(err, pred, rtol=1e-6, atol=1e-8)
    assert np.abs(np.asarray(tr.error[-1])).max() < 0.1  # |e0| = 1 → 5e-2 at 2/c (the old T_bad: stalls)


class _RT(eqx.Module):
    """R·T(t) for a constant R (a leaf: one compilation for every R)."""

    T: eqx.Module
    R: jax.Array

    def __call__(self, t):
        return self.R @ self.T(t)


def test_invertibility_verdict_is_scale_invariant():
    """det T ≤ 1e-12·max(max|det T|, 1) refused 1e-3·T (the same observer, z in other units: det T =
    −5.8e-13) and accepted any T with |det T| ≥ 1e-12 however ill-conditioned.  Now σ_min(T)/σ_max(T):
    s·T is accepted for s = 1, 1e-3, 1e-6 (eagerly and under jit) and recovers ŵ; R·T with R nearly
    singular (cond(R) ≈ 4e11, |det(R·T(0))| > 1e-9) is refused in every unit, eagerly and under jit."""
    A22 = lambda t: A_ex(t)[2:, 2:]
    T = lovass_nagy_T(A22, A12, F5, S_ex)  # F5 = −5I commutes with any R: R·T satisfies the condition
    R = 1e3 * jnp.array([[1.0, 1.0], [1.0, 1.0 + 1e-11]])
    plant = reduced_plant()
    build = lambda F, Ts: obsjax.GeneralizedInverseReduced(plant, F, Ts, C1=C1_slides).F
    jbuild = eqx.filter_jit(build)
    w = jnp.array([0.3, -0.7])
    for s in (1.0, 1e-3, 1e-6):
        Ts = _RT(T, s * jnp.eye(2))
        obs = obsjax.GeneralizedInverseReduced(plant, F5, Ts, C1=C1_slides, horizon=(0.0, 3.0),
                                               num_checks=31)
        jax.block_until_ready(jbuild(F5, Ts))
        xhat = obs.estimate(1.0, obs.init(1.0, jnp.concatenate([jnp.zeros(2), w]), jnp.zeros(2)),
                            jnp.zeros(2))
        np.testing.assert_allclose(np.asarray(xhat)[2:], w, rtol=1e-12)  # x̂ = [y; T⁻¹ z] recovers ŵ
        with pytest.raises(ValueError, match=r"`T` must be invertible.*σ_min\(T\)/σ_max\(T\) = "):
            obsjax.GeneralizedInverseReduced(plant, F5, _RT(T, s * R), C1=C1_slides,
                                             horizon=(0.0, 3.0), num_checks=31)
        with pytest.raises(
            (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError, ValueError),
            match=r"`T` must be invertible",
        ):
            jax.block_until_ready(jbuild(F5, _RT(T, s * R)))
    # R·T's determinant is far above the old absolute floor: the old test accepted it
    assert abs(float(jnp.linalg.det(R @ T(0.0)))) > 1e-9


def test_is_one_inverse_is_not_loosened_by_a_large_X():
    """The rounding allowance was rtol·‖C‖²‖X‖: a large X loosened its own test (X = diag(1, 1e4) passed for
    C = diag(1, 1e-6), and a 20 % residual passed beside a large null-space part)."""
    C = np.diag([1.0, 1e-6])
    assert obsjax.design.is_one_inverse(np.diag([1.0, 1e6]), C)  # the only {1}-inverse
    for x22 in (1e4, 5e5):
        assert not obsjax.design.is_one_inverse(np.diag([1.0, x22]), C)
    C = np.ones((2, 2))  # rank 1: X = C⁺ + s [[1, −1], [−1, 1]] is a {1}-inverse for every s
    X = np.linalg.pinv(C) + 1e8 * np.array([[1.0, -1.0], [-1.0, 1.0]])
    assert obsjax.design.is_one_inverse(X, C)
    assert not obsjax.design.is_one_inverse(X + 0.1 * np.eye(2), C)  # C X C = 1.2 C


def test_lovass_nagy_T_meets_its_condition_with_states_in_very_different_units():
    """R = Q K⁺ was solved through the normal equations (KᵀK)⁻¹Kᵀ, which square cond(K): with states in
    units 1e4 and 1e-4 (cond K 1e8) the returned T broke (Ṫ + TĀ − FT) N = 0 by 6 % relative."""
    def A0(t):
        return jnp.array([[-0.3, 1.0 + 0.2 * jnp.sin(t), 0.0, 0.1], [0.0, -0.1, 1.0, 0.0],
                          [0.2 * jnp.cos(0.5 * t), 0.0, -0.4, 1.0], [-1.0, 0.3, -0.5 * jnp.cos(t), -0.2]])  # fmt: skip

    F = np.diag([-2.0, -3.0, -4.0, -5.0])
    S = np.array([1e4, 1e-4, 1.0, 1.0])  # x → diag(S) x
    A = lambda t: jnp.asarray(S)[:, None] * A0(t) / jnp.asarray(S)[None, :]
    C = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.2]]) / S[None, :]
    Sf = lambda t: jnp.stack([jnp.array([1.0, 0.5 * jnp.sin(t), 0.2, 0.0]),
                              jnp.array([0.0, 1.0, 0.3 * jnp.cos(t), 1.0])], axis=1)  # fmt: skip
    T = obsjax.design.lovass_nagy_T(A, C, F, Sf)
    N = np.asarray(T.N)
    for t in (0.0, 1.0):
        Tt, Td = np.asarray(T(t)), np.asarray(jax.jacfwd(T)(t))
        M = Td + Tt @ np.asarray(A(t)) - F @ Tt
        scale = np.linalg.norm(Td @ N) + np.linalg.norm(Tt @ np.asarray(A(t)) @ N) + np.linalg.norm(F @ Tt @ N)
        assert np.linalg.norm(M @ N) / scale < 1e-9


def test_generalized_inverses_refuse_bad_matrices_and_wrong_one_inverses():
    """NaN/inf, complex and empty matrices went through moore_penrose, one_inverse and null_space_basis
    (NaN or complex results); a C1 that is not a {1}-inverse gave the residual of another equation."""
    good = np.array([[1.0, 1.0, 0.0]])
    for f in (moore_penrose, one_inverse, obsjax.design.null_space_basis):
        with pytest.raises(ValueError, match="`C` must be finite"):
            f(np.array([[1.0, np.nan, 0.0]]))
        with pytest.raises(ValueError, match="`C` must be finite"):
            f(np.array([[1.0, np.inf, 0.0]]))
        with pytest.raises(ValueError, match="`C` must be real"):
            f(good + 1j)
        with pytest.raises(ValueError, match="`C` must not be empty"):
            f(np.zeros((0, 3)))
    with pytest.raises(ValueError, match="`Y` must be finite"):
        one_inverse(good, Y=np.full((3, 1), np.nan))
    M = np.array([[1.0, 2.0, 3.0]])
    # M (I − C⁺C) = [[−0.5, 0.5, 3]] (C⁺C projects onto span{(1, 1, 0)})
    np.testing.assert_allclose(solvability_residual(M, good), [[-0.5, 0.5, 3.0]], atol=1e-14)
    with pytest.raises(ValueError, match="`C1` is not a \\{1\\}-inverse of `C`"):
        solvability_residual(M, good, np.zeros((3, 1)))
    with pytest.raises(ValueError, match="`B1` is not a \\{1\\}-inverse of `B`"):
        obsjax.design.input_solvability_residual(np.array([[1.0], [0.0]]), np.array([1.0, 0.0]), np.zeros((1, 2)))


def test_canonical_form_names_a_redundant_output_and_pd_spectrum_refuses_non_finite_rho_bar():
    A = lambda t: jnp.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -2.0 - jnp.sin(t), -1.5]])
    C = lambda t: jnp.array([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])  # the second sensor is twice the first
    with pytest.raises(ValueError, match=r"output\(s\) \[2\] add no row independent"):
        obsjax.design.ltv_observer_canonical_form(A, C, 0.0)
    for bad in ([-1.0, np.nan, -3.0], [-1.0, -np.inf, -3.0]):
        with pytest.raises(ValueError, match="`rho_bar` must be finite"):
            obsjax.design.pd_coefficients(jnp.asarray(bad), 2.0, 0.0)


def test_null_space_basis_and_moore_penrose_agree_on_the_rank():
    """σ = (1, 1e-3, 1e-15) on a 3 × 4 C: pinv cut σ₃ (rank 2) while null_space_basis kept it (a 1-D null
    space), so C⁺C ≠ I − N Nᵀ; both now use pinv's cut-off 10·max(m, n)·ε·σ₁."""
    rng = np.random.default_rng(3)
    U, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    V, _ = np.linalg.qr(rng.standard_normal((4, 4)))
    for s3 in (1e-15, 5e-15, 1e-13):  # inside [4ε, 40ε]·σ₁ for the first two, above pinv's cut for the last
        C = U @ np.diag([1.0, 1e-3, s3]) @ V[:3]
        N = obsjax.design.null_space_basis(C)
        P = np.asarray(moore_penrose(C)) @ C
        rank = int(round(np.trace(P)))  # P is a projector: its trace is its rank
        assert rank == (2 if s3 < 1e-14 else 3) and N.shape == (4, 4 - rank), (s3, N.shape, rank)
        np.testing.assert_allclose(N.T @ N, np.eye(4 - rank), atol=1e-12)
        if rank == 2:  # with σ₃ = 1e-13 kept, C⁺C carries an error ε/σ₃
            np.testing.assert_allclose(P, np.eye(4) - N @ N.T, atol=1e-10)
            np.testing.assert_allclose(C @ N, 0.0, atol=1e-12)


def test_lovass_nagy_T_checks_a_given_null_space_basis_relative_to_C():
    """`N` was checked by ‖C N‖ ≤ 1e-9·max(1, ‖C‖): with outputs in small units (C ~ 1e-12) any N
    passed, and T was built on a subspace that is not null(C); an N with too few columns passed too."""
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -2.0, -3.0]])
    F = np.diag([-4.0, -5.0, -6.0])
    S = lambda t: jnp.ones((3, 1))
    for scale in (1.0, 1e-12):
        C = scale * np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        T = lovass_nagy_T(A, C, F, S, N=np.array([[0.0], [0.0], [1.0]]))  # the true null(C): accepted
        assert np.all(np.isfinite(np.asarray(T(0.0))))
        with pytest.raises(ValueError, match="must span null"):
            lovass_nagy_T(A, C, F, S, N=np.array([[1.0], [0.0], [0.0]]))
    with pytest.raises(ValueError, match="of dimension 2"):
        lovass_nagy_T(A, np.array([[1.0, 0.0, 0.0]]), F, S, N=np.array([[0.0], [0.0], [1.0]]))
