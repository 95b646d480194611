"""Byrski & Fuksa ("Optimal finite parameter observer", 1982): the figures of the paper's example and of its Section 4, reproduced.

- ``byrski_fuksa_norm31.png``: the norm (31) of the optimal observer of the double integrator (29) against
  the window length T (obsjax's matrix-exponential norm (15) by (28) and by (25)-(26), the closed form (31),
  an independent discretisation's values and the limit √1.5).
- ``byrski_fuksa_kernels30.png``: the optimal kernels G1, G2 at T = 1 against the closed form (30).
- ``byrski_fuksa_deadbeat.png``: the closed loop (33)-(35) with u = P x̂, eig(A + BP) = {−1, −2}: the state,
  the estimate, the state-feedback trajectory of (42) from x(T) (Lemma 4), and the decay of ‖x‖ against
  e^{max Re eig(A+BP) t}.
- ``byrski_fuksa_delay_loop.png``: the closed loop (33)-(37) simulated directly as a delay equation (method
  of steps) against the sample-and-propagate observer in ``obsjax.simulate`` for 5 to 80 window pieces.
- ``byrski_fuksa_ltv.png``: Theorem 1 for an LTV plant of our own: the optimal kernels (β = 0: the window
  gramian's; β = 30), and the identification of a constant force θ (a second use of Theorem 1) on sliding
  windows of noisy data.
"""

from __future__ import annotations

import os

import numpy as np


def _model29():
    import obsjax

    return obsjax.LTI([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[2.0, 0.0]])


def norm31(T):
    """(31): ‖(G1, G2)‖(T) = √((3 sh 2T + sin 2T) / (4 (sh²T − sin²T)))."""
    T = np.asarray(T, dtype=float)
    return np.sqrt((3 * np.sinh(2 * T) + np.sin(2 * T)) / (4 * (np.sinh(T) ** 2 - np.sin(T) ** 2)))


def kernels30(t, T):
    """(30): the optimal kernels of (29) at α = β = I, as arrays (len(t), 2)."""
    sh, ch, s, c = np.sinh, np.cosh, np.sin, np.cos
    R = np.array(
        [
            [sh(T) * c(T) - ch(T) * s(T), 2 * sh(T) * s(T)],
            [-2 * sh(T) * s(T), 2 * (sh(T) * c(T) + ch(T) * s(T))],
        ]
    ) / (2 * (sh(T) ** 2 - s(T) ** 2))
    g1 = (R @ np.array([2 * ch(t) * c(t), sh(t) * c(t) + ch(t) * s(t)])).T
    g2 = (R @ np.array([-2 * sh(t) * s(t), sh(t) * c(t) - ch(t) * s(t)])).T
    return g1, g2


