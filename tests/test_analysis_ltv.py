"""LTV analysis (Chen & Yen (2)-(7), (16)-(19)) against closed forms, SciPy and defining properties."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg

import obsjax
from obsjax import analysis as an
from obsjax._reproduce.references import CHEN_YEN_OPEN_LOOP_NORM_10
from obsjax.observers._least_squares import _SW_A1, _SW_A2, _SW_C1, _SW_C2

CY = obsjax.chen_yen_example()
SW = obsjax.switching_ltv_example()


def _np_A(t):  # Chen & Yen's A(t), written again in NumPy (independent of the library's version)
    c, s = np.cos(t), np.sin(t)
    return np.array([[-1 + 1.5 * c * c, 1 - 1.5 * s * c], [-1 + 1.5 * s * c, -1 + 1.5 * s * s]])


def _np_C(t):
    r = np.sqrt(t)
    return np.array([[np.cos(r) + np.sin(r), 3 * np.cos(r) ** 2]])


def _sw_transition(t, tau, period=0.7):
    """Closed form for the switching plant: a product of matrix exponentials (SciPy expm)."""
    A = [np.array(_SW_A1), np.array(_SW_A2)]
    edges = [tau] + [period * k for k in range(1, 200) if tau < period * k < t] + [t]
    Phi = np.eye(3)
    for a, b in itertools.pairwise(edges):
        mode = int(np.floor((0.5 * (a + b)) / period)) % 2
        Phi = scipy.linalg.expm(A[mode] * (b - a)) @ Phi
    return Phi


def test_transition_matrix_switching_closed_form_and_inverse():
    Phi = np.asarray(an.transition_matrix(SW, 3.3, 0.4))
    np.testing.assert_allclose(Phi, _sw_transition(3.3, 0.4), rtol=1e-8, atol=1e-10)
    back = np.asarray(an.transition_matrix(SW, 0.4, 3.3))  # backwards in time: Φ(τ, t) = Φ(t, τ)⁻¹
    np.testing.assert_allclose(back @ Phi, np.eye(3), atol=1e-8)
    np.testing.assert_allclose(np.asarray(an.transition_matrix(SW, 1.0, 1.0)), np.eye(3))


def test_transition_matrix_example_scipy_and_open_loop_instability():
    sol = scipy.integrate.solve_ivp(
        lambda t, v: (_np_A(t) @ v.reshape(2, 2)).ravel(),
        (0, 10),
        np.eye(2).ravel(),
        rtol=1e-11,
        atol=1e-13,
        method="DOP853",
    )
    Phi = np.asarray(an.transition_matrix(CY, 10.0, 0.0))
    np.testing.assert_allclose(Phi, sol.y[:, -1].reshape(2, 2), rtol=1e-7, atol=1e-9)
    # The open loop is unstable, ‖x(10)‖ = 11.63 from x(0) = [5, -5] (independent SciPy value).
    assert abs(np.linalg.norm(Phi @ [5.0, -5.0]) - CHEN_YEN_OPEN_LOOP_NORM_10) < 5e-3


@pytest.mark.extended
def test_gramians_lti_closed_form():
    A = np.array([[0.0, 1.0], [-2.0, -0.3]])
    C = np.array([[1.0, 0.0]])
    plant = obsjax.LTI(A, C=C)
    T = 1.3
    ref, _ = scipy.integrate.quad_vec(
        lambda s: scipy.linalg.expm(A.T * s) @ C.T @ C @ scipy.linalg.expm(A * s),
        0.0,
        T,
        epsabs=1e-13,
    )
    W = np.asarray(an.observability_gramian(plant, 2, T))  # window [T, 2T]; LTI: same as [0, T]
    np.testing.assert_allclose(W, ref, rtol=1e-8, atol=1e-12)
    refe, _ = scipy.integrate.quad_vec(
        lambda s: scipy.linalg.expm(-A.T * s) @ C.T @ C @ scipy.linalg.expm(-A * s),
        0.0,
        T,
        epsabs=1e-13,
    )
    We = np.asarray(an.observability_gramian(plant, 1, T, reference="end"))
    np.testing.assert_allclose(We, refe, rtol=1e-8, atol=1e-12)


@pytest.mark.extended
def test_regressor_gramian_appendix_identity():
    # W_o^z(k) = Φᵀ(kT, kT-T) W_o^end(k) Φ(kT, kT-T) (Appendix), and = W_o(k) of (4) as printed.
    T, k = 1.1, 3
    Wz = np.asarray(an.regressor_gramian(SW, k, T))
    We = np.asarray(an.observability_gramian(SW, k, T, reference="end"))
    Ws = np.asarray(an.observability_gramian(SW, k, T))
    Phi = _sw_transition(k * T, (k - 1) * T)
    np.testing.assert_allclose(Wz, Phi.T @ We @ Phi, rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(Wz, Ws, rtol=1e-10, atol=1e-12)


@pytest.mark.extended
def test_constants_lemma_and_definitions():
    T = 0.93
    c = an.uniform_observability_constants(SW, T, 9.3)
    assert c.mu.shape == (10,)
    for k in range(10):
        a = k * T
        Phi = _sw_transition(a + T, a)
        sv = np.linalg.svd(Phi, compute_uv=False)
        np.testing.assert_allclose([c.m1[k], c.m2[k]], [sv[-1], sv[0]], rtol=1e-7)
        assert (
            c.mu[k] >= max(1.0, sv[0]) - 1e-9
        )  # Φ(t_k, t_k) = I and the period's end are on the grid
        if k in (0, 5, 9):  # μ is a sup sampled on n_grid = 129 points: compare with a finer sampling
            mu_fine = max(np.linalg.norm(_sw_transition(s, a), 2) for s in np.linspace(a, a + T, 301))
            assert abs(c.mu[k] - mu_fine) < 2e-3 * mu_fine
    # The Lemma (16): α1 m1² ≤ η1 ≤ η2 ≤ α2 m2², period by period.
    assert np.all(c.alpha1 * c.m1**2 <= c.eta1 * (1 + 1e-8))
    assert np.all(c.eta2 <= c.alpha2 * c.m2**2 * (1 + 1e-8))
    assert np.all(c.alpha1 > 1e-3)  # uniformly observable with T = 0.93 (> the switching period)


@pytest.mark.extended
def test_switching_plant_needs_long_windows():
    # Each mode alone is unobservable (rank 2): a window inside one mode sees nothing of one direction.
    assert (
        int(np.linalg.matrix_rank(np.asarray(an.obsv(jnp.asarray(_SW_A1), jnp.asarray(_SW_C1)))))
        == 2
    )
    assert (
        int(np.linalg.matrix_rank(np.asarray(an.obsv(jnp.asarray(_SW_A2), jnp.asarray(_SW_C2)))))
        == 2
    )
    short = an.is_persistently_exciting(SW, 0.35, 7.0)
    assert not short and short.eta1 < 1e-12
    assert an.is_persistently_exciting(SW, 0.93, 9.3)


def test_is_persistently_exciting_closed_form():
    pe = an.is_persistently_exciting(lambda t: jnp.array([jnp.sin(t), jnp.cos(t)]), 2 * np.pi, 13.0)
    assert pe and pe.per_window.shape == (2, 2)
    np.testing.assert_allclose([pe.eta1, pe.eta2], [np.pi, np.pi], rtol=1e-8)
    flat = an.is_persistently_exciting(lambda t: jnp.array([1.0, 0.0]), 1.0, 3.0)
    assert not flat and abs(flat.eta1) < 1e-12 and abs(flat.eta2 - 1.0) < 1e-9


@pytest.mark.extended
def test_persistent_excitation_verdict_does_not_depend_on_the_components_units():
    """w = D [sin t, cos t, sin 2t + 0.3, cos 3t]: excitation is the same for every diagonal D, but the raw
    ratio η1/η2 is 1e-12 for D spanning 1e±3 and the verdict was "not exciting".  Now decided on the
    equilibrated gramians; η1 stays the raw one (closed form π·min D² here: the four components are
    orthogonal over [0, 2π] with ∫ = π, and the constant 0.3 adds 0.18π to the third)."""
    base = lambda t: jnp.array([jnp.sin(t), jnp.cos(t), jnp.sin(2 * t) + 0.3, jnp.cos(3 * t)])
    for span in (5.0,):  # components in units 1e-5 … 1e5 (identical units: the closed-form test above)
        D = np.logspace(-span, span, 4)
        pe = an.is_persistently_exciting(lambda t: jnp.asarray(D) * base(t), 2 * np.pi, 4 * np.pi)
        assert pe, span
        G = np.pi * np.diag(D**2 * np.array([1.0, 1.0, 1.18, 1.0])) + np.zeros((4, 4))
        G[2, 2] = (np.pi + 0.18 * np.pi) * D[2] ** 2  # ∫ (sin 2t + 0.3)² = π + 0.09·2π
        np.testing.assert_allclose(pe.eta1, np.linalg.eigvalsh(G)[0], rtol=1e-7)
        # two components that are one signal in different units: never exciting
        dep = an.is_persistently_exciting(
            lambda t: jnp.array([D[0] * jnp.sin(t), D[-1] * jnp.sin(t), jnp.cos(t)]), 2 * np.pi, 4 * np.pi
        )
        assert not dep, span


@pytest.mark.parametrize(
    "k, e",  # 5 s each here: second tier (the default tier's constants tests run the same scaled solve)
    [pytest.param(1.0, 1e-4, marks=pytest.mark.extended), pytest.param(1e-3, 1e-3, marks=pytest.mark.extended)],
)
def test_uniform_observability_constants_in_small_output_and_time_units(k, e):
    """The gramians were integrated with an absolute atol = 1e-12, the size of the answer for outputs in a
    unit 1e4 times larger or time in ms: α1 and η1 of the Chen & Yen example came out 1.2e-4 and 7.3e-3
    too large (an optimistic chen_yen_bound).  Reference: scipy in s = √t (which removes the kink of C
    at t = 0), period [0, 0.5]; α1, η1 scale by k e² for t' = k t, y' = e y."""
    base = obsjax.chen_yen_example()

    def A(t):
        c, s_ = np.cos(t), np.sin(t)
        return np.array([[-1 + 1.5 * c * c, 1 - 1.5 * s_ * c], [-1 + 1.5 * s_ * c, -1 + 1.5 * s_ * s_]])

    def C(t):
        r = np.sqrt(max(t, 0.0))
        return np.array([[np.cos(r) + np.sin(r), 3 * np.cos(r) ** 2]])

    def rhs(s_, y):
        t = s_ * s_
        P = y[:4].reshape(2, 2)
        w = P.T @ C(t).T
        return 2 * s_ * np.concatenate([(A(t) @ P).ravel(), (w @ w.T).ravel()])

    sol = scipy.integrate.solve_ivp(rhs, (0, np.sqrt(0.5)), np.r_[np.eye(2).ravel(), np.zeros(4)],
                                    method="DOP853", rtol=1e-13, atol=1e-16)
    PT, Wz = sol.y[:4, -1].reshape(2, 2), sol.y[4:, -1].reshape(2, 2)
    Wend = np.linalg.inv(PT).T @ Wz @ np.linalg.inv(PT)
    a1, eta1 = np.linalg.eigvalsh(Wend)[0], np.linalg.eigvalsh(Wz)[0]
    P = obsjax.LTV(lambda t: base.A_of(t / k) / k, lambda t: e * base.C_of(t / k))
    c = an.uniform_observability_constants(P, 0.5 * k, 0.5 * k)
    assert float(c.alpha1[0]) / (k * e**2) == pytest.approx(a1, rel=1e-8)
    assert float(c.eta1[0]) / (k * e**2) == pytest.approx(eta1, rel=1e-8)


@pytest.mark.extended
def test_short_pulses_in_a_callable_regressor_are_integrated_at_their_declared_jump_times():
    """w = [p(t), 1] with p a pulse of width 1e-4 in each window of length 1: ∫ w wᵀ = [[δ, δ], [δ, 1]]
    per window, δ = 1e-4.  Without its jump times the integrator stepped over every pulse and both tests
    called the regressor not exciting (η1 = 0); with `jump_ts` they give the closed form."""
    width = 1e-4

    def w(t):
        r = jnp.mod(t, 1.0)
        return jnp.array([jnp.where((r >= 0.5) & (r < 0.5 + width), 1.0, 0.0), 1.0 + 0.0 * t])

    jumps = np.concatenate([np.arange(5) + 0.5 + width, np.arange(5) + 0.5])  # unsorted on purpose
    exact = np.linalg.eigvalsh(np.array([[width, width], [width, 1.0]]))
    pe = an.is_persistently_exciting(w, 1.0, 5.0, jump_ts=jumps)
    assert pe
    np.testing.assert_allclose([pe.eta1, pe.eta2], exact, rtol=1e-8)
    mn = an.morgan_narendra(w, 1.0, 5.0, jump_ts=jumps)
    assert mn
    np.testing.assert_allclose([mn.eta1, mn.eta2], exact, rtol=1e-8)
    with pytest.raises(ValueError, match="jump_ts"):
        an.is_persistently_exciting(w, 1.0, 5.0, jump_ts=[0.5, np.nan])
    with pytest.raises(ValueError, match="plant declares"):
        an.is_persistently_exciting(SW, 0.93, 9.3, jump_ts=[1.0])


@pytest.mark.parametrize(
    "s", [pytest.param(1e-6, marks=pytest.mark.extended), pytest.param(1e-3, marks=pytest.mark.extended), 1e4]
)
@pytest.mark.extended
def test_persistent_excitation_does_not_depend_on_units(s):
    """w = s [sin t, cos t]: η1 = η2 = π s².  The verdict compared η1 with tol·max(1, η2), an absolute
    floor (False for s ≤ 1e-5 although η1/η2 = 1), and the gramian's atol was absolute (η1 1.1 % off at
    s = 1e-6).  Both are relative now; a regressor without excitation stays non-exciting at any scale;
    a plant's output map in other units scales the gramians by s² and keeps the verdict."""
    pe = an.is_persistently_exciting(lambda t: s * jnp.array([jnp.sin(t), jnp.cos(t)]), 2 * np.pi, 13.0)
    assert pe
    np.testing.assert_allclose([pe.eta1, pe.eta2], [np.pi * s**2] * 2, rtol=1e-8)
    flat = an.is_persistently_exciting(lambda t: s * jnp.array([1.0, 0.0]), 1.0, 3.0)
    assert not flat and abs(flat.eta2 - s**2) < 1e-9 * s**2
    scaled = obsjax.LTV(SW.A_of, lambda t: s * SW.C_of(t))
    for T, H, verdict in ((0.35, 7.0, False), (0.93, 9.3, True)):
        ref, got = an.is_persistently_exciting(SW, T, H), an.is_persistently_exciting(scaled, T, H)
        assert bool(got) == bool(ref) == verdict
        np.testing.assert_allclose(got.eta2, s**2 * ref.eta2, rtol=1e-6)


