"""Analysis of linear time-varying systems (Chen & Yen 1999, (2)-(7), (16)-(19), Theorem).

All integrals are computed with diffrax (Dopri8, tight tolerances); a plant's declared ``jump_ts`` are passed
to ``ClipStepSizeController`` so piecewise-constant parameters are integrated exactly.

**A note on (4) and the Lemma.**  As printed, (4) references the gramian to the *start* of the window,
W_o(k) = ∫ Φᵀ(τ, kT-T) Cᵀ C Φ(τ, kT-T) dτ over [kT-T, kT] (Rugh's definition).  The observer's regressor on
that window is w_o(τ) = Φᵀ(τ, kT-T) Cᵀ(τ) (12), so the regressor gramian (16) W_o^z(k) = ∫ w_o w_oᵀ is then
*identical* to W_o(k).  The Appendix's identity W_o^z = Φᵀ(kT, kT-T) W_o Φ(kT, kT-T), on which the Lemma's
bound α1 m1² ≤ W_o^z rests, holds for the gramian referenced to the *end* of the window,
W_o^end(k) = ∫ Φᵀ(τ, kT) Cᵀ C Φ(τ, kT) dτ.  With α1 taken from the start-referenced (4) the Lemma can fail
when m1 > 1.  :func:`observability_gramian` therefore offers both references (default: (4) as printed), and
:func:`uniform_observability_constants` / :func:`chen_yen_bound` use the end reference, which makes the
Lemma, and so the Theorem's per-period contraction factor, a valid bound.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value, scalar_value

_RTOL, _ATOL = 1e-10, 1e-12
_SOLVER = diffrax.Dopri8


def _controller(plant, rtol, atol):
    pid = diffrax.PIDController(rtol=rtol, atol=atol)
    jumps = getattr(plant, "jump_ts", None) if plant is not None else None
    if jumps is not None and jnp.size(jnp.asarray(jumps)) > 0:
        return diffrax.ClipStepSizeController(pid, jump_ts=jnp.asarray(jumps, dtype=float))
    return pid


def _solve(rhs, plant, t0, t1, y0, saveat, rtol, atol, max_steps, *, throw=True):
    """The solution's ``ys``; with ``throw=False``, ``(ys, solved)`` (the caller names the failure)."""
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(rhs),
        _SOLVER(),
        t0,
        t1,
        None,
        y0,
        saveat=saveat,
        stepsize_controller=_controller(plant, rtol, atol),
        max_steps=max_steps,
        throw=throw,
    )
    return sol.ys if throw else (sol.ys, sol.result == diffrax.RESULTS.successful)


def _check_plant(plant):
    if not (hasattr(plant, "A_of") and hasattr(plant, "C_of")):
        raise ValueError(
            f"`plant` must be an obsjax.LTV or obsjax.LTI (with A_of, C_of), got {type(plant).__name__}."
        )


@eqx.filter_jit
def _finite_on(plant, ts):
    return jax.vmap(
        lambda s: jnp.all(jnp.isfinite(jnp.asarray(plant.A_of(s))))
        & jnp.all(jnp.isfinite(jnp.asarray(plant.C_of(s))))
    )(ts)


def _probe_plant(plant, a, b, n=65):
    """ValueError naming the first time in [a, b] (a grid of n points, concrete a, b) where A(t) or C(t)
    is not finite: the integration would otherwise use up its step budget and report 'max_steps'."""
    a, b = concrete_value(jnp.asarray(a)), concrete_value(jnp.asarray(b))
    if a is None or b is None:
        return
    ts = jnp.linspace(min(float(a), float(b)), max(float(a), float(b)), n)
    ok = concrete_value(_finite_on(plant, ts))
    if ok is None:  # a traced plant (a vmapped plant family): the solve's own status checks it
        return
    if not ok.all():
        raise ValueError(
            f"A(t) or C(t) of the plant is not finite at t = {float(ts[int(np.argmin(ok))]):.6g}: the "
            "transition matrix and the gramians are undefined there."
        )


def _pos_float(x, name):
    v = scalar_value(x)
    if v is None:
        raise ValueError(f"`{name}` must be a concrete number (not traced), got a tracer.")
    if v.ndim != 0 or np.iscomplexobj(v) or not np.isfinite(v) or v <= 0:
        raise ValueError(f"`{name}` must be a positive finite real scalar, got {v.tolist()}.")
    return float(v)


def _finite_float(x, name):
    """A concrete finite scalar (a time origin), else a ValueError naming it."""
    v = scalar_value(x)
    if v is None:
        raise ValueError(f"`{name}` must be a concrete number (not traced), got a tracer.")
    if v.ndim != 0 or np.iscomplexobj(v) or not np.isfinite(v):
        raise ValueError(f"`{name}` must be a finite scalar (real), got {v.tolist()}.")
    return float(v)


def _threshold(x, name):
    """A concrete finite threshold ≥ 0 (`tol`)."""
    v = _finite_float(x, name)
    if v < 0:
        raise ValueError(f"`{name}` must be ≥ 0, got {v}.")
    return v


def _solver_tolerances(rtol, atol):
    for v, name in ((rtol, "rtol"), (atol, "atol")):
        c = concrete_value(jnp.asarray(v))
        if c is not None and (np.ndim(c) != 0 or not np.isfinite(c) or c <= 0):
            raise ValueError(f"`{name}` must be a positive finite scalar, got {np.asarray(c).tolist()}.")


