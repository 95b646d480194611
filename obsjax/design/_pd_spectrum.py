"""PD-eigenvalue assignment for LTV observers (Huang & Zhu (12)-(14), (21)-(23); Zhu's synthesis formula).

A PD-spectrum {ρ_k(t)} of an n-th order scalar LTV operator is a set of functions such that
y_k = exp(∫ρ_k dt) is a fundamental set of solutions.  With 𝒟_ρ{f} = ḟ + ρ f, the PD-modal matrix is
V_n = [𝒟_{ρ_j}^{i-1}{1}]_{ij}; the companion-form (LPDO) coefficients of

    y⁽ⁿ⁾ + α_n(t) y⁽ⁿ⁻¹⁾ + … + α_1(t) y = 0,    A(t, dt) = [[0, 1, …], …, [-α_1, …, -α_n]]

follow from the synthesis formula α_k = ṽ_{k,n+1} / det V_n (ṽ the cofactors of V_{n+1}(ρ_1, …, ρ_n, ρ)),
i.e. α V_n = -[𝒟_{ρ_1}ⁿ{1}, …, 𝒟_{ρ_n}ⁿ{1}] (Cramer's rule).  For ρ_k(t) = ρ̄_k ω(t) the modal matrix factors
as V_n = V̂_n(ω) V̄_n(ρ̄) (21), V̄ the Vandermonde matrix of ρ̄ and V̂ lower triangular with

    v̂_11 = 1,  v̂_ij = v̂˙_{i-1,j} + ω v̂_{i-1,j-1}                                        (21)-(23)

(the dot is missing in the printed recursion; the 4th-order example shows it).  High gain: ω_H = ω/ε.

The observer canonical form (9) realises the right PDO (12), so the LPDO coefficients are converted to
RPDO coefficients β (13) with δⁿ + Σ δ^{k-1}∘β_k = δⁿ + Σ α_k δ^{k-1}; the time derivatives of α needed
there are taken by automatic differentiation, as are all derivatives of ω.
"""

from __future__ import annotations

from collections.abc import Callable
from math import comb
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array, concrete_value
from .._config import require_x64
from ._ltv_canonical import (
    CANONICAL_TOL,
    LTVCanonicalForm,
    _as_time,
    _mm,
    ltv_observer_canonical_form,
    time_derivatives,
)

__all__ = [
    "PDObserverGain",
    "RampBandwidth",
    "pd_coefficients",
    "pd_modal_matrix",
    "pd_observer_gain",
    "rpdo_coefficients",
]


class RampBandwidth(eqx.Module):
    """A smooth time-varying bandwidth ω(t) = ω_1 + (ω_0 − ω_1) exp(−t/τ).

    Starting the observer at a low bandwidth ω_0 and raising it to ω_1 limits peaking while keeping the
    small steady-state error of a high bandwidth (Huang & Zhu, Remark 2).  All three are array leaves, so
    they can be tuned.

    **Example:** ``TrajectoryLinearization(model, [-1., -2.], RampBandwidth(0.5, 4.0, 1.0), eps=0.2)``
    """

    omega0: jax.Array
    omega1: jax.Array
    tau: jax.Array

    def __init__(self, omega0, omega1, tau):
        self.omega0 = as_float_array(omega0, "omega0")
        self.omega1 = as_float_array(omega1, "omega1")
        self.tau = as_float_array(tau, "tau")
        for v, name in ((self.omega0, "omega0"), (self.omega1, "omega1"), (self.tau, "tau")):
            if v.ndim != 0:
                raise ValueError(f"`{name}` must be a scalar, got shape {tuple(v.shape)}.")
            c = concrete_value(v)
            if c is not None and not c > 0:
                raise ValueError(f"`{name}` must be > 0, got {float(c)}.")

    def __call__(self, t):
        return self.omega1 + (self.omega0 - self.omega1) * jnp.exp(-t / self.tau)


