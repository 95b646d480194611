"""Trajectory linearization control (TLC): the controller that the trajectory linearization observer serves
(Huang & Zhu, Section II.A, Fig. 1-2, (15)-(17), (24)-(28), Remark 2).

Two parts, as in the paper's Fig. 1:

1. the nominal trajectory (ξ̄(t), μ̄(t)) of (2) from a nominal output η̄(t) by dynamic inversion
   (:func:`dynamic_inversion`, for input-affine plants of full relative degree; :meth:`NominalTrajectory.
   from_state` when a feasible nominal state is known);
2. the tracking-error state feedback μ̃ = K(t) ξ̃ (15) designed on the linearisation (4)
   A_c(t) = ∂f/∂ξ, B_c(t) = ∂f/∂μ along the nominal, by PD-eigenstructure assignment
   (:func:`pd_controller_gain`), applied to the estimate: μ̃ = K(t) ξ̃̂ (17), with the control saturated
   against the observer's peaking (Remark 2) (:class:`TrajectoryLinearizationController`).

**The PD-eigenstructure assignment for the controller, by duality.**  Observability of the pair
(Ā(s), C̄(s)) = (A(−s)ᵀ, B(−s)ᵀ) at s = −t is controllability of (A, B) at t: the Lie derivative
𝓛̄c = dc/ds + c Ā of a row c(s) = b(−s)ᵀ is (−ḃ + A b)(−s)ᵀ, the operator 𝓛̃ of (8)-(10) that builds the
controllability matrix.  So the observer canonical form (9)-(11) of the dual pair,
z̄ = T̄(s) x̄, Ā_z = T̄ĀT̄⁻¹ + T̄'T̄⁻¹, C̄_z = C̄T̄⁻¹, gives the LTV *controller* canonical form of (A, B):

    x = M(t) z_c,   M(t) = T̄(−t)ᵀ,   A_c = M⁻¹ A M − M⁻¹ Ṁ = Ā_z(−t)ᵀ,   B_c = M⁻¹ B = C̄_z(−t)ᵀ,

i.e. one companion block per input with ones on the super-diagonal and free last rows, and B_c non-zero
only in the last row d_i of each block (a unit lower-triangular R_cᵀ).  Block i is the scalar operator
z^{(p_i)} + α_{p_i} z^{(p_i−1)} + … + α_1 z of its first coordinate: a *left* PDO, whose coefficients
for the PD-spectrum {ρ̄_k ω(t)} come straight from the synthesis formula (:func:`pd_coefficients`; no
conversion to the right PDO as for the observer, (12)-(13)).  The gain K_c cancels every coupling row
and places those coefficients; K = K_c M⁻¹.  Then the closed loop A + BK is, in z_c, block diagonal with
the assigned PD-spectra, and the tracking error of (16) decays with modes exp(ρ̄_k ∫ω dt).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array, concrete_value, vector
from .._config import require_x64
from ..analysis._lti import DEFAULT_TOL, relative_residuals
from ..systems._plants import AbstractSystem
from ._ltv_canonical import (
    _as_time,
    _check_indices,
    _mm,
    ltv_observability_indices,
    ltv_observer_canonical_form,
    margin_at,
    time_derivatives,
)
from ._pd_spectrum import check_rho_bar, check_time, omega_function, pd_coefficients

__all__ = [
    "NominalTrajectory",
    "PDControllerGain",
    "TrajectoryLinearizationController",
    "dynamic_inversion",
    "ltv_controllability_indices",
    "pd_controller_gain",
]


# --------------------------------------------------------------------------------------------------
# the controller canonical form by duality, and the PD-eigenstructure gain
# --------------------------------------------------------------------------------------------------


def _dual(A: Callable, B: Callable):
    """(s ↦ A(−s)ᵀ, s ↦ B(−s)ᵀ): observability of the dual pair at −t is controllability at t."""
    return (lambda s: jnp.asarray(A(-s)).T), (lambda s: jnp.asarray(B(-s)).T)


def ltv_controllability_indices(A: Callable, B: Callable, ts) -> tuple[int, ...]:
    """Controllability indices (p_1, …, p_l) of the LTV pair (A(t), B(t)), fixed lexicographic basis.

    The observability indices of the dual pair (A(−s)ᵀ, B(−s)ᵀ) at s = −t
    (:func:`obsjax.design.ltv_observability_indices`): the columns b_1, …, b_l, 𝓛̃b_1, …, 𝓛̃b_l, … with
    𝓛̃b = −ḃ + A b, searched in that order.  Raises ``ValueError`` where the pair is not controllable or the
    indices change.

    **Example:** ``ltv_controllability_indices(lambda t: A, lambda t: B, [0.0, 1.0])``
    """
    Ad, Cd = _dual(A, B)
    ts = -np.atleast_1d(np.asarray(ts, dtype=float))
    try:
        return ltv_observability_indices(Ad, Cd, ts)
    except ValueError as e:
        raise ValueError(
            str(e)
            .replace("(A, C)", "(A, B) (through its dual)")
            .replace("not observable", "not controllable")
            .replace("observability", "controllability")
            + " (Times are those of the dual pair, s = −t.)"
        ) from None


class PDControllerGain(NamedTuple):
    """Result of :func:`pd_controller_gain`.

    - `K` (l, n): the state feedback u = K(t) x (15).
    - `Kc` (l, n): the same in controller canonical coordinates, u = K_c z_c (K_c = K M).
    - `alpha` (n,): the left-PDO coefficients of the blocks (concatenated), from the synthesis formula.
    - `M` (n, n): x = M(t) z_c; `Ac` (n, n), `Bc` (n, l): the controller canonical form.
    - `indices`: controllability indices (p_1, …, p_l).
    - `margin`: the staircase margin of P_0 (strong controllability; the observability margin of the
      dual pair, :func:`obsjax.design.strong_observability`): scale-invariant, 0 where P_0 is singular.
    """

    K: jax.Array
    Kc: jax.Array
    alpha: jax.Array
    M: jax.Array
    Ac: jax.Array
    Bc: jax.Array
    indices: tuple[int, ...]
    margin: jax.Array


def pd_controller_gain(
    A: Callable, B: Callable, rho_bar, omega, t, *, indices=None, threshold: float = DEFAULT_TOL
) -> PDControllerGain:
    """State feedback K(t) by PD-eigenstructure assignment (Huang & Zhu, Section II.A and (15)-(16)).

    For ẋ = A(t) x + B(t) u and u = K(t) x, the closed loop ẋ = (A + BK) x has, in the controller
    canonical coordinates x = M z_c (obtained by duality from the observer canonical form (8)-(11), see
    the module docstring), the block-diagonal companion form

        block i:  ż_1 = z_2, …, ż_{p_i} = −α_1 z_1 − … − α_{p_i} z_{p_i},

    whose first coordinate obeys z^{(p_i)} + α_{p_i} z^{(p_i−1)} + … + α_1 z = 0, the left PDO with the
    PD-spectrum {ρ̄_k ω(t)} of that block (α by the synthesis formula, (21); :func:`pd_coefficients`).
    K_c = R_c⁻¹ (target rows − A_c rows), K = K_c M⁻¹; every time derivative by automatic differentiation.

    **Arguments:**

    - `A`, `B`: callables of t (A_c(t), B_c(t) of (4) for the TLC).
    - `rho_bar`: (n,) nominal PD-eigenvalues, split over the input blocks in order (p_1 for input 1, …),
      distinct within each block.
    - `omega`: the bandwidth ω > 0: a constant or a callable of t.
    - `t`: the time (may be traced when `indices` is given).
    - `indices`: controllability indices; computed at t (concrete) when ``None``.
    - `threshold`: strong controllability: when t is concrete, a staircase margin of the
      controllability matrix P_0 (the rank mechanism of the indices, on the dual pair; scale-invariant)
      at or below it raises ``ValueError``; under ``jit`` the margin is in the result.

    **Returns:** :class:`PDControllerGain`.

    **Example:**

        A = lambda t: jnp.array([[0., 1.], [-1. - 0.5 * jnp.sin(t), -0.1]])
        B = lambda t: jnp.array([[0.], [1.]])
        K = pd_controller_gain(A, B, jnp.array([-1., -2.]), 2.0, 0.3).K      # eig(A + BK) frozen ≠ PD
    """
    require_x64("pd_controller_gain")
    t = check_time(t, "pd_controller_gain")
    Ad, Cd = _dual(A, B)
    tc = concrete_value(t)
    if indices is None:
        if tc is None:
            raise ValueError(
                "`indices` must be given when `t` is traced (controllability indices are static)."
            )
        indices = ltv_controllability_indices(A, B, tc)
    n = jax.eval_shape(A, t).shape[0]
    l = jax.eval_shape(B, t).shape[1]
    idx = _check_indices(indices, n, l)
    if not threshold >= 0:
        raise ValueError(f"`threshold` must be >= 0, got {threshold}.")
    try:
        form = ltv_observer_canonical_form(
            Ad, Cd, -t, indices=idx, threshold=max(float(threshold), 1e-300)
        )
    except ValueError as e:
        if "not strongly observable" not in str(e):
            raise
        m = concrete_value(margin_at(Ad, Cd, -t, idx))
        raise ValueError(
            f"The pair (A, B) is not strongly controllable at t = {float(tc):.6g}: the staircase margin "
            f"of its controllability matrix P_0 is {float(m):.3e} ≤ threshold {threshold:.1e}."
        ) from None
    rho_bar = check_rho_bar(rho_bar, distinct=False)
    if rho_bar.shape[0] != n:
        raise ValueError(
            f"`rho_bar` must have n = {n} entries (split as {idx}), got {rho_bar.shape[0]}."
        )
    w = omega_function(omega)
    M = form.T.T  # x = M z_c
    Minv = form.Tinv.T
    Ac = form.Az.T
    Bc = form.Cz.T
    d = [int(v) - 1 for v in np.cumsum(idx)]
    rows, alphas, start = [], [], 0
    for i, p in enumerate(idx):
        check_rho_bar(rho_bar[start : start + p], f"rho_bar[{start}:{start + p}]")
        a = pd_coefficients(rho_bar[start : start + p], w, t)
        target = jnp.zeros(n, dtype=a.dtype).at[start : start + p].set(-a)
        rows.append(target - Ac[d[i]])
        alphas.append(a)
        start += p
    Rc = Bc[jnp.asarray(d)]  # (l, l): unit lower triangular
    Kc = jnp.linalg.solve(Rc, jnp.stack(rows))
    K = _mm(Kc, Minv)
    return PDControllerGain(K, Kc, jnp.concatenate(alphas), M, Ac, Bc, idx, form.margin)


# --------------------------------------------------------------------------------------------------
# the nominal trajectory by dynamic inversion
# --------------------------------------------------------------------------------------------------


def _affine_parts(model):
    """f0(t, x) = f(t, x, 0) and g(t, x) = ∂f/∂u (t, x, 0) of an input-affine model."""
    p = model.p

    def f0(t, x):
        return model.f(t, x, jnp.zeros(p, dtype=x.dtype))

    def g(t, x):
        return jax.jacfwd(lambda u: model.f(t, x, u))(jnp.zeros(p, dtype=x.dtype))

    return f0, g


def _check_input_affine(model, t, x, what):
    """f(t, x, u) − f0 − g u = 0 at a few inputs (relative to ‖f‖): the plant must be input-affine."""
    f0, g = _affine_parts(model)
    rng = np.random.default_rng(0)
    us = jnp.asarray(rng.normal(size=(3, model.p)) * (1.0 + float(jnp.max(jnp.abs(x)))))

    @jax.jit
    def misfit(t, x, us):
        full = jax.vmap(lambda u: model.f(t, x, u))(us)
        lin = f0(t, x)[None] + us @ g(t, x).T
        hu = jax.jacfwd(lambda u: model.h(t, x, u))(jnp.zeros(model.p))
        err = jnp.max(jnp.abs(full - lin))
        scale = jnp.max(jnp.abs(full)) + jnp.max(jnp.abs(lin)) + 1e-300
        return err, scale, jnp.max(jnp.abs(hu))

    err, scale, hu = (float(v) for v in misfit(t, x, us))
    if not err <= 1e-9 * scale:
        raise ValueError(
            f"{what}: the plant must be input-affine, ξ̇ = f0(t, ξ) + g(t, ξ) μ; f(t, x, u) differs from "
            f"f(t, x, 0) + ∂f/∂u·u by {err:.3e} (relative {err / scale:.1e}) at t = {float(t):.4g}."
        )
    if hu > 0:
        raise ValueError(f"{what}: the output must not depend on the input (relative degree ≥ 1).")


def _lie_ladder(model, depth):
    """[φ_0, …, φ_depth] with φ_0(t, x) = h(t, x, 0), φ_{k+1} = ∂φ_k/∂t + ∂φ_k/∂x · f0 (time-varying Lie
    derivatives along the drift), each t, x ↦ (m,)."""
    f0, _ = _affine_parts(model)
    phis = [lambda t, x: model.h(t, x, jnp.zeros(model.p, dtype=x.dtype))]
    for _ in range(depth):
        prev = phis[-1]

        def nxt(t, x, prev=prev):
            return jax.jvp(prev, (t, x), (jnp.ones_like(t), f0(t, x)))[1]

        phis.append(nxt)
    return phis


def _relative_degree(model, t, x, tol):
    """Vector relative degree at (t, x): r_i = 1 + min{k : ∂φ_{k,i}/∂x · g ≠ 0} (a relative test)."""
    n = model.n
    _, g = _affine_parts(model)
    phis = _lie_ladder(model, n - 1)

    @jax.jit
    def ladder(t, x):
        return jnp.stack([jax.jacfwd(phis[k], argnums=1)(t, x) for k in range(n)]), g(t, x)

    Js, G = (np.asarray(v) for v in ladder(t, x))  # (n, m, n), (n, p)
    r = [None] * model.m
    for k in range(n):
        LgLf = Js[k] @ G
        for i in range(model.m):
            scale = np.linalg.norm(Js[k, i]) * np.linalg.norm(G) + 1e-300
            if r[i] is None and np.max(np.abs(LgLf[i])) > tol * scale:
                r[i] = k + 1
    return r


class NominalTrajectory(eqx.Module):
    """A nominal trajectory t ↦ (ξ̄(t), μ̄(t)) of (2), ξ̄˙ = f(t, ξ̄, μ̄), for the TLO and the TLC.

    Built by :func:`dynamic_inversion` (from a nominal output) or :meth:`from_state` (from a nominal
    state).  Calling it returns ``(xbar, ubar)``; both are differentiable in t to any order (the state by
    the implicit-function theorem), as the PD-eigenvalue designs need.
    """

    model: AbstractSystem
    y_ref: Callable | None
    x_ref: Callable | None
    guess: Callable
    degrees: tuple[int, ...] = eqx.field(static=True)
    iterations: int = eqx.field(static=True)
    tol: float = eqx.field(static=True)

    # ---- the state ---------------------------------------------------------------------------------
    def _Phi(self, t, x):
        """Stacked [φ_0,i, …, φ_{r_i−1,i}]_i (n,)."""
        phis = _lie_ladder(self.model, max(self.degrees))
        vals = [phis[k](t, x) for k in range(max(self.degrees))]
        return jnp.concatenate(
            [jnp.stack([vals[k][i] for k in range(r)]) for i, r in enumerate(self.degrees)]
        )

    def _Y(self, t):
        """Stacked [ȳ_i, ȳ_i', …, ȳ_i^{(r_i−1)}] (n,) and the top derivatives ȳ_i^{(r_i)} (m,)."""
        ders = time_derivatives(
            lambda s: jnp.asarray(self.y_ref(s)), t, max(self.degrees)
        )  # (R+1, m)
        Y = jnp.concatenate([ders[:r, i] for i, r in enumerate(self.degrees)])
        top = jnp.stack([ders[r, i] for i, r in enumerate(self.degrees)])
        return Y, top

    def state(self, t):
        """ξ̄(t)."""
        t = _as_time(t)
        if self.x_ref is not None:
            return jnp.asarray(self.x_ref(t))
        return _inverse_state(self, t)

    def input(self, t):
        """μ̄(t): Δ⁻¹(ȳ^{(r)} − φ_r(t, ξ̄)) (dynamic inversion) or g⁺(ξ̄˙ − f0) (from a state)."""
        t = _as_time(t)
        f0, g = _affine_parts(self.model)
        if self.x_ref is not None:
            x, xd = jax.jvp(self.state, (t,), (jnp.ones_like(t),))
            G = g(t, x)  # full column rank: the normal equations (smooth, cheap under nested jvp)
            return jnp.linalg.solve(G.T @ G, G.T @ (xd - f0(t, x)))
        x = self.state(t)
        _, top = self._Y(t)
        phis = _lie_ladder(self.model, max(self.degrees))
        G = g(t, x)
        rows_b, rows_D = [], []
        for i, r in enumerate(self.degrees):
            rows_b.append(phis[r](t, x)[i])
            rows_D.append(jax.jacfwd(phis[r - 1], argnums=1)(t, x)[i] @ G)
        return jnp.linalg.solve(jnp.stack(rows_D), top - jnp.stack(rows_b))

    def __call__(self, t):
        return self.state(t), self.input(t)

    def residual(self, t):
        """ξ̄˙ − f(t, ξ̄, μ̄) (n,): zero for a consistent nominal trajectory (2)."""
        t = _as_time(t)
        x, xd = jax.jvp(self.state, (t,), (jnp.ones_like(t),))
        return xd - self.model.f(t, x, self.input(t))

    @classmethod
    def from_state(
        cls, model, x_ref: Callable, *, check_ts=None, rtol: float = 1e-8
    ) -> NominalTrajectory:
        """The nominal input of a given nominal state: μ̄ = g(t, ξ̄)⁺ (ξ̄˙ − f0(t, ξ̄)) (least squares, g of full
        column rank).

        ξ̄ must be feasible: ξ̄˙ − f0 ∈ range g(t, ξ̄).  On `check_ts` the residual ‖ξ̄˙ − f(t, ξ̄, μ̄)‖ is
        compared with rtol·(‖ξ̄˙‖ + ‖f0‖) and a ``ValueError`` names the first time where it is larger.

        **Example:** ``NominalTrajectory.from_state(model, lambda t: jnp.array([jnp.sin(t), jnp.cos(t)]))``
        """
        require_x64("NominalTrajectory.from_state")
        if not isinstance(model, AbstractSystem):
            raise ValueError(f"`model` must be an obsjax plant, got {type(model).__name__}.")  # noqa: TRY004 (project rule: ValueError)
        if not callable(x_ref):
            raise ValueError("`x_ref` must be a callable t -> (n,) nominal state.")  # noqa: TRY004 (project rule: ValueError)
        t0 = _as_time(0.0 if check_ts is None else np.atleast_1d(check_ts)[0])
        _check_input_affine(model, t0, jnp.asarray(x_ref(t0)), "NominalTrajectory.from_state")
        nom = cls(model, None, x_ref, lambda t: jnp.zeros(model.n), (), 0, 0.0)
        if check_ts is not None:
            ts = np.atleast_1d(np.asarray(check_ts, dtype=float))
            res = np.asarray(jax.vmap(nom.residual)(jnp.asarray(ts)))
            f0, _ = _affine_parts(model)

            def scale(t):
                x, xd = jax.jvp(nom.state, (t,), (jnp.ones_like(t),))
                return jnp.linalg.norm(xd) + jnp.linalg.norm(f0(t, x))

            sc = np.asarray(jax.vmap(scale)(jnp.asarray(ts)))
            bad = np.linalg.norm(res, axis=1) > rtol * np.maximum(sc, 1e-300)
            if bad.any():
                k = int(np.argmax(bad))
                raise ValueError(
                    f"`x_ref` is not a trajectory of the plant for any input: ‖ξ̄˙ − f(t, ξ̄, μ̄)‖ = "
                    f"{np.linalg.norm(res[k]):.3e} at t = {ts[k]:.6g} (ξ̄˙ − f0 ∉ range g)."
                )
        return nom


def _inverse_state_impl(nom, t):
    """Newton's method for Φ(t, x) = Y(t) from the guess (fixed number of iterations)."""
    Y, _ = nom._Y(t)
    Y = eqx.error_if(
        Y,
        ~jnp.all(jnp.isfinite(Y)),
        "dynamic_inversion: the nominal output η̄(t) or one of its derivatives η̄', η̄'', … is not finite "
        "at this t (check `y_ref`).",
    )
    x = jnp.asarray(nom.guess(t), dtype=Y.dtype)

    def body(_, x):
        r = nom._Phi(t, x) - Y
        J = jax.jacfwd(lambda z: nom._Phi(t, z))(x)
        return x - jnp.linalg.solve(J, r)

    x = jax.lax.fori_loop(0, nom.iterations, body, x)
    r = nom._Phi(t, x) - Y
    scale = jnp.linalg.norm(Y) + jnp.linalg.norm(nom._Phi(t, x)) + 1e-300
    return eqx.error_if(
        x,
        ~(jnp.linalg.norm(r) <= nom.tol * scale),
        "dynamic_inversion: Newton's method did not solve [h, L_f h, …](t, ξ) = [η̄, η̄', …](t) for the "
        "nominal state (start from a better `guess`, or the map is not invertible there).",
    )


@eqx.filter_custom_jvp
def _inverse_state(nom, t):
    return _inverse_state_impl(nom, t)


@_inverse_state.def_jvp
def _inverse_state_jvp(primals, tangents):
    nom, t = primals
    dnom, dt = tangents
    x = _inverse_state(nom, t)

    # implicit function theorem on R(nom, t, x) = Φ(t, x) − Y(t) = 0: Φ_x dx = −(∂R/∂t dt + ∂R/∂nom dnom)
    def R(nom_, t_):
        return nom_._Phi(t_, x) - nom_._Y(t_)[0]

    dt = jnp.zeros_like(t) if dt is None else dt
    _, dR = eqx.filter_jvp(R, (nom, t), (dnom, dt))
    J = jax.jacfwd(lambda z: nom._Phi(t, z))(x)
    return x, -jnp.linalg.solve(J, dR)


def dynamic_inversion(
    model,
    y_ref: Callable,
    *,
    guess=None,
    relative_degree=None,
    t_check: float = 0.0,
    iterations: int = 20,
    tol: float = 1e-9,
) -> NominalTrajectory:
    """Nominal state and control for a nominal output, by dynamic inversion of an input-affine plant.

    For ξ̇ = f0(t, ξ) + g(t, ξ) μ, η = h(t, ξ) with (vector) relative degree (r_1, …, r_m), Σ r_i = n and
    m = l (Huang & Zhu, Section II.A: "a dynamic inverse I/O mapping of the plant to compute the nominal
    control μ̄(t) for any given nominal output trajectory η̄(t)"), with the time-varying Lie derivatives
    φ_0 = h, φ_{k+1} = ∂φ_k/∂t + ∂φ_k/∂ξ f0:

        φ_{k,i}(t, ξ̄) = η̄_i^{(k)}(t),  k < r_i        (n equations: ξ̄(t), by Newton's method)
        μ̄ = Δ(t, ξ̄)⁻¹ (η̄^{(r)}(t) − [φ_{r_i,i}(t, ξ̄)]_i),   Δ_ij = ∂φ_{r_i−1,i}/∂ξ · g_j       (2)

    so that ξ̄˙ = f(t, ξ̄, μ̄) and η̄ = h(t, ξ̄) exactly.  The derivatives of η̄ come from automatic
    differentiation; ξ̄(t) is differentiable to any order (implicit-function theorem in a custom JVP), so
    the returned :class:`NominalTrajectory` can be the ``nominal`` of :class:`obsjax.TrajectoryLinearization`
    and of :class:`TrajectoryLinearizationController`.  Plants with internal dynamics (Σ r_i < n) need a
    nominal state: :meth:`NominalTrajectory.from_state`.

    **Arguments:**

    - `model`: the plant model (:class:`obsjax.Nonlinear`, …), input-affine (checked at `t_check`).
    - `y_ref`: callable t ↦ η̄(t) (m,), smooth (JAX-traceable).
    - `guess`: initial state for Newton's method, an (n,) array or a callable of t (zeros by default).
    - `relative_degree`: the r_i; computed at (t_check, guess) when ``None`` (a relative test of
      L_g L_f^k h against ‖∂φ_k/∂ξ‖‖g‖).
    - `iterations`, `tol`: Newton iterations and the relative residual accepted (``eqx.error_if``).

    **Returns:** a :class:`NominalTrajectory`.

    **Example:** a pendulum with a time-varying length of arm, tracking η̄ = 0.5 sin t::

        model = obsjax.Nonlinear(lambda t, x, u: jnp.array([x[1], -jnp.sin(x[0]) + (1 + 0.2 * jnp.cos(t)) * u[0]]),
                                 lambda t, x, u: x[:1], 2, 1, 1)
        nominal = obsjax.dynamic_inversion(model, lambda t: jnp.array([0.5 * jnp.sin(t)]))
        xbar, ubar = nominal(1.0)
    """
    require_x64("dynamic_inversion")
    if not isinstance(model, AbstractSystem):
        raise ValueError(f"`model` must be an obsjax plant, got {type(model).__name__}.")  # noqa: TRY004 (project rule: ValueError)
    if not callable(y_ref):
        raise ValueError("`y_ref` must be a callable t -> (m,) nominal output.")  # noqa: TRY004 (project rule: ValueError)
    n, m, p = model.n, model.m, model.p
    if p != m:
        raise ValueError(
            f"dynamic_inversion needs as many inputs as outputs (a square decoupling matrix), got "
            f"{p} inputs and {m} outputs."
        )
    shp = tuple(jax.eval_shape(y_ref, _as_time(0.0)).shape)
    if shp != (m,):
        raise ValueError(f"`y_ref(t)` must return shape ({m},), got {shp}.")
    if guess is None:
        guess_fn = lambda t: jnp.zeros(n)
    elif callable(guess):
        guess_fn = guess
    else:
        g0 = vector(guess, "guess", n)
        guess_fn = lambda t: g0
    tc = _as_time(t_check)
    x_c = jnp.asarray(guess_fn(tc), dtype=float)
    _check_input_affine(model, tc, x_c, "dynamic_inversion")
    if relative_degree is None:
        r = _relative_degree(model, tc, x_c, 1e-9)
        if any(v is None for v in r):
            raise ValueError(
                f"dynamic_inversion: output(s) {[i for i, v in enumerate(r) if v is None]} have no relative "
                f"degree ≤ n = {n} at t = {t_check} (the input never reaches them); give `relative_degree` "
                f"if this is a singular point of the guess."
            )
    else:
        r = [int(v) for v in np.atleast_1d(relative_degree)]
        if len(r) != m or any(v < 1 for v in r):
            raise ValueError(
                f"`relative_degree` must be {m} integers >= 1, got {relative_degree!r}."
            )
    if sum(r) != n:
        raise ValueError(
            f"dynamic_inversion needs full relative degree Σ r_i = n = {n}, found r = {tuple(r)} (sum "
            f"{sum(r)}): the plant has {n - sum(r)} internal state(s); give a feasible nominal state with "
            f"NominalTrajectory.from_state."
        )
    nom = NominalTrajectory(model, y_ref, None, guess_fn, tuple(r), int(iterations), float(tol))
    Yc, topc = nom._Y(tc)
    if not (np.all(np.isfinite(np.asarray(Yc))) and np.all(np.isfinite(np.asarray(topc)))):
        raise ValueError(
            f"dynamic_inversion: `y_ref` or one of its first {max(r)} time derivatives is not finite at "
            f"t_check = {t_check}: η̄, η̄', … = {np.asarray(Yc).tolist()}, top derivatives "
            f"{np.asarray(topc).tolist()}."
        )
    # the decoupling matrix must be invertible at t_check (the staircase's relative residuals: each row
    # against its own norm, so the units of the outputs do not matter)
    _, g = _affine_parts(model)
    phis = _lie_ladder(model, max(r))

    @jax.jit
    def decoupling(t):
        x1 = nom.state(t)
        return jnp.stack(
            [jax.jacfwd(phis[ri - 1], argnums=1)(t, x1)[i] @ g(t, x1) for i, ri in enumerate(r)]
        )

    Dl = decoupling(tc)
    rc = float(jnp.min(relative_residuals(Dl, jnp.linalg.norm(Dl, axis=1))))
    if not rc > DEFAULT_TOL:
        raise ValueError(
            f"dynamic_inversion: the decoupling matrix Δ = [L_g L_f^(r_i−1) h_i] is singular at t = {t_check} "
            f"(smallest residual of a row outside the rows before it, relative to its norm: {rc:.2e})."
        )
    return nom


# --------------------------------------------------------------------------------------------------
# the controller
# --------------------------------------------------------------------------------------------------


@eqx.filter_jit
def _gain(ctrl, t):
    """K(t) as its own jitted function (traced once per simulation, reused by every solver stage)."""
    return ctrl.gain(t)


class TrajectoryLinearizationController(eqx.Module):
    """Trajectory linearization controller with PD-eigenstructure state feedback (Huang & Zhu, Fig. 1-2,
    (15)-(17), (24)-(28), Remark 2).

    The control is the nominal control plus the tracking-error feedback applied to the estimate,

        μ = sat(μ̄(t) + K(t) (ξ̂ − ξ̄(t))),        μ̃ = K(t) ξ̃̂                                    (15), (17)

    with K(t) from :func:`pd_controller_gain` on the linearisation (4) A_c = ∂f/∂ξ, B_c = ∂f/∂μ along the
    nominal trajectory: the linearised tracking error of the state-feedback loop (16) has the PD-spectrum
    {ρ̄_k ω(t)}.  Call it as ``controller(t, xhat)``, the form of :func:`obsjax.simulate`'s ``controller``;
    with ``xhat = x`` it is the state feedback (15)-(16), with the estimate of a
    :class:`obsjax.TrajectoryLinearization` (whose ``nominal`` is the same trajectory) it is the output
    feedback (17)-(18).  In the observer's canonical coordinates z = T_2 ξ̃ this is (24)-(28):
    μ̃ = K_z ẑ with K_z = K T_2⁻¹ (:meth:`canonical_gain`).

    **Saturation (Remark 2).**  A high-gain observer peaks (ξ̂ − ξ of order 1/ε^{k} during a transient
    of length O(ε)); the feedback turns that into an impulse-like control that can drive the plant far
    away, or to a finite escape time.  With ``u_max`` the control is clipped to
    [u_min, u_max] (``u_min = −u_max`` by default); choose the bound above the control of the state-feedback
    loop over the region of interest, so that it only acts during peaking (Khalil, *Nonlinear Systems*,
    §14.5).  ``None`` gives the unsaturated law (bounds ±inf, leaves like the finite ones, so saturated
    and unsaturated controllers share one compiled simulation).

    **Arguments:**

    - `model`: the plant model (:class:`obsjax.Nonlinear`, :class:`obsjax.LTV`, …).
    - `nominal`: callable t ↦ (ξ̄(t), μ̄(t)) (e.g. :func:`dynamic_inversion`).
    - `rho_bar`: (n,) nominal PD-eigenvalues ρ̄_k < 0, distinct within each input block.
    - `omega`: bandwidth ω > 0, a constant or a callable of t (e.g. :class:`obsjax.design.RampBandwidth`).
    - `u_max`, `u_min`: optional saturation bounds (scalars or (l,) vectors).
    - `indices`: controllability indices of (A_c, B_c); computed at t = 0 when ``None``.
    - `check_ts`: times where strong controllability is checked at construction.
    - `threshold`: the strong-controllability threshold (the staircase margin of P_0, see
      :func:`pd_controller_gain`); along the trajectory a margin at or below it stops the simulation
      (``eqx.error_if``).

    **Example:** output feedback through the TLO::

        nominal = obsjax.dynamic_inversion(model, lambda t: jnp.array([jnp.sin(t)]))
        tlc = obsjax.TrajectoryLinearizationController(model, nominal, [-1., -2.], 2.0, u_max=5.0)
        tlo = obsjax.TrajectoryLinearization(model, [-1., -2.], 2.0, eps=0.1, nominal=nominal)
        traj = obsjax.simulate(plant, tlo, x0, nominal.state(0.0), ts, controller=tlc)
    """

    model: AbstractSystem
    nominal: Callable
    rho_bar: jax.Array
    omega: jax.Array | Callable
    u_max: jax.Array
    u_min: jax.Array
    indices: tuple[int, ...] = eqx.field(static=True)
    threshold: float = eqx.field(static=True, default=DEFAULT_TOL)

    def __init__(
        self,
        model,
        nominal,
        rho_bar,
        omega,
        *,
        u_max=None,
        u_min=None,
        indices=None,
        check_ts=None,
        threshold: float = DEFAULT_TOL,
    ):
        require_x64("TrajectoryLinearizationController")
        if not isinstance(model, AbstractSystem):
            raise ValueError(f"`model` must be an obsjax plant, got {type(model).__name__}.")  # noqa: TRY004 (project rule: ValueError)
        if not callable(nominal):
            raise ValueError(  # noqa: TRY004 (project rule: ValueError)
                "`nominal` must be a callable t -> (xbar, ubar) (e.g. obsjax.dynamic_inversion)."
            )
        if model.p < 1:
            raise ValueError("`model` has no input (p = 0): nothing to control.")
        self.model = model
        self.nominal = nominal
        self.rho_bar = check_rho_bar(rho_bar, "rho_bar", negative=True, distinct=False)
        if self.rho_bar.shape[0] != model.n:
            raise ValueError(
                f"`rho_bar` must hold n = {model.n} nominal PD-eigenvalues, got {self.rho_bar.shape[0]}."
            )
        self.omega = omega if callable(omega) else as_float_array(omega, "omega")
        omega_function(self.omega)
        l = model.p
        if u_max is None and u_min is not None:
            raise ValueError("`u_min` needs `u_max` (give both bounds, or only u_max for ±u_max).")
        # always arrays (±inf: no saturation), so that saturated and unsaturated controllers share one trace
        self.u_max = jnp.broadcast_to(
            as_float_array(jnp.inf if u_max is None else u_max, "u_max"), (l,)
        )
        self.u_min = (
            -self.u_max if u_min is None else jnp.broadcast_to(as_float_array(u_min, "u_min"), (l,))
        )
        lo, hi = concrete_value(self.u_min), concrete_value(self.u_max)
        if lo is not None and hi is not None and not np.all(lo < hi):
            raise ValueError(
                f"`u_min` must be < `u_max` elementwise, got {lo.tolist()} and {hi.tolist()}."
            )
        if not threshold > 0:
            raise ValueError(f"`threshold` must be > 0, got {threshold}.")
        self.threshold = float(threshold)
        A, B = self.jacobians()
        if indices is None:
            indices = ltv_controllability_indices(A, B, 0.0 if check_ts is None else check_ts)
        self.indices = _check_indices(indices, model.n, l)
        start = 0
        for p in self.indices:
            check_rho_bar(self.rho_bar[start : start + p], f"rho_bar[{start}:{start + p}]")
            start += p
        if check_ts is not None:
            for tk in np.atleast_1d(np.asarray(check_ts, dtype=float)):
                pd_controller_gain(
                    A,
                    B,
                    self.rho_bar,
                    self.omega,
                    float(tk),
                    indices=self.indices,
                    threshold=self.threshold,
                )

    def jacobians(self):
        """t ↦ A_c(t) = ∂f/∂ξ, t ↦ B_c(t) = ∂f/∂μ along the nominal (4)."""
        f = self.model.f

        def xu(s):
            xb, ub = self.nominal(s)
            return jnp.asarray(xb), jnp.asarray(ub).reshape(self.model.p)

        def A(s):
            xb, ub = xu(s)
            return jax.jacfwd(f, argnums=1)(s, xb, ub)

        def B(s):
            xb, ub = xu(s)
            return jax.jacfwd(f, argnums=2)(s, xb, ub)

        return A, B

    def design(self, t) -> PDControllerGain:
        """The full PD-eigenstructure design at time t."""
        A, B = self.jacobians()
        return pd_controller_gain(
            A, B, self.rho_bar, self.omega, t, indices=self.indices, threshold=0.0
        )

    def gain(self, t) -> jax.Array:
        """K(t), shape (l, n) (μ̃ = K ξ̃)."""
        d = self.design(jnp.asarray(t, dtype=float))
        return eqx.error_if(
            d.K,
            ~(d.margin > self.threshold),
            "TrajectoryLinearizationController: the linearised pair (A_c, B_c) lost strong "
            "controllability (the staircase margin of P_0 fell to `threshold`).",
        )

    def canonical_gain(self, t, T2) -> jax.Array:
        """K_z = K T_2⁻¹ of (25)/(28) for a coordinate transformation z = T_2(t) ξ̃ (e.g. the TLO's
        observer canonical form); μ̃ = K_z ẑ equals K ξ̃̂."""
        return jnp.linalg.solve(jnp.asarray(T2).T, self.gain(t).T).T

    def unsaturated(self, t, xhat) -> jax.Array:
        """μ̄(t) + K(t)(ξ̂ − ξ̄(t)) before saturation."""
        t = jnp.asarray(t, dtype=float)
        xb, ub = self.nominal(t)
        K = _gain(self, t)
        return jnp.asarray(ub).reshape(self.model.p) + K @ (jnp.asarray(xhat) - jnp.asarray(xb))

    def __call__(self, t, xhat) -> jax.Array:
        return jnp.clip(self.unsaturated(t, xhat), self.u_min, self.u_max)
