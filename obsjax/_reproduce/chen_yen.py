"""Chen & Yen (IEEE TAC 44(9), 1999): Figs. 1 and 2, the state estimation error of the example, reproduced.

- ``chen_yen_fig1.png``: x̃(t) = x̂(t) − x(t) for γ = 20, p0 = 0.1, x̂(0) = [5, −5], T = 0.25 (Fig. 1): the
  two components (as in the paper) and ‖x̃(t)‖ on a log scale with independent SciPy reference values, the reset
  instants and the Theorem's guaranteed envelope Π ρ_k ‖x̃(0)‖ (22).
- ``chen_yen_fig2.png``: the same with T = 2 (Fig. 2).

Run with ``obsjax reproduce chen-yen`` (or ``python -m obsjax._reproduce.chen_yen OUTDIR``).
"""

from __future__ import annotations

import os
import sys

import numpy as np

from .references import CHEN_YEN_ERROR_NORM

# Independent SciPy values of ‖x̃‖ at t = 1, 2, 5, 10 (see obsjax/_reproduce/references.py), by period T.
REFERENCE = {T: CHEN_YEN_ERROR_NORM[(20.0, 0.1, T)] for T in (0.25, 2.0)}


def simulate_example(T, gamma=20.0, p0=0.1, ts=None, rtol=1e-9, atol=1e-11):
    """The paper's example with the least-squares observer; returns the obsjax Trajectory."""
    import diffrax
    import jax.numpy as jnp

    import obsjax

    plant = obsjax.chen_yen_example()
    obs = obsjax.LeastSquaresReset(plant, gamma, p0, T)
    ts = jnp.linspace(0.0, 10.0, 1001) if ts is None else ts
    return obsjax.simulate(
        plant,
        obs,
        jnp.zeros(2),
        jnp.array([5.0, -5.0]),
        ts,
        solver=diffrax.Dopri8(),
        rtol=rtol,
        atol=atol,
    )


def _figure(T, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import obsjax
    from obsjax import analysis

    tr = simulate_example(T)
    ts, err = np.asarray(tr.ts), np.asarray(tr.error)
    nrm = np.linalg.norm(err, axis=1)
    rho = np.asarray(analysis.chen_yen_bound(obsjax.chen_yen_example(), 20.0, 0.1, T, 10.0))
    env_t = T * np.arange(len(rho) + 1)
    env = np.concatenate([[nrm[0]], nrm[0] * np.cumprod(rho)])

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 3.8))
    ax1.plot(ts, err[:, 0], label=r"$\tilde x_1$")
    ax1.plot(ts, err[:, 1], label=r"$\tilde x_2$")
    ax1.set_xlabel("time t (s)")
    ax1.set_ylabel(r"estimation error $\tilde x_i(t) = \hat x_i(t) - x_i(t)$")
    ax1.set_title(
        f"Chen & Yen Fig. {1 if T < 1 else 2}: γ = 20, " + r"$p_0$" + f" = 0.1, T = {T:g} s"
    )
    ax1.grid(True, alpha=0.3)
    ax1.legend()
    ax2.semilogy(ts, nrm, label=r"$\|\tilde x(t)\|$ (obsjax)")
    ref = REFERENCE[T]
    ax2.semilogy(
        list(ref),
        list(ref.values()),
        "o",
        mfc="none",
        color="k",
        label="independent SciPy solution",
    )
    ax2.semilogy(
        env_t,
        env,
        "--",
        color="gray",
        lw=1,
        label=r"Theorem (22): $\prod_{j<k} \rho_j\, \|\tilde x(0)\|$ at $t = kT$",
    )
    for k in range(1, len(rho)):
        ax2.axvline(
            k * T,
            color="C2",
            lw=0.4,
            alpha=0.4,
            label="covariance resets t = kT" if k == 1 else None,
        )
    ax2.set_xlabel("time t (s)")
    ax2.set_ylabel(r"$\|\tilde x(t)\|$")
    ax2.set_ylim(min(nrm.min(), 1e-4) / 2, max(env.max(), nrm.max()) * 2)
    ax2.grid(True, which="both", alpha=0.3)
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def reproduce(outdir: str) -> list[str]:
    """Write Figs. 1 and 2 of Chen & Yen as PNGs in `outdir`; returns their paths."""
    os.makedirs(outdir, exist_ok=True)
    return [
        _figure(0.25, os.path.join(outdir, "chen_yen_fig1.png")),
        _figure(2.0, os.path.join(outdir, "chen_yen_fig2.png")),
    ]


def paper_values():
    """Chen & Yen's example against the independent SciPy values of ``references.py`` (the paper gives its
    results as Figs. 1-2 only) and against the Theorem's bound (22) at t = 10."""
    import diffrax
    import equinox as eqx
    import jax.numpy as jnp

    import obsjax
    from obsjax import analysis

    from ._report import Row
    from .references import CHEN_YEN_OPEN_LOOP_NORM_10

    plant = obsjax.chen_yen_example()
    tq = jnp.asarray([0.0, 1.0, 2.0, 5.0, 10.0])

    @eqx.filter_jit
    def norms(obs):  # one compilation for every (γ, p0, T): 40 segments cover [0, 10] for T ≥ 0.25
        traj = obsjax.simulate(
            plant,
            obs,
            jnp.zeros(2),
            jnp.array([5.0, -5.0]),
            tq,
            solver=diffrax.Dopri8(),
            rtol=1e-9,
            atol=1e-11,
            max_segments=40,
        )
        return traj.error_norm

    rows = []
    for (gamma, p0, T), ref in CHEN_YEN_ERROR_NORM.items():
        nrm = dict(
            zip(
                np.asarray(tq).tolist(),
                np.asarray(norms(obsjax.LeastSquaresReset(plant, gamma, p0, T))),
            )
        )
        fig = {0.25: " (Fig. 1)", 2.0: " (Fig. 2)"}.get(T, "") if (gamma, p0) == (20.0, 0.1) else ""
        for t, value in ref.items():
            rows.append(
                Row(
                    f"‖x̃({t:g})‖, γ = {gamma:g}, p0 = {p0:g}, T = {T:g}{fig}",
                    value,
                    float(nrm[t]),
                    "SciPy reference",
                    rtol=1e-3,
                )
            )
        if (gamma, p0, T) == (20.0, 0.1, 0.25):
            rho = np.asarray(analysis.chen_yen_bound(plant, gamma, p0, T, 10.0))
            rows.append(
                Row(
                    "‖x̃(10)‖ ≤ Π ρ_k ‖x̃(0)‖, T = 0.25",
                    float(nrm[0.0] * np.prod(rho)),
                    float(nrm[10.0]),
                    "Theorem (22)",
                    rtol=0.0,
                    relation="<=",
                )
            )
    Phi = np.asarray(analysis.transition_matrix(plant, 10.0, 0.0))
    rows.append(
        Row(
            "open loop ‖x(10)‖ from x(0) = [5, −5]",
            CHEN_YEN_OPEN_LOOP_NORM_10,
            float(np.linalg.norm(Phi @ [5.0, -5.0])),
            "SciPy reference",
            rtol=1e-3,
        )
    )
    return rows


if __name__ == "__main__":  # pragma: no cover
    print("\n".join(reproduce(sys.argv[1] if len(sys.argv) > 1 else "obsjax-demo")))
