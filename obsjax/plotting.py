"""Matplotlib figures for observer studies: error norms, states and estimates, tuning histories.

- `plot_error_norm`: ‖x̂(t) − x(t)‖ on a log scale, for one trajectory or as the median and 10–90 % band
  of a batch.
- `plot_states`: the true states (solid) and their estimates (dashed).
- `plot_tune_history`: the loss and the tuned parameters against the optimiser step of
  :func:`obsjax.tune`.

Monte-Carlo studies draw their own figure with :meth:`obsjax.MonteCarloResult.plot`.

Every axis is labelled; time is in seconds by default (``time_unit=`` changes the label, e.g. to ``""``
for the documents' dimensionless time).  matplotlib is imported only when a function is called.

Example:

```python
import jax.numpy as jnp
import matplotlib
matplotlib.use("Agg")
import obsjax
from obsjax.plotting import plot_error_norm

plant = obsjax.LTI(A=[[-2.0, 1.0], [0.0, -1.0]], B=[[0.0], [1.0]], C=[[1.0, 0.0]])
obs = obsjax.Luenberger.from_poles(plant, [-3.0, -3.0])
traj = obsjax.simulate(plant, obs, jnp.array([1.0, -1.0]), jnp.zeros(2), jnp.linspace(0.0, 5.0, 201))
ax = plot_error_norm(traj, label="poles {-3, -3}")
ax.figure.savefig("error_norm.png", dpi=120)
```
"""

from __future__ import annotations

import numpy as np

__all__ = ["plot_error_norm", "plot_states", "plot_tune_history"]


def _ax(ax):
    if ax is None:
        import matplotlib.pyplot as plt

        _, ax = plt.subplots(figsize=(6, 3.5))
    return ax


def _time_label(time_unit: str) -> str:
    return f"time t ({time_unit})" if time_unit else "time t"


def plot_error_norm(traj, ax=None, label=None, log=True, time_unit="s", **kw):
    """‖x̂(t) − x(t)‖ against t (log scale by default).

    **Arguments:**

    - `traj`: an :class:`obsjax.Trajectory`; a batch (leading axis) is drawn as its median with the
      10–90 % band shaded.
    - `ax`: the matplotlib axes to draw on (a new figure when ``None``).
    - `label`: legend label of the curve.
    - `log`: logarithmic y axis.
    - `time_unit`: unit of t shown on the x axis (``""`` for none).
    - `**kw`: passed to ``ax.plot``.

    **Returns:** the axes.
    """
    ax = _ax(ax)
    ts = np.asarray(traj.ts)
    e = np.linalg.norm(np.asarray(traj.error), axis=-1)
    if e.ndim == 1:
        ax.plot(ts, e, label=label, **kw)
    else:
        t = ts if ts.ndim == 1 else ts[0]
        lo, med, hi = np.quantile(e, [0.1, 0.5, 0.9], axis=0)
        band = None if label is None else f"{label}: 10–90 %"
        (line,) = ax.plot(t, med, label=None if label is None else f"{label}: median", **kw)
        ax.fill_between(t, lo, hi, alpha=0.25, color=line.get_color(), lw=0, label=band)
    if log:
        ax.set_yscale("log")
    ax.set_xlabel(_time_label(time_unit))
    ax.set_ylabel(r"estimation error $\|\hat x(t) - x(t)\|$")
    ax.grid(True, which="both", alpha=0.3)
    if label is not None:
        ax.legend()
    return ax


def plot_states(traj, ax=None, indices=None, time_unit="s"):
    """True states x_i(t) (solid) and their estimates x̂_i(t) (dashed, same colour).

    **Arguments:**

    - `traj`: one :class:`obsjax.Trajectory` (no batch axis).
    - `ax`: the matplotlib axes to draw on (a new figure when ``None``).
    - `indices`: the state components to draw (all when ``None``).
    - `time_unit`: unit of t shown on the x axis (``""`` for none).

    **Returns:** the axes.
    """
    ax = _ax(ax)
    ts = np.asarray(traj.ts)
    x, xh = np.asarray(traj.x), np.asarray(traj.xhat)
    idx = range(x.shape[-1]) if indices is None else indices
    for i in idx:
        (line,) = ax.plot(ts, x[:, i], label=rf"$x_{{{i + 1}}}$")
        if xh.shape == x.shape:
            ax.plot(ts, xh[:, i], "--", color=line.get_color(), label=rf"$\hat x_{{{i + 1}}}$")
    ax.set_xlabel(_time_label(time_unit))
    ax.set_ylabel("state and estimate")
    ax.legend(ncol=2)
    ax.grid(True, alpha=0.3)
    return ax


def plot_tune_history(result, axes=None, names=None):
    """Loss and tuned parameters against the optimiser step of :func:`obsjax.tune`.

    **Arguments:**

    - `result`: the :class:`obsjax.TuneResult`.
    - `axes`: 1 + (number of tuned leaves) matplotlib axes (a new row of panels when ``None``).
    - `names`: axis labels of the tuned leaves (with their units), in the order of ``where``.

    **Returns:** the axes.  A dotted vertical line marks the step with the lowest loss (the observer
    returned), named in the legend.
    """
    import matplotlib.pyplot as plt

    h = result.history
    params = h["params"]
    if axes is None:
        _, axes = plt.subplots(1, 1 + len(params), figsize=(4 * (1 + len(params)), 3))
    axes = np.atleast_1d(axes)
    axes[0].semilogy(h["loss"], label="loss")
    axes[0].axvline(h["best_step"], color="k", ls=":", lw=1, label="lowest loss (returned)")
    axes[0].set_xlabel("optimiser step")
    axes[0].set_ylabel("loss")
    axes[0].legend(fontsize=8)
    for i, p in enumerate(params):
        p = np.asarray(p).reshape(p.shape[0], -1)
        axes[i + 1].plot(np.real(p))
        axes[i + 1].set_xlabel("optimiser step")
        axes[i + 1].set_ylabel(names[i] if names else f"parameter {i}")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    return axes
