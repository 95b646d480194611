"""Trajectory linearization control (Huang & Zhu, Section II.A, (15)-(17), (24)-(28), Remark 2): the
PD-eigenstructure state feedback, dynamic inversion for the nominal trajectory, the output-feedback loop
with the TLO, and peaking with and without control saturation, on plants of our own.

Independent references: the first controller-canonical coordinate z_1 = qᵀx with q the last row of
[b, 𝓛̃b, 𝓛̃²b]⁻¹ built here from the definition 𝓛̃b = −ḃ + Ab; the closed loop integrated by diffrax in
the test; least-squares fits on the modes exp(ρ̄_k ∫ω dt) with ∫ω in closed form; the plant equations
for the nominal trajectory; a state-feedback simulation written here for the recovery check; central
finite differences for gradients.
"""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import obsjax
from obsjax.design import NominalTrajectory, pd_coefficients, pd_controller_gain


def omega_tv(t):
    return 2.0 + jnp.sin(t)


def omega_int(t):  # ∫_0^t ω
    return 2.0 * t + 1.0 - jnp.cos(t)


# ---- a single-input LTV plant, n = 3, with time-varying A and B ---------------------------------------
def A3(t):
    return jnp.array(
        [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0 - 0.3 * jnp.sin(t), -2.0, -1.0 + 0.2 * jnp.cos(t)]]
    )


def B3(t):
    return jnp.array([[0.0], [0.2 * jnp.sin(t)], [1.0]])


RHO3 = jnp.array([-0.5, -1.0, -1.5])


# ---- a two-input LTV plant, n = 4 ---------------------------------------------------------------------
def A4(t):
    return jnp.array(
        [
            [0.0, 1.0, 0.0, 0.0],
            [-2.0 - 0.5 * jnp.sin(t), -0.3, 0.4, 0.0],
            [0.0, 0.0, 0.0, 1.0],
            [0.3, 0.0, -1.0 - 0.3 * jnp.cos(t), -0.2],
        ]
    )


def B4(t):
    return jnp.array(
        [[0.0, 0.0], [1.0 + 0.2 * jnp.sin(t), 0.3], [0.0, 0.0], [0.1 * jnp.cos(t), 1.0]]
    )


RHO4 = jnp.array([-1.0, -2.0, -1.5, -3.0])


def q_independent(t):
    """Last row of the controllability matrix P = [b, 𝓛̃b, 𝓛̃²b]⁻¹, 𝓛̃b = −ḃ + A b (from the definition)."""
    b0 = lambda s: B3(s)[:, 0]
    b1 = lambda s: -jax.jacfwd(b0)(s) + A3(s) @ b0(s)
    b2 = lambda s: -jax.jacfwd(b1)(s) + A3(s) @ b1(s)
    P = jnp.stack([b0(t), b1(t), b2(t)], axis=1)
    return jnp.linalg.inv(P)[-1]


@pytest.mark.extended
def test_closed_loop_canonical_form_is_the_assigned_companion_mimo():
    """(A + BK) in x = M z_c: block-diagonal companions with last rows −α(t) of the synthesis formula."""
    assert obsjax.design.ltv_controllability_indices(A4, B4, [0.0, 1.0, 2.0]) == (2, 2)

    @jax.jit
    def closed(s):
        K = pd_controller_gain(A4, B4, RHO4, omega_tv, s, indices=(2, 2)).K
        M, Md = jax.jvp(
            lambda r: pd_controller_gain(A4, B4, RHO4, omega_tv, r, indices=(2, 2)).M,
            (s,),
            (jnp.ones_like(s),),
        )
        Mi = jnp.linalg.inv(M)
        return Mi @ (A4(s) + B4(s) @ K) @ M - Mi @ Md

    for t in (0.4, 2.2):
        Acl = np.asarray(closed(jnp.asarray(t)))
        expected = np.zeros((4, 4))
        expected[0, 1] = expected[2, 3] = 1.0
        expected[1, :2] = -np.asarray(pd_coefficients(RHO4[:2], omega_tv, t))
        expected[3, 2:] = -np.asarray(pd_coefficients(RHO4[2:], omega_tv, t))
        np.testing.assert_allclose(Acl, expected, atol=1e-9 * np.abs(expected).max())


