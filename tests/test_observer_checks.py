"""Observers' own checks: every gain finite at construction, value checks that survive ``jit``.

One test per bad-input class: NaN/inf gains and matrices (a ``ValueError`` naming the gain, what was
expected and what was found, at construction and from ``check()`` after an ``eqx.tree_at`` update,
as in :func:`obsjax.tune`), and traced values that fail (``eqx.error_if``: the message names the
gain).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg as sl
import pytest

import obsjax
from obsjax.design import lovass_nagy_T

LTI2 = obsjax.LTI([[-2.0, 1.0], [0.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]])
CY = obsjax.chen_yen_example()
NAN, INF = float("nan"), float("inf")
# a check that fires in a compiled kernel: JAX raises it as a RuntimeError, or as a ValueError when
# the kernel came from its cache; the message (matched below) names the gain either way
RuntimeCheck = (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError, ValueError)


def _under_jit(fn, *args):
    """Run fn under jit and block (a failing eqx.error_if raises here)."""
    return jax.block_until_ready(jax.jit(fn)(*args))


# ---- LeastSquaresReset
# -------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["gamma", "p0", "T"])
@pytest.mark.parametrize("bad", [INF, NAN])
def test_least_squares_nonfinite_gain(name, bad):
    kw = dict(gamma=20.0, p0=0.1, T=0.25)
    kw[name] = bad
    with pytest.raises(ValueError, match=rf"`{name}` must be > 0 and finite.*got \[?{bad}"):
        obsjax.LeastSquaresReset(CY, **kw)


def test_least_squares_tree_at_update_is_rechecked():
    obs = obsjax.LeastSquaresReset(CY, 20.0, 0.1, 0.25)
    with pytest.raises(ValueError, match="`gamma` must be > 0 and finite"):
        eqx.tree_at(lambda o: o.gamma, obs, jnp.asarray(INF)).check()
    with pytest.raises(RuntimeCheck, match=r"`T` must be > 0 and finite \(the reset period\)"):
        _under_jit(lambda T: eqx.tree_at(lambda o: o.T, obs, T).check().T, jnp.asarray(NAN))


# ---- Kalman-Bucy and the extended Kalman filter
# ------------------------------------------------------------


@pytest.mark.parametrize("name", ["Qw", "Rv", "P0"])
def test_kalman_bucy_nonfinite_matrix(name):
    kw = dict(Qw=0.1 * np.eye(2), Rv=0.01 * np.eye(1), P0=np.eye(2))
    kw[name] = kw[name].copy()
    kw[name][0, 0] = NAN
    with pytest.raises(
        ValueError, match=rf"`{name}` must be finite \(no NaN or inf\), got \[\[nan"
    ):
        obsjax.KalmanBucy(CY, **kw)


@pytest.mark.parametrize(
    "name,value,kind",
    [
        ("Qw", -np.eye(2), "positive semidefinite"),
        ("Rv", -np.eye(1), "positive definite"),
        ("P0", np.array([[1.0, 2.0], [0.0, 1.0]]), "positive definite"),
        ("Rv", np.full((1, 1), INF), "positive definite"),
    ],
)
def test_kalman_bucy_traced_checks_survive_jit(name, value, kind):
    kb = obsjax.KalmanBucy(CY, Qw=0.1 * jnp.eye(2), Rv=0.01 * jnp.eye(1), P0=jnp.eye(2))
    where = lambda o: getattr(o, name)  # noqa: E731
    with pytest.raises(ValueError, match=f"`{name}`"):  # eagerly, after a tree_at update
        eqx.tree_at(where, kb, jnp.asarray(value)).check()
    with pytest.raises(RuntimeCheck, match=f"`{name}` .*must be a finite symmetric {kind} matrix"):
        _under_jit(lambda v: where(eqx.tree_at(where, kb, v).prepare()), jnp.asarray(value))
    _under_jit(
        lambda v: where(eqx.tree_at(where, kb, v).prepare()), where(kb)
    )  # a valid value passes


EKF_MODEL = obsjax.Nonlinear(
    lambda t, x, u: jnp.array([x[1], -x[0] - 0.3 * x[1]]), lambda t, x, u: x[:1], 2, 1
)


@pytest.mark.parametrize("name", ["Q", "R", "P0"])
@pytest.mark.parametrize("bad", [INF, NAN])
def test_ekf_nonfinite_covariance(name, bad):
    kw = dict(Q=0.1, R=0.01, P0=1.0)
    kw[name] = bad
    with pytest.raises(ValueError, match=rf"`{name}` must be finite"):
        obsjax.ExtendedKalman(EKF_MODEL, **kw)


def test_ekf_traced_checks_survive_jit_inside_simulate():
    """R not positive definite, Q or P0 indefinite: under jit the solve stops, naming the gain."""
    ekf = obsjax.ExtendedKalman(EKF_MODEL, Q=0.1, R=0.01, P0=1.0)
    ts = jnp.linspace(0.0, 0.2, 3)

    def run(R, Q, P0):
        obs = eqx.tree_at(lambda o: (o.R, o.Q, o.P0), ekf, (R, Q, P0))
        return obsjax.simulate(EKF_MODEL, obs, jnp.ones(2), jnp.zeros(2), ts).xhat

    good = (ekf.R, ekf.Q, ekf.P0)
    assert np.all(np.isfinite(_under_jit(run, *good)))
    with pytest.raises(
        RuntimeCheck, match=r"`R` \(ExtendedKalman's measurement-noise intensity\) must be"
    ):
        _under_jit(run, -ekf.R, ekf.Q, ekf.P0)
    with pytest.raises(RuntimeCheck, match=r"`Q` .*positive semidefinite"):
        _under_jit(run, ekf.R, -ekf.Q, ekf.P0)
    with pytest.raises(RuntimeCheck, match=r"`P0` .*symmetric positive semidefinite"):
        _under_jit(run, ekf.R, ekf.Q, jnp.array([[1.0, 1.0], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="`R` must be positive definite"):  # eagerly, from check()
        eqx.tree_at(lambda o: o.R, ekf, -ekf.R).check()


# ---- trajectory linearization observer
# ---------------------------------------------------------------------

TLO_MODEL = obsjax.Nonlinear(lambda t, x, u: jnp.array([x[1], -x[0]]), lambda t, x, u: x[:1], 2, 1)


@pytest.mark.parametrize(
    "kw,match",
    [
        (dict(eps=INF), r"`eps` must be > 0 and finite \(the high-gain factor"),
        (dict(eps=NAN), r"`eps` must be > 0 and finite"),
        (dict(eps=-0.1), r"`eps` must be > 0 \(the high-gain factor, ω_H = ω/ε\), got -0.1"),
        (dict(rho_bar=[-1.0, -INF]), r"`rho_bar` must be finite"),
        (dict(omega=INF), r"`omega` must be finite"),
    ],
)
def test_tlo_bad_gains(kw, match):
    args = dict(rho_bar=[-1.0, -2.0], omega=2.0, eps=0.2)
    args.update(kw)
    with pytest.raises(ValueError, match=match):
        obsjax.TrajectoryLinearization(TLO_MODEL, **args)


def test_tlo_traced_eps_and_rho_bar_checks_survive_jit():
    tlo = obsjax.TrajectoryLinearization(TLO_MODEL, [-1.0, -2.0], 2.0, 0.2)
    for bad in (0.0, -0.2, NAN, INF):
        with pytest.raises(
            RuntimeCheck, match=r"`eps` must be > 0 and finite \(the high-gain factor"
        ):
            _under_jit(
                lambda e: eqx.tree_at(lambda o: o.eps, tlo, e).prepare().eps, jnp.asarray(bad)
            )
    with pytest.raises(RuntimeCheck, match="`rho_bar` .*must be < 0 and finite"):
        _under_jit(
            lambda r: eqx.tree_at(lambda o: o.rho_bar, tlo, r).prepare().rho_bar,
            jnp.array([-1.0, 0.5]),
        )
    assert (
        float(
            _under_jit(
                lambda e: eqx.tree_at(lambda o: o.eps, tlo, e).prepare().eps, jnp.asarray(0.3)
            )
        )
        == 0.3
    )
    with pytest.raises(ValueError, match="`eps` must be > 0 and finite"):
        eqx.tree_at(lambda o: o.eps, tlo, jnp.asarray(INF)).check()


# ---- generalized-inverse observers
# -------------------------------------------------------------------------

F_GI = jnp.array([[-3.0, 1.0], [0.0, -4.0]])
T_GI = lovass_nagy_T(LTI2.A, LTI2.C, F_GI, lambda t: jnp.array([0.3, 1.0]))


def test_generalized_inverse_nonfinite_F_and_C1():
    with pytest.raises(ValueError, match=r"`F` must be finite \(no NaN or inf\), got \[\[nan"):
        obsjax.GeneralizedInverse(LTI2, F_GI.at[0, 0].set(NAN), T_GI)
    with pytest.raises(ValueError, match=r"`C1` must be finite"):
        obsjax.GeneralizedInverse(LTI2, F_GI, T_GI, C1=[[INF], [0.0]])


def test_generalized_inverse_solvability_is_checked_under_jit():
    """The condition (Ṫ + TA − FT)(I − C^{1}C) = 0 holds for F_GI and its T; another F breaks it.
    Eagerly a ValueError (construction, check()), under jit an eqx.error_if (construction and
    prepare())."""
    obs = obsjax.GeneralizedInverse(LTI2, F_GI, T_GI, horizon=(0.0, 1.0), num_checks=5)
    F_bad = F_GI.at[0, 1].set(3.0)
    with pytest.raises(ValueError, match="solvability condition fails"):
        obsjax.GeneralizedInverse(LTI2, F_bad, T_GI)
    with pytest.raises(ValueError, match="solvability condition fails"):
        eqx.tree_at(lambda o: o.F, obs, F_bad).check()
    with pytest.raises(
        RuntimeCheck, match="GeneralizedInverse: the Lovass-Nagy solvability condition"
    ):
        _under_jit(lambda F: eqx.tree_at(lambda o: o.F, obs, F).prepare().F, F_bad)
    with pytest.raises(
        RuntimeCheck, match="GeneralizedInverse: the Lovass-Nagy solvability condition"
    ):
        _under_jit(lambda F: obsjax.GeneralizedInverse(LTI2, F, T_GI).F, F_bad)
    np.testing.assert_array_equal(
        _under_jit(lambda F: eqx.tree_at(lambda o: o.F, obs, F).prepare().F, F_GI), F_GI
    )


def test_generalized_inverse_singular_T_is_checked_under_jit():
    obs = obsjax.GeneralizedInverse(LTI2, F_GI, T_GI)

    def with_scaled_T(
        c,
    ):  # T scaled by a traced factor: singular for c = 0, the condition still holds
        return eqx.tree_at(lambda o: o.T, obs, lambda t: c * T_GI(t)).prepare().F

    _under_jit(with_scaled_T, jnp.asarray(2.0))
    with pytest.raises(RuntimeCheck, match=r"`T` must be invertible"):
        _under_jit(with_scaled_T, jnp.asarray(0.0))


# ---- adaptive observers
# ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kw,match",
    [
        (dict(filter_pole=INF), r"`filter_pole` must be > 0 and finite"),
        (dict(scheme="integral", q=NAN), r"`q` must be > 0 and finite"),
        (dict(a0=[NAN, 0.0]), r"`a0` must be finite"),
        (dict(G=INF), r"`G` must be finite"),
        (dict(poles=[-1.0, -INF]), r"`poles` must be finite"),
    ],
)
def test_kreisselmeier_bad_gains(kw, match):
    args = dict(n=2, poles=[-1.0, -2.0], G=1.0)
    args.update(kw)
    with pytest.raises(ValueError, match=match):
        obsjax.Kreisselmeier(**args)


def test_kreisselmeier_traced_checks():
    obs = obsjax.Kreisselmeier(2, [-1.0, -2.0], 1.0, scheme="integral", q=0.5)
    with pytest.raises(RuntimeCheck, match="`poles` must be finite, in the open left half-plane"):
        _under_jit(
            lambda p: eqx.tree_at(lambda o: o.poles, obs, p).prepare().poles, jnp.array([-1.0, 0.5])
        )
    with pytest.raises(RuntimeCheck, match="`G` must be finite"):
        _under_jit(lambda g: eqx.tree_at(lambda o: o.G, obs, g).prepare().G, jnp.asarray(INF))
    with pytest.raises(RuntimeCheck, match="`q` must be > 0 and finite"):
        _under_jit(lambda q: eqx.tree_at(lambda o: o.q, obs, q).prepare().q, jnp.asarray(NAN))
    with pytest.raises(ValueError, match="`poles` must lie in the open left half-plane"):
        eqx.tree_at(lambda o: o.poles, obs, jnp.array([-1.0, 0.5])).check()


def test_luders_narendra_bad_gains():
    with pytest.raises(ValueError, match=r"`lambdas` must be > 0 and finite"):
        obsjax.LudersNarendra(2, [1.0, INF], 1.0, 1.0)
    with pytest.raises(ValueError, match=r"`b0` must be finite"):
        obsjax.LudersNarendra(2, [1.0, 2.0], 1.0, 1.0, b0=[0.0, NAN])
    obs = obsjax.LudersNarendra(2, [1.0, 2.0], 1.0, 1.0)
    with pytest.raises(RuntimeCheck, match="`c` must be > 0 and finite"):
        _under_jit(lambda c: eqx.tree_at(lambda o: o.c, obs, c).prepare().c, jnp.array([1.0, INF]))


def test_kudva_narendra_bad_matrices():
    # a NaN in K used to reach numpy's eigvals (LinAlgError naming nothing)
    with pytest.raises(ValueError, match=r"`K` must be finite"):
        obsjax.KudvaNarendra(2, 1, K=[[NAN, 0.0], [0.0, -1.0]], Gamma1=1.0, Gamma2=1.0, Q=np.eye(2))
    with pytest.raises(ValueError, match=r"`A0` must be finite"):
        obsjax.KudvaNarendra(
            2, 1, K=-np.eye(2), Gamma1=1.0, Gamma2=1.0, Q=np.eye(2), A0=np.full((2, 2), INF)
        )
    obs = obsjax.KudvaNarendra(2, 1, K=-np.eye(2), Gamma1=1.0, Gamma2=1.0, Q=np.eye(2))
    with pytest.raises(RuntimeCheck, match="`Gamma1` must be finite"):
        _under_jit(
            lambda g: eqx.tree_at(lambda o: o.Gamma1, obs, g).prepare().Gamma1, jnp.asarray(INF)
        )


# ---- finite-window and min-max observers
# -------------------------------------------------------------------

MODEL29 = obsjax.LTI(A=[[0.0, 1.0], [0.0, 0.0]], B=[[0.0], [1.0]], C=[[2.0, 0.0]])


@pytest.mark.parametrize(
    "kw,match",
    [
        (dict(T=INF), r"`T` must be finite"),
        (dict(T=1.0, alpha=[1.0, NAN]), r"`alpha` must be finite"),
        (dict(T=1.0, beta=[INF, 1.0]), r"`beta` must be finite"),
    ],
)
def test_finite_window_nonfinite(kw, match):
    with pytest.raises(ValueError, match=match):
        obsjax.FiniteWindow(MODEL29, **kw)


def test_finite_window_traced_T_must_be_finite():
    obs = obsjax.FiniteWindow(MODEL29, 1.0)
    with pytest.raises(RuntimeCheck, match=r"`T` \(the window length\) must be > 0 and finite"):
        _under_jit(lambda T: eqx.tree_at(lambda o: o.T, obs, T).norm(), jnp.asarray(INF))


def test_minmax_luenberger_nonfinite_eps():
    A = np.diag([0.5, 0.2])
    for bad in (NAN, INF, -1.0):
        with pytest.raises(ValueError, match=r"`eps` must be >= 0 and finite"):
            obsjax.MinMaxLuenberger(A, None, np.eye(2), F=0.1 * np.eye(2), window=2, eps=bad)


@pytest.mark.parametrize("who", ["FunctionalObserver", "ReducedOrder"])
def test_observers_on_y_equals_cx_refuse_feedthrough(who):
    """A model with D ≠ 0: FunctionalObserver accepted it and estimated aᵀx with a bias eᵀ D u (−12.1 against
    −0.1 with D = 1, u = 2); ReducedOrder refused it already.  Both name `D` and what they found."""
    A = [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-6.0, -11.0, -6.0]]
    plant = obsjax.LTI(A, [[0.0], [0.0], [1.0]], [[1.0, 0.0, 0.0]], D=[[1.0]])
    with pytest.raises(ValueError, match=rf"{who} needs a model without feedthrough: `D` must be 0, got max \|D\| = 1"):
        if who == "FunctionalObserver":
            obsjax.FunctionalObserver(plant, np.array([0.0, 1.0, 0.0]), [-4.0, -5.0])
        else:
            obsjax.ReducedOrder(plant, poles=[-4.0, -5.0])
    # the same model without feedthrough is accepted
    obsjax.FunctionalObserver(obsjax.LTI(A, [[0.0], [0.0], [1.0]], [[1.0, 0.0, 0.0]]), np.array([0.0, 1.0, 0.0]), [-4.0, -5.0])


@pytest.mark.extended
def test_reduced_order_does_not_depend_on_the_units_of_the_sensors():
    """Two independent sensors in units 1e10 apart: the rank test of C was unscaled and refused them
    ("rank 1"), though Luenberger placed the same pair.  Now the estimate of x is the same in any units
    (the reduced error decays at the requested rate; x̂ does not depend on how the complement is scaled)."""
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -2.0, -3.0]])
    B = np.array([[0.0], [0.0], [1.0]])
    ts = np.linspace(0.0, 3.0, 7)
    x0, xh0 = jnp.array([1.0, -0.5, 0.3]), jnp.zeros(3)
    runs = []
    for k in (1.0, 1e-5):
        plant = obsjax.LTI(A, B, np.array([[k, 0.0, 0.0], [0.0, 1.0 / k, 0.0]]))
        obs = obsjax.ReducedOrder.from_poles(plant, [-4.0])
        runs.append(np.asarray(obsjax.simulate(plant, obs, x0, xh0, ts, rtol=1e-10, atol=1e-12).error))
    np.testing.assert_allclose(runs[1], runs[0], rtol=1e-9, atol=1e-12)
    # x̃ = x̂ − x lies along the unmeasured state and decays as e^{−4t}
    np.testing.assert_allclose(runs[0][:, :2], 0.0, atol=1e-7)
    np.testing.assert_allclose(runs[0][-1, 2] / runs[0][0, 2], np.exp(-12.0), rtol=1e-4)


def test_reduced_order_with_a_rank_deficient_a12_places_under_jit():
    """m = 3 outputs > n − m = 2 unmeasured states, rank A12 = 1: the poles are placed on the rank-1 rows
    of A12 decided at construction; under jit the traced path kept both rows of its QR factor and the
    gain was refused at run time ("does not place the poles") though the eager one places them exactly."""
    import equinox as eqx

    A = np.zeros((5, 5))
    A[0, 3], A[1, 3], A[3, 4], A[4, 3], A[3, 3], A[4, 4] = 1.0, 2.0, 0.5, -1.0, -1.0, 0.3
    plant = obsjax.LTI(A, np.ones((5, 1)), np.eye(5)[:3])
    obs = obsjax.ReducedOrder.from_poles(plant, [-2.0, -3.0])
    _, _, _, A12, _, A22, _, _ = (np.asarray(x) for x in obs._blocks())
    for G in (np.asarray(obs.gain), np.asarray(eqx.filter_jit(lambda o: o.gain)(obs))):
        np.testing.assert_allclose(np.sort(np.linalg.eigvals(A22 - G @ A12).real), [-3.0, -2.0], rtol=1e-10)


@pytest.mark.parametrize("c", [1.0, 1e4, 1e5])
def test_functional_observer_does_not_depend_on_the_time_unit(c):
    """A → cA, poles → c·poles (n = 4, one output, order 3): the conditions were solved with the companion
    matrix of the poles, entries up to c³, and the design was refused from c = 1e4 on ("cannot be
    observed").  Defining properties in every unit: eig F = the poles, TA − FT = GC and aᵀ = kᵀT + eᵀC."""
    rng = np.random.default_rng(13)
    A, B, C, a = (rng.standard_normal(s) for s in ((4, 4), (4, 1), (1, 4), (4,)))
    poles = c * np.array([-1.0, -2.0, -3.0])
    obs = obsjax.FunctionalObserver(obsjax.LTI(c * A, B, C), a, poles)
    F, T, G, k, e = (np.asarray(x) for x in (obs.F, obs.T, obs.G, obs.k, obs.e))
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(F).real), np.sort(poles), rtol=1e-9)
    lhs = T @ (c * A) - F @ T
    assert np.abs(lhs - G @ C).max() <= 1e-10 * max(np.abs(lhs).max(), np.abs(G @ C).max())
    np.testing.assert_allclose(k @ T + e @ C, a, rtol=1e-10, atol=1e-12 * np.abs(a).max())


