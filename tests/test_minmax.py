"""Min-max (ℓ∞) initial-state estimation and the min-max + Luenberger combination (slides 002).

Independent references: the forward simulation written here (not the transition matrices inside); numpy
least squares; a brute-force vertex enumeration of the Chebyshev problem; the identity θ̂(ε) = θ̂(0) + ε
(max(|r + ε|, |r − ε|) = |r| + ε); the discrete error law z − T x = F^k (z0 − T0 x0) for an exact model.
"""

import itertools

import numpy as np
import pytest

import obsjax
from obsjax.observers._minmax import window_regression


def alpha(k):
    return -0.4 * np.exp(np.sin(0.3 * k) - 0.5)


def beta(k):
    return 0.4 * np.cos(0.3 * k) - 0.5


def A_mm(k):  # slides, min-max example
    return (
        np.array(
            [[10, 10 * alpha(k), 1, 0], [-2, 0, -1, -1], [0, -1, -5, 0], [-1, 2, 4 / beta(k), -5]]
        )
        / 20.0
    )


B_mm = np.array([[1.0], [1.0], [0.0], [1.0]])
C_mm = np.array([[0.0, 0.0, 0.0, 1.0]])
X0 = np.array([10.0, 10.0, 0.0, 0.0])


def A_comb(k):  # slides, combination example
    return (
        np.array(
            [
                [-10, 10 * alpha(k), 0, -1],
                [-1, -10, -5, 5],
                [0, -1, -5, 0],
                [-1, 0, -4 / beta(k), 0],
            ]
        )
        / 20.0
    )


P_err = 0.02 * np.array([[1, 1, 1, 1], [1, 0, 1, 0], [0, 0, 0, 0], [0, 0, 0, 0]], dtype=float)
B_comb = np.ones((4, 1))
C_comb = np.fliplr(np.eye(4))
F_comb = 0.01 * np.diag([-10.0, -20.0, -30.0, -40.0])


def simulate(A_of, B, C, x0, us):
    x, xs, ys = np.array(x0, float), [], []
    for k in range(len(us) + 1):
        xs.append(x)
        ys.append(C @ x)
        if k < len(us):
            x = A_of(k) @ x + B @ us[k]
    return np.array(xs), np.array(ys)


def data(N, noise=0.0, seed=0):
    us = np.sin(0.5 * np.arange(N))[:, None]
    xs, ys = simulate(A_mm, B_mm, C_mm, X0, us)
    ys = ys + np.random.default_rng(seed).uniform(-noise, noise, ys.shape)
    As = np.stack([A_mm(k) for k in range(N)])
    return As, us, xs, ys


def test_exact_data_recovers_x0_and_theta_is_eps():
    As, us, _xs, ys = data(12)
    x0, theta = obsjax.minmax_initial_state(As, B_mm, C_mm, ys, us, eps=0.05)
    assert np.allclose(x0, X0, atol=1e-6)
    assert theta == pytest.approx(0.05, abs=1e-8)
    # window regression: ȳ = ψ x0 on exact data (ψ, ȳ against the forward simulation above)
    ybar, psi = window_regression(As, B_mm, C_mm, ys, us)
    assert np.allclose(psi @ X0, ybar, atol=1e-10)


def test_minmax_value_is_chebyshev_plus_eps_and_same_estimate():
    """max over |δ| ≤ ε adds ε: θ̂(ε) = θ̂(0) + ε, and the estimate solves the plain min ‖ȳ − ψx0‖∞."""
    As, us, _xs, ys = data(10, noise=0.05)
    ybar, psi = window_regression(As, B_mm, C_mm, ys, us)
    _x_c, th_c = obsjax.minmax_initial_state(As, B_mm, C_mm, ys, us, eps=0.0)
    for eps in [0.01, 0.3]:
        x_e, th_e = obsjax.minmax_initial_state(As, B_mm, C_mm, ys, us, eps=eps)
        assert th_e == pytest.approx(th_c + eps, abs=1e-8)
        assert np.abs(ybar - psi @ x_e).max() == pytest.approx(th_c, abs=1e-8)