@pytest.mark.extended
def test_chen_yen_bound_formula_and_small_T():
    c = an.uniform_observability_constants(CY, 2.0, 10.0)
    rho = np.asarray(an.chen_yen_bound(CY, 20.0, 0.1, 2.0, 10.0))
    np.testing.assert_allclose(rho, c.mu / (1 + 2.0 * c.alpha1 * c.m1**2), rtol=1e-12)
    assert rho.shape == (5,)
    # Remark 2: as T → 0, α1 → 0 (no observability on a short window) and the factor tends to μ ≥ 1.
    Ts = (0.8, 0.4, 0.2, 0.1)
    a1 = [float(an.uniform_observability_constants(CY, T, T, t0=1.0).alpha1[0]) for T in Ts]
    r = [float(an.chen_yen_bound(CY, 20.0, 0.1, T, T, t0=1.0)[0]) for T in Ts]
    assert all(x > y > 0 for x, y in itertools.pairwise(a1)) and a1[-1] < 1e-4 * a1[0]
    assert all(x > y >= 1.0 for x, y in itertools.pairwise(r)) and r[-1] < 1.02


def test_decay_rate_exact_exponential():
    ts = jnp.linspace(0.0, 5.0, 51)
    err = 3.0 * jnp.exp(-0.7 * ts)[:, None] * jnp.array([0.6, -0.8])
    assert abs(float(an.decay_rate((ts, err))) - 0.7) < 1e-12
    # samples below `floor` (round-off) and outside the window are left out
    err2 = err.at[40:].set(0.0).at[:5].set(100.0)
    assert abs(float(an.decay_rate((ts, err2), t_min=0.5)) - 0.7) < 1e-12