def _functional_plant():
    rng = np.random.default_rng(3)
    n, m = 5, 2
    A, B, C, a = rng.standard_normal((n, n)), rng.standard_normal((n, 1)), rng.standard_normal((m, n)), rng.standard_normal(n)
    return obsjax.LTI(A=A, B=B, C=C), a


def test_functional_observer_is_differentiable_in_its_poles():
    """Built with traced poles (under jit, grad), FunctionalObserver raised TracerArrayConversionError, so
    its poles could not be tuned.  The traced design equals the eager one (n = 5, two outputs, order 2,
    a minimum-norm solution), keeps TA − FT = GC and aᵀ = kᵀT + eᵀC, and its derivative in the poles
    matches central differences; NaN poles and complex traced poles are refused.  (Through a simulation:
    the second tier's twin below.)"""
    plant, a = _functional_plant()
    A, C = np.asarray(plant.A), np.asarray(plant.C)
    poles = np.array([-2.0, -3.0])
    eager = obsjax.FunctionalObserver(plant, a, poles)
    design = jax.jit(lambda p: (lambda o: (o.F, o.T, o.G, o.e))(obsjax.FunctionalObserver(plant, a, p)))
    for x, y in zip((eager.F, eager.T, eager.G, eager.e), design(jnp.asarray(poles))):
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-12, atol=1e-13 * np.abs(x).max())
    F, T, G, e = (np.asarray(v) for v in design(jnp.array([-1.5, -4.0])))
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(F).real), [-4.0, -1.5], rtol=1e-12)
    assert np.abs(T @ A - F @ T - G @ C).max() < 1e-12 and np.abs(T[-1] + e @ C - a).max() < 1e-12

    def size(p):  # a smooth function of the design: T, G and e all move with the poles
        _, T, G, e = design(p)
        return jnp.sum(T**2) + jnp.sum(jnp.sin(G)) + jnp.sum(e**3)

    g = np.asarray(jax.grad(size)(jnp.asarray(poles)))
    h = 1e-5
    fd = [(size(jnp.asarray(poles + h * d)) - size(jnp.asarray(poles - h * d))) / (2 * h) for d in np.eye(2)]
    np.testing.assert_allclose(g, np.asarray(fd), rtol=1e-7)
    assert np.all(np.abs(g) > 1e-3)
    with pytest.raises(Exception, match="`poles` must be finite"):
        jax.block_until_ready(design(jnp.array([np.nan, -3.0])))
    with pytest.raises(ValueError, match="traced complex"):
        jax.jit(lambda p: obsjax.FunctionalObserver(plant, a, p).T)(jnp.array([-1 + 1j, -1 - 1j]))