def test_chebyshev_against_vertex_enumeration_and_least_squares():
    """Independent: the LP optimum is at a vertex with n + 1 active rows ψ_i x + s_i θ = ȳ_i."""
    As, us, _xs, ys = data(7, noise=0.05, seed=3)
    ybar, psi = window_regression(As, B_mm, C_mm, ys, us)
    r, n = psi.shape
    best = np.inf
    for rows in itertools.combinations(range(r), n + 1):
        for signs in itertools.product([-1.0, 1.0], repeat=n + 1):
            M = np.hstack([psi[list(rows)], np.array(signs)[:, None]])
            if abs(np.linalg.det(M)) < 1e-12:
                continue
            sol = np.linalg.solve(M, ybar[list(rows)])
            x, th = sol[:n], sol[n]
            if th >= -1e-12 and np.abs(ybar - psi @ x).max() <= th + 1e-9:
                best = min(best, th)
    x_c, th_c = obsjax.minmax_initial_state(As, B_mm, C_mm, ys, us, eps=0.0)
    assert th_c == pytest.approx(best, rel=1e-7, abs=1e-10)
    x_ls = np.linalg.lstsq(psi, ybar, rcond=None)[0]
    assert np.abs(ybar - psi @ x_ls).max() >= th_c - 1e-10  # Chebyshev minimises the ℓ∞ residual
    assert (
        np.linalg.norm(ybar - psi @ x_ls) <= np.linalg.norm(ybar - psi @ x_c) + 1e-10
    )  # LS the ℓ2 one


def test_slides_algorithm_inequality_figure4():
    """Slides' Figure 4 quantity ‖ȳ + ε·1 − ψ x̃0‖∞ − θ̂ over growing windows.  It cannot be positive
    (θ̂ = θ̃ + ε ≥ ‖ȳ + ε·1 − ψx̃0‖∞); on these data it is 0 to LP accuracy, i.e. the slides' '≥ 0' holds
    only with equality: the min-max estimate coincides with the Chebyshev one."""
    eps = 0.05
    As, us, _xs, ys = data(20, noise=eps, seed=1)
    gaps = []
    for N in range(4, 21):
        alg = obsjax.minmax_algorithm(As[:N], B_mm, C_mm, ys[: N + 1], us[:N], eps)
        assert alg.theta_minmax == pytest.approx(alg.theta_cheb + eps, abs=1e-8)
        assert alg.residual_minmax_shifted <= alg.theta_minmax + 1e-8
        gaps.append(alg.gap)
    gaps = np.array(gaps)
    assert np.all(gaps <= 1e-8)
    assert np.all(np.abs(gaps) <= 1e-8)


def test_figure3_state_error_small_with_exact_data():
    As, us, xs, ys = data(20)
    x0, _ = obsjax.minmax_initial_state(As, B_mm, C_mm, ys, us, eps=0.0)
    xhat = simulate(A_mm, B_mm, C_mm, x0, us)[0]
    assert np.linalg.norm(xhat - xs, axis=1).max() < 1e-6


def test_constant_and_stacked_matrices_agree():
    A = A_mm(0)
    us = np.zeros((6, 1))
    _xs, ys = simulate(lambda k: A, B_mm, C_mm, X0, us)
    a = obsjax.minmax_initial_state(A, B_mm, C_mm, ys, us, 0.0)[0]
    b = obsjax.minmax_initial_state(np.stack([A] * 6), B_mm, np.stack([C_mm] * 7), ys, us, 0.0)[0]
    assert np.allclose(a, b, atol=1e-8) and np.allclose(a, X0, atol=1e-6)