def _grid_size(n_grid):
    if isinstance(n_grid, bool) or not isinstance(n_grid, (int, np.integer)) or n_grid < 2:
        raise ValueError(f"`n_grid` must be an integer ≥ 2, got {n_grid!r}.")
    return int(n_grid)


def transition_matrix(plant, t, tau, *, rtol=_RTOL, atol=_ATOL, max_steps=65536):
    """State transition matrix Φ(t, τ) of ẋ = A(t)x (Chen & Yen (2), (11)).

    Solves ∂Φ(s, τ)/∂s = A(s) Φ(s, τ), Φ(τ, τ) = I from s = τ to s = t (t < τ integrates backwards).

    **Arguments:**

    - `plant`: an :class:`obsjax.LTV` or :class:`obsjax.LTI` (anything with ``A_of(t)``); its ``jump_ts``
      are stepped onto exactly.
    - `t`, `tau`: scalar times (may be traced; the function works under ``jax.jit`` and ``jax.vmap``,
      also over a plant family, and is differentiable in reverse mode, ``jax.grad``, by diffrax's default
      adjoint; at t = τ its derivatives are ±A(τ)).
    - `rtol`, `atol`, `max_steps`: solver settings (Dopri8).

    **Returns:** the (n, n) matrix Φ(t, τ).

    **Example:**

        Phi = obsjax.analysis.transition_matrix(obsjax.chen_yen_example(), 10.0, 0.0)
    """
    _check_plant(plant)
    _solver_tolerances(rtol, atol)
    t, tau = jnp.asarray(t, dtype=float), jnp.asarray(tau, dtype=float)
    for v, name in ((t, "t"), (tau, "tau")):
        c = concrete_value(v)
        if c is not None and (c.ndim != 0 or not np.isfinite(c)):
            raise ValueError(f"`{name}` must be a finite scalar time, got {c.tolist()}.")
    _probe_plant(plant, t, tau)
    return _transition(plant, t, tau, rtol, atol, max_steps)


@eqx.filter_jit
def _transition(plant, t, tau, rtol, atol, max_steps):
    n = plant.n

    def rhs(s, Phi, args):
        return plant.A_of(s) @ Phi

    eye = jnp.eye(n)
    # traced times: a NaN would give the identity (diffrax returns y0 for a NaN end), so it raises
    t = eqx.error_if(t, ~(jnp.isfinite(t) & jnp.isfinite(tau)), "transition_matrix: `t` and `tau` must be finite.")
    # diffrax refuses t0 == t1 only under some controllers; guard the trivial case.
    same = t == tau
    t_end = jnp.where(same, tau + 1.0, t)
    Phi = _solve(rhs, plant, tau, t_end, eye, diffrax.SaveAt(t1=True), rtol, atol, max_steps)[0]
    # at t = τ the value is I and the derivatives are ∂Φ/∂t = A(τ), ∂Φ/∂τ = −A(τ): the first-order term
    # (zero there) keeps them
    return jnp.where(same, eye + (t - tau) * jnp.asarray(plant.A_of(tau)), Phi)


def _period(plant, a, T, n_grid, rtol, atol, max_steps):
    """Φ(s, a) on a grid of [a, a+T] and G(a+T) = ∫_a^{a+T} Φᵀ(τ, a) Cᵀ C Φ(τ, a) dτ."""
    n = plant.n

    def rhs(s, y, args):
        Phi, _ = y
        w = Phi.T @ plant.C_of(s).T  # regressor w_o(s) of (12)
        return plant.A_of(s) @ Phi, w @ w.T

    ts = a + T * jnp.linspace(0.0, 1.0, n_grid)
    y0 = (jnp.eye(n), jnp.zeros((n, n)))
    save = diffrax.SaveAt(ts=ts)
    (Phis, Gs), ok = _solve(rhs, plant, a, a + T, y0, save, rtol, atol, max_steps, throw=False)
    G = Gs[-1]
    return Phis, 0.5 * (G + G.T), ok


def _periods(plant, starts, T, n_grid, rtol, atol, *, where):
    """For each period start a: (max_s ‖Φ(s, a)‖ on the grid, Φ(a+T, a), W_o^z), each solve checked:
    a ValueError naming `where` (an `eqx.error_if` when traced) if one did not finish."""
    mu, PhiT, Wz, ok = _periods_solve(plant, starts, T, n_grid, rtol, atol)
    message = (
        f"{where}: the solve for Φ(t, t_k) over a period did not finish within 65536 Dopri8 steps. "
        "Either Φ overflows float64 within the period (an unstable mode λ with λT ≳ 700: use a shorter "
        "period T) or A(t) varies too fast for rtol/atol."
    )
    okv = concrete_value(ok)
    if okv is None:
        return eqx.error_if((mu, PhiT, Wz), ~jnp.all(ok), message)
    if not np.all(okv):
        raise ValueError(message)
    return mu, PhiT, Wz


@eqx.filter_jit
def _periods_solve(plant, starts, T, n_grid, rtol, atol):
    """The compiled part of :func:`_periods` — compiled once per plant."""

    def one(a):
        Phis, Wz, ok = _period(plant, a, T, n_grid, rtol, atol, 65536)
        return jnp.max(jnp.linalg.norm(Phis, ord=2, axis=(1, 2))), Phis[-1], Wz, ok

    return jax.vmap(one)(starts)


