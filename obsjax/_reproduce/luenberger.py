"""Hassan thesis, chapters 2-3: the Luenberger family on example (2.8) and the closed-loop eigenvalues.

- Example (2.8): A = [[-2, 1], [0, -1]], B = [0, 1]ᵀ, C = [1, 0], identity observer with both poles at -3,
  G = [3, 4]ᵀ and A - GC = [[-5, 1], [-4, -1]]; the simulated error x̂ - x against exp((A - GC) t) x̃(0).
- Reduced-order observer (2.13)-(2.16) for the same plant, pole -3: G = 2 (A22 - G A12 = -1 - G).
- Section 2.5: with u = K x̂ the composite system (2.22) has the eigenvalues of A + BK and of F
  (Theorem 4); the eigenvalues of the simulated closed loop's matrix and the trajectories with the
  true-state and observer-based feedback.
- Section 3.2 (Theorem 1, Figs. 3.1-3.4): a fourth-order plant of two second-order subsystems coupled
  only through the measured x1 and x3.  Subsystem 1 is (3.2); Fig. 3.1's second block is not legible in
  the text, so subsystem 2 is chosen (ẋ3 = −x3 + x4, ẋ4 = −x1 + u) such that the thesis's own second
  observer, ẇ = −3w + x3 − (u − x1)/6 with x̂4 = 3x3 − 6w, is exact for it.  The observer of (3.5)-(3.7)
  (ż = −3z + x1 − x3, x̂2 = x1 − z) is integrated as printed with SciPy and compared with obsjax's
  reduced-order observer with poles {−3, −3} (G = [[1, 0], [0, 3]]); the multi-output canonical form
  (3.1c) gives the indices (2, 2).

``reproduce(outdir)`` writes the PNGs and returns their paths.
"""

from __future__ import annotations

import os

import numpy as np

A = np.array([[-2.0, 1.0], [0.0, -1.0]])
B = np.array([[0.0], [1.0]])
C = np.array([[1.0, 0.0]])
#: state feedback of the closed-loop example: eig(A + BK) = {-1 ± 1j}
K_POLES = (-1.0 + 1.0j, -1.0 - 1.0j)

#: Section 3.2: subsystem 1 is (3.2); subsystem 2 is consistent with the thesis's observer for it.
A4 = np.array([[-2.0, 1.0, 0.0, 0.0], [0.0, -2.0, 1.0, 0.0], [0.0, 0.0, -1.0, 1.0], [-1.0, 0.0, 0.0, 0.0]])
B4 = np.array([[0.0], [0.0], [0.0], [1.0]])
C4 = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])


def thesis_observer_35_37(x1, x3, u, z, w):
    """(ż, ẇ) of the thesis's observers as printed: (3.5) ż = −3z + x1 − x3 and
    ẇ = −3w + x3 − (u − x1)/6; the estimates are (3.6) x̂2 = x1 − z, x̂4 = 3x3 − 6w and (3.7) their sum."""
    return (-3.0 * z + x1 - x3, -3.0 * w + x3 - (u - x1) / 6.0)


def example_28():
    """The plant (2.8) and its identity observer with poles {-3, -3} (G = [3, 4]ᵀ)."""
    import obsjax

    plant = obsjax.LTI(A, B, C)
    return plant, obsjax.Luenberger.from_poles(plant, [-3.0, -3.0])


def feedback_gain():
    """State feedback K with eig(A + BK) = K_POLES (pole placement on the dual pair (Aᵀ, Bᵀ))."""
    import obsjax

    L = np.asarray(obsjax.design.place(A.T, B.T, np.array(K_POLES)))
    return -np.real(L).T  # eig(Aᵀ − L Bᵀ) = eig(A − B Lᵀ) = eig(A + BK) with K = −Lᵀ


