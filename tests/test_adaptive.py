"""Adaptive observers (Hassan thesis ch. 4-6): Kudva–Narendra, Lüders–Narendra, Kreisselmeier.

Independent references: SciPy (expm, Lyapunov solver, solve_ivp), NumPy resolvents, the frequency-domain
averaged rate (no simulation), and defining properties (Lyapunov functions, the closed form (5.9), (6.12)).
Simulations share shapes (save grid, gain shapes, number of sinusoids) so each structure compiles once.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg

import obsjax
from obsjax._reproduce.adaptive import (
    KREISSELMEIER_2,
    KREISSELMEIER_3,
    KUDVA_NARENDRA,
    LUDERS_NARENDRA_2,
    LUDERS_NARENDRA_3,
    fit_rate,
    jax_output,
    kreisselmeier_gain,
    simulate_kreisselmeier,
    simulate_luders_narendra,
    time_to,
)
from obsjax.observers import mean_regressor_covariance, observer_form, resolvent_numerators
from obsjax.observers._adaptive_common import lyapunov, poly_from_roots

K2_T1, K2_NUM = (
    300.0,
    601,
)  # horizon and grid of every 2nd-order Kreisselmeier run (one compile per scheme)
LN_T1, LN_NUM = 200.0, 401  # the same for the 2nd-order Lüders–Narendra runs
LN_KW = {"rtol": 1e-9, "atol": 1e-11, "max_steps": 400_000}


# =========================================================================== Kreisselmeier (chapter 6)
def test_resolvent_numerators_match_numpy():
    """(6.9): (sI − F)⁻¹ e_i = T_i (sI − Fᵀ)⁻¹ e_1 at complex s, against numpy.linalg.solve."""
    for poles in ([-1.0, -2.0, -3.0], [-1.0 + 1.0j, -1.0 - 1.0j, -0.5], [-2.0, -2.0, -2.0, -0.3]):
        f = poly_from_roots(jnp.asarray(poles))
        F = np.asarray(observer_form(f))
        n = F.shape[0]
        np.testing.assert_allclose(
            np.poly(F), np.real(np.poly(np.asarray(poles))), atol=1e-12
        )  # eig(F) = poles
        T = np.asarray(resolvent_numerators(jnp.asarray(F), f))
        for s in (0.3 + 1.1j, -0.7 + 0.2j, 2.0):
            rhs_basis = np.linalg.solve(s * np.eye(n) - F.T, np.eye(n)[:, 0])
            # (6.8): (sI − Fᵀ)⁻¹ e1 = [s^{n−1}, ..., 1]/det(sI − F)
            np.testing.assert_allclose(
                rhs_basis,
                np.array([s ** (n - 1 - k) for k in range(n)]) / np.prod(s - np.asarray(poles)),
                rtol=1e-10,
            )
            for i in range(n):
                lhs = np.linalg.solve(s * np.eye(n) - F, np.eye(n)[:, i])
                np.testing.assert_allclose(lhs, T[i] @ rhs_basis, rtol=1e-10, atol=1e-12)


@pytest.mark.extended
def test_parametrized_observer_at_matching_point_is_luenberger():
    """With p = p* (6.5) frozen, (6.12): x̂(t) − x(t) = e^{Ft}(x̂0 − x0) exactly (SciPy expm).

    Same shapes and solver settings as the 2nd-order convergence runs (one compilation).
    """
    ex = KREISSELMEIER_2
    n = 2
    plant = obsjax.kreisselmeier_form(ex["a"], ex["b"])
    obs = obsjax.Kreisselmeier(
        n, ex["poles"], 1e-300 * np.ones(2 * n), a0=ex["a"], b0=ex["b"]
    )  # adaptation off
    x0, xhat0 = jnp.array([1.0, -2.0]), jnp.array([0.5, 0.5])
    ts = jnp.linspace(0.0, K2_T1, K2_NUM)
    traj = obsjax.simulate(
        plant,
        obs,
        x0,
        xhat0,
        ts,
        u=obsjax.signals.multisine(ex["amplitudes"], ex["frequencies"]),
        max_steps=200_000,
    )
    F = np.asarray(observer_form(poly_from_roots(jnp.asarray(ex["poles"]))))
    k = 41  # t <= 20
    expected = np.stack(
        [scipy.linalg.expm(F * t) @ np.asarray(xhat0 - x0) for t in np.asarray(ts[:k])]
    )
    np.testing.assert_allclose(np.asarray(traj.error[:k]), expected, atol=2e-6)
    # (6.14): ŷ − y = cᵀ e^{Ft} (x̂0 − x0)
    out = np.asarray(jax_output(obs, traj))[:k] - np.asarray(traj.y[:k, 0])
    np.testing.assert_allclose(out, expected[:, 0], atol=2e-6)
    # and the parameters did not move
    np.testing.assert_allclose(
        np.asarray(traj.z.p[-1]), np.asarray(obs.matching_point(ex["a"], ex["b"])), atol=1e-12
    )


@pytest.mark.extended
def test_generalized_error_vanishes_at_matching_point():
    """Lion's realisation of (6.18): with p = p* frozen the filtered generalised error 𝒵ᵀp* − Y decays to 0
    (the filtered pair obeys y = Zᵀp* + cᵀe^{Ft}x0 too), and the filter states are successive derivatives:
    d/dt (s^k/L Z) = s^{k+1}/L Z (no signal is differentiated)."""
    ex = KREISSELMEIER_2
    plant = obsjax.kreisselmeier_form(ex["a"], ex["b"])
    G = 1e-300 * np.ones(4)
    obs = obsjax.Kreisselmeier(2, ex["poles"], G, scheme="generalized", a0=ex["a"], b0=ex["b"])
    u = obsjax.signals.multisine(ex["amplitudes"], ex["frequencies"])
    ts = jnp.linspace(0.0, K2_T1, K2_NUM)
    traj = obsjax.simulate(
        plant, obs, jnp.array([1.0, -2.0]), jnp.array([0.5, 0.5]), ts, u=u, max_steps=200_000
    )
    _, ell = obs._lion()

    def filtered_regressor(z):  # 𝒵 of (6.18b) for the filtered Z: [s^k/L Z], k = 0..2n−1
        Z = jnp.concatenate([z.eta1, z.eta2])
        return jnp.concatenate([z.W, (Z - z.W @ ell)[:, None]], axis=1)

    pstar = obs.matching_point(ex["a"], ex["b"])
    E = []
    for k in (0, 100, 300, 600):
        z = jax.tree_util.tree_map(lambda v, k=k: v[k], traj.z)
        Zf = filtered_regressor(z)
        yc = traj.y[k, 0] - z.free[0]
        Yf = jnp.concatenate([z.omega, (yc - ell @ z.omega)[None]])
        E.append(float(jnp.linalg.norm(Zf.T @ pstar - Yf)))
        # derivative structure of the filter: d/dt column k of W = column k+1 of 𝒵_f
        dz = obs.vector_field(traj.ts[k], z, traj.y[k], u(traj.ts[k]))
        np.testing.assert_allclose(np.asarray(dz.W), np.asarray(Zf[:, 1:]), atol=1e-12)
    assert E[0] > 0.1 and E[-1] < 1e-7 * E[0] and E[2] < E[1] < E[0]


@pytest.fixture(scope="module")
def k2_runs():
    """The three schemes on the 2nd-order example, u = sin 0.7t + sin 2t (two frequencies, n = 2)."""
    return {
        ("gradient", 2.0): simulate_kreisselmeier(
            KREISSELMEIER_2, "gradient", gamma=2.0, t1=K2_T1, num=K2_NUM
        ),
        ("gradient", 4.0): simulate_kreisselmeier(
            KREISSELMEIER_2, "gradient", gamma=4.0, t1=K2_T1, num=K2_NUM
        ),
        ("generalized", 2.0): simulate_kreisselmeier(
            KREISSELMEIER_2, "generalized", gamma=2.0, t1=K2_T1, num=K2_NUM
        ),
        ("generalized", 4.0): simulate_kreisselmeier(
            KREISSELMEIER_2, "generalized", gamma=4.0, t1=K2_T1, num=K2_NUM
        ),
        ("integral", 2.0): simulate_kreisselmeier(
            KREISSELMEIER_2, "integral", gamma=2.0, q=0.2, t1=K2_T1, num=K2_NUM
        ),
    }


@pytest.mark.parametrize(
    "scheme,gamma,horizon",
    [("gradient", 4.0, 150.0), ("generalized", 4.0, 250.0), ("integral", 2.0, 100.0)],
)
@pytest.mark.extended
def test_kreisselmeier_converges_second_order(k2_runs, scheme, gamma, horizon):
    """Rich input (2 frequencies): ‖p − p*‖/‖p*‖ < 1e-3 by the reported horizon, and x̂ → x."""
    ts, err, traj, _ = k2_runs[(scheme, gamma)]
    k = np.searchsorted(ts, horizon)
    assert err[0] == pytest.approx(1.0)
    assert np.all(err[k:] < 1e-3), (scheme, err[k:].max())
    assert float(traj.error_norm[-1]) < 1e-4


@pytest.mark.extended
def test_kreisselmeier_integral_converges_third_order():
    """3rd order, 3 frequencies, integral scheme: relative parameter error < 1e-3 from t = 150 on; x̂ → x."""
    ts, err, traj, obs = simulate_kreisselmeier(
        KREISSELMEIER_3, "integral", gamma=2.0, q=0.2, t1=200.0, num=401
    )
    assert np.all(err[ts >= 150.0] < 1e-3)
    assert float(traj.error_norm[-1]) < 1e-4
    a_hat, b_hat = obs.parameters(jax.tree_util.tree_map(lambda v: v[-1], traj.z))
    np.testing.assert_allclose(
        np.r_[a_hat, b_hat], np.r_[KREISSELMEIER_3["a"], KREISSELMEIER_3["b"]], rtol=1e-3
    )


@pytest.mark.extended
def test_richness_single_sinusoid_third_order():
    """One sinusoid (2 spectral lines < 2n = 6 parameters): the output error vanishes, the parameters don't.

    Same signal shapes as the rich run (the two other amplitudes are zero), so u(t) = sin(1.2 t) exactly.
    """
    ex = KREISSELMEIER_3
    G = kreisselmeier_gain(ex, 2.0)
    single = obsjax.signals.multisine([0.0, 1.0, 0.0], list(ex["frequencies"]))
    ts, err, traj, obs = simulate_kreisselmeier(
        ex, "integral", G=G, q=0.2, t1=200.0, num=401, u=single
    )
    yhat = np.asarray(jax_output(obs, traj))
    out_err = np.abs(yhat - np.asarray(traj.y[:, 0]))
    assert out_err[ts >= 150.0].max() < 1e-4  # ŷ → y
    assert err[-1] > 0.1  # p does not reach p*
    # the limit is not p*: the regressor covariance has rank 2 at one frequency
    R = mean_regressor_covariance(ex["a"], ex["b"], ex["poles"], [1.0], [1.2])
    assert np.linalg.matrix_rank(R, tol=1e-10 * np.linalg.norm(R)) == 2


@pytest.mark.extended
def test_kreisselmeier_rates_match_averaging(k2_runs):
    """Fitted decay rates of ‖p − p*‖ against λ_min(G M̄) from the frequency response (no simulation);
    for the same G the integral scheme is faster by about 1/q."""
    ex = KREISSELMEIER_2
    rates = {}
    for scheme in ("gradient", "generalized", "integral"):
        ts, err, _, obs = k2_runs[(scheme, 2.0)]
        lo = 20.0 if scheme == "integral" else 100.0
        hi = 200.0 if scheme == "integral" else ts[-1]
        fitted = fit_rate(ts, err, lo=lo, hi=hi)
        predicted = obs.averaged_rate(ex["a"], ex["b"], ex["amplitudes"], ex["frequencies"])
        rates[scheme] = fitted
        tol = 0.3 if scheme == "generalized" else 0.06
        assert fitted == pytest.approx(predicted, rel=tol), (scheme, fitted, predicted)
    assert rates["integral"] / rates["gradient"] == pytest.approx(1 / 0.2, rel=0.1)


def _param_loss(obs, plant, u, pstar, ts):
    traj = obsjax.simulate(
        plant, obs, jnp.ones(2), jnp.zeros(2), ts, u=u, rtol=1e-9, atol=1e-11, max_steps=100_000
    )
    e2 = jnp.sum((traj.z.p - pstar) ** 2, axis=-1)
    return jnp.sum(0.5 * (e2[1:] + e2[:-1]) * jnp.diff(ts))


def _check_kreisselmeier_gradients(scheme, extra):
    ex = KREISSELMEIER_2
    plant = obsjax.kreisselmeier_form(ex["a"], ex["b"])
    u = obsjax.signals.multisine(ex["amplitudes"], ex["frequencies"])
    kw = {"q": 0.5} if scheme == "integral" else {}
    obs = obsjax.Kreisselmeier(
        2, ex["poles"], jnp.asarray(kreisselmeier_gain(ex, 2.0, scheme)), scheme=scheme, **kw
    )
    pstar = obs.matching_point(jnp.asarray(ex["a"]), jnp.asarray(ex["b"]))
    ts = jnp.linspace(0.0, 20.0, 81)
    loss = eqx.filter_jit(lambda o: _param_loss(o, plant, u, pstar, ts))
    grads = eqx.filter_grad(lambda o: loss(o))(obs)
    h = 1e-5
    for k in range(4):
        step = jnp.zeros(4).at[k].set(h * obs.G[k])
        fp = loss(eqx.tree_at(lambda o: o.G, obs, obs.G + step))
        fm = loss(eqx.tree_at(lambda o: o.G, obs, obs.G - step))
        fd = (fp - fm) / (2 * h * obs.G[k])
        assert float(grads.G[k]) == pytest.approx(float(fd), rel=1e-4, abs=1e-9)
    for name in extra:  # scalar leaves
        leaf = getattr(obs, name)
        fd = (
            loss(eqx.tree_at(lambda o, name=name: getattr(o, name), obs, leaf + h))
            - loss(eqx.tree_at(lambda o, name=name: getattr(o, name), obs, leaf - h))
        ) / (2 * h)
        assert float(getattr(grads, name)) == pytest.approx(float(fd), rel=1e-4), name


@pytest.mark.extended
def test_kreisselmeier_gradient_wrt_rates_matches_fd():
    """d/dG and d/dq of ∫‖p − p*‖² dt (integral scheme: both rates): autodiff through diffrax against
    central differences."""
    _check_kreisselmeier_gradients("integral", ("q",))


@pytest.mark.slow
@pytest.mark.parametrize("scheme,extra", [("generalized", ("Q", "filter_pole")), ("gradient", ())])
def test_kreisselmeier_gradient_other_schemes_matches_fd(scheme, extra):
    """The same check for the generalised law (G, Q, Lion's ℓ) and the gradient law (G)."""
    _check_kreisselmeier_gradients(scheme, extra)


@pytest.mark.slow
def test_tuning_shortens_time_to_one_percent():
    """Adam on log G (obsjax.tune) over ∫‖p − p*‖²: time to 1 % parameter error drops (gradient scheme)."""
    import optax

    ex = KREISSELMEIER_2
    ts, err, _, obs = simulate_kreisselmeier(ex, "gradient", gamma=2.0, t1=K2_T1, num=K2_NUM)
    before = time_to(ts, err, 1e-2)
    pstar = obs.matching_point(jnp.asarray(ex["a"]), jnp.asarray(ex["b"]))

    def loss(traj):
        e2 = jnp.sum((traj.z.p - pstar) ** 2, axis=-1)
        return jnp.sum(0.5 * (e2[1:] + e2[:-1]) * jnp.diff(traj.ts))

    res = obsjax.tune(
        obs,
        obsjax.kreisselmeier_form(ex["a"], ex["b"]),
        where=lambda o: o.G,
        loss=loss,
        x0s=jnp.ones((1, 2)),
        xhat0s=jnp.zeros((1, 2)),
        ts=jnp.linspace(0.0, 150.0, 301),
        optimizer=optax.adam(0.1),
        steps=30,
        progress=False,
        u=obsjax.signals.multisine(ex["amplitudes"], ex["frequencies"]),
        simulate_kwargs={"max_steps": 100_000},
    )
    ts2, err2, _, _ = simulate_kreisselmeier(ex, "gradient", G=res.observer.G, t1=K2_T1, num=K2_NUM)
    after = time_to(ts2, err2, 1e-2)
    assert after < 0.8 * before, (before, after)


# --------------------------------------------------------------------------- Kreisselmeier: bad input
@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"n": 2, "poles": [-1.0], "G": 1.0}, "poles"),
        ({"n": 2, "poles": [-1.0, 0.5], "G": 1.0}, "left half-plane"),
        ({"n": 2, "poles": [-1.0 + 1j, -2.0], "G": 1.0}, "conjugate"),
        ({"n": 2, "poles": [-1.0, -2.0], "G": 0.0}, "`G` must be > 0"),
        ({"n": 2, "poles": [-1.0, -2.0], "G": np.ones(3)}, "`G` must be a scalar"),
        ({"n": 2, "poles": [-1.0, -2.0], "G": np.triu(np.ones((4, 4)))}, "`G` must be a symmetric"),
        ({"n": 2, "poles": [-1.0, -2.0], "G": -np.eye(4)}, "`G` must be positive definite"),
        ({"n": 2, "poles": [-1.0, -2.0], "G": 1.0, "scheme": "integral"}, "`q`"),
        (
            {"n": 2, "poles": [-1.0, -2.0], "G": 1.0, "scheme": "integral", "q": -1.0},
            "`q` must be > 0",
        ),
        ({"n": 2, "poles": [-1.0, -2.0], "G": 1.0, "scheme": "gradient", "q": 1.0}, "unused"),
        ({"n": 2, "poles": [-1.0, -2.0], "G": 1.0, "scheme": "lms"}, "`scheme`"),
        (
            {"n": 2, "poles": [-1.0, -2.0], "G": 1.0, "scheme": "generalized", "filter_pole": 0.0},
            "filter_pole",
        ),
        ({"n": 2, "poles": [-1.0, -2.0], "G": 1.0, "a0": [1.0]}, "`a0`"),
        ({"n": 0, "poles": [], "G": 1.0}, "`n`"),
    ],
)
def test_kreisselmeier_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        obsjax.Kreisselmeier(**kwargs)


