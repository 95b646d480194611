"""Trajectory linearization observer with PD-eigenvalue assignment and time-varying high gain
(Huang & Zhu, (5)-(7), (18), (21)-(23))."""

from __future__ import annotations

from collections.abc import Callable
from math import factorial

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array, concrete_value, vector
from ..design._ltv_canonical import CANONICAL_TOL
from ..design._ltv_canonical import (
    _check_indices,
    ltv_observability_indices,
    strong_observability,
    time_derivatives,
)
from ..analysis._lti import balancing
from ..design._pd_spectrum import (
    RHO_BAR_MIN_GAP,
    check_rho_bar,
    omega_function,
    pd_observer_gain,
    rho_bar_too_close,
)
from ..systems._plants import AbstractSystem
from ._base import AbstractObserver
from ._validation import positive_scalar, require_finite

_EPS_WHAT = " (the high-gain factor, ω_H = ω/ε)"


def _horner(cs, tau):
    """Σ_j c_j τ^j / j! in Horner form (multiplications and additions only: cheap under nested jvp)."""
    x = cs[-1] / factorial(len(cs) - 1)
    for j in range(len(cs) - 2, -1, -1):
        x = x * tau + cs[j] / factorial(j)
    return x


def _flow_polynomial(f, t, x0, u, order: int):
    """Taylor polynomial (degree `order`) at t of the model flow ẋ = f(s, x, u) through x(t) = x0, input
    frozen at u.  Coefficient k+1 is the k-th derivative of f along the degree-k polynomial (nested jvp)."""
    coeffs = [x0]
    for k in range(order):
        cs = tuple(coeffs)

        def g(tau, cs=cs):
            return f(t + tau, _horner(cs, tau), u)

        coeffs.append(time_derivatives(g, jnp.zeros_like(t), k)[-1])
    cs = tuple(coeffs)

    def xbar(s):
        return _horner(cs, s - t)

    return xbar


@eqx.filter_jit
def _gain(observer, t, z, u):
    """K_o(t) as its own jitted function: an implicit solver traces, linearises and batches the vector
    field several times per step, and JAX caches the traced gain (and its jvp / batching) per call site
    signature, so the PD-eigenvalue design is traced once instead of once per use."""
    return observer.gain(t, z, u)


