"""Trajectory linearization observer (Huang & Zhu): canonical form (8)-(11), PD-spectrum of the error,
high gain and peaking, the implicit-solver rule, the EKF baseline, gradients and tuning."""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.linalg

import obsjax
from obsjax.design import (
    RampBandwidth,
    ltv_observability_indices,
    ltv_observer_canonical_form,
    pd_observer_gain,
    rpdo_coefficients,
    strong_observability,
)

# -- LTV test systems ------------------------------------------------------------------------------------


def A3(t):
    return jnp.array(
        [[-1.0, 1 + 0.5 * jnp.sin(t), 0.0], [0.0, 0.0, 1.0], [0.3 * jnp.cos(t), -1.0, -0.5]]
    )


def C3(t):
    return jnp.array([[1.0, 0.0, 0.2 * jnp.cos(t)]])


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


SYSTEMS = {3: (A3, C3, (3,), [-1.0, -2.0, -3.0]), 4: (A4, C4, (2, 2), [-1.0, -2.0, -1.5, -3.0])}


def omega_tv(t):
    return 2.0 + jnp.sin(t)


def omega_int(t):
    return 2.0 * t + 1.0 - jnp.cos(t)


def _T_of(A, C, idx):
    return lambda s: jnp.linalg.inv(ltv_observer_canonical_form(A, C, s, indices=idx).Tinv)


@functools.cache
def _jitted(n):
    """Jitted per-system helpers (compiled once per system, reused across tests and ε)."""
    A, C, idx, rho = SYSTEMS[n]
    rho = jnp.asarray(rho)
    Tf = _T_of(A, C, idx)

    @jax.jit
    def closed_loop(t, omega, eps):
        """Ã_z(t) = T (A + K_o C) T⁻¹ + Ṫ T⁻¹ by (11), Ṫ by jvp of T(t) (independent of the α columns)."""
        T, Td = jax.jvp(Tf, (t,), (jnp.ones_like(t),))
        K = pd_observer_gain(A, C, rho, omega, t, eps=eps, indices=idx).Ko
        Ti = jnp.linalg.inv(T)
        return T @ (A(t) + K @ C(t)) @ Ti + Td @ Ti, K, T, Td

    form = jax.jit(lambda t: ltv_observer_canonical_form(A, C, t, indices=idx))
    return closed_loop, form, jax.jit(jax.vmap(Tf))


@functools.cache
def _jitted_tv(n):
    """Ã_z(t) by (11) with the time-varying bandwidth ω(t) = 2 + sin t, and the RPDO β of each block."""
    A, C, idx, rho = SYSTEMS[n]
    Tf = _T_of(A, C, idx)

    @jax.jit
    def f(t):
        T, Td = jax.jvp(Tf, (t,), (jnp.ones_like(t),))
        K = pd_observer_gain(A, C, jnp.asarray(rho), omega_tv, t, indices=idx).Ko
        Ti = jnp.linalg.inv(T)
        blocks, start = [], 0
        for p in idx:
            blocks.append(rpdo_coefficients(jnp.asarray(rho[start : start + p]), omega_tv, t))
            start += p
        return T @ (A(t) + K @ C(t)) @ Ti + Td @ Ti, blocks

    return f


# -- (8)-(11): the canonical form ----------------------------------------------------------------------------


@pytest.mark.parametrize("n", [3, 4])
@pytest.mark.extended
def test_canonical_form_matches_definition_11(n):
    A, C, idx, _ = SYSTEMS[n]
    assert ltv_observability_indices(A, C, np.linspace(0.0, 6.0, 7)) == idx
    closed_loop, form, _ = _jitted(n)
    t = jnp.asarray(0.7)
    cf = form(t)
    _, _, T, Td = closed_loop(t, 1.0, 1.0)
    Ti = jnp.linalg.inv(T)
    np.testing.assert_allclose(cf.Az, T @ A(t) @ Ti + Td @ Ti, atol=1e-10)
    # structure of (9): sub-diagonal ones inside each block, free entries only in columns d_i
    d = np.cumsum(idx) - 1
    free = np.zeros((n, n), bool)
    free[:, d] = True
    start = 0
    for p in idx:
        for j in range(1, p):
            assert abs(cf.Az[start + j, start + j - 1] - 1.0) < 1e-10
            free[start + j, start + j - 1] = True
        start += p
    np.testing.assert_allclose(np.where(free, 0.0, cf.Az), 0.0, atol=1e-10)
    # C_z = R C_can with R unit-diagonal
    np.testing.assert_allclose(np.delete(np.asarray(cf.Cz), d, axis=1), 0.0, atol=1e-10)
    np.testing.assert_allclose(np.diag(cf.R), 1.0, atol=1e-10)


