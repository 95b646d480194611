"""A hand-written Dormand–Prince 5(4) for Chen & Yen's plant and least-squares observer, in numba.

The comparison point of ``g_numba_dopri5.py``: what a user writes without obsjax, one trajectory at
a time, one thread.  The right-hand side is written out here from the paper's equations (Chen & Yen,
IEEE TAC 44(9), 1999, (1), (8), (11), (13) and the information form of (15)), not taken from obsjax:

    ẋ = A(t) x,        y = C(t) x,
    dx̂/dt = A x̂ + Φ Q⁻¹ w (y − C x̂),   w = Φᵀ Cᵀ,
    dΦ/dt = A Φ,       dQ/dt = w wᵀ,      (Q = P⁻¹/γ, the information matrix)

with A(t) = [[−1 + 1.5 cos²t, 1 − 1.5 sin t cos t], [−1 + 1.5 sin t cos t, −1 + 1.5 sin²t]] and
C(t) = [cos √t + sin √t, 3 cos² √t], and at every t = kT the reset Φ = I, Q = I/(γ p0).

The integrator: the Dormand–Prince pair with Shampine's embedded fourth-order weights (the pair
diffrax's ``Dopri5`` uses), first same as last; error norm RMS of err/(atol + rtol·max(|y0|, |y1|))
over the 12 states; integral control h ← h·clip(0.9·err^(−1/5), 0.2, 10) (no growth after a
rejection, at most 0.9×); each reset segment is a fresh solve whose first step is Hairer & Wanner's
starting step (Solving ODEs I, II.4) or a given dt0; a step within 100 ULP of the segment's end is
rounded onto it.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# Dormand & Prince (1980) nodes and coupling coefficients.
C2, C3, C4, C5 = 1 / 5, 3 / 10, 4 / 5, 8 / 9
A21 = 1 / 5
A31, A32 = 3 / 40, 9 / 40
A41, A42, A43 = 44 / 45, -56 / 15, 32 / 9
A51, A52, A53, A54 = 19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729
A61, A62, A63, A64, A65 = 9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656
B1, B3, B4, B5, B6 = 35 / 384, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84
# fifth minus (Shampine's) fourth order weights
E1 = 35 / 384 - 1951 / 21600
E3 = 500 / 1113 - 22642 / 50085
E4 = 125 / 192 - 451 / 720
E5 = -2187 / 6784 + 12231 / 42400
E6 = 11 / 84 - 649 / 6300
E7 = -1 / 60
N = 12  # x (2), x̂ (2), Φ (4, row-major), Q (4, row-major)


@numba.njit(cache=False, fastmath=False)
def rhs(t, s, out):
    c, sn = math.cos(t), math.sin(t)
    a11, a12 = -1.0 + 1.5 * c * c, 1.0 - 1.5 * sn * c
    a21, a22 = -1.0 + 1.5 * sn * c, -1.0 + 1.5 * sn * sn
    r = math.sqrt(t) if t > 0.0 else 0.0
    cr = math.cos(r)
    c1, c2 = cr + math.sin(r), 3.0 * cr * cr
    x1, x2, h1, h2 = s[0], s[1], s[2], s[3]
    p11, p12, p21, p22 = s[4], s[5], s[6], s[7]
    q11, q12, q21, q22 = s[8], s[9], s[10], s[11]
    w1 = p11 * c1 + p21 * c2  # w = Φᵀ Cᵀ
    w2 = p12 * c1 + p22 * c2
    qs = 0.5 * (q12 + q21)  # Q⁻¹ w by Cramer's rule on the symmetric part
    det = q11 * q22 - qs * qs
    v1 = (q22 * w1 - qs * w2) / det
    v2 = (q11 * w2 - qs * w1) / det
    l1 = p11 * v1 + p12 * v2  # L = Φ Q⁻¹ w
    l2 = p21 * v1 + p22 * v2
    innov = c1 * (x1 - h1) + c2 * (x2 - h2)
    out[0] = a11 * x1 + a12 * x2
    out[1] = a21 * x1 + a22 * x2
    out[2] = a11 * h1 + a12 * h2 + l1 * innov
    out[3] = a21 * h1 + a22 * h2 + l2 * innov
    out[4] = a11 * p11 + a12 * p21
    out[5] = a11 * p12 + a12 * p22
    out[6] = a21 * p11 + a22 * p21
    out[7] = a21 * p12 + a22 * p22
    out[8] = w1 * w1
    out[9] = w1 * w2
    out[10] = w2 * w1
    out[11] = w2 * w2


@numba.njit(cache=False)
def _rms_scaled(v, y0, y1, rtol, atol):
    acc = 0.0
    for i in range(N):
        sc = atol + rtol * max(abs(y0[i]), abs(y1[i]))
        acc += (v[i] / sc) ** 2
    return math.sqrt(acc / N)


@numba.njit(cache=False)
def _start_step(t, y, f0, rtol, atol, tmp, f1):
    """Hairer & Wanner's starting step for an order-5 pair (two evaluations of f, the first
    given)."""
    d0 = 0.0
    d1 = 0.0
    for i in range(N):
        sc = atol + abs(y[i]) * rtol
        d0 += (y[i] / sc) ** 2
        d1 += (f0[i] / sc) ** 2
    d0 = math.sqrt(d0 / N)
    d1 = math.sqrt(d1 / N)
    h0 = 1e-6 if (d0 < 1e-5 or d1 < 1e-5) else 0.01 * d0 / d1
    for i in range(N):
        tmp[i] = y[i] + h0 * f0[i]
    rhs(t + h0, tmp, f1)
    d2 = 0.0
    for i in range(N):
        sc = atol + abs(y[i]) * rtol
        d2 += ((f1[i] - f0[i]) / sc) ** 2
    d2 = math.sqrt(d2 / N) / h0
    md = max(d1, d2)
    h1 = max(1e-6, h0 * 1e-3) if md <= 1e-15 else (0.01 / md) ** (1.0 / 5.0)
    return min(100.0 * h0, h1)


@numba.njit(cache=False)
def _segment(t0, t1, floor1, y, rtol, atol, dt0, max_steps, work):
    """Integrate y in place from t0 to t1; returns (accepted, rejected, ok)."""
    k1, k2, k3, k4, k5, k6, k7 = work[0], work[1], work[2], work[3], work[4], work[5], work[6]
    ys, y1, err = work[7], work[8], work[9]
    rhs(t0, y, k1)
    h = _start_step(t0, y, k1, rtol, atol, ys, k2) if dt0 <= 0.0 else dt0
    t = t0
    tn = min(t0 + h, t1)
    acc = 0
    rej = 0
    while t < t1:
        if acc + rej >= max_steps:
            return acc, rej, False
        h = tn - t
        for i in range(N):
            ys[i] = y[i] + h * A21 * k1[i]
        rhs(t + C2 * h, ys, k2)
        for i in range(N):
            ys[i] = y[i] + h * (A31 * k1[i] + A32 * k2[i])
        rhs(t + C3 * h, ys, k3)
        for i in range(N):
            ys[i] = y[i] + h * (A41 * k1[i] + A42 * k2[i] + A43 * k3[i])
        rhs(t + C4 * h, ys, k4)
        for i in range(N):
            ys[i] = y[i] + h * (A51 * k1[i] + A52 * k2[i] + A53 * k3[i] + A54 * k4[i])
        rhs(t + C5 * h, ys, k5)
        for i in range(N):
            ys[i] = y[i] + h * (A61 * k1[i] + A62 * k2[i] + A63 * k3[i] + A64 * k4[i] + A65 * k5[i])
        rhs(tn, ys, k6)
        for i in range(N):
            y1[i] = y[i] + h * (B1 * k1[i] + B3 * k3[i] + B4 * k4[i] + B5 * k5[i] + B6 * k6[i])
        rhs(tn, y1, k7)
        for i in range(N):
            err[i] = h * (
                E1 * k1[i] + E3 * k3[i] + E4 * k4[i] + E5 * k5[i] + E6 * k6[i] + E7 * k7[i]
            )
        en = _rms_scaled(err, y, y1, rtol, atol)
        if math.isnan(en):  # NaN error: reject
            en = math.inf
        keep = en < 1.0
        fac = 0.9 * en ** (-0.2) if en > 0.0 else math.inf
        if keep:
            fac = min(max(fac, 1.0), 10.0)
            acc += 1
            t = tn
            for i in range(N):
                y[i] = y1[i]
                k1[i] = k7[i]
        else:
            fac = min(max(fac, 0.2), 0.9)
            rej += 1
        tn = t + h * fac
        if tn > floor1:
            tn = t1 if keep else t + 0.5 * (t1 - t)
        if tn <= t < t1:
            return acc, rej, False
    return acc, rej, True


@numba.njit(cache=False)
def _reset(y, q0):
    y[4], y[5], y[6], y[7] = 1.0, 0.0, 0.0, 1.0
    y[8], y[9], y[10], y[11] = q0, 0.0, 0.0, q0


@numba.njit(cache=False)
def solve_batch(x0s, xh0s, ends, floors, gamma_p0, rtol, atol, dt0, max_steps):
    """Every trajectory from t = 0 through the reset instants ``ends`` (the last is the horizon).

    Returns ‖x̂ − x‖ at 0 and at every end (B, len(ends) + 1), accepted and rejected steps (B,), ok
    (B,).
    """
    B = x0s.shape[0]
    nseg = ends.shape[0]
    out = np.empty((B, nseg + 1))
    acc = np.zeros(B, np.int64)
    rej = np.zeros(B, np.int64)
    ok = np.ones(B, np.bool_)
    y = np.empty(N)
    work = np.empty((10, N))
    q0 = 1.0 / gamma_p0
    for b in range(B):
        y[0], y[1], y[2], y[3] = x0s[b, 0], x0s[b, 1], xh0s[b, 0], xh0s[b, 1]
        _reset(y, q0)
        out[b, 0] = math.hypot(y[2] - y[0], y[3] - y[1])
        t = 0.0
        for k in range(nseg):
            if k > 0:
                _reset(y, q0)
            a, r, good = _segment(t, ends[k], floors[k], y, rtol, atol, dt0, max_steps, work)
            acc[b] += a
            rej[b] += r
            if not good:
                ok[b] = False
                break
            t = ends[k]
            out[b, k + 1] = math.hypot(y[2] - y[0], y[3] - y[1])
        if not ok[b]:
            out[b, :] = np.nan
    return out, acc, rej, ok


def segment_ends(T, t1):
    """The reset instants kT up to t1 (the last one t1) and the floats 100 ULP below each."""
    n = math.ceil(t1 / T - 1e-9)
    ends = np.minimum(T * np.arange(1, n + 1), t1)
    ends[-1] = t1
    floors = ends.copy()
    for _ in range(100):
        floors = np.nextafter(floors, -np.inf)
    return ends, floors


@numba.njit(cache=False)
def rhs_repeat(n, s, out):
    """Evaluate :func:`rhs` `n` times at times 0.1, 0.1 + 1e-5, … feeding a little of each result back
    into the state (so that no evaluation can be skipped): the vector field's own cost, for benchmark
    (g)'s breakdown."""
    t = 0.1
    acc = 0.0
    for _ in range(n):
        rhs(t, s, out)
        for j in range(N):
            s[j] += 1e-9 * out[j]
        acc += out[0]
        t += 1e-5
    return acc


def start_state_for_breakdown():
    """x = (0.3, -0.2), x̂ = (5, -5), Φ = I, Q = I / (γ p0) with γ p0 = 2: a state of the example."""
    return [0.3, -0.2, 5.0, -5.0, 1.0, 0.0, 0.0, 1.0, 0.5, 0.0, 0.0, 0.5]
