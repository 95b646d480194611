"""Min-max (ℓ∞) initial-state estimation for discrete LTV systems and its combination with a Luenberger
observer (Chaisanguanmitt, slides "Finding the optimal initial condition ... by min max optimization" and
"The combination of two kinds of observers").

System (discrete time, k = 0, 1, ..., N):

    x(k+1) = A(k) x(k) + B(k) u(k),     y(k) = C(k) x(k).

Stacking y(k) = C(k)[Φ(k, 0) x0 + Σ_{j<k} Φ(k, j+1) B(j) u(j)] over the window gives the slides' (1)-(2)

    ȳ = ψ x0 + (residual),    ȳ(k) = y(k) − C(k) Σ_{j<k} Φ(k, j+1) B(j) u(j),    ψ(k) = C(k) Φ(k, 0).

The min-max problem (3)-(5) with measurement errors ‖δy‖∞ ≤ ε is the linear program

    min θ  over (x0, θ)   s.t.  −θ ≤ ȳ_i − (ψ x0)_i ± ε ≤ θ  for every row i,

solved here with HiGHS (``scipy.optimize.linprog(method="highs")``).  Because max(|r + ε|, |r − ε|) =
|r| + ε, its value is θ̂ = min ‖ȳ − ψ x0‖∞ + ε and its minimisers are those of the plain Chebyshev
problem (ε = 0): the ℓ∞ box of disturbances moves the optimal value, not the estimate.  Consequently the
quantity of the slides' Algorithm, ‖ȳ + ε·1 − ψ x̃0‖∞ − θ̂ (Figure 4), is never positive; it is zero
whenever the Chebyshev residual reaches +θ̃ on some row (the generic case), which
:func:`minmax_certificate` reports.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value


def _np(x, name):
    v = concrete_value(jnp.asarray(x)) if not isinstance(x, np.ndarray) else x
    if v is None:
        raise ValueError(
            f"`{name}` must be concrete (the min-max LP runs in SciPy/HiGHS, not under jit)."
        )
    if np.iscomplexobj(v):  # (NumPy would drop the imaginary part with a warning)
        raise ValueError(f"`{name}` must be real, got an array of dtype {np.asarray(v).dtype}.")
    v = np.asarray(v, dtype=float)
    if not np.all(np.isfinite(v)):
        raise ValueError(f"`{name}` must be finite, found NaN or inf.")
    return v


def _stack(x, name, count, shape):
    """Broadcast a constant matrix to (count, *shape) or check a stacked one."""
    x = _np(x, name)
    if x.ndim == 2:
        if x.shape != shape:
            raise ValueError(
                f"`{name}` must have shape {shape} (or ({count}, {shape[0]}, {shape[1]}) "
                f"stacked over k), got {x.shape}."
            )
        return np.broadcast_to(x, (count, *shape)).copy()
    if x.ndim == 3:
        if x.shape != (count, *shape):
            raise ValueError(
                f"`{name}` stacked over k must have shape ({count}, {shape[0]}, {shape[1]}), "
                f"got {x.shape}."
            )
        return x
    raise ValueError(
        f"`{name}` must be a matrix {shape} or a stack ({count}, ...), got shape {x.shape}."
    )


def _parse(A, B, C, ys, us):
    ys = _np(ys, "ys")
    if ys.ndim == 1:
        ys = ys[:, None]
    if ys.ndim != 2 or ys.shape[0] < 1:
        raise ValueError(f"`ys` must have shape (N + 1, m), got {ys.shape}.")
    N1, m = ys.shape
    N = N1 - 1
    A_ = _np(A, "A")
    n = A_.shape[-1]
    A = _stack(A_, "A", N, (n, n)) if N > 0 else np.zeros((0, n, n))
    C = _stack(C, "C", N1, (m, n))
    if B is None:
        B, p = np.zeros((N, n, 0)), 0
        if us is not None and _np(us, "us").size:
            raise ValueError("`us` given but `B` is None.")
        us = np.zeros((N, 0))
    else:
        B_ = _np(B, "B")
        p = B_.shape[-1]
        B = _stack(B_, "B", N, (n, p)) if N > 0 else np.zeros((0, n, p))
        if us is None:
            raise ValueError(f"`us` of shape ({N}, {p}) is required when `B` is given.")
        us = _np(us, "us")
        if us.ndim == 1 and p == 1:
            us = us[:, None]
        if us.shape != (N, p):
            raise ValueError(f"`us` must have shape (N, p) = ({N}, {p}), got {us.shape}.")
    return A, B, C, ys, us, N, n, m, p


def window_regression(A, B, C, ys, us=None):
    """ȳ and ψ of the slides' (2): ȳ = ψ x0 for exact data.

    **Arguments:** `A` (n, n) or (N, n, n); `B` (n, p), (N, n, p) or ``None``; `C` (m, n) or (N+1, m, n);
    `ys` (N+1, m); `us` (N, p) (``None`` when B is None).

    **Returns:** ``(ybar, psi)`` with ybar of shape ((N+1)·m,) and psi ((N+1)·m, n), rows ordered by k.
    """
    A, B, C, ys, us, N, n, _m, _p = _parse(A, B, C, ys, us)
    Phi = np.eye(n)  # Φ(k, 0)
    forced = np.zeros(n)  # Σ_{j<k} Φ(k, j+1) B(j) u(j)
    psi, ybar = [], []
    for k in range(N + 1):
        psi.append(C[k] @ Phi)
        ybar.append(ys[k] - C[k] @ forced)
        if k < N:
            Phi = A[k] @ Phi
            forced = A[k] @ forced + B[k] @ us[k]
    return np.concatenate(ybar), np.vstack(psi)


def _solve_lp(ybar, psi, eps):
    r, n = psi.shape
    # variables v = [x0, θ]; 4 inequalities per row (the slides' two double inequalities).
    one = np.ones((r, 1))
    A_ub = np.vstack(
        [
            np.hstack([-psi, -one]),  # ȳ − ψx + ε ≤ θ
            np.hstack([psi, -one]),  # −θ ≤ ȳ − ψx + ε
            np.hstack([-psi, -one]),  # ȳ − ψx − ε ≤ θ
            np.hstack([psi, -one]),  # −θ ≤ ȳ − ψx − ε
        ]
    )
    b_ub = np.concatenate([-ybar - eps, ybar + eps, -ybar + eps, ybar - eps])
    c = np.zeros(n + 1)
    c[-1] = 1.0
    bounds = [(None, None)] * n + [(0.0, None)]
    res = _linprog(c, A_ub=A_ub, b_ub=b_ub, bounds=bounds, method="highs")
    if res.status != 0:
        raise ValueError(
            f"The min-max linear program failed (HiGHS status {res.status}: {res.message})."
        )
    return res.x[:n], float(res.x[-1])


def _linprog(*args, **kwargs):
    import scipy.optimize  # imported on first use: importing obsjax stays free of SciPy's 0.4 s

    return scipy.optimize.linprog(*args, **kwargs)


def _solve_lp_sum(ybar, psi, eps, m):
    """The slides' cost (1): min Σ_k max_{‖δy(k)‖∞ ≤ ε} ‖ȳ(k) + δy(k) − ψ(k) x0‖∞ as an LP in (x0, θ_0..θ_N)."""
    r, n = psi.shape
    K = r // m
    S = np.kron(np.eye(K), np.ones((m, 1)))  # row (k, i) -> θ_k
    A_ub = np.vstack([np.hstack([-psi, -S]), np.hstack([psi, -S])])  # ±(ȳ − ψx) + ε ≤ θ_k
    b_ub = np.concatenate([-ybar - eps, ybar - eps])
    c = np.concatenate([np.zeros(n), np.ones(K)])
    bounds = [(None, None)] * n + [(0.0, None)] * K
    res = _linprog(c, A_ub=A_ub, b_ub=b_ub, bounds=bounds, method="highs")
    if res.status != 0:
        raise ValueError(
            f"The min-max linear program (cost (1)) failed (HiGHS status {res.status}: {res.message})."
        )
    return res.x[:n], float(res.fun)


