"""Morgan–Narendra uniform asymptotic stability and richness conditions (Hassan thesis, (4.20)-(4.21)).

The error equations of the adaptive observers of chapter 4 are linear, homogeneous and non-autonomous,

    (i)  ẋ = −B(t) Bᵀ(t) x,          (ii)  [ẋ; ẏ] = [[A, −Bᵀ(t)], [B(t), 0]] [x; y],

(4.21): (i) is the identifier (4.2) (B = Γ^{1/2} α) and (ii) the scalar error system (4.20)
(A = −K, B = −[√γ₁ x_p; √γ₂ u]) and the output-error laws (4.17)-(4.19).  Morgan and Narendra's conditions
for their uniform asymptotic stability are richness conditions on B(t):

- (i): ∫_{t0}^{t} ‖B(τ)Bᵀ(τ) w‖ dτ ≥ a (t − t0) + b for every unit w, a > 0;
- (ii): there are t_0, ε_0, δ_0 > 0 such that for every t_1 ≥ 0 and unit w some t_2 ∈ [t_1, t_1 + t_0] has
  ‖∫_{t_2}^{t_2+δ_0} Bᵀ(τ) w dτ‖ ≥ ε_0.

:func:`morgan_narendra` computes constants for which both hold over a given horizon, from window gramians
(so its verdict is the persistence-of-excitation test of :func:`obsjax.analysis.is_persistently_exciting`),
and the exponential rate of (i) (exact per window, and a bound from the gramians).
"""

from __future__ import annotations

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._ltv import _ATOL, _RTOL, _Breaks, _finite_float, _jump_times, _n_periods, _pos_float, _solve, _solver_tolerances, _threshold


@dataclasses.dataclass(frozen=True)
class MorganNarendra:
    """Result of :func:`morgan_narendra`; ``bool(result)`` is `uniform`.

    - `uniform`: the richness verdict: λ_min of every window gramian ∫ B Bᵀ exceeds `tol` · `eta2`
      (scale-invariant), so (4.21) (i) and (ii) are uniformly asymptotically stable.
    - `eta1`, `eta2`: smallest and largest eigenvalue of the window gramians ∫_{window} B Bᵀ dτ (the η1, η2
      of the persistence-of-excitation test).
    - `a`, `b`: constants of condition (i), ∫_{t0}^{t} ‖B Bᵀ w‖ dτ ≥ a (t − t0) + b for every unit w and
      every t0 ≤ t in the horizon: a = eta1 / T, b = −2 eta1.
    - `epsilon0`, `delta0`, `search_window`: constants of condition (ii) (ε_0, δ_0, and the thesis's t_0 =
      2T): every window [t_1, t_1 + 2T] in the horizon holds a t_2 with ‖∫_{t_2}^{t_2+δ_0} Bᵀ w‖ ≥ ε_0.
    - `rate`: the exponential rate σ of (i) on the horizon, σ = −ln(max_k ‖Φ_k‖₂)/T from the transition
      matrices Φ_k of ẋ = −B Bᵀ x over the windows: ‖x(t)‖ ≤ ‖x(s)‖ e^{−σ (t − s − T)} for s on the window
      grid (‖x‖ never increases in between); 0 when not uniform.
    - `rate_bound`: the rate guaranteed by the gramians alone, σ_G = min_k −ln(1 − 2λ_min(G_k)/(1 + ‖G_k‖_F)²)
      / (2T) ≤ `rate` (see :func:`morgan_narendra`).
    - `direction`: the unit w of least excitation (eigenvector of λ_min of the worst window).
    - `per_window`: (K, 5) array: λ_min and λ_max of ∫ B Bᵀ, ε_0, σ and σ_G for each window.
    """

    uniform: bool
    eta1: float
    eta2: float
    a: float
    b: float
    epsilon0: float
    delta0: float
    search_window: float
    rate: float
    rate_bound: float
    direction: np.ndarray
    per_window: np.ndarray

    def __bool__(self):
        return bool(self.uniform)


