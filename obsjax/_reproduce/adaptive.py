"""Adaptive observers of the Hassan thesis, chapters 4-6: the examples, their helpers and the figures.

The thesis gives no numerical example for chapters 4-6, so the plants below are chosen (stable, minimal,
2nd and 3rd order) and the figures show what the chapters claim: parameter convergence of the three
Kreisselmeier schemes (chapter 6) with the fitted exponential rates, the Lüders–Narendra state and
parameter errors with its Lyapunov function (chapter 5), the Kudva–Narendra identifier (section 4.3), and
the richness condition (a single sinusoid on a 3rd-order plant: the output error vanishes, the parameters
do not converge).  Chapter 4's identifier (4.2), minimal (4.14)-(4.18) and non-minimal (4.19) observers
and the Morgan–Narendra conditions (4.20)-(4.21) get three more figures (:func:`reproduce_chapter4`), and
:func:`comparison_study` measures the time to 1 % parameter error of the five adaptive laws on one plant
(notebook 03).

``reproduce(outdir)`` writes the PNGs and returns their paths.
"""

from __future__ import annotations

import os

import equinox as eqx
import jax
import jax.numpy as jnp
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
    """Write the chapter 4-6 figures as PNGs into ``outdir`` and return their paths (about a minute)."""
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
    paths += reproduce_chapter4(outdir)
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


# =========================================================================== chapter 4: identifier, minimal and
# non-minimal adaptive observers, Morgan–Narendra conditions, and the comparison of the five adaptive laws
#: Section 4.5: a 3rd-order plant y = (s² + 1.5s + 2)/((s + 1)(s² + s + 2)) u in the form (4.12), with a_1 = 2
#: and b_1 = 1 known and (a_2, a_3, b_2, b_3) unknown: two unknown parameters per channel (x_1 and u).  Filters
#: D(s) = R(s) = (s + 2)(s + 3), λ = λ_0 = 0.5; rich input sin 0.8t + sin 2.5t (4 spectral lines for 4
#: unknowns), poor input sin 0.8t alone (amplitudes (1, 0): same signal shape, so compiled runs are shared).
ADAPTIVE_3 = {
    "a": (2.0, 3.0, 2.0),
    "b": (1.0, 1.5, 2.0),
    "adapt": (False, True, True, False, True, True),
    "filter_poles": (-2.0, -3.0),
    "lam": 0.5,
    "amplitudes": (1.0, 1.0),
    "frequencies": (0.8, 2.5),
    "poor_amplitudes": (1.0, 0.0),
}
#: Section 4.2: αᵀ(t) K = b(t) with K = (1, −2, 0.5); α(t) = (1, sin t, c_1 cos 2t + c_2 sin t): c = (1, 0) is
#: persistently exciting, c = (0, 2) is not (α_3 = 2 α_2: the direction w = (0, 2, −1)/√5 is never excited).
IDENTIFIER_3 = {"K": (1.0, -2.0, 0.5), "rich": (1.0, 0.0), "poor": (0.0, 2.0)}
#: (4.20): the scalar plant ẋ_p = −x_p + 2u identified with all states accessible (K = 2, P = 1/4,
#: γ₁ = γ₂ = 4): u = sin t is rich (two spectral lines, two parameters), the step u = 1 is not.
SCALAR_420 = {"ap": -1.0, "bp": 2.0, "k": 2.0, "gamma": 4.0}


class IdentifierRegressor(eqx.Module):
    """α(t) = (1, sin t, c_1 cos 2t + c_2 sin t) of :data:`IDENTIFIER_3` (c is a leaf: rich and poor runs
    share one compilation)."""

    c: jax.Array

    def __init__(self, c):
        self.c = jnp.asarray(c, dtype=float)

    def __call__(self, t, u=None):
        return jnp.stack(
            [jnp.ones_like(t), jnp.sin(t), self.c[0] * jnp.cos(2 * t) + self.c[1] * jnp.sin(t)]
        )


