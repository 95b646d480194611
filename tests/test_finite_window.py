"""Byrski & Fuksa's minimum-norm finite-window observer (1982): kernels (25)-(28), norm (15)/(31), the
defining properties (16), (18), exact reconstruction, minimality, disturbance bound, gradients, the
sliding-window observer in `simulate` and the closed loop (33)-(42).

Independent references: the paper's closed forms (30), (31) and an independent discretisation's values (obsjax/_reproduce/references.py); SciPy (`expm`, `solve_ivp`)
on the same problems; a direct finite-dimensional discretisation of the minimum-norm problem of Theorem 1
(a KKT solve in NumPy that shares no code with the Hamiltonian/matrix-exponential formulas); central finite
differences for gradients.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate as si
import scipy.linalg as sl

import obsjax
from obsjax._reproduce.references import BYRSKI_FUKSA_NORM31

A29 = np.array([[0.0, 1.0], [0.0, 0.0]])
B29 = np.array([[0.0], [1.0]])
C29 = np.array([[2.0, 0.0]])
MODEL29 = obsjax.LTI(A29, B29, C29)

# Byrski & Fuksa: the norm (31) checked by an independent discretisation (values and provenance in
# obsjax/_reproduce/references.py).
REFERENCE_31 = BYRSKI_FUKSA_NORM31


def norm31(T):
    """The paper's closed form (31) of the norm for the double integrator (29), α = β = I."""
    return np.sqrt((3 * np.sinh(2 * T) + np.sin(2 * T)) / (4 * (np.sinh(T) ** 2 - np.sin(T) ** 2)))


def simpson_weights(K, T):
    w = np.ones(K)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    return w * T / (K - 1) / 3.0


def expm_grid(A, h, K):
    """e^{A k h} for k = 0, …, K − 1: one SciPy ``expm`` and repeated products (uniform grids)."""
    E, out = sl.expm(A * h), [np.eye(A.shape[0])]
    for _ in range(K - 1):
        out.append(out[-1] @ E)
    return np.stack(out)


def random_plant(n, m, p, seed):
    """An observable plant with at least one unstable eigenvalue."""
    rng = np.random.default_rng(seed)
    while True:
        A = rng.normal(size=(n, n))
        A = A - (np.max(np.linalg.eigvals(A).real) - 0.4) * np.eye(n)  # spectral abscissa 0.4 > 0
        B = rng.normal(size=(n, p))
        C = rng.normal(size=(m, n))
        O = np.vstack([C @ np.linalg.matrix_power(A, k) for k in range(n)])
        if np.linalg.svd(O, compute_uv=False)[-1] > 1e-2:
            return A, B, C


# ------------------------------------------------------------------------------------------------------
# Item 2: the norm (31) and the reference values
# ------------------------------------------------------------------------------------------------------


@pytest.mark.extended
def test_norm_31_reference_table_both_formulas():
    obs28 = obsjax.FiniteWindow(MODEL29, 1.0)
    obs25 = obsjax.FiniteWindow(MODEL29, 1.0, alpha=[1.0, 1.0], beta=[1.0, 1.0])
    assert obs28.formula == "(28)" and obs25.formula == "(25)"
    for T, ref in REFERENCE_31.items():
        for obs in (obs28, obs25):
            val = float(eqx.tree_at(lambda o: o.T, obs, jnp.asarray(T)).norm())
            assert val == pytest.approx(ref, abs=6e-6)
            assert val == pytest.approx(norm31(T), rel=1e-11)
    # strictly decreasing towards √1.5
    Ts = np.array([0.5, 1.0, 2.0, 4.0, 6.0, 8.0])
    vals = np.array([float(eqx.tree_at(lambda o: o.T, obs28, jnp.asarray(T)).norm()) for T in Ts])
    assert np.all(np.diff(vals) < 0)
    assert vals[-1] == pytest.approx(np.sqrt(1.5), rel=1e-6)
    assert np.all(vals > np.sqrt(1.5))


# ------------------------------------------------------------------------------------------------------
# Item 1: kernels (30), (25)-(26) versus (28)
# ------------------------------------------------------------------------------------------------------


@pytest.mark.extended
def test_kernels_match_closed_form_30_and_25_equals_28():
    T = 1.0
    t = np.linspace(0.0, T, 7)
    sh, ch, s, c = np.sinh, np.cosh, np.sin, np.cos
    R = np.array(
        [
            [sh(T) * c(T) - ch(T) * s(T), 2 * sh(T) * s(T)],
            [-2 * sh(T) * s(T), 2 * (sh(T) * c(T) + ch(T) * s(T))],
        ]
    ) / (2 * (sh(T) ** 2 - s(T) ** 2))
    g1 = (R @ np.array([2 * ch(t) * c(t), sh(t) * c(t) + ch(t) * s(t)])).T  # (30)
    g2 = (R @ np.array([-2 * sh(t) * s(t), sh(t) * c(t) - ch(t) * s(t)])).T
    G1, G2 = obsjax.FiniteWindow(MODEL29, T).kernels(t)
    assert G1.shape == (7, 2, 1) and G2.shape == (7, 2, 1)
    np.testing.assert_allclose(G1[..., 0], g1, atol=1e-12)
    np.testing.assert_allclose(G2[..., 0], g2, atol=1e-12)
    # (25)-(26) with γ_i = 1 but α ≠ I: the same kernels as (28) (the rows decouple; only γ matters)
    H1, H2 = obsjax.FiniteWindow(MODEL29, T, alpha=[2.0, 0.5], beta=[2.0, 0.5]).kernels(t)
    np.testing.assert_allclose(H1, G1, atol=1e-12)
    np.testing.assert_allclose(H2, G2, atol=1e-12)
    # scalar s
    g, h = obsjax.FiniteWindow(MODEL29, T).kernels(0.0)
    assert g.shape == (2, 1) and h.shape == (2, 1)
    np.testing.assert_allclose(h, 0.0, atol=1e-14)  # G2(0) = 0 (after (18))


