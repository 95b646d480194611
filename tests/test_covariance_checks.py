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