# --- bad input -----------------------------------------------------------------------------------------
def test_window_too_short_is_refused():
    As, us, _xs, ys = data(2)
    with pytest.raises(ValueError, match="rank 3 < n = 4"):
        obsjax.minmax_initial_state(As, B_mm, C_mm, ys, us)


def test_negative_eps():
    As, us, _xs, ys = data(6)
    with pytest.raises(ValueError, match="`eps` must be >= 0"):
        obsjax.minmax_initial_state(As, B_mm, C_mm, ys, us, eps=-0.1)


def test_stacked_A_wrong_length():
    As, us, _xs, ys = data(6)
    with pytest.raises(ValueError, match=r"`A` stacked over k must have shape \(6, 4, 4\)"):
        obsjax.minmax_initial_state(As[:5], B_mm, C_mm, ys, us)


def test_us_wrong_shape():
    As, us, _xs, ys = data(6)
    with pytest.raises(ValueError, match=r"`us` must have shape \(N, p\) = \(6, 1\)"):
        obsjax.minmax_initial_state(As, B_mm, C_mm, ys, us[:4])


def test_nan_measurements():
    As, us, _xs, ys = data(6)
    ys[2] = np.nan
    with pytest.raises(ValueError, match="`ys` must be finite"):
        obsjax.minmax_initial_state(As, B_mm, C_mm, ys, us)


# --- the combination ----------------------------------------------------------------------------------
def test_discrete_luenberger_error_law_exact_model():
    """With the exact model, z − T x obeys z(k) − T x(k) = F^k (z0 − T0 x0) (T = I here)."""
    K = 15
    us = np.sin(0.5 * np.arange(K))[:, None]
    xs, ys = simulate(A_comb, B_comb, C_comb, X0, us)
    obs = obsjax.MinMaxLuenberger(A_comb, B_comb, C_comb, F_comb, window=3)
    xhat0 = np.zeros(4)
    xh = obs.luenberger(ys, us, xhat0)
    for k in range(K + 1):
        assert np.allclose(
            xh[k] - xs[k], np.linalg.matrix_power(F_comb, k) @ (xhat0 - X0), atol=1e-12
        )


def test_combination_beats_pure_minmax_under_model_error_figure5():
    """Slides' Figure 5: plant A(k) + P(k), model A(k); free response from x0 = [10, 10, 0, 0].  The
    min-max start replayed through the Luenberger observer has a smaller error than the same start
    propagated by the model, at every k (window W = 5)."""
    K = 40
    us = np.zeros((K, 1))
    xs, ys = simulate(lambda k: A_comb(k) + P_err, B_comb, C_comb, X0, us)
    obs = obsjax.MinMaxLuenberger(A_comb, B_comb, C_comb, F_comb, window=5, eps=0.0)
    res = obs.run(ys, us)
    e_comb = np.linalg.norm(res.xhat - xs[res.ks], axis=1)
    e_mm = np.linalg.norm(res.xhat_minmax - xs[res.ks], axis=1)
    assert np.all(e_mm - e_comb > 0)
    assert e_comb.mean() < 0.5 * e_mm.mean()
    # with the exact model both are exact (the difference is due to the model error P)
    xs0, ys0 = simulate(A_comb, B_comb, C_comb, X0, us)
    res0 = obs.run(ys0, us)
    assert np.allclose(res0.xhat, xs0[res0.ks], atol=1e-7)
    assert np.allclose(res0.xhat_minmax, xs0[res0.ks], atol=1e-7)


def test_combination_solvability_failure():
    """T = I needs (A − F)(I − C^{1}C) = 0: false with the single output of the min-max example."""
    obs = obsjax.MinMaxLuenberger(A_mm, B_mm, C_mm, 0.5 * np.eye(4), window=5)
    with pytest.raises(ValueError, match="fails at k = 0: residual"):
        obs.gains(3)


def test_combination_unstable_F():
    with pytest.raises(ValueError, match="`F` must have its eigenvalues inside the unit circle"):
        obsjax.MinMaxLuenberger(A_comb, B_comb, C_comb, 1.5 * np.eye(4), window=5)