# ------------------------------------------------------------------------------------------------------
# Item 3: (16), (18), exact reconstruction on random plants of order 2 to 4 (unstable A), general α, β
# ------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("n,m,p,seed", [(2, 1, 1, 0), (3, 1, 2, 1), (4, 2, 1, 2)])
@pytest.mark.extended
def test_unbiasedness_volterra_and_exact_reconstruction(n, m, p, seed):
    A, B, C = random_plant(n, m, p, seed)
    rng = np.random.default_rng(100 + seed)
    alpha, beta = rng.uniform(0.5, 2.0, n), rng.uniform(0.0, 3.0, n)
    T, K = 1.5, 301
    obs = obsjax.FiniteWindow(obsjax.LTI(A, B, C), T, alpha=alpha, beta=beta)
    s = np.linspace(0.0, T, K)
    G1, G2 = (np.asarray(g) for g in obs.kernels(s))
    w = simpson_weights(K, T)
    # (16): ∫ G1(τ) C e^{−A(T−τ)} dτ = I
    back = expm_grid(-A, T / (K - 1), K)[::-1]  # e^{−A(T − s_k)}
    integrand = np.einsum("kim,mj,kjl->kil", G1, C, back)
    np.testing.assert_allclose(
        np.einsum("k,kij->ij", w, integrand), np.eye(n), atol=1e-6
    )  # Simpson O(h⁴)
    # (18): G2(t) = ∫₀ᵗ G1(τ) C e^{A(τ−t)} B dτ, checked at a few t by Simpson on [0, t]
    for kt in (60, 150, 300):
        tt, kk = s[kt], 2 * kt + 1
        tau = np.linspace(0.0, tt, kk)
        G1t, _ = (np.asarray(g) for g in obs.kernels(tau))
        back = expm_grid(-A, tt / (kk - 1), kk)[::-1]  # e^{A(τ_k − t)}
        vals = np.einsum("kim,mj,kjl,lr->kir", G1t, C, back, B)
        np.testing.assert_allclose(
            np.einsum("k,kij->ij", simpson_weights(kk, tt), vals), G2[kt], atol=1e-6
        )
    # exact reconstruction of x(T) for arbitrary x0 and input, the plant integrated by SciPy
    x0 = rng.normal(size=n)
    amp, frq, ph = (
        rng.normal(size=(p, 3)),
        rng.uniform(0.3, 4.0, (p, 3)),
        rng.uniform(0, 6.3, (p, 3)),
    )

    def u(t):
        return np.sum(amp * np.sin(frq * t + ph), axis=1)

    t0 = 0.7  # a window [t0, t0 + T] that does not start at 0
    sol = si.solve_ivp(
        lambda t, x: A @ x + B @ u(t), (0.0, t0 + T), x0, rtol=1e-12, atol=1e-12, dense_output=True
    )
    ts = t0 + s
    ys = np.stack([C @ sol.sol(t) for t in ts])
    us = np.stack([u(t) for t in ts])
    xT = sol.sol(t0 + T)
    est = np.asarray(obs.estimate_window(ts, ys, us))
    np.testing.assert_allclose(est, xT, rtol=1e-6, atol=1e-6 * np.linalg.norm(xT))
    # the trapezoid is O(h²): worse than Simpson, still consistent
    est_tr = np.asarray(obs.estimate_window(ts, ys, us, rule="trapezoid"))
    err_tr = np.linalg.norm(est_tr - xT)
    assert 1e-9 < err_tr < 1e-2 * np.linalg.norm(xT)


# ------------------------------------------------------------------------------------------------------
# Item 3: optimality against an independent discretisation of Theorem 1, and minimality against the Gram
# observer of Lemma 1's proof and random members of S
# ------------------------------------------------------------------------------------------------------


def _discrete_problem(A, B, C, T, K):
    """Trapezoid discretisation: constraint matrix of (16), the Volterra map (18) and the weights."""
    m, p = C.shape[0], B.shape[1]
    tau = np.linspace(0.0, T, K)
    h = T / (K - 1)
    q = np.full(K, h)
    q[0] = q[-1] = h / 2
    back = expm_grid(-A, h, K)  # e^{−A d h}
    Hc = np.concatenate([q[k] * (C @ back[K - 1 - k]).T for k in range(K)], axis=1)  # (n, K m)
    # g2(t_l) = Σ_{k≤l} q_k^{(l)} Bᵀ e^{−Aᵀ(l−k)h} Cᵀ g1(τ_k), cumulative trapezoid weights q_k^{(l)}
    E = np.einsum("pi,dji,mj->dpm", B.T, back, C)  # Bᵀ e^{−Aᵀ d h} Cᵀ, (K, p, m)
    ll, kk = np.meshgrid(np.arange(K), np.arange(K), indexing="ij")
    wts = np.where(kk < ll, h, 0.0)
    wts[kk == 0] = h / 2
    wts[(kk == ll)] = h / 2
    wts[0, 0] = 0.0
    blocks = wts[:, :, None, None] * E[np.clip(ll - kk, 0, K - 1)]  # (K, K, p, m)
    L = blocks.transpose(0, 2, 1, 3).reshape(K * p, K * m)
    Qy = np.kron(np.diag(q), np.eye(m))
    Qu = np.kron(np.diag(q), np.eye(p))
    return tau, Hc, L, Qy, Qu