@pytest.mark.parametrize("units", [1.0, 1e-13, 1e9])
def test_decay_rate_is_relative_and_refuses_a_failed_trajectory(units):
    """The floor was an absolute 1e-12: an error in units 1e-13 was refused as "at round-off".  A NaN
    tail (a solve that failed at t = 6) was dropped by the floor test and the clean rate returned, as if
    the trajectory had converged; all samples at one time gave NaN eagerly.  Now: the floor is relative
    to the largest error in the window; a non-finite sample in the window raises eagerly and gives NaN
    traced (also under vmap, member by member)."""
    ts = np.linspace(0.0, 10.0, 101)
    err = units * np.exp(-ts)[:, None] * np.array([[1.0, 2.0]])
    assert abs(float(an.decay_rate((ts, err))) - 1.0) < 1e-10
    bad = err.copy()
    bad[60:] = np.nan
    with pytest.raises(ValueError, match=r"not finite at t = 6 .*failed trajectory"):
        an.decay_rate((ts, bad))
    assert abs(float(an.decay_rate((ts, bad), t_max=5.5)) - 1.0) < 1e-10  # a window before the failure
    rates = jax.vmap(lambda e: an.decay_rate((jnp.asarray(ts), e)))(jnp.stack([jnp.asarray(err), jnp.asarray(bad)]))
    assert abs(float(rates[0]) - 1.0) < 1e-10 and np.isnan(float(rates[1]))
    with pytest.raises(ValueError, match="distinct times"):
        an.decay_rate((np.ones(5), units * np.exp(-np.arange(5.0))))