@pytest.mark.extended
def test_strong_observability_failure_names_the_time():
    A = lambda t: jnp.array([[0.0, 1.0], [0.0, 0.0]])
    C = lambda t: jnp.array([[t - 1.0, 0.0]])
    with pytest.raises(ValueError, match=r"not strongly observable.*t = 1\b"):
        strong_observability(A, C, np.linspace(0.0, 2.0, 21))
    with pytest.raises(ValueError, match=r"not strongly observable.*t = 1\b"):
        ltv_observer_canonical_form(A, C, 1.0, indices=(2,))


def test_unobservable_pair_is_refused():
    A = lambda t: jnp.zeros((2, 2))
    C = lambda t: jnp.array([[1.0, 0.0]])
    with pytest.raises(ValueError, match="not observable at t = 0"):
        ltv_observability_indices(A, C, 0.0)


def test_changing_observability_indices_are_refused():
    A = lambda t: jnp.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    C = lambda t: jnp.array([[1.0, 0.0, 0.0], [0.0, t, 0.0]])
    with pytest.raises(ValueError, match="indices of .* change at t = 1"):
        ltv_observability_indices(A, C, [0.0, 1.0])


# -- requirement 4: the error obeys the assigned PD-spectrum -----------------------------------------------------


@pytest.mark.parametrize("n", [3, 4])
@pytest.mark.extended
def test_constant_bandwidth_gives_lti_error_dynamics_with_eigenvalues_rho_omega(n):
    from scipy.integrate import solve_ivp

    A, C, _, rho = SYSTEMS[n]
    closed_loop, _, _ = _jitted(n)
    for eps in (1.0, 0.5):
        M1, _, T1, _ = closed_loop(jnp.asarray(0.3), 1.5, eps)
        M2, _, T2, _ = closed_loop(jnp.asarray(1.9), 1.5, eps)
        np.testing.assert_allclose(M1, M2, atol=1e-8)  # LTI in canonical coordinates
        ev = np.sort(np.linalg.eigvals(np.asarray(M1)).real)
        np.testing.assert_allclose(ev, np.sort(np.array(rho) * 1.5 / eps), rtol=1e-8)
        # the closed loop A + K_o C integrated by SciPy in the original coordinates, mapped by T, equals
        # exp(Ã_z t) z0 (SciPy expm)
        z0 = np.arange(1.0, n + 1)

        def rhs(t, x, eps=eps):
            return np.asarray((A(t) + closed_loop(jnp.asarray(t), 1.5, eps)[1] @ C(t)) @ x)

        sol = solve_ivp(
            rhs, (0.3, 1.9), np.linalg.solve(T1, z0), rtol=1e-11, atol=1e-13, method="DOP853"
        )
        Phi = scipy.linalg.expm(np.asarray(M1) * 1.6)
        np.testing.assert_allclose(np.asarray(T2) @ sol.y[:, -1], Phi @ z0, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("n", [3, 4])
def test_time_varying_bandwidth_closed_loop_is_the_decoupled_observer_form_of_beta(n):
    """Ã_z(t) (by (11), Ṫ by autodiff) is block diagonal, block i in observer form with last column −β_i(t),
    β_i the RPDO whose modes are exp(ρ̄_k ∫ω) (checked in test_pd_spectrum)."""
    idx = SYSTEMS[n][2]
    for t in (0.4, 2.2):
        M, blocks = _jitted_tv(n)(jnp.asarray(t))
        expected = np.zeros((n, n))
        start = 0
        for p, beta in zip(idx, blocks):
            for j in range(1, p):
                expected[start + j, start + j - 1] = 1.0
            expected[start : start + p, start + p - 1] = -np.asarray(beta)
            start += p
        np.testing.assert_allclose(M, expected, atol=1e-8 * np.abs(expected).max())


@pytest.mark.extended
def test_time_varying_bandwidth_error_modes_follow_exp_integral_rho():
    """MIMO n = 4, two outputs: simulate plant + TLO; in canonical coordinates each block output z_{d_i}
    is a combination of exp(ρ̄_k ∫ω dt) over the block's ρ̄_k (fitted by least squares, residual ~ 0)."""
    A, C, idx, rho = SYSTEMS[4]
    plant = obsjax.LTV(A, C)
    obs = obsjax.TrajectoryLinearization(
        plant,
        rho,
        omega_tv,
        1.0,
        nominal=lambda t: (jnp.zeros(4), jnp.zeros(0)),
        check_ts=np.linspace(0, 3, 7),
    )
    ts = jnp.linspace(0.0, 3.0, 31)
    traj = obsjax.simulate(
        plant, obs, jnp.array([1.0, -1.0, 0.5, 0.0]), jnp.zeros(4), ts, rtol=1e-11, atol=1e-13
    )
    Ts = _jitted(4)[2](ts)
    z = jnp.einsum("tij,tj->ti", Ts, traj.error)
    W = np.asarray(omega_int(ts))
    d = np.cumsum(idx) - 1
    start = 0
    for i, p in enumerate(idx):
        basis = np.exp(np.outer(W, rho[start : start + p]))
        yi = np.asarray(z[:, d[i]])
        coef, *_ = np.linalg.lstsq(basis, yi, rcond=None)
        assert np.max(np.abs(basis @ coef - yi)) < 1e-6 * np.max(np.abs(yi))
        assert np.max(np.abs(yi)) > 1e-2
        # a wrong spectrum does not fit
        wrong = np.exp(np.outer(W, 1.3 * np.asarray(rho[start : start + p])))
        c2, *_ = np.linalg.lstsq(wrong, yi, rcond=None)
        assert np.max(np.abs(wrong @ c2 - yi)) > 1e-3 * np.max(np.abs(yi))
        start += p


# -- requirement 5: high gain, peaking, the implicit-solver rule ---------------------------------------------------


EPS = [1.0, 0.5, 0.2, 0.1, 0.05]
TS_HG = jnp.concatenate([jnp.linspace(0.0, 0.5, 51), jnp.linspace(0.6, 8.0, 38)])


def vdp(d):
    return lambda t, x, u: jnp.array([x[1], (1 - x[0] ** 2) * x[1] - x[0] + d * jnp.sin(2 * t)])


def duffing(d):
    def f(t, x, u):
        k = 0.5
        return jnp.array(
            [
                x[1],
                -x[0] - x[0] ** 3 - 0.3 * x[1] + k * (x[2] - x[0]) + d * jnp.sin(1.5 * t),
                x[3],
                -x[2] - 0.5 * x[2] ** 3 - 0.3 * x[3] + k * (x[0] - x[2]) + d * jnp.cos(t),
            ]
        )

    return f


def _high_gain_study(plant, model, rho, x0, solver):
    obs = obsjax.TrajectoryLinearization(model, rho, 2.0, 1.0)
    run = eqx.filter_jit(
        lambda o: obsjax.simulate(
            plant, o, x0, jnp.zeros(model.n), TS_HG, solver=solver, throw=False
        )
    )
    ss, pk = [], []
    for eps in EPS:
        traj = run(eqx.tree_at(lambda o: o.eps, obs, jnp.asarray(eps)))
        assert int(traj.status) == 0
        e = np.asarray(traj.error_norm)
        ss.append(e[np.asarray(TS_HG) >= 5.0].max())
        pk.append(e.max())
    return np.array(ss), np.array(pk)


@pytest.mark.extended
def test_high_gain_van_der_pol_steady_state_falls_peak_grows():
    h = lambda t, x, u: x[:1]
    plant, model = obsjax.Nonlinear(vdp(0.5), h, 2, 1), obsjax.Nonlinear(vdp(0.0), h, 2, 1)
    ss, pk = _high_gain_study(plant, model, [-1.0, -2.0], jnp.array([2.0, 0.0]), diffrax.Tsit5())
    assert np.all(np.diff(ss) < 0), ss
    assert np.all(np.diff(pk) > 0), pk
    assert ss[-1] < 0.1 * ss[0]  # ~ ε: 0.27 → 0.019
    assert pk[-1] > 10 * pk[0]  # peaking ~ 1/ε


@pytest.mark.extended
def test_high_gain_mimo_duffing_steady_state_falls_peak_grows():
    h = lambda t, x, u: jnp.array([x[0], x[2]])
    plant, model = obsjax.Nonlinear(duffing(0.5), h, 4, 2), obsjax.Nonlinear(duffing(0.0), h, 4, 2)
    ss, pk = _high_gain_study(
        plant, model, [-1.0, -2.0, -1.0, -2.0], jnp.array([1.0, 0.0, -1.0, 0.5]), diffrax.Tsit5()
    )
    assert np.all(np.diff(ss) < 0), ss
    assert np.all(np.diff(pk) > 0), pk


def test_solver_rule_picks_implicit_for_small_eps():
    h = lambda t, x, u: x[:1]
    model = obsjax.Nonlinear(vdp(0.0), h, 2, 1)
    rates = []
    for eps in EPS:
        obs = obsjax.TrajectoryLinearization(model, [-1.0, -2.0], 2.0, eps)
        rates.append(obs.fastest_rate())
        implicit = isinstance(obs.recommended_solver(), diffrax.Kvaerno5)
        assert implicit == (2.0 * 2.0 / eps > obs.stiff_rate)
    assert rates == pytest.approx([4.0 / e for e in EPS])
    assert isinstance(
        obsjax.TrajectoryLinearization(model, [-1.0, -2.0], 2.0, 0.05).recommended_solver(),
        diffrax.Kvaerno5,
    )
    assert isinstance(
        obsjax.TrajectoryLinearization(model, [-1.0, -2.0], 2.0, 1.0).recommended_solver(),
        diffrax.Tsit5,
    )
    # a time-varying bandwidth is judged by its largest value on the given times
    ramp = obsjax.TrajectoryLinearization(model, [-1.0, -2.0], RampBandwidth(0.5, 40.0, 1.0), 1.0)
    assert isinstance(ramp.recommended_solver([0.0]), diffrax.Tsit5)
    assert isinstance(ramp.recommended_solver(np.linspace(0, 10, 11)), diffrax.Kvaerno5)
    # traced ε: cannot judge, so implicit
    assert jax.jit(
        lambda e: jnp.asarray(
            isinstance(eqx.tree_at(lambda o: o.eps, ramp, e).recommended_solver(), diffrax.Kvaerno5)
        )
    )(1.0)


@pytest.mark.slow
def test_implicit_solver_agrees_with_explicit_at_small_eps():
    h = lambda t, x, u: x[:1]
    plant, model = obsjax.Nonlinear(vdp(0.5), h, 2, 1), obsjax.Nonlinear(vdp(0.0), h, 2, 1)
    obs = obsjax.TrajectoryLinearization(model, [-1.0, -2.0], 2.0, 0.05)
    solver = obs.recommended_solver()
    assert isinstance(solver, diffrax.Kvaerno5)
    x0 = jnp.array([2.0, 0.0])
    a = obsjax.simulate(plant, obs, x0, jnp.zeros(2), TS_HG, solver=solver)
    b = obsjax.simulate(
        plant, obs, x0, jnp.zeros(2), TS_HG, solver=diffrax.Tsit5(), rtol=1e-9, atol=1e-11
    )
    np.testing.assert_allclose(a.xhat, b.xhat, atol=1e-3 * float(jnp.max(jnp.abs(b.xhat))))


# -- requirement 6: the EKF baseline -----------------------------------------------------------------------------


def test_ekf_on_a_linear_plant_reaches_the_riccati_solution():
    A = np.array([[0.0, 1.0], [-2.0, -0.5]])
    C = np.array([[1.0, 0.0]])
    Q, R = np.diag([0.1, 0.4]), np.array([[0.05]])
    plant = obsjax.LTI(A, C=C)
    ekf = obsjax.ExtendedKalman(plant, Q=Q, R=R, P0=1.0)
    traj = obsjax.simulate(plant, ekf, jnp.array([1.0, 0.0]), jnp.zeros(2), jnp.linspace(0, 15, 16))
    P_inf = scipy.linalg.solve_continuous_are(A.T, C.T, Q, R)
    np.testing.assert_allclose(traj.z[1][-1], P_inf, rtol=1e-5)
    assert float(traj.error_norm[-1]) < 1e-3


def test_ekf_bad_noise_intensity_is_refused():
    plant = obsjax.LTI([[0.0, 1.0], [0.0, 0.0]], C=[[1.0, 0.0]])
    with pytest.raises(ValueError, match="`R` must be positive definite"):
        obsjax.ExtendedKalman(plant, Q=0.1, R=0.0, P0=1.0)


def test_ekf_asymmetric_Q_is_refused():
    plant = obsjax.LTI([[0.0, 1.0], [0.0, 0.0]], C=[[1.0, 0.0]])
    with pytest.raises(ValueError, match="`Q` must be symmetric"):
        obsjax.ExtendedKalman(plant, Q=[[1.0, 0.5], [0.0, 1.0]], R=1.0, P0=1.0)


def test_ekf_wrong_shape_P0_is_refused():
    plant = obsjax.LTI([[0.0, 1.0], [0.0, 0.0]], C=[[1.0, 0.0]])
    with pytest.raises(ValueError, match=r"`P0` must be .*\(2, 2\)"):
        obsjax.ExtendedKalman(plant, Q=0.1, R=1.0, P0=np.ones((3, 3)))


# -- requirement 7: gradients and tuning ---------------------------------------------------------------------------


def _ltv_disturbed():
    """n = 2 LTV plant with a non-vanishing disturbance the model lacks (a matched model error)."""
    A = lambda t: jnp.array([[0.0, 1.0], [-1.0 - 0.3 * jnp.sin(t), -0.4]])
    C = lambda t: jnp.array([[1.0, 0.0]])
    plant = obsjax.Nonlinear(
        lambda t, x, u: A(t) @ x + jnp.array([0.0, 0.6 * jnp.sin(1.3 * t)]),
        lambda t, x, u: C(t) @ x,
        2,
        1,
    )
    model = obsjax.LTV(A, C)
    return plant, model


TS_G = jnp.linspace(0.0, 4.0, 81)
# fixed Heun steps: the loss is smooth in the parameters (clean FD), and a 2-stage solver compiles fast
KW_G = dict(solver=diffrax.Heun(), dt0=0.01, adaptive=False)


def _tradeoff(traj):
    """Steady-state error (t ≥ 2) against peaking: mean ‖x̃‖² late + 0.05·peak."""
    late = TS_G >= 2.0
    steady = jnp.sum(jnp.where(late, traj.error_norm**2, 0.0)) / jnp.sum(late)
    return steady + 0.05 * obsjax.losses.peak(traj)


@functools.cache
def _gradient_problem():
    plant, model = _ltv_disturbed()
    obs = obsjax.TrajectoryLinearization(
        model,
        [-1.0, -2.0],
        RampBandwidth(1.0, 3.0, 1.0),
        0.3,
        nominal=lambda t: (jnp.zeros(2), jnp.zeros(0)),
    )
    x0 = jnp.array([1.5, 0.0])

    @jax.jit
    def J(p):
        o = eqx.tree_at(
            lambda o: (o.eps, o.omega.omega0, o.omega.omega1, o.omega.tau), obs, tuple(p)
        )
        return _tradeoff(obsjax.simulate(plant, o, x0, jnp.zeros(2), TS_G, **KW_G))

    return plant, obs, x0, J


@pytest.mark.extended
def test_gradient_wrt_eps_and_bandwidth_matches_finite_differences():
    *_, J = _gradient_problem()
    p = jnp.array([0.3, 1.0, 3.0, 1.0])
    g = jax.jit(jax.grad(J))(p)
    h = 1e-5
    fd = np.array([(J(p.at[i].add(h)) - J(p.at[i].add(-h))) / (2 * h) for i in range(4)])
    np.testing.assert_allclose(g, fd, rtol=2e-5, atol=1e-9)
    assert np.all(np.abs(fd) > 1e-5)


@pytest.mark.extended
def test_tune_finds_an_interior_optimum_of_eps():
    plant, obs, x0, J = _gradient_problem()
    w = obs.omega
    res = obsjax.tune(
        eqx.tree_at(lambda o: o.eps, obs, jnp.asarray(0.8)),
        plant,
        where=lambda o: o.eps,
        loss=_tradeoff,
        x0s=x0[None],
        xhat0s=jnp.zeros((1, 2)),
        ts=TS_G,
        optimizer=optax.adam(0.15),
        steps=20,
        progress=False,
        simulate_kwargs=KW_G,
    )
    eps_star = float(res.observer.eps)
    Je = lambda e: float(J(jnp.array([e, w.omega0, w.omega1, w.tau])))
    grid = np.geomspace(0.06, 1.0, 9)
    vals = np.array([Je(e) for e in grid])
    k = int(np.argmin(vals))
    assert 0 < k < len(grid) - 1, vals  # the trade-off has an interior minimiser
    assert grid[k - 1] < eps_star < grid[k + 1]
    assert Je(eps_star) <= vals.min() * 1.001
    assert Je(eps_star) < Je(0.7 * eps_star) and Je(eps_star) < Je(1.4 * eps_star)


@pytest.mark.slow
def test_gradient_along_the_running_estimate_matches_finite_differences():
    """Van der Pol, nominal=None: K_o depends on x̂ through the Jacobians and their flow derivatives."""
    h = lambda t, x, u: x[:1]
    plant, model = obsjax.Nonlinear(vdp(0.5), h, 2, 1), obsjax.Nonlinear(vdp(0.0), h, 2, 1)
    obs = obsjax.TrajectoryLinearization(model, [-1.0, -2.0], RampBandwidth(1.0, 3.0, 1.0), 0.3)

    @jax.jit
    def J(p):
        o = eqx.tree_at(
            lambda o: (o.eps, o.omega.omega0, o.omega.omega1, o.omega.tau), obs, tuple(p)
        )
        return _tradeoff(
            obsjax.simulate(plant, o, jnp.array([2.0, 0.0]), jnp.zeros(2), TS_G, **KW_G)
        )

    p = jnp.array([0.3, 1.0, 3.0, 1.0])
    g = jax.jit(jax.grad(J))(p)
    fd = np.array([(J(p.at[i].add(1e-5)) - J(p.at[i].add(-1e-5))) / 2e-5 for i in range(4)])
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-8)