def _discrete_optimum(A, B, C, T, alpha, beta, K):
    """min Σ αᵢ‖g1ⁱ‖² + βᵢ‖g2ⁱ‖² subject to (16), g2 = (18)(g1): the norm² and the kernels G1 (K, n, m)."""
    n, m = A.shape[0], C.shape[0]
    _, Hc, L, Qy, Qu = _discrete_problem(A, B, C, T, K)
    total, rows = 0.0, []
    for i in range(n):
        H = alpha[i] * Qy + beta[i] * L.T @ Qu @ L
        X = np.linalg.solve(H, Hc.T)
        S = Hc @ X
        lam = np.linalg.solve(S, np.eye(n)[i])
        g = X @ lam
        total += np.eye(n)[i] @ lam
        rows.append(g.reshape(K, m))
    return total, np.stack(rows, axis=1)


def test_optimal_norm_and_kernels_match_an_independent_discretisation():
    A, B, C = random_plant(3, 1, 1, seed=7)
    alpha, beta = np.array([1.0, 2.0, 0.5]), np.array([0.3, 1.5, 2.0])  # three different γ
    T = 1.2
    obs = obsjax.FiniteWindow(obsjax.LTI(A, B, C), T, alpha=alpha, beta=beta)
    exact = float(obs.norm()) ** 2
    v1, _ = _discrete_optimum(A, B, C, T, alpha, beta, 121)
    v2, G1d = _discrete_optimum(A, B, C, T, alpha, beta, 241)
    richardson = (4 * v2 - v1) / 3  # the trapezoid is O(h²)
    assert abs(v2 - exact) / exact < 2e-3
    assert abs(richardson - exact) / exact < 2e-5
    G1, _ = obs.kernels(np.linspace(0.0, T, 241))
    np.testing.assert_allclose(G1, G1d, atol=5e-3 * np.abs(G1d).max())


def test_minimality_against_the_gram_observer_and_other_members_of_S():
    for (A, B, C), T, alpha, beta in [
        ((A29, B29, C29), 1.0, np.ones(2), np.ones(2)),
        (random_plant(3, 1, 1, seed=3), 1.0, np.array([1.0, 2.0, 0.7]), np.array([0.5, 0.0, 2.0])),
    ]:
        n = A.shape[0]
        opt = float(obsjax.FiniteWindow(obsjax.LTI(A, B, C), T, alpha=alpha, beta=beta).norm()) ** 2
        gram_norms = []
        for K in (201, 401):
            _, Hc, L, Qy, Qu = _discrete_problem(A, B, C, T, K)

            def weighted(G1rows, L=L, Qy=Qy, Qu=Qu, alpha=alpha, beta=beta, n=n):
                """G1rows: (n, K m) → the norm² (15), G2 from (18)."""
                G2rows = G1rows @ L.T
                return sum(
                    alpha[i] * G1rows[i] @ Qy @ G1rows[i] + beta[i] * G2rows[i] @ Qu @ G2rows[i]
                    for i in range(n)
                )

            # Lemma 1's observer: g1 = (h1|h1')⁻¹ h1, g2 = −H2* g1 (rows of Gram⁻¹ e^{−Aᵀ(T−t)}Cᵀ)
            h1 = Hc / np.diag(Qy)[None, :]  # the values of h1 = (C e^{−A(T−τ)})ᵀ at the nodes
            G_gram = np.linalg.solve(Hc @ h1.T, h1)
            np.testing.assert_allclose(Hc @ G_gram.T, np.eye(n), atol=1e-10)  # it is in S (16)
            gram_norms.append(weighted(G_gram))
        gram = (4 * gram_norms[1] - gram_norms[0]) / 3  # Richardson: the trapezoid is O(h²)
        assert abs(gram - gram_norms[1]) < 2e-4 * gram
        assert gram > opt * (1 + 1e-4)
        # random members of S: the Gram observer plus kernels annihilated by (16)
        rng = np.random.default_rng(0)
        proj = np.eye(Hc.shape[1]) - Hc.T @ np.linalg.solve(Hc @ Hc.T, Hc)
        for _ in range(5):
            G = G_gram + rng.normal(size=G_gram.shape) @ proj * 0.3
            np.testing.assert_allclose(Hc @ G.T, np.eye(n), atol=1e-9)
            assert weighted(G) > opt * (1 + 1e-3)


# ------------------------------------------------------------------------------------------------------
# Item 3: disturbances in the unit ball (Section 2.2)
# ------------------------------------------------------------------------------------------------------