def filtered_regressor_power(a, b, poles, amplitudes, frequencies):
    """Mean square of v = [s^{n−i}/D y; s^{n−i}/D u] (i = 1..n) in steady state, D with roots ``poles``,
    for y = (b_1 s^{n−1} + ...)/(s^n + a_1 s^{n−1} + ...) u and u = Σ A_k sin ω_k t (frequency response)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = a.shape[0]
    D = np.real(np.poly(np.asarray(poles))) if n > 1 else np.ones(1)
    power = np.zeros(2 * n)
    for A, w in zip(np.ravel(amplitudes), np.ravel(frequencies)):
        s = 1j * w
        G = np.polyval(b, s) / np.polyval(np.r_[1.0, a], s)
        basis = np.array([s ** (n - 1 - k) for k in range(n)]) / np.polyval(D, s)
        power += A**2 / 2 * np.abs(np.r_[basis * G, basis]) ** 2
    return power


def chapter4_gain(example, gamma):
    """Diagonal Γ = γ / mean(v_i²) for the minimal and non-minimal observers (same filters D = R)."""
    return gamma / filtered_regressor_power(
        example["a"], example["b"], example["filter_poles"], example["amplitudes"], example["frequencies"]
    )


def _known_start(example):
    """Initial (â, b̂): the true value where the parameter is known, zero where it is not."""
    adapt = np.asarray(example.get("adapt", (True,) * (2 * len(example["a"]))))
    n = len(example["a"])
    truth = np.r_[example["a"], example["b"]]
    start = np.where(adapt, 0.0, truth)
    return start[:n], start[n:]


def build_chapter4_observer(kind, example, gamma=5.0, G=None):
    """The minimal (``kind="minimal"``) or non-minimal (``"nonminimal"``) observer for an example, started at
    zero for the unknown parameters and at the truth for the known ones."""
    import jax.numpy as jnp

    import obsjax

    n = len(example["a"])
    G = chapter4_gain(example, gamma) if G is None else G
    a0, b0 = _known_start(example)
    adapt = example.get("adapt")
    if kind == "minimal":
        return obsjax.MinimalAdaptiveObserver(
            n, example["filter_poles"], example["lam"], jnp.asarray(G), a0=a0, b0=b0, adapt=adapt
        )
    if kind == "nonminimal":
        probe = obsjax.NonMinimalAdaptiveObserver(n, example["filter_poles"], example["lam"], 1.0)
        a0, b0 = probe.matching_point(jnp.asarray(a0), jnp.asarray(b0))
        return obsjax.NonMinimalAdaptiveObserver(
            n, example["filter_poles"], example["lam"], jnp.asarray(G), a0=a0, b0=b0, adapt=adapt
        )
    raise ValueError(f"`kind` must be 'minimal' or 'nonminimal', got {kind!r}.")


def simulate_chapter4(kind, example, gamma=5.0, G=None, amplitudes=None, t1=200.0, num=401, x0=None, **kw):
    """Simulate the minimal or non-minimal observer on an example (x̂(0) = x(0) = 0 by default);
    returns (ts, relative parameter error in the form (4.12), traj, obs)."""
    import jax.numpy as jnp

    import obsjax

    n = len(example["a"])
    obs = build_chapter4_observer(kind, example, gamma, G)
    plant = obsjax.kreisselmeier_form(example["a"], example["b"])
    amps = example["amplitudes"] if amplitudes is None else amplitudes
    u = obsjax.signals.multisine(amps, example["frequencies"])
    x0 = jnp.zeros(n) if x0 is None else jnp.asarray(x0)
    ts = jnp.linspace(0.0, t1, num)
    kw = {"rtol": 1e-8, "atol": 1e-10, "max_steps": 400_000, **kw}
    traj = obsjax.simulate(plant, obs, x0, x0, ts, u=u, **kw)
    a_hat, b_hat = obs.parameters(traj.z)
    err = relative_parameter_error(a_hat, b_hat, example["a"], example["b"])
    return np.asarray(ts), err, traj, obs


def simulate_identifier(which, gamma=1.0, t1=60.0, num=241, **kw):
    """The identifier (4.2) on :data:`IDENTIFIER_3` with the rich or poor regressor; returns
    (ts, K̃ (T, 3), traj, identifier)."""
    import jax.numpy as jnp

    import obsjax

    K = jnp.asarray(IDENTIFIER_3["K"])
    ident = obsjax.LeastSquaresIdentifier(3, IdentifierRegressor(IDENTIFIER_3[which]), Gamma=gamma)
    ts = jnp.linspace(0.0, t1, num)
    kw = {"rtol": 1e-10, "atol": 1e-12, "max_steps": 100_000, **kw}
    traj = obsjax.simulate(ident.plant(), ident, K, jnp.zeros(3), ts, **kw)
    return np.asarray(ts), np.asarray(traj.error), traj, ident


#: The inputs of :data:`SCALAR_420` as one sinusoid A sin(ωt + φ): rich u = sin t, poor u = sin(0·t + π/2) = 1
#: (one signal type, so both runs share a compilation).
SCALAR_420_INPUTS = {"rich": (1.0, 1.0, 0.0), "poor": (1.0, 0.0, np.pi / 2)}


class Scalar420Regressor(eqx.Module):
    """B(t) = −[√γ₁ x_p(t); √γ₂ u(t)] of (4.20) for :data:`SCALAR_420`, u = A sin(ωt + φ), x_p(0) = 0, with
    x_p in closed form (steady state through G(jω) = b_p/(jω − a_p), plus the transient e^{a_p t})."""

    amplitude: jax.Array
    omega: jax.Array
    phase: jax.Array

    def __init__(self, which):
        A, w, ph = SCALAR_420_INPUTS[which]
        self.amplitude, self.omega, self.phase = (jnp.asarray(v, dtype=float) for v in (A, w, ph))

    def _steady(self, t):
        ex = SCALAR_420
        G = ex["bp"] / (1j * self.omega - ex["ap"])
        return self.amplitude * jnp.abs(G) * jnp.sin(self.omega * t + self.phase + jnp.angle(G))

    def __call__(self, t):
        ex = SCALAR_420
        xp = self._steady(t) - self._steady(0.0) * jnp.exp(ex["ap"] * t)
        u = self.amplitude * jnp.sin(self.omega * t + self.phase)
        return -jnp.sqrt(ex["gamma"]) * jnp.stack([xp, u])


def simulate_420(which, t1=60.0, num=241):
    """The Kudva–Narendra identifier (4.4)-(4.7) of :data:`SCALAR_420`: its errors (e, φ, ψ) obey (4.20).
    Returns (ts, e, φ, ψ) with e = x_m − x_p, φ = A_m − A_p, ψ = B_m − B_p."""
    import obsjax

    ex = SCALAR_420
    plant = obsjax.LTI([[ex["ap"]]], [[ex["bp"]]], [[1.0]])
    k = ex["k"]
    # Γ⁻¹ P = γ with P = 1/(2k):  Γ = 1 / (2 k γ)
    obs = obsjax.KudvaNarendra(
        1, 1, K=[[-k]], Gamma1=1 / (2 * k * ex["gamma"]), Gamma2=1 / (2 * k * ex["gamma"]), Q=[[1.0]]
    )
    A, w, ph = SCALAR_420_INPUTS[which]
    u = obsjax.signals.multisine([A], [w], [ph])
    ts = jnp.linspace(0.0, t1, num)
    traj = obsjax.simulate(plant, obs, jnp.zeros(1), jnp.zeros(1), ts, u=u, rtol=1e-10, atol=1e-12)
    return (
        np.asarray(ts),
        np.asarray(traj.error[:, 0]),
        np.asarray(traj.z.Am[:, 0, 0]) - ex["ap"],
        np.asarray(traj.z.Bm[:, 0, 0]) - ex["bp"],
    )


# --------------------------------------------------------------------------- the comparison (notebook 03)
#: The five laws on one plant, y = (s + 1)/(s² + 2s + 2) u (:data:`KREISSELMEIER_2`), u = sin 0.7t + sin 2t,
#: every realisation started at rest (so all see the same y(t)) and every estimate at zero in its own
#: coordinates.  Filters: D = R = s + 1, λ = λ_0 = 1 (minimal, non-minimal); Λ = 0.5, λ_1 = 1 (Lüders–Narendra,
#: form (5.2)); K = −2I, Q = I (Kudva–Narendra, all states measured); F with eigenvalues {−2, −2}
#: (Kreisselmeier).
COMPARISON = {
    "a": (2.0, 2.0),
    "b": (1.0, 1.0),
    "filter_poles": (-1.0,),
    "lam": 1.0,
    "ln_lambdas": (1.0, 0.5),
    "kn_k": 2.0,
    "poles": (-2.0, -2.0),
    "amplitudes": (1.0, 1.0),
    "frequencies": (0.7, 2.0),
}


def luders_narendra_parameters(a, b, lambdas):
    """(a', b') of the form (5.2) with the known Λ = diag(−λ_2, ..., −λ_n) realising the transfer function
    (b_1 s^{n−1} + ...)/(s^n + a_1 s^{n−1} + ...) of the form (4.12)/(6.2).

    For (5.2), det(sI − A) = s Π − (a'_1 Π + Σ_{i≥2} a'_i Π_{≠i}) and the numerator is b'_1 Π + Σ b'_i Π_{≠i},
    Π = Π_{i≥2}(s + λ_i), Π_{≠i} the product without (s + λ_i): two linear systems in the basis (Π, Π_{≠i}).
    """
    a, b = np.asarray(a, float), np.asarray(b, float)
    lam = np.asarray(lambdas, float).reshape(-1)
    n = a.shape[0]
    lam = lam[1:] if lam.shape[0] == n else lam
    Pi = np.atleast_1d(np.poly(-lam))  # degree n − 1
    basis = [Pi] + [np.atleast_1d(np.poly(-np.delete(lam, i))) for i in range(n - 1)]
    Bmat = np.stack([np.pad(p, (n - p.shape[0], 0)) for p in basis], axis=1)  # (n coeffs, n)
    sPi_minus_den = np.polysub(np.polymul([1.0, 0.0], Pi), np.r_[1.0, a])[-n:]
    a_ln = np.linalg.solve(Bmat, np.pad(sPi_minus_den, (n - sPi_minus_den.shape[0], 0)))
    b_ln = np.linalg.solve(Bmat, b)
    return a_ln, b_ln


def _filter_power(signal_tf, poles, n, amplitudes, frequencies):
    """Mean square of s^{n−i}/D(s) applied to a signal with the given frequency response, i = 1..n."""
    D = np.real(np.poly(np.asarray(poles))) if len(poles) else np.ones(1)
    p = np.zeros(n)
    for A, w in zip(amplitudes, frequencies):
        s = 1j * w
        p += A**2 / 2 * np.abs(np.array([s ** (n - 1 - k) for k in range(n)]) / np.polyval(D, s)
                               * signal_tf(s)) ** 2
    return p


def comparison_observers(gamma):
    """The five laws on :data:`COMPARISON` with rates normalised by their regressors' mean squares, times γ.

    Returns {name: (plant, observer, truth-vector, parameter-extractor)}: the parameter error of each law is
    measured in its own coordinates (the transfer function's (a, b) for the minimal, non-minimal and
    Kreisselmeier observers, (5.2) for Lüders–Narendra, the entries of (A_p, B_p) for Kudva–Narendra).
    """
    import jax.numpy as jnp

    import obsjax

    ex = COMPARISON
    a, b = np.asarray(ex["a"]), np.asarray(ex["b"])
    n = a.shape[0]
    amps, freqs = ex["amplitudes"], ex["frequencies"]
    out = {}
    plant = obsjax.kreisselmeier_form(a, b)
    truth = np.r_[a, b]
    # Kudva–Narendra (4.4)-(4.7), all states measured: Γ⁻¹ P = γ / mean‖x‖², γ / mean u² (P = I/(2k))
    Ap, Bp = np.asarray(plant.A), np.asarray(plant.B)
    k = ex["kn_k"]
    xpow = 0.0
    for A_, w in zip(amps, freqs):
        xpow += A_**2 / 2 * np.sum(np.abs(np.linalg.solve(1j * w * np.eye(n) - Ap, Bp[:, 0])) ** 2) / n
    upow = sum(A_**2 / 2 for A_ in amps)
    kn = obsjax.KudvaNarendra(
        n, 1, K=-k * jnp.eye(n), Gamma1=xpow / (2 * k * gamma), Gamma2=upow / (2 * k * gamma),
        Q=jnp.eye(n),
    )
    out["Kudva–Narendra (4.6)-(4.7)"] = (
        obsjax.LTI(Ap, Bp, jnp.eye(n)), kn, np.r_[Ap.ravel(), Bp.ravel()],
        lambda z: np.concatenate([np.asarray(z.Am).reshape(len(z.Am), -1),
                                  np.asarray(z.Bm).reshape(len(z.Bm), -1)], axis=1),
    )
    # minimal (4.14)-(4.18) and non-minimal (4.19): same filters, Γ = γ / mean v²
    G = gamma / filtered_regressor_power(a, b, ex["filter_poles"], amps, freqs)
    mini = obsjax.MinimalAdaptiveObserver(n, ex["filter_poles"], ex["lam"], jnp.asarray(G))
    nonmin = obsjax.NonMinimalAdaptiveObserver(n, ex["filter_poles"], ex["lam"], jnp.asarray(G))
    a0, b0 = nonmin.matching_point(jnp.zeros(n), jnp.zeros(n))
    nonmin = obsjax.NonMinimalAdaptiveObserver(
        n, ex["filter_poles"], ex["lam"], jnp.asarray(G), a0=a0, b0=b0
    )

    def tf_params(o):
        return lambda z: np.concatenate([np.asarray(p) for p in o.parameters(z)], axis=1)

    out["minimal (4.14)-(4.18)"] = (plant, mini, truth, tf_params(mini))
    out["non-minimal (4.19)"] = (plant, nonmin, truth, tf_params(nonmin))
    # Lüders–Narendra (5.3)-(5.12) in the form (5.2)
    lam = ex["ln_lambdas"]
    a_ln, b_ln = luders_narendra_parameters(a, b, lam)
    c, d = luders_narendra_rates(
        {"a": a_ln, "b": b_ln, "lambdas": lam, "amplitudes": amps, "frequencies": freqs}, gamma
    )
    ln = obsjax.LudersNarendra(n, lam, jnp.asarray(c), jnp.asarray(d))
    out["Lüders–Narendra (5.12)"] = (
        obsjax.luders_narendra_form(a_ln, b_ln, lam), ln, np.r_[a_ln, b_ln],
        lambda z: np.concatenate([np.asarray(z.alpha), np.asarray(z.beta)], axis=1),
    )
    # Kreisselmeier (6.16) and (6.23)-(6.24)
    kex = {"a": ex["a"], "b": ex["b"], "poles": ex["poles"], "amplitudes": amps, "frequencies": freqs}
    for scheme, label, extra in (("gradient", "Kreisselmeier (6.16)", {}),
                                 ("integral", "Kreisselmeier (6.23), q = 0.2", {"q": 0.2})):
        kr = obsjax.Kreisselmeier(
            n, ex["poles"], jnp.asarray(kreisselmeier_gain(kex, gamma, scheme)), scheme=scheme, **extra
        )
        out[label] = (plant, kr, truth, tf_params(kr))
    return out


def comparison_study(gammas=(0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0), t1=300.0, num=601):
    """Time to 1 % parameter error of the five laws on :data:`COMPARISON`, for each normalised rate γ.

    Returns {"ts", "gammas", "t_1pct": {name: array over γ}, "errors": {name: (len(γ), num) array},
    "best": {name: (γ, t_1pct)}, "failed": {name: number of γ whose solve failed}}.  A failed solve (the
    explicit solver's step budget exhausted: high rates make the laws stiff) counts as NaN, never as a time.
    Each law compiles once (its rates are leaves).
    """
    import equinox as eqx
    import jax.numpy as jnp

    import obsjax

    ex = COMPARISON
    ts = jnp.linspace(0.0, t1, num)
    u = obsjax.signals.multisine(ex["amplitudes"], ex["frequencies"])

    @eqx.filter_jit
    def run(plant, obs):
        n = plant.n
        return obsjax.simulate(
            plant, obs, jnp.zeros(n), jnp.zeros(n), ts, u=u, rtol=1e-8, atol=1e-10, max_steps=400_000,
            throw=False,
        )

    t1pct, errors, failed = {}, {}, {}
    for gamma in gammas:
        for name, (plant, obs, truth, params) in comparison_observers(gamma).items():
            traj = run(plant, obs)
            ok = int(traj.status) == 0
            p = params(traj.z)
            err = np.linalg.norm(p - truth, axis=1) / np.linalg.norm(truth) if ok else np.full(num, np.nan)
            errors.setdefault(name, []).append(err)
            t1pct.setdefault(name, []).append(time_to(np.asarray(ts), err, 1e-2) if ok else np.nan)
            failed[name] = failed.get(name, 0) + (not ok)
    t1pct = {k: np.asarray(v) for k, v in t1pct.items()}
    best = {}
    for name, times in t1pct.items():
        i = int(np.nanargmin(np.where(np.isnan(times), np.inf, times)))
        best[name] = (float(gammas[i]), float(times[i]))
    return {
        "ts": np.asarray(ts),
        "gammas": np.asarray(gammas, float),
        "t_1pct": t1pct,
        "errors": {k: np.stack(v) for k, v in errors.items()},
        "best": best,
        "failed": failed,
    }


class SteadyStateRegressor(eqx.Module):
    """v(t) in steady state for u = Σ A_k sin ω_k t: v_i(t) = Σ_k A_k |H_i(jω_k)| sin(ω_k t + ∠H_i(jω_k)),
    H_i the transfer function from u to v_i (array leaves: one compilation per shape)."""

    amplitude: jax.Array  # (n_v, k)
    phase: jax.Array  # (n_v, k)
    frequencies: jax.Array  # (k,)

    def __call__(self, t):
        return jnp.sum(self.amplitude * jnp.sin(self.frequencies * t + self.phase), axis=-1)


def chapter4_regressor(example, amplitudes=None, gamma=5.0):
    """Γ_uu^{1/2} v_u(t) in steady state for the minimal/non-minimal observers of an example (the unknown
    parameters' rows only): the B(t) of (4.21)(ii) for their error system."""
    a, b = np.asarray(example["a"]), np.asarray(example["b"])
    n = a.shape[0]
    amps = np.asarray(example["amplitudes"] if amplitudes is None else amplitudes, float)
    freqs = np.asarray(example["frequencies"], float)
    D = np.real(np.poly(np.asarray(example["filter_poles"]))) if n > 1 else np.ones(1)
    H = []
    for w in freqs:
        s = 1j * w
        basis = np.array([s ** (n - 1 - k) for k in range(n)]) / np.polyval(D, s)
        H.append(np.r_[basis * np.polyval(b, s) / np.polyval(np.r_[1.0, a], s), basis])
    H = np.stack(H, axis=1)  # (2n, k)
    unknown = np.flatnonzero(example.get("adapt", (True,) * (2 * n)))
    scale = np.sqrt(chapter4_gain(example, gamma))[unknown, None]
    return SteadyStateRegressor(
        jnp.asarray(scale * np.abs(H[unknown]) * amps), jnp.asarray(np.angle(H[unknown])), jnp.asarray(freqs)
    )


# --------------------------------------------------------------------------- chapter 4 figures
def reproduce_chapter4(outdir: str) -> list[str]:
    """The figures of chapter 4's identifier (4.2), minimal and non-minimal observers (4.14)-(4.19) and the
    Morgan–Narendra conditions (4.20)-(4.21); returns the PNG paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import obsjax

    os.makedirs(outdir, exist_ok=True)
    paths = []

    # 1. The identifier (4.2): rich against poor α, the certified rate of (4.21)(i), the stalled direction.
    gamma, period = 1.0, 2 * np.pi
    runs = {w: simulate_identifier(w, gamma=gamma) for w in ("rich", "poor")}
    mns = {
        w: obsjax.analysis.morgan_narendra(
            lambda t, w=w: np.sqrt(gamma) * IdentifierRegressor(IDENTIFIER_3[w])(t), T=period,
            horizon=60.0, delta0=1.0,
        )
        for w in ("rich", "poor")
    }
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.2))
    K = np.asarray(IDENTIFIER_3["K"])
    for w, ls in (("rich", "-"), ("poor", "--")):
        ts, Kt, _, _ = runs[w]
        for i in range(3):
            axes[0].plot(ts, Kt[:, i] + K[i], ls, color=f"C{i}", label=f"K̂{i + 1} ({w} α)")
    for i in range(3):
        axes[0].axhline(K[i], color="k", lw=0.5, ls=":", label="true values" if i == 0 else None)
    axes[0].set(xlabel="time t (s)", ylabel="parameter estimates K̂", title="estimates K̂ of (4.2)")
    axes[0].legend(ncol=2, fontsize=8, loc="upper right")
    null = np.array([0.0, 2.0, -1.0]) / np.sqrt(5.0)
    for w, c in (("rich", "C0"), ("poor", "C3")):
        ts, Kt, _, _ = runs[w]
        mn = mns[w]
        axes[1].semilogy(ts, np.linalg.norm(Kt, axis=1) + 1e-16, color=c,
                         label=f"‖K̃‖, {w} α: a = {mn.a:.3g}, ε₀ = {mn.epsilon0:.3g}")
    ts, Kt, _, _ = runs["rich"]
    mn = mns["rich"]
    for sig, ls, lab in ((mn.rate, "k--", "σ from Φ of (4.21)(i)"), (mn.rate_bound, "k:", r"$\sigma_G$ from ∫ααᵀ")):
        bound = np.linalg.norm(Kt[0]) * np.exp(-sig * np.clip(ts - period, 0.0, None))
        axes[1].semilogy(ts, bound, ls, lw=0.8, label=r"$\|\tilde K(0)\|\,e^{-\sigma(t-T)}$" + f", {lab} = {sig:.3g}")
    axes[1].semilogy(ts, np.abs(runs["poor"][1] @ null) + 1e-16, "C3-.", label="|wᵀK̃|, poor α (constant)")
    axes[1].set(xlabel="time t (s)", ylabel="‖K̂ − K‖", ylim=(1e-9, 10),
                title="‖K̂ − K‖ and the Morgan–Narendra certificate")
    axes[1].legend(fontsize=8)
    for w, c in (("rich", "C0"), ("poor", "C3")):
        pw = mns[w].per_window
        axes[2].semilogy(np.arange(len(pw)), np.clip(pw[:, 0] / period, 1e-17, None), "o-", color=c,
                         label=r"$\lambda_{\min}$ ∫ααᵀ / T, " + w)
        axes[2].semilogy(np.arange(len(pw)), np.clip(pw[:, 2], 1e-17, None), "s--", color=c,
                         label=f"ε₀ (δ₀ = 1), {w}")
    axes[2].set(xlabel="window k (T = 2π s)", ylabel="per-window excitation", ylim=(1e-18, 10),
                title="richness per window, (4.21)(i)-(ii); ≤ 1e-15 is rounding (zero)")
    axes[2].legend(fontsize=8)
    axes[2].xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    fig.suptitle("Identification law (4.2): α = (1, sin t, cos 2t) rich, α = (1, sin t, 2 sin t) poor")
    fig.tight_layout()
    paths.append(_save(fig, outdir, "adaptive_ch4_identifier.png"))

    # 2. Minimal (4.14)-(4.18) and non-minimal (4.19) observers, 3rd order, two unknowns per channel.
    ex = ADAPTIVE_3
    res = {}
    for kind in ("minimal", "nonminimal"):
        for which, amps in (("rich", ex["amplitudes"]), ("poor", ex["poor_amplitudes"])):
            res[kind, which] = simulate_chapter4(kind, ex, gamma=5.0, amplitudes=amps)
    fig, axes = plt.subplots(2, 2, figsize=(13, 8.5))
    axes = axes.ravel()
    truth = np.r_[ex["a"], ex["b"]]
    names = ["a₂", "a₃", "b₂", "b₃"]
    unknown = np.flatnonzero(ex["adapt"])
    for kind, ls in (("minimal", "-"), ("nonminimal", "--")):
        ts, _, traj, obs = res[kind, "rich"]
        est = np.concatenate([np.asarray(p) for p in obs.parameters(traj.z)], axis=1)
        for j, i in enumerate(unknown):
            axes[0].plot(ts, est[:, i], ls, color=f"C{j}", label=f"{names[j]} ({kind})")
    for i in unknown:
        axes[0].axhline(truth[i], color="k", lw=0.5, ls=":", label="true values" if i == unknown[0] else None)
    axes[0].set(xlabel="time t (s)", ylabel="parameter estimates", title="unknown parameters, rich u")
    axes[0].legend(ncol=2, fontsize=8)
    for (kind, which), (ts, err, traj, obs) in res.items():
        ls = "-" if kind == "minimal" else "--"
        axes[1].semilogy(ts, err, ls, color="C0" if which == "rich" else "C3", label=f"{kind}, {which} u")
        if which == "rich":
            axes[2].semilogy(ts, np.asarray(traj.error_norm) + 1e-16, ls, label=kind)
    axes[1].set(xlabel="time t (s)", ylabel="‖(â, b̂) − (a, b)‖ / ‖(a, b)‖", title="parameter error")
    axes[1].legend(fontsize=8)
    axes[2].set(xlabel="time t (s)", ylabel="‖x̂ − x‖", title="state error (form (4.12)), rich u")
    axes[2].legend(fontsize=8)
    for kind, ls in (("minimal", "-"), ("nonminimal", "--")):
        ts, _, traj, obs = res[kind, "rich"]
        V = np.asarray(obs.lyapunov(traj.z, traj.y, np.asarray(ex["a"]), np.asarray(ex["b"])))
        axes[3].semilogy(ts, V, ls, label=f"{kind}: max increase {max(np.diff(V).max(), 0):.1e}")
    axes[3].set(xlabel="time t (s)", ylabel="V", title="V = ½ε₁² + ½θ̃ᵀΓ⁻¹θ̃ (x̂(0) = x(0), plant at rest)")
    axes[3].legend(fontsize=8)
    fig.suptitle(
        "Adaptive observers of section 4.5 on y = (s² + 1.5s + 2)/((s + 1)(s² + s + 2)) u: a₁, b₁ known;\n"
        "rich u = sin 0.8t + sin 2.5t, poor u = sin 0.8t; Γ = 5/diag(mean vvᵀ)"
    )
    fig.tight_layout()
    paths.append(_save(fig, outdir, "adaptive_ch4_minimal_nonminimal.png"))

    # 3. The scalar error system (4.20) and the Morgan–Narendra conditions (4.21).
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.2))
    for ax, which, title in ((axes[0], "rich", "u = sin t"), (axes[1], "poor", "u = 1")):
        ts, e, phi, psi = simulate_420(which)
        for sig_, lab in ((e, "|e|"), (phi, "|φ|"), (psi, "|ψ|")):
            ax.semilogy(ts, np.abs(sig_) + 1e-16, label=lab)
        ax.set(xlabel="time t (s)", ylabel="error magnitudes", title=f"(4.20), {title}", ylim=(1e-10, 10))
        ax.legend(fontsize=8)
    t0 = 20.0
    for which, c in (("rich", "C0"), ("poor", "C3")):
        mn = obsjax.analysis.morgan_narendra(
            Scalar420Regressor(which), T=2 * np.pi, horizon=8 * np.pi, t0=t0, delta0=1.0
        )
        pw = mn.per_window
        axes[2].semilogy(np.arange(len(pw)), np.clip(pw[:, 0] / (2 * np.pi), 1e-17, None), "o-", color=c,
                         label=f"{which}: a = {mn.a:.3g}, verdict {mn.uniform}")
        axes[2].semilogy(np.arange(len(pw)), np.clip(pw[:, 2], 1e-17, None), "s--", color=c,
                         label=f"{which}: ε₀ = {mn.epsilon0:.3g}")
    axes[2].set_ylim(1e-18, 10)
    axes[2].set(xlabel=f"window k (T = 2π s, from t = {t0:g} s)", ylabel="per-window excitation",
                title=r"B = −[√γ₁ $x_p$; √γ₂ u]: (4.21)(i) a and (ii) ε₀")
    axes[2].legend(fontsize=8)
    axes[2].xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    fig.suptitle(r"Scalar error system (4.20): $\dot x_p = -x_p + 2u$ identified by (4.4)-(4.7), K = 2, γ₁ = γ₂ = 4")
    fig.tight_layout()
    paths.append(_save(fig, outdir, "adaptive_ch4_morgan_narendra.png"))
    return paths