def test_constant_bandwidth_gives_frozen_lti_canonical_loop():
    """With constant ω the canonical closed loop is LTI with eigenvalues ρ̄ ω, although A + BK itself has
    time-varying frozen eigenvalues."""

    @jax.jit
    def closed(s):
        K = pd_controller_gain(A3, B3, RHO3, 1.5, s, indices=(3,)).K
        M, Md = jax.jvp(
            lambda r: pd_controller_gain(A3, B3, RHO3, 1.5, r, indices=(3,)).M,
            (s,),
            (jnp.ones_like(s),),
        )
        Mi = jnp.linalg.inv(M)
        return Mi @ (A3(s) + B3(s) @ K) @ M - Mi @ Md, K

    ev = []
    for t in (0.3, 1.9):
        Acl, K = (np.asarray(v) for v in closed(jnp.asarray(t)))
        np.testing.assert_allclose(
            np.sort(np.linalg.eigvals(Acl).real), np.sort(1.5 * np.asarray(RHO3)), rtol=1e-9
        )
        ev.append(np.sort(np.linalg.eigvals(np.asarray(A3(t) + B3(t) @ K)).real))
    assert np.abs(ev[0] - ev[1]).max() > 1e-3  # frozen eigenvalues move: PD ≠ frozen


@functools.cache
def _siso_loop():
    """x̃˙ = (A + BK) x̃ for the n = 3 plant with ω(t) = 2 + sin t, integrated by diffrax."""
    ts = jnp.linspace(0.0, 3.0, 31)

    @jax.jit
    def run(x0):
        def rhs(t, x, args):
            K = pd_controller_gain(A3, B3, RHO3, omega_tv, t, indices=(3,)).K
            return (A3(t) + B3(t) @ K) @ x

        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(rhs),
            diffrax.Tsit5(),
            0.0,
            3.0,
            None,
            x0,
            saveat=diffrax.SaveAt(ts=ts),
            stepsize_controller=diffrax.PIDController(rtol=1e-11, atol=1e-13),
        )
        return sol.ys

    return ts, run


@pytest.mark.extended
def test_tracking_error_modes_follow_exp_integral_rho():
    """The assigned PD-spectrum, checked on the solution: z_1 = qᵀ x̃ (q from the definition) is a
    combination of exp(ρ̄_k ∫ω dt); a 20 % wrong spectrum does not fit."""
    ts, run = _siso_loop()
    xs = run(jnp.array([1.0, -0.5, 0.8]))
    qs = jax.vmap(q_independent)(ts)
    z1 = np.asarray(jnp.einsum("ti,ti->t", qs, xs))
    W = np.asarray(omega_int(ts))
    basis = np.exp(np.outer(W, np.asarray(RHO3)))
    coef, *_ = np.linalg.lstsq(basis, z1, rcond=None)
    assert np.max(np.abs(basis @ coef - z1)) < 1e-8 * np.max(np.abs(z1))
    wrong = np.exp(np.outer(W, 1.2 * np.asarray(RHO3)))
    c2, *_ = np.linalg.lstsq(wrong, z1, rcond=None)
    assert np.max(np.abs(wrong @ c2 - z1)) > 1e-3 * np.max(np.abs(z1))


