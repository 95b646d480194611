"""Hassan thesis chapter 4: the identifier (4.1)-(4.2), the minimal (4.12)-(4.18) and non-minimal (4.19)
adaptive observers, and the Morgan–Narendra conditions (4.20)-(4.21).

Independent references: SciPy ``solve_ivp`` integrations of the equations written here with NumPy (no obsjax
code), closed forms (the auxiliary matrices C_i, window integrals of sinusoids), NumPy polynomial division,
defining properties (the error equivalence of the proposition of section 4.5.1, the constant unexcited
component of (4.2), Lyapunov functions), and central finite differences for every adaptation gain.
Plants: a 3rd-order plant with two unknown parameters per channel (none of them is an example of the thesis).
Runs share shapes (save grid, gains, input shape) so that each law compiles once.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate

import obsjax
from obsjax._reproduce.adaptive import (
    ADAPTIVE_3,
    IDENTIFIER_3,
    SCALAR_420,
    IdentifierRegressor,
    chapter4_gain,
    simulate_420,
    simulate_chapter4,
    simulate_identifier,
)
from obsjax.observers import auxiliary_matrices

EX = ADAPTIVE_3
A3, B3 = np.asarray(EX["a"]), np.asarray(EX["b"])
T1, NUM = 200.0, 401


# =========================================================================== independent NumPy pieces
def c_closed_form(d):
    """C_i of the auxiliary signals from the closed form of the recursion q_{m+1} = s q_m − x_m:
    q_m = −s^{m−1−i} Σ_{l≥m} d_l s^{n−l} (i < m), q_m = s^{n−i} Σ_{l<m} d_l s^{m−1−l} (i ≥ m), 1-based."""
    n = len(d)
    C = np.zeros((n, n, n - 1))
    for i in range(1, n + 1):
        for m in range(2, n + 1):
            q = np.zeros(2 * n)  # ascending coefficients
            if i < m:
                for ell in range(m, n + 1):
                    q[m - 1 - i + n - ell] -= d[ell - 1]
            else:
                for ell in range(1, m):
                    q[n - i + m - 1 - ell] += d[ell - 1]
            assert np.all(q[n - 1 :] == 0)
            C[i - 1, m - 1] = q[: n - 1]
    return C


def companion(coeffs):
    """A = [−coeffs | I; 0] (first column −coeffs, ones on the superdiagonal)."""
    n = len(coeffs)
    A = np.eye(n, k=1)
    A[:, 0] = -np.asarray(coeffs)
    return A


def filt(omega, sig, delta):
    """ω̇ of 1/D(s) in controllable form and v = [s^{n−i}/D sig]_{i=1..n}."""
    r = len(delta)
    top = sig - np.dot(np.asarray(delta)[::-1], omega)
    domega = np.r_[omega[1:], top] if r else omega
    v = np.r_[top, omega[::-1]] if r else np.array([sig])
    return domega, v


def u_of(t, amps, freqs):
    return sum(A * np.sin(w * t) for A, w in zip(amps, freqs))


# =========================================================================== shared runs
@pytest.fixture(scope="module")
def ch4_runs():
    """Minimal and non-minimal observers, rich and poor input (4 runs, 2 compilations)."""
    out = {}
    for kind in ("minimal", "nonminimal"):
        for which, amps in (("rich", EX["amplitudes"]), ("poor", EX["poor_amplitudes"])):
            out[kind, which] = simulate_chapter4(
                kind, EX, gamma=5.0, amplitudes=amps, t1=T1, num=NUM
            )
    return out


# =========================================================================== minimal observer (4.12)-(4.18)
@pytest.mark.parametrize("poles", [[-1.0], [-2.0, -3.0], [-1.0 + 1.0j, -1.0 - 1.0j, -0.5]])
def test_auxiliary_matrices(poles):
    """C_i against the closed form, and the defining property (sI − K) C_i b(s)/D(s) = e_i − d s^{n−i}/D(s)
    at complex s, b(s) = [1, s, ..., s^{n−2}], with det(sI − K) = (s + λ) D(s) (NumPy only)."""
    D = np.real(np.poly(poles))
    d = D.copy()
    n = len(d)
    C = np.asarray(auxiliary_matrices(jnp.asarray(d)))
    np.testing.assert_allclose(C, c_closed_form(d), atol=1e-12)
    lam = 0.7
    K = companion(np.real(np.poly(np.r_[-lam, poles]))[1:])
    for s in (0.4 + 1.3j, -0.2 + 0.5j, 1.7):
        basis = np.array([s**j for j in range(n - 1)])
        Ds = np.polyval(D, s)
        for i in range(n):
            lhs = (s * np.eye(n) - K) @ (C[i] @ basis / Ds)
            rhs = np.eye(n)[i] - d * s ** (n - 1 - i) / Ds
            np.testing.assert_allclose(lhs, rhs, atol=1e-12)


def test_minimal_error_equivalence_pointwise():
    """The proposition of section 4.5.1: at any state, ε = e − ρ (ρ = Σ φ_i C_i ω⁽¹⁾ + ψ_i C_i ω⁽²⁾) obeys
    ε̇ = K ε + d θᵀ v, with θ = [a − â; b̂ − b] (jvp of the plant + observer vector field; C_i in closed form)."""
    n = 3
    obs = obsjax.MinimalAdaptiveObserver(
        n, [-2.0, -3.0], 0.5, jnp.array([1.0, 2.0, 3.0, 0.5, 1.5, 2.5])
    )
    plant = obsjax.kreisselmeier_form(A3, B3)
    d = np.r_[1.0, np.real(np.poly([-2.0, -3.0]))[1:]]
    C = c_closed_form(d)
    K = companion(np.real(np.poly([-0.5, -2.0, -3.0]))[1:])
    rng = np.random.default_rng(0)
    for _ in range(3):
        x = rng.normal(size=n)
        z = obsjax.observers._minimal_adaptive.MinimalAdaptiveState(
            *(jnp.asarray(rng.normal(size=s)) for s in (n, n, n, n - 1, n - 1))
        )
        u = rng.normal(size=1)
        y = plant.h(0.0, x, u)
        dz = obs.vector_field(0.0, z, y, u)
        dx = np.asarray(plant.f(0.0, x, u))
        phi, psi = A3 - np.asarray(z.a), np.asarray(z.b) - B3
        rho = np.einsum("i,imj,j->m", phi, C, z.omega_y) + np.einsum(
            "i,imj,j->m", psi, C, z.omega_u
        )
        drho = (
            np.einsum("i,imj,j->m", -np.asarray(dz.a), C, z.omega_y)
            + np.einsum("i,imj,j->m", phi, C, dz.omega_y)
            + np.einsum("i,imj,j->m", np.asarray(dz.b), C, z.omega_u)
            + np.einsum("i,imj,j->m", psi, C, dz.omega_u)
        )
        eps = np.asarray(z.xhat) - x - rho
        deps = np.asarray(dz.xhat) - dx - drho
        _, v1 = filt(np.asarray(z.omega_y), float(y[0]), d[1:])
        _, v2 = filt(np.asarray(z.omega_u), float(u[0]), d[1:])
        np.testing.assert_allclose(deps, K @ eps + d * (phi @ v1 + psi @ v2), atol=1e-11)
        assert abs(rho[0]) < 1e-12  # ρ_1 ≡ 0: e and ε have the same output


def test_minimal_lyapunov_derivative_pointwise_full_gain():
    """With a full s.p.d. Γ and known a_1, b_1 (held at the truth): V̇ = −λ ε_1² + ε_1 η at any state, where
    η = hᵀK ε + λ ε_1 and ε = e − ρ (jvp of V along the plant + observer flow; ρ from the closed-form C_i)."""
    n, lam = 3, 0.5
    rng = np.random.default_rng(1)
    M = rng.normal(size=(6, 6))
    Gamma = M @ M.T + 0.5 * np.eye(6)
    obs = obsjax.MinimalAdaptiveObserver(n, [-2.0, -3.0], lam, Gamma, adapt=EX["adapt"])
    plant = obsjax.kreisselmeier_form(A3, B3)
    d = np.r_[1.0, np.real(np.poly([-2.0, -3.0]))[1:]]
    C = c_closed_form(d)
    K = companion(np.real(np.poly([-lam, -2.0, -3.0]))[1:])
    a, b = jnp.asarray(A3), jnp.asarray(B3)
    for _ in range(3):
        x = jnp.asarray(rng.normal(size=n))
        z = obs.init(0.0, jnp.asarray(rng.normal(size=n)), None)
        z = eqx.tree_at(
            lambda s: (s.a, s.b, s.omega_y, s.omega_u),
            z,
            tuple(
                jnp.asarray(v)
                for v in (
                    np.r_[A3[0], rng.normal(size=2)],
                    np.r_[B3[0], rng.normal(size=2)],
                    rng.normal(size=2),
                    rng.normal(size=2),
                )
            ),
        )
        u = jnp.asarray(rng.normal(size=1))
        dz = obs.vector_field(0.0, z, plant.h(0.0, x, u), u)
        dx = plant.f(0.0, x, u)
        _, dV = jax.jvp(lambda zz, xx: obs.lyapunov(zz, xx[:1], a, b), (z, x), (dz, dx))
        phi, psi = A3 - np.asarray(z.a), np.asarray(z.b) - B3
        rho = np.einsum("i,imj,j->m", phi, C, z.omega_y) + np.einsum(
            "i,imj,j->m", psi, C, z.omega_u
        )
        eps = np.asarray(z.xhat - x) - rho
        eta = (K @ eps)[0] + lam * eps[0]
        assert float(dV) == pytest.approx(-lam * eps[0] ** 2 + eps[0] * eta, rel=1e-9, abs=1e-12)


def minimal_rhs(example, G, amps):
    """Plant (4.12) + observer (4.14), filters, (4.18), written with NumPy (closed-form C_i)."""
    a, b = np.asarray(example["a"]), np.asarray(example["b"])
    n = len(a)
    mask = np.asarray(example["adapt"], float)
    delta = np.real(np.poly(example["filter_poles"]))[1:]
    d = np.r_[1.0, delta]
    k = np.real(np.poly(np.r_[-example["lam"], example["filter_poles"]]))[1:]
    K, Ap, C = companion(k), companion(a), c_closed_form(d)

    def rhs(t, w):
        x, xh, ah, bh = w[:n], w[n : 2 * n], w[2 * n : 3 * n], w[3 * n : 4 * n]
        oy, ou = w[4 * n : 5 * n - 1], w[5 * n - 1 :]
        u = u_of(t, amps, example["frequencies"])
        y = x[0]
        doy, v1 = filt(oy, y, delta)
        dou, v2 = filt(ou, u, delta)
        dtheta = -(xh[0] - y) * mask * G * np.r_[v1, v2]
        dphi, dpsi = dtheta[:n], dtheta[n:]
        wsig = np.einsum("i,imj,j->m", dphi, C, oy) + np.einsum("i,imj,j->m", dpsi, C, ou)
        dxh = K @ xh + (k - ah) * y + bh * u + wsig
        return np.r_[Ap @ x + b * u, dxh, -dphi, dpsi, doy, dou]

    return rhs


@pytest.mark.extended
def test_minimal_matches_scipy(ch4_runs):
    """x̂, â, b̂ of the simulation equal a SciPy DOP853 integration of (4.12)-(4.18) as rebuilt."""
    ts, _, traj, _ = ch4_runs["minimal", "rich"]
    n = 3
    G = chapter4_gain(EX, 5.0)
    a0 = np.where(EX["adapt"][:n], 0.0, A3)
    b0 = np.where(EX["adapt"][n:], 0.0, B3)
    w0 = np.r_[np.zeros(2 * n), a0, b0, np.zeros(2 * (n - 1))]
    sol = scipy.integrate.solve_ivp(
        minimal_rhs(EX, G, EX["amplitudes"]),
        (0.0, 60.0),
        w0,
        method="DOP853",
        rtol=1e-11,
        atol=1e-13,
        t_eval=ts[ts <= 60.0],
    )
    k = sol.t.shape[0]
    np.testing.assert_allclose(np.asarray(traj.xhat[:k]), sol.y[n : 2 * n].T, atol=2e-5)
    np.testing.assert_allclose(np.asarray(traj.z.a[:k]), sol.y[2 * n : 3 * n].T, atol=2e-5)
    np.testing.assert_allclose(np.asarray(traj.z.b[:k]), sol.y[3 * n : 4 * n].T, atol=2e-5)


def test_minimal_lyapunov_and_convergence(ch4_runs):
    """x̂(0) = x(0): V = ½ε₁² + ½θᵀΓ⁻¹θ is non-increasing; rich input: (â, b̂) → (a, b) and x̂ → x."""
    ts, err, traj, obs = ch4_runs["minimal", "rich"]
    V = np.asarray(obs.lyapunov(traj.z, traj.y, A3, B3))
    assert np.max(np.diff(V)) <= 1e-9 * V[0]
    assert V[-1] < 1e-8 * V[0]
    assert err[0] > 0.8 and np.all(err[ts >= 180.0] < 1e-4), err[-1]
    assert float(traj.error_norm[-1]) < 1e-4
    # the known parameters never moved
    np.testing.assert_array_equal(np.asarray(traj.z.a[:, 0]), A3[0])
    np.testing.assert_array_equal(np.asarray(traj.z.b[:, 0]), B3[0])


# =========================================================================== non-minimal observer (4.19)
def state_from_filters(alpha, bhat, rho, oy, ou, y):
    """x̂ of the form (4.12) from the filter states, with NumPy's polynomial division (descending arrays)."""
    n = len(alpha)
    R, Rp = np.r_[1.0, rho], np.r_[1.0, alpha]
    x = np.zeros(n)
    for j in range(1, n + 1):
        U, V = np.r_[1.0, alpha[: j - 1]], bhat[: j - 1]
        q, rem = np.polydiv(np.polymul(U, R), Rp)
        S = np.polysub(np.polymul(q, bhat), np.polymul(V, R)) if j > 1 else np.zeros(1)
        rem = np.r_[np.zeros(n), rem][-n:][::-1]  # ascending, degree ≤ n − 1
        S = np.r_[np.zeros(n), S][-(n - 1) :][::-1]  # ascending, degree ≤ n − 2
        top = y - np.dot(rho[::-1], oy)
        x[j - 1] = rem[: n - 1] @ oy + rem[n - 1] * top + S @ ou
    return x