def test_combination_record_too_short():
    obs = obsjax.MinMaxLuenberger(A_comb, B_comb, C_comb, F_comb, window=5)
    with pytest.raises(ValueError, match="more than window"):
        obs.run(np.zeros((4, 4)), np.zeros((3, 1)))
    # an input record one row short was a NumPy reshape error
    with pytest.raises(ValueError, match=r"`us` must have K = 9 rows .* got shape \(8, 1\)"):
        obs.run(np.zeros((10, 4)), np.zeros((8, 1)))


@pytest.mark.parametrize("window", [2.5, True, 0])
def test_combination_window_must_be_a_positive_integer(window):
    """window = 2.5 was truncated to 2 without a word."""
    with pytest.raises(ValueError, match=r"`window` must be an integer >= 1"):
        obsjax.MinMaxLuenberger(A_comb, B_comb, C_comb, F_comb, window=window)


# --- the slides' basic cost (1): a sum over k of ∞-norms ----------------------------------------------


def _cost1(ybar, psi, x, m):
    r = (ybar - psi @ x).reshape(-1, m)
    return np.abs(r).max(axis=1).sum()


def test_cost1_single_output_is_least_absolute_deviations_by_enumeration():
    """m = 1: cost (1) is Σ_k |ȳ(k) − ψ(k) x0|, minimised at a vertex through n samples (enumerated)."""
    As, us, _xs, ys = data(8, noise=0.05, seed=5)
    ybar, psi = window_regression(As, B_mm, C_mm, ys, us)
    r, n = psi.shape
    best, x_best = np.inf, None
    for rows in itertools.combinations(range(r), n):
        M = psi[list(rows)]
        if abs(np.linalg.det(M)) < 1e-12:
            continue
        x = np.linalg.solve(M, ybar[list(rows)])
        c = _cost1(ybar, psi, x, 1)
        if c < best:
            best, x_best = c, x
    x1, c1 = obsjax.minmax_sum_initial_state(As, B_mm, C_mm, ys, us, eps=0.0)
    assert c1 == pytest.approx(best, rel=1e-8)
    assert _cost1(ybar, psi, x1, 1) == pytest.approx(c1, rel=1e-9)
    np.testing.assert_allclose(x1, x_best, atol=1e-6 * np.abs(x_best).max())


def test_cost1_eps_adds_N_plus_1_eps_and_keeps_the_estimate():
    As, us, _xs, ys = data(10, noise=0.05, seed=2)
    _x0, c0 = obsjax.minmax_sum_initial_state(As, B_mm, C_mm, ys, us, eps=0.0)
    x1, c1 = obsjax.minmax_sum_initial_state(As, B_mm, C_mm, ys, us, eps=0.02)
    assert c1 == pytest.approx(c0 + 11 * 0.02, abs=1e-8)
    ybar, psi = window_regression(As, B_mm, C_mm, ys, us)
    assert _cost1(ybar, psi, x1, 1) == pytest.approx(c0, abs=1e-8)


def test_cost1_two_outputs_is_a_global_minimum_of_the_written_cost():
    """m = 2: the LP optimum is not beaten by any of 4000 perturbations of the cost evaluated directly
    (the cost is convex, so a local minimum is global), and differs from the stacked cost (2)."""
    C2 = np.array([[0.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0, 0.0]])
    N = 9
    us = np.sin(0.5 * np.arange(N))[:, None]
    _xs, ys = simulate(A_mm, B_mm, C2, X0, us)
    ys = ys + np.random.default_rng(8).uniform(-0.05, 0.05, ys.shape)
    As = np.stack([A_mm(k) for k in range(N)])
    ybar, psi = window_regression(As, B_mm, C2, ys, us)
    x1, c1 = obsjax.minmax_sum_initial_state(As, B_mm, C2, ys, us)
    assert _cost1(ybar, psi, x1, 2) == pytest.approx(c1, rel=1e-9)
    rng = np.random.default_rng(0)
    for scale in (1e-6, 1e-3, 1e-1, 3.0):
        xs = x1 + scale * rng.normal(size=(1000, 4))
        costs = np.array([_cost1(ybar, psi, x, 2) for x in xs])
        assert costs.min() >= c1 - 1e-10
    x2, _ = obsjax.minmax_initial_state(As, B_mm, C2, ys, us)
    assert _cost1(ybar, psi, x2, 2) > c1 + 1e-6