def test_gain_gradient_matches_finite_differences():
    """K(t) is differentiable in ρ̄ and in the bandwidth's leaves (RampBandwidth ω0, ω1, τ)."""

    @jax.jit
    def k(rho, w):
        om = obsjax.design.RampBandwidth(w[0], w[1], w[2])
        return pd_controller_gain(A3, B3, rho, om, 0.8, indices=(3,)).K[0]

    w0 = jnp.array([0.7, 2.0, 1.3])
    Jr, Jw = jax.jacfwd(k, argnums=(0, 1))(RHO3, w0)
    h = 1e-6
    for i in range(3):
        e = jnp.zeros(3).at[i].set(h)
        np.testing.assert_allclose(
            Jr[:, i], (k(RHO3 + e, w0) - k(RHO3 - e, w0)) / (2 * h), rtol=1e-6, atol=1e-8
        )
        np.testing.assert_allclose(
            Jw[:, i], (k(RHO3, w0 + e) - k(RHO3, w0 - e)) / (2 * h), rtol=1e-6, atol=1e-8
        )
    assert np.abs(np.asarray(Jw)).max() > 1e-2


def test_uncontrollable_pair_is_refused():
    A = lambda t: jnp.array([[0.0, 1.0], [0.0, 0.0]])
    B = lambda t: jnp.array([[1.0], [0.0]])
    with pytest.raises(ValueError, match="not controllable"):
        pd_controller_gain(A, B, [-1.0, -2.0], 1.0, 0.0)
    # strongly controllable fails where B(t) vanishes
    Bt = lambda t: jnp.array([[0.0], [t - 1.0]])
    with pytest.raises(ValueError, match=r"not strongly controllable at t = 1\b"):
        pd_controller_gain(A, Bt, [-1.0, -2.0], 1.0, 1.0, indices=(2,))


# ---- dynamic inversion ---------------------------------------------------------------------------------
def arm(t, x, u):
    """A pendulum with a time-varying input gain: input-affine, relative degree 2 from y = x1."""
    return jnp.array([x[1], -jnp.sin(x[0]) - 0.4 * x[1] + (1.5 + 0.5 * jnp.cos(x[0])) * u[0]])


ARM = obsjax.Nonlinear(arm, lambda t, x, u: x[:1], 2, 1, 1)


def y_arm(t):
    return jnp.array([0.8 * jnp.sin(t)])


@pytest.mark.extended
def test_dynamic_inversion_reproduces_the_plant_and_the_output():
    nom = obsjax.dynamic_inversion(ARM, y_arm)
    assert nom.degrees == (2,)
    ts = jnp.array([0.0, 0.9, 2.7])
    xb, ub = jax.vmap(nom)(ts)
    xd = jax.vmap(jax.jacfwd(nom.state))(ts)
    np.testing.assert_allclose(xd, jax.vmap(arm)(ts, xb, ub), atol=1e-12)
    np.testing.assert_allclose(xb, 0.8 * np.stack([np.sin(ts), np.cos(ts)], 1), atol=1e-12)
    # MIMO, relative degrees (1, 2), a state-dependent input matrix and a Newton solve
    f = lambda t, x, u: jnp.array(
        [x[1] + 0.3 * jnp.sin(x[2]) + u[0], -x[0] + x[2], u[1] + 0.2 * x[0] ** 2]
    )
    h = lambda t, x, u: jnp.array([x[0] + 0.1 * x[1] ** 2, x[1]])
    mdl = obsjax.Nonlinear(f, h, 3, 2, 2)
    yr = lambda t: jnp.array([0.5 * jnp.cos(t), 0.4 * jnp.sin(1.3 * t)])
    nom2 = obsjax.dynamic_inversion(mdl, yr)
    assert nom2.degrees == (1, 2)

    @jax.jit
    def check(t):
        xb, ub = nom2(t)
        x1 = jax.jacfwd(nom2.state)(t)
        # second derivative of the state (what the TLO and TLC differentiate) against the plant's f
        x2 = jax.jacfwd(jax.jacfwd(nom2.state))(t)
        fd = (f(t + 1e-5, *nom2(t + 1e-5)) - f(t - 1e-5, *nom2(t - 1e-5))) / 2e-5
        return h(t, xb, ub) - yr(t), x1 - f(t, xb, ub), x2 - fd

    for t in (0.3, 1.7):
        r_out, r_f, r_2 = check(jnp.asarray(t))
        np.testing.assert_allclose(r_out, 0.0, atol=1e-10)
        np.testing.assert_allclose(r_f, 0.0, atol=1e-9)
        np.testing.assert_allclose(r_2, 0.0, atol=1e-6)