def test_nonminimal_matches_scipy(ch4_runs):
    """ŷ, â, b̂ and the state estimate equal a SciPy integration of (4.19) with Figs. 4.4-4.5 as rebuilt."""
    ts, _, traj, _ = ch4_runs["nonminimal", "rich"]
    n = 3
    lam0 = EX["lam"]
    rho = np.real(np.poly(EX["filter_poles"]))[1:]
    c = np.real(np.poly(np.r_[-lam0, EX["filter_poles"]]))[1:]
    mask = np.asarray(EX["adapt"], float)
    G = chapter4_gain(EX, 5.0)
    Ap = companion(A3)

    def rhs(t, w):
        x, yh, ah, bh = w[:n], w[n], w[n + 1 : 2 * n + 1], w[2 * n + 1 : 3 * n + 1]
        oy, ou = w[3 * n + 1 : 4 * n], w[4 * n :]
        u = u_of(t, EX["amplitudes"], EX["frequencies"])
        y = x[0]
        doy, v1 = filt(oy, y, rho)
        dou, v2 = filt(ou, u, rho)
        dth = -(yh - y) * mask * G * np.r_[v1, v2]
        return np.r_[Ap @ x + B3 * u, -lam0 * yh + ah @ v1 + bh @ v2, dth, doy, dou]

    a0 = c - np.where(EX["adapt"][:n], 0.0, A3)
    b0 = np.where(EX["adapt"][n:], 0.0, B3)
    w0 = np.r_[np.zeros(n), 0.0, a0, b0, np.zeros(2 * (n - 1))]
    sol = scipy.integrate.solve_ivp(
        rhs, (0.0, 60.0), w0, method="DOP853", rtol=1e-11, atol=1e-13, t_eval=ts[ts <= 60.0]
    )
    k = sol.t.shape[0]
    np.testing.assert_allclose(np.asarray(traj.z.yhat[:k]), sol.y[n], atol=2e-5)
    np.testing.assert_allclose(np.asarray(traj.z.a[:k]), sol.y[n + 1 : 2 * n + 1].T, atol=2e-5)
    np.testing.assert_allclose(np.asarray(traj.z.b[:k]), sol.y[2 * n + 1 : 3 * n + 1].T, atol=2e-5)
    for j in (0, 40, 80, k - 1):
        w = sol.y[:, j]
        xh = state_from_filters(
            c - w[n + 1 : 2 * n + 1],
            w[2 * n + 1 : 3 * n + 1],
            rho,
            w[3 * n + 1 : 4 * n],
            w[4 * n :],
            w[0],
        )
        np.testing.assert_allclose(np.asarray(traj.xhat[j]), xh, atol=5e-5)