def test_functional_observer_traced_equals_eager_and_moves_smoothly_with_the_poles():
    """Integer-valued plant (n = 5, two outputs, order 2: many observers satisfy the conditions, the
    minimum-norm one in scaled unknowns is chosen).  The equilibration depended on the poles and was
    computed with np.log2 eagerly and jnp.log2 when traced (log2(8) rounds differently): the traced
    observer was another one (T 3.4 relative off, kᵀT x0 5.5 for 14.9), and the chosen observer jumped
    as a pole moved (9.4 % in a simulated loss between −1.1037 and −1.1040).  The scaling now comes from
    A and C alone; poles all small against A (1e-5·‖A‖) were refused and are solved."""
    A = np.array([[-1.0, 6, 8, -4, -7], [2, 3, 5, 2, 4], [7, 7, 7, 6, 4], [7, -8, -8, 5, -1], [4, 0, 7, -7, 3]])
    C = np.array([[-8.0, -6, 6, -4, 8], [-3, 5, 8, -3, 8]])
    a = np.array([3.0, 8, -3, 0, 4])
    plant = obsjax.LTI(A=A, B=np.ones((5, 1)), C=C)
    design = jax.jit(lambda p: (lambda o: (o.F, o.T, o.G, o.e))(obsjax.FunctionalObserver(plant, a, p)))
    for poles in ([-1.0, -1.0], [-1.1035, -2.0], [0.0, 0.0], [-2e-4, -3e-4]):
        eager = obsjax.FunctionalObserver(plant, a, np.array(poles))
        F, T, G, e = (np.asarray(v) for v in design(jnp.asarray(poles)))
        for x, y in zip((eager.F, eager.T, eager.G, eager.e), (F, T, G, e)):
            np.testing.assert_allclose(y, np.asarray(x), rtol=1e-10, atol=1e-12 * np.abs(x).max())
        scale = max(np.abs(T @ A).max(), np.abs(G @ C).max())
        assert np.abs(T @ A - F @ T - G @ C).max() < 1e-12 * scale
        np.testing.assert_allclose(T[-1] + e @ C, a, atol=1e-12 * np.abs(a).max())
        np.testing.assert_allclose(np.sort(np.linalg.eigvals(F).real), np.sort(poles), atol=1e-9 * (1 + np.abs(poles).max()))
    # kᵀ T x0 (the initial functional error from x̂0 = 0) along p1: second differences of a smooth curve
    p1 = np.linspace(-1.1030, -1.1040, 11)
    v = np.array([float(design(jnp.array([q, -2.0]))[1][-1].sum()) for q in p1])
    assert np.abs(np.diff(v, 2)).max() < 1e-6 * np.abs(v).max()