# -- bad input ------------------------------------------------------------------------------------------------------


def _vdp_model():
    return obsjax.Nonlinear(vdp(0.0), lambda t, x, u: x[:1], 2, 1)


def test_wrong_number_of_pd_eigenvalues_is_refused():
    with pytest.raises(ValueError, match="`rho_bar` must hold n = 2"):
        obsjax.TrajectoryLinearization(_vdp_model(), [-1.0, -2.0, -3.0], 1.0, 1.0)


def test_unstable_pd_eigenvalues_are_refused():
    with pytest.raises(ValueError, match="`rho_bar` must be < 0"):
        obsjax.TrajectoryLinearization(_vdp_model(), [1.0, -2.0], 1.0, 1.0)


def test_repeated_pd_eigenvalues_in_a_block_are_refused():
    with pytest.raises(ValueError, match="distinct"):
        obsjax.TrajectoryLinearization(_vdp_model(), [-2.0, -2.0], 1.0, 1.0)


def test_nonpositive_eps_is_refused():
    with pytest.raises(ValueError, match="`eps` must be > 0"):
        obsjax.TrajectoryLinearization(_vdp_model(), [-1.0, -2.0], 1.0, 0.0)


def test_nonpositive_omega_is_refused():
    with pytest.raises(ValueError, match="`omega` must be finite and > 0"):
        obsjax.TrajectoryLinearization(_vdp_model(), [-1.0, -2.0], -1.0, 1.0)