def test_kreisselmeier_form_bad_input():
    with pytest.raises(ValueError, match="same length"):
        obsjax.kreisselmeier_form([1.0, 2.0], [1.0])


# =========================================================================== Lüders–Narendra (chapter 5)
@pytest.fixture(scope="module")
def ln2_run():
    return simulate_luders_narendra(
        LUDERS_NARENDRA_2, gamma=5.0, t1=LN_T1, num=LN_NUM, rtol=1e-9, atol=1e-11
    )


@pytest.mark.extended
def test_luders_narendra_lyapunov_non_increasing(ln2_run):
    """(5.11) with x̂_i(0) = x_i(0) (i ≥ 2): f ≡ 0 in (5.13), so V̇ = −λ1 e1² ≤ 0 along the simulation."""
    ex = LUDERS_NARENDRA_2
    _ts, _, traj, obs = ln2_run
    V = np.asarray(obs.lyapunov(traj.z, traj.y, jnp.asarray(ex["a"]), jnp.asarray(ex["b"])))
    assert V[-1] < 1e-6 * V[0]
    assert np.max(np.diff(V)) <= 1e-7 * V[0]
    # pointwise: V̇ = −λ1 e1² along the flow (jvp of V along the plant + observer vector field)
    plant = obsjax.luders_narendra_form(ex["a"], ex["b"], ex["lambdas"])
    u = obsjax.signals.multisine(ex["amplitudes"], ex["frequencies"])
    a, b = jnp.asarray(ex["a"]), jnp.asarray(ex["b"])
    for k in (0, 3, 40, 200):
        t, x = traj.ts[k], traj.x[k]
        z = jax.tree_util.tree_map(lambda v, k=k: v[k], traj.z)
        dz = obs.vector_field(t, z, plant.h(t, x, u(t)), u(t))
        dx = plant.f(t, x, u(t))
        _, dV = jax.jvp(lambda zz, xx: obs.lyapunov(zz, xx[:1], a, b), (z, x), (dz, dx))
        e1 = z.xhat[0] - x[0]
        assert float(dV) == pytest.approx(-ex["lambdas"][0] * float(e1) ** 2, rel=1e-9, abs=1e-14)