def test_functional_observer_follows_a_change_of_state_units_and_refuses_singular_conditions():
    """x' = S x with S spread over 1e±3 (n = 6, one output, order 5: a unique observer, T' = T S⁻¹): with
    the time unit set by ‖A‖₂ in the user's units the conditions became numerically singular and a
    truncated least-squares solution passed the residual test (kᵀT x0 −0.82 for 48.99).  The design runs
    in balanced state units now.  Conditions that are numerically singular in any units (poles from
    −0.01 to −1000: kᵀT x0 −17.7 for 1.0e6) are refused, eagerly and under jit."""
    rng = np.random.default_rng(5)
    n = 6
    A, B, C, a = rng.standard_normal((n, n)), rng.standard_normal((n, 1)), rng.standard_normal((1, n)), rng.standard_normal(n)
    poles = -np.logspace(-1, 1, 5)
    ref = obsjax.FunctionalObserver(obsjax.LTI(A=A, B=B, C=C), a, poles)
    s = np.logspace(3, -3, n)
    scaled = obsjax.LTI(A=s[:, None] * A / s[None, :], B=s[:, None] * B, C=C / s[None, :])
    x0 = np.ones(n)

    def error(F, T, x0):  # kᵀ e^{Ft} T (x̂0 − x0) from x̂0 = 0: the functional error, whatever z's realisation
        return np.array([-(sl.expm(np.asarray(F) * t) @ np.asarray(T) @ x0)[-1] for t in (0.0, 0.5, 2.0)])

    want = error(ref.F, ref.T, x0)
    design = jax.jit(lambda p: (lambda o: (o.F, o.T))(obsjax.FunctionalObserver(scaled, a / s, p)))
    got = obsjax.FunctionalObserver(scaled, a / s, poles)
    for F, T in ((got.F, got.T), design(jnp.asarray(poles))):
        np.testing.assert_allclose(error(F, T, s * x0), want, rtol=1e-6)
    bad = -np.logspace(-2, 3, 5)
    plant = obsjax.LTI(A=A, B=B, C=C)
    with pytest.raises(ValueError, match="numerically singular"):
        obsjax.FunctionalObserver(plant, a, bad)
    with pytest.raises(Exception, match="numerically singular"):
        jax.block_until_ready(jax.jit(lambda p: obsjax.FunctionalObserver(plant, a, p).T)(jnp.asarray(bad)))