def test_nonminimal_state_estimate_exact_at_matching_point():
    """Parameters frozen at the truth (Γ → 0): x̂ − x decays with the filter poles (x(0) ≠ 0)."""
    n = 3
    probe = obsjax.NonMinimalAdaptiveObserver(n, EX["filter_poles"], EX["lam"], 1.0)
    a_s, b_s = probe.matching_point(jnp.asarray(A3), jnp.asarray(B3))
    obs = obsjax.NonMinimalAdaptiveObserver(
        n,
        EX["filter_poles"],
        EX["lam"],
        jnp.asarray(1e-300 * np.ones(2 * n)),
        a0=a_s,
        b0=b_s,
        adapt=EX["adapt"],
    )
    traj = obsjax.simulate(
        obsjax.kreisselmeier_form(A3, B3),
        obs,
        jnp.array([1.0, -1.0, 2.0]),
        jnp.zeros(n),
        jnp.linspace(0.0, T1, NUM),
        u=obsjax.signals.multisine(EX["amplitudes"], EX["frequencies"]),
        rtol=1e-8,
        atol=1e-10,
        max_steps=400_000,
    )
    e = np.asarray(traj.error_norm)
    assert e[0] > 0.5 and e[20] < 1e-2 and e[40] < 1e-5 and e[-1] < 1e-8  # t = 0, 10, 20, 200
    np.testing.assert_allclose(np.asarray(traj.error[:, 0]), 0.0, atol=1e-12)  # x̂_1 = y


