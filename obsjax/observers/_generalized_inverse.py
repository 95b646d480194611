"""Lovass-Nagy full-state and reduced-order LTV observers by matrix {1}-inverses (Chaisanguanmitt, slides).

Full-state (slides (1)-(9) and steps 1-6): for ẋ = A x + B u, y = C x and an invertible T(t),

    ż = F z + G y + T B u,     G = (Ṫ + T A − F T) C^{1},     x̂ = T⁻¹ z,

which needs the solvability condition (Ṫ + T A − F T)(I − C^{1} C) = 0; then d/dt(z − T x) = F (z − T x).

Reduced order, derived here (the slides' derivation (5)-(13) has two slips, see
:class:`GeneralizedInverseReduced`).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value, matrix
from ..design._ginverse import equilibrated_rcond
from ._base import AbstractObserver, require_no_feedthrough
from ._validation import require_finite


def _time_grid(horizon, num):
    t0, t1 = (float(h) for h in horizon)
    if not t1 > t0:
        raise ValueError(f"`horizon` must be (t0, t1) with t1 > t0, got {horizon}.")
    return np.linspace(t0, t1, int(num))


def _rcond_sign(T):
    """(σ_min/σ_max of the equilibrated T, sign det T): invertibility of T by a scale-invariant test (the
    same verdict for T and s·T, z in other units, and for the state in other units,
    :func:`obsjax.design._ginverse.equilibrated_rcond`), and the sign of det T from ``slogdet`` (no over- or
    underflow)."""
    return equilibrated_rcond(T), jnp.linalg.slogdet(T)[0]


def _checks_at(obs, t):
    res, scale, det = obs.solvability(t)
    rcond, sign = _rcond_sign(jax.lax.stop_gradient(obs.T_of(t)))  # a verdict, never differentiated
    return res, scale, det, rcond, sign


@eqx.filter_jit
def _solvability_on_grid(obs, ts):
    return jax.vmap(lambda t: _checks_at(obs, t))(ts)


def _relative(res, scale, xp):
    """res / scale, the residual relative to the size of the terms of M = Ṫ + TA − FT (no absolute
    floor: invariant under time units A → cA, F → cF, Ṫ → cṪ and z units T → sT).  scale = 0 means
    M = 0 exactly: relative 0 when res = 0 too, inf otherwise."""
    safe = xp.where(scale > 0, scale, 1.0)
    return xp.where(scale > 0, res / safe, xp.where(res == 0, 0.0, xp.inf))


def _solvability(T, Td, F, A, C, C1):
    """(‖M (I − C1 C)‖, scale ‖Ṫ‖ + ‖TA‖ + ‖FT‖, det T) with M = Ṫ + TA − FT: the Lovass-Nagy condition.

    The full observer uses (A, C); the reduced one (A22, A12)."""
    M = Td + T @ A - F @ T
    P = jnp.eye(C.shape[1], dtype=M.dtype) - C1 @ C
    scale = jnp.linalg.norm(Td) + jnp.linalg.norm(T @ A) + jnp.linalg.norm(F @ T)
    return jnp.linalg.norm(M @ P), scale, jnp.linalg.det(T)


def _check_over(obs, ts, what):
    """Evaluate solvability residuals and the invertibility of T on `ts`; raise ValueError naming the
    worst time.  Both tests are scale-invariant: the residual relative to ‖Ṫ‖ + ‖TA‖ + ‖FT‖, and
    σ_min(T)/σ_max(T) > `rcond_min` (plus no sign change of det T between grid points).
    Returns False when the values are traced (nothing could be checked here: see
    :func:`_guard_traced`)."""
    ts = jnp.asarray(ts, dtype=float)
    vals = [concrete_value(v) for v in _solvability_on_grid(obs, ts)]
    if any(v is None for v in vals):
        return False  # traced (inside jit/grad)
    res, scale, det, rcond, sign = (np.asarray(v) for v in vals)
    ts = np.asarray(ts)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = _relative(res, scale, np)
    i = int(np.argmax(np.where(np.isfinite(rel), rel, -1.0)))
    if not np.all(np.isfinite(rel)) or rel[i] > obs.rtol:
        j = i if np.all(np.isfinite(rel)) else int(np.argmax(~np.isfinite(rel)))
        raise ValueError(
            f"{what}: the Lovass-Nagy solvability condition fails: the residual "
            f"‖(Ṫ + T·Ā − F·T)(I − C^{{1}}·C)‖ = {res[j]:.3e}, relative to ‖Ṫ‖ + ‖T·Ā‖ + ‖F·T‖ = "
            f"{scale[j]:.3e}: {rel[j]:.3e} > rtol = {obs.rtol:.1e}, at t = {ts[j]:.6g}; "
            f"G·C = Ṫ + T·Ā − F·T has no solution G there. "
            f"Choose T(t) with obsjax.design.lovass_nagy_T or change F."
        )
    # det T is continuous: a sign change between grid points means T is singular in between.
    k = int(np.argmin(np.where(np.isfinite(rcond), rcond, -1.0)))
    flips = np.nonzero(sign[:-1] * sign[1:] < 0)[0]
    tiny = not rcond[k] > obs.rcond_min
    if not (np.all(np.isfinite(det)) and np.all(np.isfinite(rcond))) or tiny or flips.size:
        if flips.size and not tiny:
            j = int(flips[0])
            where = (
                f"det T changes sign between t = {ts[j]:.6g} and t = {ts[j + 1]:.6g} "
                f"({det[j]:.3e} → {det[j + 1]:.3e})"
            )
        else:
            where = (
                f"σ_min(T)/σ_max(T) = {rcond[k]:.3e} (≤ rcond_min = {obs.rcond_min:.1e}, det T = "
                f"{det[k]:.3e}) at t = {ts[k]:.6g}"
            )
        raise ValueError(
            f"{what}: `T` must be invertible over the horizon (det T ≠ 0, expected "
            f"σ_min(T)/σ_max(T) > rcond_min = {obs.rcond_min:.1e}), found {where}."
        )
    return True


def _guard_traced(obs, what, ts=None):
    """`obs.F` guarded by ``eqx.error_if`` (survives jit): the solvability condition and the
    invertibility of T on the check grid (`ts`, else the horizon's, or t = 0), the same scale-invariant
    tests as :func:`_check_over` applies to concrete values eagerly."""
    if ts is None:
        ts = [0.0] if obs.horizon is None else _time_grid(obs.horizon, obs.num_checks)
    ts = jnp.asarray(ts)
    res, scale, _det, rcond, sign = jax.vmap(lambda t: _checks_at(obs, t))(ts)
    rel = _relative(res, scale, jnp)
    F = eqx.error_if(
        obs.F,
        jnp.any(~(rel <= obs.rtol)),
        f"{what}: the Lovass-Nagy solvability condition "
        f"‖(Ṫ + T·Ā − F·T)(I − C^{{1}}·C)‖ ≤ rtol·(‖Ṫ‖ + ‖T·Ā‖ + ‖F·T‖) (rtol = {obs.rtol:.1e}) fails "
        "(or is not finite) on the check grid: G·C = Ṫ + T·Ā − F·T has no solution G there.",
    )
    tiny = jnp.any(~(rcond > obs.rcond_min))
    flips = jnp.any(sign[:-1] * sign[1:] < 0) if sign.shape[0] > 1 else False
    return eqx.error_if(
        F,
        tiny | flips,
        f"{what}: `T` must be invertible over the check grid (det T ≠ 0, expected "
        f"σ_min(T)/σ_max(T) > rcond_min = {obs.rcond_min:.1e}), found a smaller or non-finite "
        "σ_min/σ_max, or a sign change of det T.",
    )


def _check_span(obs, t0, t1, what):
    """`obs` after the checks of ``check_horizon`` on a simulated span [t0, t1] that its `horizon` does not
    cover, on `num_checks` points (with ``horizon=None`` only t = 0 was checked at construction: a T(t)
    singular later in the simulation gave a wrong estimate with status 0).  ``ValueError`` when the
    values are concrete; under ``jit`` the same tests by ``eqx.error_if`` on the returned observer."""
    h = obs.horizon
    if h is not None and h[0] <= t0 and t1 <= h[1]:
        return obs
    what = f"{what} (on the simulated span)"
    grid = _time_grid((t0, t1), obs.num_checks)
    if _check_over(obs, grid, what):
        return obs
    return eqx.tree_at(lambda o: o.F, obs, _guard_traced(obs, what, grid))


def _require_stable_F(F, law):
    """``ValueError`` when a concrete F has an eigenvalue with Re λ ≥ 0: the observer error `law` must decay
    (an unstable F was accepted, and the simulation reported success while the error grew from 1 to 3e3).
    A traced F (built under ``jit``) is not checked: the eigenvalues of a nonsymmetric matrix are
    not computed there; the trajectory's error shows it."""
    Fc = concrete_value(F)
    if Fc is not None and not np.all(np.linalg.eigvals(Fc).real < 0):
        raise ValueError(
            f"`F` must have its eigenvalues in the open left half-plane ({law} must decay), got "
            f"{np.round(np.linalg.eigvals(Fc), 6).tolist()}."
        )


class GeneralizedInverse(AbstractObserver):
    """Lovass-Nagy full-state LTV observer (slides, (2), (6)-(9), procedure steps 1-6).

        ż = F z + G y + T B u,      G(t) = (Ṫ + T A − F T) C^{1},      x̂ = T⁻¹ z          (2), (8)

    valid when (Ṫ + T A − F T)(I − C^{1} C) = 0 and det T ≠ 0; then d/dt(z − T x) = F (z − T x) (7).
    Ṫ is computed by automatic differentiation of ``T`` (``jax.jacfwd`` in t).

    **Arguments:**

    - `model`: the observer's plant model (``obsjax.LTV`` or ``obsjax.LTI``: ``A_of``, ``B_of``, ``C_of``).
    - `F`: (n, n) constant observer matrix with the desired eigenvalues, in the open left half-plane (a
      leaf).
    - `T`: callable t -> (n, n), differentiable (e.g. from :func:`obsjax.design.lovass_nagy_T`).
    - `C1`: optional constant (n, m) {1}-inverse of C (Moore–Penrose of C(t) when ``None``).
    - `horizon`: optional (t0, t1): the condition and det T ≠ 0 are checked on `num_checks` points of
      it at construction (and by :meth:`check`); with ``None`` only t = 0 is checked there.  Use
      :meth:`check_horizon` for another horizon.  Each simulation (:func:`obsjax.simulate`,
      ``simulate_batch``, ``estimate``) checks its span of save times the same way where the
      horizon does not cover it (:meth:`check_span`).
    - `rtol`: relative tolerance on the solvability residual: ‖(Ṫ + TA − FT)(I − C^{1}C)‖ ≤
      rtol·(‖Ṫ‖ + ‖TA‖ + ‖FT‖), the same verdict in any time unit and any units of z (T → sT).
    - `rcond_min`: smallest admissible σ_min(T)/σ_max(T) on the check grid (T invertible, a
      scale-invariant test; a sign change of det T between grid points is refused too).

    **Example:**

        T = obsjax.design.lovass_nagy_T(plant.A_of, C, F, S)
        obs = obsjax.GeneralizedInverse(plant, F, T, horizon=(0.0, 5.0))
        traj = obsjax.simulate(plant, obs, x0, xhat0, ts)
    """

    model: eqx.Module
    F: jax.Array
    T: Callable
    C1: jax.Array | None
    horizon: tuple[float, float] | None = eqx.field(static=True)
    num_checks: int = eqx.field(static=True)
    rtol: float = eqx.field(static=True)
    rcond_min: float = eqx.field(static=True)

    def __init__(self, model, F, T, C1=None, *, horizon=None, num_checks=201, rtol=1e-7,
                 rcond_min=1e-10):
        require_no_feedthrough(model, "GeneralizedInverse")
        n, m = int(model.n), int(model.m)
        self.model = model
        self.F = matrix(F, "F", (n, n))
        if not callable(T):
            raise ValueError("`T` must be a callable of t returning an (n, n) matrix.")  # noqa: TRY004 (project rule: ValueError)
        T0 = jax.eval_shape(T, jnp.asarray(0.0))
        if tuple(T0.shape) != (n, n):
            raise ValueError(f"`T(t)` must return shape ({n}, {n}), got {tuple(T0.shape)}.")
        self.T = T
        self.C1 = None if C1 is None else require_finite(matrix(C1, "C1", (n, m)), "C1")
        require_finite(self.F, "F")
        _require_stable_F(self.F, "z − T x = e^{Ft}(z0 − T0 x0)")
        self.horizon = None if horizon is None else (float(horizon[0]), float(horizon[1]))
        self.num_checks = int(num_checks)
        self.rtol = float(rtol)
        self.rcond_min = float(rcond_min)
        ts = [0.0] if self.horizon is None else _time_grid(self.horizon, self.num_checks)
        if not _check_over(self, ts, "GeneralizedInverse"):  # built under jit: eqx.error_if
            self.F = _guard_traced(self, "GeneralizedInverse")

    # --- the design quantities -------------------------------------------------------------------
    def T_of(self, t):
        return jnp.asarray(self.T(jnp.asarray(t, dtype=self.F.dtype)))

    def Tdot_of(self, t):
        return jax.jacfwd(self.T_of)(jnp.asarray(t, dtype=self.F.dtype))

    def C1_of(self, t):
        return jnp.linalg.pinv(self.model.C_of(t)) if self.C1 is None else self.C1

    def M_of(self, t):
        """M(t) = Ṫ + T A − F T (slides (9))."""
        T = self.T_of(t)
        return self.Tdot_of(t) + T @ self.model.A_of(t) - self.F @ T

    def G_of(self, t):
        """G(t) = (Ṫ + T A − F T) C^{1} (step 5)."""
        return self.M_of(t) @ self.C1_of(t)

    def solvability(self, t):
        """(‖M (I − C^{1}C)‖, scale ‖Ṫ‖ + ‖TA‖ + ‖FT‖, det T) at time t."""
        return _solvability(self.T_of(t), self.Tdot_of(t), self.F, self.model.A_of(t), self.model.C_of(t),
                            self.C1_of(t))

    def check_horizon(self, t0, t1, num=201):
        """Raise ValueError if the condition or det T ≠ 0 fails somewhere on [t0, t1]."""
        _check_over(self, _time_grid((t0, t1), num), "GeneralizedInverse")
        return self

    def check_span(self, t0, t1):
        """The checks of :meth:`check_horizon` on a simulated span (:func:`_check_span`)."""
        return _check_span(self, t0, t1, "GeneralizedInverse")

    def check(self):
        ts = [0.0] if self.horizon is None else _time_grid(self.horizon, self.num_checks)
        _check_over(self, ts, "GeneralizedInverse")
        return self

    def prepare(self):
        """The checks of :meth:`check` once per simulation: eagerly when the values are concrete
        (``ValueError``), by ``eqx.error_if`` when anything they depend on is traced (F, C1, the
        model's or T's leaves, or values T closes over)."""
        ts = [0.0] if self.horizon is None else _time_grid(self.horizon, self.num_checks)
        if _check_over(self, ts, "GeneralizedInverse"):
            return self
        return eqx.tree_at(lambda o: o.F, self, _guard_traced(self, "GeneralizedInverse"))

    # --- the observer protocol -------------------------------------------------------------------
    def init(self, t0, xhat0, y0):
        return self.T_of(t0) @ jnp.asarray(xhat0)

    def _T_G(self, t):
        """(T, G) at t with Ṫ from one forward-mode pass (jax.jvp in t)."""
        t = jnp.asarray(t, dtype=self.F.dtype)
        T, Td = jax.jvp(self.T_of, (t,), (jnp.ones_like(t),))
        G = (Td + T @ self.model.A_of(t) - self.F @ T) @ self.C1_of(t)
        return T, G

    def vector_field(self, t, z, y, u):
        T, G = self._T_G(t)
        dz = self.F @ z + G @ y
        B = self.model.B_of(t)
        if B.shape[1] > 0:
            dz = dz + T @ (B @ u)
        return dz

    def estimate(self, t, z, y):
        return jnp.linalg.solve(self.T_of(t), z)


class GeneralizedInverseReduced(AbstractObserver):
    """Lovass-Nagy reduced-order LTV observer, differentiation-free form (derived; cf. slides (3)-(13)).

    The model is partitioned as x = [y; w] (C = [I, 0]):

        ẏ = A11 y + A12 w + B1 u,     ẇ = A21 y + A22 w + B2 u,

    so ȳ := ẏ − A11 y − B1 u = A12 w is a measurement of w, and A21 y + B2 u is a *known* input of the
    w-subsystem (y is measured).  The observer ż = F z + G ȳ + T A21 y + T B2 u gives

        d/dt(z − T w) = F z + (G A12 − Ṫ − T A22) w,

    so with the design equation (replacing the slides' (11)-(12), which carry a spurious T A21 C term
    because they write the input A21 y as A21 ȳ)

        Ṫ + T A22 − F T = G A12,    G = (Ṫ + T A22 − F T) A12^{1},
        solvable iff (Ṫ + T A22 − F T)(I − A12^{1} A12) = 0,

    the defining property d/dt(z − T w) = F (z − T w) holds exactly.  To avoid ẏ, put z = p + G y; since
    G is time-varying, ż = ṗ + Ġ y + G ẏ (the slides drop Ġ y), hence

        ṗ = F (p + G y) + (T A21 − G A11 − Ġ) y + (T B2 − G B1) u,
        z = p + G y,     ŵ = T⁻¹ z,     x̂ = [y; ŵ].

    Ġ is computed by automatic differentiation (it involves T̈, so T must be twice differentiable).

    **Arguments:**

    - `model`: plant model with C = [I_m, 0] (``obsjax.LTV`` or ``obsjax.LTI``).
    - `F`: (n−m, n−m) constant observer matrix, eigenvalues in the open left half-plane (a leaf).
    - `T`: callable t -> (n−m, n−m), twice differentiable (see :func:`obsjax.design.lovass_nagy_T`).
    - `C1`: optional constant (n−m, m) {1}-inverse of A12; the Moore–Penrose inverse of A12(t) if None.
    - `horizon`, `num_checks`, `rtol`, `rcond_min`: as in :class:`GeneralizedInverse`.

    The observer state is p (n−m,).

    **Example:** the slides' 4th-order example::

        T = obsjax.design.lovass_nagy_T(A22, A12, -5 * jnp.eye(2), S)
        obs = obsjax.GeneralizedInverseReduced(plant, -5 * jnp.eye(2), T,
                                               C1=[[0., 0.], [0.5, 0.5]], horizon=(0., 5.))
    """

    model: eqx.Module
    F: jax.Array
    T: Callable
    C1: jax.Array | None
    horizon: tuple[float, float] | None = eqx.field(static=True)
    num_checks: int = eqx.field(static=True)
    rtol: float = eqx.field(static=True)
    rcond_min: float = eqx.field(static=True)

    def __init__(self, model, F, T, C1=None, *, horizon=None, num_checks=201, rtol=1e-7,
                 rcond_min=1e-10):
        require_no_feedthrough(model, "GeneralizedInverseReduced")
        n, m = int(model.n), int(model.m)
        q = n - m
        if q <= 0:
            raise ValueError(
                f"`model` must have fewer outputs than states for a reduced observer, got "
                f"n = {n}, m = {m}."
            )
        C = concrete_value(jnp.asarray(model.C_of(jnp.asarray(0.0))))
        expected = np.hstack([np.eye(m), np.zeros((m, q))])
        if C is not None and (C.shape != expected.shape or not np.allclose(C, expected)):
            raise ValueError(
                f"`model` must be in the partitioned form x = [y; w], i.e. C = [I_{m}, 0] of shape "
                f"({m}, {n}); got C(0) = {np.asarray(C).tolist()}. Transform the state first."
            )
        self.model = model
        self.F = matrix(F, "F", (q, q))
        if not callable(T):
            raise ValueError(f"`T` must be a callable of t returning a ({q}, {q}) matrix.")  # noqa: TRY004 (project rule: ValueError)
        T0 = jax.eval_shape(T, jnp.asarray(0.0))
        if tuple(T0.shape) != (q, q):
            raise ValueError(
                f"`T(t)` must return shape ({q}, {q}) (n − m = {q}), got {tuple(T0.shape)}."
            )
        self.T = T
        self.C1 = None if C1 is None else require_finite(matrix(C1, "C1", (q, m)), "C1")
        require_finite(self.F, "F")
        _require_stable_F(self.F, "z − T w = e^{Ft}(z0 − T0 w0)")
        self.horizon = None if horizon is None else (float(horizon[0]), float(horizon[1]))
        self.num_checks = int(num_checks)
        self.rtol = float(rtol)
        self.rcond_min = float(rcond_min)
        ts = [0.0] if self.horizon is None else _time_grid(self.horizon, self.num_checks)
        if not _check_over(self, ts, "GeneralizedInverseReduced"):  # under jit: eqx.error_if
            self.F = _guard_traced(self, "GeneralizedInverseReduced")

    @property
    def m(self) -> int:
        return int(self.model.m)

    def blocks(self, t):
        """(A11, A12, A21, A22, B1, B2) of the model at time t."""
        m = self.m
        A = jnp.asarray(self.model.A_of(t))
        B = jnp.asarray(self.model.B_of(t))
        return A[:m, :m], A[:m, m:], A[m:, :m], A[m:, m:], B[:m], B[m:]

    def T_of(self, t):
        return jnp.asarray(self.T(jnp.asarray(t, dtype=self.F.dtype)))

    def Tdot_of(self, t):
        return jax.jacfwd(self.T_of)(jnp.asarray(t, dtype=self.F.dtype))

    def C1_of(self, t):
        return jnp.linalg.pinv(self.blocks(t)[1]) if self.C1 is None else self.C1

    def M_of(self, t):
        """M(t) = Ṫ + T A22 − F T."""
        T = self.T_of(t)
        return self.Tdot_of(t) + T @ self.blocks(t)[3] - self.F @ T

    def G_of(self, t):
        """G(t) = (Ṫ + T A22 − F T) A12^{1}."""
        return self.M_of(t) @ self.C1_of(t)

    def Gdot_of(self, t):
        return jax.jacfwd(self.G_of)(jnp.asarray(t, dtype=self.F.dtype))

    def solvability(self, t):
        """(‖M (I − A12^{1} A12)‖, scale, det T) at time t."""
        _, A12, _, A22, _, _ = self.blocks(t)
        return _solvability(self.T_of(t), self.Tdot_of(t), self.F, A22, A12, self.C1_of(t))

    def check_horizon(self, t0, t1, num=201):
        """Raise ValueError if the condition or det T ≠ 0 fails somewhere on [t0, t1]."""
        _check_over(self, _time_grid((t0, t1), num), "GeneralizedInverseReduced")
        return self

    def check_span(self, t0, t1):
        """The checks of :meth:`check_horizon` on a simulated span (:func:`_check_span`)."""
        return _check_span(self, t0, t1, "GeneralizedInverseReduced")

    def check(self):
        ts = [0.0] if self.horizon is None else _time_grid(self.horizon, self.num_checks)
        _check_over(self, ts, "GeneralizedInverseReduced")
        return self

    def prepare(self):
        """The checks of :meth:`check` once per simulation: eagerly when the values are concrete
        (``ValueError``), by ``eqx.error_if`` when anything they depend on is traced (F, C1, the
        model's or T's leaves, or values T closes over)."""
        ts = [0.0] if self.horizon is None else _time_grid(self.horizon, self.num_checks)
        if _check_over(self, ts, "GeneralizedInverseReduced"):
            return self
        return eqx.tree_at(lambda o: o.F, self, _guard_traced(self, "GeneralizedInverseReduced"))

    def z_of(self, t, p, y):
        """z = p + G y, the estimate of T w."""
        return p + self.G_of(t) @ y

    # --- the observer protocol -------------------------------------------------------------------
    def init(self, t0, xhat0, y0):
        """p0 = T(t0) ŵ0 − G(t0) y0, with ŵ0 = xhat0[m:] (so z0 = T(t0) ŵ0)."""
        w0 = jnp.asarray(xhat0)[self.m :]
        return self.T_of(t0) @ w0 - self.G_of(t0) @ jnp.asarray(y0)

    def init_from_z(self, t0, z0, y0):
        """p0 = z0 − G(t0) y0 (the slides give z0 directly)."""
        return jnp.asarray(z0) - self.G_of(t0) @ jnp.asarray(y0)

    def _T_G(self, t):
        """(T, G) at t with Ṫ from one forward-mode pass (jax.jvp in t)."""
        T, Td = jax.jvp(self.T_of, (t,), (jnp.ones_like(t),))
        G = (Td + T @ self.blocks(t)[3] - self.F @ T) @ self.C1_of(t)
        return T, G

    def vector_field(self, t, z, y, u):
        p = z
        t = jnp.asarray(t, dtype=self.F.dtype)
        A11, _, A21, _, B1, B2 = self.blocks(t)
        # T, G and Ġ in one nested forward-mode pass (the same quantities as T_of, G_of, Gdot_of)
        (T, G), (_, Gdot) = jax.jvp(self._T_G, (t,), (jnp.ones_like(t),))
        dp = self.F @ (p + G @ y) + (T @ A21 - G @ A11 - Gdot) @ y
        if B1.shape[1] > 0:
            dp = dp + (T @ B2 - G @ B1) @ u
        return dp

    def estimate(self, t, z, y):
        w = jnp.linalg.solve(self.T_of(t), self.z_of(t, z, y))
        return jnp.concatenate([jnp.asarray(y), w])


class GeneralizedInverseODE(AbstractObserver):
    """Lovass-Nagy full-state LTV observer with T(t) from the design condition solved as a matrix ODE.

    The solvability condition (Ṫ + T A − F T)(I − C^{1} C) = 0 (slides, step 3) holds iff
    Ṫ + T A − F T = G C for some G; so for any free gain G(t) the pair

        Ṫ = F T − T A + G C,                 ż = F z + G y + T B u,       x̂ = T⁻¹ z          (9), (2), (8)

    satisfies (6) by construction and d/dt(z − T x) = F (z − T x) (7): z − T x = e^{F(t−t0)}(z0 − T0 x0).
    T is integrated together with z (the observer state is (z, T)), so the law holds to the solver's
    tolerance, for any (A(t), C(t)) — constant or time-varying C, any number of outputs — without the rank
    condition of :func:`obsjax.design.lovass_nagy_T`.  The gain of step 5, G_LN = (Ṫ + T A − F T) C^{1}
    = G C C^{1}, gives G_LN y = G y for every y in range C, so G is used directly (no {1}-inverse needed).

    What remains of the procedure is step 4, det T ≠ 0: a design choice of G, of F's entries above its
    diagonal and of T(t0).  By default T(t0) is the frozen Sylvester solution T A(t0) − F T = G(t0) C(t0)
    (:func:`obsjax.design.frozen_T0`), invertible for observable (A(t0), C(t0)) and controllable (F, G).
    With `horizon`, T is integrated once at construction (:func:`obsjax.design.lovass_nagy_T_ode`) and a
    singular T (scale-invariant test σ_min/σ_max ≤ `rcond_min`, or a sign change of det T) raises
    ``ValueError`` naming the time.  In a simulation a singular T makes x̂ non-finite (status 2 with
    ``throw=False``).

    **Arguments:**

    - `model`: the observer's plant model (``obsjax.LTV`` or ``obsjax.LTI``).
    - `F`: (n, n) constant observer matrix, eigenvalues in the open left half-plane (a leaf).
    - `G`: (n, m) constant gain (a leaf) or a callable of t.
    - `T0`: optional (n, n) T(t0) (a leaf); the frozen Sylvester solution at t0 when ``None``.
    - `horizon`: optional (t0, t1) on which invertibility of T is checked at construction
      (`num_checks` points; T0 must then be given or computed at t0 = horizon[0]).
    - `rcond_min`: smallest admissible σ_min(T)/σ_max(T) for that check.

    **Example:** 3 states, 1 output (where the algebraic completion does not exist)::

        plant = obsjax.LTV(A, lambda t: jnp.array([[1., 0., 0.]]))
        obs = obsjax.GeneralizedInverseODE(plant, jnp.diag(jnp.array([-4., -5., -6.])), jnp.ones((3, 1)),
                                           horizon=(0.0, 10.0))
        traj = obsjax.simulate(plant, obs, x0, jnp.zeros(3), ts)
    """

    model: eqx.Module
    F: jax.Array
    G: jax.Array | Callable
    T0: jax.Array | None
    horizon: tuple[float, float] | None = eqx.field(static=True)
    num_checks: int = eqx.field(static=True)
    rcond_min: float = eqx.field(static=True)

    def __init__(self, model, F, G, T0=None, *, horizon=None, num_checks=201, rcond_min=1e-10):
        require_no_feedthrough(model, "GeneralizedInverseODE")
        n, m = int(model.n), int(model.m)
        self.model = model
        self.F = require_finite(matrix(F, "F", (n, n)), "F")
        if callable(G):
            shape = tuple(jax.eval_shape(G, jnp.asarray(0.0)).shape)
            if shape != (n, m):
                raise ValueError(f"`G(t)` must return shape ({n}, {m}), got {shape}.")
            self.G = G
        else:
            self.G = require_finite(matrix(G, "G", (n, m)), "G")
        self.T0 = None if T0 is None else require_finite(matrix(T0, "T0", (n, n)), "T0")
        self.horizon = None if horizon is None else (float(horizon[0]), float(horizon[1]))
        self.num_checks = int(num_checks)
        self.rcond_min = float(rcond_min)
        _require_stable_F(self.F, "z − T x = e^{Ft}(z0 − T0 x0)")
        self.check()

    def G_of(self, t):
        return jnp.asarray(self.G(t)) if callable(self.G) else self.G

    def T0_of(self, t0):
        """T(t0): the given T0, or the frozen Sylvester solution T A(t0) − F T = G(t0) C(t0)."""
        if self.T0 is not None:
            return self.T0
        from ..design._ginverse import frozen_T0

        return frozen_T0(self.model.A_of(t0), self.model.C_of(t0), self.F, self.G_of(t0))

    def T_flow(self, ts):
        """T(t) on the times `ts` from T(ts[0]) (:func:`obsjax.design.lovass_nagy_T_ode`)."""
        from ..design._ginverse import lovass_nagy_T_ode

        ts = jnp.asarray(ts, dtype=float)
        return lovass_nagy_T_ode(
            self.model.A_of, self.model.C_of, self.F, self.G_of, ts, T0=self.T0_of(ts[0]),
            rcond_min=self.rcond_min,
        )

    def check_horizon(self, t0, t1, num=201):
        """Raise ValueError if T(t) from T(t0) becomes singular on [t0, t1]."""
        self.T_flow(_time_grid((t0, t1), num))
        return self

    def check(self):
        if self.horizon is not None:
            self.check_horizon(*self.horizon, num=self.num_checks)
        return self

    # --- the observer protocol -------------------------------------------------------------------
    def init(self, t0, xhat0, y0):
        """(z0, T0) with z0 = T0 x̂0."""
        T0 = self.T0_of(jnp.asarray(t0, dtype=self.F.dtype))
        return (T0 @ jnp.asarray(xhat0), T0)

    def vector_field(self, t, z, y, u):
        zz, T = z
        G = self.G_of(t)
        dz = self.F @ zz + G @ y
        B = self.model.B_of(t)
        if B.shape[1] > 0:
            dz = dz + T @ (B @ u)
        dT = self.F @ T - T @ self.model.A_of(t) + G @ self.model.C_of(t)
        return (dz, dT)

    def estimate(self, t, z, y):
        zz, T = z
        return jnp.linalg.solve(T, zz)