def test_cost1_ignores_an_outlier_that_cost2_balances():
    """One corrupted sample: the sum of ∞-norms (1) still passes through the clean data (x0 exact), the
    stacked ∞-norm (2) spreads the outlier over the estimate."""
    As, us, _xs, ys = data(16)
    ys = ys.copy()
    ys[5] += 3.0
    x1, _ = obsjax.minmax_sum_initial_state(As, B_mm, C_mm, ys, us)
    x2, _ = obsjax.minmax_initial_state(As, B_mm, C_mm, ys, us)
    np.testing.assert_allclose(x1, X0, atol=1e-6)
    assert np.abs(x2 - X0).max() > 0.1


def test_cost1_bad_inputs():
    As, us, _xs, ys = data(6)
    with pytest.raises(ValueError, match="`eps` must be >= 0"):
        obsjax.minmax_sum_initial_state(As, B_mm, C_mm, ys, us, eps=-1.0)
    with pytest.raises(ValueError, match="rank"):
        obsjax.minmax_sum_initial_state(As[:1], B_mm, C_mm, ys[:2], us[:1])


# --- scale-invariant verdicts (review findings 2, 3, 4) ---------------------------------------------------
def _np_chain(A, C, x0, N):
    xs = [np.asarray(x0, dtype=float)]
    for _ in range(N):
        xs.append(A @ xs[-1])
    xs = np.array(xs)
    return xs, xs @ C.T


def test_combination_solvability_verdict_does_not_depend_on_units_of_z():
    """The test was res ≤ rtol·max(1, ‖M‖): T_bad (a relative 1e-4 off the condition) was refused, but
    1e-5·T_bad (the same observer, z in other units) accepted, and its error then followed x, not F^k.
    Now refused for s = 1, 1e-5, 1e5; the exact T0 is accepted for each s and its error is
    T0⁻¹ F^k T0 e0 (numpy matrix powers)."""
    A = np.array([[0.9, 0.2], [-0.1, 0.8]])
    C = np.array([[1.0, 0.0]])
    F = np.diag([0.2, 0.3])
    t1 = np.array([1.0, 1.0])  # column 2 of T from (T A − F T)[:, 1] = 0
    T0 = np.column_stack([t1, np.linalg.solve(A[1, 1] * np.eye(2) - F, -A[0, 1] * t1)])
    T_bad = T0 * (1 + np.array([[0.0, 1e-4], [0.0, 1e-4]]))
    xs, ys = _np_chain(A, C, [1.0, -2.0], 30)
    for s in (1.0, 1e-5, 1e5):
        with pytest.raises(ValueError, match=r"fails at k = 0: residual .*expected ≤ rtol"):
            obsjax.MinMaxLuenberger(A, None, C, F, window=3, T=s * T_bad).gains(3)
        xh = obsjax.MinMaxLuenberger(A, None, C, F, window=3, T=s * T0).luenberger(ys, None, np.zeros(2))
        e0 = -xs[0]
        for k in (0, 5, 10, 30):
            pred = np.linalg.solve(T0, np.linalg.matrix_power(F, k) @ T0 @ e0)
            np.testing.assert_allclose(xh[k] - xs[k], pred, rtol=1e-7, atol=1e-13)