# The scaled backward solve is stiff where the forward one is (a fast stable mode, normalised away, leaves
# the others decaying at its rate, Ĝ at twice it): a larger budget than the forward solves' 65536 steps.
_END_MAX_STEPS = 262144


def _period_end(plant, b, T, rtol, atol, max_steps):
    """Φ(b − T, b) and W_o^end = ∫_{b−T}^{b} Φᵀ(τ, b) Cᵀ C Φ(τ, b) dτ, in a scaled form that neither
    overflows nor loses the small singular values of Φ(b, b − T) to the absolute tolerance.

    Integrating Φ(s, b) backwards from s = b, its fast stable modes grow like exp(|λ|(b − s)).  The
    solve carries Ψ̂ = Φ(s, b) e^{−ℓ(s)} with ‖Ψ̂‖_F constant, the log-scale ℓ, and Ĝ = G e^{−2ℓ} where
    G(s) = ∫_s^b Φᵀ(τ, b) Cᵀ C Φ(τ, b) dτ:

        dΨ̂/ds = A Ψ̂ − r Ψ̂,   dℓ/ds = r,   dĜ/ds = −2 r Ĝ − (C Ψ̂)ᵀ (C Ψ̂),   r = ⟨Ψ̂, A Ψ̂⟩_F / ‖Ψ̂‖_F²,

    so that Φ(b − T, b) = e^ℓ Ψ̂ and W_o^end = e^{2ℓ} Ĝ at s = b − T, with every solved quantity of order
    one: the solver's tolerances are then relative to each of them.  Returns (ℓ, Ψ̂, Ĝ, ok).
    """
    n = plant.n

    def rhs(s, y, args):
        Psi, _, G = y
        APsi = plant.A_of(s) @ Psi
        r = jnp.sum(Psi * APsi) / jnp.sum(Psi * Psi)
        CPsi = plant.C_of(s) @ Psi
        return APsi - r * Psi, r, -2.0 * r * G - CPsi.T @ CPsi

    y0 = (jnp.eye(n), jnp.zeros(()), jnp.zeros((n, n)))
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(rhs),
        _SOLVER(),
        b,
        b - T,
        None,
        y0,
        saveat=diffrax.SaveAt(t1=True),
        stepsize_controller=_controller(plant, rtol, atol),
        max_steps=max_steps,
        throw=False,
    )
    Psi, ell, G = (v[0] for v in sol.ys)
    return ell, Psi, 0.5 * (G + G.T), sol.result == diffrax.RESULTS.successful


@eqx.filter_jit
def _periods_end(plant, ends, T, rtol, atol):
    """For each period end b: (log σ_max Φ(b − T, b), log λ_max(W_o^end), W_o^end, solved) — see
    :func:`_period_end`; the logarithms stay finite where the values themselves over- or underflow."""

    def one(b):
        ell, Psi, G, ok = _period_end(plant, b, T, rtol, atol, _END_MAX_STEPS)
        log_sv = ell + jnp.log(jnp.linalg.norm(Psi, ord=2))
        ew = jnp.linalg.eigvalsh(G)
        log_ew = 2.0 * ell + jnp.log(ew[-1])
        # the smallest eigenvalue relative to the largest (accurate when W_o^end is well conditioned)
        ratio = jnp.maximum(ew[0], 0.0) / jnp.where(ew[-1] > 0, ew[-1], 1.0)
        return log_sv, log_ew, jnp.exp(2.0 * ell) * G, ok, ratio

    return jax.vmap(one)(ends)


def _end_failed(ok, where, value=None):
    """A ValueError naming `where` when a backward solve did not finish; `value` returned, with an
    ``eqx.error_if`` on `ok` when it is traced (a vmapped plant family)."""
    message = (
        f"{where}: the backward solve for Φ(t_k, t_k + T) and the end-referenced gramian did not "
        f"finish within its step budget ({_END_MAX_STEPS} Dopri8 steps per period) at rtol/atol; a "
        "plant whose A(t) varies this fast needs a shorter period T or looser tolerances."
    )
    okv = concrete_value(ok)
    if okv is None:
        return None if value is None else eqx.error_if(value, ~jnp.all(ok), message)
    if not bool(np.all(okv)):
        raise ValueError(message)
    return value


def _window(k, T, t0):
    if isinstance(k, bool):
        raise ValueError(f"`k` must be an integer >= 1 (window [kT - T, kT]), got {k!r}.")
    kv = k if isinstance(k, (int, np.integer)) else concrete_value(jnp.asarray(k))
    if kv is None:
        raise ValueError("`k` must be a concrete integer >= 1 (not traced).")
    kv = np.asarray(kv)
    if kv.ndim != 0 or not np.isfinite(kv) or kv != np.round(kv) or kv < 1:
        raise ValueError(f"`k` must be an integer >= 1 (window [kT - T, kT]), got {k!r}.")
    return t0 + (int(kv) - 1) * T