def test_nonminimal_lyapunov_and_convergence(ch4_runs):
    ts, err, traj, obs = ch4_runs["nonminimal", "rich"]
    V = np.asarray(obs.lyapunov(traj.z, traj.y, A3, B3))
    assert np.max(np.diff(V)) <= 1e-9 * V[0]  # plant and filters at rest: the transient τ ≡ 0
    assert np.all(err[ts >= 180.0] < 1e-4), err[-1]
    assert float(traj.error_norm[-1]) < 1e-4


def test_minimal_and_nonminimal_coincide(ch4_runs):
    """With D = R, λ = λ_0, the plant at rest and x̂(0) = x(0), both laws are error model 2 with
    W = 1/(s + λ) and the same regressor: the parameter estimates coincide (in the form (4.12))."""
    for which in ("rich", "poor"):
        _, _, tm, om = ch4_runs["minimal", which]
        _, _, tn, on = ch4_runs["nonminimal", which]
        for pm, pn in zip(om.parameters(tm.z), on.parameters(tn.z)):
            np.testing.assert_allclose(np.asarray(pm), np.asarray(pn), atol=1e-5)


def test_poor_input_stalls(ch4_runs):
    """u = sin 0.8t (2 spectral lines, 4 unknowns): the output error vanishes, the parameters stall far from
    the truth, and the regressor is not rich by (4.21) (nor persistently exciting)."""
    for kind in ("minimal", "nonminimal"):
        ts, err, traj, _ = ch4_runs[kind, "poor"]
        _, err_rich, _, _ = ch4_runs[kind, "rich"]
        yhat = traj.xhat[:, 0] if kind == "minimal" else traj.z.yhat
        out = np.abs(np.asarray(yhat) - np.asarray(traj.y[:, 0]))
        assert out[ts >= 150.0].max() < 1e-3 * out.max()
        assert err[-1] > 0.5 and err[-1] > 1e4 * err_rich[-1]
        # stalled: the estimates no longer move
        assert abs(err[-1] - err[ts >= 150.0][0]) < 1e-3


