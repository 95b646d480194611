"""Plants with a feedthrough D (y = C x + D u): the observers written with y = C x either compare y with
C x̂ + D u or refuse the model.  Before, the Kalman–Bucy filter and the least-squares observer left a
constant bias (1.40 and 1.13 for D = 1, u = 1) reported as a success, and the Lovass-Nagy observers did
the same; the extended Kalman filter (through h) is the independent reference."""

import diffrax
import jax.numpy as jnp
import numpy as np
import pytest

import obsjax

A, B, C, D = [[0.0, 1.0], [-2.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]], [[1.0]]
U = lambda t: jnp.array([1.0])  # noqa: E731
TS = jnp.linspace(0.0, 20.0, 5)
KW = dict(u=U, solver=diffrax.Dopri8(), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize(
    "make",
    [
        lambda p: obsjax.KalmanBucy(p, Qw=0.1 * jnp.eye(2), Rv=0.01 * jnp.eye(1), P0=jnp.eye(2)),
        pytest.param(lambda p: obsjax.LeastSquaresReset(p, 20.0, 1.0, 1.0), marks=pytest.mark.extended),
    ],
    ids=["Kalman-Bucy", "least squares"],
)
def test_filters_subtract_the_feedthrough(make):
    plant = obsjax.LTI(A, B, C, D)
    tr = obsjax.simulate(plant, make(plant), jnp.zeros(2), jnp.array([0.5, -0.5]), TS, **KW)
    assert int(tr.status) == 0
    assert float(tr.error_norm[-1]) < 1e-10  # it settled at 1.40 (Kalman–Bucy), 1.13 (least squares)
    # the same estimate as the filter on the plant without D fed y − D u
    plain = obsjax.LTI(A, B, C)
    ref = obsjax.simulate(plain, make(plain), jnp.zeros(2), jnp.array([0.5, -0.5]), TS, **KW)
    np.testing.assert_allclose(tr.xhat, ref.xhat, atol=1e-9)


@pytest.mark.extended
def test_kalman_bucy_with_a_feedthrough_matches_the_extended_filter():
    """The extended Kalman filter reads the output through h(t, x, u) = C x + D u (independent of the
    feedthrough term added to the Kalman–Bucy filter); on a linear plant the two are the same filter."""
    plant = obsjax.LTI(A, B, C, D)
    kb = obsjax.KalmanBucy(plant, Qw=0.1 * jnp.eye(2), Rv=0.01 * jnp.eye(1), P0=jnp.eye(2))
    ekf = obsjax.ExtendedKalman(plant, Q=0.1, R=0.01, P0=1.0)
    ts = jnp.linspace(0.0, 5.0, 11)
    a = obsjax.simulate(plant, kb, jnp.zeros(2), jnp.array([0.5, -0.5]), ts, **KW)
    b = obsjax.simulate(plant, ekf, jnp.zeros(2), jnp.array([0.5, -0.5]), ts, **KW)
    np.testing.assert_allclose(a.xhat, b.xhat, atol=1e-9)


def test_lovass_nagy_observers_refuse_a_feedthrough():
    plant = obsjax.LTI([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-6.0, -11.0, -6.0]], [[0.0], [0.0], [1.0]],
                       [[1.0, 0.0, 0.0]], [[1.0]])
    with pytest.raises(ValueError, match="GeneralizedInverseODE needs a model without feedthrough"):
        obsjax.GeneralizedInverseODE(plant, jnp.diag(jnp.array([-4.0, -5.0, -6.0])), jnp.ones((3, 1)),
                                     horizon=(0.0, 10.0))
    T = lambda t: jnp.eye(3)  # noqa: E731  (refused before T is used)
    with pytest.raises(ValueError, match="GeneralizedInverse needs a model without feedthrough"):
        obsjax.GeneralizedInverse(plant, -jnp.eye(3), T, horizon=(0.0, 1.0))
    with pytest.raises(ValueError, match="GeneralizedInverseReduced needs a model without feedthrough"):
        obsjax.GeneralizedInverseReduced(plant, -jnp.eye(2), lambda t: jnp.eye(2), horizon=(0.0, 1.0))