def norm_curve(Ts, formula="(28)"):
    """obsjax's norm (15) of (29) at each T (one compiled function, T a traced leaf)."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import obsjax

    kw = {} if formula == "(28)" else {"alpha": [1.0, 1.0], "beta": [1.0, 1.0]}
    obs = obsjax.FiniteWindow(_model29(), 1.0, **kw)
    f = jax.jit(jax.vmap(lambda T: eqx.tree_at(lambda o: o.T, obs, T).norm()))
    return np.asarray(f(jnp.asarray(Ts, dtype=float)))


def deadbeat_loop(T=1.0, n_chunks=10, t1=8.0, P=((-2.0, -3.0),), x0=(1.0, -0.5), xhat0=(0.3, 0.2)):
    """Simulate the closed loop (33)-(35) of (29) with u = P x̂; returns (ts, x, xhat, x42) with x42 the
    state-feedback trajectory of (42) started from x(T) (NaN before T)."""
    import jax.numpy as jnp
    import scipy.linalg as sl

    import obsjax

    model = _model29()
    P = np.asarray(P, dtype=float)
    obs = obsjax.FiniteWindow(model, T, n_chunks=n_chunks)
    ts = np.linspace(0.0, t1, round(t1 / T * n_chunks) * 2 + 1)
    tr = obsjax.simulate(
        model,
        obs,
        jnp.asarray(x0),
        jnp.asarray(xhat0),
        ts,
        controller=lambda t, xh: jnp.asarray(P) @ xh,
        rtol=1e-10,
        atol=1e-12,
    )
    x, xh = np.asarray(tr.x), np.asarray(tr.xhat)
    Acl = np.asarray(model.A) + np.asarray(model.B) @ P
    iT = int(np.argmin(np.abs(ts - T)))
    x42 = np.full_like(x, np.nan)
    x42[iT:] = np.stack([sl.expm(Acl * (t - ts[iT])) @ x[iT] for t in ts[iT:]])
    return ts, x, xh, x42, Acl


def delay_loop_study(chunks=(5, 10, 20, 40, 80), T=1.0, t1=4.0, P=((-2.0, -3.0),), x0=(1.0, -0.5),
                     xhat0=(0.3, 0.2), steps_per_window=400):
    """(33)-(37) of (29) simulated directly (:func:`obsjax.delay_closed_loop`) and by the sample-and-propagate
    observer with n_chunks pieces.  Returns (delay loop, {n_chunks: (ts, x)}, {n_chunks: max |x − x_delay|})."""
    import jax.numpy as jnp

    import obsjax

    model = _model29()
    P = jnp.asarray(P, dtype=float)
    ref = obsjax.delay_closed_loop(obsjax.FiniteWindow(model, T), P, jnp.asarray(x0), jnp.asarray(xhat0), t1,
                                   steps_per_window=steps_per_window)
    step = steps_per_window // 20
    ts = np.asarray(ref.ts)[::step]
    xr = np.asarray(ref.x)[::step]
    runs, dev = {}, {}
    for nc in chunks:
        obs = obsjax.FiniteWindow(model, T, n_chunks=nc)
        x = np.asarray(obsjax.simulate(model, obs, jnp.asarray(x0), jnp.asarray(xhat0), jnp.asarray(ts),
                                       controller=lambda t, xh: P @ xh, rtol=1e-10, atol=1e-12).x)
        runs[nc] = (ts, x)
        dev[nc] = float(np.abs(x - xr).max())
    return ref, runs, dev


def ltv_plant():
    """A time-varying plant of our own (3 states, 1 output, 1 input) and its input."""
    import jax.numpy as jnp

    import obsjax

    A = lambda t: jnp.array(
        [[0.0, 1.0, 0.0], [-1.0 - 0.5 * jnp.sin(t), -0.2, 0.5], [0.3 * jnp.cos(t), 0.0, -0.4]]
    )
    B = lambda t: jnp.array([[0.0], [1.0 + 0.3 * jnp.cos(2.0 * t)], [0.2]])
    C = lambda t: jnp.array([[1.0, 0.1 * jnp.cos(t), 0.0]])
    u = lambda t: jnp.array([jnp.sin(3.0 * t) + 0.5])
    return obsjax.LTV(A, C, B), A, B, C, u


def ltv_study(theta=0.7, sigma=0.01, window=4.0, t_end=12.0, samples=201, seed=0):
    """Kernels on [0.5, 2.5] (β = 0 and β = 30), and θ̂ (with x̂) on sliding windows [t − window, t] of data
    from ẋ = A x + B u + E θ, y = C x + noise (σ)."""
    import diffrax
    import jax
    import jax.numpy as jnp

    import obsjax

    plant, A, B, C, u = ltv_plant()
    s = jnp.linspace(0.5, 2.5, 201)
    kern = {}
    for label, beta in (("β = 0 (gramian kernel)", [0.0, 0.0, 0.0]), ("β = 30", [30.0, 30.0, 30.0])):
        G1, G2 = obsjax.FiniteWindowLTV(plant, 0.5, 2.5, beta=beta).kernels(s)
        kern[label] = (np.asarray(G1)[:, :, 0], np.asarray(G2)[:, :, 0])
    E = jnp.array([0.0, 1.0, 0.0])
    x0 = jnp.array([1.0, -0.5, 0.8])
    tt = jnp.linspace(0.0, t_end, round(t_end / window * (samples - 1)) + 1)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, x, a: A(t) @ x + B(t) @ u(t) + theta * E), diffrax.Dopri8(), 0.0, t_end,
        None, x0, saveat=diffrax.SaveAt(ts=tt), stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-13),
    )
    ys = jax.vmap(lambda t, x: C(t) @ x)(tt, sol.ys)
    ys_noisy = ys + sigma * jax.random.normal(jax.random.PRNGKey(seed), ys.shape)
    us = jax.vmap(u)(tt)
    fw = obsjax.FiniteWindowLTV(plant, 0.0, window, E=lambda t: E[:, None])
    step = samples - 1

    @jax.jit
    def est(k0, yw, uw):
        t0 = tt[k0]
        f = eqx_tree_at(fw, t0, t0 + window)
        return f.estimate_window(jax.lax.dynamic_slice_in_dim(tt, k0, samples), yw, uw, rule="simpson")

    starts = np.arange(0, len(tt) - step, step // 10)
    rows = {"t": [], "theta": [], "theta_noisy": [], "x_err": [], "x_err_noisy": []}
    for k0 in starts:
        sl_ = slice(int(k0), int(k0) + samples)
        e_clean = est(int(k0), ys[sl_], us[sl_])
        e_noisy = est(int(k0), ys_noisy[sl_], us[sl_])
        xT = np.asarray(sol.ys[int(k0) + step])
        rows["t"].append(float(tt[int(k0) + step]))
        rows["theta"].append(float(e_clean[3]))
        rows["theta_noisy"].append(float(e_noisy[3]))
        rows["x_err"].append(float(np.linalg.norm(np.asarray(e_clean[:3]) - xT)))
        rows["x_err_noisy"].append(float(np.linalg.norm(np.asarray(e_noisy[:3]) - xT)))
    return np.asarray(s), kern, {k: np.asarray(v) for k, v in rows.items()}, theta, sigma


def eqx_tree_at(fw, t0, t1):
    import equinox as eqx

    return eqx.tree_at(lambda o: (o.t0, o.t1), fw, (t0, t1))


def _extension_figures(outdir):
    import matplotlib.pyplot as plt

    paths = []
    ref, runs, dev = delay_loop_study()
    fig, axs = plt.subplots(1, 2, figsize=(11, 3.8))
    tr, xr = np.asarray(ref.ts), np.asarray(ref.x)
    axs[0].plot(tr, xr[:, 1], "k-", lw=3, alpha=0.35, label="delay equation (37), method of steps")
    for i, nc in enumerate(runs):
        ts, x = runs[nc]
        axs[0].plot(ts, x[:, 1], f"C{i}--", lw=1, label=f"sample-and-propagate, {nc} pieces")
    axs[0].axvline(1.0, color="gray", lw=0.8, label="t = T: first full window")
    axs[0].set_xlabel("time t (s)")
    axs[0].set_ylabel("state $x_2$")
    axs[0].set_title(r"closed loop (33)-(37) of (29), $u = P\hat x$, $\hat x_0 \neq x_0$")
    axs[0].legend(fontsize=7)
    ncs = np.array(list(dev))
    axs[1].loglog(ncs, [dev[k] for k in ncs], "o-", label="max |x − x_delay| on [0, 4]")
    axs[1].loglog(ncs, dev[ncs[0]] * ncs[0] / ncs, "k--", lw=0.8, label="∝ 1/n_chunks")
    axs[1].set_xticks(ncs)
    axs[1].set_xticks([], minor=True)
    axs[1].set_xticklabels([str(k) for k in ncs])
    axs[1].set_xlabel("window pieces n_chunks")
    axs[1].set_ylabel("max deviation from (37)")
    axs[1].set_title("sample-and-propagate → the delay equation")
    axs[1].grid(True, which="both", alpha=0.3)
    axs[1].legend(fontsize=8)
    fig.tight_layout()
    p = os.path.join(outdir, "byrski_fuksa_delay_loop.png")
    fig.savefig(p, dpi=120)
    plt.close(fig)
    paths.append(p)

    s, kern, rows, theta, sigma = ltv_study()
    fig, axs = plt.subplots(1, 3, figsize=(15, 3.8))
    for j, (label, (G1, G2)) in enumerate(kern.items()):
        for i in range(3):
            axs[0].plot(s, G1[:, i], f"C{i}" + ("-" if j else ":"), label=f"row {i + 1}, {label}")
            axs[1].plot(s, G2[:, i], f"C{i}" + ("-" if j else ":"), label=f"row {i + 1}, {label}")
    axs[0].set_title("$G_1(t)$ on [0.5, 2.5] (LTV plant), dotted: β = 0")
    axs[1].set_title("$G_2(t)$")
    for a in axs[:2]:
        a.set_xlabel("time t in the window [0.5, 2.5] (s)")
        a.set_ylabel("kernel entries")
        a.legend(fontsize=6, ncol=2)
    axs[2].plot(rows["t"], rows["theta_noisy"], "C0o-", ms=3, label=f"θ̂, noise σ = {sigma}")
    axs[2].plot(rows["t"], rows["theta"], "C1.", label="θ̂, noise-free")
    axs[2].axhline(theta, color="k", lw=0.8, label="θ")
    axs[2].set_xlabel("end of the window t (s) (window length 4 s)")
    axs[2].set_ylabel("force estimate θ̂")
    axs[2].set_title("constant force θ identified on sliding windows")
    axs[2].legend(fontsize=8)
    fig.tight_layout()
    p = os.path.join(outdir, "byrski_fuksa_ltv.png")
    fig.savefig(p, dpi=120)
    plt.close(fig)
    paths.append(p)
    return paths


def reproduce(outdir: str) -> list[str]:
    """Write the three figures to ``outdir`` and return their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import obsjax  # noqa: F401  (float64)

    os.makedirs(outdir, exist_ok=True)
    paths = []

    # 1. the norm (31)
    Ts = np.linspace(0.3, 6.0, 58)
    n28, n25 = norm_curve(Ts, "(28)"), norm_curve(Ts, "(25)")
    from .references import BYRSKI_FUKSA_NORM31 as ref

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.semilogy(Ts, norm31(Ts), "k-", lw=3, alpha=0.3, label="closed form (31)")
    ax.semilogy(Ts, n28, "C0-", label="obsjax, (28) (matrix exponentials)")
    ax.semilogy(Ts[::4], n25[::4], "C1o", ms=4, label="obsjax, (25)-(26)")
    ax.semilogy(list(ref), list(ref.values()), "C3s", mfc="none", ms=8, label="independent discretisation")
    ax.axhline(np.sqrt(1.5), color="gray", ls="--", label=r"limit $\sqrt{1.5}$")
    ax.set_xlabel("window length T (s)")
    ax.set_ylabel(r"$\|(G_1, G_2)\|(T)$")
    ax.set_yticks([2, 3, 5, 10])
    ax.yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_title("Byrski & Fuksa (29): norm of the optimal observer (31)")
    ax.legend()
    fig.tight_layout()
    p = os.path.join(outdir, "byrski_fuksa_norm31.png")
    fig.savefig(p, dpi=120)
    plt.close(fig)
    paths.append(p)

    # 2. the kernels (30)
    import obsjax as oj

    T = 1.0
    t = np.linspace(0.0, T, 101)
    G1, G2 = oj.FiniteWindow(_model29(), T).kernels(t)
    g1, g2 = kernels30(t, T)
    fig, axs = plt.subplots(1, 2, figsize=(9, 3.6), sharex=True)
    for i in range(2):
        axs[0].plot(t, g1[:, i], "k-", lw=3, alpha=0.3)
        axs[0].plot(t, np.asarray(G1)[:, i, 0], f"C{i}--", label=f"row {i + 1}")
        axs[1].plot(t, g2[:, i], "k-", lw=3, alpha=0.3)
        axs[1].plot(t, np.asarray(G2)[:, i, 0], f"C{i}--", label=f"row {i + 1}")
    axs[0].set_title(r"$G_1(s)$ (grey: closed form (30))")
    axs[1].set_title(r"$G_2(s)$ (grey: closed form (30))")
    for a in axs:
        a.set_xlabel("time s in the window [0, T] (s), T = 1 s")
        a.set_ylabel("kernel entries")
        a.legend()
    fig.tight_layout()
    p = os.path.join(outdir, "byrski_fuksa_kernels30.png")
    fig.savefig(p, dpi=120)
    plt.close(fig)
    paths.append(p)

    # 3. the deadbeat closed loop (33)-(42)
    ts, x, xh, x42, Acl = deadbeat_loop()
    rate = np.max(np.linalg.eigvals(Acl).real)
    fig, axs = plt.subplots(1, 2, figsize=(10, 3.8))
    for i in range(2):
        axs[0].plot(ts, x[:, i], f"C{i}-", label=f"$x_{i + 1}$")
        axs[0].plot(ts, xh[:, i], f"C{i}:", label=rf"$\hat x_{i + 1}$")
        axs[0].plot(ts, x42[:, i], "k--", lw=1, label="(42) from x(T)" if i == 0 else None)
    axs[0].axvline(1.0, color="gray", lw=0.8, label="t = T: first full window")
    axs[0].set_xlabel("time t (s)")
    axs[0].set_ylabel("state and estimate")
    axs[0].set_title(r"closed loop (33)-(35), $u = P\hat x$, T = 1")
    axs[0].legend(ncol=2, fontsize=8)
    nx = np.linalg.norm(x, axis=1)
    axs[1].semilogy(ts, nx, "C0-", label=r"$\|x(t)\|$")
    axs[1].semilogy(
        ts, np.maximum(np.linalg.norm(xh - x, axis=1), 1e-16), "C3-", label=r"$\|\hat x - x\|$"
    )
    iT = int(np.argmin(np.abs(ts - 1.0)))
    axs[1].semilogy(
        ts[iT:],
        nx[-1] * np.exp(rate * (ts[iT:] - ts[-1])),
        "k--",
        lw=1,
        label=rf"slope {rate:.0f} = max Re eig$(A + BP)$ (1/s)",
    )
    axs[1].axvline(1.0, color="gray", lw=0.8, label="t = T: first full window")
    axs[1].set_xlabel("time t (s)")
    axs[1].set_ylabel("norm")
    axs[1].set_title("deadbeat after T (Lemma 4)")
    axs[1].legend(fontsize=8)
    fig.tight_layout()
    p = os.path.join(outdir, "byrski_fuksa_deadbeat.png")
    fig.savefig(p, dpi=120)
    plt.close(fig)
    paths.append(p)
    paths.extend(_extension_figures(outdir))
    return paths