def test_error_transition_matrix_bad_plant():
    with pytest.raises(ValueError, match="plant"):
        an.transition_matrix(object(), 1.0, 0.0)


def test_error_gramian_bad_k():
    with pytest.raises(ValueError, match="`k`"):
        an.observability_gramian(CY, 0, 1.0)
    for k in (1.5, 2.7, float("nan"), True):  # was truncated to a window [0.5, 1.5] for k = 1.5
        with pytest.raises(ValueError, match=r"`k` must be an integer >= 1"):
            an.observability_gramian(CY, k, 1.0)
    np.testing.assert_allclose(an.observability_gramian(CY, 2.0, 1.0), an.observability_gramian(CY, 2, 1.0))


@pytest.mark.extended
def test_error_gramian_end_reference_that_overflows():
    """A fast stable mode over T = 2: Φ(kT − T, kT) overflows (e^{2000} for the mode −1e3), and the
    end-referenced gramian came back with −inf on its diagonal (a gramian is positive semidefinite).  (The
    case was first a mode −1e5, whose explicit solve took a minute: the same overflow, far more steps.)"""
    import obsjax

    A = np.diag([-1.0, -30.0, -1e3]) + np.eye(3, k=1)
    plant = obsjax.LTI(A, np.zeros((3, 1)), np.array([[1.0, 1.0, 1.0]]))
    with pytest.raises(ValueError, match=r"reference='end'\): W_o\(k\) .* overflows"):
        an.observability_gramian(plant, 1, 2.0, reference="end")
    assert np.all(np.isfinite(np.asarray(an.observability_gramian(plant, 1, 2.0))))  # start reference