def test_check_ts_needs_nominal():
    with pytest.raises(ValueError, match="`check_ts`.*`nominal`"):
        obsjax.TrajectoryLinearization(_vdp_model(), [-1.0, -2.0], 1.0, 1.0, check_ts=[0.0, 1.0])


def test_nominal_losing_strong_observability_names_the_time():
    f = lambda t, x, u: jnp.array([x[1], 0.0 * x[0]])
    h = lambda t, x, u: jnp.array([x[0] * x[1]])
    model = obsjax.Nonlinear(f, h, 2, 1)
    nominal = lambda t: (jnp.array([0.0 * t, t - 2.0]), jnp.zeros(0))
    with pytest.raises(ValueError, match=r"not strongly observable.*t = 2\b"):
        obsjax.TrajectoryLinearization(
            model,
            [-1.0, -2.0],
            1.0,
            1.0,
            nominal=nominal,
            indices=(2,),
            check_ts=np.linspace(0.0, 3.0, 7),
        )


def test_model_must_be_a_plant():
    with pytest.raises(ValueError, match="`model` must be an obsjax plant"):
        obsjax.TrajectoryLinearization(lambda t, x: x, [-1.0, -2.0], 1.0, 1.0)


def test_nominal_must_be_callable():
    with pytest.raises(ValueError, match="`nominal` must be None or a callable"):
        obsjax.TrajectoryLinearization(_vdp_model(), [-1.0, -2.0], 1.0, 1.0, nominal=3.0)