@pytest.mark.extended
def test_dynamic_inversion_refusals():
    nonaffine = obsjax.Nonlinear(
        lambda t, x, u: jnp.array([x[1], u[0] ** 3]), lambda t, x, u: x[:1], 2, 1, 1
    )
    with pytest.raises(ValueError, match="input-affine"):
        obsjax.dynamic_inversion(nonaffine, y_arm)
    internal = obsjax.Nonlinear(
        lambda t, x, u: jnp.array([x[1] + u[0], -x[0]]), lambda t, x, u: x[:1], 2, 1, 1
    )
    with pytest.raises(ValueError, match="internal state.*from_state"):
        obsjax.dynamic_inversion(internal, y_arm)
    with pytest.raises(ValueError, match="as many inputs as outputs"):
        obsjax.dynamic_inversion(
            obsjax.Nonlinear(arm, lambda t, x, u: x, 2, 2, 1), lambda t: jnp.zeros(2)
        )
    # a reference output that is not finite at t_check (or whose derivative is not): named, where before
    # Newton's method failed to converge with no word of the cause
    with pytest.raises(ValueError, match="`y_ref` or one of its first 2 time derivatives is not finite"):
        obsjax.dynamic_inversion(ARM, lambda t: jnp.array([jnp.nan * t]))
    with pytest.raises(ValueError, match="not finite at t_check = 0.0"):
        obsjax.dynamic_inversion(ARM, lambda t: jnp.array([jnp.sqrt(t)]))  # η̄' = ∞ at 0
    late = obsjax.dynamic_inversion(ARM, lambda t: jnp.array([jnp.where(t < 1.0, jnp.sin(t), jnp.nan)]))
    with pytest.raises(Exception, match="nominal output η̄\\(t\\) or one of its derivatives"):
        jax.block_until_ready(late.state(2.0))
    # a nominal state that no input can produce (ẋ1 ≠ x2)
    with pytest.raises(ValueError, match="not a trajectory of the plant"):
        NominalTrajectory.from_state(
            ARM, lambda t: jnp.array([jnp.sin(t), 0.0 * t]), check_ts=[0.5]
        )
    ok = NominalTrajectory.from_state(
        ARM, lambda t: jnp.array([jnp.sin(t), jnp.cos(t)]), check_ts=[0.5, 1.5]
    )
    xb, ub = ok(0.5)
    np.testing.assert_allclose(
        jnp.array([jnp.cos(0.5), -jnp.sin(0.5)]), arm(0.5, xb, ub), atol=1e-12
    )


# ---- the output-feedback loop with the TLO, peaking and saturation (Remark 2) ---------------------------
TS_PK = jnp.concatenate([jnp.linspace(0.0, 0.5, 51), jnp.linspace(0.55, 6.0, 110)])
EPS_PK = (0.2, 0.1, 0.05, 0.02)


@functools.cache
def _peaking_setup():
    # the nominal state in closed form (dynamic inversion gives the same, tested above; the closed form
    # keeps the compiled loop small)
    nom = NominalTrajectory.from_state(ARM, lambda t: 0.8 * jnp.array([jnp.sin(t), jnp.cos(t)]))
    x0 = nom.state(0.0) + jnp.array([0.3, -0.5])
    tlc = obsjax.TrajectoryLinearizationController(ARM, nom, [-1.0, -2.0], 1.5)
    tlo = obsjax.TrajectoryLinearization(ARM, [-1.0, -2.0], 2.0, 1.0, nominal=nom)

    @jax.jit
    def state_feedback():
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(lambda t, x, a: arm(t, x, tlc(t, x))),
            diffrax.Tsit5(),
            0.0,
            6.0,
            None,
            x0,
            saveat=diffrax.SaveAt(ts=TS_PK),
            stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-10),
        )
        return sol.ys

    @eqx.filter_jit
    def output_feedback(eps, u_max):
        o = eqx.tree_at(lambda o: o.eps, tlo, eps)
        c = eqx.tree_at(
            lambda c: (c.u_max, c.u_min), tlc, (jnp.full(1, u_max), jnp.full(1, -u_max))
        )
        tr = obsjax.simulate(
            ARM,
            o,
            x0,
            nom.state(0.0),
            TS_PK,
            controller=c,
            solver=diffrax.Tsit5(),
            rtol=1e-7,
            atol=1e-9,
            max_steps=100_000,
        )
        return tr, jax.vmap(c)(TS_PK, tr.xhat)

    return nom, tlc, state_feedback, output_feedback


