"""Chen & Yen's least-squares observer with covariance reset for LTV systems.

Source: M.-S. Chen and J.-Y. Yen, "Application of the least squares algorithm to the observer design for
linear time-varying systems", IEEE Transactions on Automatic Control, 44(9), 1999.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import real_array, static_value
from .._linalg import spd_solve
from ..systems._plants import LTV
from ._base import AbstractObserver, feedthrough
from ._validation import positive_scalar


def _safe_sqrt(t):
    # sqrt with a zero (instead of infinite) derivative at t = 0: the example's C(t) uses sqrt(t), and the
    # first reset instant t = 0 * T carries a zero tangent with respect to T; inf * 0 would be NaN.
    pos = t > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, t, 1.0)), 0.0)


def _example_A(t):
    c, s = jnp.cos(t), jnp.sin(t)
    return jnp.array(
        [
            [-1.0 + 1.5 * c * c, 1.0 - 1.5 * s * c],
            [-1.0 + 1.5 * s * c, -1.0 + 1.5 * s * s],
        ]
    )


def _example_C(t):
    r = _safe_sqrt(t)
    return jnp.array([[jnp.cos(r) + jnp.sin(r), 3.0 * jnp.cos(r) ** 2]])


def chen_yen_example(B=None) -> LTV:
    """The LTV plant of Chen & Yen's example (Section III), shared by tests, demo and notebooks.

        A(t) = [[-1 + 1.5 cos²t,      1 - 1.5 sin t cos t],
                [-1 + 1.5 sin t cos t, -1 + 1.5 sin²t     ]],
        C(t) = [cos √t + sin √t,  3 cos² √t].

    The (2, 1) entry is taken as printed, ``-1 + 1.5 sin t cos t`` (the textbook Markus-Yamabe matrix has
    ``-1 - 1.5 sin t cos t``, whose solutions grow like e^{t/2}: ‖x(10)‖ ≈ 742 from [5, -5]).  With the
    printed matrix the open loop is unstable but mildly so, ‖x(10)‖ = 11.63 from x(0) = [5, -5], as in
    the paper and in an independent SciPy integration.  ``√t`` is implemented with a zero derivative at t = 0 so that
    gradients with respect to the reset period T stay finite.

    **Arguments:**

    - `B`: optional callable t -> (2, p) input matrix (the paper's example has no input).

    **Returns:** an :class:`obsjax.LTV` with n = 2 states and m = 1 output.

    **Example:**

        plant = chen_yen_example()
        obs = LeastSquaresReset(plant, gamma=20.0, p0=0.1, T=0.25)
    """
    return LTV(_example_A, _example_C, B=B)


_SW_A1 = ((0.0, 1.0, 0.0), (-1.0, 0.1, 0.0), (0.5, 0.0, -0.3))
_SW_C1 = ((1.0, 0.0, 0.0),)
_SW_A2 = ((-0.2, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -2.0, 0.0))
_SW_C2 = ((0.0, 0.0, 1.0),)


class _Switching(eqx.Module):
    # Mode index from the declared jump times themselves, so that the solver's t = nextafter(jump) is on the
    # right side of every jump (floor(t / period) can be off by one at t = k * period in floating point);
    # past the last declared jump the switching goes on by the period (it stopped there before: the plant
    # then stayed in mode 2, which is not observable).
    jumps: jax.Array
    first: jax.Array
    second: jax.Array
    period: float = eqx.field(static=True)

    def __call__(self, t):
        count = jnp.sum(t >= self.jumps)
        if self.jumps.shape[0]:
            last = self.jumps[-1]
            count = jnp.where(t > last, self.jumps.shape[0] + jnp.floor((t - last) / self.period), count)
        else:
            count = jnp.maximum(jnp.floor(t / self.period), 0.0)
        odd = (count % 2) == 1
        return jnp.where(odd, self.second, self.first)


def switching_ltv_example(period: float = 0.7, horizon: float = 60.0) -> LTV:
    """A 3-state LTV plant with piecewise-constant parameters: Chen & Yen's discontinuous case.

    On [2j·τ, (2j+1)·τ) mode 1 and on [(2j+1)·τ, (2j+2)·τ) mode 2, τ = `period`:

        A1 = [[0, 1, 0], [-1, 0.1, 0], [0.5, 0, -0.3]],   C1 = [1, 0, 0]   (x3 unobservable)
        A2 = [[-0.2, 0, 0], [0, 0, 1], [0, -2, 0]],       C2 = [0, 0, 1]   (x1 unobservable)

    Neither mode is observable alone (rank 2 each), but the switched pair is uniformly observable for
    windows T ≳ τ (α1 > 0), with observability indices that change with time, and no derivative of A or C
    exists at the switches; mode 1's oscillator is slightly unstable.  The switching instants up to `horizon`
    are declared as ``jump_ts``, so the solver steps onto them and gradients with respect to the reset
    period T are exact; the plant goes on switching after `horizon` (t ≥ 0), but there the solver is not
    told where: build it with a `horizon` that covers the simulation.

    **Returns:** an :class:`obsjax.LTV` with n = 3, m = 1.

    **Example:**

        plant = switching_ltv_example()
        obs = LeastSquaresReset(plant, gamma=20.0, p0=1.0, T=0.93)
    """
    period, horizon = float(period), float(horizon)
    if not (np.isfinite(period) and period > 0):
        raise ValueError(f"`period` must be finite and > 0, got {period}.")
    if not (np.isfinite(horizon) and horizon > 0):
        raise ValueError(f"`horizon` must be finite and > 0, got {horizon}.")
    jumps = tuple(float(period * k) for k in range(1, int(horizon / period) + 1))
    ja = jnp.asarray(jumps, dtype=float)
    A = _Switching(ja, jnp.asarray(_SW_A1), jnp.asarray(_SW_A2), period)
    C = _Switching(ja, jnp.asarray(_SW_C1), jnp.asarray(_SW_C2), period)
    return LTV(A, C, jump_ts=jumps)


class LeastSquaresState(NamedTuple):
    """State of :class:`LeastSquaresReset`.

    - `xhat`: (n,) estimate x̂(t).
    - `Phi`: (n, n) open-loop transition matrix Φ(t, kT) of the model since the last reset, (11).
    - `Qinv`: (n, n) information matrix (γ P(t))⁻¹ = P⁻¹(t) / γ, with P = P_o of (15).
    """

    xhat: jax.Array
    Phi: jax.Array
    Qinv: jax.Array


def _scalar_gain(x, name, *, keep_constant=False):
    """A positive finite scalar as a float array of the default precision.  With `keep_constant`, a
    value that is a constant of the computation (not a tracer) is kept as a NumPy array: inside
    ``jax.jit`` every ``jnp`` operation is traced, and a reset period T written as a literal there must
    stay concrete for ``simulate`` to count its reset segments (without ``max_segments``)."""
    if keep_constant and static_value(x) is not None:
        v = np.asarray(static_value(x))
        if v.size == 1 and np.issubdtype(v.dtype, np.number) and not np.iscomplexobj(v):
            v = np.asarray(v.reshape(()), dtype=jnp.result_type(float))
            positive_scalar(v, name)
            return v
    arr = real_array(x, name)
    if arr.ndim != 0:
        if arr.size == 1:
            arr = arr.reshape(())
        else:
            raise ValueError(
                f"`{name}` must be a scalar, got an array of shape {tuple(arr.shape)}."
            )
    positive_scalar(arr, name)  # > 0 and finite: γ = inf or NaN is refused here, not in a solve
    # a strongly typed float64 scalar, so observers built from ints or Python floats share one jit trace
    return jnp.asarray(arr, dtype=jnp.result_type(float))


def _check_model(model):
    for attr in ("A_of", "C_of", "B_of"):
        if not hasattr(model, attr):
            raise ValueError(
                f"`model` must be an obsjax.LTV or obsjax.LTI plant (with A_of, B_of, C_of), got "
                f"{type(model).__name__}."
            )


class LeastSquaresReset(AbstractObserver):
    r"""Least-squares observer with covariance reset (Chen & Yen 1999, (8), (11), (13), (15)).

    For the LTV model ẋ = A(t)x + B(t)u, y = C(t)x (Chen & Yen (1)), on each interval [kT, (k+1)T):

        dx̂/dt = A(t) x̂ + B(t) u + L(t) (y - C(t) x̂ - D u),                    (8)  (D: an LTI model's feedthrough)
        L(t)  = γ Φ(t, kT) P(t) Φᵀ(t, kT) Cᵀ(t),                                 (13)
        ∂Φ(t, kT)/∂t = A(t) Φ(t, kT),            Φ(kT, kT) = I,                  (11)
        dP/dt = -γ P w wᵀ P,   w = Φᵀ(t, kT) Cᵀ(t),   P(kT⁺) = p0 I,             (15)

    and at every t = t0 + kT the observer resets Φ = I and P = p0 I (x̂ is continuous).  The error
    x̃ = x̂ - x obeys (9) and contracts by μ / (1 + γ p0 α1 m1²) per period (Theorem; see
    :func:`obsjax.analysis.chen_yen_bound`).

    **State and numerics.**  The state (:class:`LeastSquaresState`) holds x̂, Φ and the information matrix
    Qinv = (γP)⁻¹ = P⁻¹/γ instead of P.  The proof of the Theorem gives d(P⁻¹)/dt = γ w wᵀ, so

        d Qinv / dt = w wᵀ,      Qinv(kT⁺) = I / (γ p0),      L = Φ Qinv⁻¹ Φᵀ Cᵀ.

    This is linear in Qinv (no Riccati quadratic term, no stiffness from it), its solution
    Qinv(t) = I/(γp0) + ∫ w wᵀ is a sum of a positive definite and positive semidefinite terms, so it stays
    symmetric positive definite (and its eigenvalues only grow) whatever the solver's local error, whereas
    integrating (15) directly can lose definiteness when γ p0 ‖w‖² T is large.  The gain needs one small
    (n × n) symmetric solve per evaluation.  P itself is recovered by :meth:`covariance`.

    **γ and p0 enter only through their product.**  With Q = γP the law reads L = Φ Q Φᵀ Cᵀ,
    dQ/dt = -Q w wᵀ Q, Q(kT⁺) = γ p0 I: the estimate depends on γ and p0 only through γ·p0 (tests check
    it).  Tuning both is redundant: under :func:`obsjax.tune`'s positive (log) parametrisation the two
    gradients are equal, so tune γ (or p0) and T, or read the product as the gain.

    **Units.**  The reset P = p0·I (the paper's (15)) weighs every state alike, so the observer is not
    invariant under a change of the states' relative units: with states in units 1e-3 and 1e3 it is a
    different observer (its gain favours the directions that are large in those units).  Under a common
    state scale s, output scale e and time scale k (t' = k t) it transforms exactly with
    γ·p0 ↦ γ·p0·s²/(k e²).  Give the states comparable units (or a P0 shaped to them through a state
    transformation of the model) before comparing gains across models.

    **Arguments:**

    - `model`: the observer's model of the plant, an :class:`obsjax.LTV` (or :class:`obsjax.LTI`); A(t),
      B(t) (inputs supported) and C(t) are read from it.
    - `gamma`: least-squares gain γ > 0 (differentiable leaf).
    - `p0`: reset value p0 > 0 of P (differentiable leaf).
    - `T`: reset period T > 0 (differentiable leaf; the reset instants move with it).

    A non-positive or non-finite γ, p0 or T raises ``ValueError`` (or fails via ``eqx.error_if``
    when traced).

    **Kinks in T.**  Where a save time coincides with a reset instant t0 + kT, the error and hence
    any loss on the save grid has a kink as a function of T: a slightly shorter period puts the
    reset (and the fresh gain γ p0 I) before the save time, a slightly longer one after it.
    Autodiff then returns a one-sided derivative (at an interior save time, the derivative from the
    left).  On the paper's example with x̂(0) = (5, −5), γ = 20, p0 = 0.1 and the ISE on a 0.1 s
    grid over [0, 10], T = 2.3 puts four save times on reset instants: autodiff gives dJ/dT = −11.84
    (the left derivative), the right derivative is −13.97. :func:`obsjax.tune` warns when this
    happens; keep T off the save grid when tuning it.  On recorded data (:func:`obsjax.estimate`)
    the samples are the save times and the same holds at a reset on a sample instant (the derivative
    from the left; :func:`obsjax.tune_on_data` warns, for every experiment of a batch).  At t1 itself
    a reset is not applied, so there the derivative is the one from the right; a loss with kinks both
    inside the horizon and at t1 gets a mix of the two sides, neither one-sided derivative of J.

    **Example:** Fig. 1 of the paper::

        plant = obsjax.chen_yen_example()
        obs = obsjax.LeastSquaresReset(plant, gamma=20.0, p0=0.1, T=0.25)
        traj = obsjax.simulate(plant, obs, jnp.zeros(2), jnp.array([5.0, -5.0]), jnp.linspace(0, 10, 201))
    """

    model: eqx.Module
    gamma: jax.Array
    p0: jax.Array
    T: jax.Array

    def __init__(self, model, gamma, p0, T):
        _check_model(model)
        self.model = model
        self.gamma = _scalar_gain(gamma, "gamma")
        self.p0 = _scalar_gain(p0, "p0")
        self.T = _scalar_gain(T, "T", keep_constant=True)

    @property
    def n(self) -> int:
        return self.model.n

    @property
    def reset_period(self):
        return self.T

    def check(self) -> LeastSquaresReset:
        """Re-validate γ, p0, T > 0 and finite: ``ValueError`` for concrete values,
        ``eqx.error_if`` for traced ones.

        Concrete leaves are returned untouched (so a concrete T stays concrete and ``simulate`` can count
        the reset segments itself under ``jit``).
        """
        new = tuple(
            positive_scalar(leaf, name, " (the reset period)" if name == "T" else "")
            for name, leaf in (("gamma", self.gamma), ("p0", self.p0), ("T", self.T))
        )
        return eqx.tree_at(lambda o: (o.gamma, o.p0, o.T), self, new)

    def prepare(self) -> LeastSquaresReset:
        return self.check()

    def _reset_state(self, xhat):
        n = self.model.n
        eye = jnp.eye(n, dtype=jnp.result_type(xhat, self.gamma))
        return LeastSquaresState(xhat, eye, eye / (self.gamma * self.p0))

    def init(self, t0, xhat0, y0):
        return self._reset_state(jnp.asarray(xhat0))

    def reset(self, t, z):
        """Covariance reset at t = kT: Φ(kT, kT) = I (11), P(kT⁺) = p0 I (15); x̂ unchanged."""
        return self._reset_state(z.xhat)

    def _injection(self, t, z):
        # Returns L(t) of (13) and w = Φᵀ Cᵀ.
        C = self.model.C_of(t)
        w = z.Phi.T @ C.T
        Qinv = 0.5 * (z.Qinv + z.Qinv.T)
        L = z.Phi @ spd_solve(Qinv, w)
        return L, w, C

    def gain(self, t, z):
        """Observer gain L(t) = γ Φ P Φᵀ Cᵀ of (13), shape (n, m)."""
        return self._injection(t, z)[0]

    def covariance(self, z):
        """P(t) of (15) recovered from the state: P = Qinv⁻¹ / γ."""
        return jnp.linalg.inv(0.5 * (z.Qinv + z.Qinv.T)) / self.gamma

    def vector_field(self, t, z, y, u):
        A = self.model.A_of(t)
        L, w, C = self._injection(t, z)
        dxhat = A @ z.xhat + L @ (y - C @ z.xhat - feedthrough(self.model, u))
        if u is not None and self.model.p > 0:
            dxhat = dxhat + self.model.B_of(t) @ u
        return LeastSquaresState(dxhat, A @ z.Phi, w @ w.T)

    def estimate(self, t, z, y):
        return z.xhat
