"""Byrski & Fuksa beyond the LTI example: Theorem 1 for linear time-varying maps (the state of an LTV plant
at the end of a window, and a constant parameter), and the closed loop (33)-(37) simulated directly as a
delay equation.

Independent references: SciPy's solve_ivp for the plant, the transition matrix and the gramian; a
discretised minimum-norm quadratic program of Theorem 1 written here (a KKT solve in NumPy sharing no code
with the Hamiltonian ODEs); the LTI observer FiniteWindow (block matrix exponentials) on an LTI plant;
Lemma 4's (42) with SciPy's expm; (39) evaluated by quadrature with finite-difference u̇; central finite
differences for gradients.
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


# ---- an LTV plant of our own: 3 states, 1 output, 1 input, everything time-varying ---------------------
def A3(t):
    return jnp.array(
        [[0.0, 1.0, 0.0], [-1.0 - 0.5 * jnp.sin(t), -0.2, 0.5], [0.3 * jnp.cos(t), 0.0, -0.4]]
    )


def B3(t):
    return jnp.array([[0.0], [1.0 + 0.3 * jnp.cos(2.0 * t)], [0.2]])


def C3(t):
    return jnp.array([[1.0, 0.1 * jnp.cos(t), 0.0]])


def u3(t):
    return jnp.array([jnp.sin(3.0 * t) + 0.5])


PLANT3 = obsjax.LTV(A3, C3, B3)
T0, T1 = 0.5, 2.5
X0 = jnp.array([1.0, -0.5, 0.8])
ALPHA, BETA = np.array([1.0, 2.0, 0.5]), np.array([0.3, 1.5, 0.0])  # three different γ, one zero


@jax.jit
def _plant_solution(theta):
    E = jnp.array([0.0, 1.0, 0.0])
    return diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, x, a: A3(t) @ x + B3(t) @ u3(t) + a * E),
        diffrax.Dopri8(),
        T0,
        T1,
        None,
        X0,
        args=theta,
        saveat=diffrax.SaveAt(dense=True, t1=True),
        stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-14),
        max_steps=100_000,
    )


@functools.cache
def plant_solution(theta=0.0):
    """The plant with a constant force θ on x2, dense (diffrax Dopri8, tight tolerances)."""
    return _plant_solution(jnp.asarray(theta))


def transition(ts):
    """Φ(t_k, t0) on a grid by SciPy."""

    def rhs(t, v):
        return (np.asarray(A3(t)) @ v.reshape(3, 3)).ravel()

    sol = si.solve_ivp(
        rhs, (ts[0], ts[-1]), np.eye(3).ravel(), t_eval=ts, rtol=1e-12, atol=1e-13, method="DOP853"
    )
    return sol.y.T.reshape(-1, 3, 3)


@pytest.mark.extended
def test_exact_reconstruction_of_x_t1_from_noise_free_data():
    sol = plant_solution()
    xT = np.asarray(sol.ys[-1])
    y = lambda t: C3(t) @ sol.evaluate(t)
    for fw in (
        obsjax.FiniteWindowLTV(PLANT3, T0, T1),
        obsjax.FiniteWindowLTV(PLANT3, T0, T1, ALPHA, BETA),
    ):
        np.testing.assert_allclose(
            fw.estimate(y, u3), xT, atol=1e-9
        )  # (14) integrated in the solve
        ts = jnp.linspace(T0, T1, 201)
        ys, us = jax.vmap(y)(ts), jax.vmap(u3)(ts)
        np.testing.assert_allclose(
            fw.estimate_window(ts, ys, us), xT, atol=1e-7
        )  # Simpson, h = 0.01


@pytest.mark.extended
@pytest.mark.extended
def test_estimate_window_grid_checks_hold_under_jit():
    """With traced sample times the eager grid checks did not run: a non-uniform grid with
    rule='simpson' gave x̂(t1) 0.27 off, a grid covering [t0, 1.5] of a window [0, 2] 0.071 off, swapped
    samples a number; all three raise under jit now, and a valid grid gives the eager estimate."""
    sol = plant_solution()
    y = lambda t: C3(t) @ sol.evaluate(t)
    fw = obsjax.FiniteWindowLTV(PLANT3, T0, T1)
    est = jax.jit(lambda ts, ys, us: fw.estimate_window(ts, ys, us, rule="simpson"))
    est_tr = jax.jit(lambda ts, ys, us: fw.estimate_window(ts, ys, us, rule="trapezoid"))
    ts = np.linspace(T0, T1, 101)
    data = lambda g: (jnp.asarray(g), jax.vmap(y)(jnp.asarray(g)), jax.vmap(u3)(jnp.asarray(g)))
    np.testing.assert_allclose(np.asarray(est(*data(ts))), np.asarray(fw.estimate_window(*data(ts))), rtol=1e-12, atol=1e-13)
    bent = ts + 0.3 * (ts - T0) * (T1 - ts) / (T1 - T0) ** 2 * (ts[1] - ts[0])
    with pytest.raises(Exception, match="uniform grid"):
        jax.block_until_ready(est(*data(bent)))
    short = np.linspace(T0, T0 + 0.75 * (T1 - T0), 101)
    with pytest.raises(Exception, match="must run from t0 to t1"):
        jax.block_until_ready(est_tr(*data(short)))
    swapped = ts.copy()
    swapped[[10, 20]] = swapped[[20, 10]]
    with pytest.raises(Exception, match="strictly increasing"):
        jax.block_until_ready(est_tr(*data(swapped)))


@pytest.mark.extended
def test_beta_zero_gives_the_gramian_kernel():
    """γ = 0: G1(t) = M⁻¹ Φ(t, t1)ᵀ C(t)ᵀ with the window gramian M (SciPy transition matrix, Simpson)."""
    ts = np.linspace(T0, T1, 401)
    Phi = transition(ts)  # Φ(t, t0)
    Phi_t1 = Phi @ np.linalg.inv(Phi[-1])  # Φ(t, t1)
    H = np.stack([np.asarray(C3(t)) @ P for t, P in zip(ts, Phi_t1)])  # (K, 1, 3): h1(t)ᵀ
    w = np.ones(401)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    w *= (ts[1] - ts[0]) / 3
    M = np.einsum("k,kmi,kmj->ij", w, H, H)
    fw = obsjax.FiniteWindowLTV(PLANT3, T0, T1, beta=np.zeros(3))
    np.testing.assert_allclose(fw.gramian(), M, rtol=1e-8)
    G1, _ = fw.kernels(jnp.asarray(ts[::40]))
    expected = np.einsum("ij,kmj->kim", np.linalg.inv(M), H[::40])
    np.testing.assert_allclose(G1, expected, atol=1e-7 * np.abs(expected).max())


def _discrete_qp(alpha, beta, K):
    """Theorem 1 discretised on K trapezoid points: min Σᵢ αᵢ‖g1ⁱ‖² + βᵢ‖g2ⁱ‖² subject to (16), with
    g2 = −ℋ2*g1 (18).  Returns the optimal norm² and the kernels G1 (K, n, m)."""
    ts = np.linspace(T0, T1, K)
    h = ts[1] - ts[0]
    w = np.full(K, h)
    w[0] = w[-1] = h / 2
    X = transition(ts)
    Xi = np.linalg.inv(X)
    C = np.stack([np.asarray(C3(t)) for t in ts])
    B = np.stack([np.asarray(B3(t)) for t in ts])
    n, m, p = 3, 1, 1
    # constraint (16): Σ_k w_k g_kᵀ C_k Φ(t_k, t1) = I
    Hc = np.concatenate([w[k] * (C[k] @ X[k] @ Xi[-1]).T for k in range(K)], axis=1)  # (n, K m)
    # (18): g2(t_j) = B_jᵀ Σ_{k ≤ j} w^{(j)}_k Φ(t_k, t_j)ᵀ C_kᵀ g_k
    L = np.zeros((K * p, K * m))
    for j in range(1, K):
        wj = np.full(j + 1, h)
        wj[0] = wj[-1] = h / 2
        for k in range(j + 1):
            L[j * p : (j + 1) * p, k * m : (k + 1) * m] = wj[k] * B[j].T @ (X[k] @ Xi[j]).T @ C[k].T
    Qy = np.kron(np.diag(w), np.eye(m))
    Qu = np.kron(np.diag(w), np.eye(p))
    total, rows = 0.0, []
    for i in range(n):
        Hm = alpha[i] * Qy + beta[i] * L.T @ Qu @ L
        Y = np.linalg.solve(Hm, Hc.T)
        lam = np.linalg.solve(Hc @ Y, np.eye(n)[i])
        total += lam[i]
        rows.append((Y @ lam).reshape(K, m))
    return total, np.stack(rows, axis=1), ts


@pytest.mark.extended
def test_norm_and_kernels_match_a_discretised_minimum_norm_program():
    fw = obsjax.FiniteWindowLTV(PLANT3, T0, T1, ALPHA, BETA)
    exact = float(fw.norm()) ** 2
    v1, _, _ = _discrete_qp(ALPHA, BETA, 101)
    v2, G1d, ts = _discrete_qp(ALPHA, BETA, 201)
    richardson = (4 * v2 - v1) / 3  # the trapezoid is O(h²)
    assert abs(v2 - exact) / exact < 2e-3
    assert abs(richardson - exact) / exact < 1e-5
    G1, _ = fw.kernels(jnp.asarray(ts))
    np.testing.assert_allclose(G1, G1d, atol=2e-3 * np.abs(G1d).max())


@pytest.mark.extended
def test_lti_plant_agrees_with_the_matrix_exponential_observer():
    A = np.array([[0.4, 1.0, 0.0], [0.0, -1.0, 1.0], [-1.0, 0.0, -0.5]])
    B, C = np.array([[0.0], [1.0], [0.5]]), np.array([[1.0, 0.0, 0.0]])
    lti = obsjax.LTI(A, B, C)
    a, b = np.array([1.0, 2.0, 0.5]), np.array([0.3, 1.5, 2.0])
    ref = obsjax.FiniteWindow(lti, 1.5, alpha=a, beta=b)
    fw = obsjax.FiniteWindowLTV(lti, 1.0, 2.5, a, b)
    np.testing.assert_allclose(fw.norm(), ref.norm(), rtol=1e-9)
    s = jnp.linspace(0.0, 1.5, 7)
    for mine, theirs in zip(fw.kernels(1.0 + s), ref.kernels(s)):
        np.testing.assert_allclose(mine, theirs, atol=1e-9 * np.abs(np.asarray(theirs)).max())


@pytest.mark.extended
def test_parameter_identification_of_a_constant_force():
    """ẋ = A x + B u + E θ: the window gives x(t1) and θ exactly from noise-free data."""
    theta = 0.7
    sol = plant_solution(theta)
    E = lambda t: jnp.array([[0.0], [1.0], [0.0]])
    fw = obsjax.FiniteWindowLTV(PLANT3, T0, T1, E=E)
    assert fw.dim == 4
    est = fw.estimate(lambda t: C3(t) @ sol.evaluate(t), u3)
    np.testing.assert_allclose(est[:3], sol.ys[-1], atol=1e-9)
    assert float(est[3]) == pytest.approx(theta, abs=1e-8)
    # a sensor offset y = x + θ indistinguishable from the state (ẋ = 0): Lemma 1 refuses
    still = obsjax.LTV(
        lambda t: jnp.zeros((1, 1)), lambda t: jnp.ones((1, 1)), lambda t: jnp.ones((1, 1))
    )
    with pytest.raises(ValueError, match="Lemma 1"):
        obsjax.FiniteWindowLTV(still, 0.0, 1.0, D=lambda t: jnp.ones((1, 1)))


@pytest.mark.extended
def test_norm_gradient_wrt_window_and_weights():
    fw = obsjax.FiniteWindowLTV(PLANT3, T0, T1, ALPHA, BETA)

    @jax.jit
    def nrm(t1, alpha, beta):
        return eqx.tree_at(lambda o: (o.t1, o.alpha, o.beta), fw, (t1, alpha, beta)).norm()

    a, b = jnp.asarray(ALPHA), jnp.asarray(BETA) + 0.1
    g = jax.grad(nrm, argnums=(0, 1, 2))(jnp.asarray(T1), a, b)
    h = 1e-5
    fd_t = (nrm(T1 + h, a, b) - nrm(T1 - h, a, b)) / (2 * h)
    np.testing.assert_allclose(g[0], fd_t, rtol=1e-6)
    assert float(g[0]) < 0  # a longer window gives a smaller norm
    # Central differences carry an absolute error (the quadrature's and the h² term), so each weight's
    # component is compared at rtol 1e-6 with an absolute floor of 1e-8 of the whole gradient's size
    # (3e-8 here; the smallest component, 1.2e-3 in a gradient of norm 3.2, differed by 3e-9 with
    # jaxlib 0.10.1 where 0.10.2 had met rtol 1e-6).
    floor = 1e-8 * float(jnp.linalg.norm(jnp.concatenate([g[1], g[2]])))
    for i in range(3):
        e = jnp.zeros(3).at[i].set(h)
        np.testing.assert_allclose(
            g[1][i], (nrm(T1, a + e, b) - nrm(T1, a - e, b)) / (2 * h), rtol=1e-6, atol=floor
        )
        np.testing.assert_allclose(
            g[2][i], (nrm(T1, a, b + e) - nrm(T1, a, b - e)) / (2 * h), rtol=1e-6, atol=floor
        )


def test_bad_inputs():
    with pytest.raises(ValueError, match="`t1` must be > `t0`"):
        obsjax.FiniteWindowLTV(PLANT3, 1.0, 1.0)
    with pytest.raises(ValueError, match="`t1` must be a finite time, got inf"):  # was an error from the solve
        obsjax.FiniteWindowLTV(PLANT3, 0.0, np.inf)
    with pytest.raises(ValueError, match="`alpha`"):
        obsjax.FiniteWindowLTV(PLANT3, 0.0, 1.0, alpha=[1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match=r"`E\(t\)` must return a \(3, q\) matrix"):
        obsjax.FiniteWindowLTV(PLANT3, 0.0, 1.0, E=lambda t: jnp.ones((2, 1)))
    with pytest.raises(ValueError, match="must be an obsjax.LTV"):
        obsjax.FiniteWindowLTV(
            obsjax.Nonlinear(lambda t, x, u: x, lambda t, x, u: x, 1, 1), 0.0, 1.0
        )
    fw = obsjax.FiniteWindowLTV(PLANT3, T0, T1)
    with pytest.raises(ValueError, match="`ts` must run from t0"):
        fw.estimate_window(jnp.linspace(0.0, 2.5, 5), jnp.zeros((5, 1)))


# ------------------------------------------------------------------------------------------------------
# The closed loop (33)-(37) as a delay equation, against Lemma 4, (39), and the sample-and-propagate form
# ------------------------------------------------------------------------------------------------------
MODEL29 = obsjax.LTI([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[2.0, 0.0]])
P29 = jnp.array([[-2.0, -3.0]])  # eig(A + BP) = {−1, −2}
FW29 = obsjax.FiniteWindow(MODEL29, 1.0, n_chunks=10)
XA, XHA = jnp.array([1.0, -0.5]), jnp.array([0.3, 0.2])


@functools.cache
def delay_run(consistent, N):
    return obsjax.delay_closed_loop(
        FW29, P29, XA, XA if consistent else XHA, 4.0, steps_per_window=N
    )


@pytest.mark.extended
def test_delay_loop_is_second_order_and_equals_sample_and_propagate_on_consistent_data():
    """x̂0 = x0: the history is the plant's own free response, the data are model-consistent, and both
    forms give x(t) = e^{(A+BP)t} x0: the sample-and-propagate form to the ODE tolerance, the delay loop
    to O(h²) (the error falls 4× when h halves)."""
    ts = jnp.linspace(0.0, 4.0, 41)
    tr = obsjax.simulate(
        MODEL29, FW29, XA, XA, ts, controller=lambda t, xh: P29 @ xh, rtol=1e-10, atol=1e-12
    )
    Acl = np.asarray(MODEL29.A + MODEL29.B @ P29)
    exact = np.stack([sl.expm(Acl * float(t)) @ np.asarray(XA) for t in ts])
    np.testing.assert_allclose(tr.x, exact, atol=1e-8)
    errs = [np.abs(np.asarray(delay_run(True, N).x)[:: N // 10] - exact).max() for N in (100, 200)]
    assert errs[1] < 5e-5
    assert 3.5 < errs[0] / errs[1] < 4.5


@pytest.mark.extended
def test_delay_loop_is_deadbeat_after_T():
    """x̂0 ≠ x0 (the data jump at t0): for t ≥ T the window holds plant data only, x̂ = x and the state
    follows ẋ = (A + BP) x (Lemma 4, (42))."""
    r = delay_run(False, 200)
    ts, x, xh = (np.asarray(v) for v in (r.ts, r.x, r.xhat))
    late = ts >= 1.0
    np.testing.assert_allclose(xh[late], x[late], atol=1e-4)
    Acl = np.asarray(MODEL29.A + MODEL29.B @ P29)
    i1 = int(np.argmax(late))
    x42 = np.stack([sl.expm(Acl * (t - ts[i1])) @ x[i1] for t in ts[late]])
    np.testing.assert_allclose(x[late], x42, atol=1e-4)
    assert np.abs(x[i1]).max() > 0.2
    assert np.abs(xh[0] - np.asarray(XHA)).max() < 1e-4  # x̂(t0) from the history alone is x̂0


@pytest.mark.extended
def test_delay_loop_satisfies_the_differentiated_form_39():
    """u̇ = −P∫Ġ1(T+s)Cx(t+s) − P∫Ġ2 u + P G1(T)C x(t) − P G1(0) C x(t−T) + P G2(T)u(t) − P G2(0)u(t−T)."""
    r = delay_run(False, 200)
    N, h = 200, 1.0 / 200
    x, u = np.asarray(r.x), np.asarray(r.u)
    s = jnp.linspace(0.0, 1.0, N + 1)
    G1, G2 = (np.asarray(g) for g in FW29.kernels(s))
    d = jax.vmap(jax.jacfwd(lambda q: FW29.kernels(q)))(s)
    dG1, dG2 = np.asarray(d[0]), np.asarray(d[1])
    C, P = np.asarray(MODEL29.C), np.asarray(P29)
    w = np.full(N + 1, h)
    w[0] = w[-1] = h / 2
    for t in (1.5, 2.3, 3.1):  # t > T: the window holds plant data only
        k = round(t / h)
        xw, uw = x[k - N : k + 1], u[k - N : k + 1]
        rhs = (
            -P @ np.einsum("j,jim,mn,jn->i", w, dG1, C, xw)
            - P @ np.einsum("j,jip,jp->i", w, dG2, uw)
            + P @ G1[-1] @ C @ x[k]
            - P @ G1[0] @ C @ x[k - N]
            + P @ G2[-1] @ u[k]
            - P @ G2[0] @ u[k - N]
        )
        udot = (u[k + 1] - u[k - 1]) / (2 * h)
        np.testing.assert_allclose(udot, rhs, atol=1e-3 * max(1.0, np.abs(udot).max()))


@pytest.mark.slow
def test_sample_and_propagate_converges_to_the_delay_loop_as_chunks_shrink():
    """Inconsistent data at t0 (x̂0 ≠ x0): the two forms differ on [0, T]; the difference is O(1/n_chunks)."""
    ref = delay_run(False, 400)
    ts = jnp.linspace(0.0, 4.0, 41)
    xr = np.asarray(ref.x)[::40]
    devs = []
    for nc in (10, 20, 40):
        fw = obsjax.FiniteWindow(MODEL29, 1.0, n_chunks=nc)
        tr = obsjax.simulate(
            MODEL29, fw, XA, XHA, ts, controller=lambda t, xh: P29 @ xh, rtol=1e-10, atol=1e-12
        )
        devs.append(np.abs(np.asarray(tr.x) - xr).max())
    assert devs[0] / devs[1] > 1.7 and devs[1] / devs[2] > 1.7


@pytest.mark.extended
def test_estimate_window_keeps_simpson_on_clock_times_and_under_jit():
    """Two ways the quadrature fell back to the trapezoid rule without a word (error 1.7e-4 for 8.8e-10):
    a uniform grid on a clock (t = 1e6 + …, whose steps differ by rounding, 1e-8 of the step) was taken as
    non-uniform (and rule="simpson" refused it); and under ``jit`` a NumPy grid closed over was read as
    traced.  LTV and LTI windows; x(t1) from the matrix exponential."""
    A0 = np.array([[0.0, 1.0, 0.0], [-2.0, -0.3, 0.4], [0.2, 0.0, -0.5]])
    C0 = np.array([[1.0, 0.0, 0.0]])
    x0 = np.array([0.7, -0.4, 1.1])
    plant = obsjax.LTV(lambda t: jnp.asarray(A0), lambda t: jnp.asarray(C0))
    exact = sl.expm(A0 * 2.5) @ x0
    ys = np.array([C0 @ sl.expm(A0 * t) @ x0 for t in np.linspace(0.5, 2.5, 201)])
    for shift in (0.0, 1e6):
        ts = shift + np.linspace(0.5, 2.5, 201)
        assert np.ptp(np.diff(ts)) > 1e-9 * np.diff(ts)[0] or shift == 0.0  # the clock's rounding is there
        windows = (
            obsjax.FiniteWindowLTV(plant, shift + 0.5, shift + 2.5),
            obsjax.FiniteWindow(obsjax.LTI(A0, None, C0), 2.0),
        )
        for fw in windows:
            for rule in ("auto", "simpson"):
                np.testing.assert_allclose(fw.estimate_window(ts, ys, rule=rule), exact, atol=1e-8)
            jitted = jax.jit(lambda y, fw=fw, ts=ts: fw.estimate_window(ts, y))(ys)
            np.testing.assert_allclose(jitted, exact, atol=1e-8)