@pytest.mark.extended
def test_disturbance_error_is_bounded_by_the_norm():
    T, K = 1.0, 401
    obs = obsjax.FiniteWindow(MODEL29, T)
    bound = float(obs.norm())
    ts = np.linspace(0.0, T, K)
    w = simpson_weights(K, T)
    G1, G2 = (np.asarray(g) for g in obs.kernels(ts))
    M1 = np.einsum("k,kim,kjm->ij", w, G1, G1)  # ∫ G1 G1ᵀ
    M2 = np.einsum("k,kim,kjm->ij", w, G2, G2)
    assert np.trace(M1 + M2) == pytest.approx(bound**2, rel=1e-8)  # (15) with α = β = I
    rng = np.random.default_rng(1)
    dirs = rng.normal(size=(200, 2))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    evals, evecs = np.linalg.eigh(M1 + M2)
    dirs = np.vstack([dirs, evecs[:, -1]])
    worst = 0.0
    for v in dirs:
        # the worst disturbance for direction v in the unit ball of Y × U: z ∝ (G1ᵀ v, G2ᵀ v)
        z1, z2 = G1[:, :, 0] @ v, G2[:, :, 0] @ v
        scale = np.sqrt(w @ (z1**2 + z2**2))
        z1, z2 = z1 / scale, z2 / scale
        # the estimation error is the observer applied to the disturbance alone (linearity of (14))
        err = np.asarray(obs.estimate_window(ts, z1[:, None], z2[:, None]))
        assert np.linalg.norm(err) <= bound * (1 + 1e-9)
        worst = max(worst, np.linalg.norm(err))
    assert worst == pytest.approx(np.sqrt(evals[-1]), rel=1e-6)  # attained: √λmax(M1 + M2) ≤ norm
    # random disturbances inside the ball stay within the bound too
    for _ in range(20):
        z1, z2 = rng.normal(size=K), rng.normal(size=K)
        r = rng.uniform() / np.sqrt(w @ (z1**2 + z2**2))
        err = np.asarray(obs.estimate_window(ts, (r * z1)[:, None], (r * z2)[:, None]))
        assert np.linalg.norm(err) <= bound
    # with z1 and z2 each in its own unit ball the worst error is max_v √(vᵀM1v) + √(vᵀM2v): above
    # √λmax(M1+M2), at most √2·norm (the paper's inequality holds for the product ball).
    sep = max(np.sqrt(v @ M1 @ v) + np.sqrt(v @ M2 @ v) for v in dirs)
    assert np.sqrt(evals[-1]) < sep <= np.sqrt(2) * bound
    assert (
        sep > bound
    )  # (29), T = 1: about 2.535 > 2.093, a counterexample to the separate-ball reading


# ------------------------------------------------------------------------------------------------------
# Item 5: gradients of the norm with respect to T, α, β
# ------------------------------------------------------------------------------------------------------


def _fd(f, x, h=1e-3):
    """Central finite difference, five-point stencil (truncation O(h⁴); h large enough that the
    ~1e-13 relative rounding of the norm does not dominate)."""
    return (-f(x + 2 * h) + 8 * f(x + h) - 8 * f(x - h) + f(x - 2 * h)) / (12 * h)


@pytest.mark.extended
def test_gradient_of_norm_wrt_T_alpha_beta_general_formula():
    A, B, C = random_plant(3, 1, 1, seed=5)
    model = obsjax.LTI(A, B, C)
    alpha, beta = np.array([1.0, 2.0, 0.5]), np.array([0.3, 1.5, 2.0])
    obs = obsjax.FiniteWindow(model, 1.3, alpha=alpha, beta=beta)
    g = eqx.filter_grad(lambda o: o.norm())(obs)
    h = 1e-3
    dT = _fd(lambda T: float(obsjax.FiniteWindow(model, T, alpha=alpha, beta=beta).norm()), 1.3, h)
    assert float(g.T) == pytest.approx(dT, rel=1e-6)
    for i in range(3):
        e = np.eye(3)[i]
        da = _fd(
            lambda a, e=e: float(
                obsjax.FiniteWindow(model, 1.3, alpha=alpha + a * e, beta=beta).norm()
            ),
            0.0,
            h,
        )
        db = _fd(
            lambda b, e=e: float(
                obsjax.FiniteWindow(model, 1.3, alpha=alpha, beta=beta + b * e).norm()
            ),
            0.0,
            h,
        )
        assert float(g.alpha[i]) == pytest.approx(da, rel=1e-6, abs=1e-9)
        assert float(g.beta[i]) == pytest.approx(db, rel=1e-6, abs=1e-9)


@pytest.mark.extended
def test_gradient_of_norm_formula_28_matches_closed_form_and_fd():
    obs = obsjax.FiniteWindow(MODEL29, 1.0)
    g = eqx.filter_grad(lambda o: o.norm())(obs)
    # d(31)/dT by differentiating the closed form (independent of the kernels)
    d31 = jax.grad(
        lambda T: jnp.sqrt(
            (3 * jnp.sinh(2 * T) + jnp.sin(2 * T)) / (4 * (jnp.sinh(T) ** 2 - jnp.sin(T) ** 2))
        )
    )(1.0)
    assert float(g.T) == pytest.approx(float(d31), rel=1e-9)
    assert float(g.T) == pytest.approx(_fd(norm31, 1.0), rel=1e-7)
    # α, β: finite differences of the true optimum (moving γ off 1 needs (25)); equal by the envelope
    # theorem at γ = 1
    h = 1e-3
    for i in range(2):
        e = np.eye(2)[i]
        da = _fd(
            lambda a, e=e: float(
                obsjax.FiniteWindow(MODEL29, 1.0, alpha=1 + a * e, beta=np.ones(2)).norm()
            ),
            0.0,
            h,
        )
        db = _fd(
            lambda b, e=e: float(
                obsjax.FiniteWindow(MODEL29, 1.0, alpha=np.ones(2), beta=1 + b * e).norm()
            ),
            0.0,
            h,
        )
        assert float(g.alpha[i]) == pytest.approx(da, rel=1e-6)
        assert float(g.beta[i]) == pytest.approx(db, rel=1e-6)


# ------------------------------------------------------------------------------------------------------
# Item 4: the sliding-window observer in simulate, and the closed loop (33)-(35) with u = P x̂
# ------------------------------------------------------------------------------------------------------