# =========================================================================== identifier (4.1)-(4.2)
@pytest.fixture(scope="module")
def ident_runs():
    return {w: simulate_identifier(w) for w in ("rich", "poor")}


def test_identifier_matches_scipy(ident_runs):
    """K̂ of (4.2) against SciPy, K̂̇ = −(α αᵀ K̂ − α b), b = αᵀ K."""
    K = np.asarray(IDENTIFIER_3["K"])
    for which, (ts, Kt, traj, _) in ident_runs.items():
        c = IDENTIFIER_3[which]

        def rhs(t, Kh, c=c):
            al = np.array([1.0, np.sin(t), c[0] * np.cos(2 * t) + c[1] * np.sin(t)])
            return -(al * (al @ Kh) - al * (al @ K))

        sol = scipy.integrate.solve_ivp(
            rhs, (0, ts[-1]), np.zeros(3), method="DOP853", rtol=1e-12, atol=1e-14, t_eval=ts
        )
        np.testing.assert_allclose(np.asarray(traj.xhat), sol.y.T, atol=1e-8)


@pytest.mark.extended
def test_identifier_rich_converges_at_the_morgan_narendra_rate(ident_runs):
    """Rich α: K̂ → K no slower than the rate of (4.21)(i) computed by morgan_narendra (worst case over
    windows), itself no slower than its gramian bound; V = ½K̃ᵀΓ⁻¹K̃ is non-increasing."""
    ts, Kt, traj, ident = ident_runs["rich"]
    T = 2 * np.pi
    mn = obsjax.analysis.morgan_narendra(
        IdentifierRegressor(IDENTIFIER_3["rich"]), T, 60.0, delta0=0.8
    )
    assert mn.uniform and mn.rate >= mn.rate_bound > 0
    nrm = np.linalg.norm(Kt, axis=1)
    bound = nrm[0] * np.exp(-mn.rate * np.clip(ts - T, 0.0, None))
    assert np.all(nrm <= bound * (1 + 1e-6) + 1e-12)
    assert nrm[-1] < 1e-5
    V = np.asarray(ident.lyapunov(traj.z, jnp.asarray(IDENTIFIER_3["K"])))
    assert np.max(np.diff(V)) <= 1e-12


