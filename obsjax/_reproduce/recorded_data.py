"""Observers on recorded data: a DC motor's velocity estimated from encoder and current samples.

The worked example of :func:`obsjax.estimate` (notebook 08 and ``obsjax reproduce data``).  A 3-state
electromechanical plant (a DC motor: angle θ, velocity ω, armature current i) is simulated by python-control
(not by obsjax) at 1 kHz under a load torque the observers do not know; it is sampled at 100 Hz by a
quantising encoder (4096 counts per revolution) and a noisy current sensor, both reporting one sample late,
and saved to CSV.  The unmeasured velocity is estimated from the CSV files by four observers (Luenberger,
Kalman–Bucy, continuous–discrete Kalman, Chen & Yen's least-squares observer), compared on the RMS error
against the hidden true velocity; gains are tuned on one experiment and validated on another.

``reproduce(outdir)`` writes the CSV files and the PNGs and returns the figures' paths; ``paper_values()``
checks the continuous–discrete filter against a NumPy discrete Kalman filter on the recorded data and that
tuning on one run improves the other; ``rms_table()`` is the table of RMS errors per observer.
"""

from __future__ import annotations

import functools
import os

import numpy as np

# DC motor (SI units): J ω̇ = −b ω + K i − τ_load,  L i̇ = −R i − K ω + V
J_M, B_M, K_M, R_M, L_M = 0.01, 0.05, 0.1, 2.0, 0.05
A = np.array([[0.0, 1.0, 0.0], [0.0, -B_M / J_M, K_M / J_M], [0.0, -K_M / L_M, -R_M / L_M]])
B = np.array([[0.0], [0.0], [1.0 / L_M]])
B_LOAD = np.array([[0.0], [-1.0 / J_M], [0.0]])
C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # encoder angle, current
FAST, RATE = 1000.0, 100.0  # simulation and sampling rates (Hz)
ENCODER_STEP = 2 * np.pi / 4096  # rad per count
CURRENT_SIGMA = 0.02  # A, current-sensor noise
LOAD_SIGMA = 0.01  # N·m, load-torque disturbance (low-pass filtered white noise)
DURATION = 6.0  # s per experiment
H = 1.0 / RATE


def _voltage(t, rng):
    """A random staircase (a new level every 0.4 s, ±8 V) plus a slow sine: rich enough to excite ω."""
    levels = rng.uniform(-8.0, 8.0, size=int(np.ceil(t[-1] / 0.4)) + 1)
    return levels[np.minimum((t / 0.4).astype(int), len(levels) - 1)] + 2.0 * np.sin(2 * np.pi * 0.3 * t)


def _load(t, rng):
    """Low-pass (5 Hz) filtered white noise, scaled to standard deviation LOAD_SIGMA."""
    import scipy.signal

    w = rng.normal(size=t.shape)
    b, a = scipy.signal.butter(2, 5.0 / (FAST / 2))
    tau = scipy.signal.lfilter(b, a, w)
    return LOAD_SIGMA * tau / np.std(tau)


def simulate_experiment(seed: int):
    """(true 1 kHz trajectory, 100 Hz recorded samples) of one experiment, simulated by python-control.

    Returns ``(t_fast, x_fast, t, samples)``: ``samples`` has the columns t, theta_enc, current, volts, and
    omega_tacho (a noisy tachometer, used for validation only)."""
    import control as ct

    rng = np.random.default_rng(seed)
    t_fast = np.arange(0.0, DURATION + 0.5 / FAST, 1.0 / FAST)
    V, tau = _voltage(t_fast, rng), _load(t_fast, rng)
    plant = ct.ss(A, np.hstack([B, B_LOAD]), np.eye(3), np.zeros((3, 2)))
    resp = ct.forced_response(plant, t_fast, np.vstack([V, tau]), X0=np.zeros(3))
    x = np.asarray(resp.states).T  # (N, 3)
    step = int(round(FAST / RATE))
    idx = np.arange(0, len(t_fast), step)
    t, xs = t_fast[idx], x[idx]
    delayed = np.vstack([xs[:1], xs[:-1]])  # both sensors report the previous sample
    theta = ENCODER_STEP * np.floor(delayed[:, 0] / ENCODER_STEP)
    current = delayed[:, 2] + CURRENT_SIGMA * rng.normal(size=len(t))
    tacho = xs[:, 1] + 0.5 * rng.normal(size=len(t))
    samples = np.column_stack([t, theta, current, V[idx], tacho])
    return t_fast, x, t, samples


