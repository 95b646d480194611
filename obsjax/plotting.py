"""Matplotlib figures for observer studies (error norms, bands, gains, tuning histories).

Imported lazily: matplotlib is needed only when these functions are called.
"""

from __future__ import annotations

import numpy as np


def _ax(ax):
    if ax is None:
        import matplotlib.pyplot as plt

        _, ax = plt.subplots(figsize=(6, 3.5))
    return ax


def plot_error_norm(traj, ax=None, label=None, log=True, **kw):
    """‖x̃(t)‖ against t on a log scale (one trajectory, or the median and 10-90 % band of a batch)."""
    ax = _ax(ax)
    ts = np.asarray(traj.ts)
    e = np.linalg.norm(np.asarray(traj.error), axis=-1)
    if e.ndim == 1:
        ax.plot(ts, e, label=label, **kw)
    else:
        t = ts if ts.ndim == 1 else ts[0]
        lo, med, hi = np.quantile(e, [0.1, 0.5, 0.9], axis=0)
        (line,) = ax.plot(t, med, label=label, **kw)
        ax.fill_between(t, lo, hi, alpha=0.25, color=line.get_color())
    if log:
        ax.set_yscale("log")
    ax.set_xlabel("t")
    ax.set_ylabel("‖x̂ − x‖")
    ax.grid(True, which="both", alpha=0.3)
    if label is not None:
        ax.legend()
    return ax


def plot_states(traj, ax=None, indices=None):
    """True states (solid) and estimates (dashed)."""
    ax = _ax(ax)
    ts = np.asarray(traj.ts)
    x, xh = np.asarray(traj.x), np.asarray(traj.xhat)
    idx = range(x.shape[-1]) if indices is None else indices
    for i in idx:
        (line,) = ax.plot(ts, x[:, i], label=f"x{i + 1}")
        if xh.shape == x.shape:
            ax.plot(ts, xh[:, i], "--", color=line.get_color(), label=f"x̂{i + 1}")
    ax.set_xlabel("t")
    ax.legend(ncol=2)
    ax.grid(True, alpha=0.3)
    return ax


def plot_tune_history(result, axes=None, names=None):
    """Loss and tuned parameters against the step of :func:`obsjax.tune`."""
    import matplotlib.pyplot as plt

    h = result.history
    params = h["params"]
    if axes is None:
        _, axes = plt.subplots(1, 1 + len(params), figsize=(4 * (1 + len(params)), 3))
    axes = np.atleast_1d(axes)
    axes[0].semilogy(h["loss"])
    axes[0].axvline(h["best_step"], color="k", ls=":", lw=1)
    axes[0].set_xlabel("step")
    axes[0].set_ylabel("loss")
    for i, p in enumerate(params):
        p = np.asarray(p).reshape(p.shape[0], -1)
        axes[i + 1].plot(np.real(p))
        axes[i + 1].set_xlabel("step")
        axes[i + 1].set_ylabel(names[i] if names else f"parameter {i}")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    return axes