def test_combination_invertibility_of_T_is_scale_invariant():
    """|det T| < 1e-12 refused T = 1e-6·I (det 1e-18) and accepted a nearly singular T with det 1e-5.
    Now σ_min/σ_max: s·I is accepted for s = 1, 1e-6, 1e6 and recovers the state exactly (C = I: the
    condition holds for any T); R = 1e3·[[1, 1, 0], [1, 1 + 1e-11, 0], [0, 0, 1]] is refused for each s."""
    rng = np.random.default_rng(4)
    Ak = lambda k: np.array([[0.9, 0.1 * np.sin(0.3 * k), 0.0], [0.0, 0.8, 0.2], [0.05, 0.0, 0.95]])
    B = np.array([[0.0], [1.0], [0.5]])
    K = 12
    us = rng.standard_normal((K, 1))
    xs, ys = simulate(Ak, B, np.eye(3), np.array([1.0, -2.0, 0.5]), us)
    F = np.diag([0.1, -0.2, 0.3])
    R = 1e3 * np.array([[1.0, 1.0, 0.0], [1.0, 1.0 + 1e-11, 0.0], [0.0, 0.0, 1.0]])
    assert abs(np.linalg.det(R)) > 1e-6  # far above the old absolute floor
    for s in (1.0, 1e-6, 1e6):
        res = obsjax.MinMaxLuenberger(Ak, B, np.eye(3), F, window=4, T=s * np.eye(3)).run(ys, us)
        np.testing.assert_allclose(res.xhat, xs[res.ks], atol=1e-12)
        with pytest.raises(ValueError, match=r"`T\(0\)` must be invertible: expected σ_min"):
            obsjax.MinMaxLuenberger(Ak, B, np.eye(3), F, window=4, T=s * R).run(ys, us)


def _mass_spring(s):
    """Discretised 4-state mass-spring pair (h = 0.1), one output, states in units diag(s, 1/s, 1, 1)."""
    import scipy.linalg

    Ac = np.array([[0, 1, 0, 0], [-2, -0.1, 1, 0], [0, 0, 0, 1], [1, 0, -1, -0.1]], dtype=float)
    Bc = np.array([[0.0], [1.0], [0.0], [0.0]])
    Ad = scipy.linalg.expm(0.1 * Ac)
    Bd = np.linalg.solve(Ac, Ad - np.eye(4)) @ Bc
    S = np.diag([s, 1 / s, 1.0, 1.0])
    Si = np.diag([1 / s, s, 1.0, 1.0])
    return S @ Ad @ Si, S @ Bd, np.array([[1.0, 0, 0, 0]]) @ Si, S