def minmax_sum_initial_state(A, B, C, ys, us=None, eps=0.0):
    """Estimate of x(k0) minimising the slides' basic cost (1), a sum over k of ∞-norms.

        min_{x0} Σ_{k=k0}^{k0+N} max_{‖δy(k)‖∞ ≤ ε} ‖ȳ(k) + δy(k) − ψ(k) x0‖∞                        (1), (3)
          = min Σ_k θ_k  s.t.  −θ_k + ε ≤ ȳ(k)_i − (ψ(k) x0)_i ≤ θ_k − ε   ∀ k, i,

    a linear program in (x0, θ_0, …, θ_N) solved by HiGHS.  Cost (1) sums the per-sample worst residual
    (an ℓ1 norm over time of ℓ∞ norms over outputs); :func:`minmax_initial_state` minimises the stacked
    form (2), the ℓ∞ norm over all samples and outputs.  With one output, (1) is the least-absolute-deviation
    problem Σ_k |ȳ(k) − ψ(k) x0|, which passes exactly through n of the samples and ignores outliers that
    (2) has to balance.  The disturbance box adds (N + 1)·ε to the value and leaves the minimisers unchanged
    (max_{|δ| ≤ ε} ‖r + δ‖∞ = ‖r‖∞ + ε, sample by sample).

    **Arguments:** as :func:`minmax_initial_state`.

    **Returns:** ``(x0, cost)``: the estimate of x(k0) and the optimal value of (1).

    **Example:**

        x0, cost = obsjax.minmax_sum_initial_state(A_stack, B, C, ys, us, eps=0.01)
    """
    eps_v = float(_np(eps, "eps"))
    if eps_v < 0:
        raise ValueError(f"`eps` must be >= 0 (a bound on |δy|), got {eps_v}.")
    ybar, psi = window_regression(A, B, C, ys, us)
    m = psi.shape[0] // _window_len(ys)
    psi_s, d = _equilibrate(psi)
    _require_full_rank(psi_s, m)
    x, cost = _refine(lambda yb, ps, e: _solve_lp_sum(yb, ps, e, m), ybar, psi_s, eps_v)
    return d * x, cost