def observability_gramian(plant, k, T, *, t0=0.0, reference="start", rtol=_RTOL, atol=_ATOL):
    """Observability gramian W_o(k) of Chen & Yen (4) on the window [t0 + kT - T, t0 + kT].

        reference="start":  W_o(k) = ∫ Φᵀ(τ, kT-T) Cᵀ(τ) C(τ) Φ(τ, kT-T) dτ      ((4) as printed)
        reference="end":    W_o(k) = ∫ Φᵀ(τ, kT)   Cᵀ(τ) C(τ) Φ(τ, kT)   dτ

    The end reference is the one for which the Appendix's identity W_o^z = Φᵀ W_o Φ and the Lemma (16)
    hold (see the module docstring).  The pair is uniformly observable (Definition 1, (3)) when
    α1 I ≤ W_o(k) ≤ α2 I for all k.

    **Arguments:** `plant` (LTV/LTI), `k` (integer ≥ 1), `T` (> 0), `t0` (time origin), `reference`.

    The end-referenced gramian comes from a scaled backward solve of Φ(τ, kT) and is accurate relative to
    its norm.  When a fast stable mode makes it ill-conditioned beyond float64 (cond ≈ e^{2|λ|T}), its
    smallest eigenvalue is not resolved by any float64 matrix: take α1 from
    :func:`uniform_observability_constants`, which computes it from the forward quantities.

    **Returns:** the symmetric (n, n) matrix W_o(k).

    **Example:**

        W = obsjax.analysis.observability_gramian(obsjax.chen_yen_example(), k=1, T=2.0)
    """
    _check_plant(plant)
    _solver_tolerances(rtol, atol)
    T = _pos_float(T, "T")
    t0 = _finite_float(t0, "t0")
    if reference not in ("start", "end"):
        raise ValueError(f"`reference` must be 'start' or 'end', got {reference!r}.")
    a = _window(k, T, t0)
    _probe_plant(plant, a, a + T)
    if reference == "start":
        a_ = _pad(jnp.asarray([a]))
        return _periods(plant, a_, jnp.asarray(T), 2, rtol, atol, where="observability_gramian")[2][0]
    # Φ(kT − T, kT) by a scaled backward solve (not inv(Φ(kT, kT − T)): the small singular values of
    # Φ(kT, kT − T) are lost to the absolute tolerance when a fast stable mode decays over the window)
    log_sv, _, W, ok, _ = _periods_end(plant, _pad(jnp.asarray([a + T])), jnp.asarray(T), rtol, atol)
    log_sv, W, ok = log_sv[0], W[0], ok[0]
    okv, Wv = concrete_value(ok), concrete_value(W)
    if okv is None:
        return eqx.error_if(W, ~ok, "observability_gramian(reference='end'): the backward solve failed.")
    _end_failed(okv, "observability_gramian(reference='end')")
    if not np.all(np.isfinite(Wv)):
        raise ValueError(
            "observability_gramian(reference='end'): W_o(k) = ∫ Φᵀ(τ, kT) Cᵀ C Φ(τ, kT) dτ overflows: "
            "Φ(kT − T, kT) = Φ(kT, kT − T)⁻¹ grows like exp(−λ T) for a fast stable mode λ "
            f"(‖Φ(kT − T, kT)‖ = 10^{float(log_sv) / np.log(10):.1f}). Use a shorter window T or "
            "reference='start'."
        )
    return W


def regressor_gramian(plant, k, T, *, t0=0.0, rtol=_RTOL, atol=_ATOL):
    """Gramian of the observer's regressor, W_o^z(k) of Chen & Yen (16).

        W_o^z(k) = ∫_{kT-T}^{kT} w_o(τ) w_o(τ)ᵀ dτ,     w_o(τ) = Φᵀ(τ, kT-T) Cᵀ(τ)   (12).

    It is the increment of P⁻¹/γ of the least-squares observer over one period (proof of the Theorem),
    and equals Φᵀ(kT, kT-T) W_o^end(k) Φ(kT, kT-T) (Appendix).

    **Returns:** the symmetric (n, n) matrix W_o^z(k).

    **Example:**

        Wz = obsjax.analysis.regressor_gramian(obsjax.chen_yen_example(), k=1, T=0.25)
    """
    _check_plant(plant)
    _solver_tolerances(rtol, atol)
    T = _pos_float(T, "T")
    a = _window(k, T, _finite_float(t0, "t0"))
    a_ = _pad(jnp.asarray([a]))
    return _periods(plant, a_, jnp.asarray(T), 2, rtol, atol, where="regressor_gramian")[2][0]


class UniformObservability(NamedTuple):
    """Per-period constants of Chen & Yen on the periods [t_k, t_k + T), t_k = t0 + kT.

    - `t_start`: (K,) period starts.
    - `mu`: (K,) max over the period of ‖Φ(t, t_k)‖ (2) (sampled on `n_grid` points, ends included).
    - `alpha1`, `alpha2`: (K,) extreme eigenvalues of the (end-referenced) gramian W_o of the period (3).
    - `m1`, `m2`: (K,) extreme singular values of Φ(t_k + T, t_k) (17).
    - `eta1`, `eta2`: (K,) extreme eigenvalues of the regressor gramian W_o^z (16), i.e. the PE
      constants (7) of w_o.

    The paper's constants are the extremes over k: μ = max mu, α1 = min alpha1, m1 = min m1, etc.

    m1 = 1/‖Φ(t_k, t_k + T)‖ and α2 come from a scaled backward solve; α1 from the backward W_o^end, or as
    1/λ_max(Φ_T (W_o^z)⁻¹ Φ_Tᵀ) from the forward solve where W_o^z is the better conditioned of the two, so
    that each is accurate relative to itself even when a fast stable mode makes W_o^end ill-conditioned
    beyond float64 (m1 = e^{−100} is returned as 3.7e-44, not at the absolute
    tolerance); m1 is 0 and α2 is ∞ only where the exact values lie outside float64's range.
    """

    t_start: jax.Array
    mu: jax.Array
    alpha1: jax.Array
    alpha2: jax.Array
    m1: jax.Array
    m2: jax.Array
    eta1: jax.Array
    eta2: jax.Array