def test_luders_narendra_closed_form_59():
    """(5.9): e_i = v_i φ_i + s_i ψ_i + e^{−λ_i t} e_i(0) for i ≥ 2, with x̂_i(0) ≠ x_i(0)."""
    ex = LUDERS_NARENDRA_2
    plant = obsjax.luders_narendra_form(ex["a"], ex["b"], ex["lambdas"])
    obs = obsjax.LudersNarendra(2, ex["lambdas"], 3.0, 2.0, a0=[0.5, 0.5], b0=[0.0, 0.0])
    x0, xhat0 = jnp.array([1.0, 2.0]), jnp.array([0.0, -1.0])
    ts = jnp.linspace(0.0, LN_T1, LN_NUM)
    traj = obsjax.simulate(
        plant,
        obs,
        x0,
        xhat0,
        ts,
        u=obsjax.signals.multisine(ex["amplitudes"], ex["frequencies"]),
        **LN_KW,
    )
    phi = np.asarray(traj.z.alpha[:, 1]) - ex["a"][1]
    psi = np.asarray(traj.z.beta[:, 1]) - ex["b"][1]
    e2 = np.asarray(traj.error[:, 1])
    expected = (
        np.asarray(traj.z.v[:, 0]) * phi
        + np.asarray(traj.z.s[:, 0]) * psi
        + np.exp(-ex["lambdas"][1] * np.asarray(ts)) * float(xhat0[1] - x0[1])
    )
    np.testing.assert_allclose(e2, expected, atol=1e-7)