class TrajectoryLinearization(AbstractObserver):
    """Trajectory linearization observer (TLO), MIMO and time-varying high gain (Huang & Zhu).

    In state coordinates (ξ̂ = ξ̄ + ξ̃̂, so that F(ξ̃̂, …) + f(ξ̄, μ̄) = f(ξ̂, μ)), the observer (5)/(18) is

        ξ̂˙ = f(t, ξ̂, u) + K_o(t) (h(t, ξ̂, u) − y),                                         (5), (18)

    and its linearised error obeys x̃˙ = (A_o + K_o C_o) x̃ (6) with the Jacobians (7)

        A_o(t) = ∂f/∂ξ (t, ξ̄(t), μ̄(t)),    C_o(t) = ∂h/∂ξ (t, ξ̄(t), μ̄(t))    (by ``jax.jacfwd``).

    K_o(t) is designed at every t by PD-eigenvalue assignment (Step (b)): the pair (A_o, C_o) is put in the
    LTV observer canonical form (8)-(11), the closed loop of output block i is given the PD-spectrum
    {ρ̄_k ω_H(t)}, ω_H = ω/ε (21)-(23), through the synthesis formula and the coupling cancellation (14),
    and K_o = T⁻¹K_z (see :func:`obsjax.design.pd_observer_gain`).  All time derivatives (Ċ_o, Q̇_0, ω̇, …)
    are taken by automatic differentiation.

    **Step (c), the implementation choice.**  K_o depends on the trajectory it linearises about.

    - With ``nominal`` (a callable t ↦ (ξ̄(t), μ̄(t))), the Jacobians and all their time derivatives are
      taken along that nominal trajectory: this is the paper's K_o(0, μ(t)) (zero tracking-error estimate),
      and the gain does not depend on the estimate.
    - With ``nominal=None``, the Jacobians are evaluated at the running estimate ξ̂(t), and their time
      derivatives are those along the model flow through ξ̂(t) with the input frozen at u(t) (a Taylor
      polynomial of degree 2·max p_i − 1 built by nested ``jax.jvp``).  The output-injection term and u̇ are
      left out of these derivatives; like the replacement of Step (c) they enter the error dynamics only as
      a vanishing perturbation.

    **Stiffness.**  The fastest assigned PD-eigenvalue is max|ρ̄_k| · ω / ε; for small ε the observer is
    stiff.  :meth:`recommended_solver` returns ``diffrax.Kvaerno5()`` when that rate exceeds ``stiff_rate``
    (default 50 s⁻¹) and ``diffrax.Tsit5()`` otherwise; pass it to :func:`obsjax.simulate`'s ``solver``.
    Under ``jit`` with ε (or ω) a traced leaf the rate cannot be known, so ``simulate``'s default is then
    the implicit Kvaerno5, whose Newton Jacobian differentiates the gain: 3–4× the compile time of
    Tsit5 (benchmarks/results/c_compile_time.md).  When ε stays in the non-stiff range, choose the solver
    outside ``jit`` (``solver=obs.recommended_solver(ts)``), as :mod:`obsjax._reproduce.huang_zhu` does.

    **Cost.**  K_o is traced once per simulation (a jitted inner function, reused by every solver stage
    and by the Newton Jacobian), and the canonical form is computed in truncated Taylor-series arithmetic
    (:func:`obsjax.design.ltv_observer_canonical_form`), so the traced graph grows polynomially with the
    derivative order 2·max p_i − 1.

    **Arguments:**

    - `model`: the observer's model of the plant (:class:`obsjax.Nonlinear`, or any obsjax plant).
    - `rho_bar`: (n,) nominal PD-eigenvalues ρ̄_k < 0, distinct within each output block, listed block by
      block (p_1 values for output 1, then p_2 for output 2, …).
    - `omega`: the bandwidth ω > 0: a constant or a callable of t (e.g. :class:`obsjax.design.RampBandwidth`;
      its array leaves are tunable).  A callable is checked where the gain is evaluated: ω(t) ≤ 0 or
      not finite there raises (``ValueError`` eagerly, ``eqx.error_if`` in a simulation), since the
      PD-spectrum ρ̄_k ω(t) would have the wrong sign (an unstable observer).
    - `eps`: the high-gain factor ε > 0 (ω_H = ω/ε).
    - `nominal`: ``None`` or a callable t ↦ (ξ̄(t), μ̄(t)).
    - `indices`: the observability indices (p_1, …, p_m) of (A_o, C_o); computed at t = 0 along the nominal
      (without a nominal: at ξ = 0, μ = 0) when ``None``.
    - `check_ts`: times at which strong observability of (A_o, C_o) along the nominal is checked at
      construction (``ValueError`` naming the first failing time); requires `nominal`.
    - `threshold`: the smallest admissible staircase margin of (A_o, C_o) (default 1e-6, below which the
      canonical form loses more than about 2e-4 of its accuracy, see :func:`obsjax.design.ltv_observer_canonical_form`): the
      scale-invariant form of Huang & Zhu's strong-observability constant (|det QᵀQ| ≥ c, which changes
      with the units), computed by the rank mechanism of the indices
      (:func:`obsjax.design.strong_observability`).  A margin of the rows of Q_0 at or below it stops
      the simulation (``eqx.error_if``), and a margin of Q below it fails the `check_ts` check.
    - `stiff_rate`: see Stiffness.
    - `on_unobservable`: ``"error"`` (default) raises at run time (``eqx.error_if``) when the staircase
      margin of Q_0 (see `threshold`) falls to `threshold` along the trajectory; ``"nan"`` makes the gain NaN instead, so that in a
      vmapped study only that trajectory fails (``simulate(..., throw=False)`` reports status 2).

    **Example:** Van der Pol oscillator, y = x₁::

        f = lambda t, x, u: jnp.array([x[1], (1 - x[0] ** 2) * x[1] - x[0]])
        h = lambda t, x, u: x[:1]
        model = obsjax.Nonlinear(f, h, n=2, m=1)
        obs = obsjax.TrajectoryLinearization(model, rho_bar=[-1.0, -2.0], omega=2.0, eps=0.2)
        traj = obsjax.simulate(model, obs, jnp.array([2., 0.]), jnp.zeros(2), ts,
                               solver=obs.recommended_solver())
    """

    model: AbstractSystem
    rho_bar: jax.Array
    omega: jax.Array | Callable
    eps: jax.Array
    nominal: Callable | None
    indices: tuple[int, ...] = eqx.field(static=True)
    threshold: float = eqx.field(static=True, default=CANONICAL_TOL)
    stiff_rate: float = eqx.field(static=True, default=50.0)
    on_unobservable: str = eqx.field(static=True, default="error")
    # the state scaling of the balanced pair at t = 0 (the margin's state units, computed once)
    state_scale: tuple[float, ...] | None = eqx.field(static=True, default=None)

    def __init__(
        self,
        model,
        rho_bar,
        omega,
        eps=1.0,
        nominal=None,
        *,
        indices=None,
        check_ts=None,
        threshold: float = CANONICAL_TOL,
        stiff_rate: float = 50.0,
        on_unobservable: str = "error",
    ):
        if not isinstance(model, AbstractSystem):
            raise ValueError(
                f"`model` must be an obsjax plant (Nonlinear, LTV, LTI), got {type(model).__name__}."
            )
        if nominal is not None and not callable(nominal):
            raise ValueError(
                f"`nominal` must be None or a callable t -> (xbar, ubar), got {type(nominal).__name__}."
            )
        if not threshold > 0:
            raise ValueError(f"`threshold` must be > 0, got {threshold}.")
        if not stiff_rate > 0:
            raise ValueError(f"`stiff_rate` must be > 0, got {stiff_rate}.")
        if on_unobservable not in ("error", "nan"):
            raise ValueError(
                f"`on_unobservable` must be 'error' or 'nan', got {on_unobservable!r}."
            )
        self.on_unobservable = on_unobservable
        if check_ts is not None and nominal is None:
            raise ValueError(
                "`check_ts` checks strong observability along `nominal`; give `nominal` too."
            )
        self.model = model
        self.nominal = nominal
        self.rho_bar = check_rho_bar(rho_bar, "rho_bar", negative=True, distinct=False)
        if self.rho_bar.shape[0] != model.n:
            raise ValueError(
                f"`rho_bar` must hold n = {model.n} nominal PD-eigenvalues, got {self.rho_bar.shape[0]}."
            )
        self.omega = omega if callable(omega) else as_float_array(omega, "omega")
        omega_function(self.omega)
        self.eps = as_float_array(eps, "eps")
        self.threshold = float(threshold)
        self.stiff_rate = float(stiff_rate)
        # the indices and the strong-observability test are decided on the model's values; built inside
        # jit (a traced ε), the model's Jacobians are staged like everything else, so they are evaluated at
        # trace time instead (they do not depend on what is traced)
        tracing = (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError)
        try:
            self._structure(indices, check_ts)
        except tracing:
            try:
                with jax.ensure_compile_time_eval():
                    self._structure(indices, check_ts)
            except tracing as e:
                raise ValueError(
                    "TrajectoryLinearization decides its observability indices (and the check over "
                    "`check_ts`) on the model's values, and the model is traced here: pass `indices`, or "
                    "build the observer outside jit and change its gains with eqx.tree_at."
                ) from e
        self.check()

    def _structure(self, indices, check_ts):
        model = self.model
        A0f, C0f = self._frozen_jacobians()
        if indices is None:
            indices = ltv_observability_indices(A0f, C0f, 0.0 if check_ts is None else check_ts)
        self.indices = _check_indices(indices, model.n, model.m)
        A0v, C0v = np.asarray(A0f(jnp.asarray(0.0)), float), np.asarray(C0f(jnp.asarray(0.0)), float)
        self.state_scale = None
        if np.all(np.isfinite(A0v)) and np.all(np.isfinite(C0v)):
            d = np.asarray(balancing(A0v, C0v)[0], float)
            if np.all(np.isfinite(d)) and np.all(d > 0):
                self.state_scale = tuple(float(v) for v in d)
        if check_ts is not None:
            A, C = self._jacobian_fns(None, None)
            strong_observability(A, C, check_ts, threshold=self.threshold)

    # ------------------------------------------------------------------ validation
    def check(self) -> TrajectoryLinearization:
        """Eager checks (``ValueError``): ε finite > 0, ρ̄ finite < 0 (distinct per block), a
        constant ω finite > 0.  :meth:`prepare` repeats the value checks with ``eqx.error_if``
        under ``jit``."""
        if self.eps.ndim != 0:
            raise ValueError(f"`eps` must be a scalar, got shape {tuple(self.eps.shape)}.")
        positive_scalar(self.eps, "eps", _EPS_WHAT)
        require_finite(self.rho_bar, "rho_bar")
        if not callable(self.omega):
            require_finite(self.omega, "omega")
        check_rho_bar(self.rho_bar, "rho_bar", negative=True, distinct=False)
        start = 0
        for p in self.indices:
            check_rho_bar(self.rho_bar[start : start + p], f"rho_bar[{start}:{start + p}]")
            start += p
        omega_function(self.omega)
        return self

    def prepare(self) -> TrajectoryLinearization:
        """Value checks that survive ``jit`` (``eqx.error_if``): ε finite > 0, ρ̄ finite < 0, a
        constant ω finite > 0; concrete values were checked eagerly by :meth:`check`."""
        eps = positive_scalar(self.eps, "eps", _EPS_WHAT)
        rho = self.rho_bar
        if concrete_value(rho) is None:
            rho = eqx.error_if(
                rho,
                jnp.any(~(rho < 0) | ~jnp.isfinite(rho)),
                "`rho_bar` (the nominal PD-eigenvalues) must be < 0 and finite.",
            )
            close, start = jnp.asarray(False), 0
            for p in self.indices:  # distinct within each block, as check_rho_bar eagerly
                close = close | rho_bar_too_close(rho[start : start + p])
                start += p
            rho = eqx.error_if(
                rho,
                close,
                f"`rho_bar` must hold distinct values within each output block, at least {RHO_BAR_MIN_GAP:g}"
                "·max|ρ̄| apart (the Vandermonde solve of (21) loses its accuracy near a repeated value).",
            )
        new = eqx.tree_at(lambda o: (o.eps, o.rho_bar), self, (eps, rho))
        if not callable(self.omega):
            omega = positive_scalar(self.omega, "omega", " (the bandwidth)")
            new = eqx.tree_at(lambda o: o.omega, new, omega)
        return new

    # ------------------------------------------------------------------ linearisation (7)
    def _input_zeros(self):
        return jnp.zeros((self.model.p,))

    def _frozen_jacobians(self):
        """Jacobians at t = 0 along the nominal (or at ξ = 0, μ = 0), for the observability indices."""
        if self.nominal is not None:
            return self._jacobian_fns(None, None)
        x0, u0 = jnp.zeros(self.model.n), self._input_zeros()
        Ax = jax.jacfwd(self.model.f, argnums=1)(0.0, x0, u0)
        Cx = jax.jacfwd(self.model.h, argnums=1)(0.0, x0, u0)
        return (lambda s: Ax + 0.0 * s), (lambda s: Cx + 0.0 * s)

    def _jacobian_fns(self, t, xhat, u=None):
        """s ↦ A_o(s), s ↦ C_o(s) of (7) along the nominal, or along the model flow through x̂(t)."""
        f, h = self.model.f, self.model.h
        if self.nominal is not None:

            def xu(s):
                xb, ub = self.nominal(s)
                ub = (
                    jnp.zeros((self.model.p,))
                    if ub is None
                    else jnp.asarray(ub).reshape(self.model.p)
                )
                return jnp.asarray(xb), ub

        else:
            order = 2 * max(self.indices) - 1
            xbar = _flow_polynomial(f, t, xhat, u, order)

            def xu(s):
                return xbar(s), u

        def A(s):
            xb, ub = xu(s)
            return jax.jacfwd(f, argnums=1)(s, xb, ub)

        def C(s):
            xb, ub = xu(s)
            return jax.jacfwd(h, argnums=1)(s, xb, ub)

        return A, C

    def design(self, t, xhat=None, u=None):
        """The full PD-eigenvalue design (:class:`obsjax.design.PDObserverGain`) at time t (and estimate x̂,
        input u when there is no nominal)."""
        t = jnp.asarray(t, dtype=float)
        if self.nominal is None:
            if xhat is None:
                raise ValueError(
                    "`xhat` is needed for the gain along the running estimate (nominal=None)."
                )
            xhat = jnp.asarray(xhat, dtype=float)
            u = (
                self._input_zeros()
                if u is None
                else jnp.asarray(u, dtype=float).reshape(self.model.p)
            )
        A, C = self._jacobian_fns(t, xhat, u)
        return pd_observer_gain(
            A,
            C,
            self.rho_bar,
            self.omega,
            t,
            eps=self.eps,
            indices=self.indices,
            threshold=self.threshold,
            state_scale=None if self.state_scale is None else np.asarray(self.state_scale),
        )

    def gain(self, t, xhat=None, u=None) -> jax.Array:
        """K_o(t), shape (n, m) (multiplies ŷ − y)."""
        d = self.design(t, xhat, u)
        margin = d.form.margin
        ok = margin > self.threshold  # the staircase margin (no tangent: a decision)
        if self.on_unobservable == "nan":
            return jnp.where(ok, d.Ko, jnp.nan)
        # A NaN margin comes from a non-finite estimate or input, not from the pair: the gain is NaN and
        # the integration reports it as a status (so `throw=False` and one bad member of a batch do not
        # abort the study); only a finite margin at or below `threshold` is the loss of observability.
        lost = jnp.isfinite(margin) & ~ok
        return eqx.error_if(
            jnp.where(ok, d.Ko, jnp.nan),
            lost,
            "TrajectoryLinearization: the linearised pair (A_o, C_o) lost strong observability "
            "(the staircase margin of Q_0 fell to `threshold`); the PD-eigenvalue gain is undefined "
            "there.",
        )

    # ------------------------------------------------------------------ observer protocol
    def init(self, t0, xhat0, y0):
        return vector(xhat0, "xhat0", self.model.n)

    def vector_field(self, t, z, y, u):
        K = _gain(self, t, z, u)
        e = self.model.h(t, z, u) - y
        return self.model.f(t, z, u) + jnp.sum(K * e[None, :], axis=1)  # K (ŷ − y), no dot kernel

    def estimate(self, t, z, y):
        return z

    # ------------------------------------------------------------------ solver choice
    def fastest_rate(self, ts=None) -> float | None:
        """max|ρ̄_k| · max ω(t) / ε over `ts` (default t = 0), or ``None`` when a value is traced."""
        ts = np.atleast_1d(np.asarray([0.0] if ts is None else ts, dtype=float))
        w = omega_function(self.omega)
        wv = concrete_value(jnp.stack([jnp.asarray(w(jnp.asarray(s))) for s in ts]))
        rv, ev = concrete_value(self.rho_bar), concrete_value(self.eps)
        if wv is None or rv is None or ev is None:
            return None
        return float(np.max(np.abs(rv)) * np.max(np.abs(wv)) / ev)

    def recommended_solver(self, ts=None) -> diffrax.AbstractSolver:
        """``Kvaerno5()`` (implicit) when the fastest PD-eigenvalue rate max|ρ̄|·ω/ε exceeds ``stiff_rate``
        or cannot be known (traced ε or ω), ``Tsit5()`` otherwise."""
        rate = self.fastest_rate(ts)
        if rate is None or rate > self.stiff_rate:
            return diffrax.Kvaerno5()
        return diffrax.Tsit5()