def test_error_gramian_bad_reference():
    with pytest.raises(ValueError, match="reference"):
        an.observability_gramian(CY, 1, 1.0, reference="middle")


def test_error_nonpositive_T():
    with pytest.raises(ValueError, match="`T`"):
        an.uniform_observability_constants(CY, -0.5, 10.0)


def test_error_horizon_shorter_than_T():
    with pytest.raises(ValueError, match="horizon"):
        an.chen_yen_bound(CY, 20.0, 0.1, 2.0, 1.0)


def test_error_bound_nonpositive_gain():
    with pytest.raises(ValueError, match="gamma"):
        an.chen_yen_bound(CY, 0.0, 0.1, 2.0, 10.0)


def test_error_pe_bad_regressor():
    with pytest.raises(ValueError, match="w\\(t\\)"):
        an.is_persistently_exciting(lambda t: jnp.zeros((2, 2, 2)), 1.0, 2.0)


def test_error_decay_rate_shape():
    with pytest.raises(ValueError, match="error"):
        an.decay_rate((jnp.linspace(0, 1, 5), jnp.ones((4, 2))))


def test_non_finite_times_and_bad_tolerances_are_refused():
    """A NaN time gave the identity for Φ (eagerly and under jit; diffrax returns y0 for a NaN end), a NaN
    or infinite t0 gave gramians of inf or zeros and PE verdicts of False, and tol = −1 called a constant
    two-dimensional regressor persistently exciting."""
    import jax
    import jax.numpy as jnp

    import obsjax

    pl = obsjax.LTV(lambda t: jnp.array([[0.0, 1.0], [-1.0, 0.0]]), lambda t: jnp.array([[1.0, 0.0]]))
    sc = lambda t: jnp.array([jnp.sin(t), jnp.cos(t)])  # noqa: E731 - PE, η1 = π per window 2π
    cases = [
        (lambda: an.transition_matrix(pl, np.nan, 0.0), r"`t` must be a finite scalar time"),
        (lambda: an.transition_matrix(pl, 2.0, 0.0, rtol=-1.0), r"`rtol` must be a positive finite scalar"),
        (lambda: an.observability_gramian(pl, 1, 1.0, t0=np.nan), r"`t0` must be a finite scalar"),
        (lambda: an.regressor_gramian(pl, 1, 1.0, t0=np.inf), r"`t0` must be a finite scalar"),
        (lambda: an.uniform_observability_constants(pl, 1.0, 3.0, t0=np.nan), r"`t0` must be a finite scalar"),
        (lambda: an.uniform_observability_constants(pl, 1.0, 3.0, n_grid=2.7), r"`n_grid` must be an integer"),
        (lambda: an.is_persistently_exciting(sc, T=2 * np.pi, horizon=20.0, t0=np.nan), r"`t0` must be a finite"),
        (lambda: an.is_persistently_exciting(sc, T=2 * np.pi, horizon=20.0, tol=np.nan), r"`tol` must be a finite"),
        (lambda: an.is_persistently_exciting(lambda t: jnp.array([1.0, 2.0]), T=1.0, horizon=5.0, tol=-1.0),
         r"`tol` must be ≥ 0"),
        (lambda: an.morgan_narendra(sc, T=2 * np.pi, horizon=20.0, t0=np.nan), r"`t0` must be a finite"),
        (lambda: an.morgan_narendra(sc, T=2 * np.pi, horizon=20.0, tol=np.nan), r"`tol` must be a finite"),
    ]
    for call, match in cases:
        with pytest.raises(ValueError, match=match):
            call()
    with pytest.raises(Exception, match=r"`t` and `tau` must be finite"):
        jax.block_until_ready(jax.jit(lambda t: an.transition_matrix(pl, t, 0.0))(jnp.nan))
    assert bool(an.is_persistently_exciting(sc, T=2 * np.pi, horizon=20.0))  # the valid call is unchanged