def test_luders_narendra_converges_second_order(ln2_run):
    ts, err, traj, _ = ln2_run
    assert np.all(err[ts >= 120.0] < 1e-3)
    assert float(traj.error_norm[-1]) < 1e-4


@pytest.mark.extended
def test_luders_narendra_converges_third_order():
    """3rd order, four sinusoids: the slowest example (rate ≈ 1.1e-3 /s), cheap once compiled."""
    ts, err, traj, _ = simulate_luders_narendra(LUDERS_NARENDRA_3, gamma=2.0, t1=8000.0, num=401)
    assert np.all(err[ts >= 7000.0] < 1e-3), err[ts >= 7000.0].max()
    assert float(traj.error_norm[-1]) < 1e-3


def test_luders_narendra_matches_scipy():
    """The observer + plant ODE against an independent SciPy solve_ivp of (5.2), (5.3), (5.6), (5.7), (5.12)."""
    ex = LUDERS_NARENDRA_2
    lam = np.asarray(ex["lambdas"])
    c, d = np.array([2.0, 3.0]), np.array([1.5, 0.5])
    a, b = np.asarray(ex["a"]), np.asarray(ex["b"])
    A = np.array([[a[0], 1.0], [a[1], -lam[1]]])

    def u(t):
        return np.sin(0.5 * t) + np.sin(3.0 * t)

    def rhs(t, w):
        x, xh, al, be, v, s = w[0:2], w[2:4], w[4:6], w[6:8], w[8], w[9]
        x1, uu = x[0], u(t)
        e1 = xh[0] - x1
        dx = A @ x + b * uu
        w2 = -(c[1] * v**2 + d[1] * s**2) * e1
        dxh = [
            al[0] * x1 + xh[1] + be[0] * uu - lam[0] * e1,
            al[1] * x1 - lam[1] * xh[1] + be[1] * uu + w2,
        ]
        dal = [-c[0] * e1 * x1, -c[1] * e1 * v]
        dbe = [-d[0] * e1 * uu, -d[1] * e1 * s]
        return np.r_[dx, dxh, dal, dbe, -lam[1] * v + x1, -lam[1] * s + uu]

    x0, xh0 = np.array([1.0, -1.0]), np.array([0.0, 0.5])
    sol = scipy.integrate.solve_ivp(
        rhs,
        (0, LN_T1),
        np.r_[x0, xh0, np.zeros(6)],
        method="DOP853",
        rtol=1e-11,
        atol=1e-13,
        t_eval=np.linspace(0, LN_T1, LN_NUM),
    )
    obs = obsjax.LudersNarendra(2, lam, c, d)
    plant = obsjax.luders_narendra_form(a, b, lam)
    traj = obsjax.simulate(
        plant,
        obs,
        jnp.asarray(x0),
        jnp.asarray(xh0),
        jnp.linspace(0.0, LN_T1, LN_NUM),
        u=obsjax.signals.multisine([1.0, 1.0], [0.5, 3.0]),
        **LN_KW,
    )
    np.testing.assert_allclose(np.asarray(traj.xhat), sol.y[2:4].T, atol=1e-6)
    np.testing.assert_allclose(np.asarray(traj.z.alpha), sol.y[4:6].T, atol=1e-6)
    np.testing.assert_allclose(np.asarray(traj.z.beta), sol.y[6:8].T, atol=1e-6)