def morgan_narendra(
    B, T, horizon, *, delta0=None, t0=0.0, tol=1e-9, jump_ts=None, rtol=_RTOL, atol=_ATOL
) -> MorganNarendra:
    """Morgan–Narendra richness of a regressor B(t) over a horizon (thesis (4.20)-(4.21)).

    The horizon [t0, t0 + horizon] is cut into K = ⌊horizon / T⌋ windows of length T.  On each window
    the gramian G_k = ∫ B Bᵀ dτ and the gramian of the moving integral M(τ) = ∫_τ^{τ+δ0} B(s) ds,
    H_k = ∫ M Mᵀ dτ, are integrated with diffrax (Dopri8, tolerances `rtol`, `atol`).  Then:

    - (i): ‖B Bᵀ w‖ ≥ wᵀ B Bᵀ w for unit w, so every whole window adds at least η1 = min_k λ_min(G_k) to
      the integral of (i): a = η1 / T, b = −2 η1.
    - (ii): the maximum of ‖M(τ)ᵀ w‖ over a window is at least its root mean square, so
      ε_0 = min_k (λ_min(H_k) / T)^{1/2}; any [t_1, t_1 + 2T] holds a whole window (t_0 = 2T).
      (A δ0 equal to a period of B can hide its excitation: ε_0 then vanishes although η1 > 0.)
    - rates of (i): the transition matrix Φ_k of ẋ = −B Bᵀ x over each window gives the exact worst-case
      contraction, `rate` = −ln(max_k ‖Φ_k‖₂)/T.  From the gramians alone: with I = ∫‖Bᵀx‖² over a window
      (‖x(s)‖² − ‖x(s + T)‖² = 2I) and x(τ) − x(s) = −∫_s^τ B Bᵀ x, Cauchy–Schwarz gives
      ∫‖Bᵀ(τ)(x(τ) − x(s))‖² ≤ I ‖G_k‖_F², so λ_min(G_k)‖x(s)‖² ≤ I (1 + ‖G_k‖_F)² and
      ‖x(s + T)‖² ≤ (1 − 2λ_min(G_k)/(1 + ‖G_k‖_F)²)‖x(s)‖²: `rate_bound` ≤ `rate`.

    The verdict `uniform` is η1 > `tol` · η2, the persistence-of-excitation condition (Chen & Yen (7)),
    which is necessary and sufficient for the uniform asymptotic stability of (i), and of (ii) for a
    bounded B and A with the structure of (4.20).

    **Arguments:**

    - `B`: a callable t -> (n,) or (n, m) array (a regressor; (n,) is read as (n, 1)).  A sampled signal can
      be passed as ``diffrax.LinearInterpolation(ts, values).evaluate``.
    - `T`: window length (> 0); `horizon`: analysed time (K = ⌊horizon / T⌋ ≥ 1 windows); `t0`: origin.
    - `delta0`: δ_0 of (ii) (default T / 4).
    - `tol`: relative threshold of the verdict (and of ε_0 > 0).
    - `jump_ts`: the times where B is discontinuous (pulses, switches, a sampled signal's knots); the
      integrator steps onto each (and onto each less δ0, for the moving integral), so a pulse shorter than
      its steps is not stepped over.

    **Returns:** a :class:`MorganNarendra`.

    **Example:**

        mn = obsjax.analysis.morgan_narendra(lambda t: jnp.array([jnp.sin(t), jnp.cos(t)]),
                                             T=2 * jnp.pi, horizon=20.0, delta0=1.0)
        assert mn and abs(mn.a - 0.5) < 1e-8                 # λ_min ∫₀^{2π} = π
        assert abs(mn.epsilon0 - 2 ** 0.5 * np.sin(0.5)) < 1e-8
    """
    _solver_tolerances(rtol, atol)
    T = _pos_float(T, "T")
    horizon = _pos_float(horizon, "horizon")
    t0 = _finite_float(t0, "t0")
    tol = _threshold(tol, "tol")
    delta0 = T / 4.0 if delta0 is None else _pos_float(delta0, "delta0")
    K = _n_periods(T, horizon)
    n, m = _signal_shape(B, float(t0))
    probe = float(t0) + K * T * np.linspace(0.0, 1.0, 65)
    vals = np.asarray(jax.vmap(lambda s: _matrix(B, s, n, m))(jnp.asarray(probe)))
    bad = ~np.all(np.isfinite(vals), axis=(1, 2))
    if bad.any():
        raise ValueError(
            f"`B(t)` must be finite over the horizon; it is not at t = {probe[np.argmax(bad)]:g} (a non-finite "
            "regressor would exhaust the integrator's step budget before failing)."
        )
    starts = float(t0) + T * jnp.arange(K, dtype=float)
    breaks = _jump_times(jump_ts, "jump_ts")
    if breaks is not None:
        breaks = jnp.asarray(np.unique(np.concatenate([breaks, breaks - delta0])))
    Gs, Hs, contraction = _windows(
        B, starts, jnp.asarray(T), jnp.asarray(delta0), n, m, rtol, atol, breaks
    )
    evals, evecs = np.linalg.eigh(np.asarray(Gs))
    lam_min, lam_max = evals[:, 0], evals[:, -1]
    h = np.linalg.eigvalsh(np.asarray(Hs))
    eps = np.where(h[:, 0] > tol * h[:, -1], np.sqrt(np.clip(h[:, 0], 0.0, None) / T), 0.0)
    eta1, eta2 = float(lam_min.min()), float(lam_max.max())
    uniform = bool(eta2 > 0 and eta1 > tol * eta2)
    frob = np.linalg.norm(np.asarray(Gs), axis=(1, 2))
    frac = 2.0 * np.clip(lam_min, 0.0, None) / (1.0 + frob) ** 2
    sigma_bound = -np.log1p(-np.minimum(frac, 0.5)) / (2.0 * T)
    contraction = np.asarray(contraction)
    sigma = -np.log(np.clip(contraction, 1e-300, None)) / T
    worst = int(np.argmin(lam_min))
    return MorganNarendra(
        uniform=uniform,
        eta1=eta1,
        eta2=eta2,
        a=max(eta1, 0.0) / T,
        b=-2.0 * max(eta1, 0.0),
        epsilon0=float(eps.min()),
        delta0=float(delta0),
        search_window=2.0 * T,
        rate=float(sigma.min()) if uniform else 0.0,
        rate_bound=float(sigma_bound.min()) if uniform else 0.0,
        direction=evecs[worst, :, 0],
        per_window=np.stack([lam_min, lam_max, eps, sigma, sigma_bound], axis=1),
    )