def _pad(starts):
    # pad the batch of periods to a power of two so that changing the horizon or T rarely recompiles
    K = starts.shape[0]
    size = max(64, 1 << (K - 1).bit_length())
    return jnp.concatenate([starts, jnp.full((size - K,), starts[-1])])


def _n_periods(T, horizon):
    K = int(np.floor(horizon / T + 1e-9))
    if K < 1:
        raise ValueError(f"`horizon` ({horizon}) must hold at least one period T = {T}.")
    return K


def uniform_observability_constants(
    plant, T, horizon, *, t0=0.0, n_grid=129, rtol=_RTOL, atol=_ATOL
) -> UniformObservability:
    """The constants μ (2), α1, α2 (3), m1, m2 (17) and η1, η2 (16) of each period in a horizon.

    The periods are [t0 + kT, t0 + (k+1)T) for k = 0 … K-1, K = ⌊horizon / T⌋.  μ is the maximum of
    ‖Φ(t, kT)‖ over `n_grid` equally spaced points of the period.  α1, α2 bound the gramian referenced to
    the end of the period (see the module docstring), so that α1 m1² ≤ η1 (Lemma) holds.

    **Arguments:** `plant` (LTV/LTI), `T` (> 0), `horizon` (> 0, ≥ T), `t0`, `n_grid` (≥ 2).

    **Returns:** :class:`UniformObservability` with (K,) arrays.

    **Example:**

        c = obsjax.analysis.uniform_observability_constants(obsjax.chen_yen_example(), 0.25, 10.0)
        mu, alpha1, m1 = c.mu.max(), c.alpha1.min(), c.m1.min()
    """
    _check_plant(plant)
    _solver_tolerances(rtol, atol)
    T = _pos_float(T, "T")
    horizon = _pos_float(horizon, "horizon")
    n_grid = _grid_size(n_grid)
    K = _n_periods(T, horizon)
    starts = _finite_float(t0, "t0") + T * jnp.arange(K, dtype=float)
    _probe_plant(plant, starts[0], starts[0] + K * T, n=max(65, 8 * K + 1))

    where = "uniform_observability_constants"
    # the gramians are integrated for C/(σ√T), σ the largest entry of C(t) on a probe grid, and scaled
    # back by σ²T: `atol` is then relative to their size (absolute, it was at the level of the answer for
    # outputs in units 1e4 times larger, or time in ms: α1 came out 1.2e-4 and 7.3e-3 too large)
    probe = starts[0] + (K * T) * np.linspace(0.0, 1.0, 33)
    g2 = (_probe_scale(lambda t: plant.C_of(t), probe) ** 2) * T
    scaled = _ScaledOutput(plant, float(np.sqrt(g2)))
    mu, PhiT, Wz = _periods(scaled, _pad(starts), jnp.asarray(T), n_grid, rtol, atol, where=where)
    mu, PhiT, Wz = mu[:K], PhiT[:K], Wz[:K] * g2
    log_sv, log_ew, _, ok, ratio = _periods_end(scaled, _pad(starts + T), jnp.asarray(T), rtol, atol)
    log_ew = log_ew + np.log(g2)
    log_sv = _end_failed(ok[:K], "uniform_observability_constants", log_sv)
    # m1 = 1/‖Φ(t_k, t_k + T)‖ and α2 = λ_max(W_o^end) from the scaled backward solve: forward, the small
    # singular values of Φ(t_k + T, t_k) sit at the absolute tolerance (a mode e^{−50·2} gave 3e-14
    # for 4e-44).  exp rounds them to 0 or ∞ only where float64 cannot hold them.
    m1, alpha2 = jnp.exp(-log_sv[:K]), jnp.exp(log_ew[:K])
    m2 = jnp.linalg.norm(PhiT, ord=2, axis=(1, 2))
    # α1 = λ_min(W_o^end) two ways, each accurate where its matrix is well conditioned: from the backward
    # W_o^end itself (its error ~ tol·α2), or as 1/λ_max(Φ_T (W_o^z)⁻¹ Φ_Tᵀ) (Appendix: W_o^z =
    # Φ_Tᵀ W_o^end Φ_T), a largest eigenvalue of forward quantities (its error ~ tol·cond W_o^z): a fast
    # stable mode makes W_o^end ill-conditioned, an unstable one W_o^z.  The better conditioned one is used.
    ez, U = jnp.linalg.eigh(Wz)
    inv_sqrt = jnp.where(ez > 0, 1.0 / jnp.sqrt(jnp.where(ez > 0, ez, 1.0)), jnp.inf)
    s_max = jnp.linalg.norm((PhiT @ U) * inv_sqrt[:, None, :], ord=2, axis=(1, 2))
    alpha1_fwd = jnp.where(ez[:, 0] > 0, 1.0 / s_max**2, 0.0)
    ratio = ratio[:K]
    alpha1_end = ratio * alpha2
    inv_cond_z = jnp.maximum(ez[:, 0], 0.0) / jnp.where(ez[:, -1] > 0, ez[:, -1], 1.0)
    alpha1 = jnp.where(ratio >= inv_cond_z, alpha1_end, alpha1_fwd)
    return UniformObservability(starts, mu, alpha1, alpha2, m1, m2, ez[:, 0], ez[:, -1])