def minmax_initial_state(A, B, C, ys, us=None, eps=0.0):
    """Min-max estimate of x(k0) from a window of data (slides (1)-(5)).

        min_{x0} max_{‖δy‖∞ ≤ ε} ‖ȳ + δy − ψ x0‖∞
          = min θ  s.t.  −θ ≤ ȳ_i − (ψx0)_i + ε ≤ θ,  −θ ≤ ȳ_i − (ψx0)_i − ε ≤ θ  ∀ i,

    a linear program solved by HiGHS (``scipy.optimize.linprog(method="highs")``).  ``eps = 0`` gives the
    plain Chebyshev estimate min ‖ȳ − ψ x0‖∞ (step 1 of the slides' Algorithm).  Note θ̂(ε) = θ̂(0) + ε.

    **Arguments:**

    - `A`: (n, n) or stacked (N, n, n); `B`: (n, p), (N, n, p) or ``None``; `C`: (m, n) or (N+1, m, n).
    - `ys`: (N+1, m) measurements y(k0), ..., y(k0+N); `us`: (N, p) inputs u(k0), ..., u(k0+N−1).
    - `eps`: bound ε ≥ 0 on the measurement errors.

    **Returns:** ``(x0, theta)``: the estimate of x(k0) (n,) and the optimal value θ̂.

    Raises ``ValueError`` when ψ has rank < n (x0 is not determined by the window), for bad shapes or
    ε < 0, and when the LP solver does not report an optimum.

    **Example:**

        x0, theta = obsjax.minmax_initial_state(A_stack, B, C, ys, us, eps=0.01)
    """
    eps_v = float(_np(eps, "eps"))
    if eps_v < 0:
        raise ValueError(f"`eps` must be >= 0 (a bound on |δy|), got {eps_v}.")
    ybar, psi = window_regression(A, B, C, ys, us)
    psi_s, d = _equilibrate(psi)
    _require_full_rank(psi_s, psi.shape[0] // _window_len(ys))
    x, theta = _refine(_solve_lp, ybar, psi_s, eps_v)
    return d * x, theta


def _window_len(ys):
    return int(np.asarray(ys).shape[0])


def _refine(solve, ybar, psi, eps, rounds=4):
    """The LP, then the same LP for a correction δ on the residual ȳ − ψ x (min over x + δ is the
    same problem), while the value improves.  HiGHS's tolerances are relative to the size of the data:
    when ȳ spans many orders of magnitude (a fast growing mode over a long window) one solve leaves an
    error of order 1e-7·‖ȳ‖∞ in the value; each correction shrinks the data to the last residual."""
    x, val = solve(ybar, psi, eps)
    for _ in range(rounds):
        r = ybar - psi @ x
        dx, new = solve(r, psi, eps)
        if not new < val:
            break
        x, val = x + dx, new
    return x, val


def _equilibrate(psi):
    """(ψ D, diag D) with D = diag(1/‖ψ_j‖) (columns of unit norm; a zero column is kept as it is).

    x0 = D x̃0 maps the estimate back: the rank test and the LP on ψ D give the same verdict and the
    same x0 whatever the units of the states (x → S x with S diagonal: ψ → ψ S⁻¹, ψ D unchanged)."""
    norms = np.linalg.norm(psi, axis=0)
    d = np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 1.0)
    return psi * d, d