def test_bad_indices_are_refused():
    with pytest.raises(ValueError, match="`indices` must be 1 positive integers summing to n = 2"):
        obsjax.TrajectoryLinearization(_vdp_model(), [-1.0, -2.0], 1.0, 1.0, indices=(1,))


def _losing_model():
    """ẋ1 = x2, ẋ2 = 0, y = x1·x2: C_o = [x̂2, x̂1] vanishes at x̂ = 0 (not observable there)."""
    return obsjax.Nonlinear(
        lambda t, x, u: jnp.array([x[1], 0.0 * x[0]]), lambda t, x, u: x[:1] * x[1:], 2, 1
    )


def test_losing_strong_observability_along_the_estimate_stops_the_simulation():
    model = _losing_model()
    obs = obsjax.TrajectoryLinearization(model, [-1.0, -2.0], 1.0, 1.0, indices=(2,))
    with pytest.raises(Exception, match="lost strong observability"):
        obsjax.simulate(model, obs, jnp.array([1.0, 1.0]), jnp.zeros(2), jnp.linspace(0.0, 1.0, 3))


@pytest.mark.slow
def test_losing_strong_observability_with_nan_policy_fails_only_that_trajectory():
    model = _losing_model()
    obs = obsjax.TrajectoryLinearization(
        model, [-1.0, -2.0], 1.0, 1.0, indices=(2,), on_unobservable="nan"
    )
    run = jax.vmap(
        lambda xh0: (
            obsjax.simulate(
                model, obs, jnp.array([1.0, 1.0]), xh0, jnp.linspace(0.0, 1.0, 3), throw=False
            ).status
        )
    )
    status = run(jnp.array([[0.0, 0.0], [1.1, 0.9]]))
    assert int(status[0]) != 0 and int(status[1]) == 0