def test_decay_rate_refuses_a_window_it_cannot_fit():
    """A window past the data, t_min > t_max, one sample left or an error at round-off gave NaN; ts of
    shape (51, 1) gave 1.4e-18 instead of the true rate 2."""
    ts = np.linspace(0.0, 5.0, 51)
    err = np.exp(-2.0 * ts)[:, None] * np.array([[1.0, 0.5]])
    assert abs(float(an.decay_rate((ts, err))) - 2.0) < 1e-12
    for kw, match in (
        (dict(t_min=10.0), "at least 2 samples"),
        (dict(t_min=5.0), "at least 2 samples"),
        (dict(t_min=3.0, t_max=1.0), r"`t_min` must be < `t_max`"),
    ):
        with pytest.raises(ValueError, match=match):
            an.decay_rate((ts, err), **kw)
    with pytest.raises(ValueError, match="at least 2 samples"):
        an.decay_rate((ts, np.zeros_like(err)))
    with pytest.raises(ValueError, match=r"`ts` must be a 1-D array"):
        an.decay_rate((ts[:, None], err))


def test_decay_rate_refuses_a_bad_floor_or_window_bound():
    """floor < 0 let exact zeros into the log fit (NaN); a NaN floor or t_min was reported as 'needs at
    least 2 samples'."""
    ts = jnp.linspace(0.0, 5.0, 11)
    err = jnp.exp(-2.0 * ts).at[-1].set(0.0)
    np.testing.assert_allclose(an.decay_rate((ts, err), t_max=4.9), 2.0, rtol=1e-12)
    for kw, what in (({"floor": -1e-3}, "floor"), ({"floor": float("nan")}, "floor"), ({"floor": 1.0}, "floor"),
                     ({"t_min": float("nan")}, "t_min"), ({"t_max": float("inf")}, "t_max")):
        with pytest.raises(ValueError, match=f"`{what}` must be"):
            an.decay_rate((ts, err), **kw)


def test_a_non_finite_plant_or_regressor_is_named_before_integrating():
    """NaN in A(t) or in a regressor used up the integrator's step budget and was reported as 'maximum
    number of solver steps ... increase max_steps'; it is refused by name, with the time, now."""
    bad_plant = obsjax.LTV(lambda t: jnp.where(t > 3, jnp.nan, 1.0) * jnp.eye(2), lambda t: jnp.array([[1.0, 1.0]]))
    with pytest.raises(ValueError, match=r"not finite at t = 3\.0"):
        an.transition_matrix(bad_plant, 5.0, 0.0)
    with pytest.raises(ValueError, match="not finite"):
        an.observability_gramian(bad_plant, 1, 4.0)
    with pytest.raises(ValueError, match="not finite"):
        an.uniform_observability_constants(bad_plant, 1.0, 5.0)
    w = lambda t: jnp.where((t > 1) & (t < 2), jnp.nan, 1.0) * jnp.array([jnp.sin(t), jnp.cos(t)])  # noqa: E731
    with pytest.raises(ValueError, match="regressor .* not finite"):
        an.is_persistently_exciting(w, 2 * np.pi, 20.0)
    np.testing.assert_allclose(an.transition_matrix(bad_plant, 2.0, 0.0), np.exp(2.0) * np.eye(2), rtol=1e-9)


