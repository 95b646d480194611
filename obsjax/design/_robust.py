"""Robust, differentiable observer pole placement (the eigenvector method, dual of state feedback).

The observer gain L with eig(A − LC) = {λ_k} is built from a real matrix T of left eigenvectors (Jordan
chains where a pole must be defective) and the real block-diagonal F with the requested spectrum:

    T (A − L C) = F T     ⇔     T A − F T = G C,  G = T L,     L = (A − T⁻¹ F T) C⁺,

the Sylvester form of Theorem 1 of the thesis ((2.2)-(2.4)) for the identity observer.  Row k of T may be
any vector of the admissible space S(λ_k) = {t : t(A − λ_k I) ∈ rowspace C} (dimension m for an
observable pair); an orthonormal basis is the t-part of the left null space of the PBH matrix
[A − λ_k I; C], from a complete QR factorisation (Kautsky, Nichols & Van Dooren, "Robust pole assignment
in linear state feedback", Int. J. Control 41(5), 1985).  Within these spaces T minimises the
Tits-Yang measure

    φ(T) = Σ_k log ‖x_k‖ − log |det X|

of the complex eigenvector matrix X (rows x_k; a conjugate pair shares a real row pair of T), i.e. makes
the eigenvectors as orthogonal as the spaces allow (Tits & Yang, "Globally convergent algorithms for
robust pole assignment by state feedback", IEEE TAC 41(10), 1996), by Newton's method with the exact
Hessian.  The derivative of L with respect to A, C and the poles is that of the minimiser: the optimality
condition ∇φ = 0 is differentiated (implicit function theorem; the scale and phase symmetries of each
chain are removed), in a smooth local parametrisation of the admissible spaces (the orthogonal projection
of the bases found at the solution).

The layout of a placement (which rows are real, pairs, chained, fixed) is *data* (integer and float
arrays), so one compiled program serves every pole pattern of a given (n, m) and maximal chain length.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import device_array
from ._poles import Block

_MAXITER = 60
#: Curvature of φ below this fraction of its largest is flat (at a minimiser the symmetries give
#: |w| ≈ 1e-16 relative; the other curvatures seen on isolated minimisers are above 1e-3).
_FLAT = 1e-8
_GTOL = 1e-12
_LOCAL = 1e-4


class Layout(NamedTuple):
    """Row layout of T as arrays (leaves, so that pole patterns do not trigger recompilation).

    - `avg` (n, n): row r's eigenvalue is avg[r] @ poles (the mean of its cluster's copies; the member
      with Im > 0 for both rows of a pair).
    - `flag` (n,): 0 real row, 1 first row of a pair (Re x), 2 second row (−Im x).
    - `partner` (n,): the other row of a pair (itself for a real row).
    - `nxt` (n,), `has_next` (n,): the row of the next element of its Jordan chain; `prv`, `has_prev`
      the previous one.
    - `fixed` (n,): basis index l of a fixed row (a cluster of m simple copies), −1 otherwise.
    - `block` (n,): chain id (scale and phase symmetries, normalisation); `group` (n,): row group of φ
      (the two rows of a pair element share one); `gw` (n,): weight of each group id (0 if unused).
    - `nnull`: the number of symmetry directions of φ at its minimiser (each chain's scale, a pair's
      phase, and the orthogonal (unitary) mixing of the copies of a repeated simple pole), along which
      L does not change.
    """

    avg: jax.Array
    flag: jax.Array
    partner: jax.Array
    nxt: jax.Array
    has_next: jax.Array
    fixed: jax.Array
    block: jax.Array
    group: jax.Array
    gw: jax.Array
    nnull: jax.Array
    prv: jax.Array
    has_prev: jax.Array


def make_layout(blocks: tuple[Block, ...], n_poles: int) -> tuple[Layout, int]:
    """The :class:`Layout` of a tuple of :class:`Block` (numpy), and the longest chain."""
    n = sum(b.kind * b.length for b in blocks)
    avg = np.zeros((n, n_poles))
    flag = np.zeros(n, np.int32)
    partner = np.arange(n, dtype=np.int32)
    nxt = np.arange(n, dtype=np.int32)
    has_next = np.zeros(n)
    fixed = -np.ones(n, np.int32)
    block = np.zeros(n, np.int32)
    group = np.zeros(n, np.int32)
    gw = np.zeros(n)
    members: dict[int, list[int]] = {}
    for b in blocks:
        members.setdefault(b.cluster, []).extend(b.indices)
    fixed_count: dict[int, int] = {}
    r0, g = 0, 0
    for bid, b in enumerate(blocks):
        idx = members[b.cluster]
        for i in range(b.length):
            rows = [r0 + b.kind * i + j for j in range(b.kind)]
            for j, r in enumerate(rows):
                avg[r, idx] = 1.0 / len(idx)
                block[r] = bid
                group[r] = g
                if b.kind == 2:
                    flag[r] = 1 + j
                    partner[r] = rows[1 - j]
                if i + 1 < b.length:
                    nxt[r] = r + b.kind
                    has_next[r] = 1.0
                if b.fixed:
                    fixed[r] = fixed_count.get(b.cluster, 0)
            gw[g] = 0.5 if b.kind == 1 else 1.0
            g += 1
        if b.fixed:
            fixed_count[b.cluster] = fixed_count.get(b.cluster, 0) + 1
        r0 += b.kind * b.length
    prv = np.arange(n, dtype=np.int32)
    has_prev = np.zeros(n)
    for r in range(n):
        if has_next[r]:
            prv[nxt[r]], has_prev[nxt[r]] = r, 1.0
    nnull = 0
    for c in members:
        cb = [b for b in blocks if b.cluster == c]
        if cb[0].fixed:
            continue
        k, kind = len(cb), cb[0].kind
        if all(b.length == 1 for b in cb):
            nnull += k * (k + 1) // 2 if kind == 1 else k * k + k
        else:
            nnull += kind * k
    # (NumPy arrays moved by device_put: jnp.asarray compiles a program per shape on its first call)
    lay = Layout(
        device_array(avg),
        device_array(flag),
        device_array(partner),
        device_array(nxt),
        device_array(has_next),
        device_array(fixed),
        device_array(block),
        device_array(group),
        device_array(gw),
        jnp.asarray(nnull),
        device_array(prv),
        device_array(has_prev),
    )
    return lay, max(b.length for b in blocks)


def after(dep, x):
    """``x``, made to depend on ``dep``, so that the LAPACK call that
    consumes x runs after the one that produced dep.

    XLA runs independent operations concurrently on the CPU thread pool, and the batched LAPACK kernels of
    jaxlib 0.10 split a large batch over that pool and wait for it from inside a pool thread: two such
    kernels at once can take every thread of a small pool and wait forever (seen with 2 cores and a
    ``vmap`` over a few hundred pole sets).  The placement therefore keeps its batched factorisations
    on one chain of data dependencies: at most one runs at a time.  (An ``optimization_barrier`` does
    not do it: XLA's CPU pipeline removes it before the thunks are scheduled; x + 0·s with s a finite
    reduction of dep is a true dependency and leaves x unchanged.)"""
    s = jnp.nan_to_num(jnp.sum(jnp.real(jnp.asarray(dep))), nan=0.0, posinf=0.0, neginf=0.0)
    return x + (0.0 * s).astype(x.dtype)


#: Newton is started from this many fixed points; the minimiser kept is the one with the least
#: φ + log‖L‖ (Tits-Yang local minima of nearly equal φ can differ several-fold in gain).
_STARTS = 8


def _init(n: int, m: int, starts: int = _STARTS) -> np.ndarray:
    """Deterministic starts (starts, n·m): the sum of each row's basis vectors (SciPy's start for
    Tits-Yang), then fixed pseudo-random directions."""
    x = np.random.default_rng(20261122 + 97 * n + m).standard_normal((starts, n * m))
    x[0] = 1.0
    return x


# --------------------------------------------------------------------------------------------------
# bases of the admissible spaces, and T as a linear function of the parameters
# --------------------------------------------------------------------------------------------------


def _lams(lay: Layout, pr, pi):
    return lay.avg @ pr, lay.avg @ pi


def _pbh(A, C, lam, a, c):
    n = A.shape[0]
    return jnp.concatenate([(A - lam * jnp.eye(n)) / a, C.astype(lam.dtype) / c])


def _bases_qr(A, C, lam, a, c):
    """For one λ: N (m, n+m), left null rows of the PBH matrix with orthonormal t-parts N[:, :n]; the
    chain operator P (t ↦ the t' of least norm with t'(A − λI) − g'C = t); min |R_ii|."""
    n = A.shape[0]
    M = _pbh(A, C, lam, a, c)
    Q, R = jnp.linalg.qr(M, mode="complete")
    Nf = jnp.conj(Q[:, n:]).T
    _, Rh = jnp.linalg.qr(jnp.conj(Nf[:, :n]).T)
    N = jnp.linalg.solve(jnp.conj(Rh).T, Nf)
    R1 = after(N, R[:n])  # one factorisation at a time (see `after`)
    P = jax.scipy.linalg.solve_triangular(R1, jnp.conj(Q[:n, :n]).T, lower=False) / a
    return N, P, jnp.min(jnp.abs(jnp.diagonal(R1)))


def _bases_projected(A, C, lam, a, c, N0):
    """Smooth version of :func:`_bases_qr` near a point where N0 spans the left null space: N0 projected
    orthogonally onto it, and P from the pseudo-inverse of the PBH matrix."""
    n = A.shape[0]
    M = _pbh(A, C, lam, a, c)
    Mh = jnp.conj(M).T
    Mplus = jnp.linalg.solve(Mh @ M, Mh)
    return N0 - (N0 @ M) @ Mplus, Mplus[:, :n] / a


def _assemble(lay: Layout, N, P, m: int, depth: int):
    """T as a linear function of the parameters x (x_{r·m+q}: parameter q of row r):
    T = T_fix + Σ_k Σ_j x_k e_{R[k, j]} K[k, j] -- each parameter moves a few rows R[k, :] of T
    (compact K (n·m, 2·depth, n), rows R (n·m, 2·depth)).

    Per pair element x = (h₁ − i h₂) V, rows (Re x, −Im x); a chain element adds the next one times P
    (x_i = x_{i+1} P + h_i V, going up the chain through `prv`)."""
    n = N.shape[0]
    V = N[:, :, :n]  # (n, m, n) complex row bases
    free = (lay.fixed < 0).astype(V.real.dtype)
    sgn = jnp.where(lay.flag == 2, -1.0, 1.0)
    rows = jnp.repeat(jnp.arange(n), m)  # the parameter's own row
    part = lay.partner[rows]
    Vr = (jnp.real(V) * free[:, None, None]).reshape(n * m, n)
    Vi = (jnp.imag(V) * free[:, None, None]).reshape(n * m, n) * sgn[part][:, None]
    slots_r, slots_v = [rows, part], [Vr, Vi]
    Pre, Pim = jnp.real(P), jnp.imag(P)
    ra, rb, va, vb = rows, part, Vr, Vi
    for _ in range(depth - 1):
        ra2, rb2 = lay.prv[ra], lay.prv[rb]
        ma, mb = lay.has_prev[ra][:, None], lay.has_prev[rb][:, None]
        va2 = (jnp.einsum("pb,pbc->pc", va, Pre[ra2]) + sgn[ra2][:, None] * jnp.einsum("pb,pbc->pc", vb, Pim[ra2])) * ma
        vb2 = (jnp.einsum("pb,pbc->pc", vb, Pre[rb2]) + sgn[rb2][:, None] * jnp.einsum("pb,pbc->pc", va, Pim[rb2])) * mb
        ra, rb, va, vb = ra2, rb2, va2, vb2
        slots_r += [ra, rb]
        slots_v += [va, vb]
    K = jnp.stack(slots_v, axis=1)
    R = jnp.stack(slots_r, axis=1)
    lsafe = jnp.maximum(lay.fixed, 0)
    Vl = V[jnp.arange(n), lsafe]  # (n, n)
    Tfix = jnp.where(lay.flag == 2, -1.0, 1.0)[:, None] * jnp.where(
        (lay.flag == 2)[:, None], jnp.imag(Vl), jnp.real(Vl)
    )
    Tfix = Tfix * (lay.fixed >= 0)[:, None]
    return (K, R), Tfix


def _F(lay: Layout, lre, lim):
    n = lre.shape[0]
    pair = jnp.zeros((n, n)).at[jnp.arange(n), lay.partner].set(jnp.where(lay.flag == 1, 1.0, -1.0))
    pair = pair * (lay.flag > 0)[:, None]
    chain = jnp.zeros((n, n)).at[jnp.arange(n), lay.nxt].set(lay.has_next)
    return jnp.diag(lre) + pair * lim[:, None] + chain


# --------------------------------------------------------------------------------------------------
# the measure φ, its gradient and Hessian (T is linear in the parameters)
# --------------------------------------------------------------------------------------------------


def _T(x, K, Tfix):
    Kc, R = K
    return Tfix.at[R].add(x[:, None, None] * Kc)


def _groups(lay: Layout, T):
    s = jax.ops.segment_sum(jnp.sum(T**2, axis=1), lay.group, num_segments=T.shape[0])
    return jnp.where(lay.gw > 0, s, 1.0)


def _phi(x, K, Tfix, lay):
    T = _T(x, K, Tfix)
    return jnp.sum(lay.gw * jnp.log(_groups(lay, T))) - jnp.linalg.slogdet(T)[1]


def _grad(x, K, Tfix, lay):
    return _hess(x, K, Tfix, lay, with_grad=True)[0]


def _hess(x, K, Tfix, lay, with_grad=False):
    """Gradient and Hessian of φ = Σ_g w_g log s_g − log|det T| (s_g: squared norm of row group g), with
    T linear in x: ∂_k log|det T| = tr(T⁻¹K_k), ∂_k∂_l = −tr(T⁻¹K_k T⁻¹K_l)."""
    Kc, R = K
    T = _T(x, K, Tfix)
    n = T.shape[0]
    s = _groups(lay, T)
    coef = (2.0 * lay.gw / s)[lay.group]  # per row: 2 w_g / s_g
    Ti = jnp.linalg.inv(T)
    W = jnp.einsum("pjb,bs->pjs", Kc, Ti)  # W[k, j, s] = K[k, j] · T⁻¹[:, s]
    inner = jnp.sum(T[R] * Kc, axis=2)  # ⟨t_{R[k,j]}, K[k, j]⟩
    cols = jnp.arange(Kc.shape[0])[None, :]
    U = jnp.zeros((n, Kc.shape[0])).at[lay.group[R].T, cols].add(inner.T)  # (groups, k)
    G = jnp.einsum("pjb,qlb->pjql", Kc, Kc) * (R[:, :, None, None] == R[None, None, :, :])
    Hn = jnp.einsum("pjql,pj->pq", G, coef[R]) - (U.T * (4.0 * lay.gw / s**2)[None, :]) @ U
    Wg = W[:, :, R]  # Wg[k, j, l, i] = W[k, j, R[l, i]]
    Hd = jnp.einsum("pjql,qlpj->pq", Wg, Wg)
    H = Hn + Hd
    if not with_grad:
        return H
    tr = jnp.sum(jnp.take_along_axis(W, R[:, :, None], axis=2)[:, :, 0], axis=1)  # tr(T⁻¹ K_k)
    g = jnp.sum(coef[R] * inner, axis=1) - tr
    return g, H


def _param_rows(lay: Layout, m: int):
    return jnp.repeat(jnp.arange(lay.flag.shape[0]), m)


def _normalise(x, lay: Layout, m: int):
    """Each chain's parameters to unit norm (φ and L do not depend on that scale)."""
    b = lay.block[_param_rows(lay, m)]
    nrm = jnp.sqrt(jax.ops.segment_sum(x**2, b, num_segments=lay.flag.shape[0]))
    return x / jnp.where(nrm > 0, nrm, 1.0)[b]


def _newton(x0, K, Tfix, lay, m, maxiter):
    """Newton on φ with the absolute-value-regularised Hessian and a best-of backtracking search.

    Stops when the gradient vanishes, when no step decreases φ, or near the minimiser when the Newton
    decrement −gᵀd (the decrease the step promises) is at the rounding level of φ."""
    alphas = 2.0 ** -jnp.arange(10.0)
    fixed = jnp.repeat((lay.fixed >= 0).astype(x0.dtype), m)

    def cond(state):
        _, it, gn, done = state
        return (it < maxiter) & (gn > _GTOL) & ~done

    def body(state):
        x, it, _, _ = state
        g, H = _hess(x, K, Tfix, lay, with_grad=True)
        g = g * (1.0 - fixed)
        w, V = jnp.linalg.eigh(H)
        # saddle-free Newton: |eigenvalues|; directions of (numerically) zero curvature are the
        # symmetries of φ (scales, phases), along which nothing is to be gained: left out
        aw = jnp.abs(w)
        keep = aw > 1e-9 * jnp.max(aw)
        d = -V @ jnp.where(keep, (V.T @ g) / jnp.where(keep, aw, 1.0), 0.0) * (1.0 - fixed)
        # φ at x and along d in one batched call after the Hessian's (see `after`)
        steps = jnp.concatenate([jnp.zeros(1, alphas.dtype), alphas])
        pts = jax.vmap(lambda a: jnp.where(a == 0, x, x + a * d))(steps)
        both = jax.vmap(lambda p: _phi(p, K, Tfix, lay))(pts)
        f0, vals = both[0], both[1:]
        vals = jnp.where(jnp.isfinite(vals), vals, jnp.inf)
        k = jnp.argmin(vals)
        gn = jnp.linalg.norm(g)
        # near the minimiser φ no longer resolves the decrease: take the full (quadratically
        # convergent) Newton step there
        local = (gn < _LOCAL) & (vals[0] <= f0 + 1e-12 * (1.0 + jnp.abs(f0)))
        better = vals[k] < f0
        step = jnp.where(local, 1.0, alphas[k])
        xn = jnp.where(local | better, _normalise(x + step * d, lay, m), x)
        done = ~(local | better) | (local & (-(g @ d) < 1e-13 * (1.0 + jnp.abs(f0))))
        return xn, it + 1, gn, done

    init = (x0, jnp.asarray(0), jnp.asarray(jnp.inf, x0.dtype), jnp.asarray(False))
    x, it, gn, _ = jax.lax.while_loop(cond, body, init)
    return x, it, gn


# --------------------------------------------------------------------------------------------------
# the gain and its derivative
# --------------------------------------------------------------------------------------------------


def _gain(A, C, T, F):
    """L = (A − T⁻¹ F T) C⁺ with C⁺ = Q R⁻ᵀ from Cᵀ = Q R."""
    Qc, Rc = jnp.linalg.qr(C.T)
    M = A - jnp.linalg.solve(T, F @ T)
    return jax.scipy.linalg.solve_triangular(Rc, (M @ Qc).T, lower=False).T


def _scales(A, C, lre, lim):
    big = jnp.max(jnp.abs(lre + 1j * lim))
    a = jax.lax.stop_gradient(jnp.linalg.norm(A) + big + jnp.finfo(A.dtype).tiny)
    c = jax.lax.stop_gradient(jnp.linalg.norm(C) + jnp.finfo(A.dtype).tiny)
    return a, c


def forward(lay: Layout, A, C, pr, pi, *, m: int, depth: int, maxiter: int = _MAXITER):
    """The placement without derivatives: (L, T, x, N, (a, c), info)."""
    n = A.shape[0]
    lre, lim = _lams(lay, pr, pi)
    a, c = _scales(A, C, lre, lim)
    # Householder QR keeps real data real: the bases of real poles come out real.
    qr = jax.vmap(_bases_qr, in_axes=(None, None, 0, None, None))
    N, P, piv = qr(A, C, lre + 1j * lim, a, c)
    K, Tfix = _assemble(lay, N, P, m, depth)
    F = _F(lay, lre, lim)
    if m == 1:  # nothing to choose: the eigenvectors (and chains) are unique up to scale
        x = _normalise(jnp.asarray(_init(n, m, 1)[0], A.dtype), lay, m)
        it, gn = jnp.asarray(0), jnp.asarray(0.0, A.dtype)
    else:
        x0s = jax.vmap(lambda x: _normalise(x, lay, m))(jnp.asarray(_init(n, m), A.dtype))
        xs, its, gns = jax.vmap(lambda x0: _newton(x0, K, Tfix, lay, m, maxiter))(x0s)
        Ls = jax.vmap(lambda x: _gain(A, C, _T(x, K, Tfix), F))(xs)
        phis = jax.vmap(lambda x: _phi(x, K, Tfix, lay))(after(Ls, xs))
        score = phis + jnp.log(jnp.linalg.norm(Ls, axis=(1, 2)))
        score = jnp.where(jnp.isfinite(score), score, jnp.inf)
        # a start still running at maxiter is used only if all are; one whose gain broke down (not
        # finite: a NaN gradient also stops its loop early) never counts as converged, so that it cannot
        # shut out the finite starts
        converged = (its < maxiter) & jnp.isfinite(score)
        k = jnp.argmin(jnp.where(converged | ~jnp.any(converged), score, jnp.inf))
        x, it, gn = xs[k], its[k], gns[k]
    T = _T(x, K, Tfix)
    L = _gain(A, C, T, F)
    info = {"iterations": it, "gradient": gn, "pivot": jnp.min(piv), "F": F}
    return L, T, x, N, (a, c), info


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def robust_gain(m, depth, maxiter, lay, A, C, pr, pi):
    """(L, T, F): the gain, its eigenvector matrix T and F, with T (A − LC) = F T."""
    L, T, _, _, _, info = forward(lay, A, C, pr, pi, m=m, depth=depth, maxiter=maxiter)
    return L, T, info["F"]


@robust_gain.defjvp
def _robust_gain_jvp(m, depth, maxiter, primals, tangents):
    lay, A, C, pr, pi = primals
    _, dA, dC, dpr, dpi = tangents
    _, _, xs, N0, (a, c), _ = forward(lay, A, C, pr, pi, m=m, depth=depth, maxiter=maxiter)
    xs, N0 = jax.lax.stop_gradient(xs), jax.lax.stop_gradient(N0)

    def local(A, C, pr, pi):
        lre, lim = _lams(lay, pr, pi)
        N, P = jax.vmap(_bases_projected, in_axes=(None, None, 0, None, None, 0))(
            A, C, lre + 1j * lim, a, c, N0
        )
        K, Tfix = _assemble(lay, N, P, m, depth)
        return K, Tfix, _F(lay, lre, lim)

    theta, dtheta = (A, C, pr, pi), (dA, dC, dpr, dpi)
    if m > 1:
        fixed = jnp.repeat((lay.fixed >= 0).astype(xs.dtype), m)

        def grad_x(A, C, pr, pi):
            K, Tfix, _ = local(A, C, pr, pi)
            return _grad(xs, K, Tfix, lay) * (1.0 - fixed)

        _, b = jax.jvp(grad_x, theta, dtheta)
        K0, Tf0, _ = local(*theta)
        H = _hess(xs, K0, Tf0, lay)
        w, V = jnp.linalg.eigh(H + jnp.diag(fixed) * jnp.max(jnp.abs(jnp.diagonal(H))))
        keep = (jnp.arange(w.shape[0]) >= lay.nnull) & (jnp.abs(w) > 1e-11 * jnp.max(jnp.abs(w)))
        dx = -V @ jnp.where(keep, (V.T @ b) / jnp.where(keep, w, 1.0), 0.0)
        # A minimiser that is not isolated (more flat directions than the symmetries of φ: whole
        # families of equally good eigenvector matrices, e.g. m > (n+1)/2 for distinct real poles)
        # has no derivative: which member the Newton runs return depends on rounding, and the implicit
        # derivative follows none of them.  Where a derivative is asked for, refuse it.
        flat = jnp.sum(jnp.abs(w) <= _FLAT * jnp.max(jnp.abs(w)))
        not_isolated = flat > lay.nnull
    else:
        dx = jnp.zeros_like(xs)
        not_isolated = jnp.asarray(False)

    def gain(x, A, C, pr, pi):
        K, Tfix, F = local(A, C, pr, pi)
        T = _T(x, K, Tfix)
        return _gain(A, C, T, F), T, F

    (L, T, F), tangents = jax.jvp(gain, (xs, *theta), (dx, *dtheta))
    # checked on a primal factor of the tangents: in reverse mode under jit the primal output is not
    # computed when only the gradient is returned, but a factor of the tangents is
    one = eqx.error_if(
        jnp.ones((), L.dtype),
        not_isolated,
        "place (method='robust'): the gain is not differentiable here. The best-conditioned "
        "eigenvector matrices form a family (the Tits-Yang minimiser is not isolated; typical when "
        "the number of outputs m exceeds (n+1)/2), the gain returned is one member of it, and it "
        "does not move smoothly with A, C or the poles. Use method='canonical' to differentiate "
        "the placement, or keep the gain fixed.",
    )
    return (L, T, F), jax.tree_util.tree_map(lambda t: t * one, tangents)