@pytest.mark.extended
def test_luders_narendra_gradient_wrt_rates_matches_fd():
    ex = LUDERS_NARENDRA_2
    plant = obsjax.luders_narendra_form(ex["a"], ex["b"], ex["lambdas"])
    u = obsjax.signals.multisine(ex["amplitudes"], ex["frequencies"])
    obs = obsjax.LudersNarendra(2, ex["lambdas"], jnp.array([2.0, 3.0]), jnp.array([1.5, 0.5]))
    ts = jnp.linspace(0.0, 15.0, 61)
    a, b = jnp.asarray(ex["a"]), jnp.asarray(ex["b"])

    @eqx.filter_jit
    def loss(o):
        traj = obsjax.simulate(plant, o, jnp.ones(2), jnp.zeros(2), ts, u=u, rtol=1e-9, atol=1e-11)
        e2 = jnp.sum((traj.z.alpha - a) ** 2 + (traj.z.beta - b) ** 2, axis=-1)
        return jnp.sum(0.5 * (e2[1:] + e2[:-1]) * jnp.diff(ts))

    g = eqx.filter_grad(loss)(obs)
    h = 1e-5
    for name in ("c", "d", "lambdas"):
        for k in range(2):
            leaf = getattr(obs, name)
            step = jnp.zeros(2).at[k].set(h)
            fp = loss(eqx.tree_at(lambda o, name=name: getattr(o, name), obs, leaf + step))
            fm = loss(eqx.tree_at(lambda o, name=name: getattr(o, name), obs, leaf - step))
            assert float(getattr(g, name)[k]) == pytest.approx(
                float((fp - fm) / (2 * h)), rel=1e-4, abs=1e-8
            )


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"n": 2, "lambdas": [1.0], "c": 1.0, "d": 1.0}, "`lambdas`"),
        ({"n": 2, "lambdas": [1.0, -1.0], "c": 1.0, "d": 1.0}, "`lambdas` must be > 0"),
        ({"n": 2, "lambdas": [1.0, 1.0], "c": 0.0, "d": 1.0}, "`c` must be > 0"),
        ({"n": 2, "lambdas": [1.0, 1.0], "c": 1.0, "d": [1.0, 2.0, 3.0]}, "`d`"),
        ({"n": 2, "lambdas": [1.0, 1.0], "c": 1.0, "d": 1.0, "b0": [1.0]}, "`b0`"),
        ({"n": 0, "lambdas": [], "c": 1.0, "d": 1.0}, "`n`"),
    ],
)
def test_luders_narendra_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        obsjax.LudersNarendra(**kwargs)


def test_luders_narendra_form_bad_input():
    with pytest.raises(ValueError, match="`lambdas`"):
        obsjax.luders_narendra_form([1.0, 2.0], [1.0, 1.0], [1.0, 2.0, 3.0])


# =========================================================================== Kudva–Narendra (section 4.3-4.4)
def _kn_setup():
    ex = KUDVA_NARENDRA
    Ap, Bp = jnp.asarray(ex["Ap"]), jnp.asarray(ex["Bp"])
    plant = obsjax.LTI(Ap, Bp, jnp.eye(2))
    u = obsjax.signals.multisine(ex["amplitudes"], ex["frequencies"])
    return Ap, Bp, plant, u