def chen_yen_bound(plant, gamma, p0, T, horizon, *, t0=0.0, n_grid=129) -> jax.Array:
    """Contraction factor of Chen & Yen's Theorem for each period of a horizon.

        ‖x̃(t_k + T)‖ ≤ ρ_k ‖x̃(t_k)‖,      ρ_k = μ_k / (1 + γ p0 α1_k m1_k²)      ((19)-(22))

    with μ_k, α1_k, m1_k of the period [t_k, t_k + T) from :func:`uniform_observability_constants`.  The
    Theorem's hypothesis is ρ_k < 1 for all k; then ‖x̃(t_K)‖ ≤ Π ρ_k ‖x̃(t0)‖ (22).

    **Arguments:** `plant` (the observer's model), `gamma`, `p0`, `T` (> 0), `horizon`, `t0`, `n_grid`.

    **Returns:** (K,) array of ρ_k, K = ⌊horizon / T⌋.

    **Example:**

        rho = obsjax.analysis.chen_yen_bound(obsjax.chen_yen_example(), 20.0, 0.1, 0.25, 10.0)
    """
    g = _pos_float(gamma, "gamma")
    p = _pos_float(p0, "p0")
    c = uniform_observability_constants(plant, T, horizon, t0=t0, n_grid=n_grid)
    return c.mu / (1.0 + g * p * c.alpha1 * c.m1**2)


@dataclasses.dataclass(frozen=True)
class PersistentExcitation:
    """Result of :func:`is_persistently_exciting`: ``bool(result)`` is `excited`.

    - `excited`: η1 > tol·η2, i.e. (7) holds on every window of the horizon.
    - `eta1`, `eta2`: smallest and largest eigenvalue of ∫ w wᵀ over the windows (7).
    - `per_window`: (K, 2) array of (λ_min, λ_max) per window.
    """

    excited: bool
    eta1: float
    eta2: float
    per_window: np.ndarray

    def __bool__(self):
        return bool(self.excited)


def is_persistently_exciting(w, T, horizon, *, t0=0.0, tol=1e-9, jump_ts=None, rtol=_RTOL, atol=_ATOL):
    """Persistent excitation (Chen & Yen Definition 2, (7)) of a regressor over a horizon.

        η1 I ≤ ∫_{kT-T}^{kT} w(τ) wᵀ(τ) dτ ≤ η2 I     for every window in [t0, t0 + horizon].

    **Arguments:**

    - `w`: a callable t -> (n, m) (or (n,)) regressor, or an LTV/LTI plant, in which case the observer's
      regressor w_o = Φᵀ(t, kT) Cᵀ(t) of (12) is used (the Lemma: uniform observability ⇒ PE).
    - `T`: window length (> 0); `horizon`: total time (K = ⌊horizon / T⌋ windows); `t0`: origin.
    - `tol`: the verdict: η̂1 > `tol`·η̂2, where η̂1, η̂2 are the bounds (7) of the equilibrated gramians
      S⁻¹ G_k S⁻¹, S = diag(max_k G_k)^{1/2} (one S for all windows).  Excitation is a property of the
      directions the regressor spans, not of its components' units: the verdict does not change when
      w is replaced by D w for any invertible diagonal D (components in other units), which the raw
      ratio η1/η2 does (components in units spanning 1e±3 read 1e-12 for a regressor that excites
      every direction).  The returned η1, η2 are those of the raw gramians.  A callable regressor is
      integrated with each component divided by its largest value on a probe grid (and multiplied
      back), so `atol` is relative to each component's scale; a plant's regressor with the largest
      entry of C(t).
    - `jump_ts`: for a callable `w`, the times where it is discontinuous (pulses, switches, a sampled
      signal's knots).  The integrator steps onto each, so a pulse shorter than its steps is not stepped
      over: without them, a regressor that is zero but for pulses of width 1e-4 was called not exciting
      (η1 = 0).  A plant declares its own ``jump_ts``.

    **Returns:** :class:`PersistentExcitation` (truthy when exciting) with η1, η2 and per-window values.

    **Example:**

        pe = obsjax.analysis.is_persistently_exciting(lambda t: jnp.array([jnp.sin(t), jnp.cos(t)]),
                                                      T=2 * jnp.pi, horizon=20.0)
        assert pe and abs(pe.eta1 - jnp.pi) < 1e-8
    """
    _solver_tolerances(rtol, atol)
    T = _pos_float(T, "T")
    horizon = _pos_float(horizon, "horizon")
    tol = _threshold(tol, "tol")
    t0 = _finite_float(t0, "t0")
    K = _n_periods(T, horizon)
    starts = t0 + T * jnp.arange(K, dtype=float)
    probe = t0 + (K * T) * np.linspace(0.0, 1.0, 33)
    breaks = _jump_times(jump_ts, "jump_ts")
    if breaks is not None:
        inside = np.sort(breaks[(breaks >= t0) & (breaks <= t0 + K * T)])
        # the value at each break and between consecutive ones (a pulse's height enters the scale)
        probe = np.concatenate([probe, inside, 0.5 * (inside[1:] + inside[:-1])])
    if hasattr(w, "A_of") and hasattr(w, "C_of"):
        _probe_plant(w, t0, t0 + K * T, n=max(65, 8 * K + 1))
        if breaks is not None:
            raise ValueError(
                "`jump_ts` is for a callable regressor; a plant declares its discontinuities as its own "
                "`jump_ts` (e.g. obsjax.LTV(A, C, jump_ts=...))."
            )
        sigma = _probe_scale(lambda t: w.C_of(t), probe) * np.sqrt(T)  # the gramians' size: ‖C‖²T
        scaled, where = _ScaledOutput(w, sigma), "is_persistently_exciting"
        Gs = _periods(scaled, _pad(starts), jnp.asarray(T), 2, rtol, atol, where=where)[2][:K]
        Gs = Gs * sigma**2

    elif callable(w):
        try:
            w0 = jnp.asarray(w(jnp.asarray(float(t0))))
        except Exception as e:  # noqa: BLE001
            raise ValueError(
                f"`w` must be a callable of t returning an (n, m) array; it failed: {e}"
            )
        if w0.ndim not in (1, 2):
            raise ValueError(
                f"`w(t)` must return an (n,) or (n, m) array, got shape {tuple(w0.shape)}."
            )
        n = w0.shape[0]
        sigma = _probe_row_scale(lambda t: jnp.asarray(w(t)).reshape(n, -1), probe)  # (n,)

        def wm(t):
            return jnp.asarray(w(t)).reshape(n, -1) / sigma[:, None]

        def gram(a):
            def rhs(s, G, args):
                ws = wm(s)
                return ws @ ws.T

            G = _solve(
                rhs, _Breaks(breaks), a, a + T, jnp.zeros((n, n)), diffrax.SaveAt(t1=True), rtol, atol,
                65536,
            )[0]
            return 0.5 * (G + G.T)

        Gs = jax.jit(jax.vmap(gram))(starts) * (sigma[:, None] * sigma[None, :])
    else:
        raise ValueError(
            f"`w` must be a callable of t or an LTV/LTI plant, got {type(w).__name__}."
        )

    Gs = np.asarray(Gs)
    eig = np.linalg.eigvalsh(Gs)
    per = np.stack([eig[:, 0], eig[:, -1]], axis=1)
    eta1, eta2 = float(per[:, 0].min()), float(per[:, 1].max())
    # the verdict on the Jacobi-equilibrated gramians (one scaling for all windows): invariant to the
    # units of the regressor's components; a component that is zero on every window is not excited
    d = np.sqrt(np.max(np.maximum(np.diagonal(Gs, axis1=1, axis2=2), 0.0), axis=0))
    if not np.all(d > 0.0):
        return PersistentExcitation(False, eta1, eta2, per)
    eq = np.linalg.eigvalsh(Gs / d[None, :, None] / d[None, None, :])
    excited = bool(eta2 > 0.0 and eq[:, 0].min() > tol * eq[:, -1].max())
    return PersistentExcitation(excited, eta1, eta2, per)