@pytest.mark.extended
def test_sliding_window_observer_open_loop_unstable_plant():
    """x̂(t) = x(t) for t ≥ T; at the instants t0 + kh < T, x̂ equals (14) over [t − T, t] computed from
    SciPy-simulated data and the history (36) (the free response through x̂0)."""
    A, B, C = random_plant(3, 1, 2, seed=11)
    plant = obsjax.LTI(A, B, C)
    T, N = 1.0, 6
    obs = obsjax.FiniteWindow(plant, T, alpha=[1.0, 2.0, 1.0], beta=[0.5, 1.0, 2.0], n_chunks=N)
    amp, frq = np.array([[0.8, -0.5], [0.3, 1.0]]), np.array([[1.3, 3.1], [0.7, 2.2]])

    def u_np(t):
        return np.sum(amp * np.sin(frq * t), axis=1)  # u(0) = 0 = the history's input

    u = obsjax.signals.multisine(amp, frq)
    x0 = np.array([1.0, -0.5, 0.8])
    null = sl.null_space(C)[:, 0]
    xhat0 = x0 + 0.7 * null  # y continuous at t0, so Simpson panels stay smooth
    ts = np.linspace(0.0, 2.0, 2 * N + 1)
    tr = obsjax.simulate(plant, obs, x0, xhat0, ts, u=u, rtol=1e-10, atol=1e-12)
    err = np.asarray(tr.error)
    assert np.abs(err[N:]).max() < 1e-7 * np.abs(np.asarray(tr.x)).max()
    assert np.abs(err[: N // 2]).min() > 1e-3  # before T the (wrong) history is still in the window
    np.testing.assert_allclose(np.asarray(tr.xhat[0]), xhat0, atol=1e-12)
    sol = si.solve_ivp(
        lambda t, x: A @ x + B @ u_np(t), (0.0, 2.0), x0, rtol=1e-12, atol=1e-12, dense_output=True
    )
    np.testing.assert_allclose(np.asarray(tr.x), sol.sol(ts).T, atol=1e-7)
    for k in (1, 3, 5):
        tk = ts[k]
        # the same grid size as the (3, 1, 2) plant above (kernels compiled once); t0 = 0 falls on an
        # even node, a Simpson panel edge, so the history's kink does not spoil the O(h⁴) rule
        grid = np.linspace(tk - T, tk, 50 * N + 1)
        ys = np.stack([C @ (sl.expm(A * t) @ xhat0) if t < 0 else C @ sol.sol(t) for t in grid])
        us = np.stack([np.zeros(2) if t < 0 else u_np(t) for t in grid])
        ref = np.asarray(obs.estimate_window(grid, ys, us, rule="simpson"))
        np.testing.assert_allclose(np.asarray(tr.xhat[k]), ref, atol=1e-6 * np.linalg.norm(ref))


def test_lemma4_exponential_solutions_give_the_spectrum_of_A_plus_BP():
    """(41): for x(t) = x0 e^{λt}, u = u0 e^{λt} with (λ − A) x0 = B u0 the observer returns x0, so the
    characteristic matrix of (40), I − P·[∫G1(T+s) C x̂(λ) e^{λs} ds + ∫G2(T+s) e^{λs} ds], has the zeros of
    det(λ − A − BP) (Lemma 4)."""
    T, K = 1.0, 401
    s = np.linspace(0.0, T, K)
    w = simpson_weights(K, T)
    G1, G2 = (np.asarray(g) for g in obsjax.FiniteWindow(MODEL29, T).kernels(s))
    P = np.array([[-2.0, -3.0]])

    def transfer(lam):  # the observer's response to exponential data, per unit u0
        xu = np.linalg.solve(lam * np.eye(2) - A29, B29)  # x0 per unit u0
        e = np.exp(lam * (s - T))
        return np.einsum("k,kim,mj,k->ij", w, G1, C29 @ xu, e) + np.einsum(
            "k,kij,k->ij", w, G2, e
        ), xu

    for lam in (0.3 + 0.0j, -0.7 + 1.2j, 1.5 - 2.0j, -2.5 + 0.4j):
        obs_resp, xu = transfer(lam)
        np.testing.assert_allclose(obs_resp, xu, atol=1e-8)  # the observer reproduces x0
        char = 1.0 - (P @ obs_resp)[0, 0]
        np.testing.assert_allclose(
            char,
            np.linalg.det(lam * np.eye(2) - A29 - B29 @ P) / np.linalg.det(lam * np.eye(2) - A29),
            atol=1e-8,
        )
    # and the characteristic matrix vanishes exactly at eig(A + BP)
    for lam in np.linalg.eigvals(A29 + B29 @ P):
        obs_resp, _ = transfer(complex(lam))
        assert abs(1.0 - (P @ obs_resp)[0, 0]) < 1e-8


@pytest.mark.extended
def test_closed_loop_deadbeat_and_decay_of_A_plus_BP():
    """(33)-(35) on the double integrator (29), u = P x̂ with eig(A + BP) = {−1, −2}: for t ≥ T the state
    is the state-feedback trajectory of (42) (Lemma 4) and decays at the rate of eig(A + BP)."""
    P = np.array([[-2.0, -3.0]])
    Acl = A29 + B29 @ P
    assert np.allclose(np.sort(np.linalg.eigvals(Acl).real), [-2.0, -1.0])
    T, N = 1.0, 10
    obs = obsjax.FiniteWindow(MODEL29, T, n_chunks=N)
    ts = np.linspace(0.0, 8.0, 81)
    x0, xhat0 = np.array([1.0, -0.5]), np.array([0.3, 0.2])
    # max_segments above the 80 needed (zero-length segments at the end)
    tr = obsjax.simulate(
        MODEL29,
        obs,
        x0,
        xhat0,
        ts,
        controller=lambda t, xh: jnp.asarray(P) @ xh,
        rtol=1e-10,
        atol=1e-12,
        max_segments=90,
    )
    x = np.asarray(tr.x)
    iT = 10  # ts[10] = T
    ref = np.stack([sl.expm(Acl * (t - T)) @ x[iT] for t in ts[iT:]])
    np.testing.assert_allclose(x[iT:], ref, atol=1e-8)
    np.testing.assert_allclose(np.asarray(tr.xhat)[iT:], x[iT:], atol=1e-8)
    assert np.abs(np.asarray(tr.error)[:iT]).max() > 0.1  # not exact before the window fills
    # before T the loop is not (42): the state differs from the state feedback from x0
    ref0 = np.stack([sl.expm(Acl * t) @ x0 for t in ts[: iT + 1]])
    assert np.abs(x[: iT + 1] - ref0).max() > 1e-2
    # decay: fitted slope of log‖x‖ on [5, 8] is the slowest eigenvalue −1
    sel = ts >= 5.0
    slope = np.polyfit(ts[sel], np.log(np.linalg.norm(x[sel], axis=1)), 1)[0]
    assert slope == pytest.approx(np.max(np.linalg.eigvals(Acl).real), abs=0.02)


# ------------------------------------------------------------------------------------------------------
# Bad input: one test per ValueError
# ------------------------------------------------------------------------------------------------------


def test_model_must_be_lti():
    ltv = obsjax.LTV(lambda t: jnp.asarray(A29), lambda t: jnp.asarray(C29))
    with pytest.raises(ValueError, match="`model` must be an obsjax.LTI"):
        obsjax.FiniteWindow(ltv, 1.0)


def test_T_must_be_positive():
    with pytest.raises(ValueError, match=r"`T` \(the window length\) must be > 0, got -1.0"):
        obsjax.FiniteWindow(MODEL29, -1.0)


def test_T_must_be_scalar():
    with pytest.raises(ValueError, match="`T` must be a scalar"):
        obsjax.FiniteWindow(MODEL29, [1.0, 2.0])


def test_alpha_shape():
    with pytest.raises(ValueError, match="`alpha` must have length 2"):
        obsjax.FiniteWindow(MODEL29, 1.0, alpha=[1.0, 1.0, 1.0])


def test_alpha_positive():
    with pytest.raises(ValueError, match="`alpha`.*must be > 0"):
        obsjax.FiniteWindow(MODEL29, 1.0, alpha=[1.0, 0.0])


def test_beta_nonnegative():
    with pytest.raises(ValueError, match="`beta`.*must be >= 0"):
        obsjax.FiniteWindow(MODEL29, 1.0, beta=[1.0, -0.1])


def test_unobservable_model():
    with pytest.raises(ValueError, match="observable.*rank 1, expected 2"):
        obsjax.FiniteWindow(obsjax.LTI(A29, B29, [[0.0, 1.0]]), 1.0)


def test_unknown_formula():
    with pytest.raises(ValueError, match="`formula` must be one of"):
        obsjax.FiniteWindow(MODEL29, 1.0, formula="(29)")


def test_formula_28_needs_gamma_one():
    with pytest.raises(ValueError, match=r"needs every γᵢ = βᵢ/αᵢ = 1"):
        obsjax.FiniteWindow(MODEL29, 1.0, alpha=[1.0, 1.0], beta=[1.0, 2.0], formula="(28)")


def test_n_chunks_positive_integer():
    with pytest.raises(ValueError, match="`n_chunks` must be an integer >= 1"):
        obsjax.FiniteWindow(MODEL29, 1.0, n_chunks=0)


def test_check_after_tree_at():
    obs = eqx.tree_at(
        lambda o: o.alpha, obsjax.FiniteWindow(MODEL29, 1.0, formula="(25)"), jnp.array([1.0, -2.0])
    )
    with pytest.raises(ValueError, match="`alpha`.*must be > 0"):
        obs.check()


def test_T_checked_under_jit():
    obs = obsjax.FiniteWindow(MODEL29, 1.0)
    with pytest.raises(Exception, match="must be > 0"):
        jax.block_until_ready(jax.jit(lambda T: eqx.tree_at(lambda o: o.T, obs, T).norm())(-1.0))


_TS = np.linspace(0.0, 1.0, 11)


def test_window_span():
    with pytest.raises(ValueError, match="`ts` must span the window"):
        obsjax.FiniteWindow(MODEL29, 1.0).estimate_window(
            _TS * 0.9, np.zeros((11, 1)), np.zeros((11, 1))
        )


@pytest.mark.extended
def test_window_span_is_checked_in_the_time_unit_of_the_window():
    """The span check allowed an absolute 1e-9: a window of 1e-6 (the plant in seconds, its dynamics in
    microseconds) accepted a grid 0.05 % too long.  It is now 1e-9 of T plus the rounding of the times,
    eagerly and under jit, and a grid ending at t = 1e3 still passes."""
    import jax

    model = obsjax.LTI([[0.0, 1e6], [0.0, 0.0]], [[0.0], [1e6]], [[2.0, 0.0]])
    obs = obsjax.FiniteWindow(model, 1e-6)
    z = np.zeros((11, 1))
    with pytest.raises(ValueError, match="`ts` must span the window"):
        obs.estimate_window(np.linspace(0.0, 1.0005e-6, 11), z, z)
    with pytest.raises(Exception, match="must span"):
        jax.block_until_ready(jax.jit(lambda a, b, c: obs.estimate_window(a, b, c))(np.linspace(0.0, 1.0005e-6, 11), z, z))
    ts = 1e3 + np.linspace(-1e-6, 0.0, 11)  # rounding of ts − ts[0] ≈ 1e-13, 1e-7 of T
    y, u = np.cos(1e6 * ts)[:, None], np.sin(1e6 * ts)[:, None]
    # the same problem in μs (the kernels scale by 1e6 and the norm's weighting with them)
    ref = obsjax.FiniteWindow(MODEL29, 1.0).estimate_window(np.linspace(0.0, 1.0, 11), y, u, rule="trapezoid")
    np.testing.assert_allclose(obs.estimate_window(ts, y, u, rule="trapezoid"), ref, rtol=1e-6, atol=1e-9)


@pytest.mark.extended
def test_kernels_are_covariant_under_a_change_of_state_units():
    """Each row of (G1, G2) is its own minimum-norm problem, so with x' = D x the kernels are D G1, D G2
    exactly.  The Hamiltonians were exponentiated in the user's units: with D spanning 1e-2 … 1e3 the
    reconstruction was 7e-8 off, and with 1e-4 … 1e4 the design overflowed ("not finite").  The design
    now runs in balanced state units."""
    A = np.array([[0.0, 1.0, 0.0, 0.0], [-2.0, -0.4, 0.5, 0.0], [0.0, 0.0, -1.0, 2.0], [0.3, 0.0, -2.0, -0.5]])
    B, C = np.array([[0.0], [1.0], [0.0], [0.5]]), np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    s = np.linspace(0.0, 1.0, 5)
    G1, G2 = obsjax.FiniteWindow(obsjax.LTI(A, B, C), 1.0).kernels(s)
    for d in (np.array([1e-2, 1e-1, 1e2, 1e3]), np.array([1e-4, 1e-1, 1e2, 1e4])):
        model = obsjax.LTI(d[:, None] * A / d[None, :], d[:, None] * B, C / d[None, :])
        for alpha in (None, np.array([1.0, 2.0, 0.5, 1.0])):  # formulas (28) and (25)
            obs = obsjax.FiniteWindow(model, 1.0, alpha=alpha)
            G1d, G2d = obs.kernels(s)
            if alpha is None:
                np.testing.assert_allclose(np.asarray(G1d) / d[:, None], G1, rtol=1e-9, atol=1e-9 * np.abs(G1).max())
                np.testing.assert_allclose(np.asarray(G2d) / d[:, None], G2, rtol=1e-9, atol=1e-9 * np.abs(G2).max())
            # the defining property in the new units: ∫₀ᵀ G1(σ) C' e^{A'σ} dσ = e^{A'T} (u = 0)
            q = np.linspace(0.0, 1.0, 401)
            G1q = np.asarray(obs.kernels(q)[0])
            E = np.stack([sl.expm(np.asarray(model.A) * t) for t in q])
            f = np.einsum("kim,mj,kjl->kil", G1q, np.asarray(model.C), E)
            w = np.full(q.size, 2.0); w[1:-1:2] = 4.0; w[0] = w[-1] = 1.0  # Simpson
            lhs = np.einsum("k,kij->ij", w * (q[1] - q[0]) / 3.0, f)
            rhs = sl.expm(np.asarray(model.A))
            np.testing.assert_allclose(lhs / d[:, None] * d[None, :], rhs / d[:, None] * d[None, :], atol=1e-8)


@pytest.mark.extended
def test_balancing_ignores_rounding_residue_and_negligible_couplings():
    """The balanced design fitted every nonzero entry: a coupling A21 = 1e-30 in (29) put the
    reconstruction 1.6e-8 off (1e-100: refused as "not finite"), and 1e-17 residue of a similarity
    round trip made a 4-state design overflow.  Both are now as in the user's units."""
    for tiny in (1e-30, 1e-100):
        A = np.array([[0.0, 1.0], [tiny, 0.0]])
        obs = obsjax.FiniteWindow(obsjax.LTI(A, [[0.0], [1.0]], [[2.0, 0.0]]), 1.0)
        assert float(obs.norm()) == pytest.approx(norm31(1.0), rel=1e-12)  # the closed form (31)
        G1, G2 = obs.kernels(np.linspace(0.0, 1.0, 3))
        G1r, G2r = obsjax.FiniteWindow(MODEL29, 1.0).kernels(np.linspace(0.0, 1.0, 3))
        np.testing.assert_allclose(G1, G1r, rtol=1e-12, atol=1e-12)
    rng = np.random.default_rng(1)
    A = np.array([[0.0, 1.0, 0.0, 0.0], [-2.0, -0.4, 0.5, 0.0], [0.0, 0.0, 0.0, 1.0], [0.3, 0.0, -2.0, -0.5]])
    B, C = np.array([[0.0], [1.0], [0.0], [0.0]]), np.array([[1.0, 0.0, 0.0, 0.0]])
    Q, _ = np.linalg.qr(rng.standard_normal((4, 4)))
    A2, B2, C2 = Q.T @ (Q @ A @ Q.T) @ Q, Q.T @ (Q @ B), (C @ Q.T) @ Q  # residue ~1e-16 where A has zeros
    assert np.count_nonzero(A2) > np.count_nonzero(A)
    ref = float(obsjax.FiniteWindow(obsjax.LTI(A, B, C), 1.0).norm())
    assert float(obsjax.FiniteWindow(obsjax.LTI(A2, B2, C2), 1.0).norm()) == pytest.approx(ref, rel=1e-9)


def test_window_ys_shape():
    with pytest.raises(ValueError, match=r"`ys` must have shape \(11, 1\)"):
        obsjax.FiniteWindow(MODEL29, 1.0).estimate_window(_TS, np.zeros((11, 2)), np.zeros((11, 1)))


def test_window_us_shape():
    with pytest.raises(ValueError, match=r"`us` must have shape \(11, 1\)"):
        obsjax.FiniteWindow(MODEL29, 1.0).estimate_window(_TS, np.zeros((11, 1)), np.zeros(11))


def test_window_increasing():
    with pytest.raises(ValueError, match="strictly increasing"):
        obsjax.FiniteWindow(MODEL29, 1.0).estimate_window(_TS[::-1], np.zeros((11, 1)))


def test_window_too_few_samples():
    with pytest.raises(ValueError, match="at least 2 sample times"):
        obsjax.FiniteWindow(MODEL29, 1.0).estimate_window([1.0], np.zeros((1, 1)))


def test_simpson_needs_odd_count():
    ts = np.linspace(0.0, 1.0, 10)
    with pytest.raises(ValueError, match="odd number of samples"):
        obsjax.FiniteWindow(MODEL29, 1.0).estimate_window(ts, np.zeros((10, 1)), rule="simpson")


def test_simpson_needs_uniform_grid():
    ts = np.array([0.0, 0.1, 0.5, 0.6, 1.0])
    with pytest.raises(ValueError, match="uniform grid"):
        obsjax.FiniteWindow(MODEL29, 1.0).estimate_window(ts, np.zeros((5, 1)), rule="simpson")


def test_unknown_rule():
    with pytest.raises(ValueError, match="`rule` must be"):
        obsjax.FiniteWindow(MODEL29, 1.0).estimate_window(_TS, np.zeros((11, 1)), rule="gauss")


@pytest.mark.slow
def test_gradient_through_the_closed_loop_wrt_T():
    """d/dT of a closed-loop cost through `simulate` (T moves the reset instants and the kernels) against
    central finite differences.  T = 1.03 keeps the instants off the save times (where x(tᵢ) has a kink
    in T, since u = P x̂ jumps at every instant before the window fills)."""
    P = jnp.array([[-2.0, -3.0]])
    ts = jnp.linspace(0.0, 4.0, 41)

    def loss(T):
        obs = eqx.tree_at(lambda o: o.T, obsjax.FiniteWindow(MODEL29, 1.0, n_chunks=5), T)
        tr = obsjax.simulate(
            MODEL29,
            obs,
            jnp.array([1.0, -0.5]),
            jnp.array([0.3, 0.2]),
            ts,
            controller=lambda t, xh: P @ xh,
            rtol=1e-10,
            atol=1e-12,
            max_segments=40,
        )
        return jnp.sum(tr.x[:, 0] ** 2) * 0.1

    g = jax.jit(jax.grad(loss))(1.03)
    lf = jax.jit(loss)
    h = 1e-4
    assert float(g) == pytest.approx(float((lf(1.03 + h) - lf(1.03 - h)) / (2 * h)), rel=1e-6)


@pytest.mark.extended
def test_estimate_window_grid_checks_hold_under_jit():
    """Eagerly a non-uniform grid with rule='simpson' and a non-monotone ts are refused; under jit both ran
    (x̂(T) 0.46 off on the non-uniform Simpson grid).  Now both raise there too; a valid grid is unchanged."""
    import jax

    A, B, C = np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0]]), np.array([[2.0, 0.0]])
    obs = obsjax.FiniteWindow(obsjax.LTI(A=A, B=B, C=C), T=1.0)
    g = np.sort(np.concatenate([[0.0, 1.0], np.random.default_rng(0).uniform(0.0, 1.0, 99)]))
    y, u = np.cos(g)[:, None], np.sin(g)[:, None]
    with pytest.raises(Exception, match="Simpson's rule needs a uniform grid"):
        jax.block_until_ready(jax.jit(lambda a, b, c: obs.estimate_window(a, b, c, rule="simpson"))(g, y, u))
    ts = np.linspace(0.0, 1.0, 101)
    swapped = ts.copy()
    swapped[[10, 20]] = swapped[[20, 10]]
    with pytest.raises(Exception, match="`ts` must be strictly increasing"):
        jax.block_until_ready(jax.jit(lambda a, b, c: obs.estimate_window(a, b, c, rule="trapezoid"))(swapped, y, u))
    yu = (np.cos(ts)[:, None], np.sin(ts)[:, None])
    np.testing.assert_allclose(
        np.asarray(jax.jit(lambda a, b, c: obs.estimate_window(a, b, c, rule="simpson"))(ts, *yu)),
        np.asarray(obs.estimate_window(ts, *yu, rule="simpson")), rtol=1e-12, atol=1e-14,
    )