@pytest.mark.extended
def test_functional_observer_pole_derivative_of_an_ill_conditioned_design():
    """n = 6, one output, order 5, poles from −0.1 to −100 (a square system of condition about 1e11):
    the derivative through JAX's pseudo-inverse was 3.7e3 times the true one (its projector terms,
    zero in exact arithmetic, were amplified by cond²).  Against the same design in 40-digit arithmetic."""
    mp = pytest.importorskip("mpmath")
    mp.mp.dps = 40
    rng = np.random.default_rng(5)
    n, r = 6, 5
    A, B, C, a = rng.standard_normal((n, n)), rng.standard_normal((n, 1)), rng.standard_normal((1, n)), rng.standard_normal(n)
    plant = obsjax.LTI(A=A, B=B, C=C)
    p = -np.logspace(-1, 2, 5)
    w = np.random.default_rng(7).standard_normal(r * n)

    def f(q):
        return jnp.sum(w * obsjax.FunctionalObserver(plant, a, q).T.ravel())

    def f_mp(q):  # the conditions TA − FT = GC, e_rᵀT + eC = aᵀ with F = s·companion(q/s), solved exactly
        s = mp.sqrt(sum(mp.mpf(x) ** 2 for x in q) / r + mp.mpf(float(np.linalg.norm(A, 2))) ** 2)
        c = [mp.mpf(1)]
        for z in q:
            c = [c[0]] + [c[i] - (z / s) * c[i - 1] for i in range(1, len(c))] + [-(z / s) * c[-1]]
        F = mp.zeros(r, r)
        for i in range(1, r):
            F[i, i - 1] = s
        for i in range(r):
            F[i, r - 1] = -s * c[r - i]
        M, b = mp.zeros(r * n + n, r * n + r + 1), mp.zeros(r * n + n, 1)
        for i in range(r):
            for j in range(n):
                for k in range(n):
                    M[i * n + j, i * n + k] += A[k, j]
                for k in range(r):
                    M[i * n + j, k * n + j] -= F[i, k]
                M[i * n + j, r * n + i] -= C[0, j]
        for j in range(n):
            M[r * n + j, (r - 1) * n + j] += 1
            M[r * n + j, r * n + r] += C[0, j]
            b[r * n + j] = a[j]
        x = mp.lu_solve(M, b)
        return sum(w[i] * x[i] for i in range(r * n))

    h = mp.mpf("1e-20")
    ref = np.array([float((f_mp([mp.mpf(x) + h * d for x, d in zip(p, e)]) - f_mp([mp.mpf(x) - h * d for x, d in zip(p, e)])) / (2 * h)) for e in np.eye(r)])
    g = np.asarray(jax.grad(f)(jnp.asarray(p)))
    np.testing.assert_allclose(g, ref, rtol=1e-4, atol=1e-4 * np.abs(ref).max())
    np.testing.assert_allclose(np.asarray(jax.jacfwd(f)(jnp.asarray(p))), ref, atol=1e-4 * np.abs(ref).max())