def test_bad_unobservable_policy_is_refused():
    with pytest.raises(ValueError, match="`on_unobservable` must be"):
        obsjax.TrajectoryLinearization(
            _vdp_model(), [-1.0, -2.0], 1.0, 1.0, on_unobservable="ignore"
        )


@pytest.mark.slow
def test_simulate_applies_the_solver_rule_by_default():
    """solver=None in simulate uses the observer's recommended (implicit) solver at small ε."""
    model = obsjax.Nonlinear(
        lambda t, x, u: jnp.array([x[1], -x[0] + (1 - x[0] ** 2) * x[1]]), lambda t, x, u: x[:1], 2, 1
    )
    obs = obsjax.TrajectoryLinearization(model, [-1.0, -2.0], 2.0, 0.05)
    assert isinstance(obs.recommended_solver(), diffrax.Kvaerno5)
    ts = jnp.linspace(0.0, 1.0, 11)
    a = obsjax.simulate(model, obs, jnp.array([2.0, 0.0]), jnp.zeros(2), ts)
    b = obsjax.simulate(model, obs, jnp.array([2.0, 0.0]), jnp.zeros(2), ts, solver=diffrax.Kvaerno5())
    np.testing.assert_array_equal(np.asarray(a.xhat), np.asarray(b.xhat))