def paper_values():
    """The paper's closed forms for the double integrator (29): norm (31) and its limit √1.5, the kernels
    (30), and the closed loop (33)-(42) (exact estimate after T, eig(A + BP) = {−1, −2})."""
    import obsjax

    from ._report import Row
    from .references import BYRSKI_FUKSA_NORM31, BYRSKI_FUKSA_NORM31_LIMIT

    Ts = np.array(list(BYRSKI_FUKSA_NORM31))
    got = norm_curve(Ts, "(28)")
    rows = [
        Row(f"norm (31), T = {T:g}", float(norm31(T)), float(g), "closed form (31)")
        for T, g in zip(Ts, got)
    ]
    rows += [
        Row(f"norm (31), T = {T:g}", ref, float(g), "discretisation (600 points)", rtol=1e-4)
        for (T, ref), g in zip(BYRSKI_FUKSA_NORM31.items(), got)
    ]
    rows.append(
        Row(
            "norm (31), T = 12 → √1.5",
            BYRSKI_FUKSA_NORM31_LIMIT,
            float(norm_curve(np.array([12.0]), "(28)")[0]),
            "limit below (31)",
            rtol=1e-5,
        )
    )
    t = np.array([0.5])
    G1, G2 = obsjax.FiniteWindow(_model29(), 1.0).kernels(t)
    g1, g2 = kernels30(t, 1.0)
    for name, G, g in (("G1", G1, g1), ("G2", G2, g2)):
        rows += [
            Row(
                f"kernel (30) {name}(0.5)[{i + 1}], T = 1",
                float(g[0, i]),
                float(np.asarray(G)[0, i, 0]),
                "closed form (30)",
            )
            for i in range(2)
        ]
    ts, x, xh, _, _ = deadbeat_loop()
    after = ts >= 1.0 + 1e-9
    rows.append(
        Row(
            "(33)-(35): max ‖x̂ − x‖ for t > T = 1 (Lemma 4)",
            0.0,
            float(np.max(np.linalg.norm(xh[after] - x[after], axis=1))),
            "Lemma 4",
            rtol=0.0,
            atol=1e-7,
        )
    )
    # The closed loop's eigenvalues identified from the simulated x1(t), t ≥ T, alone: a sampled solution
    # of a 2nd-order linear ODE obeys x1[k+2] = c1 x1[k+1] + c0 x1[k] with roots z = exp(λ h) (Prony).
    h = ts[1] - ts[0]
    x1 = x[after, 0]
    c = np.linalg.lstsq(np.stack([x1[1:-1], x1[:-2]], 1), x1[2:], rcond=None)[0]
    lam = np.sort(np.log(np.roots([1.0, -c[0], -c[1]]).astype(complex)).real / h)
    rows += [
        Row(
            f"(42): eigenvalue {i + 1} of the closed loop, from x1(t), t > T",
            v,
            float(lam[::-1][i]),
            "text: eig(A + BP) = {−1, −2}",
            rtol=1e-4,
        )
        for i, v in enumerate((-1.0, -2.0))
    ]
    return rows
