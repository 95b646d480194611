"""The LTV observer canonical form by time-varying Lie derivatives (Huang & Zhu (8)-(11)).

For the pair ẋ = A(t) x, y = C(t) x (8), with the differential operators

    𝓛 c = ċ + c A          (row vectors, observability side),
    𝓛̃ q = -q̇ + A q          (column vectors, its dual),

the observability matrix is Q(t) = [Cᵀ, (𝓛C)ᵀ, …, (𝓛ⁿ⁻¹C)ᵀ]ᵀ; the pair is *strongly observable* when
|det Qᵀ(t)Q(t)| ≥ c > 0 for all t.  With observability indices p_1 … p_m (Σ p_i = n, d_i = p_1 + … + p_i),

    Q_0(t) = [Γ_{p_1}(c_1); …; Γ_{p_m}(c_m)],   Γ_p(c) = [c; 𝓛c; …; 𝓛^{p-1}c],
    q_i(t) = Q_0⁻¹(t) e_{d_i},
    T⁻¹(t) = [Γ̃_{p_1}(q_1) | … | Γ̃_{p_m}(q_m)],   Γ̃_p(q) = [q, 𝓛̃q, …, 𝓛̃^{p-1}q],             (10)

and z = T(t) x puts (8) in the observer canonical form (9) with

    A_z = T A T⁻¹ + Ṫ T⁻¹,     C_z = C T⁻¹ = R(t) C_can.                                       (11)

A_z has ones on the sub-diagonal of each p_i × p_i block and its only other non-zero entries in the
columns d_1, …, d_m: column d_i equals T 𝓛̃^{p_i} q_i (this follows from A T⁻¹ − (T⁻¹)˙ = [𝓛̃q …]).
C_can selects the states z_{d_i}; R(t) = C T⁻¹ restricted to those columns is invertible with a unit
diagonal (upper triangular in the lexicographic order of the indices).

Every time derivative (Ċ, Q̇_0, q̇, …) is exact and automatic: the Taylor coefficients of the user's
callables A(t), C(t) are taken by nested forward-mode ``jax.jvp`` in t (C to order 2·max p_i − 1, A one
order less), and everything built from them (the Lie stacks, Q_0⁻¹ by one LU factorisation, the dual
Lie stack) is computed in truncated Taylor-series arithmetic.  This is the same calculation as nested
jvp through Q_0(s)⁻¹, with a traced graph that grows polynomially, not exponentially, with the order
(what keeps the jitted TLO's compile time down).  Nothing is differentiated by hand.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg
import numpy as np

from .._checks import concrete_value
from .._config import require_x64
from ..analysis._lti import DEFAULT_TOL, balancing, lexicographic_step, relative_residuals

#: Default smallest staircase margin of Q_0 for the canonical form (and the PD-eigenvalue gain and the
#: trajectory-linearisation observer built on it).  The form inverts T⁻¹, whose conditioning grows like
#: 1/margin²: the form loses about ε/margin² of its relative accuracy (measured: α off by 0.02–0.03 of
#: ε/margin² against a 50-digit reference on a pair whose outputs approach dependence, e.g. 5e-3 at
#: margin 3e-8 and 234 % at 1.5e-9).  Margins at or below 1e-6 (a loss above about 2e-4) are refused.
CANONICAL_TOL = 1e-6

__all__ = [
    "LTVCanonicalForm",
    "ltv_observability_indices",
    "ltv_observability_matrix",
    "ltv_observer_canonical_form",
    "strong_observability",
]


# --------------------------------------------------------------------------------------------------
# automatic time derivatives
# --------------------------------------------------------------------------------------------------


def _as_time(t) -> jax.Array:
    return jnp.asarray(t, dtype=jnp.result_type(float))


def time_derivatives(fn: Callable, t, order: int) -> jax.Array:
    """[fn(t), fn'(t), …, fn^(order)(t)] stacked on a new leading axis, by nested ``jax.jvp`` in t."""
    t = _as_time(t)

    # level(k)(s) = (fn^(k)(s), (fn(s), …, fn^(k-1)(s))): only the top derivative is differentiated
    # again, the lower ones ride along as auxiliary outputs (no redundant tangents).
    def level(k):
        if k == 0:
            return lambda s: (jnp.asarray(fn(s)), ())
        prev = level(k - 1)

        def g(s):
            val, der, lower = jax.jvp(prev, (s,), (jnp.ones_like(s),), has_aux=True)
            return der, (*lower, val)

        return g

    top, lower = level(order)(t)
    return jnp.stack([*lower, top])


def _taylor(fn: Callable, t, order: int) -> jax.Array:
    """Taylor coefficients [fn(t), fn'(t), fn''(t)/2!, …, fn^(order)(t)/order!] (nested jvp in t)."""
    ders = time_derivatives(fn, t, order)
    fact = np.array([float(np.prod(np.arange(1, k + 1))) for k in range(order + 1)])
    return ders / jnp.asarray(fact, dtype=ders.dtype).reshape((-1,) + (1,) * (ders.ndim - 1))


def _mm(X: jax.Array, Y: jax.Array) -> jax.Array:
    """X @ Y as broadcast-multiply-sum (fuses into one loop; these matrices are n × n with small n)."""
    return jnp.sum(X[:, :, None] * Y[None, :, :], axis=1)


def _smul(X: jax.Array, Y: jax.Array) -> jax.Array:
    """Product of matrix-valued truncated series X (L, a, b), Y (L, b, c): Z_k = Σ_{i+j=k} X_i Y_j."""
    L = X.shape[0]
    k, i = np.meshgrid(np.arange(L), np.arange(L), indexing="ij")
    # Yshift[k, i] = Y_{k−i} (zero for i > k), shape (L, L, b, c)
    Yshift = jnp.where((i <= k)[:, :, None, None], Y[np.maximum(k - i, 0)], 0.0)
    # broadcast-multiply-sum, not a dot: one fusible loop for these tiny matrices
    return jnp.sum(X[None, :, :, :, None] * Yshift[:, :, None, :, :], axis=(1, 3))


def _sderiv(X: jax.Array) -> jax.Array:
    """Series of the time derivative (one order shorter): coefficient k is (k + 1) X_{k+1}."""
    L = X.shape[0]
    return X[1:] * jnp.arange(1, L, dtype=X.dtype).reshape((-1,) + (1,) * (X.ndim - 1))


def _ssolve(M: jax.Array, B: jax.Array) -> jax.Array:
    """Series X with M X = B (M (L, n, n), B (L, n, c)): X_k = M_0⁻¹ (B_k − Σ_{j=1}^{k} M_j X_{k−j}),
    with M_0⁻¹ formed once."""
    M0inv = jnp.linalg.inv(M[0])
    xs = []
    for k in range(M.shape[0]):
        rhs = B[k]
        for j in range(1, k + 1):
            rhs = rhs - _mm(M[j], xs[k - j])
        xs.append(_mm(M0inv, rhs))
    return jnp.stack(xs)


def _lie_stack(A: Callable, C: Callable, depth: int) -> Callable:
    """s ↦ [C, 𝓛C, …, 𝓛^depth C] of shape (depth + 1, m, n); 𝓛c = ċ + cA by nested jvp."""

    def level(k):
        if k == 0:
            return lambda s: jnp.asarray(C(s))[None]
        prev = level(k - 1)

        def g(s):
            vals, ders = jax.jvp(prev, (s,), (jnp.ones_like(s),))
            new = ders[-1] + vals[-1] @ jnp.asarray(A(s))
            return jnp.concatenate([vals, new[None]], axis=0)

        return g

    return level(depth)


# --------------------------------------------------------------------------------------------------
# observability
# --------------------------------------------------------------------------------------------------


def _dims(A: Callable, C: Callable, t) -> tuple[int, int]:
    if not callable(A) or not callable(C):
        raise ValueError(
            "`A` and `C` must be callables of t returning the (n, n) and (m, n) matrices of (8); got "
            f"{type(A).__name__} and {type(C).__name__}."
        )
    sa = jax.eval_shape(A, _as_time(t)).shape
    sc = jax.eval_shape(C, _as_time(t)).shape
    if len(sa) != 2 or sa[0] != sa[1]:
        raise ValueError(f"`A(t)` must return a square (n, n) matrix, got shape {sa}.")
    if len(sc) != 2 or sc[1] != sa[0]:
        raise ValueError(f"`C(t)` must return an (m, {sa[0]}) matrix, got shape {sc}.")
    return sa[0], sc[0]


def _concrete_times(ts, why: str) -> np.ndarray:
    if isinstance(ts, jax.core.Tracer):
        v = concrete_value(ts)
        if v is None:
            raise ValueError(f"`ts` must be concrete ({why}); got a traced value.")
        ts = v
    return np.atleast_1d(np.asarray(ts, dtype=float))


def ltv_observability_matrix(A: Callable, C: Callable, t) -> jax.Array:
    """Observability matrix Q(t) = [C; 𝓛C; …; 𝓛ⁿ⁻¹C] of (8), shape (n·m, n), rows grouped by power of 𝓛.

    **Arguments:** `A`, `C`: callables of t; `t`: the time.

    **Returns:** Q(t), with 𝓛C = Ċ + CA (Huang & Zhu, below (8)) by automatic differentiation.
    """
    n, m = _dims(A, C, t)
    return _lie_stack(A, C, n - 1)(_as_time(t)).reshape(n * m, n)


def output_scales(norms):
    """One scale per output: ‖c_i(t)‖, or the largest ‖𝓛^k c_i‖ when c_i(t) = 0 (1 when all vanish).

    ``norms`` (levels, m): the row norms of [C; 𝓛C; …] at one time (numpy or jax).  Dividing output i's
    rows by it makes the rank decisions independent of the outputs' units (C → S C, S diagonal), which
    the scales ρ_k of :func:`level_scales` alone are not: their max over outputs lets a large output hide
    a small one."""
    xp = jnp if isinstance(norms, jax.Array) else np
    top = xp.max(norms, axis=0)
    s = xp.where(norms[0] > 0, norms[0], top)
    return xp.where(s > 0, s, 1.0)


def level_scales(norms, a_norm):
    """The scales ρ_k of the levels of the lexicographic search: ρ_0 = max_i ‖c_i‖ and
    ρ_k = max(max_i ‖𝓛^k c_i‖, ‖A(t)‖ ρ_{k−1}) (``norms`` (levels, m): the row norms; numpy or jax)."""
    xp = jnp if isinstance(norms, jax.Array) else np
    rho = [xp.max(norms[0])]
    for k in range(1, norms.shape[0]):
        rho.append(xp.maximum(xp.max(norms[k]), a_norm * rho[-1]))
    return xp.stack(rho)


def balance_levels(levels, A0, state_scale=None):
    """The Lie stack and A in balanced state units: (levels·D, D⁻¹A D), D = diag(d) the state scaling of
    :func:`obsjax.analysis.balancing` of the pair (A(t), C(t)) (log-magnitude scaling, then Osborne).

    A change of state units x → S x (S diagonal) maps the rows 𝓛ᵏc_i to 𝓛ᵏc_i S⁻¹ and A to S A S⁻¹; the
    balanced pair does not change, so neither do the rank decisions and the margin taken on it.  Without
    it the level scales ρ_k (built on ‖A‖) moved with the state units: states in units 30 and 900 apart
    made a well-conditioned 4-state pair "rank < 4".  NumPy in, NumPy out; otherwise traced (not
    differentiated: the decisions are not).  Non-finite input is returned as it is.  `state_scale` (n,)
    gives d instead (the state units do not change in time: a caller that evaluates the margin at every
    step of a simulation computes d once, :class:`obsjax.TrajectoryLinearization` at construction)."""
    if state_scale is not None:  # the units given (e.g. once per simulation: they do not change in time)
        levels, A0 = jax.lax.stop_gradient(levels), jax.lax.stop_gradient(A0)
        d = jnp.asarray(state_scale, dtype=jnp.result_type(levels))
    elif isinstance(levels, np.ndarray):
        if not (np.all(np.isfinite(levels)) and np.all(np.isfinite(A0))):
            return levels, A0
        d = np.asarray(balancing(np.asarray(A0, dtype=float), np.asarray(levels[0], dtype=float))[0], dtype=float)
    else:
        levels, A0 = jax.lax.stop_gradient(levels), jax.lax.stop_gradient(A0)
        finite = jnp.all(jnp.isfinite(levels)) & jnp.all(jnp.isfinite(A0))
        d, _ = balancing(jnp.where(finite, A0, 0.0), jnp.where(finite, levels[0], 1.0))
        d = jnp.where(finite & jnp.all(jnp.isfinite(d)) & jnp.all(d > 0), d, 1.0)
    return levels * d[None, None, :], A0 * (d[None, :] / d[:, None])


def _search(Qs: np.ndarray, tol: float, A0: np.ndarray) -> tuple[tuple[int, ...] | None, float]:
    """Lexicographic search c_1, …, c_m, 𝓛c_1, …, 𝓛c_m, … keeping independent rows.

    The rank decisions are those of the LTI staircase (:func:`obsjax.analysis._lti.lexicographic_step`):
    a row is independent when its component outside the rows kept so far exceeds ``tol`` times the
    scale ρ_k of its level (:func:`level_scales`).  Every threshold is relative to its own level, so the
    decisions do not change when time is rescaled (A → cA, 𝓛 → c𝓛) or the outputs are (C → SC, S
    diagonal: each output's rows are first divided by :func:`output_scales`), and the search runs in
    balanced state units (:func:`balance_levels`), so a change of state units does not change them either.

    Returns the indices (``None`` when fewer than n rows are independent) and the staircase margin: the
    smallest kept residual relative to its level's scale (0 when the rank is short)."""
    Qs, A0 = balance_levels(np.asarray(Qs, dtype=float), np.asarray(A0, dtype=float))
    a_norm = float(np.linalg.norm(A0, 2)) if np.all(np.isfinite(A0)) else np.nan
    depth1, m, n = Qs.shape
    Qs = Qs / output_scales(np.linalg.norm(Qs, axis=2))[None, :, None]
    rho = level_scales(np.linalg.norm(Qs, axis=2), a_norm)
    basis: list = []
    alive = [True] * m
    p = [0] * m
    margin = np.inf
    for j in range(depth1):
        if rho[j] == 0.0:
            break
        res = lexicographic_step(basis, Qs[j], alive, [tol * rho[j]] * m)
        for i in range(m):
            if np.any(res[i]):
                p[i] += 1
                margin = min(margin, float(np.linalg.norm(res[i])) / rho[j])
        if len(basis) == n or not any(alive):
            break
    if len(basis) < n:
        return None, 0.0
    return tuple(p), float(margin)


def staircase_margin(levels: jax.Array, A0: jax.Array, indices, state_scale=None) -> jax.Array:
    """The staircase margin of the rows that the indices select, as a traced value (for ``jit``).

    ``levels`` (≥ max p_i, m, n): [C; 𝓛C; …] at one time; ``A0``: A at that time.  The rows 𝓛ʲc_i
    (j < p_i) are taken in the lexicographic order of the search and each one's residual outside those
    before it is divided by its level's scale ρ_j (:func:`level_scales`) --
    :func:`obsjax.analysis._lti.relative_residuals`, the traced twin of the search's decisions.  The
    minimum is 0 where the rows are dependent, and does not change when A → cA, C → dC or the states'
    units change (:func:`balance_levels`).  It is NaN
    when A or the rows are not finite (a non-finite estimate, not a loss of observability)."""
    pmax = max(indices)
    levels, A0 = balance_levels(levels, A0, state_scale)  # state units (stop_gradient inside)
    levels = (levels / output_scales(jnp.linalg.norm(levels, axis=2))[None, :, None])[:pmax]
    rho = level_scales(jnp.linalg.norm(levels, axis=2), jnp.linalg.norm(A0, 2))
    order = [(j, i) for j in range(pmax) for i in range(len(indices)) if j < indices[i]]
    rows = jnp.stack([levels[j, i] for j, i in order])
    scales = jnp.stack([rho[j] for j, _ in order])
    finite = jnp.all(jnp.isfinite(levels)) & jnp.all(jnp.isfinite(A0))
    return jnp.where(finite, jnp.min(relative_residuals(rows, scales)), jnp.nan)  # NaN: not a rank question


def ltv_observability_indices(
    A: Callable, C: Callable, ts, *, tol: float = DEFAULT_TOL
) -> tuple[int, ...]:
    """Observability indices p_1, …, p_m of the LTV pair (8) (fixed lexicographic basis).

    The rows c_1, …, c_m, 𝓛c_1, …, 𝓛c_m, 𝓛²c_1, … are searched in that order and a row is kept when it is
    independent of those kept before; once 𝓛ʲc_i is dependent, output i contributes no further rows.
    p_i is the number of rows kept for output i, Σ p_i = n.  With several times `ts`, the indices must be
    the same at every time (the "fixed lexicographic basis" assumption of Huang & Zhu).

    **Arguments:**

    - `A`, `C`: callables of t returning (n, n) and (m, n) matrices.
    - `ts`: a time or a 1-D array of times (concrete values).
    - `tol`: relative threshold of the independence decisions (the mechanism of the LTI staircase,
      :func:`obsjax.analysis.observability_staircase`): a row is kept when its component outside the
      rows kept before exceeds ``tol`` times the scale of its level (so the indices do not change when
      time or the outputs are rescaled).

    **Returns:** the tuple (p_1, …, p_m).

    Raises ``ValueError`` naming the time where the pair is not observable or where the indices change.

    **Example:**

        ltv_observability_indices(lambda t: A, lambda t: C, 0.0)   # (2, 2) for a generic 4x4, 2-output pair
    """
    require_x64("ltv_observability_indices")
    tsv = _concrete_times(ts, "observability indices are static")
    n, _ = _dims(A, C, tsv[0])
    if not tol > 0:
        raise ValueError(f"`tol` must be > 0, got {tol}.")
    stack = jax.jit(_lie_stack(A, C, n - 1))
    found = None
    for tk in tsv:
        p, _ = _search(np.asarray(stack(_as_time(tk))), tol, np.asarray(A(_as_time(tk)), dtype=float))
        if p is None:
            raise ValueError(
                f"The pair (A, C) is not observable at t = {float(tk):.6g}: the observability matrix "
                f"[C; 𝓛C; …; 𝓛^{n - 1}C] has rank < {n}."
            )
        if found is None:
            found = p
        elif p != found:
            raise ValueError(
                f"The observability indices of (A, C) change at t = {float(tk):.6g}: expected the fixed "
                f"lexicographic basis {found}, found {p}."
            )
    return found


def margin_at(A: Callable, C: Callable, t, indices) -> jax.Array:
    """:func:`staircase_margin` of the rows of Q_0 that `indices` select, at time t."""
    t = _as_time(t)
    return staircase_margin(_lie_stack(A, C, max(indices) - 1)(t), jnp.asarray(A(t)), tuple(indices))


def strong_observability(
    A: Callable, C: Callable, ts, *, threshold: float = DEFAULT_TOL
) -> np.ndarray:
    """Check strong observability of (8) on the times `ts`, scale-invariantly.

    Huang & Zhu call (8) strongly observable when |det Qᵀ(t)Q(t)| ≥ c > 0 for all t (below (8)).  That
    number changes with the units (A → cA multiplies it by a power of c), so the test here is the
    staircase's: at each time the rows of Q(t) are searched in the lexicographic order (the decisions of
    :func:`ltv_observability_indices`, with ``tol = threshold``) and the *staircase margin* is the
    smallest residual of a kept row outside the rows before it, relative to the scale of its level; it
    is 0 where Q(t) has rank < n, lies in (0, 1], and does not change when A → cA or C → dC.

    **Arguments:**

    - `A`, `C`: callables of t.
    - `ts`: 1-D array of (concrete) times.
    - `threshold`: the smallest admissible margin (default 1e-9).

    **Returns:** the staircase margins at `ts` (numpy array).

    Raises ``ValueError`` naming the first time at which the margin is below `threshold`.

    **Example:**

        strong_observability(A, C, jnp.linspace(0, 10, 101))
    """
    require_x64("strong_observability")
    if not threshold > 0:
        raise ValueError(f"`threshold` must be > 0, got {threshold}.")
    tsv = _concrete_times(ts, "the strong-observability check runs before tracing")
    n, _ = _dims(A, C, tsv[0])
    stack = jax.jit(_lie_stack(A, C, n - 1))
    a_of = jax.jit(lambda s: jnp.asarray(A(s), dtype=float))
    margins = np.empty(tsv.shape[0])
    for k, tk in enumerate(tsv):
        Qs = np.asarray(stack(_as_time(tk)))
        A0 = np.asarray(a_of(_as_time(tk)))
        ok = np.all(np.isfinite(Qs)) and np.all(np.isfinite(A0))
        margins[k] = _search(Qs, threshold, A0)[1] if ok else np.nan
        if not margins[k] >= threshold:
            raise ValueError(
                f"The pair (A, C) is not strongly observable: the staircase margin of Q(t) = [C; 𝓛C; …] "
                f"is {margins[k]:.3e} < threshold {threshold:.3e} at t = {tk:.6g}."
            )
    return margins


# --------------------------------------------------------------------------------------------------
# the canonical form
# --------------------------------------------------------------------------------------------------


class LTVCanonicalForm(NamedTuple):
    """The observer canonical form (9)-(11) of an LTV pair at one time.

    Fields: `indices` (p_1, …, p_m); `Q0` (n, n); `Tinv` T⁻¹(t) (n, n); `T` (n, n); `Az` (n, n);
    `Cz` (m, n); `R` (m, m) with C_z = R C_can; `alpha` (n, m): column i is column d_i of A_z, the
    α_{·,i}(t) of (9); `margin`: the staircase margin of the rows of Q_0 (:func:`staircase_margin`;
    0 where they are dependent, a traced value under ``jit``).
    """

    indices: tuple[int, ...]
    Q0: jax.Array
    Tinv: jax.Array
    T: jax.Array
    Az: jax.Array
    Cz: jax.Array
    R: jax.Array
    alpha: jax.Array
    margin: jax.Array


def block_ends(indices) -> tuple[int, ...]:
    """d_i = p_1 + … + p_i (1-based ends of the blocks)."""
    return tuple(int(v) for v in np.cumsum(indices))


def canonical_structure(indices) -> np.ndarray:
    """The constant part of A_can: ones on the sub-diagonal of each p_i × p_i block."""
    n = int(sum(indices))
    S = np.zeros((n, n))
    start = 0
    for p in indices:
        for j in range(1, p):
            S[start + j, start + j - 1] = 1.0
        start += p
    return S


def _check_indices(indices, n: int, m: int) -> tuple[int, ...]:
    try:
        idx = tuple(int(v) for v in indices)
    except TypeError:
        raise ValueError(
            f"`indices` must be a sequence of {m} positive integers, got {indices!r}."
        ) from None
    if len(idx) != m or any(v < 1 for v in idx) or sum(idx) != n:
        raise ValueError(
            f"`indices` must be {m} positive integers summing to n = {n}, got {idx} (sum {sum(idx)})."
        )
    return idx


def ltv_observer_canonical_form(
    A: Callable, C: Callable, t, *, indices=None, threshold: float = CANONICAL_TOL, state_scale=None
) -> LTVCanonicalForm:
    """Transform the LTV pair (8) to the MIMO observer canonical form (9)-(11) at time t (Huang & Zhu).

        T⁻¹(t) = [Γ̃_{p_1}(q_1) | … | Γ̃_{p_m}(q_m)],  q_i = Q_0⁻¹ e_{d_i},                      (10)
        A_z = T A T⁻¹ + Ṫ T⁻¹,  C_z = C T⁻¹ = R C_can.                                         (11)

    **Arguments:**

    - `A`, `C`: callables of t returning A(t) (n, n) and C(t) (m, n); they are differentiated in t by
      ``jax.jvp`` up to order 2·max(p_i) − 1 (so they must be smooth and JAX-traceable).
    - `t`: the time (may be traced under ``jit`` when `indices` is given).
    - `indices`: the observability indices (p_1, …, p_m); computed by
      :func:`ltv_observability_indices` at `t` when ``None`` (then `t` must be concrete).
    - `threshold`: when `t` is concrete, a staircase margin of the rows of Q_0(t) at or below it
      (:func:`staircase_margin`: scale-invariant, 0 for dependent rows) raises ``ValueError`` naming t;
      under ``jit`` the margin is returned in the result for the caller's ``eqx.error_if``.  Default
      ``CANONICAL_TOL`` = 1e-6, not the 1e-9 of the rank decisions: the form inverts T⁻¹, whose
      conditioning grows like 1/margin², and loses about ε/margin² of its relative accuracy (α was off by
      5e-3 at margin 3e-8 and by 234 % at 1.5e-9 on a pair whose outputs approach dependence).  A smaller
      threshold accepts such pairs at that cost.
    - `state_scale`: optional (n,) state scaling of the balanced pair (:func:`balance_levels`) for the
      margin; computed from (A(t), C(t)) when ``None``.

    **Returns:** an :class:`LTVCanonicalForm` (indices, Q0, Tinv, T, Az, Cz, R, alpha).

    **Example:**

        cf = ltv_observer_canonical_form(lambda t: A(t), lambda t: C(t), 0.5)
        cf.Az   # sub-diagonal ones in each block, α columns at d_i
    """
    require_x64("ltv_observer_canonical_form")
    t = _as_time(t)
    n, m = _dims(A, C, t)
    tc = concrete_value(t)
    if indices is None:
        if tc is None:
            raise ValueError(
                "`indices` must be given when `t` is traced (observability indices are static)."
            )
        indices = ltv_observability_indices(A, C, tc)
        zero = [i + 1 for i, p in enumerate(indices) if int(p) == 0]
        if zero:
            raise ValueError(
                f"The observability indices at t = {float(tc):.6g} are {tuple(int(p) for p in indices)}: "
                f"output(s) {zero} add no row independent of the others (p_i = 0), and the canonical form "
                "(9)-(11) needs every p_i ≥ 1; drop the redundant output(s) from C."
            )
    idx = _check_indices(indices, n, m)
    if not threshold > 0:
        raise ValueError(f"`threshold` must be > 0, got {threshold}.")
    pmax = max(idx)
    d = block_ends(idx)
    # Every quantity is carried as a truncated Taylor series in s about t (coefficient k = k-th derivative
    # / k!): C to order K = 2·pmax − 1, A to order K − 1 (nested jvp of the user's callables only), then
    # the Lie stacks, Q_0⁻¹ and the dual Lie stack are series arithmetic (Cauchy products, shifts, one LU).
    # This is the same maths as nested jvp through Q_0(s)⁻¹, but the traced graph is polynomial, not
    # exponential, in the derivative order.
    K = 2 * pmax - 1
    Cs = _taylor(C, t, K)  # (K + 1, m, n)
    As = _taylor(A, t, K - 1)  # (K, n, n)
    lie = [Cs]  # 𝓛ʲC, series of length K + 1 − j
    for _ in range(pmax - 1):
        prev = lie[-1]
        lie.append(_sderiv(prev) + _smul(prev[:-1], As[: prev.shape[0] - 1]))
    margin = staircase_margin(jnp.stack([lv[0] for lv in lie]), As[0], idx, state_scale)
    mc = concrete_value(margin)
    if tc is not None and mc is not None and not np.isfinite(float(mc)):
        raise ValueError(
            f"A(t) or C(t) (or their derivatives) is not finite at t = {float(tc):.6g}: the canonical "
            "form is undefined there."
        )
    if tc is not None and mc is not None and not float(mc) > threshold:
        raise ValueError(
            f"The pair (A, C) is not strongly observable at t = {float(tc):.6g}: the rows of Q_0 "
            f"selected by the indices {idx} have staircase margin {float(mc):.3e} ≤ threshold "
            f"{threshold:.1e} (dependent, or nearly so, relative to their scale: the form would lose about "
            f"ε/margin² = {np.finfo(float).eps / max(float(mc), 1e-300) ** 2:.1e} of its relative accuracy)."
        )
    N = pmax  # q is needed to order pmax (depth of the dual Lie stack)
    Q0s = jnp.stack([lie[j][: N + 1, i] for i in range(m) for j in range(idx[i])], axis=1)
    E = jnp.eye(n)[:, [di - 1 for di in d]]
    qs = _ssolve(Q0s, jnp.broadcast_to(E, (N + 1, n, m)) * (jnp.arange(N + 1) == 0)[:, None, None])
    G = [qs]  # 𝓛̃ᵏq, series of length N + 1 − k
    for _ in range(pmax):
        prev = G[-1]
        G.append(-_sderiv(prev) + _smul(As[: prev.shape[0] - 1], prev[:-1]))
    G = jnp.stack([g[0] for g in G])  # (pmax + 1, n, m): values at t
    Tinv = jnp.concatenate([G[: idx[i], :, i].T for i in range(m)], axis=1)
    T = jnp.linalg.inv(Tinv)
    last = jnp.stack([G[idx[i], :, i] for i in range(m)], axis=1)  # 𝓛̃^{p_i} q_i, (n, m)
    alpha = _mm(T, last)
    Az = jnp.asarray(canonical_structure(idx)).at[:, [di - 1 for di in d]].set(alpha)
    Cz = _mm(Cs[0], Tinv)
    R = Cz[:, [di - 1 for di in d]]
    return LTVCanonicalForm(idx, Q0s[0], Tinv, T, Az, Cz, R, alpha, margin)