def test_lyapunov_solution_matches_scipy():
    K = jnp.array([[-2.0, 1.0], [0.3, -1.5]])
    Q = jnp.array([[2.0, 0.5], [0.5, 1.0]])
    P = np.asarray(lyapunov(K, Q))
    np.testing.assert_allclose(
        P, scipy.linalg.solve_continuous_lyapunov(np.asarray(K).T, -np.asarray(Q)), rtol=1e-12
    )


@pytest.fixture(scope="module")
def kn_run():
    Ap, Bp, plant, u = _kn_setup()
    obs = obsjax.KudvaNarendra(
        2,
        2,
        K=jnp.array([[-2.0, 0.0], [0.0, -2.0]]),
        Gamma1=jnp.array([0.02, 0.02]),
        Gamma2=jnp.array([0.02, 0.02]),
        Q=jnp.eye(2),
    )
    ts = jnp.linspace(0.0, 100.0, 401)
    traj = obsjax.simulate(
        plant,
        obs,
        jnp.array([1.0, -1.0]),
        jnp.zeros(2),
        ts,
        u=u,
        rtol=1e-9,
        atol=1e-11,
        max_steps=100_000,
    )
    return Ap, Bp, obs, traj


@pytest.mark.extended
def test_kudva_narendra_lyapunov(kn_run):
    """V = ½[eᵀPe + tr(φᵀΓ₁φ + ψᵀΓ₂ψ)] is non-increasing, and V̇ = −½ eᵀQe pointwise along the flow."""
    Ap, Bp, obs, traj = kn_run
    _, _, plant, u = _kn_setup()
    V = np.asarray(obs.lyapunov(traj.z, traj.x, Ap, Bp))
    assert np.max(np.diff(V)) <= 1e-9 * V[0]
    assert V[-1] < 1e-8 * V[0]
    for k in (0, 5, 100):
        t, x = traj.ts[k], traj.x[k]
        z = jax.tree_util.tree_map(lambda v, k=k: v[k], traj.z)
        dz, dx = obs.vector_field(t, z, x, u(t)), plant.f(t, x, u(t))
        _, dV = jax.jvp(lambda zz, xx: obs.lyapunov(zz, xx, Ap, Bp), (z, x), (dz, dx))
        e = z.xm - x
        assert float(dV) == pytest.approx(-0.5 * float(e @ obs.Q @ e), rel=1e-9, abs=1e-14)


def test_kudva_narendra_identifies_mimo_plant(kn_run):
    """Two inputs with two sinusoids each: A_m → A_p, B_m → B_p (relative error < 1e-3 from t = 75)."""
    Ap, Bp, obs, traj = kn_run
    Am, Bm = obs.parameters(traj.z)
    err = np.sqrt(
        np.sum((np.asarray(Am) - np.asarray(Ap)) ** 2, axis=(1, 2))
        + np.sum((np.asarray(Bm) - np.asarray(Bp)) ** 2, axis=(1, 2))
    )
    rel = err / np.sqrt(np.sum(np.asarray(Ap) ** 2) + np.sum(np.asarray(Bp) ** 2))
    assert np.all(rel[np.asarray(traj.ts) >= 75.0] < 1e-3), rel[-1]
    assert float(traj.error_norm[-1]) < 1e-5


def test_kudva_narendra_error_is_error_model_1():
    """(4.5) is error model 1 (4.8) with θᵀ = [φ, ψ], V = [x_p; u], and (4.6)-(4.7) are its law (4.9)."""
    key = jax.random.PRNGKey(0)
    k1, k2, k3, k4, k5, k6 = jax.random.split(key, 6)
    Ap, Bp = jax.random.normal(k1, (2, 2)), jax.random.normal(k2, (2, 3))
    K, Q, G = (
        jnp.array([[-2.0, 0.5], [-0.5, -1.0]]),
        jnp.array([[2.0, 0.3], [0.3, 1.0]]),
        jnp.array([[1.5, 0.2], [0.2, 0.7]]),
    )
    obs = obsjax.KudvaNarendra(2, 3, K, G, G, Q)
    em = obsjax.ErrorModel1(K, G, Q)
    z = obs.init(0.0, jax.random.normal(k3, (2,)), None)
    z = eqx.tree_at(
        lambda s: (s.Am, s.Bm), z, (jax.random.normal(k4, (2, 2)), jax.random.normal(k5, (2, 3)))
    )
    xp, u = jax.random.normal(k6, (2,)), jnp.array([0.3, -1.0, 2.0])
    dz = obs.vector_field(0.0, z, xp, u)
    de_plant = dz.xm - (Ap @ xp + Bp @ u)
    thetaT = jnp.concatenate([z.Am - Ap, z.Bm - Bp], axis=1)
    de, dthetaT = em.vector_field(0.0, (z.xm - xp, thetaT), jnp.concatenate([xp, u]))
    np.testing.assert_allclose(de_plant, de, atol=1e-12)
    np.testing.assert_allclose(jnp.concatenate([dz.Am, dz.Bm], axis=1), dthetaT, atol=1e-12)