@pytest.mark.extended
def test_identifier_poor_stalls_along_the_unexcited_direction(ident_runs):
    """α_3 = 2α_2: wᵀ α(t) ≡ 0 for w = (0, 2, −1)/√5, so wᵀK̃ is constant; morgan_narendra finds w."""
    _, Kt, _, _ = ident_runs["poor"]
    w = np.array([0.0, 2.0, -1.0]) / np.sqrt(5.0)
    np.testing.assert_allclose(Kt @ w, Kt[0] @ w, atol=1e-9)
    assert np.linalg.norm(Kt[-1] - (Kt[-1] @ w) * w) < 1e-6  # the excited part has converged
    mn = obsjax.analysis.morgan_narendra(
        IdentifierRegressor(IDENTIFIER_3["poor"]), 2 * np.pi, 60.0, delta0=0.8
    )
    assert not mn.uniform and mn.rate == 0.0 and mn.epsilon0 == 0.0
    assert abs(abs(mn.direction @ w) - 1.0) < 1e-8


def test_identifier_bad_input():
    with pytest.raises(ValueError, match="`regressor` must be a callable"):
        obsjax.LeastSquaresIdentifier(3, np.ones(3))
    with pytest.raises(ValueError, match="`Gamma` must be > 0"):
        obsjax.LeastSquaresIdentifier(3, lambda t, u: jnp.ones(3), Gamma=-1.0)
    ident = obsjax.LeastSquaresIdentifier(3, lambda t, u: jnp.ones(2))
    with pytest.raises(ValueError, match=r"must return an array of shape \(3,\)"):
        ident.plant()
    with pytest.raises(ValueError, match="`n`"):
        obsjax.LeastSquaresIdentifier(0, lambda t, u: jnp.ones(1))


# =========================================================================== Morgan–Narendra (4.20)-(4.21)
@pytest.mark.extended
def test_morgan_narendra_closed_forms_and_the_pe_test():
    """α = (1, sin t, cos 2t), T = 2π: ∫ααᵀ = diag(2π, π, π), so η1 = π and a = 1/2; the moving integrals
    over δ0 are δ0, 2 sin(δ0/2) sin(τ + δ0/2) and sin δ0 cos(2τ + δ0), orthogonal over a period, so
    ε_0 = min(δ0, √2 |sin(δ0/2)|, |sin δ0|/√2).  α = (1, sin t, 2 sin t) is not rich.  Both verdicts agree
    with is_persistently_exciting."""
    T, d0, horizon = (
        2 * np.pi,
        0.8,
        60.0,
    )  # nine windows, as in the identifier tests (one compilation)
    rich = obsjax.analysis.morgan_narendra(
        IdentifierRegressor(IDENTIFIER_3["rich"]), T, horizon, delta0=d0
    )
    assert rich.uniform and bool(rich)
    assert rich.eta1 == pytest.approx(np.pi, rel=1e-8) and rich.eta2 == pytest.approx(
        2 * np.pi, rel=1e-8
    )
    assert rich.a == pytest.approx(0.5, rel=1e-8) and rich.b == pytest.approx(-2 * np.pi, rel=1e-8)
    assert rich.per_window.shape == (9, 5) and rich.search_window == pytest.approx(2 * T)
    eps = min(d0, np.sqrt(2) * abs(np.sin(d0 / 2)), abs(np.sin(d0)) / np.sqrt(2))
    assert rich.epsilon0 == pytest.approx(eps, rel=1e-7)
    assert rich.rate >= rich.rate_bound > 0
    poor = obsjax.analysis.morgan_narendra(
        IdentifierRegressor(IDENTIFIER_3["poor"]), T, horizon, delta0=d0
    )
    assert not poor.uniform and poor.epsilon0 == 0.0 and poor.rate == 0.0 and poor.a < 1e-12
    pe = {
        w: obsjax.analysis.is_persistently_exciting(IdentifierRegressor(IDENTIFIER_3[w]), T, 2 * T)
        for w in ("rich", "poor")
    }
    assert bool(pe["rich"]) and not bool(pe["poor"])
    assert pe["rich"].eta1 == pytest.approx(rich.eta1, rel=1e-8)


