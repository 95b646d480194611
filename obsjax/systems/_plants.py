"""Plants: the truth that :func:`obsjax.simulate` integrates, and the models observers carry.

Every plant is an :class:`equinox.Module` with

    ẋ = f(t, x, u),     y = h(t, x, u),

``n`` ≥ 1 states, ``m`` ≥ 1 outputs and ``p`` ≥ 0 inputs (static).  ``jump_ts`` lists known
discontinuities in time (switching parameters).  :func:`obsjax.simulate` makes every declared jump a segment
boundary of its integration: no solve ever steps across one (a solve ends one float before the jump and the
next starts at it), so the vector field is smooth inside every solve and gradients with respect to anything
that moves the time grid (a reset period above all) are those of smooth solves.

Matrices are checked when the plant is built: real, finite, of consistent shapes (a ``ValueError`` names the
matrix, the expected and the found value).  Float32 input is promoted to float64.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import device_array, matrix, real_array, require_finite


def _jump_ts(jump_ts):
    if jump_ts is None:
        return None
    try:
        arr = np.atleast_1d(np.asarray(jump_ts, dtype=float))
    except (TypeError, ValueError) as e:
        raise ValueError(f"`jump_ts` must be a 1-D sequence of real times: {e}") from None
    if arr.ndim != 1:
        raise ValueError(f"`jump_ts` must be a 1-D sequence of times, got shape {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"`jump_ts` must hold finite times, got {arr[~np.isfinite(arr)].tolist()}.")
    return tuple(float(a) for a in np.sort(arr))


def _dimension(value, name, minimum):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"`{name}` must be an integer ≥ {minimum}, got {value!r}.")
    return int(value)


def _real_finite(x, name):
    """A real matrix with finite entries when its value is known (complex or NaN/inf is refused)."""
    arr = real_array(x, name)
    require_finite(arr, name)
    return arr


class AbstractSystem(eqx.Module):
    """A continuous-time plant ẋ = f(t, x, u), y = h(t, x, u)."""

    def f(self, t, x, u):
        raise NotImplementedError

    def h(self, t, x, u):
        raise NotImplementedError

    @property
    def jumps(self):
        """Known discontinuity times as an array, or ``None``."""
        jt = getattr(self, "jump_ts", None)
        return None if jt is None else jnp.asarray(jt)


class LTI(AbstractSystem):
    """Linear time-invariant plant (thesis (2.1), (2.5)).

        ẋ = A x + B u,      y = C x + D u.

    **Arguments:**

    - `A`: (n, n) system matrix.
    - `B`: (n, p) input matrix, or ``None`` for a free system (p = 0).
    - `C`: (m, n) output matrix.
    - `D`: (m, p) feedthrough, zero when ``None``.
    - `jump_ts`: optional known discontinuity times (finite) of the inputs used with this plant; they become
      segment boundaries of :func:`obsjax.simulate`.

    Shapes are checked: a wrong shape raises ``ValueError`` naming the matrix, the expected and the found
    shape; complex or non-finite entries are refused the same way (when the values are known, i.e. outside
    ``jit``).  All matrices are leaves, so a plant can be batched with ``jax.vmap`` (model uncertainty) and
    differentiated.

    **Example:** thesis example (2.8)::

        plant = obsjax.LTI(A=[[-2., 1.], [0., -1.]], B=[[0.], [1.]], C=[[1., 0.]])
    """

    A: jax.Array
    B: jax.Array
    C: jax.Array
    D: jax.Array
    jump_ts: tuple[float, ...] | None = eqx.field(static=True, default=None)

    def __init__(self, A, B=None, C=None, D=None, jump_ts=None):
        A = _real_finite(A, "A")
        if A.ndim != 2 or A.shape[0] != A.shape[1]:
            raise ValueError(f"`A` must be a square (n, n) matrix, got shape {tuple(A.shape)}.")
        n = A.shape[0]
        if n < 1:
            raise ValueError("`A` must have at least one state (n ≥ 1), got shape (0, 0).")
        if C is None:
            raise ValueError("`C` (the (m, n) output matrix) is required.")
        C = _real_finite(C, "C")
        if C.ndim == 1 and C.shape[0] == n:
            raise ValueError(
                f"`C` must be a 2-D (m, n) matrix, got a vector of shape {tuple(C.shape)}; "
                f"write [[...]] for one output."
            )
        C = matrix(C, "C", (None, n))
        m = C.shape[0]
        if m < 1:
            raise ValueError(f"`C` must have at least one output row (m ≥ 1), got shape {tuple(C.shape)}.")
        if B is None:
            B = device_array(np.zeros((n, 0), dtype=A.dtype))
        else:
            B = _real_finite(B, "B")
            if B.ndim == 1:
                raise ValueError(
                    f"`B` must be a 2-D (n, p) matrix, got a vector of shape {tuple(B.shape)}; "
                    f"write [[b1], [b2], ...] for one input."
                )
            B = matrix(B, "B", (n, None))
        p = B.shape[1]
        D = device_array(np.zeros((m, p), dtype=A.dtype)) if D is None else matrix(_real_finite(D, "D"), "D", (m, p))
        self.A, self.B, self.C, self.D = A, B, C, D
        self.jump_ts = _jump_ts(jump_ts)

    @property
    def n(self) -> int:
        return self.A.shape[0]

    @property
    def m(self) -> int:
        return self.C.shape[0]

    @property
    def p(self) -> int:
        return self.B.shape[1]

    def f(self, t, x, u):
        return self.A @ x + self.B @ u

    def h(self, t, x, u):
        return self.C @ x + self.D @ u

    # LTV-style accessors, so LTV observers accept LTI models unchanged.
    def A_of(self, t):
        return self.A

    def B_of(self, t):
        return self.B

    def C_of(self, t):
        return self.C

    @classmethod
    def from_control(cls, sys) -> "LTI":
        """Import a continuous-time ``control.StateSpace`` (python-control)."""
        dt = getattr(sys, "dt", 0)
        if dt not in (0, None) and dt is not False:
            raise ValueError(f"`sys` must be continuous-time (dt = 0), got dt = {dt}.")
        return cls(np.asarray(sys.A), np.asarray(sys.B), np.asarray(sys.C), np.asarray(sys.D))


def _shape_of(fn, name, t0=0.0):
    """Shape of ``fn(t0)``, checking that its value is a real, finite matrix."""
    try:
        out = jnp.asarray(fn(device_array(t0, dtype=jnp.result_type(float))))
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"`{name}` must be a callable of t returning a matrix; calling it failed: {e}")
    if out.ndim != 2:
        raise ValueError(f"`{name}(t)` must return a 2-D matrix, got shape {tuple(out.shape)}.")
    _real_finite(out, f"{name}(t) at t = {t0}")
    return out.shape


class LTV(AbstractSystem):
    """Linear time-varying plant (Chen & Yen (1)):

        ẋ = A(t) x + B(t) u,      y = C(t) x.

    **Arguments:**

    - `A`, `C`, `B`: callables of t returning (n, n), (m, n) and (n, p) matrices (``B=None``: free system).
      They may be equinox modules with array leaves (then a plant family can be vmapped), or closures over
      a parameter being differentiated (``jax.grad`` of a loss that builds ``LTV(lambda t: a * A0(t), ...)``
      differentiates in ``a``, with or without ``jit``).
    - `jump_ts`: times where A, B or C switch (piecewise-constant parameters); every solve of
      :func:`obsjax.simulate` ends at them (segment boundaries), none steps across.

    Shapes, realness and finiteness are checked by calling each callable at t = 0.
    """

    A_fn: Callable
    C_fn: Callable
    B_fn: Callable | None
    n: int = eqx.field(static=True)
    m: int = eqx.field(static=True)
    p: int = eqx.field(static=True)
    jump_ts: tuple[float, ...] | None = eqx.field(static=True, default=None)

    def __init__(self, A, C, B=None, jump_ts=None):
        if not callable(A) or not callable(C) or (B is not None and not callable(B)):
            raise ValueError("`A`, `C` (and `B` if given) must be callables of t returning matrices.")
        sa = _shape_of(A, "A")
        if sa[0] != sa[1] or sa[0] < 1:
            raise ValueError(f"`A(t)` must be square (n, n) with n ≥ 1, got shape {sa}.")
        n = sa[0]
        sc = _shape_of(C, "C")
        if sc[1] != n or sc[0] < 1:
            raise ValueError(f"`C(t)` must have shape (m, {n}) with m ≥ 1, got {sc}.")
        p = 0
        if B is not None:
            sb = _shape_of(B, "B")
            if sb[0] != n:
                raise ValueError(f"`B(t)` must have shape ({n}, p), got {sb}.")
            p = sb[1]
        self.A_fn, self.C_fn, self.B_fn = A, C, B
        self.n, self.m, self.p = n, sc[0], p
        self.jump_ts = _jump_ts(jump_ts)

    def A_of(self, t):
        return jnp.asarray(self.A_fn(t))

    def B_of(self, t):
        if self.B_fn is None:
            return jnp.zeros((self.n, 0))
        return jnp.asarray(self.B_fn(t))

    def C_of(self, t):
        return jnp.asarray(self.C_fn(t))

    def f(self, t, x, u):
        return self.A_of(t) @ x + self.B_of(t) @ u

    def h(self, t, x, u):
        return self.C_of(t) @ x


class Nonlinear(AbstractSystem):
    """Nonlinear (time-varying) plant ẋ = f(t, x, u), y = h(t, x, u) (Huang & Zhu (1)).

    **Arguments:** `f`, `h` callables; `n` ≥ 1 states, `m` ≥ 1 outputs, `p` ≥ 0 inputs (static integers);
    `jump_ts` optional (finite times).  ``f`` and ``h`` are checked once on zeros for their output shapes.
    """

    f_fn: Callable
    h_fn: Callable
    n: int = eqx.field(static=True)
    m: int = eqx.field(static=True)
    p: int = eqx.field(static=True)
    jump_ts: tuple[float, ...] | None = eqx.field(static=True, default=None)

    def __init__(self, f, h, n, m, p=0, jump_ts=None):
        if not callable(f) or not callable(h):
            raise ValueError("`f` and `h` must be callables f(t, x, u) and h(t, x, u).")
        n, m, p = _dimension(n, "n", 1), _dimension(m, "m", 1), _dimension(p, "p", 0)
        x, u = jnp.zeros(n), jnp.zeros(p)
        try:
            fx = jax.eval_shape(f, 0.0, x, u)
            hx = jax.eval_shape(h, 0.0, x, u)
        except Exception as e:  # noqa: BLE001
            raise ValueError(
                f"`f(t, x, u)` and `h(t, x, u)` must accept x of shape ({n},) and u of shape ({p},); "
                f"evaluating them failed: {e}"
            ) from None
        if fx.shape != (n,):
            raise ValueError(f"`f(t, x, u)` must return shape ({n},), got {fx.shape}.")
        if hx.shape != (m,):
            raise ValueError(f"`h(t, x, u)` must return shape ({m},), got {hx.shape}.")
        self.f_fn, self.h_fn = f, h
        self.n, self.m, self.p = n, m, p
        self.jump_ts = _jump_ts(jump_ts)

    def f(self, t, x, u):
        return self.f_fn(t, x, u)

    def h(self, t, x, u):
        return self.h_fn(t, x, u)