def test_error_model_2_converges_with_rich_input():
    """(4.10)-(4.11) with H = DᵀP: W non-increasing, ε → 0 and θ → 0 under a rich V(t) (diffrax directly)."""
    K = jnp.array([[0.0, 1.0], [-2.0, -3.0]])
    D = jnp.array([[0.0], [1.0]])
    em = obsjax.ErrorModel2(K, D, Gamma=1.0, Q=jnp.eye(2))

    def V(t):
        return jnp.array([jnp.sin(t), jnp.cos(2.3 * t)])

    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, s, args: em.vector_field(t, s, V(t))),
        diffrax.Tsit5(),
        0.0,
        300.0,
        0.01,
        (jnp.array([1.0, -1.0]), jnp.array([[2.0, -1.0]])),
        saveat=diffrax.SaveAt(ts=jnp.linspace(0, 300, 601)),
        stepsize_controller=diffrax.PIDController(rtol=1e-9, atol=1e-11),
        max_steps=100_000,
    )
    W = np.asarray(em.lyapunov(sol.ys))
    assert np.max(np.diff(W)) <= 1e-9 * W[0]
    assert W[-1] < 1e-6 * W[0]
    assert float(jnp.abs(sol.ys[1][-1]).max()) < 1e-3


@pytest.mark.extended
def test_kudva_narendra_gradient_wrt_gamma_matches_fd():
    Ap, Bp, plant, u = _kn_setup()
    obs = obsjax.KudvaNarendra(
        2,
        2,
        K=-2.0 * jnp.eye(2),
        Gamma1=jnp.array([0.5, 0.8]),
        Gamma2=jnp.array([0.7, 0.4]),
        Q=jnp.eye(2),
    )
    ts = jnp.linspace(0.0, 10.0, 41)

    @eqx.filter_jit
    def loss(o):
        traj = obsjax.simulate(
            plant, o, jnp.array([1.0, -1.0]), jnp.zeros(2), ts, u=u, rtol=1e-9, atol=1e-11
        )
        e2 = jnp.sum((traj.z.Am - Ap) ** 2, axis=(-2, -1)) + jnp.sum(
            (traj.z.Bm - Bp) ** 2, axis=(-2, -1)
        )
        return jnp.sum(0.5 * (e2[1:] + e2[:-1]) * jnp.diff(ts))

    g = eqx.filter_grad(loss)(obs)
    h = 1e-5
    # the rates Γ₁, Γ₂ (diagonals), and the model matrix K and Lyapunov weight Q (symmetric perturbation)
    cases = [("Gamma1", (0,)), ("Gamma1", (1,)), ("Gamma2", (0,)), ("Gamma2", (1,))]
    cases += [("K", (0, 1)), ("K", (1, 1)), ("Q", (0, 0)), ("Q", (0, 1))]
    for name, idx in cases:
        leaf = getattr(obs, name)
        step = jnp.zeros(leaf.shape).at[idx].set(h)
        if name == "Q":
            step = 0.5 * (step + step.T)
        fd = (
            loss(eqx.tree_at(lambda o, name=name: getattr(o, name), obs, leaf + step))
            - loss(eqx.tree_at(lambda o, name=name: getattr(o, name), obs, leaf - step))
        ) / (2 * h)
        directional = float(jnp.sum(getattr(g, name) * step) / h)
        assert directional == pytest.approx(float(fd), rel=1e-4, abs=1e-8), (name, idx)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"K": jnp.eye(2)}, "`K` must be a stable"),
        ({"K": -jnp.eye(3)}, "`K`"),
        ({"Q": -jnp.eye(2)}, "`Q` must be positive definite"),
        ({"Q": jnp.array([[1.0, 1.0], [0.0, 1.0]])}, "`Q` must be a symmetric"),
        ({"Gamma1": jnp.ones(3)}, "`Gamma1`"),
        ({"Gamma2": -1.0}, "`Gamma2` must be > 0"),
        ({"B0": jnp.zeros((2, 2))}, "`B0`"),
    ],
)
def test_kudva_narendra_bad_input(kwargs, match):
    args = {"n": 2, "m": 1, "K": -jnp.eye(2), "Gamma1": 1.0, "Gamma2": 1.0, "Q": jnp.eye(2)}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        obsjax.KudvaNarendra(**args)


def test_error_model_2_bad_h():
    with pytest.raises(ValueError, match="`H` must equal"):
        obsjax.ErrorModel2(
            -jnp.eye(2), jnp.array([[1.0], [0.0]]), 1.0, jnp.eye(2), H=jnp.array([[0.0, 1.0]])
        )


# =========================================================================== guards under jit
def test_guards_survive_jit():
    """Gains updated under jit (as tune does) are checked by eqx.error_if in prepare()."""
    k = obsjax.Kreisselmeier(2, [-1.0, -2.0], jnp.ones(4), scheme="integral", q=1.0)
    ln = obsjax.LudersNarendra(2, [1.0, 1.0], 1.0, 1.0)
    kn = obsjax.KudvaNarendra(2, 1, -jnp.eye(2), 1.0, 1.0, jnp.eye(2))
    cases = [
        (lambda v: eqx.tree_at(lambda o: o.G, k, v * jnp.ones(4)).prepare().G, "`G` must be finite and > 0"),
        (lambda v: eqx.tree_at(lambda o: o.q, k, v).prepare().q, "`q` must be > 0"),
        (lambda v: eqx.tree_at(lambda o: o.c, ln, v * jnp.ones(2)).prepare().c, "`c` must be > 0"),
        (
            lambda v: eqx.tree_at(lambda o: o.K, kn, -v * jnp.eye(2)).prepare().K,
            "`K` must be stable",
        ),
    ]
    for fn, match in cases:
        assert jnp.all(jnp.isfinite(jax.jit(fn)(1.0)))
        with pytest.raises(Exception, match=match):
            jax.block_until_ready(jax.jit(fn)(-1.0))


@pytest.mark.parametrize("n", [2.5, True, 0])
def test_kreisselmeier_order_must_be_a_positive_integer(n):
    """n = 2.5 was truncated to 2 without a word."""
    with pytest.raises(ValueError, match=r"`n` \(the plant order\) must be an integer >= 1"):
        obsjax.Kreisselmeier(n, [-1.0, -2.0], np.ones(4))