def omega_function(omega, name: str = "omega") -> Callable:
    """A callable t ↦ ω(t) from a positive constant or a callable."""
    if callable(omega):
        return omega
    w = as_float_array(omega, name)
    if w.ndim != 0:
        raise ValueError(
            f"`{name}` must be a positive scalar or a callable of t, got shape {tuple(w.shape)}."
        )
    c = concrete_value(w)
    if c is not None and not (np.isfinite(c) and c > 0):
        raise ValueError(f"`{name}` must be finite and > 0 (a bandwidth), got {float(c)}.")
    return lambda t: w + jnp.zeros_like(t)


#: the smallest relative gap min|ρ̄_i − ρ̄_j| / max|ρ̄| of nominal PD-eigenvalues (the synthesis solves the
#: Vandermonde system V̄(ρ̄), whose error grows like the rounding unit over the gap)
RHO_BAR_MIN_GAP = 1e-8


def rho_bar_too_close(r):
    """True when two entries of r are closer than RHO_BAR_MIN_GAP·max|r| (NumPy or traced)."""
    xp = np if isinstance(r, np.ndarray) else jnp
    if r.shape[0] < 2:
        return xp.asarray(False)
    gap = xp.abs(r[:, None] - r[None, :]) + xp.where(xp.eye(r.shape[0], dtype=bool), xp.inf, 0.0)
    return xp.min(gap) <= RHO_BAR_MIN_GAP * xp.max(xp.abs(r))


def guard_bandwidth(omega_fn: Callable, t, result, name: str = "omega"):
    """`result`, refused unless the bandwidth ω(t) is a finite positive scalar: ``ValueError`` when ω(t)
    is concrete, ``eqx.error_if`` when it is traced (a callable ω is not checked at construction: a ramp
    that turns negative before t = 0, or a tuned leaf, would otherwise place ρ̄ω with the wrong sign,
    an unstable observer reported as a success)."""
    wt = jnp.asarray(omega_fn(t))
    if wt.ndim != 0:
        raise ValueError(f"`{name}(t)` must be a scalar (a bandwidth), got shape {tuple(wt.shape)}.")
    c = concrete_value(wt)
    if c is not None:
        if not (np.isfinite(c) and c > 0):
            raise ValueError(
                f"`{name}` must be a finite bandwidth > 0 wherever it is used, got {float(c)} at "
                f"t = {float(concrete_value(jnp.asarray(t)))}."
            )
        return result
    return eqx.error_if(
        result,
        ~(jnp.isfinite(wt) & (wt > 0)),
        f"`{name}` (the bandwidth) must be finite and > 0 wherever it is used: the PD-spectrum ρ̄_k·ω(t) "
        "would have the wrong sign or be undefined.",
    )


def check_rho_bar(
    rho_bar, name: str = "rho_bar", *, negative: bool = False, distinct: bool = True
) -> jax.Array:
    """Validate nominal PD-eigenvalues: a real 1-D vector (of distinct values, negative, if asked)."""
    r = as_float_array(rho_bar, name)
    if r.ndim == 0:
        r = r.reshape(1)
    if r.ndim != 1 or r.shape[0] == 0:
        raise ValueError(
            f"`{name}` must be a non-empty 1-D vector of real numbers, got shape {tuple(r.shape)}."
        )
    if jnp.issubdtype(r.dtype, jnp.complexfloating):
        raise ValueError(f"`{name}` must be real (PD-spectrum ρ_k = ρ̄_k ω(t)), got complex values.")
    c = concrete_value(r)
    if c is not None:
        if not np.all(np.isfinite(c)):
            raise ValueError(f"`{name}` must be finite (no NaN or inf), got {c.tolist()}.")
        if negative and not np.all(c < 0):
            raise ValueError(f"`{name}` must be < 0 (a stable PD-spectrum ρ̄ ω(t) of the observer or controller), got {c.tolist()}.")
        if distinct and bool(rho_bar_too_close(np.asarray(c, dtype=float))):
            raise ValueError(
                f"`{name}` must hold distinct values, at least {RHO_BAR_MIN_GAP:g}·max|ρ̄| apart (the "
                "Vandermonde matrix V̄(ρ̄) of (21) is solved: with values 1e-14 apart the coefficients "
                f"were 6 % off), got {c.tolist()}."
            )
        return r
    # traced (jit, vmap, a tuned leaf): the same value checks at run time
    r = eqx.error_if(r, ~jnp.all(jnp.isfinite(r)), f"`{name}` must be finite (no NaN or inf).")
    if negative:
        r = eqx.error_if(r, jnp.any(~(r < 0)), f"`{name}` must be < 0 (a stable PD-spectrum ρ̄ ω(t) of the observer or controller).")
    if distinct:
        r = eqx.error_if(
            r,
            rho_bar_too_close(r),
            f"`{name}` must hold distinct values, at least {RHO_BAR_MIN_GAP:g}·max|ρ̄| apart (the "
            "Vandermonde matrix V̄(ρ̄) of (21) is solved).",
        )
    return r