@pytest.mark.extended
def test_functional_observer_poles_gradient_through_a_simulation():
    """The derivative in the poles of a simulated loss (Σ (ŝ − aᵀx)² on 81 save points, an input) against
    central differences."""
    plant, a = _functional_plant()
    poles = np.array([-2.0, -3.0])
    ts = jnp.linspace(0.0, 4.0, 81)
    u = obsjax.signals.multisine([1.0], [0.7])

    def loss(p):
        o = obsjax.FunctionalObserver(plant, a, p)
        return jnp.sum(obsjax.simulate(plant, o, jnp.ones(5), jnp.zeros(5), ts, u=u, rtol=1e-10, atol=1e-12).error ** 2)

    g = np.asarray(jax.grad(loss)(jnp.asarray(poles)))
    h = 1e-4
    fd = [(loss(jnp.asarray(poles + h * d)) - loss(jnp.asarray(poles - h * d))) / (2 * h) for d in np.eye(2)]
    np.testing.assert_allclose(g, np.asarray(fd), rtol=1e-6)
    assert np.all(np.abs(g) > 1e-3)


@pytest.mark.parametrize("c", [1.0, 1e3, 1e5])
@pytest.mark.parametrize("small", [0.0, -1e-12, -1e-20])
def test_functional_observer_with_a_pole_at_or_near_zero(c, small):
    """Poles [small, −2, −3] (n = 7, two outputs, order 3): the time unit was the poles' geometric mean,
    1 for a pole at 0 (refused after A → 1e3 A: residual 1.1e-7) and tiny for −1e-12 (refused in any
    unit).  It is their RMS magnitude now: accepted in every unit, with TA − FT = GC and
    aᵀ = kᵀT + eᵀC to rounding."""
    rng = np.random.default_rng(11)
    n, m = 7, 2
    A, B, C, a = rng.standard_normal((n, n)), rng.standard_normal((n, 1)), rng.standard_normal((m, n)), rng.standard_normal(n)
    poles = c * np.array([small, -2.0, -3.0])
    obs = obsjax.FunctionalObserver(obsjax.LTI(c * A, B, C), a, poles)
    F, T, G, k, e = (np.asarray(x) for x in (obs.F, obs.T, obs.G, obs.k, obs.e))
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(F).real), np.sort(poles), rtol=1e-6, atol=1e-9 * c)
    lhs = T @ (c * A) - F @ T
    assert np.abs(lhs - G @ C).max() <= 1e-10 * max(np.abs(lhs).max(), np.abs(G @ C).max())
    np.testing.assert_allclose(k @ T + e @ C, a, rtol=1e-10, atol=1e-12 * np.abs(a).max())