_SISO_OBSERVERS = pytest.mark.parametrize(
    "make",
    [
        lambda: obsjax.MinimalAdaptiveObserver(2, filter_poles=[-1.0], lam=1.0, Gamma=20.0),
        lambda: obsjax.NonMinimalAdaptiveObserver(2, filter_poles=[-1.0], lam0=1.0, Gamma=20.0),
        lambda: obsjax.Kreisselmeier(2, [-2.0, -2.0], 10.0, "integral", q=0.2),
        lambda: obsjax.LudersNarendra(2, lambdas=[1.0, 0.5], c=[28.0, 21.0], d=[5.0, 5.0]),
    ],
    ids=["minimal", "non-minimal", "Kreisselmeier", "Luders-Narendra"],
)


def _siso_pair():
    """(A, b) of the second-order plant that the SISO tests below give one or two inputs or outputs."""
    A = np.asarray(obsjax.kreisselmeier_form(np.array([2.0, 2.0]), np.array([1.0, 1.0])).A)
    return A, np.array([[1.0], [1.0]])


@_SISO_OBSERVERS
def test_siso_adaptive_observers_refuse_plants_with_several_inputs_or_outputs(make):
    """The plant forms (4.12), (5.1), (6.1) are single-input single-output.  A plant with two inputs was
    accepted and its second input silently dropped: status 0 and (â, b̂) = (−0.67, 0.82), (1.46, 0.02)
    for (2, 2), (1, 1) (the minimal observer); now a ValueError naming the signal."""
    A, b = _siso_pair()
    ts = jnp.linspace(0.0, 1.0, 3)
    two_in = obsjax.LTI(A, np.c_[b, [0.5, -1.0]], np.eye(1, 2))
    two_out = obsjax.LTI(A, b, np.array([[0.0, 1.0], [1.0, 0.0]]))
    for plant, sig, u in ((two_in, "`u`", jnp.ones(2)), (two_out, "`y`", jnp.ones(1))):
        with pytest.raises(ValueError, match=f"single-input single-output.*{sig}"):
            obsjax.simulate(plant, make(), jnp.ones(2), jnp.zeros(2), ts, u=lambda t, u=u: u)


@_SISO_OBSERVERS
@pytest.mark.extended
def test_siso_adaptive_observers_accept_the_single_input_single_output_plant(make):
    """The counterpart of the refusal above: the same plant with one input and one output runs."""
    A, b = _siso_pair()
    one = obsjax.LTI(A, b, np.eye(1, 2))
    ts = jnp.linspace(0.0, 1.0, 3)
    tr = obsjax.simulate(one, make(), jnp.ones(2), jnp.zeros(2), ts, u=lambda t: jnp.ones(1))
    assert int(tr.status) == 0


def test_morgan_narendra_refuses_a_non_finite_regressor_at_once():
    """A regressor that is NaN used up the integrator's whole step budget (7 s) before failing with
    'maximum number of solver steps'; it is refused before integrating now, at t0 and later."""
    with pytest.raises(ValueError, match="finite"):
        obsjax.analysis.morgan_narendra(lambda t: jnp.array([jnp.nan, 1.0]), T=1.0, horizon=5.0)
    with pytest.raises(ValueError, match=r"t = 2\.4"):
        obsjax.analysis.morgan_narendra(
            lambda t: jnp.array([jnp.where(t > 2.4, jnp.nan, 1.0), jnp.sin(t)]), T=1.0, horizon=5.0
        )


@pytest.mark.extended
def test_traced_adaptive_gains_and_poles_keep_the_eager_checks():
    """Under jit the guards tested only Re < 0 and the eigenvalues of the symmetric part: a
    non-symmetric Γ was used as it is, filter poles (−1 + j, −1 + 2j) (not closed under conjugation)
    became the filter s² + 2s − 1 with a root at +0.41, and Γ = ∞ reached the generic non-finite error.
    Each is refused by name now; valid traced values still run."""
    import equinox as eqx

    ts = jnp.linspace(0.0, 5.0, 11)
    plant = obsjax.kreisselmeier_form([3.0, 4.0, 2.5], [1.0, 0.5, 2.0])
    u = obsjax.signals.multisine([1.0, 0.8, 0.6], [0.5, 1.3, 2.7])
    x0 = jnp.array([0.3, -0.2, 0.5])

    def run(G, fp):
        obs = obsjax.MinimalAdaptiveObserver(3, fp, 1.5, G)
        return obsjax.simulate(plant, obs, x0, jnp.zeros(3), ts, u=u).xhat[-1]

    run_j = eqx.filter_jit(run)
    good = np.asarray(run_j(jnp.asarray(2.0 * np.eye(6)), jnp.array([-1.0, -2.0])))
    np.testing.assert_allclose(good, run(2.0 * np.eye(6), [-1.0, -2.0]), rtol=1e-10, atol=1e-12)
    for G, fp, what in (
        (np.eye(6) + 0.3 * np.triu(np.ones((6, 6)), 1), np.array([-1.0, -2.0]), "Gamma"),
        (np.asarray(np.inf), np.array([-1.0, -2.0]), "Gamma"),
        (2.0 * np.eye(6), np.array([-1 + 1j, -1 + 2j]), "filter_poles"),
        (2.0 * np.eye(6), np.array([np.nan, -2.0]), "filter_poles"),
    ):
        with pytest.raises(Exception, match=f"`{what}` must be finite"):
            jax.block_until_ready(run_j(jnp.asarray(G), jnp.asarray(fp)))
    pair = jnp.array([-1 + 1j, -1 - 1j])  # a conjugate pair passes traced too
    assert np.all(np.isfinite(np.asarray(run_j(jnp.asarray(2.0 * np.eye(6)), pair))))