CSV_HEADER = ["t", "theta_enc", "current", "volts", "omega_tacho"]


def write_csv(outdir: str, seed: int, name: str):
    """Simulate one experiment and write ``<name>.csv`` (the recording) and ``<name>_truth.csv`` (the hidden
    true state at the samples).  Returns the two paths."""
    _, x_fast, t, samples = simulate_experiment(seed)
    os.makedirs(outdir, exist_ok=True)
    rec = os.path.join(outdir, f"{name}.csv")
    np.savetxt(rec, samples, delimiter=",", header=",".join(CSV_HEADER), comments="", fmt="%.10g")
    truth = os.path.join(outdir, f"{name}_truth.csv")
    xs = x_fast[:: int(round(FAST / RATE))]
    np.savetxt(truth, np.column_stack([t, xs]), delimiter=",", header="t,theta,omega,current", comments="",
               fmt="%.12g")
    return rec, truth


def load(path, tacho=False):
    """The recording as :class:`obsjax.Measurements` (zero-order hold), the tachometer as validation state."""
    import obsjax

    extra = dict(x=["omega_tacho"], x_index=[1]) if tacho else {}
    return obsjax.Measurements.from_csv(path, t="t", y=["theta_enc", "current"], u=["volts"], **extra)


def observers():
    """The four observers with hand-chosen initial gains, by name."""
    import jax.numpy as jnp

    import obsjax

    model = obsjax.LTI(A, B, C)
    qd = np.diag([ENCODER_STEP**2 / 12, CURRENT_SIGMA**2])  # per-sample measurement covariances
    Qw = np.diag([1e-6, 10.0, 1e-2])  # a guess: the load torque enters ω
    P0 = np.diag([1e-4, 1.0, 1e-2])
    return {
        "Luenberger": obsjax.Luenberger.from_poles(model, jnp.array([-15.0, -20.0, -60.0])),
        # a continuous-time filter sees the held samples: its measurement noise must include the hold's
        # error (about (h·ω)² for θ), not only the sensors' covariances (with qd·h it trusts the staircase)
        "Kalman–Bucy": obsjax.KalmanBucy(model, Qw, np.diag([1e-5, 1e-3]) * H, P0),
        "continuous–discrete Kalman": obsjax.ContinuousDiscreteKalman(model, Qw, qd, P0),
        "least squares (Chen & Yen)": obsjax.LeastSquaresReset(model, gamma=1e4, p0=1.0, T=0.5),
    }


def _normalised_output_error(est):
    """Output prediction error with each output scaled by its measurement noise (encoder θ, current i)."""
    import obsjax

    return obsjax.losses.output_error(est, weight=np.array([12 / ENCODER_STEP**2, 1 / CURRENT_SIGMA**2]))


OUTPUT_LOSS = _normalised_output_error


def velocity_rms(est, truth):
    return float(np.sqrt(np.mean((np.asarray(est.xhat[:, 1]) - truth[:, 2]) ** 2)))


_LAST: dict = {}


def _latest(outdir):
    """The study of `outdir`, or the last one computed (``paper_values`` after ``reproduce``), or a new one
    in a temporary directory."""
    if outdir is not None:
        return study(outdir)
    if "study" in _LAST:
        return _LAST["study"]
    import tempfile

    return study(tempfile.mkdtemp(prefix="obsjax_recorded_data_"))