def check_time(t, what: str) -> jax.Array:
    """t as a float array; a traced t must be finite at run time (``eqx.error_if``; a NaN time would
    give a NaN gain).  A concrete non-finite t is left to the caller's own eager check."""
    t = _as_time(t)
    if concrete_value(t) is None:
        t = eqx.error_if(t, ~jnp.isfinite(t), f"{what}: the time `t` must be finite.")
    return t


def _vhat(omega_fn: Callable, N: int) -> Callable:
    """s ↦ V̂_N(ω)(s), the N × N lower-triangular matrix of (21)-(23), by nested jvp in s."""

    def level(k):
        if k == 1:
            return lambda s: jnp.zeros((1, N), dtype=s.dtype).at[0, 0].set(1.0)
        prev = level(k - 1)

        def g(s):
            rows, drows = jax.jvp(prev, (s,), (jnp.ones_like(s),))
            shifted = jnp.concatenate([jnp.zeros(1, dtype=s.dtype), rows[-1, :-1]])
            new = drows[-1] + omega_fn(s) * shifted
            return jnp.concatenate([rows, new[None]], axis=0)

        return g

    return level(N)


def _modal(rho_bar, omega, t):
    rho_bar = check_rho_bar(rho_bar)
    n = rho_bar.shape[0]
    t = _as_time(t)
    Vh = _vhat(omega_function(omega), n + 1)(t)  # (n+1, n+1)
    Vbar_ext = rho_bar[None, :] ** jnp.arange(n + 1)[:, None]  # (n+1, n): powers 0..n
    return _mm(Vh, Vbar_ext)  # rows 0..n-1: V_n; row n: 𝒟ⁿ_{ρ_j}{1}


def pd_modal_matrix(rho_bar, omega, t) -> jax.Array:
    """PD-modal matrix V_n(t) = V̂_n(ω) V̄_n(ρ̄) of the PD-spectrum ρ_k(t) = ρ̄_k ω(t) (Huang & Zhu (21)).

    **Arguments:** `rho_bar` (n,) distinct nominal PD-eigenvalues; `omega` a positive constant or a callable
    of t (derivatives by autodiff); `t` the time.

    **Returns:** V_n(t), (n, n), with entries 𝒟_{ρ_j}^{i-1}{1}.

    **Example:** ``pd_modal_matrix([-1., -2.], 3.0, 0.0)`` is ``[[1, 1], [-3, -6]]``.
    """
    require_x64("pd_modal_matrix")
    M = _modal(rho_bar, omega, t)
    return guard_bandwidth(omega_function(omega), _as_time(t), M[:-1])