def test_adaptive_observers_refuse_non_integer_orders_complex_gains_and_asymmetry_at_any_scale():
    """`n = 2.7` was truncated to 2 (and True, "3" accepted) by int(); a complex Gamma passed check() and
    failed inside the solver naming nothing; the symmetry test of a matrix gain had an absolute floor
    1e-12 (an asymmetric gain of size 1e-13 passed); the conjugate-pair test of poles an absolute 1e-9
    (its verdict moved with the time unit)."""
    reg = lambda t, u: jnp.ones(3)
    for bad in (2.7, True, "3", 0, np.nan):
        with pytest.raises(ValueError, match="`n`.* must be an integer >= 1"):
            obsjax.LeastSquaresIdentifier(bad, reg)
        with pytest.raises(ValueError, match="`n`.* must be an integer >= 1"):
            obsjax.Kreisselmeier(bad, [-1.0, -2.0], 1.0)
    with pytest.raises(ValueError, match="`m` must be an integer >= 0"):
        obsjax.KudvaNarendra(2, 0.5, K=[[-1.0, 0.0], [0.0, -1.0]], Gamma1=1.0, Gamma2=1.0, Q=np.eye(2))
    assert obsjax.LeastSquaresIdentifier(np.int64(3), reg).n == 3 == obsjax.LeastSquaresIdentifier(3.0, reg).n
    with pytest.raises(ValueError, match="`Gamma` must be real"):
        obsjax.LeastSquaresIdentifier(3, reg, Gamma=1 + 1j)
    G = 1e-13 * np.array([[2.0, 0.5, 0.0], [0.1, 2.0, 0.0], [0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="`Gamma` must be a symmetric matrix"):
        obsjax.LeastSquaresIdentifier(3, reg, Gamma=G)
    obsjax.LeastSquaresIdentifier(3, reg, Gamma=0.5 * (G + G.T))  # symmetric at that scale: accepted
    for k in (1e-3, 1.0, 1e3):  # poles −1 ± 2i and −1 ± (2 + 1e-7)i, in three time units
        ok = k * np.array([-1 + 2j, -1 - 2j, -3.0])
        obsjax.Kreisselmeier(3, ok, 1.0)
        with pytest.raises(ValueError, match="complex-conjugate pairs"):
            obsjax.Kreisselmeier(3, k * np.array([-1 + 2j, -1 - (2 + 1e-7) * 1j, -3.0]), 1.0)


def test_least_squares_identifier_names_a_data_regressor_mismatch_and_a_complex_regressor():
    """Data with 2 outputs for a one-column regressor failed with a TypeError from reshape; a complex
    regressor with a dtype error from inside the solver."""
    ident = obsjax.LeastSquaresIdentifier(3, lambda t, u: jnp.array([1.0, jnp.sin(t), jnp.cos(2 * t)]))
    data = obsjax.Measurements(np.linspace(0.0, 5.0, 11), np.ones((11, 2)))
    with pytest.raises(ValueError, match="the measurement has 2 output.* m = 1 column"):
        obsjax.estimate(ident, data, jnp.zeros(3))
    bad = obsjax.LeastSquaresIdentifier(3, lambda t, u: jnp.array([1.0, jnp.sin(t), 1j]))
    with pytest.raises(ValueError, match="must return real values"):
        obsjax.simulate(ident.plant(), bad, jnp.ones(3), jnp.zeros(3), jnp.linspace(0.0, 1.0, 3))


@pytest.mark.parametrize("rtol", [-1.0, 0.0, float("nan"), True, "1e-8"])
def test_functional_observer_refuses_a_bad_rtol(rtol):
    """`rtol` = −1 or NaN was reported as "the functional cannot be observed" (a residual of 8e-16 against
    the bad tolerance): the argument itself is named now."""
    plant = obsjax.LTI([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -3.0, -3.0]], [[0.0], [0.0], [1.0]], [[1.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="`rtol`"):
        obsjax.FunctionalObserver(plant, [0.0, 1.0, 1.0], [-2.0, -3.0], rtol=rtol)


def test_a_structure_that_contradicts_concrete_real_poles_is_refused():
    """Luenberger/ReducedOrder with concrete real poles and a `structure` of another pattern: the repeated
    pole of the structure (which the values do not have) was warned about and the gain then failed at run
    time with a callback error.  It is refused at construction, as `design.place` refuses it; a structure
    that matches the real encoding is accepted."""
    from obsjax.design import pole_structure
    from obsjax.design._poles import encode

    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -2.0, -3.0]])
    plant = obsjax.LTI(A, np.eye(3)[:, :1], np.eye(3)[:2])
    with pytest.raises(ValueError, match="`structure` .* does not match the pattern of `poles`"):
        obsjax.Luenberger(plant, poles=np.array([-1.0, -2.0, -3.0]), structure=pole_structure([-1.0, -1.0, -2.0]))
    with pytest.raises(ValueError, match="`structure` .* does not match the pattern of `poles`"):
        obsjax.ReducedOrder(
            obsjax.LTI(A, np.eye(3)[:, :1], np.eye(3)[:1]), poles=np.array([-1.0, -2.0]),
            structure=pole_structure([-1.0, -1.0]),
        )
    pair = np.array([-1 + 2j, -1 - 2j, -3.0])
    st = pole_structure([-5 + 1j, -5 - 1j, -2.0])
    obs = obsjax.Luenberger(plant, poles=encode(pair, st), structure=st)  # accepted (its gain: other tests)
    assert obs.structure == st