@functools.lru_cache(maxsize=2)
def study(outdir: str):
    """Everything the figures and tables need (computed once per output directory)."""
    import jax.numpy as jnp
    import optax

    import obsjax

    train_csv, _ = write_csv(outdir, 1, "train")
    val_csv, val_truth = write_csv(outdir, 2, "validation")
    train, val = load(train_csv, tacho=True), load(val_csv)
    truth_val = np.loadtxt(val_truth, delimiter=",", skiprows=1)
    obs = observers()
    xh0 = jnp.zeros(3)
    ests = {k: obsjax.estimate(o, val, xh0) for k, o in obs.items()}
    rms = {k: velocity_rms(e, truth_val) for k, e in ests.items()}
    kf = obs["continuous–discrete Kalman"]
    tuned_kf = obsjax.tune_on_data(kf, train, where=lambda o: o.Qw, xhat0=xh0, loss=OUTPUT_LOSS,
                                   optimizer=optax.adam(0.3), steps=12, progress=False)
    lb = obs["Luenberger"]
    tuned_lb = obsjax.tune_on_data(lb, train, where=lambda o: o.poles, xhat0=xh0,
                                   loss=obsjax.losses.state_error, optimizer=optax.adam(0.1), steps=12,
                                   progress=False)
    tuned = {"continuous–discrete Kalman": tuned_kf, "Luenberger": tuned_lb}
    ests_tuned = {k: obsjax.estimate(r.observer, val, xh0) for k, r in tuned.items()}
    rms_tuned = {k: velocity_rms(e, truth_val) for k, e in ests_tuned.items()}
    _LAST["study"] = dict(train=train, val=val, truth=truth_val, ests=ests, rms=rms, tuned=tuned,
                          ests_tuned=ests_tuned, rms_tuned=rms_tuned, outdir=outdir)
    return _LAST["study"]


def rms_table(outdir: str | None = None) -> str:
    """Markdown table: RMS velocity error (rad/s) on the validation run, per observer, initial and tuned."""
    s = _latest(outdir)
    lines = ["| observer | RMS velocity error, initial gains | after tuning on the training run |",
             "|---|---|---|"]
    for k, v in s["rms"].items():
        t = s["rms_tuned"].get(k)
        lines.append(f"| {k} | {v:.4f} | {'—' if t is None else f'{t:.4f}'} |")
    return "\n".join(lines)


def _save(fig, outdir, name):
    p = os.path.join(outdir, name)
    fig.tight_layout()
    fig.savefig(p, dpi=110)
    return p


def reproduce(outdir: str) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = study(outdir)
    val, truth = s["val"], s["truth"]
    t = np.asarray(val.ts)
    paths = []

    fig, ax = plt.subplots(3, 1, figsize=(9, 6.5), sharex=True)
    ax[0].step(t, np.asarray(val.y[:, 0]), where="post", lw=0.8, label="encoder θ (4096 counts/rev, 1 sample late)")
    ax[0].plot(truth[:, 0], truth[:, 1], "k--", lw=0.6, label="true θ")
    ax[0].set_ylabel("angle (rad)")
    ax[0].legend(fontsize=8)
    ax[1].plot(t, np.asarray(val.y[:, 1]), ".", ms=2, label="current sensor")
    ax[1].plot(truth[:, 0], truth[:, 3], "k-", lw=0.6, label="true i")
    ax[1].set_ylabel("current (A)")
    ax[1].legend(fontsize=8)
    ax[2].step(t, np.asarray(val.u[:, 0]), where="post", lw=0.8)
    ax[2].set_ylabel("voltage (V)")
    ax[2].set_xlabel("time t (s)")
    ax[0].set_title("Validation run: 100 Hz recording of a DC motor simulated by python-control at 1 kHz")
    paths.append(_save(fig, outdir, "recorded_data.png"))
    plt.close(fig)

    fig, ax = plt.subplots(1, 2, figsize=(11, 4), gridspec_kw={"width_ratios": [2, 1]})
    for k, e in s["ests"].items():
        for a in ax:
            a.plot(t, np.asarray(e.xhat[:, 1]), lw=0.9, label=f"{k} ({s['rms'][k]:.3f} rad/s RMS)")
    for a in ax:
        a.plot(truth[:, 0], truth[:, 2], "k--", lw=1.0, label="true ω (hidden)")
        a.set_xlabel("time t (s)")
    ax[0].set_ylabel("velocity ω (rad/s)")
    ax[0].legend(fontsize=7, loc="lower left")
    ax[0].set_title("Unmeasured velocity estimated from the CSV recording")
    ax[1].set_xlim(2.0, 2.8)
    ax[1].set_title("detail")
    lo, hi = truth[(truth[:, 0] > 2.0) & (truth[:, 0] < 2.8), 2].min(), truth[(truth[:, 0] > 2.0) & (truth[:, 0] < 2.8), 2].max()
    ax[1].set_ylim(lo - 0.3 * (hi - lo) - 0.5, hi + 0.3 * (hi - lo) + 0.5)
    paths.append(_save(fig, outdir, "velocity_estimates.png"))
    plt.close(fig)

    fig, ax = plt.subplots(1, 2, figsize=(11, 3.8))
    names = list(s["rms"])
    x = np.arange(len(names))
    ax[0].bar(x - 0.2, [s["rms"][k] for k in names], 0.4, label="initial gains")
    ax[0].bar(x + 0.2, [s["rms_tuned"].get(k, np.nan) for k in names], 0.4, label="tuned on the training run")
    ax[0].set_xticks(x, [n.replace(" (", "\n(").replace("continuous–discrete", "cont.–discrete") for n in names],
                     fontsize=7)
    ax[0].set_ylabel("RMS velocity error (rad/s)")
    ax[0].set_title("Validation run")
    ax[0].legend(fontsize=8)
    for k, r in s["tuned"].items():
        h = r.history["loss"]
        ax[1].semilogy(np.arange(len(h)), h / h[0], marker="o", ms=3, label=k)
    ax[1].set_xlabel("evaluation")
    ax[1].set_ylabel("training loss / initial")
    ax[1].set_title("tune_on_data on the training run")
    ax[1].legend(fontsize=8)
    paths.append(_save(fig, outdir, "tuning.png"))
    plt.close(fig)
    with open(os.path.join(outdir, "rms_table.md"), "w") as fh:
        fh.write(rms_table(outdir) + "\n")
    print(rms_table(outdir))
    return paths