@pytest.mark.extended
def test_nonfinite_initial_state_is_a_status_not_an_abort():
    """A NaN initial state (plant or estimate) with throw=False is status 2 (NONFINITE) eagerly, under
    jit and per member of a batch: the TLO's gain used to raise 'lost strong observability' from the NaN
    staircase margin (so one bad member aborted a study), and under jit the code read 1 instead of 2."""
    f = lambda t, x, u: jnp.array([x[1], (1 - x[0] ** 2) * x[1] - x[0]])
    vdp = obsjax.Nonlinear(f, lambda t, x, u: x[:1], n=2, m=1)
    tlo = obsjax.TrajectoryLinearization(vdp, rho_bar=[-1.0, -2.0], omega=2.0, eps=0.5)
    ts = np.linspace(0.0, 2.0, 11)
    nan0 = jnp.array([jnp.nan, 0.0])
    assert int(obsjax.simulate(vdp, tlo, nan0, jnp.zeros(2), ts, throw=False).status) == 2
    assert int(obsjax.simulate(vdp, tlo, jnp.ones(2), nan0, ts, throw=False).status) == 2
    run = jax.jit(jax.vmap(lambda x0: obsjax.simulate(vdp, tlo, x0, jnp.zeros(2), ts, throw=False).status))
    np.testing.assert_array_equal(run(jnp.stack([nan0, jnp.ones(2)])), [2, 0])
    batch = obsjax.simulate_batch(vdp, tlo, jnp.stack([jnp.ones(2), nan0]), jnp.zeros((2, 2)), ts, throw=False)
    np.testing.assert_array_equal(batch.status, [0, 2])
    with pytest.raises(ValueError, match="not finite at t = 0"):
        tlo.design(0.0, nan0)
    # a finite margin at the threshold is still the loss of observability, not a status
    with pytest.raises(ValueError, match="not observable at t = 0"):
        obsjax.design.ltv_observer_canonical_form(lambda t: jnp.zeros((2, 2)), lambda t: jnp.array([[1.0, 0.0]]), 0.0)