def _matrix(B, t, n, m):
    return jnp.asarray(B(t), dtype=float).reshape(n, m)


@eqx.filter_jit
def _windows(B, starts, T, delta0, n, m, rtol, atol, breaks=None):
    """Per window: ∫ B Bᵀ, ∫ M Mᵀ (M(τ) = ∫_τ^{τ+δ0} B) and ‖Φ‖₂ of ẋ = −B Bᵀ x (one compilation per
    structure of B: a module with array leaves is traced once)."""

    def window(s):
        lead0 = _solve(
            lambda tau, c, args: _matrix(B, tau, n, m),
            _Breaks(breaks),
            s,
            s + delta0,
            jnp.zeros((n, m)),
            diffrax.SaveAt(t1=True),
            rtol,
            atol,
            65536,
        )[0]

        def rhs(tau, state, args):
            lag, lead, _, _, Phi = state
            b = _matrix(B, tau, n, m)
            M = lead - lag
            bbT = b @ b.T
            return b, _matrix(B, tau + delta0, n, m), bbT, M @ M.T, -bbT @ Phi

        y0 = (jnp.zeros((n, m)), lead0, jnp.zeros((n, n)), jnp.zeros((n, n)), jnp.eye(n))
        _, _, G, H, Phi = _solve(
            rhs, _Breaks(breaks), s, s + T, y0, diffrax.SaveAt(t1=True), rtol, atol, 65536
        )
        return 0.5 * (G[0] + G[0].T), 0.5 * (H[0] + H[0].T), jnp.linalg.norm(Phi[0], 2)

    return jax.vmap(window)(starts)


def _signal_shape(B, t0):
    """(n, m) of B(t), read at t0 ((n,) counts as (n, 1))."""
    if not callable(B):
        raise ValueError(  # noqa: TRY004 (bad input is a ValueError throughout obsjax)
            f"`B` must be a callable of t returning an (n,) or (n, m) array, got {type(B).__name__}."
        )
    try:
        b0 = jnp.asarray(B(jnp.asarray(t0)))
    except Exception as e:  # noqa: BLE001
        raise ValueError(
            f"`B` must be a callable of t returning an (n, m) array; it failed: {e}"
        ) from None
    if b0.ndim not in (1, 2):
        raise ValueError(
            f"`B(t)` must return an (n,) or (n, m) array, got shape {tuple(b0.shape)}."
        )
    return b0.shape[0], 1 if b0.ndim == 1 else b0.shape[1]
