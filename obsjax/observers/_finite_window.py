"""Byrski & Fuksa: the minimum-norm finite-window observer and its closed loop.

Source: W. Byrski, S. Fuksa, "Optimal finite parameter observer. An application to synthesis of stabilizing
feedback for a linear system" (journal article, received March 1982).  Equation numbers below are the paper's.

For the LTI model ẋ = A x + B u, y = C x (12), the state at the end of a window of length T is an integral
of the measured output and input over the window (14)::

    x(T) = ∫₀ᵀ G1(τ) y(τ) dτ + ∫₀ᵀ G2(τ) u(τ) dτ.

Among all kernels (G1, G2) that reconstruct x(T) exactly, (16) and (18), the paper picks the one with minimal
weighted L2 norm (15).  Row i solves the two-point boundary-value problem (23)-(24) with the Hamiltonian matrix
W_i of γ_i = β_i / α_i, so the kernels are matrix exponentials (25)-(26), or (28) when every γ_i = 1.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import expm

from .._checks import as_float_array, concrete_value, scalar_value, static_value, vector
from .._config import require_x64
from ..analysis._lti import gram_relative_residuals, observability_staircase
from ..systems._plants import LTI
from ._adaptive_common import state_dimension
from ._base import AbstractObserver
from ._validation import require_finite, traced_finite

_FORMULAS = ("auto", "(25)", "(28)")


# ------------------------------------------------------------------------------------------------------
# The maths, as pure functions of the model matrices and the weights (all differentiable).
# ------------------------------------------------------------------------------------------------------


def _time_tol(span, *times):
    """Agreement allowed between two window times: 1e-9 of the window's length plus the rounding of the
    times themselves (16 ulps of the largest).  In the time unit's own terms, so that a window of
    microseconds (or of kiloseconds) is held to the same relative accuracy (an absolute 1e-9 let a
    window 2e-6 long be 0.05 % off)."""
    xp = np if all(isinstance(v, (int, float, np.generic, np.ndarray)) for v in (span, *times)) else jnp
    big = xp.max(xp.abs(xp.asarray([xp.asarray(v, dtype=float) for v in times])))
    return 1e-9 * xp.abs(xp.asarray(span, dtype=float)) + 16 * np.finfo(float).eps * big


def _window_scaling(A, B, C):
    """State scaling s (n,), powers of 2, for the design in balanced units x = diag(s) x_b.

    The Hamiltonians W = [[A, γBBᵀ], [CᵀC, −Aᵀ]] of a model with states in very different units span the
    square of that spread (x = S x_b maps W to diag(S⁻¹, S) W diag(S, S⁻¹)), and their exponentials lose
    about that many digits (states in units 1e-2 … 1e3 put the reconstruction 7e-8 off; 1e-3 … 1e3 made
    the design overflow).  Candidates for s minimise, over the nonzero entries, the spread of the
    log-magnitudes of

        A_ij s_j / s_i,    (BBᵀ)_ij / (s_i s_j),    (CᵀC)_ij s_i s_j

    about a common level (Curtis & Reid's log-magnitude scaling, least squares, minimum norm): once over
    every nonzero entry, once over the significant ones only (|A_ij| > 1e-13 max|A|, and off-diagonal
    entries of BBᵀ and CᵀC above 1e-13 of √(M_ii M_jj), their Cauchy–Schwarz bound), since rounding
    residue where A has zeros (1e-17) pulls a log-magnitude fit far apart.  Of these and s = 1, the one
    whose balanced W has the smallest Frobenius norm is taken (Osborne's criterion for a diagonal
    similarity): it never makes W worse than the user's units.  The kernels are covariant: each row of
    (G1, G2) is its own minimum-norm problem, so the rows in the user's units are those of the balanced
    design times s_i, exactly (powers of 2 scale without rounding).  The scaling carries no derivative
    (the result does not depend on it)."""
    A, B, C = (jax.lax.stop_gradient(jnp.asarray(M)) for M in (A, B, C))
    n = A.shape[0]
    eye = jnp.eye(n, dtype=A.dtype)
    pair = lambda sa, sb: (sa * eye[:, None, :] + sb * eye[None, :, :]).reshape(n * n, n)
    M, N = B @ B.T, C.T @ C
    blocks = [(A, pair(-1.0, 1.0)), (M, pair(-1.0, -1.0)), (N, pair(1.0, 1.0))]
    G = jnp.concatenate([jnp.concatenate([P, jnp.ones((n * n, 1), A.dtype)], axis=1) for _, P in blocks])
    v = jnp.concatenate([X.reshape(-1) for X, _ in blocks])
    b = jnp.log(jnp.abs(jnp.where(v != 0, v, 1.0)))

    def cauchy_schwarz(X):
        d = jnp.sqrt(jnp.abs(jnp.diagonal(X)))
        return jnp.abs(X) > 1e-13 * d[:, None] * d[None, :]

    significant = jnp.concatenate(
        [(jnp.abs(A) > 1e-13 * jnp.max(jnp.abs(A))).reshape(-1), cauchy_schwarz(M).reshape(-1),
         cauchy_schwarz(N).reshape(-1)]
    )

    def fit(w):
        w = w.astype(A.dtype)
        x = -jnp.linalg.pinv(w[:, None] * G) @ (w * b)  # min Σ w (b + G x)²
        # no normalisation: a common factor of s is not free here (it moves BBᵀ against CᵀC)
        return jnp.exp2(jnp.round(x[:n] / jnp.log(2.0)))

    def frobenius(sc):
        Ab, Bb, Cb = _balanced(A, B, C, sc)
        return 2 * jnp.sum(Ab**2) + jnp.sum((Bb @ Bb.T) ** 2) + jnp.sum((Cb.T @ Cb) ** 2)

    cands = jnp.stack([jnp.ones(n, A.dtype), fit(v != 0), fit((v != 0) & significant)])
    cost = jax.vmap(frobenius)(cands)
    cost = jnp.where(jnp.isfinite(cost), cost, jnp.inf)
    return cands[jnp.argmin(cost)]


def _balanced(A, B, C, s):
    """(A_b, B_b, C_b) = (S⁻¹AS, S⁻¹B, CS) for x = S x_b, S = diag(s)."""
    return A * s[None, :] / s[:, None], B / s[:, None], C * s[None, :]


def _hamiltonian(A, B, C, gamma):
    """W_i = [[A, γ_i B Bᵀ], [Cᵀ C, −Aᵀ]] (the matrix before (25); (27) when γ = 1)."""
    return jnp.block([[A, gamma * (B @ B.T)], [C.T @ C, -A.T]])


def _upper_right(X, Y, Z, T):
    """∫₀ᵀ e^{X(T−s)} Y e^{Z s} ds, the upper-right block of expm([[X, Y], [0, Z]] T) (Van Loan 1978)."""
    a, b = X.shape[0], Z.shape[0]
    M = jnp.block([[X, Y], [jnp.zeros((b, a), X.dtype), Z]])
    return expm(M * T)[:a, a:]


def _general_rows(A, B, C, T, gamma):
    """(25): the initial vectors c_i = [D_i e_i; 0] of the rows, and the matrices W_i.

    D_i = [∫₀ᵀ e^{−Aᵀ(T−τ)} Cᵀ C Φ¹¹_i(τ) dτ]⁻¹, evaluated as a block matrix exponential.
    Returns ``W`` of shape (n, 2n, 2n) and ``c`` of shape (n, 2n); row i of G1(s) is (C [I 0] e^{W_i s} c_i)ᵀ
    and row i of G2(s) is (Bᵀ [0 I] e^{W_i s} c_i)ᵀ (26).
    """
    n = A.shape[0]
    CC = C.T @ C
    E1 = jnp.concatenate([jnp.eye(n), jnp.zeros((n, n))], axis=1)  # [I 0], (n, 2n)
    W = jax.vmap(lambda g: _hamiltonian(A, B, C, g))(gamma)

    def d_inverse(Wi):
        # ∫ e^{−Aᵀ(T−τ)} CᵀC [I 0] e^{W_i τ} dτ [I; 0]
        return _upper_right(-A.T, CC @ E1, Wi, T)[:, :n]

    Dinv = jax.vmap(d_inverse)(W)  # (n, n, n): D_i⁻¹
    d = jax.vmap(lambda Di, e: jnp.linalg.solve(Di, e))(Dinv, jnp.eye(n))  # d_i = D_i e_i
    c = jnp.concatenate([d, jnp.zeros_like(d)], axis=1)
    return W, c


_CLOCK_ULPS = 16.0  # rounding of sample times on a clock: this many ulp of the largest |t|
_EPS = float(np.finfo(np.float64).eps)


def _concrete_grid(ts):
    """The sample times as a float64 NumPy array when they are constants (:func:`scalar_value`: read before
    any conversion, since ``jnp.asarray`` of a NumPy grid inside ``jit`` is traced, which made
    ``rule="auto"`` fall back to the trapezoid there), else ``None``."""
    try:
        v = scalar_value(ts)
    except Exception:  # noqa: BLE001  (refused by name by the checks that follow)
        return None
    if v is None or v.dtype == bool or not np.issubdtype(v.dtype, np.number) or np.iscomplexobj(v):
        return None
    return np.atleast_1d(np.asarray(v, np.float64))


def _uniform(tsc: np.ndarray) -> bool:
    """Whether concrete sample times are equally spaced, to 1e-9 of the step plus the rounding of the times
    themselves (16 ulp of the largest |t|: a grid on a clock at t = 1e6 carries 1e-10 per step)."""
    dt = np.diff(tsc)
    return bool(np.allclose(dt, dt[0], rtol=1e-9, atol=_CLOCK_ULPS * _EPS * np.max(np.abs(tsc))))


def _uniform_R(A, B, C, T):
    """(28): W of (27) and R = e^{AT} [∫₀ᵀ Φ¹¹(τ)ᵀ Cᵀ C e^{Aτ} dτ]⁻¹."""
    n = A.shape[0]
    W = _hamiltonian(A, B, C, 1.0)
    E1 = jnp.concatenate([jnp.eye(n), jnp.zeros((n, n))], axis=1)
    # ∫₀ᵀ e^{−Wᵀ(T−τ)} [I; 0] CᵀC e^{Aτ} dτ, then e^{WᵀT} · (that) = ∫ e^{Wᵀτ} [I;0] CᵀC e^{Aτ} dτ.
    F = _upper_right(-W.T, E1.T @ (C.T @ C), A, T)
    S = (expm(W.T * T) @ F)[:n]  # ∫ Φ¹¹(τ)ᵀ CᵀC e^{Aτ} dτ
    R = expm(A * T) @ jnp.linalg.inv(S)
    return W, R


def _gram(W, Q, T):
    """∫₀ᵀ e^{Wᵀs} Q e^{Ws} ds by Van Loan: expm([[−Wᵀ, Q], [0, W]] T) = [[·, F12], [0, e^{WT}]]."""
    k = W.shape[0]
    M = jnp.block([[-W.T, Q], [jnp.zeros((k, k), W.dtype), W]])
    E = expm(M * T)
    G = E[k:, k:].T @ E[:k, k:]
    return 0.5 * (G + G.T)


class _Window(NamedTuple):
    """Everything the sliding-window observer needs, derived once per simulation by ``prepare()``.

    - `W` (r, 2n, 2n): the r distinct Hamiltonian matrices (r = n for (25), 1 for (28)).
    - `readout` (N, n, r, 2n): x̂ = Σ_j readout[j] · buffer[j].
    - `prefill` (N, r, 2n, n): the buffer of the model's free response through x̂0 (history (36)).
    - `Bb` (n, p), `Cb` (m, n): the model's B and C in the balanced state units of the design
      (:func:`_window_scaling`); W and the pieces ζ are in those units, x̂ in the user's.
    """

    W: jax.Array
    readout: jax.Array
    prefill: jax.Array
    Bb: jax.Array
    Cb: jax.Array


# ------------------------------------------------------------------------------------------------------
# The observer.
# ------------------------------------------------------------------------------------------------------


class FiniteWindow(AbstractObserver):
    r"""Byrski & Fuksa's minimum-norm observer on a window of length T (kernels (25)-(26) or (28)).

    The state at the end of the window [t − T, t] of an LTI model ẋ = Ax + Bu, y = Cx (12) is

        x̂(t) = ∫₀ᵀ G1(s) y(t − T + s) ds + ∫₀ᵀ G2(s) u(t − T + s) ds                     (14), (33)

    with the kernels of minimal norm (15)

        ‖(G1, G2)‖² = ∫₀ᵀ Σᵢ αᵢ |row i of G1|² + βᵢ |row i of G2|² ds

    among all kernels that reconstruct x exactly ((16) and (18)).  With γᵢ = βᵢ/αᵢ and the Hamiltonian
    matrices Wᵢ = [[A, γᵢ BBᵀ], [CᵀC, −Aᵀ]], Φⁱ(s) = e^{Wᵢ s},

        row i of G1(s) = (C Φⁱ₁₁(s) Dᵢ eᵢ)ᵀ,   row i of G2(s) = (Bᵀ Φⁱ₂₁(s) Dᵢ eᵢ)ᵀ,        (25)-(26)
        Dᵢ = [∫₀ᵀ e^{−Aᵀ(T−τ)} CᵀC Φⁱ₁₁(τ) dτ]⁻¹,

    and when all γᵢ = 1 (one W, (27))

        G1(s) = R Φ₁₁(s)ᵀ Cᵀ,  G2(s) = R Φ₂₁(s)ᵀ B,  R = e^{AT}[∫₀ᵀ Φ₁₁ᵀ CᵀC e^{Aτ} dτ]⁻¹.   (28)

    Every integral is a block matrix exponential (``jax.scipy.linalg.expm``, Van Loan's method), so the
    kernels and :meth:`norm` are exact up to rounding and differentiable in T, α, β and the model.
    Accuracy: the exponentials grow like e^{ρT} with ρ the largest real part of eig(W); keep ρT ≲ 15.

    **In a simulation** (:func:`obsjax.simulate`, Section 4): the window is cut into ``n_chunks`` pieces of
    length h = T/n_chunks.  Over the current piece the observer integrates ζ̇ = w − Wᵀζ with
    w = [Cᵀ(y − Du); Bu], whose value at the end of the piece is that piece's exact contribution to (14);
    at every t0 + kh (``reset_period`` = h) the pieces are shifted through a buffer (the paper's "shift
    registers") and x̂(t0 + kh) is (14) over [t0 + kh − T, t0 + kh] exactly (no quadrature error; only the
    ODE tolerance).  Between those instants x̂ is propagated by the model, x̂̇ = Ax̂ + Bu, which equals (14) over
    [t − T, t] whenever the window's data are consistent with the model (noise-free, no model mismatch):
    every member of S reconstructs such data exactly.  Before t0 + T the window reaches into the history
    (36); it is taken as the model's free response through x̂0 (u = 0 on [t0 − T, t0)), so x̂(t0) = x̂0.
    With ``controller=lambda t, xh: P @ xh`` this is the closed loop (33)-(35): for t ≥ t0 + T the
    estimate is exact and the state follows ẋ = (A + BP)x (42) (Lemma 4's deadbeat property).

    **Gradients:** :meth:`norm` is differentiable in T, α, β.  Under formula (28) the kernels keep γ = 1;
    the gradient of :meth:`norm` in α, β is still that of the general optimum (envelope theorem: the
    derivative of a minimum in a weight is the weight's partial derivative at the minimiser), but for
    gradients of the kernels or estimates in α, β use ``formula="(25)"``.  Through :func:`obsjax.simulate`
    the derivative in T is exact (the reset instants move with T; pass ``max_segments`` under ``jit``);
    x(tᵢ) has a kink in T where a save time tᵢ coincides with a reset instant before the window fills.

    **Arguments:**

    - `model`: an :class:`obsjax.LTI` model (observable (A, C)); y − Du is used when D ≠ 0.
    - `T`: window length > 0 (a differentiable leaf).
    - `alpha`: weights αᵢ > 0 of the rows of G1 in (5)/(15), shape (n,); ones when ``None``.
    - `beta`: weights βᵢ ≥ 0 of the rows of G2, shape (n,); ones when ``None``.
    - `formula`: ``"(25)"`` (general γᵢ), ``"(28)"`` (requires all γᵢ = 1) or ``"auto"`` (the default:
      (28) when α and β are both left ``None``, (25) otherwise).
    - `n_chunks`: number of pieces of the window in a simulation (static, ≥ 1).

    **Example:** the double integrator (29); its norm is (31)::

        model = obsjax.LTI(A=[[0., 1.], [0., 0.]], B=[[0.], [1.]], C=[[2., 0.]])
        obs = obsjax.FiniteWindow(model, T=1.0)
        obs.norm()              # 2.09271...
        G1, G2 = obs.kernels(jnp.linspace(0.0, 1.0, 5))
        traj = obsjax.simulate(plant, obs, x0, xhat0, ts, controller=lambda t, xh: P @ xh)
    """

    model: LTI
    T: jax.Array
    alpha: jax.Array
    beta: jax.Array
    formula: str = eqx.field(static=True)
    n_chunks: int = eqx.field(static=True)
    window: _Window | None = None

    def __init__(self, model, T, alpha=None, beta=None, *, formula="auto", n_chunks=20):
        require_x64("FiniteWindow")
        if not isinstance(model, LTI):
            raise ValueError(  # noqa: TRY004 (the project raises ValueError for every bad input)
                f"`model` must be an obsjax.LTI (Byrski & Fuksa's observer is for ẋ = Ax + Bu, y = Cx), "
                f"got {type(model).__name__}."
            )
        n = model.n
        if formula not in _FORMULAS:
            raise ValueError(f"`formula` must be one of {_FORMULAS}, got {formula!r}.")
        if formula == "auto":
            formula = "(28)" if (alpha is None and beta is None) else "(25)"
        if (
            not isinstance(n_chunks, (int, np.integer))
            or isinstance(n_chunks, bool)
            or n_chunks < 1
        ):
            raise ValueError(f"`n_chunks` must be an integer >= 1, got {n_chunks!r}.")
        T = as_float_array(T, "T")
        if T.ndim != 0:
            raise ValueError(f"`T` must be a scalar window length, got shape {tuple(T.shape)}.")
        self.model = model
        self.T = T
        self.alpha = jnp.ones(n) if alpha is None else vector(alpha, "alpha", n)
        self.beta = jnp.ones(n) if beta is None else vector(beta, "beta", n)
        self.formula = formula
        self.n_chunks = int(n_chunks)
        self.window = None
        self._check_values()
        _check_observable(model)

    # ---- validation ---------------------------------------------------------------------------------
    def _check_values(self):
        for name, leaf in (("T", self.T), ("alpha", self.alpha), ("beta", self.beta)):
            require_finite(leaf, name)
        T, a, b = (concrete_value(v) for v in (self.T, self.alpha, self.beta))
        if T is not None and not T > 0:
            raise ValueError(f"`T` (the window length) must be > 0, got {float(T)}.")
        if a is not None and not np.all(a > 0):
            raise ValueError(
                f"`alpha` (weights of G1's rows in (15)) must be > 0, got {a.tolist()}."
            )
        if b is not None and not np.all(b >= 0):
            raise ValueError(
                f"`beta` (weights of G2's rows in (15)) must be >= 0, got {b.tolist()}."
            )
        gamma_one = a is None or b is None or np.allclose(b / a, 1.0, rtol=1e-12, atol=0.0)
        if self.formula == "(28)" and not gamma_one:
            raise ValueError(
                "`formula='(28)'` needs every γᵢ = βᵢ/αᵢ = 1, got "
                f"γ = {(b / a).tolist()}; use formula='(25)' for general weights."
            )

    def check(self) -> FiniteWindow:
        """Re-validate T > 0, α > 0, β ≥ 0 (and γ = 1 for (28)) after leaves were updated."""
        self._check_values()
        return self

    def _leaves(self):
        return self.model.A, self.model.B, self.model.C, self.T, self.alpha, self.beta

    # ---- the kernels ----------------------------------------------------------------------------------
    def _design(self):
        """(W (r, 2n, 2n), coef (n, r, 2n)): row i of G1, G2 at s comes from Σ_k e^{W_k s} coef[i, k]."""
        return _design(*self._leaves(), self.formula)

    def kernels(self, s):
        """The optimal kernels G1(s) (n, m) and G2(s) (n, p) at s ∈ [0, T] ((26) or (28)).

        **Arguments:** `s`: a scalar or a 1-D array of times in the window (0 = oldest sample).

        **Returns:** ``(G1, G2)`` with shapes (…, n, m) and (…, n, p).
        """
        s = jnp.asarray(s, dtype=self.model.A.dtype)
        W, coef, Bb, Cb, _ = self._design()
        G1, G2 = _kernels_at(W, coef, Bb, Cb, s.reshape(-1))
        if s.ndim == 0:
            return G1[0], G2[0]
        return G1, G2

    def norm(self):
        """The observer norm (15) of the optimal kernels, ‖(G1, G2)‖ (Byrski & Fuksa (5), (15), (31)).

        Computed exactly as Σᵢ cᵢᵀ (∫₀ᵀ e^{Wᵀs} Qᵢ e^{Ws} ds) cᵢ with Qᵢ = blockdiag(αᵢ CᵀC, βᵢ BBᵀ) by a
        block matrix exponential; differentiable in T, α, β (and the model).

        Meaning (Section 2.2): for disturbances z1 of y and z2 of u with ‖z1‖² + ‖z2‖² ≤ 1 (the unit ball
        of Y × U) the estimation error obeys Σᵢ min(αᵢ, βᵢ) eᵢ² ≤ ‖(G1, G2)‖², so ‖x̂ − x‖ ≤ ‖(G1, G2)‖
        when α = β = I.  (For z1, z2 each in its own unit ball the worst error can exceed the norm, by
        at most a factor √2; the paper's inequality holds for the product ball.)

        **Returns:** a scalar.  **Example:** ``FiniteWindow(model29, 1.0).norm()`` ≈ 2.09271 (31).
        """
        return _norm(*self._leaves(), self.formula)

    # ---- the estimate from a sampled window ---------------------------------------------------------
    def estimate_window(self, ts, ys, us=None, *, rule="auto"):
        r"""x(t) from samples of y and u on a window ts spanning [t − T, t] ((14); (33) at t = ts[-1]).

        **Arguments:**

        - `ts`: (K,) increasing sample times with ts[-1] − ts[0] = T.
        - `ys`: (K, m) measured outputs; `us`: (K, p) inputs (``None``: u ≡ 0).
        - `rule`: ``"simpson"`` (composite Simpson; uniform grid, odd K), ``"trapezoid"`` (any grid) or
          ``"auto"`` (Simpson when ts is concrete, uniform and K odd; the trapezoid otherwise).

        **Returns:** x̂(ts[-1]), shape (n,).

        Quadrature error, with f(s) = G1(s) y(t − T + s) + G2(s) u(t − T + s) and step h (largest step):
        trapezoid |E| ≤ T h² max|f″| / 12; Simpson |E| ≤ T h⁴ max|f⁗| / 180 (both componentwise).  The
        kernels are entire, so for smooth y, u the error is O(h²) resp. O(h⁴); e.g. (29) with T = 1,
        u = sin 3t and 101 samples: Simpson reconstructs x(T) to 3e-9, the trapezoid to 1e-4.
        """
        A = self.model.A
        m, p = self.model.m, self.model.p
        tsc = _concrete_grid(ts)
        ts = vector(ts, "ts", None)
        K = ts.shape[0]
        if K < 2:
            raise ValueError(f"`ts` must hold at least 2 sample times, got {K}.")
        ys = as_float_array(ys, "ys")
        if ys.shape != (K, m):
            raise ValueError(
                f"`ys` must have shape ({K}, {m}) (one output per sample), got {tuple(ys.shape)}."
            )
        if us is None:
            us = jnp.zeros((K, p), A.dtype)
        us = as_float_array(us, "us")
        if us.shape != (K, p):
            raise ValueError(
                f"`us` must have shape ({K}, {p}) (one input per sample), got {tuple(us.shape)}."
            )
        if rule not in ("auto", "simpson", "trapezoid"):
            raise ValueError(f"`rule` must be 'auto', 'simpson' or 'trapezoid', got {rule!r}.")
        Tc = concrete_value(self.T)
        uniform = None
        if tsc is not None:
            dt = np.diff(tsc)
            if not np.all(dt > 0):
                raise ValueError("`ts` must be strictly increasing.")
            if Tc is not None and abs((tsc[-1] - tsc[0]) - Tc) > _time_tol(Tc, tsc[0], tsc[-1]):
                raise ValueError(
                    f"`ts` must span the window [t − T, t]: ts[-1] − ts[0] = {tsc[-1] - tsc[0]!r}, "
                    f"T = {float(Tc)!r}."
                )
            uniform = _uniform(tsc)
        if rule == "auto":
            rule = "simpson" if (uniform and K % 2 == 1) else "trapezoid"
        if rule == "simpson":
            if K % 2 == 0:
                raise ValueError(f"Simpson's rule needs an odd number of samples in `ts`, got {K}.")
            if uniform is False:
                raise ValueError("Simpson's rule needs a uniform grid `ts`; use rule='trapezoid'.")
            h = (ts[-1] - ts[0]) / (K - 1)
            wts = jnp.ones(K).at[1:-1:2].set(4.0).at[2:-1:2].set(2.0) * h / 3.0
        else:
            dt = jnp.diff(ts)
            wts = jnp.concatenate([dt[:1], dt[:-1] + dt[1:], dt[-1:]]) / 2.0
        ts = eqx.error_if(
            ts,
            jnp.abs((ts[-1] - ts[0]) - self.T) > _time_tol(self.T, ts[0], ts[-1]),
            "FiniteWindow.estimate_window: `ts` must span [t − T, t].",
        )
        if tsc is None:  # the grid checks made above on concrete times, under jit
            d = jnp.diff(ts)
            ts = eqx.error_if(ts, ~jnp.all(d > 0), "FiniteWindow.estimate_window: `ts` must be strictly increasing.")
            if rule == "simpson":
                ts = eqx.error_if(
                    ts, jnp.any(jnp.abs(d - d[0]) > 1e-9 * jnp.abs(d[0]) + _CLOCK_ULPS * _EPS * jnp.max(jnp.abs(ts))),
                    "FiniteWindow.estimate_window: Simpson's rule needs a uniform grid `ts`; use rule='trapezoid'.",
                )
        G1, G2 = self.kernels(ts - ts[0])
        return _quadrature(wts, G1, G2, ys, us, self.model.D)

    # ---- the sliding-window observer in a simulation (Section 4) ------------------------------------
    @property
    def reset_period(self):
        """h = T / n_chunks: at t0 + kh the buffer of window pieces shifts and x̂ is recomputed by (14)."""
        Tc = static_value(self.T)
        # a constant T (also a closed-over one inside jit) gives a float, so simulate can count segments;
        # a T being differentiated, even by an eager jax.grad, stays traced so the reset instants move with it
        if Tc is not None:
            return float(Tc) / self.n_chunks
        return self.T / self.n_chunks

    def _window_design(self) -> _Window:
        return _window_design(*self._leaves(), self.formula, self.n_chunks)

    def prepare(self) -> FiniteWindow:
        """A copy with the window design (kernels at the piece boundaries, history) computed once."""
        win = self._window_design()
        return eqx.tree_at(lambda o: o.window, self, win, is_leaf=lambda x: x is None)

    def _win(self) -> _Window:
        return self.window if self.window is not None else self._window_design()

    def init(self, t0, xhat0, y0):
        """z0 = (x̂0, ζ = 0, buffer of the history (36) through x̂0)."""
        win = self._win()
        xhat0 = jnp.asarray(xhat0, dtype=self.model.A.dtype)
        buf = jnp.einsum("jkal,l->jka", win.prefill, xhat0)
        return (xhat0, jnp.zeros(buf.shape[1:], buf.dtype), buf)

    def vector_field(self, t, z, y, u):
        """x̂̇ = Ax̂ + Bu (between the instants t0 + kh); ζ̇_k = w − W_kᵀ ζ_k with w = [Cᵀ(y − Du); Bu]."""
        xhat, zeta, buf = z
        A, B, D = self.model.A, self.model.B, self.model.D
        win = self._win()
        w = jnp.concatenate([win.Cb.T @ (y - D @ u), win.Bb @ u])  # in the design's balanced units
        dzeta = w[None, :] - jnp.einsum("kab,ka->kb", win.W, zeta)
        return (A @ xhat + B @ u, dzeta, jnp.zeros_like(buf))

    def reset(self, t, z):
        """Shift the buffer (drop the oldest piece, append ζ), clear ζ, set x̂ to (14) over [t − T, t]."""
        _, zeta, buf = z
        win = self._win()
        buf = jnp.concatenate([buf[1:], zeta[None]], axis=0)
        xhat = jnp.einsum("jikb,jkb->i", win.readout, buf)
        return (xhat, jnp.zeros_like(zeta), buf)

    def estimate(self, t, z, y):
        return z[0]


# ------------------------------------------------------------------------------------------------------
# Jitted cores (value checks by eqx.error_if survive jit; nested under an outer jit/grad they inline).
# ------------------------------------------------------------------------------------------------------


def _checked(T, alpha, beta, formula):
    T = eqx.error_if(
        T,
        ~(T > 0) | ~jnp.isfinite(T),
        "FiniteWindow: `T` (the window length) must be > 0 and finite.",
    )
    alpha = eqx.error_if(
        alpha,
        jnp.any(~(alpha > 0) | ~jnp.isfinite(alpha)),
        "FiniteWindow: `alpha` must be > 0 and finite elementwise.",
    )
    beta = eqx.error_if(
        beta,
        jnp.any(~(beta >= 0) | ~jnp.isfinite(beta)),
        "FiniteWindow: `beta` must be >= 0 and finite elementwise.",
    )
    if formula == "(28)":
        alpha = eqx.error_if(
            alpha,
            jnp.any(jnp.abs(beta / alpha - 1.0) > 1e-12),
            "FiniteWindow: formula '(28)' needs beta == alpha (every γ = 1); use formula '(25)'.",
        )
    return T, alpha, beta


@partial(jax.jit, static_argnames="formula")
def _design(A, B, C, T, alpha, beta, formula):
    """(W, coef, B_b, C_b, s): the design in balanced state units (:func:`_window_scaling`).  W (r, 2n, 2n)
    and the generator vectors are in those units; coef[i] is scaled by s_i, so that row i of
    G1(s) = Σ_k (C_b [I 0] e^{W_k s} coef[i, k])ᵀ and of G2 (with B_b [0 I]) are in the user's units."""
    T, alpha, beta = _checked(T, alpha, beta, formula)
    n = A.shape[0]
    sc = _window_scaling(A, B, C)
    A, B, C = _balanced(A, B, C, sc)
    if formula == "(28)":
        W, R = _uniform_R(A, B, C, T)
        E1 = jnp.concatenate([jnp.eye(n), jnp.zeros((n, n))], axis=1)
        # row i of G1(s) = R[i] [I 0] e^{Wᵀs} [I; 0] Cᵀ  ⇔  generator vector e^{Ws} [I; 0] R[i]ᵀ
        coef = (R @ E1)[:, None, :]  # (n, 1, 2n)
        W = W[None]
    else:
        W, c = _general_rows(A, B, C, T, beta / alpha)
        coef = jnp.eye(n)[:, :, None] * c[None, :, :]  # (n, n, 2n): row i uses only W_i
    coef = sc[:, None, None] * coef
    bad = ~(jnp.all(jnp.isfinite(W)) & jnp.all(jnp.isfinite(coef)))
    coef = eqx.error_if(
        coef,
        bad,
        "FiniteWindow: the kernel design is not finite: the exponentials of the Hamiltonian overflow over "
        "the window (they grow like e^{ρT}, ρ the largest real part of eig W); shorten the window T.",
    )
    return W, coef, B, C, sc


@jax.jit
def _kernels_at(W, coef, B, C, s):
    n = C.shape[1]

    def at(si):
        V = jnp.einsum("kab,ikb->ia", jax.vmap(lambda Wk: expm(Wk * si))(W), coef)  # (n, 2n)
        return V[:, :n] @ C.T, V[:, n:] @ B

    return jax.vmap(at)(s)


@partial(jax.jit, static_argnames="formula")
def _norm(A, B, C, T, alpha, beta, formula):
    W, coef, B, C, _ = _design(A, B, C, T, alpha, beta, formula)  # B, C in the balanced units of W
    T, alpha, beta = _checked(T, alpha, beta, formula)
    n = A.shape[0]
    CC, BB = C.T @ C, B @ B.T
    Z = jnp.zeros((n, n), A.dtype)
    Q1 = jnp.block([[CC, Z], [Z, Z]])
    Q2 = jnp.block([[Z, Z], [Z, BB]])
    if formula == "(28)":
        c = coef[:, 0, :]  # (n, 2n)
        M1, M2 = _gram(W[0], Q1, T), _gram(W[0], Q2, T)
        val = jnp.sum(alpha * jnp.einsum("ia,ab,ib->i", c, M1, c))
        val = val + jnp.sum(beta * jnp.einsum("ia,ab,ib->i", c, M2, c))
    else:
        c = jnp.einsum("iia->ia", coef)
        M1 = jax.vmap(lambda Wi: _gram(Wi, Q1, T))(W)
        M2 = jax.vmap(lambda Wi: _gram(Wi, Q2, T))(W)
        val = jnp.sum(alpha * jnp.einsum("ia,iab,ib->i", c, M1, c))
        val = val + jnp.sum(beta * jnp.einsum("ia,iab,ib->i", c, M2, c))
    return jnp.sqrt(val)


@partial(jax.jit, static_argnames=("formula", "N"))
def _window_design(A, B, C, T, alpha, beta, formula, N) -> _Window:
    W, coef, B, C, sc = _design(A, B, C, T, alpha, beta, formula)  # (r, 2n, 2n), (n, r, 2n)
    A = A * sc[None, :] / sc[:, None]  # balanced, as B and C: ζ and the history are in those units
    n = A.shape[0]
    h = T / N
    # piece j covers s ∈ [jh, (j+1)h]; its stored value is ζ_j = ∫ e^{−Wᵀ((j+1)h − s)} w ds, so its
    # contribution to row i is Σ_k (e^{W_k (j+1)h} coef[i, k])ᵀ ζ_{j,k}.
    js = jnp.arange(1, N + 1, dtype=A.dtype)
    E = jax.vmap(lambda j: jax.vmap(lambda Wk: expm(Wk * (j * h)))(W))(js)  # (N, r, 2n, 2n)
    readout = jnp.einsum("jkba,ika->jikb", E, coef)
    # history (36): w(τ) = [CᵀC e^{A(τ − t0)} x̂0; 0] on [t0 − T, t0).  Piece j starts at t0 − (N − j)h:
    # ζ_j = ∫₀ʰ e^{−Wᵀ(h − r)} [CᵀC; 0] e^{A r} dr · e^{−A (N − j) h} x̂0.
    F = jnp.concatenate([C.T @ C, jnp.zeros((n, n), A.dtype)], axis=0)
    Gam = jax.vmap(lambda Wk: _upper_right(-Wk.T, F, A, h))(W)  # (r, 2n, n)
    back = jax.vmap(lambda j: expm(-A * ((N - j) * h)))(jnp.arange(N, dtype=A.dtype))  # (N, n, n)
    prefill = jnp.einsum("kan,jnl->jkal", Gam, back) / sc  # acts on x̂0 in the user's units: x̂0_b = x̂0 / s
    return _Window(W=W, readout=readout, prefill=prefill, Bb=B, Cb=C)


@jax.jit
def _quadrature(wts, G1, G2, ys, us, D):
    yd = ys - us @ D.T
    return jnp.einsum("k,kij,kj->i", wts, G1, yd) + jnp.einsum("k,kij,kj->i", wts, G2, us)


def _check_observable(model: LTI) -> None:
    A, C = concrete_value(model.A), concrete_value(model.C)
    if A is None or C is None:
        return
    st = observability_staircase(A, C)
    if not st.observable:
        raise ValueError(
            f"FiniteWindow needs an observable model: the staircase form of (A, C) has rank {st.rank}, "
            f"expected {A.shape[0]}, PBH margin {st.margin:.2e} relative to ‖A‖ (Lemma 1: the columns "
            f"of C e^{{−A(T−t)}} must be linearly independent)."
        )


# ------------------------------------------------------------------------------------------------------
# Theorem 1 for linear time-varying maps: the LTV state observer and parameter identification.
# ------------------------------------------------------------------------------------------------------


def _gram_rcond(M):
    """Lemma 1's rank decision on the window gramian M (the elements h_1^i are independent iff M is
    nonsingular), by the staircase's relative residuals: the smallest residual of a state direction
    outside those before it, relative to its own norm (:func:`obsjax.analysis._lti.
    gram_relative_residuals`), squared (a ratio of gramian entries, like an eigenvalue ratio).  It does
    not depend on the units of the states."""
    return jnp.min(gram_relative_residuals(M)) ** 2


def _quadrature_weights(ts, rule):
    K = ts.shape[0]
    if rule == "simpson":
        h = (ts[-1] - ts[0]) / (K - 1)
        return jnp.ones(K).at[1:-1:2].set(4.0).at[2:-1:2].set(2.0) * h / 3.0
    dt = jnp.diff(ts)
    return jnp.concatenate([dt[:1], dt[:-1] + dt[1:], dt[-1:]]) / 2.0


class WindowParameterMap(eqx.Module):
    """The linear map (x(t1), θ) ↦ y of an LTV model with a constant unknown parameter θ (q,):

        ẋ = A(t) x + B(t) u + E(t) θ,      y = C(t) x + D(t) θ,      θ̇ = 0,

    as the augmented LTV model with state [x; θ] (Byrski & Fuksa's (1) with X = R^{n+q}).  Used by
    :class:`FiniteWindowLTV` when `E` or `D` is given."""

    model: eqx.Module
    E: Callable | None
    D: Callable | None
    n: int = eqx.field(static=True)
    q: int = eqx.field(static=True)

    def A_of(self, t):
        n, q = self.n, self.q
        A = jnp.zeros((n + q, n + q)).at[:n, :n].set(jnp.asarray(self.model.A_of(t)))
        if self.E is not None:
            A = A.at[:n, n:].set(jnp.asarray(self.E(t)))
        return A

    def B_of(self, t):
        B = jnp.asarray(self.model.B_of(t))
        return jnp.concatenate([B, jnp.zeros((self.q, B.shape[1]), B.dtype)], axis=0)

    def C_of(self, t):
        C = jnp.asarray(self.model.C_of(t))
        Dq = jnp.zeros((C.shape[0], self.q)) if self.D is None else jnp.asarray(self.D(t))
        return jnp.concatenate([C, Dq], axis=1)


@eqx.filter_jit
def _window_ltv_solve(fw, save_ts, y, u):
    """One jitted solve per (model, data callables, grid shape): kernels, norm and estimates reuse it."""
    return fw._solve_raw(save_ts, y, u)


class FiniteWindowLTV(eqx.Module):
    r"""Byrski & Fuksa's minimum-norm observer for a linear time-varying map on a window [t0, t1].

    Theorem 1 holds for any pair of linear maps (1) y = ℋ1 x + ℋ2 u on Hilbert spaces.  For the LTV model
    ẋ = A(t)x + B(t)u, y = C(t)x on [t0, t1], with X = Rⁿ the state x(t1) and Y, U the L² spaces,

        (ℋ1 x)(t) = C(t) Φ(t, t1) x,    (ℋ2 u)(t) = −C(t) ∫_t^{t1} Φ(t, τ) B(τ) u(τ) dτ            (13)

    with Φ the transition matrix, and the observer is x̂(t1) = ∫ G1 y dt + ∫ G2 u dt (14).  The optimal
    kernels (11) g1 = (P⁻¹h1 | h1ᵀ)⁻¹ P⁻¹h1, g2 = −ℋ2*g1 (P = α + βℋ2ℋ2*) satisfy, row by row, the LTV form
    of (21)-(24): with γᵢ = βᵢ/αᵢ and Wᵢ(t) = [[A(t), γᵢ B Bᵀ], [CᵀC, −Aᵀ]], Ψⁱ(t, t0) its transition matrix,

        row i of G1(t) = (C(t) Ψⁱ₁₁(t, t0) Dᵢ eᵢ)ᵀ,     row i of G2(t) = (B(t)ᵀ Ψⁱ₂₁(t, t0) Dᵢ eᵢ)ᵀ,
        Dᵢ = [∫_{t0}^{t1} Φ(t, t1)ᵀ C(t)ᵀ C(t) Ψⁱ₁₁(t, t0) dt]⁻¹                                (25)-(26), LTV

    (the paper's e^{W t} becomes Ψⁱ(t, t0), e^{−Aᵀ(T−τ)} becomes Φ(τ, t1)ᵀ).  With β = 0 (γ = 0) Ψ₁₁ = Φ and the
    kernel is the gramian one, G1(t) = M⁻¹ Φ(t, t1)ᵀ C(t)ᵀ with the window gramian
    M = ∫ Φ(t, t1)ᵀ CᵀC Φ(t, t1) dt (Lemma 1's g1 = (h1|h1ᵀ)⁻¹h1).  Lemma 1: an observer exists iff M is
    nonsingular; this is checked with a scale-invariant test (the smallest relative residual of a state
    direction outside those before it, the rank mechanism of the package, squared, against `rcond_min`).

    **Parameter identification** (a second use of Theorem 1): with `E` and/or `D`, the model is
    ẋ = A x + B u + E θ, y = C x + D θ with a constant unknown θ (q,), and X = R^{n+q} holds (x(t1), θ); the
    same formulas on the augmented model [[A, E], [0, 0]], [B; 0], [C, D] give the minimum-norm estimator
    of (x(t1), θ) from the window.  Identifiability is Lemma 1's condition for the augmented map.

    Everything is computed by one diffrax solve of the matrix ODEs of Φ, Ψⁱ and the integrals of D⁻¹,
    the gramian and the norm, so kernels, estimates and :meth:`norm` are accurate to the solver tolerance
    and differentiable in t0, t1, α, β and the model.

    **Arguments:**

    - `model`: an :class:`obsjax.LTV` (or :class:`obsjax.LTI`) model (``A_of``, ``B_of``, ``C_of``).
    - `t0`, `t1`: the window (t1 > t0, leaves).
    - `alpha`, `beta`: weights (5)/(15) of the rows of G1 (> 0) and G2 (≥ 0), length n (+ q); ones if
      ``None``.
    - `E`, `D`: optional callables of t, (n, q) and (m, q): the parameter map.
    - `rtol`, `atol`: tolerances of the solve (``Tsit5``); `rcond_min`: Lemma 1's test.

    **Example:** state at the end of a window of a time-varying oscillator::

        plant = obsjax.LTV(lambda t: jnp.array([[0., 1.], [-1. - 0.5 * jnp.sin(t), -0.2]]),
                           lambda t: jnp.array([[1., 0.]]), lambda t: jnp.array([[0.], [1.]]))
        fw = obsjax.FiniteWindowLTV(plant, 0.0, 2.0)
        xT = fw.estimate_window(ts, ys, us)            # samples of y, u on [0, 2]
        bias = obsjax.FiniteWindowLTV(plant, 0.0, 2.0, E=lambda t: jnp.array([[0.], [1.]]))  # + force θ
    """

    model: eqx.Module
    t0: jax.Array
    t1: jax.Array
    alpha: jax.Array
    beta: jax.Array
    rtol: float = eqx.field(static=True)
    atol: float = eqx.field(static=True)
    rcond_min: float = eqx.field(static=True)

    def __init__(
        self, model, t0, t1, alpha=None, beta=None, *, E=None, D=None, rtol=1e-10, atol=1e-12,
        rcond_min=1e-12,
    ):
        require_x64("FiniteWindowLTV")
        for name in ("A_of", "B_of", "C_of"):
            if not hasattr(model, name):
                raise ValueError(
                    f"`model` must be an obsjax.LTV or obsjax.LTI (with A_of, B_of, C_of), got "
                    f"{type(model).__name__}."
                )
        Dc = concrete_value(getattr(model, "D", jnp.zeros(())))
        if Dc is not None and np.any(Dc != 0):
            raise ValueError(
                "`model` has a feedthrough D ≠ 0; FiniteWindowLTV uses y = C x: pass the data y − D u "
                "and a model without D."
            )
        if E is not None or D is not None:
            n, m = int(model.n), int(model.m)
            q = None
            for fn, name, rows in ((E, "E", n), (D, "D", m)):
                if fn is None:
                    continue
                if not callable(fn):
                    raise ValueError(f"`{name}` must be a callable of t returning a ({rows}, q) matrix.")  # noqa: TRY004 (project rule: ValueError)
                shp = tuple(jax.eval_shape(fn, jnp.asarray(0.0)).shape)
                if len(shp) != 2 or shp[0] != rows or (q is not None and shp[1] != q):
                    raise ValueError(
                        f"`{name}(t)` must return a ({rows}, {q if q is not None else 'q'}) matrix, got {shp}."
                    )
                q = shp[1]
            model = WindowParameterMap(model, E, D, n, q)
        self.model = model
        N = self.dim
        self.t0 = as_float_array(t0, "t0")
        self.t1 = as_float_array(t1, "t1")
        for v, name in ((self.t0, "t0"), (self.t1, "t1")):
            if v.ndim != 0:
                raise ValueError(f"`{name}` must be a scalar time, got shape {tuple(v.shape)}.")
        self.alpha = jnp.ones(N) if alpha is None else vector(alpha, "alpha", N)
        self.beta = jnp.ones(N) if beta is None else vector(beta, "beta", N)
        self.rtol, self.atol, self.rcond_min = float(rtol), float(atol), float(rcond_min)
        self.check()
        rc = concrete_value(self.gramian_rcond())
        if rc is not None and not rc > self.rcond_min:
            raise ValueError(
                f"FiniteWindowLTV: no observer exists on [{float(self.t0)}, {float(self.t1)}] (Lemma 1): the "
                f"window gramian ∫ Φᵀ CᵀC Φ dt is singular (scaled reciprocal condition {float(rc):.3e} ≤ "
                f"rcond_min = {self.rcond_min:.1e}); lengthen the window, or the parameters are not "
                f"identifiable from it."
            )

    @property
    def dim(self) -> int:
        """Dimension of X: n, or n + q with a parameter map."""
        return int(self.model.A_of(jnp.asarray(0.0)).shape[0]) if not isinstance(
            self.model, WindowParameterMap
        ) else self.model.n + self.model.q

    def check(self) -> FiniteWindowLTV:
        """Re-validate t1 > t0, α > 0, β ≥ 0."""
        t0, t1, a, b = (concrete_value(v) for v in (self.t0, self.t1, self.alpha, self.beta))
        for v, name in ((t0, "t0"), (t1, "t1")):
            if v is not None and not np.isfinite(v):
                raise ValueError(f"`{name}` must be a finite time, got {float(v)}.")
        if t0 is not None and t1 is not None and not t1 > t0:
            raise ValueError(f"`t1` must be > `t0` (a window), got t0 = {float(t0)}, t1 = {float(t1)}.")
        if a is not None and not np.all(a > 0):
            raise ValueError(f"`alpha` (weights of G1's rows in (15)) must be > 0, got {a.tolist()}.")
        if b is not None and not np.all(b >= 0):
            raise ValueError(f"`beta` (weights of G2's rows in (15)) must be >= 0, got {b.tolist()}.")
        return self

    # ---- one solve of every matrix ODE on the window ----------------------------------------------
    def _solve(self, save_ts=None, y=None, u=None):
        return _window_ltv_solve(self, save_ts, y, u)

    def _solve_raw(self, save_ts, y, u):
        import diffrax

        N = self.dim
        mdl = self.model
        gamma = self.beta / self.alpha
        I, Z = jnp.eye(N), jnp.zeros((N, N))
        Psi0 = jnp.broadcast_to(jnp.concatenate([I, Z], axis=0), (N, 2 * N, N))
        data = y is not None

        def rhs(t, s, args):
            A, B, C = mdl.A_of(t), mdl.B_of(t), mdl.C_of(t)
            CC, BB = C.T @ C, B @ B.T
            Phi, Psi = s["Phi"], s["Psi"]
            P11, P21 = Psi[:, :N], Psi[:, N:]
            d = {
                "Phi": A @ Phi,
                "Psi": jnp.concatenate(
                    [A @ P11 + gamma[:, None, None] * (BB @ P21), CC @ P11 - A.T @ P21], axis=1
                ),
                "J": jnp.einsum("ba,bc,icd->iad", Phi, CC, P11),  # Φ(t,t0)ᵀ CᵀC Ψ₁₁ⁱ
                "W0": Phi.T @ CC @ Phi,
                "Na": jnp.einsum("iba,bc,icd->iad", P11, CC, P11),
                "Nb": jnp.einsum("iba,bc,icd->iad", P21, BB, P21),
            }
            if data:
                yt = jnp.asarray(y(t))
                w = C.T @ yt
                if u is not None:
                    w2 = B @ jnp.asarray(u(t))
                else:
                    w2 = jnp.zeros(N)
                d["v"] = jnp.einsum("iba,b->ia", P11, w) + jnp.einsum("iba,b->ia", P21, w2)
            return d

        s0 = {
            "Phi": I,
            "Psi": Psi0,
            "J": jnp.zeros((N, N, N)),
            "W0": Z,
            "Na": jnp.zeros((N, N, N)),
            "Nb": jnp.zeros((N, N, N)),
        }
        if data:
            s0["v"] = jnp.zeros((N, N))
        saveat = diffrax.SaveAt(t1=True) if save_ts is None else diffrax.SaveAt(ts=save_ts, t1=True)
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(rhs),
            diffrax.Tsit5(),
            self.t0,
            self.t1,
            None,
            s0,
            saveat=saveat,
            stepsize_controller=diffrax.PIDController(rtol=self.rtol, atol=self.atol),
            max_steps=200_000,
        )
        return sol.ys

    def _design_from(self, end):
        """c_i = D_i e_i from the window integrals at t1 (rows of the LTV (25))."""
        N = self.dim
        Phi1 = end["Phi"]
        # D_i⁻¹ = ∫ Φ(t,t1)ᵀ CᵀC Ψ₁₁ⁱ dt = Φ(t1,t0)⁻ᵀ J_i
        Dinv = jax.vmap(lambda J: jnp.linalg.solve(Phi1.T, J))(end["J"])
        c = jax.vmap(lambda Di, e: jnp.linalg.solve(Di, e))(Dinv, jnp.eye(N))
        return c

    def gramian(self):
        """The window gramian referred to t1, M = ∫_{t0}^{t1} Φ(t, t1)ᵀ CᵀC Φ(t, t1) dt (Lemma 1)."""
        end = jax.tree_util.tree_map(lambda a: a[-1], self._solve())
        Pinv = jnp.linalg.inv(end["Phi"])
        return Pinv.T @ end["W0"] @ Pinv

    def gramian_rcond(self):
        """Lemma 1's scale-invariant test of the window gramian: the squared smallest relative residual
        of a state direction outside those before it (0 when the gramian is singular; ≤ 1)."""
        return _gram_rcond(self.gramian())

    def kernels(self, ts):
        """The optimal kernels G1(t) (K, N, m) and G2(t) (K, N, p) at the times `ts` ⊂ [t0, t1]."""
        ts = vector(ts, "ts", None)
        tsc, t0, t1 = concrete_value(ts), concrete_value(self.t0), concrete_value(self.t1)
        if tsc is not None and t0 is not None and t1 is not None:
            tol = float(_time_tol(t1 - t0, t0, t1))
            if tsc.min() < t0 - tol or tsc.max() > t1 + tol:
                raise ValueError(
                    f"`ts` must lie in the window [t0, t1] = [{float(t0)}, {float(t1)}], got "
                    f"[{tsc.min()}, {tsc.max()}]."
                )
        ts = jnp.clip(ts, self.t0, self.t1)  # rounding at the window's ends (e.g. t0 + T vs a sample)
        ys = self._solve(save_ts=ts)
        sel = jax.tree_util.tree_map(lambda a: a[:-1], ys)
        c = self._design_from(jax.tree_util.tree_map(lambda a: a[-1], ys))
        N = self.dim
        mdl = self.model

        def at(t, Psi):
            k1 = jnp.einsum("iab,ib->ia", Psi[:, :N], c)  # (N rows, N)
            p = jnp.einsum("iab,ib->ia", Psi[:, N:], c)
            return k1 @ mdl.C_of(t).T, p @ mdl.B_of(t)

        return jax.vmap(at)(ts, sel["Psi"])

    def norm(self):
        """The norm (15) of the optimal observer, √(Σᵢ αᵢ‖g1ⁱ‖² + βᵢ‖g2ⁱ‖²) (exact integrals)."""
        end = jax.tree_util.tree_map(lambda a: a[-1], self._solve())
        c = self._design_from(end)
        qa = jnp.einsum("ia,iab,ib->i", c, end["Na"], c)
        qb = jnp.einsum("ia,iab,ib->i", c, end["Nb"], c)
        return jnp.sqrt(jnp.sum(self.alpha * qa + self.beta * qb))

    def estimate(self, y, u=None):
        """x̂(t1) (and θ̂) from the data as callables t ↦ y(t) (m,), u(t) (p,): (14) integrated exactly
        (to the solver tolerance) inside the same solve; the data must be JAX-traceable (e.g. a diffrax
        dense solution or an interpolation of samples)."""
        if not callable(y) or (u is not None and not callable(u)):
            raise ValueError("`y` (and `u`) must be callables of t; use estimate_window for samples.")
        end = jax.tree_util.tree_map(lambda a: a[-1], self._solve(y=y, u=u))
        c = self._design_from(end)
        return jnp.einsum("ia,ia->i", c, end["v"])

    def estimate_window(self, ts, ys, us=None, *, rule="auto"):
        """x̂(t1) (and θ̂) from samples of y, u on a grid `ts` from t0 to t1 ((14) by quadrature).

        **Arguments:** `ts` (K,) increasing with ts[0] = t0, ts[-1] = t1; `ys` (K, m); `us` (K, p) or None;
        `rule`: ``"simpson"`` (uniform grid, odd K; error O(h⁴)), ``"trapezoid"`` (O(h²)) or ``"auto"``
        (Simpson when `ts` is concrete, uniform and K odd; the trapezoid otherwise, e.g. for `ts` traced
        under ``jit``: pass ``rule="simpson"`` there for Simpson's accuracy).  Under ``jit`` the grid
        checks (increasing, from t0 to t1, uniform for Simpson) run as run-time checks (``eqx.error_if``).

        Derivatives: reverse mode (``jax.grad``); forward mode (``jax.jvp``, ``jax.jacfwd``) is not
        available, since the kernels are integrated with diffrax's default adjoint (a ``custom_vjp``).

        **Returns:** the estimate, shape (N,) (N = n, or n + q with a parameter map).
        """
        tsc = _concrete_grid(ts)
        ts = vector(ts, "ts", None)
        K = ts.shape[0]
        m = int(self.model.C_of(jnp.asarray(0.0)).shape[0])
        p = int(self.model.B_of(jnp.asarray(0.0)).shape[1])
        if K < 2:
            raise ValueError(f"`ts` must hold at least 2 sample times, got {K}.")
        ys = as_float_array(ys, "ys")
        if ys.shape != (K, m):
            raise ValueError(f"`ys` must have shape ({K}, {m}), got {tuple(ys.shape)}.")
        us = jnp.zeros((K, p)) if us is None else as_float_array(us, "us")
        if us.shape != (K, p):
            raise ValueError(f"`us` must have shape ({K}, {p}), got {tuple(us.shape)}.")
        if rule not in ("auto", "simpson", "trapezoid"):
            raise ValueError(f"`rule` must be 'auto', 'simpson' or 'trapezoid', got {rule!r}.")
        t0, t1 = concrete_value(self.t0), concrete_value(self.t1)
        uniform = None
        if tsc is not None:
            dt = np.diff(tsc)
            if not np.all(dt > 0):
                raise ValueError("`ts` must be strictly increasing.")
            if t0 is not None and t1 is not None:
                tol = float(_time_tol(t1 - t0, t0, t1))
                if abs(tsc[0] - t0) > tol or abs(tsc[-1] - t1) > tol:
                    raise ValueError(
                        f"`ts` must run from t0 = {float(t0)} to t1 = {float(t1)}, got "
                        f"[{tsc[0]}, {tsc[-1]}]."
                    )
            uniform = bool(_uniform(tsc))
        if rule == "auto":
            rule = "simpson" if (uniform and K % 2 == 1) else "trapezoid"
        if rule == "simpson" and (K % 2 == 0 or uniform is False):
            raise ValueError("Simpson's rule needs a uniform grid `ts` with an odd number of samples.")
        if tsc is None or t0 is None or t1 is None:  # the checks above, at run time (traced times)
            d = jnp.diff(ts)
            tol = _time_tol(self.t1 - self.t0, self.t0, self.t1)
            ts = eqx.error_if(ts, ~jnp.all(d > 0), "FiniteWindowLTV.estimate_window: `ts` must be strictly increasing.")
            ts = eqx.error_if(
                ts,
                (jnp.abs(ts[0] - self.t0) > tol) | (jnp.abs(ts[-1] - self.t1) > tol),
                "FiniteWindowLTV.estimate_window: `ts` must run from t0 to t1.",
            )
            if rule == "simpson":
                ts = eqx.error_if(
                    ts, jnp.any(jnp.abs(d - d[0]) > 1e-9 * jnp.abs(d[0]) + _CLOCK_ULPS * _EPS * jnp.max(jnp.abs(ts))),
                    "FiniteWindowLTV.estimate_window: Simpson's rule needs a uniform grid `ts`.",
                )
        G1, G2 = self.kernels(ts)
        w = _quadrature_weights(ts, rule)
        return jnp.einsum("k,kij,kj->i", w, G1, ys) + jnp.einsum("k,kij,kj->i", w, G2, us)


# ------------------------------------------------------------------------------------------------------
# The closed loop (33)-(37) simulated directly as a delay equation (method of steps, Lemma 2).
# ------------------------------------------------------------------------------------------------------


class DelayLoop(NamedTuple):
    """Result of :func:`delay_closed_loop`: grid `ts` (K+1,), state `x` (K+1, n), control `u` (K+1, p) and the
    window estimate `xhat` (K+1, n) of (33) at each grid time (right limits at t0)."""

    ts: jax.Array
    x: jax.Array
    u: jax.Array
    xhat: jax.Array


def delay_closed_loop(observer, P, x0, xhat0, t1, *, steps_per_window=200, phi_x=None, phi_u=None, v=None):
    """The closed loop (32)-(37) of Byrski & Fuksa simulated directly, as the delay (Volterra) equation.

        ẋ = A x + B u,   u(t) = P [∫₀ᵀ G1(s) y(t − T + s) ds + ∫₀ᵀ G2(s) u(t − T + s) ds],   y = C x + v   (33)-(37)

    with the history (36) x = φ2, u = φ1 on [t0 − T, t0).  Lemma 2's method of steps on a uniform grid of
    step h = T / `steps_per_window`: the plant by the trapezoidal rule, each window integral by the
    trapezoidal rule cell by cell (each cell keeps its own end values, so the jump of the data at t0, where
    the history meets the plant's initial state, costs no accuracy), and the G2(T) u(t) term of the
    newest cell solved implicitly with the plant step (one (n + p) linear system per step).  Second-order
    accurate in h.  (39)-(40) is the derivative of (37) in t and has the same solution from u(t0) given by
    (37); the tests check (39) along the solution.  The integral form is integrated rather than (40)
    because it needs no derivative of the data (measurement noise enters as it is measured) and no Ġ1,
    Ġ2, and because the history of (36) generally jumps into the plant's data at t0.  (As printed, (40)
    has u(t) for u̇(t) on its left-hand side and Ġ2(tT + s) for Ġ2(T + s).)

    This is the loop that :func:`obsjax.simulate` with ``controller = P x̂`` approximates by the
    sample-and-propagate observer (x̂ recomputed by (14) at the ``n_chunks`` instants per window and
    propagated by the model in between); the two agree as n_chunks grows, and exactly (up to the ODE and
    quadrature errors) for model-consistent, noise-free data.

    **Arguments:**

    - `observer`: a :class:`FiniteWindow` (its model, T and kernels).
    - `P`: (p, n) state-feedback matrix.
    - `x0`: the plant state at t0 = 0; `xhat0`: the estimate whose free response is the default history.
    - `t1`: final time.
    - `steps_per_window`: grid steps per window length T.
    - `phi_x`, `phi_u`: history callables on [−T, 0) (defaults: φ2(t) = e^{At} x̂0, φ1 = 0, the history
      :class:`FiniteWindow` assumes in a simulation).
    - `v`: optional measurement noise on the grid, shape (K+1, m) (y = Cx + v for t ≥ t0).

    **Returns:** a :class:`DelayLoop` (ts, x, u, xhat).

    **Example:**

        loop = obsjax.delay_closed_loop(obsjax.FiniteWindow(model, 1.0), P, x0, xhat0, 8.0)
    """
    if not isinstance(observer, FiniteWindow):
        raise ValueError(f"`observer` must be an obsjax.FiniteWindow, got {type(observer).__name__}.")  # noqa: TRY004 (project rule: ValueError)
    mdl = observer.model
    A, B, C = mdl.A, mdl.B, mdl.C
    n, m, p = mdl.n, mdl.m, mdl.p
    P = as_float_array(P, "P")
    if P.shape != (p, n):
        raise ValueError(f"`P` must have shape ({p}, {n}), got {tuple(P.shape)}.")
    x0, xhat0 = vector(x0, "x0", n), vector(xhat0, "xhat0", n)
    P, x0, xhat0 = traced_finite(P, "P"), traced_finite(x0, "x0"), traced_finite(xhat0, "xhat0")
    Tw = concrete_value(observer.T)
    if Tw is None:
        raise ValueError("`observer.T` must be concrete (the grid is built before tracing).")
    N = state_dimension(steps_per_window, "steps_per_window", minimum=2)
    t1v = None if isinstance(t1, bool) else scalar_value(t1)
    if t1v is None or np.ndim(t1v) != 0 or not np.isfinite(t1v) or not float(t1v) > 0:
        raise ValueError(
            f"`t1` must be a concrete finite time > 0 (the loop starts at t0 = 0; the grid is built before "
            f"tracing), got {t1!r}."
        )
    h = float(Tw) / N
    K = int(np.ceil(float(t1v) / h - 1e-9))
    ts = jnp.arange(K + 1) * h
    if v is None:
        v = jnp.zeros((K + 1, m))
    v = as_float_array(v, "v")
    if v.shape != (K + 1, m):
        raise ValueError(f"`v` must have shape ({K + 1}, {m}) (one sample per grid time), got {tuple(v.shape)}.")
    v = traced_finite(v, "v")
    if phi_x is None:
        phi_x = lambda t: expm(A * t) @ xhat0
    if phi_u is None:
        phi_u = lambda t: jnp.zeros(p)
    s = jnp.arange(N + 1) * h
    G1, G2 = observer.kernels(s)  # (N+1, n, m), (N+1, n, p): s_j, j = 0..N
    # history cells j = 0..N−1 cover [−T + jh, −T + (j+1)h]: left and right end values
    th = -float(Tw) + s
    yh = jax.vmap(lambda t: C @ phi_x(t))(th)
    uh = jax.vmap(lambda t: jnp.asarray(phi_u(t)).reshape(p))(th)
    xs, us, xhs, xh0, u0 = _delay_core(A, B, C, P, G1, G2, yh, uh, x0, v, jnp.asarray(h))
    return DelayLoop(
        ts,
        jnp.concatenate([x0[None], xs]),
        jnp.concatenate([u0[None], us]),
        jnp.concatenate([xh0[None], xhs]),
    )


@jax.jit
def _delay_core(A, B, C, P, G1, G2, yh, uh, x0, v, h):
    """Method of steps for (32)-(37) on cells of length h (see :func:`delay_closed_loop`)."""
    n, m, p = A.shape[0], C.shape[0], B.shape[1]
    # the right end of the last history cell is the left limit at t0: φ(0−)
    Yl, Yr, Ul, Ur = yh[:-1], yh[1:], uh[:-1], uh[1:]
    w = 0.5 * h

    def window(Yl, Yr, Ul, Ur):
        """(14) over the N cells: x̂ = Σ_j h/2 [G(s_j) left_j + G(s_{j+1}) right_j]."""
        return w * (
            jnp.einsum("jim,jm->i", G1[:-1], Yl) + jnp.einsum("jim,jm->i", G1[1:], Yr)
            + jnp.einsum("jip,jp->i", G2[:-1], Ul) + jnp.einsum("jip,jp->i", G2[1:], Ur)
        )

    xh0 = window(Yl, Yr, Ul, Ur)  # x̂(t0) from the history alone
    u0 = P @ xh0
    I_n, I_p = jnp.eye(n), jnp.eye(p)
    # implicit step: [I − h/2 A, −h/2 B; −P w G1(T) C, I − P w G2(T)] [x⁺; u⁺] = rhs
    Mat = jnp.block([[I_n - w * A, -w * B], [-(P @ (w * G1[-1] @ C)), I_p - P @ (w * G2[-1])]])

    def step(carry, v_next):
        x, u, y, Yl, Yr, Ul, Ur = carry
        # the window at t + h drops cell 0 and appends [t, t + h] with left values (y, u) at the plant's
        # present (right limits) and right values (y⁺, u⁺) unknown
        Yl2 = jnp.concatenate([Yl[1:], y[None]])
        Ul2 = jnp.concatenate([Ul[1:], u[None]])
        Yr_known = jnp.concatenate([Yr[1:], jnp.zeros((1, m), Yr.dtype)])
        Ur_known = jnp.concatenate([Ur[1:], jnp.zeros((1, p), Ur.dtype)])
        known = window(Yl2, Yr_known, Ul2, Ur_known) + w * G1[-1] @ v_next
        rhs = jnp.concatenate([x + w * (A @ x + B @ u), P @ known])
        sol = jnp.linalg.solve(Mat, rhs)
        x1, u1 = sol[:n], sol[n:]
        y1 = C @ x1 + v_next
        Yr2 = Yr_known.at[-1].set(y1)
        Ur2 = Ur_known.at[-1].set(u1)
        xh1 = window(Yl2, Yr2, Ul2, Ur2)
        return (x1, u1, y1, Yl2, Yr2, Ul2, Ur2), (x1, u1, xh1)

    y0 = C @ x0 + v[0]
    _, (xs, us, xhs) = jax.lax.scan(step, (x0, u0, y0, Yl, Yr, Ul, Ur), v[1:])
    return xs, us, xhs, xh0, u0