class _Breaks(NamedTuple):
    """Declared discontinuities of a callable (read by :func:`_controller` as a plant's ``jump_ts``)."""

    jump_ts: Any


def _jump_times(jump_ts, name):
    """`jump_ts` as a finite 1-D float64 numpy array, or None."""
    if jump_ts is None:
        return None
    v = concrete_value(jnp.asarray(jump_ts, dtype=float))
    if v is None:
        raise ValueError(f"`{name}` must be concrete times (not traced), got a tracer.")
    v = np.asarray(v, dtype=float).reshape(-1) if np.ndim(v) <= 1 else None
    if v is None or not np.all(np.isfinite(v)):
        raise ValueError(f"`{name}` must be a 1-D sequence of finite times, got {np.asarray(jump_ts).tolist()}.")
    return np.sort(v) if v.size else None


class _ScaledOutput(eqx.Module):
    """A plant whose output map is divided by `scale` (the gramian scales by 1/scale²)."""

    plant: Any
    scale: Any  # a leaf: one compilation serves every scale

    @property
    def n(self):
        return self.plant.n

    @property
    def jump_ts(self):  # the plant's discontinuities, where the solves step
        return getattr(self.plant, "jump_ts", None)

    def A_of(self, t):
        return self.plant.A_of(t)

    def C_of(self, t):
        return self.plant.C_of(t) / self.scale


def _probe_rows(fn, times) -> np.ndarray:
    """Per row i of fn(t) (an (n,) or (n, m) array), the largest |entry| over `times`; ``ValueError`` naming
    the first time where fn is not finite."""
    def rows(t):
        a = np.abs(np.asarray(fn(jnp.asarray(float(t)))))
        return np.max(a.reshape(a.shape[0] if a.ndim else 1, -1), axis=1)

    vals = np.stack([rows(t) for t in times])
    bad = ~np.all(np.isfinite(vals), axis=1)
    if bad.any():
        raise ValueError(
            f"The regressor (or the plant's C(t)) is not finite at t = {float(times[int(np.flatnonzero(bad)[0])]):.6g}: "
            "its gramians are undefined."
        )
    return np.max(vals, axis=0)


def _probe_row_scale(fn, times) -> jnp.ndarray:
    """Per row i, the largest |entry| of row i of fn(t) over `times` (the units of each component of a
    regressor); 1 for a row that is 0 there.  Non-finite values are refused (:func:`_probe_rows`)."""
    vals = _probe_rows(fn, times)
    return jnp.asarray(np.where(vals > 0.0, vals, 1.0))


def _probe_scale(fn, times) -> float:
    """The largest |entry| of fn(t) over `times` (a regressor's or an output map's units); 1 when that is
    0.  Non-finite values are refused (:func:`_probe_rows`)."""
    big = float(np.max(_probe_rows(fn, times), initial=0.0))
    return big if big > 0.0 else 1.0