def composite_matrix(K, F, G, T, E, D):
    """Composite matrix (2.22) of plant and observer under u = E z + D y."""
    return np.block([[A + B @ D @ C, B @ E], [G @ C + T @ B @ D @ C, F + T @ B @ E]])


def reproduce(outdir: str) -> list[str]:
    import jax.numpy as jnp
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import scipy.linalg

    import obsjax

    os.makedirs(outdir, exist_ok=True)
    paths = []
    plant, obs = example_28()
    G = np.asarray(obs.gain)
    F = np.asarray(obs.observer_matrix)
    ts = np.linspace(0.0, 4.0, 201)
    x0, xh0 = np.array([1.0, -1.0]), np.zeros(2)
    u = obsjax.signals.multisine([1.0], [0.5])
    traj = obsjax.simulate(plant, obs, x0, xh0, ts, u=u, rtol=1e-9, atol=1e-11)
    e_ref = np.stack([scipy.linalg.expm(F * t) @ (xh0 - x0) for t in ts])

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    for i in range(2):
        ax[0].plot(ts, np.asarray(traj.x[:, i]), f"C{i}", label=f"$x_{i + 1}$")
        ax[0].plot(ts, np.asarray(traj.xhat[:, i]), f"C{i}--", label=rf"$\hat x_{i + 1}$")
    ax[0].set_title(f"Example (2.8): identity observer, G = [{G[0, 0]:.3g}, {G[1, 0]:.3g}]ᵀ")
    ax[0].set_xlabel("time t (s)")
    ax[0].set_ylabel("state and estimate")
    ax[0].legend(fontsize=8)
    ax[1].semilogy(ts, np.linalg.norm(np.asarray(traj.error), axis=1), label="simulated")
    ax[1].semilogy(
        ts, np.linalg.norm(e_ref, axis=1), "k:", label=r"$\|e^{(A - GC)t}\,\tilde x(0)\|$"
    )
    ax[1].set_title("A − GC = [[−5, 1], [−4, −1]], eigenvalues {−3, −3}")
    ax[1].set_xlabel("time t (s)")
    ax[1].set_ylabel(r"$\|\hat x(t) - x(t)\|$")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    p = os.path.join(outdir, "hassan_2_8_identity_observer.png")
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)

    # Reduced-order observer (2.13)-(2.16), pole -3 -> G = 2 (C = [1, 0] so w = x2).
    red = obsjax.ReducedOrder.from_poles(plant, [-3.0], Dc=[[0.0, 1.0]])
    Gr = float(np.asarray(red.gain)[0, 0])
    tr = obsjax.simulate(plant, red, x0, xh0, ts, u=u, rtol=1e-9, atol=1e-11)
    w_err_ref = np.exp(-3.0 * ts) * (xh0[1] - x0[1])
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    ax[0].plot(ts, np.asarray(tr.x[:, 1]), label="$x_2$")
    ax[0].plot(ts, np.asarray(tr.xhat[:, 1]), "--", label=r"$\hat x_2$ (reduced order)")
    ax[0].set_title(f"Reduced-order observer (2.15)-(2.16): G = {Gr:.4g}")
    ax[0].set_xlabel("time t (s)")
    ax[0].set_ylabel("unmeasured state and estimate")
    ax[0].legend(fontsize=8)
    ax[1].semilogy(ts, np.abs(np.asarray(tr.error[:, 1])), label="simulated")
    ax[1].semilogy(ts, np.abs(w_err_ref), "k:", label=r"$|\tilde x_2(0)|\, e^{-3t}$")
    ax[1].set_title(r"$A_{22} - G A_{12} = -1 - G = -3$")
    ax[1].set_xlabel("time t (s)")
    ax[1].set_ylabel(r"$|\hat x_2(t) - x_2(t)|$")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    p = os.path.join(outdir, "hassan_reduced_order.png")
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)

    # Closed loop (section 2.5): identity observer T = I, E = K, D = 0.
    K = feedback_gain()
    M = composite_matrix(K, F, G, np.eye(2), K, np.zeros((1, 1)))
    eig_comp = np.linalg.eigvals(M)
    eig_sep = np.concatenate([np.linalg.eigvals(A + B @ K), np.linalg.eigvals(F)])
    x0c = np.array([1.0, 1.0])
    tc = np.linspace(0.0, 8.0, 321)
    ctrl = lambda t, xhat: jnp.asarray(K) @ xhat
    cl = obsjax.simulate(plant, obs, x0c, np.zeros(2), tc, controller=ctrl, rtol=1e-9, atol=1e-11)
    ref = np.stack([scipy.linalg.expm(M * t) @ np.concatenate([x0c, np.zeros(2)]) for t in tc])
    full = np.stack([scipy.linalg.expm((A + B @ K) * t) @ x0c for t in tc])
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    ax[0].plot(
        eig_comp.real, eig_comp.imag, "o", ms=10, mfc="none", label="eig of composite (2.22)"
    )
    ax[0].plot(eig_sep.real, eig_sep.imag, "x", ms=8, label="eig(A + BK) ∪ eig(A − GC)")
    ax[0].axvline(0, color="k", lw=0.5, label="imaginary axis")
    ax[0].set_xlabel("Re λ (1/s)")
    ax[0].set_ylabel("Im λ (rad/s)")
    ax[0].set_title("Theorem 4: the observer adjoins its eigenvalues")
    ax[0].legend(fontsize=8)
    ax[1].plot(tc, np.asarray(cl.x[:, 0]), label=r"$u = K\hat x$ (simulated)")
    ax[1].plot(tc, ref[:, 0], "k:", label=r"$e^{Mt}$ of (2.22)")
    ax[1].plot(tc, full[:, 0], "C2--", label="u = K x (state feedback)")
    ax[1].set_xlabel("time t (s)")
    ax[1].set_ylabel("plant state $x_1(t)$")
    ax[1].set_title("observer-based feedback, x̂(0) = 0")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    p = os.path.join(outdir, "hassan_closed_loop_eigenvalues.png")
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    paths.append(_section_3_2(outdir, plt))
    return paths