def test_delay_closed_loop_refuses_bad_input_by_name():
    """NaN or inf in P, x0 or the noise samples gave NaN trajectories without a word, a steps_per_window of
    2.7 was truncated to 2, and a negative or NaN t1 failed with an unrelated TypeError or ValueError."""
    model = obsjax.LTI([[0.0, 1.0], [-1.0, 0.2]], [[0.0], [1.0]], [[1.0, 0.0]])
    fw = obsjax.FiniteWindow(model, 1.0)
    P, x0, xh0 = np.array([[-2.0, -3.0]]), np.array([1.0, 0.0]), np.zeros(2)
    cases = [
        (dict(P=np.array([[np.nan, -3.0]])), "`P` must be finite"),
        (dict(x0=np.array([np.inf, 0.0])), "`x0` must be finite"),
        (dict(xhat0=np.array([0.0, np.nan])), "`xhat0` must be finite"),
        (dict(steps_per_window=2.7), "`steps_per_window` must be an integer >= 2"),
        (dict(steps_per_window=1), "`steps_per_window` must be an integer >= 2"),
        (dict(t1=-1.0), "`t1` must be a concrete finite time > 0"),
        (dict(t1=float("nan")), "`t1` must be a concrete finite time > 0"),
        (dict(steps_per_window=4, v=np.full((21, 1), np.nan)), "`v` must be finite"),
    ]
    for change, msg in cases:
        a = dict(P=P, x0=x0, xhat0=xh0, t1=5.0)
        a.update(change)
        with pytest.raises(ValueError, match=msg):
            obsjax.delay_closed_loop(fw, a.pop("P"), a.pop("x0"), a.pop("xhat0"), a.pop("t1"), **a)