def _require_full_rank(psi_s, m):
    """Raise ValueError when ψ D (columns of unit norm) has numerical rank < n, with advice that fits:
    too few rows, a window longer than a well-conditioned one (a fast growing or decaying mode), or an
    unobservable / ill-conditioned window."""
    r, n = psi_s.shape
    sv = np.linalg.svd(psi_s, compute_uv=False)
    tol = sv.max(initial=0.0) * max(r, n) * np.finfo(float).eps
    rank = int(np.sum(sv > tol))
    if rank == n:
        return
    samples = r // m
    ratio = sv[-1] / sv[0] if sv.size == n and sv[0] > 0 else 0.0
    head = (
        f"`ys`: x(k0) is not determined by the window: ψ = [C(k)·Φ(k, k0)] (columns normalised) has "
        f"rank {rank} < n = {n} over N + 1 = {samples} samples (σ_min/σ_max = {ratio:.2e}, expected "
        f"> {max(r, n) * np.finfo(float).eps:.1e}); "
    )
    if r < n:
        raise ValueError(head + f"the window has {r} output rows < n = {n}: lengthen the window.")
    for k in range(-(-n // m), samples):  # the shortest prefix of the window with full rank
        pre, _ = _equilibrate(psi_s[: k * m])
        if np.linalg.matrix_rank(pre) == n:
            raise ValueError(
                head + f"its first {k} samples alone determine x(k0): the longer window is worse "
                "conditioned (a mode of A that grows or decays much faster than the others dominates "
                f"ψ), so lengthening it does not help: use a window of about {k} to {max(k, n)} samples "
                "or a better conditioned state basis."
            )
    raise ValueError(
        head + "the system may be unobservable over the window (a longer window helps only if it "
        "makes x(k0) observable), or ψ is too ill-conditioned (a fast growing or decaying mode: then a "
        "longer window makes it worse; try a shorter one)."
    )


class MinMaxAlgorithm(eqx.Module):
    """The quantities of the slides' Algorithm ("The useful of min max optimization")."""

    x_cheb: np.ndarray  # x̃0 = argmin ‖ȳ − ψ x0‖∞        (step 1)
    theta_cheb: float  # min ‖ȳ − ψ x0‖∞
    x_minmax: np.ndarray  # x̂0 of the min-max LP          (step 2)
    theta_minmax: float  # θ̂
    residual_cheb_shifted: float  # ‖ȳ + ε·1 − ψ x̃0‖∞      (step 3)
    residual_minmax_shifted: float  # ‖ȳ + ε·1 − ψ x̂0‖∞

    @property
    def gap(self) -> float:
        """‖ȳ + δy − ψ x̃0‖∞ − θ̂ with δy = ε·1 (the slides' Figure 4 quantity, claimed ≥ 0).

        Always ≤ 0 because ‖r + ε·1‖∞ ≤ ‖r‖∞ + ε and θ̂ = θ̃ + ε; = 0 when the Chebyshev residual reaches
        +θ̃ on some row."""
        return self.residual_cheb_shifted - self.theta_minmax


def minmax_algorithm(A, B, C, ys, us=None, eps=0.0) -> MinMaxAlgorithm:
    """Run the slides' Algorithm: steps 1-3 (Chebyshev estimate, min-max estimate, shift δy = ε·1).

    **Arguments:** as :func:`minmax_initial_state`.  **Returns:** a :class:`MinMaxAlgorithm`.
    """
    ybar, psi = window_regression(A, B, C, ys, us)
    x_t, th_t = minmax_initial_state(A, B, C, ys, us, 0.0)
    x_h, th_h = minmax_initial_state(A, B, C, ys, us, eps)
    e = float(eps)
    return MinMaxAlgorithm(
        x_cheb=x_t,
        theta_cheb=th_t,
        x_minmax=x_h,
        theta_minmax=th_h,
        residual_cheb_shifted=float(np.abs(ybar + e - psi @ x_t).max()),
        residual_minmax_shifted=float(np.abs(ybar + e - psi @ x_h).max()),
    )


def propagate(A, B, x0, us=None, steps=None):
    """x(k) of x(k+1) = A(k) x(k) + B(k) u(k) for k = 0..N from x(0) (NumPy; N from ``us`` or ``steps``)."""
    x0 = _np(x0, "x0")
    n = x0.shape[0]
    N = len(us) if us is not None else steps
    if N is None:
        raise ValueError("`us` or `steps` is required.")
    A = _stack(A, "A", N, (n, n)) if N else np.zeros((0, n, n))
    if B is None:
        B, us = np.zeros((N, n, 0)), np.zeros((N, 0))
    else:
        us = _np(us, "us").reshape(N, -1)
        B = _stack(B, "B", N, (n, us.shape[1])) if N else np.zeros((0, n, us.shape[1]))
    xs = [x0]
    for k in range(N):
        xs.append(A[k] @ xs[-1] + B[k] @ us[k])
    return np.stack(xs)


def _of_k(M, name):
    if callable(M):
        return M
    M = _np(M, name)
    if M.ndim != 2:
        raise ValueError(
            f"`{name}` must be a matrix or a callable k -> matrix, got shape {M.shape}."
        )
    return lambda k: M


class MinMaxResult(eqx.Module):
    """Output of :meth:`MinMaxLuenberger.run`: estimates of x(k) for k in ``ks``."""

    ks: np.ndarray  # (K', ) times k ≥ window
    xhat: np.ndarray  # (K', n) min-max start + Luenberger replay (the combination)
    xhat_minmax: np.ndarray  # (K', n) min-max start propagated by the model (pure min-max)
    x_start: np.ndarray  # (K', n) min-max estimate of x(k − window)
    theta: np.ndarray  # (K',) optimal θ̂ of each window's LP


class MinMaxLuenberger(eqx.Module):
    """Min-max initial-state estimate feeding a discrete Luenberger observer (slides, "The combination of
    two kinds of observers", Algorithm steps 1-4).

    At each time k (≥ W, the window length): (2) x̂(k − W) by :func:`minmax_initial_state` on the data
    y(k − W), ..., y(k) and u(k − W), ..., u(k − 1); (3)-(4) start the Luenberger observer

        z(j+1) = F z(j) + G(j) y(j) + T(j+1) B(j) u(j),     x̂(j) = T(j)⁻¹ z(j),
        G(j) = (T(j+1) A(j) − F T(j)) C^{1}(j)

    at z(k − W) = T(k − W) x̂(k − W) and replay it to k.  The discrete Lovass-Nagy condition
    (T(j+1) A(j) − F T(j))(I − C^{1} C) = 0 gives z(j+1) − T(j+1)x(j+1) = F (z(j) − T(j) x(j)) for the
    model; it is checked for every step of the record (``ValueError`` naming k and the residual).

    NumPy/SciPy (HiGHS) implementation: not jit-able.

    **Arguments:**

    - `A`, `B`, `C`: the model, constant matrices or callables of the integer k.
    - `F`: (n, n) observer matrix (eigenvalues inside the unit circle).
    - `window`: W ≥ 1, number of steps of each window [k − W, k].
    - `eps`: bound ε on measurement errors for the min-max LP.
    - `T`: optional constant matrix or callable k -> (n, n) (identity by default).
    - `rtol`: relative tolerance of the condition: ‖(T(k+1)A(k) − F T(k))(I − C^{1}C(k))‖ ≤
      rtol·(‖T(k+1)A(k)‖ + ‖F T(k)‖) (the same verdict for T and s·T).
    - `rcond_min`: smallest admissible σ_min(T(k))/σ_max(T(k)) (T(k) invertible, a scale-invariant test).

    **Example:** the slides' combination example, C invertible, T = I::

        obs = obsjax.MinMaxLuenberger(A_of_k, B, C, F=0.01 * np.diag([-10, -20, -30, -40]), window=5)
        res = obs.run(ys, us)
    """

    A: object
    B: object
    C: object
    F: np.ndarray
    T: object
    window: int = eqx.field(static=True)
    eps: float = eqx.field(static=True)
    rtol: float = eqx.field(static=True)
    rcond_min: float = eqx.field(static=True)

    def __init__(self, A, B, C, F, window, eps=0.0, T=None, rtol=1e-9, rcond_min=1e-10):
        self.A, self.B, self.C = (
            _of_k(A, "A"),
            (None if B is None else _of_k(B, "B")),
            _of_k(C, "C"),
        )
        A0, C0 = np.asarray(self.A(0), dtype=float), np.asarray(self.C(0), dtype=float)
        n = A0.shape[0]
        if A0.shape != (n, n):
            raise ValueError(f"`A(k)` must be square, got {A0.shape}.")
        if C0.ndim != 2 or C0.shape[1] != n:
            raise ValueError(f"`C(k)` must have shape (m, {n}), got {C0.shape}.")
        F = _np(F, "F")
        if F.shape != (n, n):
            raise ValueError(f"`F` must have shape ({n}, {n}), got {F.shape}.")
        rho = float(np.abs(np.linalg.eigvals(F)).max())
        if rho >= 1.0:
            raise ValueError(
                f"`F` must have its eigenvalues inside the unit circle, spectral radius {rho:.4g}."
            )
        self.F = F
        self.T = (lambda k: np.eye(n)) if T is None else _of_k(T, "T")
        if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1:
            raise ValueError(f"`window` must be an integer >= 1 (steps of each window), got {window!r}.")
        self.window = int(window)
        if not (float(eps) >= 0 and np.isfinite(float(eps))):
            raise ValueError(f"`eps` must be >= 0 and finite (a bound on |δy|), got {eps}.")
        self.eps = float(eps)
        self.rtol = float(rtol)
        self.rcond_min = float(rcond_min)

    def _stacks(self, K):
        A = np.stack([np.asarray(self.A(k), dtype=float) for k in range(K)])
        n = A.shape[1]
        B = (
            None
            if self.B is None
            else np.stack([np.asarray(self.B(k), dtype=float) for k in range(K)])
        )
        C = np.stack([np.asarray(self.C(k), dtype=float) for k in range(K + 1)])
        T = np.stack([np.asarray(self.T(k), dtype=float).reshape(n, n) for k in range(K + 1)])
        return A, B, C, T

    def gains(self, K):
        """G(k), k = 0..K−1, with the discrete Lovass-Nagy condition checked at every k."""
        A, _, C, T = self._stacks(K)
        self._check_T(T)
        Gs = []
        for k in range(K):
            M = T[k + 1] @ A[k] - self.F @ T[k]
            C1 = np.linalg.pinv(C[k])
            res = np.linalg.norm(M @ (np.eye(M.shape[1]) - C1 @ C[k]))
            # relative to the terms of M, no absolute floor: the same verdict for T and s·T (z in
            # other units) and for any scale of A and F
            scale = np.linalg.norm(T[k + 1] @ A[k]) + np.linalg.norm(self.F @ T[k])
            if not res <= self.rtol * scale:
                raise ValueError(
                    f"MinMaxLuenberger: the solvability condition (T(k+1)A(k) − F T(k))(I − C^{{1}}C(k)) = 0 "
                    f"fails at k = {k}: residual {res:.3e}, expected ≤ rtol·(‖T(k+1)A(k)‖ + ‖F T(k)‖) = "
                    f"{self.rtol:.1e}·{scale:.3e}; choose T(k) (or F) accordingly."
                )
            Gs.append(M @ C1)
        return np.stack(Gs)

    def _check_T(self, T):
        """T(k) invertible for every k: σ_min/σ_max > rcond_min (scale-invariant: T and s·T agree)."""
        for k, Tk in enumerate(T):
            sv = np.linalg.svd(Tk, compute_uv=False)
            rcond = sv[-1] / sv[0] if sv[0] > 0 else 0.0
            if not rcond > self.rcond_min:
                raise ValueError(
                    f"`T({k})` must be invertible: expected σ_min(T)/σ_max(T) > rcond_min = "
                    f"{self.rcond_min:.1e}, found {rcond:.3e} (det T = {np.linalg.det(Tk):.3e})."
                )

    def luenberger(self, ys, us=None, xhat0=None, start=0):
        """The Luenberger observer alone from x̂(start) = xhat0 over the record (k = start..K)."""
        ys = _np(ys, "ys")
        K = ys.shape[0] - 1
        _A, B, _C, T = self._stacks(K)
        G = self.gains(K)
        z = T[start] @ _np(xhat0, "xhat0")
        out = [np.linalg.solve(T[start], z)]
        for j in range(start, K):
            z = (
                self.F @ z
                + G[j] @ ys[j]
                + (0.0 if B is None else T[j + 1] @ B[j] @ np.asarray(us)[j])
            )
            out.append(np.linalg.solve(T[j + 1], z))
        return np.stack(out)

    def run(self, ys, us=None) -> MinMaxResult:
        """Estimates of x(k) for k = W..K from the record ys (K+1, m), us (K, p)."""
        ys = _np(ys, "ys")
        if ys.ndim == 1:
            ys = ys[:, None]
        K = ys.shape[0] - 1
        W = self.window
        if K < W:
            raise ValueError(f"`ys` must have more than window + 1 = {W + 1} samples, got {K + 1}.")
        A, B, C, T = self._stacks(K)
        if C.shape[1] != ys.shape[1]:
            raise ValueError(f"`ys` must have {C.shape[1]} columns (outputs), got {ys.shape[1]}.")
        if B is not None:
            if us is None:
                raise ValueError("`us` is required when the model has an input matrix B.")
            us = _np(us, "us")
            if us.ndim == 1:
                us = us[:, None]
            if us.ndim != 2 or us.shape[0] != K:
                raise ValueError(
                    f"`us` must have K = {K} rows (one input per step between the {K + 1} samples of `ys`), "
                    f"got shape {tuple(us.shape)}."
                )
        G = self.gains(K)
        ks, xc, xm, xs, th = [], [], [], [], []
        for k in range(W, K + 1):
            s = k - W
            Bw = None if B is None else B[s:k]
            uw = None if B is None else us[s:k]
            x_s, theta = minmax_initial_state(A[s:k], Bw, C[s : k + 1], ys[s : k + 1], uw, self.eps)
            # pure min-max: the model propagates x̂(k − W) to k
            x_m = x_s
            z = T[s] @ x_s
            for j in range(s, k):
                bu = 0.0 if B is None else B[j] @ us[j]
                x_m = A[j] @ x_m + bu
                z = self.F @ z + G[j] @ ys[j] + (0.0 if B is None else T[j + 1] @ bu)
            ks.append(k)
            xc.append(np.linalg.solve(T[k], z))
            xm.append(x_m)
            xs.append(x_s)
            th.append(theta)
        return MinMaxResult(
            ks=np.array(ks),
            xhat=np.stack(xc),
            xhat_minmax=np.stack(xm),
            x_start=np.stack(xs),
            theta=np.array(th),
        )
