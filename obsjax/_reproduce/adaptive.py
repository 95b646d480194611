"""Adaptive observers of the Hassan thesis, chapters 4-6: the examples, their helpers and the figures.

The thesis gives no numerical example for chapters 4-6, so the plants below are chosen (stable, minimal,
2nd and 3rd order) and the figures show what the chapters claim: parameter convergence of the three
Kreisselmeier schemes (chapter 6) with the fitted exponential rates, the Lüders–Narendra state and
parameter errors with its Lyapunov function (chapter 5), the Kudva–Narendra identifier (section 4.3), and
the richness condition (a single sinusoid on a 3rd-order plant: the output error vanishes, the parameters
do not converge).

``reproduce(outdir)`` writes the PNGs and returns their paths.
"""

from __future__ import annotations

import os

import numpy as np

# --------------------------------------------------------------------------- the examples
#: Kreisselmeier, 2nd order: y = (s + 1)/(s² + 2s + 2) u, F with eigenvalues {-2, -2}.
KREISSELMEIER_2 = {
    "a": (2.0, 2.0),
    "b": (1.0, 1.0),
    "poles": (-2.0, -2.0),
    "amplitudes": (1.0, 1.0),
    "frequencies": (0.7, 2.0),
}
#: Kreisselmeier, 3rd order: y = (s² + s + 1)/((s + 1)(s² + 2s + 2)) u, F with eigenvalues {-2, -2, -2}.
KREISSELMEIER_3 = {
    "a": (3.0, 4.0, 2.0),
    "b": (1.0, 1.0, 1.0),
    "poles": (-2.0, -2.0, -2.0),
    "amplitudes": (1.0, 1.0, 1.0),
    "frequencies": (0.5, 1.2, 3.0),
}
#: Lüders–Narendra, 2nd order in the form (5.2), Λ = diag(-0.5), λ1 = 1.
LUDERS_NARENDRA_2 = {
    "a": (-1.0, -1.0),
    "b": (1.0, -1.0),
    "lambdas": (1.0, 0.5),
    "amplitudes": (1.0, 1.0),
    "frequencies": (0.5, 3.0),
}
#: Lüders–Narendra, 3rd order in the form (5.2), Λ = diag(-0.3, -1), λ1 = 0.5, four sinusoids.
LUDERS_NARENDRA_3 = {
    "a": (-1.0, -1.0, -1.0),
    "b": (1.0, 1.0, -1.0),
    "lambdas": (0.5, 0.3, 1.0),
    "amplitudes": (1.0, 1.0, 1.0, 1.0),
    "frequencies": (0.2, 0.8, 1.2, 3.0),
}
#: Kudva–Narendra, 2 states, 2 inputs, all states measured.
KUDVA_NARENDRA = {
    "Ap": ((-1.0, 0.5), (-0.5, -2.0)),
    "Bp": ((1.0, 0.0), (0.5, 1.0)),
    "amplitudes": ((1.0, 1.0), (1.0, 1.0)),
    "frequencies": ((0.5, 1.7), (1.1, 2.9)),
}


def kreisselmeier_gain(example, gamma, scheme="gradient", filter_pole=1.0):
    """Diagonal gain G = γ / diag(M̄): each parameter adapts at the rate γ relative to its own excitation.

    M̄ is the mean regressor covariance (:func:`obsjax.observers.mean_regressor_covariance`), filtered by
    Lion's weights for the generalised scheme.
    """
    from ..observers._kreisselmeier import mean_regressor_covariance

    n = len(example["a"])
    weight = None
    if scheme == "generalized":

        def weight(w):
            v = np.array([(1j * w) ** k for k in range(2 * n)]) / (1j * w + filter_pole) ** (
                2 * n - 1
            )
            return complex(np.vdot(v, v))

    M = mean_regressor_covariance(
        example["a"],
        example["b"],
        example["poles"],
        example["amplitudes"],
        example["frequencies"],
        weight,
    )
    return gamma / np.diag(M)