def pd_coefficients(rho_bar, omega, t) -> jax.Array:
    """Companion-form coefficients α_1 … α_n synthesised from the PD-spectrum ρ_k(t) = ρ̄_k ω(t).

        α_k(t) = ṽ_{k,n+1}(t) / det V_n(ρ_1(t), …, ρ_n(t)),    V_n = V̂_n(ω) V̄_n(ρ̄)      (Huang & Zhu, Lemma; (21))

    so that y⁽ⁿ⁾ + α_n y⁽ⁿ⁻¹⁾ + … + α_1 y = 0, i.e. ẋ = A(t, dt) x with A = [[0, 1, …], …, [−α_1, …, −α_n]],
    has the fundamental solutions exp(∫ρ_k dt).  For n = 2: α_1 = ρ̄_1ρ̄_2ω², α_2 = −(ρ̄_1 + ρ̄_2)ω − ω̇/ω.
    Scaling ω → ω/ε scales α_k by ε^{−(n−k+1)} (with time scaled by ε when ω varies; the Lemma).

    **Arguments:**

    - `rho_bar`: (n,) distinct real nominal PD-eigenvalues ρ̄_k.
    - `omega`: the bandwidth: a positive constant or a callable t ↦ ω(t) (ω̇, ω̈, … by automatic
      differentiation, so the callable must be smooth and JAX-traceable).
    - `t`: the time.

    **Returns:** α = (α_1, …, α_n), shape (n,).

    **Example:**

        pd_coefficients(jnp.array([-1.0, -2.0]), 3.0, 0.0)   # [18., 9.]: s² + 9s + 18 = (s + 3)(s + 6)
    """
    require_x64("pd_coefficients")
    M = _modal(rho_bar, omega, t)
    V, last = M[:-1], M[-1]
    return guard_bandwidth(omega_function(omega), _as_time(t), -jnp.linalg.solve(V.T, last))


def _rpdo_map(n: int) -> np.ndarray:
    """B[k, r, j]: β_{k+1} = Σ_{r,j} B[k, r, j] α_{j+1}^{(r)} for δⁿ + Σ δ^{k-1}∘β_k = δⁿ + Σ α_k δ^{k-1}.

    Operator composition (Leibniz): δ^{k-1}∘β = Σ_i C(k-1, i) β^{(k-1-i)} δ^i, so matching the coefficient
    of δ^i gives α_{i+1} = Σ_{k>i} C(k-1, i) β_k^{(k-1-i)}, solved from k = n downwards.
    """
    B = np.zeros((n, n, n))
    for i in range(n - 1, -1, -1):  # β_{i+1}
        B[i, 0, i] = 1.0
        for k in range(i + 2, n + 1):  # β_k, 1-based
            shift = k - 1 - i
            c = comb(k - 1, i)
            B[i, shift:, :] -= c * B[k - 1, : n - shift, :]
    return B


def rpdo_coefficients(rho_bar, omega, t) -> jax.Array:
    """Right-PDO coefficients β (13) of the operator whose PD-spectrum is ρ_k(t) = ρ̄_k ω(t).

        D_β = δⁿ + δ^{n-1}∘β_n + … + δ∘β_2 + β_1  =  δⁿ + α_n δ^{n-1} + … + α_1          (12)-(13)

    with α from :func:`pd_coefficients`; the time derivatives of α are taken by automatic differentiation.
    For constant ω, β = α.  The observer-canonical block with last column −β (sub-diagonal ones, output
    its last state) then has the output modes exp(∫ρ_k dt).

    **Arguments:** as :func:`pd_coefficients`.  **Returns:** β = (β_1, …, β_n), shape (n,).

    **Example:** ``rpdo_coefficients([-1., -2.], lambda t: 2 + jnp.sin(t), 0.3)``
    """
    require_x64("rpdo_coefficients")
    rho_bar = check_rho_bar(rho_bar)
    n = rho_bar.shape[0]
    if n == 1:
        return pd_coefficients(rho_bar, omega, t)
    omega_function(omega)  # validate
    # dalpha[r, j] = α_{j+1}^{(r)}(t)
    dalpha = time_derivatives(lambda s: pd_coefficients(rho_bar, omega, s), t, n - 1)
    return jnp.sum(jnp.asarray(_rpdo_map(n)) * dalpha[None], axis=(1, 2))


class PDObserverGain(NamedTuple):
    """Result of :func:`pd_observer_gain`: `Ko` (n, m) in the original coordinates, `Kz` (n, m) in the
    canonical coordinates (K_z = T K_o), `beta` (n,) the RPDO coefficients per block (concatenated), and
    `form` the :class:`~obsjax.design.LTVCanonicalForm`."""

    Ko: jax.Array
    Kz: jax.Array
    beta: jax.Array
    form: LTVCanonicalForm