@pytest.mark.extended
def test_state_feedback_tracks_the_nominal():
    nom, _tlc, state_feedback, _ = _peaking_setup()
    xs = state_feedback()
    xb = jax.vmap(nom.state)(TS_PK)
    e = np.linalg.norm(np.asarray(xs - xb), axis=1)
    assert e[0] > 0.5 and e[-1] < 1e-3 * e[0]
    # the linearised error decays with the PD-spectrum ρ̄ ω = (−1.5, −3): e(t) ≈ c e^{−1.5 t} late
    late = np.asarray(TS_PK) > 3.0
    rate = np.polyfit(np.asarray(TS_PK)[late], np.log(e[late]), 1)[0]
    assert rate == pytest.approx(-1.5, abs=0.1)


@pytest.mark.extended
def test_peaking_with_and_without_saturation():
    """Without saturation the control peaks like 1/ε and the plant is kicked away from the state-feedback
    trajectory however small ε is; with |u| ≤ 3 (above the state-feedback control, max ≈ 0.64) the
    output-feedback loop recovers the state-feedback trajectory as ε → 0 (the Theorem's (iii))."""
    _, _, state_feedback, output_feedback = _peaking_setup()
    xs = state_feedback()
    peak_u, dev_free, dev_sat = [], [], []
    for eps in EPS_PK:
        tr, u = output_feedback(jnp.asarray(eps), jnp.inf)
        peak_u.append(float(jnp.abs(u).max()))
        dev_free.append(float(jnp.linalg.norm(tr.x - xs, axis=1).max()))
        tr_s, u_s = output_feedback(jnp.asarray(eps), 3.0)
        assert float(jnp.abs(u_s).max()) <= 3.0 + 1e-12
        dev_sat.append(float(jnp.linalg.norm(tr_s.x - xs, axis=1).max()))
    peak_u, dev_free, dev_sat = map(np.array, (peak_u, dev_free, dev_sat))
    assert np.all(np.diff(peak_u) > 0)
    assert peak_u[-1] * EPS_PK[-1] > 0.3 * peak_u[0] * EPS_PK[0]  # ∝ 1/ε
    assert peak_u[-1] > 20.0
    assert dev_free[-1] > 0.9 * dev_free[0]  # no recovery without saturation
    assert np.all(np.diff(dev_sat) < 1e-9)  # recovery with saturation
    assert dev_sat[-1] < 0.5 * dev_sat[0]
    assert dev_sat[-1] < 0.4 * dev_free[-1]


def test_controller_bad_inputs():
    nom = obsjax.dynamic_inversion(ARM, y_arm)
    with pytest.raises(ValueError, match="`rho_bar` must be < 0"):
        obsjax.TrajectoryLinearizationController(ARM, nom, [1.0, -2.0], 1.0)
    with pytest.raises(ValueError, match="`u_min` must be < `u_max`"):
        obsjax.TrajectoryLinearizationController(ARM, nom, [-1.0, -2.0], 1.0, u_max=1.0, u_min=2.0)
    with pytest.raises(ValueError, match="distinct"):
        obsjax.TrajectoryLinearizationController(ARM, nom, [-1.0, -1.0], 1.0)
    with pytest.raises(ValueError, match="`nominal` must be a callable"):
        obsjax.TrajectoryLinearizationController(ARM, (1.0, 2.0), [-1.0, -2.0], 1.0)