def luders_narendra_rates(example, gamma):
    """Rates c_i, d_i = γ / mean(ζ_i²) for the regressor ζ = [x_1, v_2..v_n, u, s_2..s_n] of (5.12)."""
    a, b, lams = (np.asarray(example[k], float) for k in ("a", "b", "lambdas"))
    n = a.shape[0]
    A = np.zeros((n, n))
    A[:, 0] = a
    A[0, 1:] = 1.0
    A[np.arange(1, n), np.arange(1, n)] = -lams[1:]
    power = np.zeros(2 * n)
    for amp, w in zip(example["amplitudes"], example["frequencies"]):
        s = 1j * w
        gy = np.linalg.solve(s * np.eye(n) - A, b)[0]
        H = np.r_[gy, gy / (s + lams[1:]), 1.0, 1.0 / (s + lams[1:])]
        power += amp**2 / 2 * np.abs(H) ** 2
    rates = gamma / power
    return rates[:n], rates[n:]


def relative_parameter_error(a_hat, b_hat, a, b):
    """‖(â, b̂) − (a, b)‖ / ‖(a, b)‖ along a trajectory."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    err = np.concatenate([np.asarray(a_hat) - a, np.asarray(b_hat) - b], axis=-1)
    return np.linalg.norm(err, axis=-1) / np.linalg.norm(np.r_[a, b])


def fit_rate(ts, err, lo=None, hi=None, floor=1e-11):
    """Exponential decay rate σ of err(t) ≈ C e^{−σ t}: least squares of log err on [lo, hi] (err > floor)."""
    ts, err = np.asarray(ts), np.asarray(err)
    lo = ts[0] if lo is None else lo
    hi = ts[-1] if hi is None else hi
    sel = (ts >= lo) & (ts <= hi) & (err > floor)
    if sel.sum() < 3:
        raise ValueError("fit_rate: fewer than 3 points above the floor in the window.")
    return -float(np.polyfit(ts[sel], np.log(err[sel]), 1)[0])


def time_to(ts, err, level):
    """First time after which err stays below ``level`` (inf if it never does)."""
    ts, err = np.asarray(ts), np.asarray(err)
    above = np.nonzero(err >= level)[0]
    if above.size == 0:
        return float(ts[0])
    k = above[-1]
    return float("inf") if k == len(ts) - 1 else float(ts[k + 1])


# --------------------------------------------------------------------------- simulations
def simulate_kreisselmeier(
    example,
    scheme,
    gamma=2.0,
    q=None,
    G=None,
    t1=300.0,
    num=601,
    x0=None,
    xhat0=None,
    u=None,
    filter_pole=1.0,
    **kw,
):
    """Simulate one Kreisselmeier scheme on an example; returns (ts, relative parameter error, traj, obs)."""
    import jax.numpy as jnp

    import obsjax

    n = len(example["a"])
    plant = obsjax.kreisselmeier_form(example["a"], example["b"])
    if G is None:
        G = kreisselmeier_gain(example, gamma, scheme, filter_pole)
    kwargs = {"q": q} if scheme == "integral" else {}
    if scheme == "generalized":
        kwargs["filter_pole"] = filter_pole
    obs = obsjax.Kreisselmeier(n, example["poles"], jnp.asarray(G), scheme=scheme, **kwargs)
    u = obsjax.signals.multisine(example["amplitudes"], example["frequencies"]) if u is None else u
    x0 = jnp.ones(n) if x0 is None else x0
    xhat0 = jnp.zeros(n) if xhat0 is None else xhat0
    ts = jnp.linspace(0.0, t1, num)
    traj = obsjax.simulate(plant, obs, x0, xhat0, ts, u=u, max_steps=200_000, **kw)
    a_hat, b_hat = obs.parameters(traj.z)
    err = relative_parameter_error(a_hat, b_hat, example["a"], example["b"])
    return np.asarray(ts), err, traj, obs


def simulate_luders_narendra(example, gamma=5.0, t1=200.0, num=401, **kw):
    """Simulate the Lüders–Narendra observer with normalised rates; x̂_i(0) = x_i(0) for i ≥ 2 (so V of
    (5.11) is non-increasing).  Returns (ts, relative parameter error, traj, obs)."""
    import jax.numpy as jnp

    import obsjax

    n = len(example["a"])
    plant = obsjax.luders_narendra_form(example["a"], example["b"], example["lambdas"])
    c, d = luders_narendra_rates(example, gamma)
    obs = obsjax.LudersNarendra(n, example["lambdas"], jnp.asarray(c), jnp.asarray(d))
    u = obsjax.signals.multisine(example["amplitudes"], example["frequencies"])
    x0 = jnp.ones(n)
    xhat0 = x0.at[0].set(0.0)
    ts = jnp.linspace(0.0, t1, num)
    traj = obsjax.simulate(plant, obs, x0, xhat0, ts, u=u, max_steps=400_000, **kw)
    alpha, beta = obs.parameters(traj.z)
    err = relative_parameter_error(alpha, beta, example["a"], example["b"])
    return np.asarray(ts), err, traj, obs


# --------------------------------------------------------------------------- studies
def rate_study(gamma=2.0, q=0.2, t1=300.0, num=601):
    """Fitted and predicted exponential rates of ‖p − p*‖ for the three Kreisselmeier schemes (2nd order).

    Gradient and integral use the same G = γ/diag(R̄); the generalised scheme gets its own normalised G.
    Returns a dict scheme -> {fitted, predicted, t_1pct, t_1e-3}.
    """
    ex = KREISSELMEIER_2
    out = {}
    for scheme in ("gradient", "generalized", "integral"):
        ts, err, _, obs = simulate_kreisselmeier(
            ex, scheme, gamma=gamma, q=q if scheme == "integral" else None, t1=t1, num=num
        )
        lo, hi = (20.0, 200.0) if scheme == "integral" else (t1 / 3, t1)
        out[scheme] = {
            "fitted": fit_rate(ts, err, lo=lo, hi=hi),
            "predicted": obs.averaged_rate(ex["a"], ex["b"], ex["amplitudes"], ex["frequencies"]),
            "t_1pct": time_to(ts, err, 1e-2),
            "t_1e-3": time_to(ts, err, 1e-3),
        }
    return out


def tuning_study(steps=30, learning_rate=0.1, gamma=2.0, t_tune=150.0, t1=300.0, num=601):
    """Tune the diagonal G of the gradient scheme (6.16) with :func:`obsjax.tune` (Adam on log G) on the loss
    ∫‖p − p*‖² dt over [0, t_tune]; report the time to 1 % parameter error before and after."""
    import jax.numpy as jnp
    import optax

    import obsjax

    ex = KREISSELMEIER_2
    ts, err, _, obs = simulate_kreisselmeier(ex, "gradient", gamma=gamma, t1=t1, num=num)
    pstar = obs.matching_point(jnp.asarray(ex["a"]), jnp.asarray(ex["b"]))

    def loss(traj):
        e2 = jnp.sum((traj.z.p - pstar) ** 2, axis=-1)
        return jnp.sum(0.5 * (e2[1:] + e2[:-1]) * jnp.diff(traj.ts))

    res = obsjax.tune(
        obs,
        obsjax.kreisselmeier_form(ex["a"], ex["b"]),
        where=lambda o: o.G,
        loss=loss,
        x0s=jnp.ones((1, 2)),
        xhat0s=jnp.zeros((1, 2)),
        ts=jnp.linspace(0.0, t_tune, int(2 * t_tune) + 1),
        optimizer=optax.adam(learning_rate),
        steps=steps,
        progress=False,
        u=obsjax.signals.multisine(ex["amplitudes"], ex["frequencies"]),
        simulate_kwargs={"max_steps": 200_000},
    )
    ts2, err2, _, _ = simulate_kreisselmeier(ex, "gradient", G=res.observer.G, t1=t1, num=num)
    return {
        "G_before": np.asarray(obs.G),
        "G_after": np.asarray(res.observer.G),
        "loss": np.asarray(res.history["loss"]),
        "t_1pct_before": time_to(ts, err, 1e-2),
        "t_1pct_after": time_to(ts2, err2, 1e-2),
        "t_1e-3_before": time_to(ts, err, 1e-3),
        "t_1e-3_after": time_to(ts2, err2, 1e-3),
        "ts": ts,
        "err_before": err,
        "err_after": err2,
    }


# --------------------------------------------------------------------------- figures
def reproduce(outdir: str) -> list[str]:
    """Write the chapter 4-6 figures as PNGs into ``outdir`` and return their paths (about 30 s)."""
    import matplotlib

    matplotlib.use("Agg")
    import jax.numpy as jnp
    import matplotlib.pyplot as plt

    import obsjax

    os.makedirs(outdir, exist_ok=True)
    paths = []
    ex = KREISSELMEIER_2

    # 1. Kreisselmeier: the three schemes, parameter estimates and ‖p − p*‖ with fitted rates.
    runs = {
        "gradient (6.16)": simulate_kreisselmeier(ex, "gradient", gamma=2.0, t1=300.0, num=3001),
        "generalized (6.19)": simulate_kreisselmeier(
            ex, "generalized", gamma=2.0, t1=300.0, num=3001
        ),
        "integral (6.23), q = 0.2": simulate_kreisselmeier(
            ex, "integral", gamma=2.0, q=0.2, t1=300.0, num=3001
        ),
    }
    fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    axes = axes.ravel()
    truth = np.r_[ex["a"], ex["b"]]
    labels = [f"â{i + 1}" for i in range(2)] + [f"b̂{i + 1}" for i in range(2)]
    for ax, (name, (ts, _, traj, obs)) in zip(axes[:3], runs.items()):
        a_hat, b_hat = obs.parameters(traj.z)
        est = np.concatenate([np.asarray(a_hat), np.asarray(b_hat)], axis=-1)
        for k in range(4):
            ax.plot(ts, est[:, k], label=labels[k])
            ax.axhline(
                truth[k], color="k", lw=0.5, ls="--", label="true values" if k == 0 else None
            )
        ax.set(
            xlabel="time t (s)",
            ylabel="parameter estimates",
            title=f"{name}: (â, b̂) of (6.2)",
            ylim=(-1, 4),
        )
        ax.legend(ncol=2, fontsize=8)
    for name, (ts, err, _, _) in runs.items():
        lo, hi = (20.0, 200.0) if name.startswith("integral") else (ts[-1] / 3, ts[-1])
        rate = fit_rate(ts, err, lo=lo, hi=hi)
        axes[3].semilogy(ts, err, label=f"{name}: σ = {rate:.3g}")
    axes[3].axhline(1e-3, color="k", lw=0.5, ls=":", label="relative error $10^{-3}$")
    axes[3].set(
        xlabel="time t (s)", ylabel="‖p − p*‖ / ‖p*‖", title="Kreisselmeier, 2nd order, γ = 2"
    )
    axes[3].legend(fontsize=8)
    fig.tight_layout()
    paths.append(_save(fig, outdir, "adaptive_kreisselmeier_schemes.png"))

    # 2. Lüders–Narendra: state and parameter errors, Lyapunov function (5.11).
    ex_ln = LUDERS_NARENDRA_2
    ts, err, traj, obs = simulate_luders_narendra(ex_ln, gamma=5.0, t1=200.0, num=4001)
    V = obs.lyapunov(traj.z, traj.y, jnp.asarray(ex_ln["a"]), jnp.asarray(ex_ln["b"]))
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    axes[0].semilogy(ts, np.abs(np.asarray(traj.error)) + 1e-16, label=["$i = 1$", "$i = 2$"])
    axes[0].set(xlabel="time t (s)", ylabel=r"$|\hat x_i - x_i|$", title="state errors")
    axes[0].legend()
    axes[1].semilogy(ts, err)
    axes[1].set(xlabel="time t (s)", ylabel="‖(α, β) − (a, b)‖ / ‖(a, b)‖", title="parameter error")
    axes[2].semilogy(ts, np.asarray(V))
    axes[2].set(xlabel="time t (s)", ylabel="V", title="Lyapunov function V (5.11), non-increasing")
    fig.suptitle("Lüders–Narendra adaptive observer (5.3)-(5.12), 2nd order")
    fig.tight_layout()
    paths.append(_save(fig, outdir, "adaptive_luders_narendra.png"))

    # 3. Richness: one sinusoid on the 3rd-order plant (integral scheme) against three.
    ex3 = KREISSELMEIER_3
    rich = simulate_kreisselmeier(ex3, "integral", gamma=2.0, q=0.2, t1=200.0, num=2001)
    single = obsjax.signals.multisine([0.0, 1.0, 0.0], list(ex3["frequencies"]))  # u = sin(1.2 t)
    G = kreisselmeier_gain(ex3, 2.0)
    poor = simulate_kreisselmeier(ex3, "integral", G=G, q=0.2, t1=200.0, num=2001, u=single)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for name, (ts, err, traj, obs) in (("3 sinusoids", rich), ("1 sinusoid", poor)):
        yhat = np.asarray(jax_output(obs, traj))
        axes[0].semilogy(ts, np.abs(yhat - np.asarray(traj.y[:, 0])) + 1e-16, label=name)
        axes[1].semilogy(ts, err, label=name)
    axes[0].set(xlabel="time t (s)", ylabel="|ŷ − y|", title="output error")
    axes[1].set(xlabel="time t (s)", ylabel="‖p − p*‖ / ‖p*‖", title="parameter error")
    for ax in axes:
        ax.legend()
    fig.suptitle("Richness condition, 3rd-order plant, integral scheme (6.23)")
    fig.tight_layout()
    paths.append(_save(fig, outdir, "adaptive_richness.png"))
    return paths


def jax_output(obs, traj):
    import jax

    return jax.vmap(obs.output)(traj.z)


def _save(fig, outdir, name):
    import matplotlib.pyplot as plt

    path = os.path.join(outdir, name)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def paper_values():
    """The chapters' claims on their examples (the thesis gives no numbers for chapters 4-6): the integral
    scheme (6.23) and the Lüders–Narendra observer (5.3)-(5.12) identify the plant's parameters under a
    sufficiently rich input, and V of (5.11) never increases."""
    import jax.numpy as jnp

    from ._report import Row

    ex = KREISSELMEIER_2
    _, _, traj, obs = simulate_kreisselmeier(ex, "integral", gamma=2.0, q=0.2, t1=300.0)
    a_hat, b_hat = (np.asarray(v)[-1] for v in obs.parameters(traj.z))
    names = [f"a{i + 1}" for i in range(2)] + [f"b{i + 1}" for i in range(2)]
    rows = [
        Row(
            f"Kreisselmeier (6.23), q = 0.2: {k} at t = 300 → plant's",
            v,
            float(e),
            "ch. 6: p → p*",
            rtol=1e-6,
        )
        for k, v, e in zip(names, [*ex["a"], *ex["b"]], [*a_hat, *b_hat])
    ]
    ex = LUDERS_NARENDRA_2
    _, _, traj, obs = simulate_luders_narendra(ex, gamma=5.0, t1=200.0)
    al, be = (np.asarray(v)[-1] for v in obs.parameters(traj.z))
    rows += [
        Row(
            f"Lüders–Narendra (5.12): {k} at t = 200 → plant's",
            v,
            float(e),
            "ch. 5: convergence",
            rtol=1e-4,
        )
        for k, v, e in zip(names, [*ex["a"], *ex["b"]], [*al, *be])
    ]
    V = np.asarray(obs.lyapunov(traj.z, traj.y, jnp.asarray(ex["a"]), jnp.asarray(ex["b"])))
    rows.append(
        Row(
            "Lüders–Narendra: max increase of V (5.11) between saves, relative to V(0)",
            0.0,
            float(np.max(np.diff(V)) / V[0]),
            "ch. 5: V̇ ≤ 0",
            rtol=0.0,
            atol=1e-9,
            relation="<=",
        )
    )
    return rows