def test_plant_forms_and_place_name_their_bad_arguments():
    """A NaN in `a` (kreisselmeier_form) or `lambdas` (luders_narendra_form) was reported as "`A` must be
    finite"; luders_narendra_form built the form (5.2) with a non-positive λ, which LudersNarendra refuses;
    place took boolean poles as 0/1 and reported tol ≥ 1 as "(A, C) is not observable"."""
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -2.0, -3.0]])
    C = np.eye(3)[:1]
    with pytest.raises(ValueError, match="`a` must be finite"):
        obsjax.kreisselmeier_form([1.0, np.nan], [1.0, 1.0])
    with pytest.raises(ValueError, match="`b` must be finite"):
        obsjax.kreisselmeier_form([1.0, 2.0], [np.inf, 1.0])
    with pytest.raises(ValueError, match="`lambdas` must be > 0 and finite"):
        obsjax.luders_narendra_form([1.0, 2.0], [1.0, 1.0], [np.nan])
    with pytest.raises(ValueError, match="`lambdas` must be > 0"):
        obsjax.luders_narendra_form([1.0, 2.0], [1.0, 1.0], [-1.0])
    with pytest.raises(ValueError, match="`poles` must be numbers, got booleans"):
        obsjax.design.place(A, C, [True, True, True])
    with pytest.raises(ValueError, match=r"`tol` \(a relative rank tolerance\) must be in \(0, 1\)"):
        obsjax.design.place(A, C, [-1.0, -2.0, -3.0], tol=2.0)
    # λ_1 of a length-n `lambdas` is the observer's own and not part of the form: not checked
    np.testing.assert_array_equal(obsjax.luders_narendra_form([1.0, 2.0], [1.0, 1.0], [-7.0, 3.0]).A, [[1.0, 1.0], [2.0, -3.0]])