def _section_3_2(outdir, plt):
    """Figure: the observer of (3.5)-(3.7) as printed (SciPy) against obsjax's reduced-order observer."""
    import jax.numpy as jnp
    from scipy.integrate import solve_ivp

    import obsjax

    plant = obsjax.LTI(A4, B4, C4)
    cf = obsjax.design.observable_canonical_form(A4, C4)
    red = obsjax.ReducedOrder.from_poles(plant, [-3.0, -3.0], Dc=[[0, 1, 0, 0], [0, 0, 0, 1.0]])
    G = np.asarray(red.gain)
    u = obsjax.signals.multisine([1.0], [0.7])
    ts = np.linspace(0.0, 4.0, 201)
    x0 = np.array([1.0, -1.0, 0.5, 2.0])
    tr = obsjax.simulate(plant, red, x0, np.zeros(4), jnp.asarray(ts), u=u, rtol=1e-10, atol=1e-12)

    def rhs(t, s):
        x, z, w = s[:4], s[4], s[5]
        ut = float(np.asarray(u(t))[0])
        dz, dw = thesis_observer_35_37(x[0], x[2], ut, z, w)
        return np.concatenate([A4 @ x + B4[:, 0] * ut, [dz, dw]])

    # the thesis's observer started where obsjax's is (x̂(0) = 0: z = x1 − x̂2, w = (3x3 − x̂4)/6)
    s0 = np.concatenate([x0, [x0[0], 3 * x0[2] / 6.0]])
    sol = solve_ivp(rhs, (0.0, 4.0), s0, t_eval=ts, rtol=1e-10, atol=1e-12)
    x1, x3, z, w = sol.y[0], sol.y[2], sol.y[4], sol.y[5]
    s_hat_thesis = x1 + 3 * x3 - z - 6 * w  # (3.7)
    s_hat = np.asarray(tr.xhat[:, 1] + tr.xhat[:, 3])
    s_true = sol.y[1] + sol.y[3]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    ax[0].plot(ts, s_true, "k", label="x2 + x4")
    ax[0].plot(ts, s_hat_thesis, "C0--", label="(3.7) as printed (SciPy)")
    ax[0].plot(ts, s_hat, "C1:", lw=2.5, label=f"obsjax ReducedOrder, G = {G.round(6).tolist()}")
    ax[0].set_xlabel("time t (s)")
    ax[0].set_ylabel("unmeasured x₂ + x₄ and its estimates")
    ax[0].set_title(f"§3.2: indices ν = {cf.indices}, poles {{−3, −3}}")
    ax[0].legend(fontsize=8)
    err = np.abs(s_hat - s_true)
    ax[1].semilogy(ts, np.maximum(err, 1e-16), label="|x̂2 + x̂4 − (x2 + x4)| obsjax")
    ax[1].semilogy(ts, np.maximum(np.abs(s_hat - s_hat_thesis), 1e-16), label="|obsjax − (3.7)|")
    ax[1].semilogy(ts, err[0] * np.exp(-3 * ts), "k:", label=r"$|\tilde x_2(0) + \tilde x_4(0)|\,e^{-3t}$ (A22 − G A12 = −3I)")
    ax[1].set_xlabel("time t (s)")
    ax[1].set_ylabel("estimation error and difference")
    ax[1].set_title("two single-output observers (Fig. 3.4)")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    p = os.path.join(outdir, "hassan_3_2_canonical_observer.png")
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def paper_values():
    """The thesis's stated values: example (2.8), the reduced-order gain, (3.3) and Theorem 4."""
    import obsjax

    from ._report import Row
    from .references import HASSAN_28_GAIN, HASSAN_33_T, HASSAN_REDUCED_GAIN

    plant, obs = example_28()
    G = np.asarray(obs.gain)[:, 0]
    rows = [
        Row(f"(2.8): G{i + 1}, poles {{−3, −3}}", g, float(G[i]))
        for i, g in enumerate(HASSAN_28_GAIN)
    ]
    F = np.asarray(obs.observer_matrix)
    for (i, j), v in np.ndenumerate(np.array([[-5.0, 1.0], [-4.0, -1.0]])):
        rows.append(Row(f"(2.8): (A − GC)[{i + 1},{j + 1}]", v, float(F[i, j])))
    red = obsjax.ReducedOrder.from_poles(plant, [-3.0], Dc=[[0.0, 1.0]])
    rows.append(
        Row(
            "(2.13)-(2.16): reduced-order G, pole −3",
            HASSAN_REDUCED_GAIN,
            float(np.asarray(red.gain)[0, 0]),
        )
    )
    T = np.asarray(obsjax.design.sylvester([[-2.0, 1.0], [0.0, -2.0]], [[-3.0]], [[1.0, 0.0]]))[0]
    rows += [Row(f"(3.3): T{i + 1}, F = −3", t, float(T[i])) for i, t in enumerate(HASSAN_33_T)]
    K = feedback_gain()
    M = composite_matrix(K, F, np.asarray(obs.gain), np.eye(2), K, np.zeros((1, 1)))
    eig = np.linalg.eigvals(M)
    for lam in (*K_POLES, -3.0, -3.0):
        k = int(np.argmin(np.abs(eig - lam)))
        # −3 is a double eigenvalue of a Jordan block: computed to about √ε, hence the tolerance.
        rows.append(
            Row(
                "Theorem 4: eig of (2.22) ∋ " + ("eig(A + BK)" if np.iscomplex(lam) else "eig(F)"),
                complex(lam),
                complex(eig[k]),
                rtol=1e-6,
            )
        )
        eig = np.delete(eig, k)
    return rows