def numpy_discrete_kalman(data, kf):
    """The discrete Kalman filter of the exactly discretised model (matrix exponential, ZOH), a NumPy loop."""
    import scipy.linalg

    n, p = B.shape
    y, u = np.asarray(data.y), np.asarray(data.u)
    ts = np.asarray(data.ts)
    Qw, Rv = np.asarray(kf.Qw), np.asarray(kf.Rv)
    x, P, xs = np.zeros(n), np.asarray(kf.P0).copy(), []
    for k in range(len(ts)):
        K = np.linalg.solve(C @ P @ C.T + Rv, C @ P).T
        x = x + K @ (y[k] - C @ x)
        IKC = np.eye(n) - K @ C
        P = IKC @ P @ IKC.T + K @ Rv @ K.T
        xs.append(x.copy())
        if k + 1 < len(ts):
            h = ts[k + 1] - ts[k]
            F = scipy.linalg.expm(np.block([[A, B], [np.zeros((p, n + p))]]) * h)
            V = scipy.linalg.expm(np.block([[-A, Qw], [np.zeros((n, n)), A.T]]) * h)
            Ad, Bd, Qd = F[:n, :n], F[:n, n:], V[n:, n:].T @ V[:n, n:]
            x, P = Ad @ x + Bd @ u[k], Ad @ P @ Ad.T + Qd
    return np.array(xs)


def paper_values(outdir: str | None = None):
    import diffrax
    import jax.numpy as jnp

    import obsjax

    from ._report import Row

    s = _latest(outdir)
    kf = observers()["continuous–discrete Kalman"]
    est = obsjax.estimate(kf, s["val"], jnp.zeros(3), solver=diffrax.Dopri8(), rtol=1e-12, atol=1e-13)
    ref = numpy_discrete_kalman(s["val"], kf)
    rows = [
        Row("validation run: max |ω̂| (continuous–discrete Kalman, exact ZOH propagation)",
            float(np.max(np.abs(ref[:, 1]))), float(np.max(np.abs(np.asarray(est.xhat[:, 1])))),
            source="NumPy discrete Kalman (expm)", rtol=0.0, atol=1e-8),
        Row("validation run: max |x̂ − x̂_NumPy| (all states, all samples)", 0.0,
            float(np.max(np.abs(np.asarray(est.xhat) - ref))), source="NumPy discrete Kalman (expm)",
            rtol=0.0, atol=1e-8),
    ]
    for k in s["rms_tuned"]:
        rows.append(Row(f"RMS velocity error on the validation run, {k} tuned on the training run",
                        s["rms"][k], s["rms_tuned"][k], source="initial gains", rtol=0.0, relation="<="))
    return rows
