"""The Luenberger family for LTI plants (Hassan thesis, chapters 2 and 3)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value, device_array, matrix, require_finite, vector
from ..analysis._lti import balancing, require_observable
from ..design._place import (
    as_design_matrix,
    design_pair,
    observability_indices,
    place_real,
    pole_vector,
    warn_jordan,
)
from ..design._poles import (
    PoleStructure,
    blocks_of,
    decode,
    default_structure,
    encode,
    pole_structure,
)
from ..systems._plants import LTI
from ._base import AbstractObserver, require_no_feedthrough


def _require_lti(model, who):
    if not isinstance(model, LTI):
        raise ValueError(f"{who} needs an obsjax.LTI model, got {type(model).__name__}.")


def _finite_gain(G, name: str, who: str):
    """A given gain: concrete values must be finite (``ValueError``), traced ones are checked at run time."""
    v = concrete_value(G)
    if v is not None and not np.all(np.isfinite(v)):
        raise ValueError(f"{who}: the gain `{name}` must be finite, got {v.tolist()}.")
    return G


def _poles_leaf(poles, n: int, structure, who: str):
    """(real-encoded poles, structure): complex poles never become a complex leaf (a pair a ± ib is kept
    as a and b, see :func:`obsjax.design.pole_structure`); traced poles are taken as already encoded."""
    p = pole_vector(poles, n, who)
    v = concrete_value(p)
    if v is None:
        if jnp.issubdtype(p.dtype, jnp.complexfloating):
            raise ValueError(f"{who}: traced complex `poles`; pass their real encoding and `structure`.")
        return p, default_structure(n) if structure is None else structure
    if np.iscomplexobj(v) or structure is None:
        found = pole_structure(v)
        return device_array(encode(v, found)), found
    if not isinstance(structure, PoleStructure) or structure.n != n:
        raise ValueError(f"{who}: `structure` must be a PoleStructure of {n} poles.")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{who}: `poles` must be finite, got {v.tolist()}.")
    re, im = decode(v, structure)
    found = pole_structure(np.asarray(re) + 1j * np.asarray(im))
    if found != structure:
        # (a repeated pole that the values do not have was warned about, and the gain then failed at run
        # time with a callback error)
        raise ValueError(
            f"{who}: `structure` {structure} does not match the pattern of `poles` {found} (read from "
            "their real encoding: a pair a ± ib as a, b)."
        )
    return p, structure


def _chains(A, C, structure, poles, tol, who, independent_outputs=False):
    """(Jordan chains, observability indices) of the assignment, decided at construction on the
    concrete model ((None, None) when it is traced)."""
    Av, Cv = concrete_value(A), concrete_value(C)
    if Av is None or Cv is None:
        return None, None
    st = require_observable(Av, Cv, tol, who, independent_outputs=independent_outputs)
    blocks = blocks_of(structure, Cv.shape[0], st.kronecker)
    pr, pi = decode(poles, structure)
    warn_jordan(structure, blocks, pr, pi, Cv.shape[0], st.kronecker, who, stacklevel=5)
    return blocks, st.indices


class Luenberger(AbstractObserver):
    """Identity (full-order) observer, thesis (2.7):

        ż = (A − L C) z + L y + B u − L D u,      x̂ = z.

    The error x̃ = x̂ − x obeys dx̃/dt = (A − LC) x̃ (Theorem 1 with T = I).

    **Arguments:** `model` (an :class:`obsjax.LTI`, the observer's own model of the plant); `L` (n, m) gain
    (finite: a NaN or an infinity is refused, at run time under jit); or `poles` (see :meth:`from_poles`).
    With poles, L is recomputed by :func:`obsjax.design.place` once per simulation and the poles are the
    differentiable leaf (``tune(..., where=lambda o: o.poles)``).  A conjugate pair a ± ib is stored as
    the two real numbers a (at the position of a + ib) and b > 0 (at that of a − ib), so that no complex
    leaf reaches diffrax and sign-preserving tuning keeps the pair stable and complex; :attr:`spectrum`
    gives the complex poles.  `method` (``"robust"`` or ``"canonical"``) and `tol` are those of
    :func:`obsjax.design.place`; the observability of the model and the Jordan structure of repeated
    poles are decided at construction on the concrete model (a warning names poles that need Jordan
    chains); `structure` (:func:`obsjax.design.pole_structure`) declares the pattern of traced poles.
    Poles are placed as given, in the right half-plane too (an unstable observer is a legitimate object
    of study; its error grows, which the trajectory shows).  Traced poles that are not finite (one
    member of a vmapped batch) give a NaN gain: that member's status is NONFINITE and the others run
    on; ``simulate(throw=True)`` raises on it.

    **Example:** thesis example (2.8)::

        plant = obsjax.LTI([[-2., 1.], [0., -1.]], [[0.], [1.]], [[1., 0.]])
        obs = obsjax.Luenberger.from_poles(plant, [-3., -3.])
        obs.gain   # [[3.], [4.]]
    """

    model: LTI
    L: jax.Array | None
    poles: jax.Array | None
    structure: PoleStructure | None = eqx.field(static=True, default=None)
    chains: tuple | None = eqx.field(static=True, default=None)
    indices: tuple | None = eqx.field(static=True, default=None)
    method: str = eqx.field(static=True, default="robust")

    def __init__(self, model, L=None, poles=None, *, structure=None, method="robust", tol=None):
        _require_lti(model, "Luenberger")
        if (L is None) == (poles is None):
            raise ValueError("Luenberger needs exactly one of `L` (a gain) or `poles` (use from_poles).")
        if method not in ("robust", "canonical"):
            raise ValueError(f"`method` must be 'robust' or 'canonical', got {method!r}.")
        self.model = model
        self.method = method
        if L is not None:
            self.L = _finite_gain(as_design_matrix(matrix(L, "L", (model.n, model.m)), "L"), "L", "Luenberger")
            self.poles, self.structure, self.chains, self.indices = None, None, None, None
            return
        self.L = None
        self.poles, self.structure = _poles_leaf(poles, model.n, structure, "Luenberger")
        self.chains, self.indices = _chains(
            model.A, model.C, self.structure, self.poles, tol, "Luenberger", independent_outputs=True
        )

    @classmethod
    def from_poles(cls, model, poles, *, method="robust", tol=None) -> Luenberger:
        """Observer with eig(A − LC) = ``poles`` (the poles are the tunable leaf).

        ``method`` and ``tol`` are those of :func:`obsjax.design.place`; the observability of the model
        and the Jordan structure of repeated poles are decided here, on the concrete model.
        """
        _require_lti(model, "Luenberger.from_poles")
        return cls(model, poles=poles, method=method, tol=tol)

    @property
    def spectrum(self) -> jax.Array | None:
        """The requested poles as complex numbers (``None`` for a given gain)."""
        if self.poles is None:
            return None
        re, im = decode(self.poles, self.structure)
        return re + 1j * im

    @property
    def gain(self) -> jax.Array:
        """The gain L (computed from the poles when designed by placement)."""
        if self.L is not None:
            return self.L
        A, C = design_pair(self.model.A, self.model.C, "Luenberger")
        re, im = decode(self.poles, self.structure)
        return place_real(
            A,
            C,
            re,
            im,
            self.structure,
            method=self.method,
            blocks=self.chains,
            indices=self.indices,
            warn=False,
            who="Luenberger",
            nan_for_nonfinite_poles=True,
        )

    def prepare(self):
        if self.L is not None:
            # a traced non-finite gain is not raised here: the trajectory's status says NONFINITE (per
            # member under vmap), and simulate(throw=True) raises on it
            return self
        return eqx.tree_at(lambda o: o.L, self, self.gain, is_leaf=lambda x: x is None)

    @property
    def observer_matrix(self) -> jax.Array:
        """F = A − L C."""
        return self.model.A - self.gain @ self.model.C

    def init(self, t0, xhat0, y0):
        return vector(xhat0, "xhat0", self.model.n)

    def vector_field(self, t, z, y, u):
        M = self.model
        L = self.gain
        return M.A @ z + M.B @ u + L @ (y - M.C @ z - M.D @ u)

    def estimate(self, t, z, y):
        return z


def _balanced_units(A, C):
    """State and output scalings (d, e) of the balanced pair (units of states and outputs taken out, as
    the rank decisions of the design layer do), in NumPy."""
    return balancing(np.asarray(A, float), np.asarray(C, float))


def _complement(C, tol=None, A=None):
    """Rows D completing C to a nonsingular M = [C; D]: an orthonormal basis of the null space of C.

    The rank of C is decided in the balanced units of (A, C) (`A` given; unit rows of C otherwise), so that
    independent sensors in very different units are not declared dependent; where the unscaled C already
    has full row rank its own orthonormal null-space basis is kept (the thesis's examples' gains)."""
    C = np.asarray(C, float)
    m = C.shape[0]
    tol = 1e-9 if tol is None else tol
    _, s0, vt0 = np.linalg.svd(C)
    if int(np.sum(s0 > tol * max(s0[0], np.finfo(float).tiny))) == m:
        return vt0[m:]
    d, e = _balanced_units(A, C) if A is not None else (np.ones(C.shape[1]), np.ones(m))
    Cb = e[:, None] * C * d[None, :]
    Cb = Cb / np.maximum(np.linalg.norm(Cb, axis=1, keepdims=True), np.finfo(float).tiny)
    _, s, vt = np.linalg.svd(Cb)
    r = int(np.sum(s > tol * max(s[0], np.finfo(float).tiny)))
    if r < m:
        raise ValueError(
            f"`C` must have full row rank m = {m} for a reduced-order observer, got rank {r} "
            f"(relative tolerance {tol:.1e}, in balanced units)."
        )
    # C (d ⊙ w) = 0 where (E C D) w = 0: the null space in the original units, orthonormalised
    q, _ = np.linalg.qr((vt[m:] * d[None, :]).T)
    return q.T


def _a12_rank(A12):
    """The rank of a concrete A12 (rows normalised: in any units of the outputs); ``None`` when traced."""
    v = concrete_value(A12)
    if v is None:
        return None
    return _numerical_rank(np.linalg.svd(_rows_normalised(np.asarray(v, float))[0], compute_uv=False))


def _numerical_rank(sv):
    return int(np.sum(sv > 1e-12 * sv[0])) if sv.size and sv[0] > 0 else 0


def _rows_normalised(a, xp=np):
    """(N a, N) with N = diag(1/‖row‖) (zero rows left as they are)."""
    norms = xp.linalg.norm(a, axis=1)
    inv = xp.where(norms > 0, 1.0 / xp.where(norms > 0, norms, 1.0), 1.0)
    return a * inv[:, None], inv


def _compress_rows(A12, rank=None):
    """(R, Q) with R = Qᵀ A12 and Q (m × r) of full column rank when the rows of A12 are dependent (more
    outputs than unmeasured states, m > n − m, or outputs that see the unmeasured states through the
    same combination), else (A12, None).  Then A22 − G A12 = A22 − G_r R for G = G_r Qᵀ, and (A22, R) is
    observable exactly when (A22, A12) is (A12 v = 0 ⟺ R v = 0): the poles are placed on r independent
    rows.  With full column rank and m > n − m, A12 = Q R is the reduced QR; with rank r, Q = N U_r, U_r
    the leading left singular vectors of N A12, N = diag(1/‖row‖) (so that the rank does not depend on
    the outputs' units).  The rank is decided on the concrete A12, or is `rank`, the rank decided at
    construction, when A12 is traced."""
    m, k = A12.shape
    v = concrete_value(A12)
    if v is not None:  # one SVD in NumPy gives the rank and the basis
        An, inv = _rows_normalised(np.asarray(v, float))
        U, sv, _ = np.linalg.svd(An, full_matrices=False)
        r = _numerical_rank(sv)
        Qr = (jnp.asarray(inv)[:, None] * jnp.asarray(U[:, :r])) if 0 < r else None
    else:
        r = rank
        Qr = None
        if r is not None and 0 < r < min(m, k):  # dependent rows: keep r of them
            An, inv = _rows_normalised(A12, jnp)
            Qr = inv[:, None] * jnp.linalg.svd(An, full_matrices=False)[0][:, :r]
    if r is None or r == 0 or (m <= k and r == m):
        return A12, None  # independent rows (or nothing to keep): the pair as it is
    if m > k and r == k:
        Q, R = jnp.linalg.qr(A12, mode="reduced")
        return R, Q
    return Qr.T @ A12, Qr


class ReducedOrder(AbstractObserver):
    """Reduced-order observer of order n − m, thesis (2.13)-(2.16).

    With M = [C; D] nonsingular and x̄ = M x = [y; w], the plant reads
    ẏ = A11 y + A12 w + B1 u, ẇ = A21 y + A22 w + B2 u (2.13).  The observer (2.15)-(2.16) is

        ż = (A22 − G A12) z + [(A22 − G A12) G + A21 − G A11] y + (B2 − G B1) u,
        ŵ = z + G y,      x̂ = M⁻¹ [y; ŵ],

    so that ŵ − w obeys d/dt(ŵ − w) = (A22 − G A12)(ŵ − w) without differentiating y.

    **Arguments:** `model` (LTI with D = 0), `G` ((n−m), m) gain (finite) or `poles` (n − m of them,
    placed on the pair (A22, A12) by :func:`obsjax.design.place` -- on (A22, R) with A12 = Q R and
    G = G_r Qᵀ when there are more outputs than unmeasured states --, stored as real numbers like
    :class:`Luenberger`'s), `Dc` ((n−m), n) rows completing C (an orthonormal null-space basis of C when
    ``None``).

    **Example:** the thesis plant (2.8) with pole −3 gives G = 2 (A22 − G A12 = −1 − G).
    """

    model: LTI
    G: jax.Array | None
    poles: jax.Array | None
    Dc: jax.Array
    structure: PoleStructure | None = eqx.field(static=True, default=None)
    chains: tuple | None = eqx.field(static=True, default=None)
    a12_rank: int | None = eqx.field(static=True, default=None)  # decided at construction

    def __init__(self, model, G=None, poles=None, Dc=None, *, structure=None, tol=None):
        _require_lti(model, "ReducedOrder")
        n, m = model.n, model.m
        if m >= n:
            raise ValueError(f"ReducedOrder needs fewer outputs than states, got m = {m}, n = {n}.")
        _require_no_feedthrough(model, "ReducedOrder")
        if (G is None) == (poles is None):
            raise ValueError("ReducedOrder needs exactly one of `G` (a gain) or `poles`.")
        if Dc is None:
            Cv = concrete_value(model.C)
            if Cv is None:
                raise ValueError("`Dc` must be given when the model's C is traced.")
            Dc = _complement(Cv, tol, concrete_value(model.A))
        Dc = require_finite(matrix(Dc, "Dc", (n - m, n)), "Dc")
        Mv = concrete_value(jnp.concatenate([model.C, Dc]))
        if Mv is not None:
            # in units of the states where the pair is balanced, rows normalised: a test of M that does
            # not depend on the units of states or outputs
            Av = concrete_value(model.A)
            d = _balanced_units(Av, Mv[:m])[0] if Av is not None else np.ones(n)
            Mb = Mv * d[None, :]
            Mb = Mb / np.maximum(np.linalg.norm(Mb, axis=1, keepdims=True), np.finfo(float).tiny)
            sv = np.linalg.svd(Mb, compute_uv=False)
            if not sv[-1] > 1e-12 * sv[0]:
                raise ValueError(
                    "M = [C; Dc] must be nonsingular: `Dc` does not complete `C` "
                    f"(σ_min/σ_max = {sv[-1] / sv[0]:.1e})."
                )
        self.model, self.Dc = model, Dc
        if G is not None:
            self.G = _finite_gain(as_design_matrix(matrix(G, "G", (n - m, m)), "G"), "G", "ReducedOrder")
            self.poles, self.structure, self.chains = None, None, None
            return
        self.G = None
        self.poles, self.structure = _poles_leaf(poles, n - m, structure, "ReducedOrder")
        _, _, _, A12, _, A22, _, _ = self._blocks()
        self.a12_rank = _a12_rank(A12)
        self.chains, _ = _chains(
            A22, _compress_rows(A12)[0], self.structure, self.poles, tol, "ReducedOrder (pair (A22, A12))"
        )

    @classmethod
    def from_poles(cls, model, poles, Dc=None, *, tol=None) -> ReducedOrder:
        """Reduced-order observer with eig(A22 − G A12) = ``poles`` (n − m poles)."""
        return cls(model, poles=poles, Dc=Dc, tol=tol)

    def _blocks(self):
        M = jnp.concatenate([self.model.C, self.Dc])
        Minv = jnp.linalg.inv(M)
        Ab = M @ self.model.A @ Minv
        Bb = M @ self.model.B
        m = self.model.m
        return M, Minv, Ab[:m, :m], Ab[:m, m:], Ab[m:, :m], Ab[m:, m:], Bb[:m], Bb[m:]

    @property
    def spectrum(self) -> jax.Array | None:
        """The requested poles as complex numbers (``None`` for a given gain)."""
        if self.poles is None:
            return None
        re, im = decode(self.poles, self.structure)
        return re + 1j * im

    @property
    def gain(self):
        if self.G is not None:
            return self.G
        _, _, _, A12, _, A22, _, _ = self._blocks()
        A12r, Q = _compress_rows(A12, self.a12_rank)
        A22, A12r = design_pair(A22, A12r, "ReducedOrder")
        re, im = decode(self.poles, self.structure)
        Gr = place_real(
            A22, A12r, re, im, self.structure, blocks=self.chains, warn=False, who="ReducedOrder",
            nan_for_nonfinite_poles=True,
        )
        return Gr if Q is None else Gr @ Q.T

    def prepare(self):
        if self.G is not None:
            return self  # a traced non-finite gain: the trajectory's status (NONFINITE), as for L
        return eqx.tree_at(lambda o: o.G, self, self.gain, is_leaf=lambda x: x is None)

    def init(self, t0, xhat0, y0):
        M, _, *_ = self._blocks()
        w0 = (M @ vector(xhat0, "xhat0", self.model.n))[self.model.m :]
        return w0 - self.gain @ y0

    def vector_field(self, t, z, y, u):
        _, _, A11, A12, A21, A22, B1, B2 = self._blocks()
        G = self.gain
        F = A22 - G @ A12
        return F @ z + (F @ G + A21 - G @ A11) @ y + (B2 - G @ B1) @ u

    def estimate(self, t, z, y):
        _, Minv, *_ = self._blocks()
        return Minv @ jnp.concatenate([y, z + self.gain @ y])


def _equilibrate(M, sweeps: int = 8):
    """Row and column scalings (powers of two) making every row and column of M of unit size (Ruiz):
    the least-squares solve and its residual then do not depend on the units of A, C and a."""
    r, c = np.ones(M.shape[0]), np.ones(M.shape[1])
    for _ in range(sweeps):
        S = np.abs(M / r[:, None] / c[None, :])
        rr, cc = S.max(axis=1), S.max(axis=0)
        r *= np.where(rr > 0, 2.0 ** np.round(np.log2(np.where(rr > 0, rr, 1.0)) / 2), 1.0)
        c *= np.where(cc > 0, 2.0 ** np.round(np.log2(np.where(cc > 0, cc, 1.0)) / 2), 1.0)
    return r, c


#: FunctionalObserver refuses conditions whose equilibrated matrix has σ_min/σ_max at or below this: its
#: least-squares solution is then another observer (a unique design with σ_min/σ_max ≈ 1e-16 was returned
#: with kᵀTx0 = −17.7 for 1.0e6), though its residual passes.
_FUNCTIONAL_SINGULAR = 1e-12


def _state_balancing(A, C) -> np.ndarray:
    """The state scaling d of the balanced pair (:func:`obsjax.analysis._lti.balancing`), rounded to powers
    of two (exact to apply and undo): FunctionalObserver is designed in the units x = diag(d) x_b."""
    A, C = np.asarray(A, float), np.asarray(C, float)
    if not A.size:
        return np.ones(A.shape[0])
    d, _ = balancing(A, C)
    return 2.0 ** np.round(np.log2(d))


def _functional_conditions(A, F, C, k, xp=np):
    """The matrix of FunctionalObserver's conditions T A − F T − G C = 0 (r n rows) and kᵀ T + eᵀ C = aᵀ
    (n rows) in the unknowns (vec T, vec G, e), vec row-major; `xp` is ``np`` (concrete) or ``jnp``
    (traced poles)."""
    n, m, r = A.shape[0], C.shape[0], F.shape[0]
    nT, nG = r * n, r * m
    eye_r, eye_n = xp.eye(r, dtype=A.dtype), xp.eye(n, dtype=A.dtype)
    top = xp.concatenate(
        [xp.kron(eye_r, A.T) - xp.kron(F, eye_n), -xp.kron(eye_r, C.T), xp.zeros((nT, m), A.dtype)],
        axis=1,
    )
    bottom = xp.concatenate([xp.kron(k[None, :], eye_n), xp.zeros((n, nG), A.dtype), C.T], axis=1)
    return xp.concatenate([top, bottom], axis=0)


def _functional_equilibration(A, C, r: int):
    """Row and column scalings of FunctionalObserver's conditions, from A/‖A‖₂ and C alone (concrete).

    With several outputs the conditions have many solutions and the observer is the minimum-norm one in
    the column-scaled unknowns, so the column scaling chooses the observer: it must not depend on the
    poles, or the chosen observer would jump as they move (powers of two switching) and a traced
    design could differ from the eager one by the rounding of a logarithm.  The poles' companion block
    is left out (it is of order 1 in the poles' time unit, in which the conditions are solved)."""
    a_norm = np.linalg.norm(A, 2) if A.size else 0.0
    Au = A / a_norm if a_norm > 0 else A
    return _equilibrate(_functional_conditions(Au, np.zeros((r, r)), C, _functional_k(r)))


def _functional_k(r: int, xp=np):
    """k = e_r: the functional is read from the last state of the companion-form observer."""
    k = np.zeros(r)
    if r:
        k[-1] = 1.0
    return xp.asarray(k)


def _functional_singular_message(ratio=None) -> str:
    got = "" if ratio is None else f" (σ_min/σ_max = {ratio:.1e} of the equilibrated system)"
    return (
        f"FunctionalObserver: the conditions TA − FT = GC, aᵀ = kᵀT + eᵀC are numerically singular with "
        f"these poles{got}: a least-squares solution would be another observer.  Choose other poles "
        "(closer to the plant's time scale)."
    )


def _functional_residual_message(r: int, rtol: float, res=None) -> str:
    got = "above" if res is None else f"{res:.2e} >"
    return (
        f"The functional aᵀx cannot be observed with order ν − 1 = {r} and these poles (relative "
        f"residual {got} rtol = {rtol:.1e} of TA − FT = GC, aᵀ = kᵀT + eᵀC)."
    )


@jax.custom_jvp
def _min_norm_solve(M, b):
    """The minimum-norm solution x = M⁺ b of a consistent system (SVD, the cut-off of NumPy's lstsq),
    with a derivative that stays accurate when M is ill-conditioned (see ``_min_norm_solve_jvp``), and
    M's singular values (carrying no derivative: for the conditioning test)."""
    x, (_, _, _, _, s) = _min_norm_parts(M, b)
    return x, s


def _min_norm_parts(M, b):
    U, s, Vt = jnp.linalg.svd(M, full_matrices=True)
    cut = s[0] * float(np.finfo(float).eps) * max(M.shape) if s.size else 0.0
    keep = s > cut
    inv = jnp.where(keep, 1.0 / jnp.where(keep, s, 1.0), 0.0)
    k = s.shape[0]
    x = Vt[:k].T @ (inv * (U[:, :k].T @ b))
    # the null space of M: the right singular vectors of the cut singular values and those beyond min(rows, cols)
    null = jnp.concatenate([~keep, jnp.ones(Vt.shape[0] - k, bool)])
    return x, (U[:, :k], inv, Vt, null, s)


@_min_norm_solve.defjvp
def _min_norm_solve_jvp(primals, tangents):
    """d(M⁺b) for a consistent system of constant rank: −M⁺(dM x − db) + P_N dMᵀ M⁺ᵀ x, P_N the
    projector on the null space of M (from the singular vectors themselves).  The term of the
    least-squares residual (b − Mx, zero for a consistent system) is left out: JAX's pseudo-inverse
    derivative keeps it, and with the projectors I − MM⁺, I − M⁺M formed by subtraction its rounding was
    amplified by cond(M)² (a derivative 10³ times too large on a single-output design with poles from
    −0.1 to −100)."""
    M, b = primals
    dM, db = tangents
    x, (Uk, inv, Vt, null, s) = _min_norm_parts(M, b)
    k = inv.shape[0]

    def pinv_apply(v):  # M⁺ v
        return Vt[:k].T @ (inv * (Uk.T @ v))

    dx = -pinv_apply(dM @ x - db)
    z = Uk @ (inv * (Vt[:k] @ x))  # M⁺ᵀ x
    Vn = Vt.T * null[None, :]
    dx = dx + Vn @ (Vn.T @ (dM.T @ z))
    return (x, s), (dx, jnp.zeros_like(s))


def _companion(coeffs):
    """Observer-companion matrix F (r, r) with characteristic polynomial coeffs = [1, c1, …, cr]."""
    r = coeffs.shape[0] - 1
    F = np.zeros((r, r))
    if r > 1:
        F[1:, :-1] = np.eye(r - 1)
    F[:, -1] = -np.asarray(coeffs[1:])[::-1]
    return F


# the observers built on y = Cx alone (reduced-order, functional) need D = 0
_require_no_feedthrough = require_no_feedthrough


class FunctionalObserver(AbstractObserver):
    """Observer of a single linear functional s = aᵀx with ν − 1 arbitrary poles (thesis §3.3, Theorem II).

    ν is the observability index (thesis §3.2, decided by the staircase form: it does not change when
    A → cA or C → dC).  The observer of order r = ν − 1 is

        ż = F z + G y + T B u,      ŝ = kᵀ z + eᵀ y,

    with T A − F T = G C (Theorem 1, (2.4)) and aᵀ = kᵀ T + eᵀ C, so that ŝ − s = kᵀ e^{Ft}(z(0) − T x(0)).
    F = σ F_σ, F_σ the observer-companion matrix of the poles divided by σ = √(mean |p_i|² + ‖A_b‖₂²), A_b
    the plant's A in balanced state units (the companion form in a time unit of the poles and the plant,
    which no change of the units of time, states or outputs changes; its eigenvalues are the requested
    poles),
    and k = e_r; the linear conditions are solved for (T, G, e) in balanced state units (x = D x_b, D the
    state scaling of the balanced pair, powers of two; then T = T_b D⁻¹) and in that time unit, by least
    squares with equilibrated rows and columns (powers of two, from the balanced A/‖A‖₂ and C), so that
    neither the design nor its tests depend on the units of time, states, outputs and a.  A relative
    residual above ``rtol`` raises ``ValueError`` (the functional is not observable with that order), and
    so do conditions that are numerically singular (σ_min/σ_max ≤ 1e-12 of the equilibrated system: poles
    far from the plant's time scale), whose least-squares solution would be another observer.  When ν = 1
    (r = 0) the functional is a static map of y.

    ``estimate`` returns ŝ (shape (1,)) and ``target(t, x) = aᵀx``, so ``Trajectory.error`` is ŝ − aᵀx.

    **Arguments:** `model` (LTI, D = 0), `a` (n,) the functional, `poles` (ν − 1 of them, real or
    conjugate pairs), `tol` (rank decisions, see :func:`obsjax.analysis.observability_staircase`),
    `rtol` (solvability residual, default 1e-8).  T, G, e are computed at construction.

    Gradients with respect to the poles: the construction is traceable in real poles, so a loss of a
    simulation of ``FunctionalObserver(model, a, poles)`` can be differentiated in `poles` (``jax.grad``,
    ``jax.jacfwd``) and built under ``jax.jit``: the same conditions are solved with JAX (minimum-norm
    least squares through the SVD, the same equilibration, with a derivative that stays accurate on
    ill-conditioned designs), the residual test runs
    as a run-time check (``eqx.error_if``), and non-finite poles are refused there.  The model, `a` and
    the order stay concrete; traced complex poles are refused (a conjugate pair is built from concrete
    poles only).  With several outputs the conditions have many solutions: the observer is the
    minimum-norm solution in unknowns scaled by powers of two chosen from A and C alone, so it moves
    smoothly with the poles and the traced design is the eager one.  First derivatives only (``jax.hessian``
    is not available through the minimum-norm solve).  The stored leaves (F, T, G, k, e) are those of one design:
    ``tune`` on them moves them apart from the conditions, so tune the poles through construction.

    **Example:** thesis §3.3, x2 + x4 of the fourth-order example with the pole −3::

        obs = obsjax.FunctionalObserver(plant4, [0., 1., 0., 1.], [-3.])
    """

    model: LTI
    a: jax.Array
    F: jax.Array
    T: jax.Array
    G: jax.Array
    k: jax.Array
    e: jax.Array

    def __init__(self, model, a, poles, *, tol=None, rtol=1e-8):
        _require_lti(model, "FunctionalObserver")
        _require_no_feedthrough(model, "FunctionalObserver")
        A, B, C = (concrete_value(M) for M in (model.A, model.B, model.C))
        if A is None or C is None:
            raise ValueError("FunctionalObserver is designed from concrete model matrices (not under jit).")
        design_pair(A, C, "FunctionalObserver")
        if isinstance(rtol, bool) or not (isinstance(rtol, (int, float, np.integer, np.floating)) and rtol > 0):
            raise ValueError(
                f"FunctionalObserver: `rtol` (the residual tolerance of the conditions) must be a positive "
                f"number, got {rtol!r}."
            )
        n, m = model.n, model.m
        a = require_finite(vector(a, "a", n), "a")
        nu = max(observability_indices(A, C, tol))
        r = nu - 1
        # The design runs in balanced state units x = D x_b (A_b = D⁻¹AD, C_b = CD, a_b = Da; then
        # T = T_b D⁻¹, and G, e are unchanged), so that no change of the units of the states changes it:
        # in the user's units, states in units 1e±3 made the conditions numerically singular.
        d = _state_balancing(A, C)
        A = np.asarray(A, float) * d[None, :] / d[:, None]
        C = np.asarray(C, float) * d[None, :]
        a_user, a = a, a * jnp.asarray(d)
        if any(isinstance(v, jax.core.Tracer) for v in jax.tree_util.tree_leaves(poles)):
            # traced (jit), or carrying a derivative (grad, jvp: a concrete primal is still traced)
            self._traced_design(model, A, C, a, poles, r, nu, rtol)
            self.a, self.T = a_user, self.T / jnp.asarray(d)[None, :]
            return
        pv = np.atleast_1d(np.asarray(poles))
        if pv.ndim != 1 or pv.shape[0] != r:
            raise ValueError(
                f"`poles` must hold ν − 1 = {r} poles (observability index ν = {nu}), got "
                f"{pv.shape[0] if pv.ndim == 1 else pv.shape}."
            )
        # The conditions are solved in the time unit s = √(mean |p|² + ‖A_b‖₂²) (A_b: A in balanced state
        # units): with A_s = A/s and F_s
        # the companion matrix of p/s, T A_s − F_s T = G_s C is T A − F T = G C for F = s F_s,
        # G = s G_s.  The companion matrix of p itself has entries up to |p|^r, so the test refused
        # well-posed designs after a change of time unit (A → 1e4 A, p → 1e4 p, r = 3).  (The geometric
        # mean of the poles, used before, is 0 or tiny for a pole at or near 0, which refused designs
        # accepted in another time unit; their RMS alone made A_s huge for poles all small against A,
        # refused at 1e-5·‖A‖, and switched to ‖A‖₂ at poles all 0, a jump of the design.)  s is
        # smooth in the poles, so the chosen observer is too.
        scale = 1.0
        if r > 0:
            pole_structure(pv)  # finite, conjugate-closed
            a_norm = float(np.linalg.norm(A, 2))  # A in balanced state units
            scale = float(np.sqrt(np.mean(np.abs(pv) ** 2) + a_norm**2)) or 1.0
            F = _companion(np.real(np.poly(pv / scale)))
        else:
            F = np.zeros((0, 0))
        rn, cn = _functional_equilibration(np.asarray(A, float), np.asarray(C, float), r)
        k = _functional_k(r)
        nT, nG = r * n, r * m
        Mx = _functional_conditions(np.asarray(A, float) / scale, F, np.asarray(C, float), k)
        b = np.concatenate([np.zeros(nT), np.asarray(a, float)])
        Me = Mx / rn[:, None] / cn[None, :]
        sol, *_ = np.linalg.lstsq(Me, b / rn, rcond=None)
        sol = sol / cn
        sv = np.linalg.svd(Me, compute_uv=False)
        if sv.size and not sv[-1] > _FUNCTIONAL_SINGULAR * sv[0]:
            raise ValueError(_functional_singular_message(sv[-1] / sv[0]))
        res = np.linalg.norm((Mx @ sol - b) / rn) / max(np.linalg.norm(b / rn), np.finfo(float).tiny)
        if not res <= rtol:
            raise ValueError(_functional_residual_message(r, rtol, res))
        self.model = model
        self.a = a_user
        self.F = jnp.asarray(scale * F)
        self.T = jnp.asarray(sol[:nT].reshape(r, n) / d[None, :])
        self.G = jnp.asarray(scale * sol[nT : nT + nG].reshape(r, m))
        self.k = jnp.asarray(k)
        self.e = jnp.asarray(sol[nT + nG :])

    def _traced_design(self, model, A, C, a, poles, r, nu, rtol):
        """The design of ``__init__`` for traced real poles, in JAX (see the class documentation)."""
        p = jnp.atleast_1d(jnp.asarray(poles))
        if jnp.issubdtype(p.dtype, jnp.complexfloating):
            raise ValueError(
                "FunctionalObserver: traced complex `poles`; differentiate with respect to real poles "
                "(or build the observer from concrete poles)."
            )
        if p.ndim != 1 or p.shape[0] != r:
            raise ValueError(
                f"`poles` must hold ν − 1 = {r} poles (observability index ν = {nu}), got "
                f"{p.shape[0] if p.ndim == 1 else p.shape}."
            )
        p = p.astype(jnp.result_type(float))
        n, m = A.shape[0], C.shape[0]
        a_norm = float(np.linalg.norm(np.asarray(A, float), 2))  # A in balanced state units
        rn, cn = (jnp.asarray(v) for v in _functional_equilibration(np.asarray(A, float), np.asarray(C, float), r))
        A = jnp.asarray(np.asarray(A, float))
        C = jnp.asarray(np.asarray(C, float))
        p = eqx.error_if(p, ~jnp.all(jnp.isfinite(p)), "FunctionalObserver: `poles` must be finite.")
        if r > 0:
            ms = jnp.mean(p**2) + a_norm**2
            pos = ms > 0  # (the square root's derivative at 0 is not taken)
            scale = jnp.where(pos, jnp.sqrt(jnp.where(pos, ms, 1.0)), 1.0)
            coeffs = jnp.real(jnp.poly(p / scale))
            F = jnp.zeros((r, r), A.dtype).at[:, -1].set(-coeffs[1:][::-1])
            if r > 1:
                F = F.at[1:, :-1].add(jnp.eye(r - 1, dtype=A.dtype))
        else:
            scale = jnp.asarray(1.0)
            F = jnp.zeros((0, 0), A.dtype)
        k = _functional_k(r, jnp).astype(A.dtype)
        nT, nG = r * n, r * m
        Mx = _functional_conditions(A / scale, F, C, k, jnp)
        b = jnp.concatenate([jnp.zeros(nT, A.dtype), jnp.asarray(a, A.dtype)])
        Me = Mx / rn[:, None] / cn[None, :]
        sol, sv = _min_norm_solve(Me, b / rn)
        sol = sol / cn
        sol = eqx.error_if(sol, ~(sv[-1] > _FUNCTIONAL_SINGULAR * sv[0]), _functional_singular_message())
        res = jnp.linalg.norm((Mx @ sol - b) / rn) / jnp.maximum(
            jnp.linalg.norm(b / rn), jnp.finfo(A.dtype).tiny
        )
        sol = eqx.error_if(sol, ~(res <= rtol), _functional_residual_message(r, rtol))
        self.model = model
        self.a = a
        self.F = scale * F
        self.T = sol[:nT].reshape(r, n)
        self.G = scale * sol[nT : nT + nG].reshape(r, m)
        self.k = k
        self.e = sol[nT + nG :]

    @property
    def order(self) -> int:
        return self.F.shape[0]

    def init(self, t0, xhat0, y0):
        return self.T @ vector(xhat0, "xhat0", self.model.n)

    def vector_field(self, t, z, y, u):
        return self.F @ z + self.G @ y + self.T @ (self.model.B @ u)

    def estimate(self, t, z, y):
        return jnp.atleast_1d(self.k @ z + self.e @ y)

    def target(self, t, x):
        return jnp.atleast_1d(self.a @ x)
