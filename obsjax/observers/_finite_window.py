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

from functools import partial
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import expm

from .._checks import as_float_array, concrete_value, vector
from .._config import require_x64
from ..systems._plants import LTI
from ._base import AbstractObserver
from ._validation import require_finite

_FORMULAS = ("auto", "(25)", "(28)")


# ------------------------------------------------------------------------------------------------------
# The maths, as pure functions of the model matrices and the weights (all differentiable).
# ------------------------------------------------------------------------------------------------------


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
    """

    W: jax.Array
    readout: jax.Array
    prefill: jax.Array


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
        W, coef = self._design()
        G1, G2 = _kernels_at(W, coef, self.model.B, self.model.C, s.reshape(-1))
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
        tsc, Tc = concrete_value(ts), concrete_value(self.T)
        uniform = None
        if tsc is not None:
            dt = np.diff(tsc)
            if not np.all(dt > 0):
                raise ValueError("`ts` must be strictly increasing.")
            if Tc is not None and abs((tsc[-1] - tsc[0]) - Tc) > 1e-9 * max(1.0, abs(float(Tc))):
                raise ValueError(
                    f"`ts` must span the window [t − T, t]: ts[-1] − ts[0] = {tsc[-1] - tsc[0]!r}, "
                    f"T = {float(Tc)!r}."
                )
            uniform = np.allclose(dt, dt[0], rtol=1e-9, atol=0.0)
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
            jnp.abs((ts[-1] - ts[0]) - self.T) > 1e-9 * jnp.maximum(1.0, jnp.abs(self.T)),
            "FiniteWindow.estimate_window: `ts` must span [t − T, t].",
        )
        G1, G2 = self.kernels(ts - ts[0])
        return _quadrature(wts, G1, G2, ys, us, self.model.D)

    # ---- the sliding-window observer in a simulation (Section 4) ------------------------------------
    @property
    def reset_period(self):
        """h = T / n_chunks: at t0 + kh the buffer of window pieces shifts and x̂ is recomputed by (14)."""
        Tc = concrete_value(self.T)
        if Tc is not None:  # concrete even inside jit (a closed-over T), so simulate can count segments
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
        A, B, C, D = self.model.A, self.model.B, self.model.C, self.model.D
        win = self._win()
        w = jnp.concatenate([C.T @ (y - D @ u), B @ u])
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
    T, alpha, beta = _checked(T, alpha, beta, formula)
    n = A.shape[0]
    if formula == "(28)":
        W, R = _uniform_R(A, B, C, T)
        E1 = jnp.concatenate([jnp.eye(n), jnp.zeros((n, n))], axis=1)
        # row i of G1(s) = R[i] [I 0] e^{Wᵀs} [I; 0] Cᵀ  ⇔  generator vector e^{Ws} [I; 0] R[i]ᵀ
        coef = (R @ E1)[:, None, :]  # (n, 1, 2n)
        W = W[None]
    else:
        W, c = _general_rows(A, B, C, T, beta / alpha)
        coef = jnp.eye(n)[:, :, None] * c[None, :, :]  # (n, n, 2n): row i uses only W_i
    bad = ~(jnp.all(jnp.isfinite(W)) & jnp.all(jnp.isfinite(coef)))
    coef = eqx.error_if(
        coef,
        bad,
        "FiniteWindow: the kernel design is not finite (window too long for the Hamiltonian's growth?).",
    )
    return W, coef


@jax.jit
def _kernels_at(W, coef, B, C, s):
    n = C.shape[1]

    def at(si):
        V = jnp.einsum("kab,ikb->ia", jax.vmap(lambda Wk: expm(Wk * si))(W), coef)  # (n, 2n)
        return V[:, :n] @ C.T, V[:, n:] @ B

    return jax.vmap(at)(s)


@partial(jax.jit, static_argnames="formula")
def _norm(A, B, C, T, alpha, beta, formula):
    W, coef = _design(A, B, C, T, alpha, beta, formula)
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
    W, coef = _design(A, B, C, T, alpha, beta, formula)  # (r, 2n, 2n), (n, r, 2n)
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
    prefill = jnp.einsum("kan,jnl->jkal", Gam, back)
    return _Window(W=W, readout=readout, prefill=prefill)


@jax.jit
def _quadrature(wts, G1, G2, ys, us, D):
    yd = ys - us @ D.T
    return jnp.einsum("k,kij,kj->i", wts, G1, yd) + jnp.einsum("k,kij,kj->i", wts, G2, us)


def _check_observable(model: LTI) -> None:
    A, C = concrete_value(model.A), concrete_value(model.C)
    if A is None or C is None:
        return
    n = A.shape[0]
    O = np.vstack([C @ np.linalg.matrix_power(A, k) for k in range(n)])
    s = np.linalg.svd(O, compute_uv=False)
    rank = int(np.sum(s > s[0] * 1e-10)) if s[0] > 0 else 0
    if rank < n:
        raise ValueError(
            f"FiniteWindow needs an observable model: the observability matrix of (A, C) has rank {rank}, "
            f"expected {n} (Lemma 1: the columns of C e^{{−A(T−t)}} must be linearly independent)."
        )