def pd_observer_gain(
    A: Callable, C: Callable, rho_bar, omega, t, *, eps=1.0, indices=None, threshold: float = CANONICAL_TOL,
    state_scale=None,
) -> PDObserverGain:
    """Observer gain K_o(t) by PD-eigenvalue assignment (Huang & Zhu, Step (b), (12)-(14)).

    For the observer x̂˙ = A x̂ + K_o (ŷ − y), the error obeys ẋ̃ = (A + K_o C) x̃.  In the canonical
    coordinates of (10)-(11), with C_z = R C_can, the gain K_z = K̃ R⁻¹ where column i of K̃ cancels every
    coupling column α_{·,i} and places the RPDO coefficients of block i (14):

        k̃_{d_{s-1}+k, i} = −β_{k,i} − α_{d_{s-1}+k, i}  (s = i),     −α_{d_{s-1}+k, i}  (s ≠ i),

    (the printed (14) writes +β with the sign of (13) absorbed into β); then K_o = T⁻¹ K_z.  The closed
    loop A_z + K_z C_z is block diagonal, block i in observer form with last column −β_{·,i}, whose
    PD-spectrum is {ρ̄_k ω(t)/ε : k in block i}.

    **Arguments:**

    - `A`, `C`: callables of t (the Jacobians A_o(t), C_o(t) of (7) for the TLO).
    - `rho_bar`: (n,) nominal PD-eigenvalues, split over the output blocks in order (p_1 for output 1, …),
      real, finite and distinct within each block (checked eagerly, and with ``eqx.error_if`` under
      ``jit``).  Like :func:`~obsjax.design.place`, any sign is assigned: ρ̄_k > 0 gives a growing error
      mode (:class:`~obsjax.TrajectoryLinearization` requires ρ̄ < 0).
    - `omega`: bandwidth, positive constant or callable of t.
    - `t`: the time (may be traced when `indices` is given).
    - `eps`: high-gain factor, ω_H = ω/ε (22)-(23).
    - `indices`, `threshold`, `state_scale`: as :func:`ltv_observer_canonical_form`.

    **Returns:** :class:`PDObserverGain` (Ko, Kz, beta, form).

    **Example:**

        K = pd_observer_gain(A, C, jnp.array([-1., -2., -3.]), 2.0, 0.0).Ko
    """
    require_x64("pd_observer_gain")
    t = check_time(t, "pd_observer_gain")
    form = ltv_observer_canonical_form(A, C, t, indices=indices, threshold=threshold, state_scale=state_scale)
    idx = form.indices
    n = form.Tinv.shape[0]
    # distinct within each block (checked per block below)
    rho_bar = check_rho_bar(rho_bar, distinct=False)
    if rho_bar.shape[0] != n:
        raise ValueError(
            f"`rho_bar` must have n = {n} entries (split as {idx}), got {rho_bar.shape[0]}."
        )
    w = omega_function(omega)
    eps = as_float_array(eps, "eps")
    if eps.ndim != 0:
        raise ValueError(f"`eps` (the high-gain factor) must be a scalar, got shape {tuple(eps.shape)}.")
    ce = concrete_value(eps)
    if ce is not None and not (np.isfinite(ce) and ce > 0):
        raise ValueError(f"`eps` (the high-gain factor) must be finite and > 0, got {float(ce)}.")
    if ce is None:
        eps = eqx.error_if(
            eps, ~(jnp.isfinite(eps) & (eps > 0)), "`eps` (the high-gain factor) must be finite and > 0."
        )

    def omega_H(s):
        return w(s) / eps

    betas = []
    cols = []
    start = 0
    for i, p in enumerate(idx):
        beta_i = rpdo_coefficients(rho_bar[start : start + p], omega_H, t)
        target = jnp.zeros(n, dtype=beta_i.dtype).at[start : start + p].set(-beta_i)
        cols.append(target - form.alpha[:, i])
        betas.append(beta_i)
        start += p
    Ktil = jnp.stack(cols, axis=1)
    Kz = jnp.linalg.solve(form.R.T, Ktil.T).T
    Ko = _mm(form.Tinv, Kz)
    return PDObserverGain(Ko, Kz, jnp.concatenate(betas), form)