def decay_rate(trajectory, *, t_min=None, t_max=None, floor=1e-12):
    """Exponential decay rate λ of ‖x̃(t)‖ ≈ c e^{-λ t}, by least squares on log ‖x̃‖.

    **Arguments:**

    - `trajectory`: an :class:`obsjax.Trajectory` (uses ``ts`` and ``error``) or a pair ``(ts, error)``
      with error of shape (T, n) (or (T,) of norms already).
    - `t_min`, `t_max`: fit window (default: the whole trajectory).
    - `floor`: samples with ‖x̃‖ ≤ floor · max ‖x̃‖ (the largest in the window: converged to round-off)
      are left out of the fit.  Relative, so the error's units do not matter.

    **Returns:** scalar λ (positive for a decaying error); jit/vmap compatible and differentiable (also in
    the times).  A window with fewer than two usable samples at distinct times, a non-finite error sample
    in the window (a failed trajectory: its rate is not known) or a non-finite time raises ``ValueError``
    eagerly and gives NaN traced; complex values are refused (fit the modulus).

    **Example:**

        lam = obsjax.analysis.decay_rate(traj, t_min=2.0)
    """
    if isinstance(trajectory, tuple):
        ts, err = trajectory
    else:
        ts, err = trajectory.ts, trajectory.error
    for v, name in ((ts, "ts"), (err, "error")):
        if jnp.iscomplexobj(v):
            raise ValueError(
                f"`{name}` must be real, got complex values (pass the norms |x̃| to fit the rate of the modulus)."
            )
    ts = jnp.asarray(ts, dtype=float)
    err = jnp.asarray(err, dtype=float)
    if ts.ndim != 1:
        raise ValueError(f"`ts` must be a 1-D array of times, got shape {tuple(ts.shape)}.")
    if ts.shape[0] < 2:
        raise ValueError(f"decay_rate needs at least 2 samples, got {ts.shape[0]}.")
    if err.ndim not in (1, 2) or err.shape[0] != ts.shape[0]:
        raise ValueError(
            f"`error` must have {ts.shape[0]} rows (one per time), shape (T, n) or (T,), got shape {err.shape}."
        )
    ts_c = concrete_value(ts)
    if ts_c is not None and not np.all(np.isfinite(ts_c)):
        i = int(np.flatnonzero(~np.isfinite(ts_c))[0])
        raise ValueError(f"`ts` must hold finite times, got {ts_c[i]!r} at sample {i}.")
    fl = concrete_value(jnp.asarray(floor))
    if fl is not None and not (np.ndim(fl) == 0 and np.isfinite(fl) and 0.0 <= float(fl) < 1.0):
        raise ValueError(
            f"`floor` must be a finite scalar in [0, 1) (relative to the largest error in the window), got "
            f"{np.asarray(fl).tolist()}."
        )
    for v, name in ((t_min, "t_min"), (t_max, "t_max")):
        c = None if v is None else concrete_value(jnp.asarray(v))
        if c is not None and not (np.ndim(c) == 0 and np.isfinite(c)):
            raise ValueError(f"`{name}` must be a finite time, got {np.asarray(c).tolist()}.")
    if t_min is not None and t_max is not None and not float(t_min) < float(t_max):
        raise ValueError(f"`t_min` must be < `t_max`, got t_min = {t_min}, t_max = {t_max}.")
    nrm = jnp.linalg.norm(err, axis=-1) if err.ndim == 2 else jnp.abs(err)
    window = jnp.ones(ts.shape, bool)
    if t_min is not None:
        window = window & (ts >= t_min)
    if t_max is not None:
        window = window & (ts <= t_max)
    finite = jnp.isfinite(nrm)
    bad = jnp.any(window & ~finite) | ~jnp.all(jnp.isfinite(ts))
    top = jnp.max(jnp.where(window & finite, nrm, 0.0))
    mask = window & finite & (nrm > floor * top)
    used, bad_c = concrete_value(mask), concrete_value(bad)
    if bad_c is not None and bool(bad_c):
        where_bad = np.flatnonzero(np.asarray(concrete_value(window & ~finite)))  # ts is finite here
        raise ValueError(
            f"decay_rate: the error is not finite at t = {float(ts_c[where_bad[0]]):g} (sample "
            f"{int(where_bad[0])}) in the fit window: a failed trajectory (check its status), whose decay "
            "rate is not known; fit a window before it, or drop the trajectory."
        )
    if used is not None and ts_c is not None:
        t_used = ts_c[np.asarray(used)]
        if np.unique(t_used).size < 2:
            raise ValueError(
                f"decay_rate needs at least 2 samples at distinct times with ‖x̃‖ > floor·max ‖x̃‖ "
                f"(floor = {floor:g}) in the fit window [t_min, t_max] = [{t_min}, {t_max}], got "
                f"{t_used.size} sample(s) at {np.unique(t_used).size} time(s) (an error already at "
                "round-off, or a window outside the trajectory)."
            )
    wgt = mask.astype(float)
    logn = jnp.log(jnp.where(mask, nrm, 1.0))
    sw = jnp.sum(wgt)
    tbar = jnp.sum(wgt * ts) / sw
    lbar = jnp.sum(wgt * logn) / sw
    slope = jnp.sum(wgt * (ts - tbar) * (logn - lbar)) / jnp.sum(wgt * (ts - tbar) ** 2)
    return jnp.where(bad, jnp.nan, -slope)
