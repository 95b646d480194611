"""PD-spectrum synthesis (Huang & Zhu (12)-(14), (21)-(23) and the Lemma) against independent references."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import obsjax  # noqa: F401  (x64)
from obsjax.design import RampBandwidth, pd_coefficients, pd_modal_matrix, rpdo_coefficients


def omega_tv(t):
    return 2.0 + jnp.sin(t)


def omega_int(t):  # ∫_0^t ω, closed form
    return 2.0 * t + 1.0 - jnp.cos(t)


RHO = {2: [-1.0, -2.5], 3: [-1.0, -2.0, -3.5], 4: [-0.5, -1.0, -2.0, -3.0]}


def _pd_power(rho_fn, i):
    """t ↦ 𝒟_ρ^i{1} straight from the definition 𝒟_ρ{f} = ḟ + ρ f (independent of V̂ of (21))."""
    g = lambda t: jnp.ones_like(t)
    for _ in range(i):
        g = (lambda prev: lambda t: jax.grad(prev)(t) + rho_fn(t) * prev(t))(g)
    return g


def _synthesis_by_cofactors(rho_bar, omega, t):
    """α_k = ṽ_{k,n+1} / det V_n with V_{n+1}(ρ_1, …, ρ_n, ρ) built from the definition (Lemma proof)."""
    n = len(rho_bar)
    V = np.zeros((n + 1, n))
    for j, rb in enumerate(rho_bar):
        rho_fn = lambda s, rb=rb: rb * omega(s)
        for i in range(n + 1):
            V[i, j] = float(_pd_power(rho_fn, i)(jnp.asarray(t)))
    Vn = V[:n]
    alpha = np.zeros(n)
    for k in range(n):  # cofactor of entry (k, n) of the (n+1)x(n+1) matrix (last column arbitrary)
        minor = np.delete(V, k, axis=0)
        alpha[k] = (-1) ** (k + n) * np.linalg.det(minor) / np.linalg.det(Vn)
    return alpha, Vn


@pytest.mark.parametrize("t", [0.0, 0.7, 2.3])
def test_second_order_formulas_of_the_lemma(t):
    r1, r2 = -1.0, -2.5
    a = pd_coefficients(jnp.array([r1, r2]), omega_tv, t)
    w, wd = 2.0 + np.sin(t), np.cos(t)
    np.testing.assert_allclose(a[0], r1 * r2 * w**2, rtol=1e-13)
    np.testing.assert_allclose(a[1], -(r1 + r2) * w - wd / w, rtol=1e-13)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_synthesis_matches_cofactor_formula_and_modal_determinant(n):
    t = 0.9
    alpha_ref, Vn = _synthesis_by_cofactors(RHO[n], omega_tv, t)
    np.testing.assert_allclose(
        pd_coefficients(jnp.array(RHO[n]), omega_tv, t), alpha_ref, rtol=1e-10
    )
    np.testing.assert_allclose(
        pd_modal_matrix(jnp.array(RHO[n]), omega_tv, t), Vn, rtol=1e-12, atol=1e-12
    )
    # det V_n(ω) = ω^{n(n-1)/2} Π_{i<j} (ρ̄_j − ρ̄_i)  (proof of the Lemma)
    w = 2.0 + np.sin(t)
    prod = np.prod([RHO[n][j] - RHO[n][i] for i, j in itertools.combinations(range(n), 2)])
    np.testing.assert_allclose(np.linalg.det(Vn), w ** (n * (n - 1) / 2) * prod, rtol=1e-12)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_constant_bandwidth_gives_the_lti_characteristic_polynomial(n):
    a = np.asarray(pd_coefficients(jnp.array(RHO[n]), 1.7, 0.0))
    roots = np.roots(np.concatenate([[1.0], a[::-1]]))
    np.testing.assert_allclose(np.sort(roots.real), np.sort(1.7 * np.array(RHO[n])), rtol=1e-9)
    np.testing.assert_allclose(roots.imag, 0.0, atol=1e-9)
    # and β = α when ω is constant (no derivative terms)
    np.testing.assert_allclose(rpdo_coefficients(jnp.array(RHO[n]), 1.7, 0.0), a, rtol=1e-12)


@pytest.mark.parametrize("n", [2, 3, 4])
@pytest.mark.parametrize("eps", [0.5, 0.1])
def test_lemma_scaling(n, eps):
    rho = jnp.array(RHO[n])
    k = np.arange(1, n + 1)
    # constant ω: α_k(ω/ε) = ε^{-(n-k+1)} α_k(ω)
    np.testing.assert_allclose(
        pd_coefficients(rho, 1.3 / eps, 0.0),
        eps ** (-(n - k + 1)) * pd_coefficients(rho, 1.3, 0.0),
        rtol=1e-11,
    )
    # time-varying ω with τ = t/ε: α_k(ω_H(t), dt) = ε^{-(n-k+1)} α_k(ω(ετ), dτ)
    t = 0.8
    lhs = pd_coefficients(rho, lambda s: omega_tv(s) / eps, t)
    rhs = pd_coefficients(rho, lambda tau: omega_tv(eps * tau), t / eps)
    np.testing.assert_allclose(lhs, eps ** (-(n - k + 1)) * rhs, rtol=1e-10)


def _ddt(fn, order):
    for _ in range(order):
        fn = jax.jacfwd(fn)
    return fn


@pytest.mark.parametrize("n", [2, 3, 4])
@pytest.mark.extended
def test_modes_exp_integral_rho_solve_both_operators(n):
    """Defining property: y_j = exp(ρ̄_j ∫ω) solves the LPDO δⁿ + Σ α_k δ^{k-1} and the RPDO δⁿ + Σ δ^{k-1}∘β_k."""
    rho = jnp.array(RHO[n])
    alpha = lambda s: pd_coefficients(rho, omega_tv, s)
    beta = lambda s: rpdo_coefficients(rho, omega_tv, s)

    @jax.jit
    def residuals(t, rb):
        y = lambda s: jnp.exp(rb * omega_int(s))
        top = _ddt(y, n)(t)
        lp = top + sum(alpha(t)[k - 1] * _ddt(y, k - 1)(t) for k in range(1, n + 1))
        # the RPDO check at n = 4 nests 10 derivatives (minutes to compile); n = 2, 3 cover it
        if n == 4:
            return jnp.abs(lp) / jnp.abs(top)
        rp = top + sum(
            _ddt(lambda s, k=k: beta(s)[k - 1] * y(s), k - 1)(t) for k in range(1, n + 1)
        )
        return jnp.abs(jnp.stack([lp, rp])) / jnp.abs(top)

    for t in (0.3, 1.9):
        for rb in RHO[n]:
            assert np.all(residuals(jnp.asarray(t), jnp.asarray(rb)) < 1e-10)


def test_gradient_of_coefficients_matches_finite_differences():
    @jax.jit
    def f(p):
        w = RampBandwidth(p[0], p[1], p[2])
        return jnp.sum(rpdo_coefficients(jnp.array([-1.0, -2.0, -3.0]), w, 0.6) ** 2)

    p = jnp.array([0.8, 3.0, 1.5])
    g = jax.jit(jax.grad(f))(p)
    h = 1e-6
    fd = np.array([(f(p.at[i].add(h)) - f(p.at[i].add(-h))) / (2 * h) for i in range(3)])
    np.testing.assert_allclose(g, fd, rtol=1e-6)


# -- bad input -----------------------------------------------------------------------------------------


def test_repeated_rho_bar_is_refused():
    with pytest.raises(ValueError, match="distinct"):
        pd_coefficients(jnp.array([-1.0, -1.0]), 1.0, 0.0)


def test_nonpositive_omega_is_refused():
    with pytest.raises(ValueError, match="omega.*> 0"):
        pd_coefficients(jnp.array([-1.0, -2.0]), -1.0, 0.0)


def test_matrix_omega_is_refused():
    with pytest.raises(ValueError, match="omega.*scalar"):
        pd_coefficients(jnp.array([-1.0, -2.0]), jnp.ones(2), 0.0)


def test_matrix_rho_bar_is_refused():
    with pytest.raises(ValueError, match="rho_bar.*1-D"):
        pd_coefficients(jnp.ones((2, 2)), 1.0, 0.0)


def test_ramp_bandwidth_must_be_positive():
    with pytest.raises(ValueError, match="tau.*> 0"):
        RampBandwidth(1.0, 2.0, 0.0)


# ------------------------------------------------------------------ bad bandwidths, ε and ρ̄

_A3 = lambda t: jnp.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -2.0, -0.5]]) + 0.0 * t
_C3 = lambda t: jnp.array([[1.0, 0.0, 0.0]]) + 0.0 * t
_RHO3 = jnp.array([-1.0, -2.0, -3.0])


def test_nan_or_repeated_rho_bar_and_a_nan_time_are_refused_under_jit():
    """Eagerly these raise ValueError; under jit the PD-spectrum functions returned NaN gains without a
    word (a NaN or repeated ρ̄ leaves the Vandermonde solve of (21) undefined)."""
    from obsjax.design import pd_controller_gain, pd_observer_gain

    B3 = lambda t: jnp.array([[0.0], [0.0], [1.0]]) + 0.0 * t
    fns = {
        "pd_modal_matrix": lambda r, t: pd_modal_matrix(r, 2.0, t),
        "pd_coefficients": lambda r, t: pd_coefficients(r, 2.0, t),
        "rpdo_coefficients": lambda r, t: rpdo_coefficients(r, omega_tv, t),
        "pd_observer_gain": lambda r, t: pd_observer_gain(_A3, _C3, r, 2.0, t, indices=(3,)).Ko,
        "pd_controller_gain": lambda r, t: pd_controller_gain(_A3, B3, r, 2.0, t, indices=(3,)).K,
    }
    jitted = {name: jax.jit(fn) for name, fn in fns.items()}
    np.testing.assert_allclose(jitted["pd_coefficients"](_RHO3, 0.3), [48.0, 44.0, 12.0], rtol=1e-12)  # (s+2)(s+4)(s+6)
    A = _A3(0.3)
    K = jitted["pd_observer_gain"](_RHO3, 0.3)  # the defining property: eig(A + K C) = ρ̄ω
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(A + K @ _C3(0.3)).real), [-6, -4, -2], rtol=1e-10)
    K = jitted["pd_controller_gain"](_RHO3, 0.3)
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(A + B3(0.3) @ K).real), [-6, -4, -2], rtol=1e-10)
    for name, fn in jitted.items():
        for rho, what in ((jnp.array([-1.0, jnp.nan, -3.0]), "finite"), (jnp.array([-1.0, -2.0, -2.0]), "distinct")):
            with pytest.raises(Exception, match=what):
                jax.block_until_ready(fn(rho, 0.3))
        with pytest.raises(ValueError, match=what):  # eagerly, as before
            pd_coefficients(rho, 2.0, 0.3)
    for name in ("pd_observer_gain", "pd_controller_gain"):
        with pytest.raises(Exception, match="time `t` must be finite"):
            jax.block_until_ready(jitted[name](_RHO3, jnp.nan))


@pytest.mark.extended
def test_a_bandwidth_that_is_not_positive_where_it_is_used_is_refused():
    """A callable ω was never checked: ω(t) = −2 placed eig(A + KC) = {+2, +4, +6} (an unstable observer)
    and ω(t) = t − 0.5 at t = 0.5 gave a NaN gain, both without a word; a TLO with ω = −2 ran with status
    0 while its error grew to 1e12.  Now ValueError eagerly, eqx.error_if traced; the constant ω and ε are
    checked for finiteness too (ε = ∞ gave NaN)."""
    from obsjax.design import pd_controller_gain, pd_coefficients, pd_observer_gain

    K = pd_observer_gain(_A3, _C3, _RHO3, 2.0, 0.0).Ko  # the reference: eig = ρ̄ω
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(_A3(0.0) + K @ _C3(0.0)).real), [-6, -4, -2], rtol=1e-10)
    for omega, t in ((lambda t: -2.0 + 0 * t, 0.0), (lambda t: t - 0.5, 0.5), (float("inf"), 0.0)):
        with pytest.raises(ValueError, match="omega"):
            pd_observer_gain(_A3, _C3, _RHO3, omega, t)
    with pytest.raises(ValueError, match="omega"):
        pd_coefficients(_RHO3, obsjax.design.RampBandwidth(0.5, 4.0, 1.0), -1.0)  # the ramp is < 0 there
    with pytest.raises(ValueError, match="omega"):
        pd_controller_gain(_A3, lambda t: jnp.array([[0.0], [0.0], [1.0]]), _RHO3, lambda t: -2.0 + 0 * t, 0.0)
    for eps, what in ((float("inf"), "finite"), (0.0, "> 0"), (jnp.array([0.5, 1.0]), "scalar")):
        with pytest.raises(ValueError, match="eps"):
            pd_observer_gain(_A3, _C3, _RHO3, 2.0, 0.0, eps=eps)
    gj = jax.jit(lambda e, w: pd_observer_gain(_A3, _C3, _RHO3, lambda t: w + 0 * t, 0.0, eps=e, indices=(3,)).Ko)
    np.testing.assert_allclose(gj(1.0, 2.0), K, rtol=1e-12)
    for e, w in ((-1.0, 2.0), (1.0, -2.0), (0.0, 2.0), (1.0, float("nan"))):
        with pytest.raises(Exception, match="eps|bandwidth"):
            jax.block_until_ready(gj(e, w))


@pytest.mark.extended
def test_tlo_with_a_negative_bandwidth_stops_instead_of_diverging():
    model = obsjax.LTV(lambda t: _A3(t), _C3)
    ok = obsjax.TrajectoryLinearization(model, rho_bar=_RHO3, omega=lambda t: 2.0 + 0 * t, eps=1.0)
    bad = obsjax.TrajectoryLinearization(model, rho_bar=_RHO3, omega=lambda t: 2.0 - 2.0 * t, eps=1.0)
    ts = jnp.linspace(0.0, 2.0, 5)
    x0, xh0 = jnp.array([1.0, 0.5, -0.5]), jnp.zeros(3)
    tr = obsjax.simulate(model, ok, x0, xh0, ts, rtol=1e-8, atol=1e-10)
    assert int(tr.status) == 0 and float(jnp.linalg.norm(tr.error[-1])) < float(jnp.linalg.norm(tr.error[0]))
    with pytest.raises(Exception, match="bandwidth"):  # ω crosses 0 at t = 1
        obsjax.simulate(model, bad, x0, xh0, ts, rtol=1e-8, atol=1e-10)


def test_nearly_repeated_nominal_pd_eigenvalues_are_refused():
    """ρ̄ = (−1, −1 − 1e-14, −2) passed the exact distinctness test and gave coefficients 6 % off (the
    Vandermonde solve); values closer than 1e-8·max|ρ̄| are refused now, and 1e-4 apart stay exact."""
    from obsjax.design import pd_coefficients

    with pytest.raises(ValueError, match="distinct"):
        pd_coefficients(jnp.array([-1.0, -1.0 - 1e-14, -2.0]), 3.0, 0.0)
    rb = np.array([-1.0, -1.0 - 1e-4, -2.0])
    exact = np.poly(rb * 3.0)[1:][::-1]  # α_1 … α_n of Π(s − ρ̄ω)
    np.testing.assert_allclose(pd_coefficients(jnp.asarray(rb), 3.0, 0.0), exact, rtol=1e-9)


# A 4-state, 2-output pair whose second output approaches the first (C2 = C1 + δ v(t)): observable for
# every δ ≠ 0, with a staircase margin of Q_0 about 3·δ²... (3.0e-6 at δ = 1e-4, 3.0e-8 at δ = 1e-6).
_AB = np.array([
    [-0.8019314252534474, -1.324358995628145, -0.24836162209524854, 0.4204452380655215],
    [1.1360465324896427, 0.10970639932180819, -0.5526473205362324, -0.7847803553442784],
    [0.7487457707345911, 1.6347830429585775, 0.27276877584472176, -1.2333286640307717],
    [-0.9582652054360887, 1.6000190889991115, 0.2028824405086084, -1.7321348424395848],
])  # fmt: skip
_C0, _DV = np.array([1.0, 0.5, -0.3, 0.2]), np.array([0.3, -1.0, 0.7, 0.4])
# α of the canonical form at t = 0.5, δ = 1e-4, indices (2, 2): Huang & Zhu (10)-(11) evaluated as
# truncated Taylor series in 50-digit mpmath arithmetic (an implementation independent of the library's,
# written for the review of this function), rounded to float64.
_ALPHA_REF_1E4 = np.array([
    [-591661.6183587856, 591746.7855212577],
    [-174583.7265866687, 174603.36583859066],
    [-591600.0547555942, 591685.2130453354],
    [-174564.3692129195, 174584.00619092185],
])  # fmt: skip


def _near_pair(delta):
    J = jnp.asarray(np.eye(4)[:, ::-1])
    A = lambda t: jnp.asarray(_AB) + 0.3 * jnp.sin(t) * J
    C = lambda t: jnp.stack([jnp.asarray(_C0), jnp.asarray(_C0) + delta * (jnp.asarray(_DV) + 0.1 * jnp.cos(t) * jnp.eye(4)[3])])
    return A, C


@pytest.mark.extended
def test_canonical_form_refuses_pairs_it_cannot_compute_accurately():
    """The form inverts T⁻¹, conditioned like 1/margin²: α was off by 5e-3 at margin 3e-8 and by 234 % at
    1.5e-9 (the gain of pd_observer_gain by a factor of 80), accepted by the rank threshold 1e-9.  The
    default threshold of the form is 1e-6 (a loss of about ε/margin² ≤ 2e-4)."""
    from obsjax.design import ltv_observer_canonical_form, pd_observer_gain

    @jax.jit
    def form(delta, t):  # traced t: the margin comes back for the caller's check (TrajectoryLinearization's)
        cf = ltv_observer_canonical_form(*_near_pair(delta), t, indices=(2, 2))
        return cf.alpha, cf.margin

    alpha, margin = form(1e-4, 0.5)  # margin 3.0e-6: accepted, and accurate
    assert 1e-6 < float(margin) < 1e-5
    np.testing.assert_allclose(alpha, _ALPHA_REF_1E4, rtol=5e-6)
    assert float(form(1e-6, 0.5)[1]) < obsjax.design._ltv_canonical.CANONICAL_TOL  # margin 3.0e-8
    A, C = _near_pair(1e-6)
    with pytest.raises(ValueError, match=r"would lose about ε/margin² = .* of its relative accuracy"):
        ltv_observer_canonical_form(A, C, 0.5, indices=(2, 2))
    with pytest.raises(ValueError, match="staircase margin"):
        pd_observer_gain(A, C, jnp.array([-1.0, -2.0, -3.0, -4.0]), 2.0, 0.5, indices=(2, 2))