def _stiff_exact(lam, b, T):
    """A = [[λ, 0], [1, b]], C = [1, 1] at 800 digits (cond W_o^end = e^{2|λ|T} needs |λ|T/1.15 of them): m1 = σ_min Φ(T, 0) and the extreme eigenvalues of
    W_o^end = V⁻ᵀ H V⁻¹ (A = V diag(λ, b) V⁻¹, H_ij = c_i c_j (1 − e^{−(λ_i+λ_j)T}) / (λ_i + λ_j), c = C V):
    closed forms that share nothing with the solver."""
    import mpmath as mp

    with mp.workdps(800):
        lam, b, T = mp.mpf(lam), mp.mpf(b), mp.mpf(T)
        e = lambda x: mp.e**x  # noqa: E731
        Phi = mp.matrix([[e(lam * T), 0], [(e(b * T) - e(lam * T)) / (b - lam), e(b * T)]])
        V = mp.matrix([[b - lam, 0], [-1, 1]])
        c, ev = [b - lam - 1, mp.mpf(1)], [lam, b]
        H = mp.matrix(2, 2)
        for i in range(2):
            for j in range(2):
                s = ev[i] + ev[j]
                H[i, j] = c[i] * c[j] * (1 - e(-s * T)) / s
        Vi = V**-1
        W = Vi.T * H * Vi
        ew = sorted(mp.eigsy(W, eigvals_only=True))
        m1 = min(mp.svd_r(Phi, compute_uv=False))
        return float(m1), float(ew[0]), float(ew[-1]), np.array(W.tolist(), dtype=float)


@pytest.mark.extended
def test_constants_of_a_fast_stable_mode_are_not_floored_by_the_tolerance():
    """m1 = σ_min Φ(t_k + T, t_k) and α2 = λ_max(W_o^end) with a mode e^{λT} far below the solver's atol.
    Integrated forwards, the small singular value sat at the absolute tolerance: m1 = 2.8e-14 for the exact
    3.7e-44 (λ = −50, T = 2), and α2 = 1.25e25 for 6.9e84; the end-referenced gramian was 60 orders of
    magnitude off in norm.  Where float64 cannot hold them (λ = −400) m1 rounds to 0 and α2 to ∞, while α1
    stays exact."""
    T = 2.0
    for lam in (-12.0, -50.0, -400.0):
        plant = obsjax.LTI(np.array([[lam, 0.0], [1.0, 0.1]]), None, np.array([[1.0, 1.0]]))
        m1, a1, a2, W = _stiff_exact(lam, 0.1, T)
        c = an.uniform_observability_constants(plant, T, T)
        np.testing.assert_allclose(float(c.alpha1[0]), a1, rtol=1e-8)
        if lam > -300:
            np.testing.assert_allclose(float(c.m1[0]), m1, rtol=1e-7)
            np.testing.assert_allclose(float(c.alpha2[0]), a2, rtol=1e-7)
            We = np.asarray(an.observability_gramian(plant, 1, T, reference="end"))
            assert np.linalg.norm(We - W) <= 1e-7 * np.linalg.norm(W)
        else:
            assert m1 == 0.0 and float(c.m1[0]) == 0.0  # e^{−800}: below float64
            assert a2 == np.inf and float(c.alpha2[0]) == np.inf
        rho = an.chen_yen_bound(plant, 20.0, 0.1, T, T)
        np.testing.assert_allclose(float(rho[0]), float(c.mu[0]) / (1 + 2.0 * a1 * m1**2), rtol=1e-9)


@pytest.mark.extended
def test_error_transition_that_overflows_within_a_period_names_the_cause():
    """An unstable mode e^{400 t} over T = 2 overflows float64: the forward solve used up its step budget
    and the analysis reported 'increase max_steps', which cannot help.  The end-referenced gramian, solved
    backwards, is finite there (W = diag-ish, 1/800 in the fast direction)."""
    plant = obsjax.LTI(np.diag([400.0, -1.0]), None, np.array([[1.0, 1.0]]))
    for call in (
        lambda: an.chen_yen_bound(plant, 20.0, 0.1, 2.0, 2.0),
        lambda: an.regressor_gramian(plant, 1, 2.0),
    ):
        with pytest.raises(ValueError, match=r"overflows float64 within the period .* shorter period T"):
            call()
    We = np.asarray(an.observability_gramian(plant, 1, 2.0, reference="end"))
    exact = np.array(
        [[(1 - np.exp(-1600.0)) / 800, (1 - np.exp(-798.0)) / 399], [0.0, (1 - np.exp(4.0)) / -2.0]]
    )
    exact[1, 0] = exact[0, 1]
    np.testing.assert_allclose(We, exact, rtol=1e-9)


@pytest.mark.extended
def test_transition_matrix_derivatives_at_equal_times():
    """At t = τ, Φ = I with ∂Φ/∂t = A(τ) and ∂Φ/∂τ = −A(τ) (d/dt expm(A (t − τ))); the guard of the tie
    returned a constant I there, so a loss over a time grid that contains τ lost those terms (d/dτ 0.94
    for 2.09 by central differences)."""
    A = np.array([[0.0, 1.0], [-2.0, -0.3]])
    plant = obsjax.LTI(A, np.zeros((2, 1)), [[1.0, 0.0]])
    d_t, d_tau = jax.jacrev(lambda t, tau: an.transition_matrix(plant, t, tau), argnums=(0, 1))(1.0, 1.0)
    np.testing.assert_allclose(d_t, A, atol=1e-9)
    np.testing.assert_allclose(d_tau, -A, atol=1e-9)
    assert np.array_equal(np.asarray(an.transition_matrix(plant, 1.0, 1.0)), np.eye(2))