@pytest.mark.extended
def test_scalar_error_system_420():
    """(4.20) as printed, integrated by SciPy, equals the Kudva–Narendra errors (e, φ, ψ); u = sin t is rich
    (the error system decays), the step u = 1 is not (φ, ψ stall on φ x̄_p + ψ = 0), and morgan_narendra
    says so on B = −[√γ₁ x_p; √γ₂ u]."""
    from obsjax._reproduce.adaptive import SCALAR_420_INPUTS, Scalar420Regressor

    ex = SCALAR_420
    g, k = ex["gamma"], ex["k"]
    for which in ("rich", "poor"):
        ts, e, phi, psi = simulate_420(which)
        A_, w_, ph_ = SCALAR_420_INPUTS[which]

        def rhs420(t, E, A_=A_, w_=w_, ph_=ph_):
            # the plant ẋ_p = a_p x_p + b_p u and (4.20) as printed: [[−K, x_p, u], [−γ1 x_p, 0, 0], [−γ2 u, 0, 0]]
            xp, u = E[3], A_ * np.sin(w_ * t + ph_)
            A = np.array([[-k, xp, u], [-g * xp, 0.0, 0.0], [-g * u, 0.0, 0.0]])
            return np.r_[A @ E[:3], ex["ap"] * xp + ex["bp"] * u]

        sol = scipy.integrate.solve_ivp(
            rhs420,
            (0, ts[-1]),
            [0.0, -ex["ap"], -ex["bp"], 0.0],
            method="DOP853",
            rtol=1e-12,
            atol=1e-14,
            t_eval=ts,
        )
        B = Scalar420Regressor(which)
        np.testing.assert_allclose(
            -np.asarray(jax.vmap(B)(jnp.asarray(ts)))[:, 0] / np.sqrt(g), sol.y[3], atol=1e-9
        )  # the closed form of x_p used for (4.21)
        np.testing.assert_allclose(np.c_[e, phi, psi], sol.y[:3].T, atol=1e-7)
        mn = obsjax.analysis.morgan_narendra(B, 2 * np.pi, 8 * np.pi, t0=20.0, delta0=1.0)
        final = np.abs(np.r_[e[-1], phi[-1], psi[-1]])
        if which == "rich":
            assert mn.uniform and mn.epsilon0 > 0.1
            assert final.max() < 1e-8
        else:
            assert not mn.uniform and mn.epsilon0 == 0.0
            assert np.hypot(phi[-1], psi[-1]) > 0.5
            assert abs(phi[-1] * (-ex["bp"] / ex["ap"]) + psi[-1]) < 1e-8  # φ x̄_p + ψ = 0


def test_morgan_narendra_bad_input():
    with pytest.raises(ValueError, match="`B` must be a callable"):
        obsjax.analysis.morgan_narendra(np.ones(3), 1.0, 2.0)
    with pytest.raises(ValueError, match="`T`"):
        obsjax.analysis.morgan_narendra(lambda t: jnp.ones(2), -1.0, 2.0)
    with pytest.raises(ValueError, match=r"\(n,\) or \(n, m\)"):
        obsjax.analysis.morgan_narendra(lambda t: jnp.ones((2, 2, 2)), 1.0, 2.0)


# =========================================================================== gradients and bad input
#: Fixed Ralston (2nd-order Runge–Kutta) steps: autodiff and central differences then differentiate the same
#: discrete flow, and the reverse-mode compilation is a fraction of an adaptive solve's.
FIXED = {"solver": diffrax.Ralston(), "adaptive": False, "dt0": 0.01}


def _fd_check(loss, obs, leaves, h=1e-5, rel=1e-4):
    g = eqx.filter_grad(loss)(obs)
    for name, idx in leaves:
        leaf = getattr(obs, name)
        step = jnp.zeros(leaf.shape, leaf.dtype).at[idx].set(h)
        fp = loss(eqx.tree_at(lambda o, name=name: getattr(o, name), obs, leaf + step))
        fm = loss(eqx.tree_at(lambda o, name=name: getattr(o, name), obs, leaf - step))
        fd = float((fp - fm) / (2 * h))
        ad = float(jnp.real(getattr(g, name)[idx]) if leaf.ndim else getattr(g, name))
        assert ad == pytest.approx(fd, rel=rel, abs=1e-9), (name, idx, ad, fd)


def _param_loss(kind):
    plant = obsjax.kreisselmeier_form(A3, B3)
    u = obsjax.signals.multisine(EX["amplitudes"], EX["frequencies"])
    ts = jnp.linspace(0.0, 15.0, 61)
    truth = jnp.asarray(np.r_[A3, B3])

    @eqx.filter_jit
    def loss(o):
        traj = obsjax.simulate(plant, o, jnp.zeros(3), jnp.zeros(3), ts, u=u, **FIXED)
        p = jnp.concatenate(o.parameters(traj.z), axis=-1)
        e2 = jnp.sum((p - truth) ** 2, axis=-1)
        return jnp.sum(0.5 * (e2[1:] + e2[:-1]) * jnp.diff(ts))

    return loss