@pytest.mark.extended  # 13 s
def test_built_inside_jit_with_a_traced_eps():
    """Built inside jax.jit with ε traced, the observer failed with a TracerArrayConversionError from the
    observability indices (the model's Jacobians were staged, not evaluated).  It is the same observer as
    one built outside and given ε with eqx.tree_at; a traced model is refused with a ValueError."""
    A, C = jnp.array([[0.0, 1.0], [-2.0, -3.0]]), jnp.array([[1.0, 0.0]])
    model = obsjax.Nonlinear(lambda t, x, u: A @ x, lambda t, x, u: C @ x, n=2, m=1, p=0)
    ts, x0, xh0 = jnp.linspace(0.0, 3.0, 31), jnp.array([1.0, 0.5]), jnp.zeros(2)
    outside = obsjax.TrajectoryLinearization(model, rho_bar=[-1.0, -2.0], omega=2.0, eps=0.5)
    ref = jax.jit(lambda e: obsjax.simulate(model, eqx.tree_at(lambda o: o.eps, outside, e), x0, xh0, ts).error)(0.5)
    inside = jax.jit(
        lambda e: obsjax.simulate(
            model, obsjax.TrajectoryLinearization(model, rho_bar=[-1.0, -2.0], omega=2.0, eps=e), x0, xh0, ts
        ).error
    )(0.5)
    np.testing.assert_allclose(np.asarray(inside), np.asarray(ref), rtol=1e-12, atol=1e-15)

    def traced_model(a):
        m = obsjax.Nonlinear(lambda t, x, u: a * (A @ x), lambda t, x, u: C @ x, n=2, m=1, p=0)
        return obsjax.TrajectoryLinearization(m, rho_bar=[-1.0, -2.0], omega=2.0, eps=0.5).indices

    with pytest.raises(ValueError, match="the model is traced here: pass `indices`"):
        jax.jit(traced_model)(1.0)


def test_traced_nominal_pd_eigenvalues_keep_the_distinctness_check():
    """A tuned ρ̄ whose values converge is refused under jit as eagerly (values 1e-14 apart gave
    coefficients 6 % off); distinct traced values run."""
    import equinox as eqx

    obs = obsjax.TrajectoryLinearization(_vdp_model(), [-1.0, -2.0], 2.0, 0.5)
    f = jax.jit(lambda r: eqx.tree_at(lambda o: o.rho_bar, obs, r).prepare().rho_bar)
    np.testing.assert_allclose(f(jnp.array([-1.0, -2.0])), [-1.0, -2.0])
    with pytest.raises(Exception, match="distinct"):
        jax.block_until_ready(f(jnp.array([-1.0, -1.0 - 1e-14])))
