"""Covariances and gains of the Kalman-type and least-squares observers are checked relative to their own
scale, eagerly and under jit, and complex values are refused.  Before, the tolerances had absolute floors
(1e-12), so a non-symmetric or indefinite matrix of scale 1e-12 (a variance in km² of mm-level errors)
was accepted, and complex gains lost their imaginary part with only a NumPy warning."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import obsjax

PLANT = obsjax.chen_yen_example()
NON_SYMMETRIC = np.array([[1.0, 0.5], [-0.5, 1.0]])  # its symmetric part is positive definite
INDEFINITE = np.diag([1.0, -0.9])


@pytest.mark.parametrize("s", [1.0, 1e-12, 1e12])
def test_covariances_are_checked_in_their_own_scale(s):
    cases = [
        ("P0", lambda: obsjax.KalmanBucy(PLANT, s * np.eye(2), np.eye(1), s * NON_SYMMETRIC)),
        ("P0", lambda: obsjax.ContinuousDiscreteKalman(PLANT, s * np.eye(2), np.eye(1), s * NON_SYMMETRIC, period=0.1)),
        ("P0", lambda: obsjax.ExtendedKalman(PLANT, Q=s, R=1.0, P0=s * NON_SYMMETRIC)),
        ("Q", lambda: obsjax.ExtendedKalman(PLANT, Q=s * INDEFINITE, R=1.0, P0=s)),
        ("P0", lambda: obsjax.ExtendedKalman(PLANT, Q=s, R=1.0, P0=s * INDEFINITE)),
        ("Qw", lambda: obsjax.KalmanBucy(PLANT, s * INDEFINITE, np.eye(1), s * np.eye(2))),
    ]
    for name, make in cases:
        with pytest.raises(ValueError, match=f"`{name}` must be (symmetric|positive)"):
            make()
    # a singular PSD intensity with round-off (B Bᵀ) is still accepted, at any scale
    b = np.array([[1.0], [1.0 / 3.0]])
    obsjax.KalmanBucy(PLANT, s * (b @ b.T), np.eye(1), s * np.eye(2))
    obsjax.ExtendedKalman(PLANT, Q=s * (b @ b.T), R=1.0, P0=s)

    def run(Qw):
        kb = obsjax.KalmanBucy(PLANT, Qw, s * jnp.eye(1), s * jnp.eye(2))  # the same filter at any s
        ts = jnp.linspace(0.0, 1.0, 3)
        return obsjax.simulate(PLANT, kb, jnp.zeros(2), jnp.zeros(2), ts, atol=1e-10 * min(s, 1.0)).error  # P in its units

    assert np.all(np.isfinite(np.asarray(jax.jit(run)(jnp.asarray(s * np.eye(2))))))
    with pytest.raises(Exception, match="Qw"):
        jax.block_until_ready(jax.jit(run)(jnp.asarray(s * INDEFINITE)))


def test_complex_gains_and_covariances_are_refused():
    with pytest.raises(ValueError, match="`gamma` must be real"):
        obsjax.LeastSquaresReset(PLANT, 20 + 5j, 0.1, 0.25)
    with pytest.raises(ValueError, match="`p0` must be real"):
        obsjax.LeastSquaresReset(PLANT, 20.0, 0.1 - 3j, 0.25)
    with pytest.raises(ValueError, match="`Qw` must be real"):
        obsjax.KalmanBucy(PLANT, (1 + 1j) * np.eye(2), np.eye(1), np.eye(2))
    with pytest.raises(ValueError, match="`Q` must be real"):
        obsjax.ExtendedKalman(PLANT, Q=1 + 1j, R=1.0, P0=1.0)
    with pytest.raises(ValueError, match="`gamma` must be a positive finite real scalar"):
        obsjax.analysis.chen_yen_bound(PLANT, 20 + 5j, 0.1, 0.25, 1.0)


def test_the_filters_start_from_the_symmetric_part_of_P0():
    """The default tier's twin of the next test: the derivative of the initial state in P0 is the
    symmetric part of the cotangent (P0 enters as (P0 + P0ᵀ)/2), for the three filters."""
    plant = obsjax.LTI(-np.eye(2), np.zeros((2, 1)), np.array([[1.0, 0.5]]))
    model = obsjax.Nonlinear(lambda t, x, u: -x, lambda t, x, u: jnp.array([x[0] + 0.5 * x[1]]), 2, 1, 0)
    P0 = np.array([[2.0, 0.3], [0.3, 1.0]])
    W = jnp.array([[1.0, 2.0], [-3.0, 0.5]])  # a non-symmetric cotangent
    filters = {
        "KalmanBucy": (obsjax.KalmanBucy(plant, np.eye(2), np.eye(1), P0), lambda z: z.P),
        "ContinuousDiscreteKalman": (
            obsjax.ContinuousDiscreteKalman(plant, np.eye(2), np.eye(1), P0, period=0.1), lambda z: z.P
        ),
        "ExtendedKalman": (obsjax.ExtendedKalman(model, Q=np.eye(2), R=1.0, P0=P0), lambda z: z[1]),
    }
    for name, (obs, P_of) in filters.items():
        import equinox as eqx

        f = lambda P: jnp.sum(W * P_of(eqx.tree_at(lambda o: o.P0, obs, P).init(0.0, jnp.zeros(2), jnp.zeros(1))))
        np.testing.assert_allclose(jax.grad(f)(jnp.asarray(P0)), 0.5 * (W + W.T), err_msg=name)


@pytest.mark.parametrize(
    "kind",
    [
        pytest.param("KalmanBucy", marks=pytest.mark.extended),  # 8 s, 8 s and 12 s here: second tier
        pytest.param("ExtendedKalman", marks=pytest.mark.extended),
        pytest.param("ContinuousDiscreteKalman", marks=pytest.mark.extended),
    ],
)
def test_the_derivative_in_P0_is_symmetric_and_matches_central_differences(kind):
    """P is read through C P in the gain, so the raw cotangent of P0 had an antisymmetric part as large
    as its symmetric one (max|G − Gᵀ|/max|G| = 1.07): one gradient step left a non-symmetric P0, which
    check() refused, and tune(where=P0) rejected every step.  P0 is now symmetrised where the filter
    starts, so G is the derivative over symmetric matrices."""
    import equinox as eqx

    A = np.array([[0.0, 1.0, 0.0], [-2.0, -0.4, 0.3], [0.2, 0.0, -1.0]])
    C = np.array([[1.0, 0.0, 0.0], [0.0, 0.5, 1.0]])
    plant = obsjax.LTI(A, np.zeros((3, 1)), C)
    Q = np.array([[0.1, 0.02, 0.0], [0.02, 0.3, 0.01], [0.0, 0.01, 0.05]])
    R = np.array([[0.02, 0.005], [0.005, 0.1]])
    P0 = np.array([[2.0, 0.3, 0.1], [0.3, 1.0, 0.2], [0.1, 0.2, 0.5]])
    if kind == "KalmanBucy":
        obs = obsjax.KalmanBucy(plant, Q, R, P0)
    elif kind == "ExtendedKalman":
        model = obsjax.Nonlinear(lambda t, x, u: jnp.asarray(A) @ x, lambda t, x, u: jnp.asarray(C) @ x, 3, 2, 0)
        obs = obsjax.ExtendedKalman(model, Q=Q, R=R, P0=P0)
    else:
        obs = obsjax.ContinuousDiscreteKalman(plant, Q, R, P0, period=0.25)
    x0, xh0, ts = np.array([1.0, -0.5, 0.3]), np.array([0.0, 0.2, -0.1]), np.linspace(0.0, 2.0, 21)

    @jax.jit
    def J(P):
        o = eqx.tree_at(lambda o: o.P0, obs, P)
        return obsjax.losses.ise(obsjax.simulate(plant, o, x0, xh0, ts, rtol=1e-10, atol=1e-12))

    G = np.asarray(jax.grad(J)(jnp.asarray(P0)))
    assert np.max(np.abs(G - G.T)) <= 1e-12 * np.max(np.abs(G))
    E = np.array([[0.3, -0.2, 0.1], [-0.2, 0.5, 0.4], [0.1, 0.4, -0.6]])  # a symmetric direction
    h = 1e-4
    fd = (float(J(P0 + h * E)) - float(J(P0 - h * E))) / (2 * h)
    assert np.sum(G * E) == pytest.approx(fd, rel=1e-6)
    obsjax.KalmanBucy(plant, Q, R, P0 - 0.1 * G / np.max(np.abs(G))).check()  # a step stays a covariance


def test_definiteness_verdicts_do_not_depend_on_the_state_units():
    """A P0 with eigenvalues 0.60 … 22.3 in units spread over 1e-4 … 1e4 (D P0 D, Cholesky succeeds) was
    refused ("eigenvalue −4.8e-8"), eagerly and under jit, and so was KudvaNarendra's Q; the verdicts are
    now taken on the equilibrated matrix.  An indefinite matrix in the same units is still refused."""
    rng = np.random.default_rng(7)
    M = rng.standard_normal((4, 4))
    P0 = M @ M.T + 0.5 * np.eye(4)
    bad = P0 - 1.01 * np.linalg.eigvalsh(P0)[0] * np.eye(4)  # smallest eigenvalue −0.01·λ_min < 0
    A = np.diag([-1.0, -2.0, -3.0, -4.0]) + np.diag([1.0, 1.0, 1.0], 1)
    C = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    for d in (np.array([1e-3, 1e-1, 1e2, 1e3]), np.array([1e2, 1e-4, 1e4, 1e-1])):
        Dm = np.diag(d)
        np.linalg.cholesky(Dm @ P0 @ Dm)  # positive definite in the new units: an independent check
        plant = obsjax.LTI(Dm @ A @ np.linalg.inv(Dm), np.zeros((4, 1)), C @ np.linalg.inv(Dm))
        obsjax.KalmanBucy(plant, Dm @ Dm, np.eye(2), Dm @ P0 @ Dm)
        obsjax.KudvaNarendra(4, 1, K=-np.eye(4), Gamma1=1.0, Gamma2=1.0, Q=Dm @ P0 @ Dm)
        with pytest.raises(ValueError, match="`P0` must be positive definite"):
            obsjax.KalmanBucy(plant, Dm @ Dm, np.eye(2), Dm @ bad @ Dm)
        with pytest.raises(ValueError, match="`Q` must be positive definite"):
            obsjax.KudvaNarendra(4, 1, K=-np.eye(4), Gamma1=1.0, Gamma2=1.0, Q=Dm @ bad @ Dm)
    kb = obsjax.KalmanBucy(plant, Dm @ Dm, np.eye(2), Dm @ P0 @ Dm)
    prep = jax.jit(lambda P: eqx_tree_at_P0(kb, P).prepare().P0)
    np.testing.assert_allclose(prep(jnp.asarray(Dm @ P0 @ Dm)), Dm @ P0 @ Dm)
    with pytest.raises(Exception, match="P0"):
        jax.block_until_ready(prep(jnp.asarray(Dm @ bad @ Dm)))


def eqx_tree_at_P0(obs, P):
    import equinox as eqx

    return eqx.tree_at(lambda o: o.P0, obs, P)


def test_rounding_that_equilibration_magnifies_does_not_refuse_a_valid_covariance():
    """diag(0, 1) after a rotation and back carries off-diagonal residue of 3e-17 beside a diagonal entry
    of 1e-17: equilibrated, that residue reads as an asymmetry of 1e-9 and the matrix was refused
    ("must be symmetric") as Qw, Q, P0 and as an adaptation gain.  Either test passing now suffices."""
    c, s_ = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s_], [s_, c]])
    Qx = R.T @ (R @ np.diag([0.0, 1.0]) @ R.T) @ R
    assert abs(Qx[0, 1] - Qx[1, 0]) > 0 and Qx[0, 0] != 0  # the residue is there
    obsjax.KalmanBucy(PLANT, Qx, np.eye(1), np.eye(2))
    obsjax.ExtendedKalman(PLANT, Q=Qx, R=1.0, P0=Qx)
    obsjax.KalmanBucy(PLANT, np.diag([-1e-18, 1.0]), np.eye(1), np.eye(2))
    Pd = R.T @ (R @ np.diag([1e-16, 1.0]) @ R.T) @ R
    obsjax.KalmanBucy(PLANT, np.eye(2), np.eye(1), Pd)
    with pytest.raises(ValueError, match="`P0` must be positive definite"):
        obsjax.KalmanBucy(PLANT, np.eye(2), np.eye(1), np.diag([-1e-6, 1.0]))