@pytest.mark.parametrize("kind,lam", [("minimal", "lam"), ("nonminimal", "lam0")])
@pytest.mark.extended
def test_gradients_match_central_differences(kind, lam):
    """d/dΓ (every adapted entry), d/dλ and d/d(filter poles) of ∫‖(â, b̂) − (a, b)‖² dt over [0, 15]."""
    from obsjax._reproduce.adaptive import build_chapter4_observer

    obs = build_chapter4_observer(kind, EX, gamma=5.0)
    leaves = [("Gamma", (i,)) for i in np.flatnonzero(EX["adapt"])]
    leaves += [(lam, ()), ("filter_poles", (0,)), ("filter_poles", (1,))]
    _fd_check(_param_loss(kind), obs, leaves)


def test_identifier_gradient_matches_central_differences():
    ident = obsjax.LeastSquaresIdentifier(
        3, IdentifierRegressor(IDENTIFIER_3["rich"]), Gamma=jnp.array([1.0, 0.5, 2.0])
    )
    K = jnp.asarray(IDENTIFIER_3["K"])
    ts = jnp.linspace(0.0, 10.0, 41)

    @eqx.filter_jit
    def loss(o):
        traj = obsjax.simulate(o.plant(), o, K, jnp.zeros(3), ts, **FIXED)
        e2 = jnp.sum(traj.error**2, axis=-1)
        return jnp.sum(0.5 * (e2[1:] + e2[:-1]) * jnp.diff(ts))

    _fd_check(loss, ident, [("Gamma", (i,)) for i in range(3)])


@pytest.mark.parametrize(
    "cls,kwargs,match",
    [
        ("MinimalAdaptiveObserver", {"filter_poles": [-1.0]}, "`filter_poles`"),
        ("MinimalAdaptiveObserver", {"filter_poles": [-1.0, 0.5]}, "left half-plane"),
        ("MinimalAdaptiveObserver", {"lam": -1.0}, "`lam` must be > 0"),
        ("MinimalAdaptiveObserver", {"Gamma": np.ones(5)}, "`Gamma` must be a scalar"),
        ("MinimalAdaptiveObserver", {"adapt": [True] * 5}, "`adapt` must hold 6"),
        ("MinimalAdaptiveObserver", {"adapt": [False] * 6}, "at least one"),
        ("NonMinimalAdaptiveObserver", {"lam0": 0.0}, "`lam0` must be > 0"),
        ("NonMinimalAdaptiveObserver", {"Gamma": -np.eye(6)}, "positive definite"),
        ("NonMinimalAdaptiveObserver", {"a0": [1.0]}, "`a0`"),
    ],
)
def test_observer_bad_input(cls, kwargs, match):
    args = {"n": 3, "filter_poles": [-2.0, -3.0], "Gamma": 1.0}
    args["lam" if cls.startswith("Minimal") else "lam0"] = 0.5
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        getattr(obsjax, cls)(**args)


def test_guards_survive_jit():
    """Gains updated under jit (as tune does) are checked by eqx.error_if in prepare()."""
    mo = obsjax.MinimalAdaptiveObserver(2, [-1.0], 1.0, jnp.ones(4))
    no = obsjax.NonMinimalAdaptiveObserver(2, [-1.0], 1.0, jnp.ones(4))
    li = obsjax.LeastSquaresIdentifier(2, lambda t, u: jnp.ones(2), Gamma=jnp.ones(2))
    cases = [
        (
            lambda v: eqx.tree_at(lambda o: o.Gamma, mo, v * jnp.ones(4)).prepare().Gamma,
            "`Gamma` must be finite and > 0",
        ),
        (lambda v: eqx.tree_at(lambda o: o.lam0, no, v).prepare().lam0, "`lam0` must be finite and > 0"),
        (
            lambda v: (
                eqx.tree_at(lambda o: o.filter_poles, mo, -v * jnp.ones(1)).prepare().filter_poles
            ),
            "`filter_poles` must be finite, in the open left half-plane",
        ),
        (
            lambda v: eqx.tree_at(lambda o: o.Gamma, li, v * jnp.ones(2)).prepare().Gamma,
            "`Gamma` must be finite and > 0",
        ),
    ]
    for fn, match in cases:
        assert jnp.all(jnp.isfinite(jax.jit(fn)(1.0)))
        with pytest.raises(Exception, match=match):
            jax.block_until_ready(jax.jit(fn)(-1.0))