def test_minmax_initial_state_does_not_depend_on_state_units():
    """The rank test and the LP ran on the raw ψ: with units diag(s, 1/s, 1, 1), s = 2e7 was refused
    ("rank 3 < n = 4 ... lengthen the window") and past it the LP returned a wrong x0.  Now ψ's columns
    are normalised first: the same verdict and the same x0 for s = 1, 2e7, 5e7 — exact data give x0, noisy
    data give the Chebyshev estimate of an independent scipy linprog in the natural units."""
    import scipy.optimize

    rng = np.random.default_rng(11)
    N = 30
    us = rng.standard_normal((N, 1))
    x0 = np.array([0.5, -1.0, 2.0, 0.3])
    A, B, C, _ = _mass_spring(1.0)
    xs = [x0]
    for k in range(N):
        xs.append(A @ xs[-1] + B @ us[k])
    ys = np.array(xs) @ C.T
    ysn = ys + 0.01 * rng.uniform(-1, 1, ys.shape)
    ybar, psi = window_regression(A, B, C, ysn, us)
    r = psi.shape[0]
    ref = scipy.optimize.linprog(
        np.r_[np.zeros(4), 1.0],
        A_ub=np.block([[psi, -np.ones((r, 1))], [-psi, -np.ones((r, 1))]]),
        b_ub=np.r_[ybar, -ybar],
        bounds=[(None, None)] * 4 + [(0, None)],
    )
    for s in (1.0, 2e7, 5e7):
        A_s, B_s, C_s, S = _mass_spring(s)
        xe, th = obsjax.minmax_initial_state(A_s, B_s, C_s, ys, us)
        np.testing.assert_allclose(np.linalg.solve(S, xe), x0, rtol=1e-9)
        assert th < 1e-12
        xe, _cost = obsjax.minmax_sum_initial_state(A_s, B_s, C_s, ys, us)
        np.testing.assert_allclose(np.linalg.solve(S, xe), x0, rtol=1e-9)
        xe, th = obsjax.minmax_initial_state(A_s, B_s, C_s, ysn, us, eps=0.01)
        np.testing.assert_allclose(np.linalg.solve(S, xe), ref.x[:4], rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(th, ref.fun + 0.01, rtol=1e-8)


def test_minmax_long_window_with_a_growing_mode():
    """A = diag(1.5, 0.6), C = [1, 1], exact data: N = 80 was refused with "lengthen the window" (and
    the LP alone returned HiGHS status 4).  With normalised columns ψ has full rank; the value is the
    Chebyshev residual of ȳ, whose entries reach 1.5⁸⁰ ≈ 1e14: rounding leaves θ of order 1e-16·‖ȳ‖∞ and
    x0 correct to what the early rows can resolve."""
    A = np.diag([1.5, 0.6])
    C = np.array([[1.0, 1.0]])
    x0 = np.array([1.0, 2.0])
    for N in (10, 40, 80):
        _xs, ys = _np_chain(A, C, x0, N)
        xe, th = obsjax.minmax_initial_state(A, None, C, ys)
        assert th <= 1e-15 * np.abs(ys).max()
        np.testing.assert_allclose(xe, x0, atol=1e-15 * np.abs(ys).max() + 1e-12)
        xe, _ = obsjax.minmax_sum_initial_state(A, None, C, ys)
        np.testing.assert_allclose(xe, x0, atol=1e-15 * np.abs(ys).max() + 1e-12)


def test_minmax_rank_advice_fits_the_cause():
    """"Lengthen the window" only when the window has fewer rows than states; when the first samples
    determine x0 and later ones (a huge growth along [1, 1]) make ψ rank-deficient, the message says a
    longer window does not help."""
    C = np.array([[1.0, 0.0]])
    rot = np.array([[0.0, 1.0], [-1.0, 0.0]])
    grow = 1e9 * np.array([[1.0, 1.0], [1.0, 1.0]])
    A = np.stack([rot, grow, grow, grow])
    x0 = np.array([0.3, -0.2])
    xs = [x0]
    for k in range(4):
        xs.append(A[k] @ xs[-1])
    ys = np.array(xs) @ C.T
    with pytest.raises(ValueError, match=r"rank 1 < n = 2") as err:
        obsjax.minmax_initial_state(A, None, C, ys)
    assert "lengthen the window" not in str(err.value) and "does not help" in str(err.value)
    np.testing.assert_allclose(obsjax.minmax_initial_state(A[:1], None, C, ys[:2])[0], x0, rtol=1e-12)
    with pytest.raises(ValueError, match=r"rank 1 < n = 2.*lengthen the window"):
        obsjax.minmax_initial_state(A[:0], None, C, ys[:1])


def test_complex_data_is_refused():
    """A complex `ys` (or matrix) had its imaginary part dropped with only NumPy's warning."""
    A, C = np.array([[0.9, 0.2], [-0.1, 0.8]]), np.array([[1.0, 0.0]])
    ys = np.array([[1.0], [0.9], [0.8], [0.7]])
    for fn in (obsjax.minmax_initial_state, obsjax.minmax_sum_initial_state):
        with pytest.raises(ValueError, match="`ys` must be real"):
            fn(A, None, C, ys + 1e-3j)
        with pytest.raises(ValueError, match="`A` must be real"):
            fn(A + 0j, None, C, ys)