@pytest.mark.extended
def test_a_loss_over_a_grid_containing_tau_has_the_right_gradient():
    A = np.array([[0.0, 1.0], [-2.0, -0.3]])
    plant = obsjax.LTI(A, np.zeros((2, 1)), [[1.0, 0.0]])
    x0 = np.array([1.0, -0.5])
    grid = np.array([0.0, 1.5])

    def loss_np(tau):  # independent: expm
        return sum(np.sum((scipy.linalg.expm(A * (t - tau)) @ x0) ** 2) for t in grid)

    loss = jax.jit(lambda tau: sum(jnp.sum((an.transition_matrix(plant, t, tau) @ x0) ** 2) for t in grid))
    h = 1e-6
    grad = jax.jit(jax.grad(loss))
    for tau in (0.0, 0.1):  # τ = 0 is a grid time
        fd = (loss_np(tau + h) - loss_np(tau - h)) / (2 * h)
        np.testing.assert_allclose(grad(tau), fd, rtol=1e-6)


class _FamilyA(__import__("equinox").Module):
    k: jax.Array

    def __call__(self, t):
        return jnp.array([[0.0, 1.0], [-self.k, -0.1 * jnp.cos(t)]])


def _family_member(k):
    return obsjax.LTV(_FamilyA(jnp.asarray(k)), lambda t: jnp.array([[1.0, 0.0]]))


def test_analysis_over_a_vmapped_plant_family():
    """``jax.vmap`` over a family of LTV plants (the LTV docstring's promise) crashed in the finiteness
    probe of A(t) (a NumPy conversion of a batched value); a Python-float period under ``jit`` was called
    'a tracer'."""
    make = _family_member
    ks = [1.0, 2.0]
    Phis = jax.vmap(lambda k: an.transition_matrix(make(k), 1.0, 0.0))(jnp.asarray(ks))
    for k, Phi in zip(ks, Phis):
        A = lambda t: np.array([[0.0, 1.0], [-k, -0.1 * np.cos(t)]])
        sol = scipy.integrate.solve_ivp(lambda t, y: (A(t) @ y.reshape(2, 2)).ravel(), (0.0, 1.0),
                                        np.eye(2).ravel(), rtol=1e-12, atol=1e-14)  # fmt: skip
        np.testing.assert_allclose(Phi, sol.y[:, -1].reshape(2, 2), atol=1e-9)


@pytest.mark.extended
def test_uniform_observability_constants_over_a_vmapped_plant_family():
    make = _family_member
    W = jax.jit(lambda k: an.regressor_gramian(make(k), 1, 1.0))(2.0)  # a Python-float T under jit
    np.testing.assert_allclose(W, an.regressor_gramian(make(2.0), 1, 1.0), rtol=1e-10)
    ks = [1.0, 2.0]
    uo = jax.vmap(lambda k: an.uniform_observability_constants(_family_member(k), 1.0, 2.0))(jnp.asarray(ks))
    for i, k in enumerate(ks):
        one = an.uniform_observability_constants(_family_member(k), 1.0, 2.0)
        for name in ("alpha1", "alpha2", "m1", "m2", "mu"):
            np.testing.assert_allclose(getattr(uo, name)[i], getattr(one, name), rtol=1e-9)


def test_decay_rate_refuses_bad_times_and_complex_errors_and_differentiates_in_the_times():
    ts = jnp.linspace(0.0, 5.0, 11)
    err = jnp.exp(-1.3 * ts)
    with pytest.raises(ValueError, match="`ts` must hold finite times"):
        an.decay_rate((ts.at[3].set(jnp.nan), err))
    with pytest.raises(ValueError, match="`error` must be real"):  # was the real part's rate: 1.3, not 0.246
        an.decay_rate((ts, err + 1j * jnp.exp(-0.2 * ts)))
    with pytest.raises(ValueError, match="at least 2 samples"):
        an.decay_rate((jnp.zeros(0), jnp.zeros(0)))
    assert np.isnan(float(jax.jit(an.decay_rate)((ts.at[3].set(jnp.inf), err))))
    rate = lambda c: an.decay_rate((c * ts, err))  # λ(c) = 1.3 / c
    np.testing.assert_allclose(jax.grad(rate)(1.0), -1.3, rtol=1e-12)  # eagerly (it crashed)
    np.testing.assert_allclose(jax.jit(jax.grad(rate))(1.0), -1.3, rtol=1e-12)
