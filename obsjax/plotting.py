"""Matplotlib figures for observer studies: error norms, states and estimates, tuning histories.

- `plot_error_norm`: ‖x̂(t) − x(t)‖ on a log scale, for one trajectory or as the median and 10–90 % band
  of a batch (over its successful members: failed ones are left out, with a warning and a note in the
  legend).
- `plot_states`: the true states (solid) and their estimates (dashed) of one trajectory.
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

import operator
import warnings

import numpy as np

__all__ = ["plot_error_norm", "plot_states", "plot_tune_history"]


def _ax(ax):
    if ax is None:
        import matplotlib.pyplot as plt

        _, ax = plt.subplots(figsize=(6, 3.5))
    return ax


def _time_label(time_unit: str) -> str:
    return f"time t ({time_unit})" if time_unit else "time t"


_STATUS_MEANING = {1: "solver failure", 2: "non-finite values"}


def _status_text(code: int) -> str:
    meaning = _STATUS_MEANING.get(code)
    return f"status {code}" + (f", {meaning}" if meaning else "")


def _status_of(traj, batch_shape: tuple):
    """The per-trajectory status of `traj` as a NumPy int array of shape `batch_shape`, or ``None`` when
    `traj` carries none (an object with ``ts`` and ``error`` only)."""
    st = getattr(traj, "status", None)
    if st is None:
        return None
    st = np.asarray(st)
    if st.shape != batch_shape:
        raise ValueError(
            f"`traj.status` must have shape {batch_shape} (one code per trajectory), got {st.shape}."
        )
    return st.astype(np.int64)


def plot_error_norm(traj, ax=None, label=None, log=True, time_unit="s", **kw):
    """‖x̂(t) − x(t)‖ against t (log scale by default).

    **Arguments:**

    - `traj`: an :class:`obsjax.Trajectory`; a batch (leading axis, as returned by
      :func:`obsjax.simulate_batch`) is drawn as its median with the 10–90 % band shaded.
    - `ax`: the matplotlib axes to draw on (a new figure when ``None``).
    - `label`: legend label of the curve.
    - `log`: logarithmic y axis.
    - `time_unit`: unit of t shown on the x axis (``""`` for none).
    - `**kw`: passed to ``ax.plot``.

    **Failed trajectories** (``simulate(..., throw=False)``: ``traj.status`` ≠ 0; their rows after the
    failure are not meaningful) are never drawn as if they had succeeded:

    - *a batch*: the median and the band are the quantiles over the successful members only, S = {b :
      status_b = 0 and ‖x̃_b(t)‖ finite at every save time}, i.e. at each save time t_k
      q_p(t_k) = quantile_p{‖x̃_b(t_k)‖ : b ∈ S}, p ∈ {0.1, 0.5, 0.9}.  When members are left out, a
      ``UserWarning`` names how many (and their statuses) and the legend says it
      (``"median of 8/9 (1 failed, left out)"``).  Without a ``status`` field, the members whose
      ‖x̃‖ is not finite at some save time are left out, with the same warning.  A batch with no
      successful member raises ``ValueError``.
    - *one trajectory*: a ``UserWarning`` names its status; the finite values up to the failure are
      drawn (matplotlib leaves out NaN and inf).  A failed trajectory with no finite value at all
      raises ``ValueError`` (there is nothing to draw).

    **Returns:** the axes.
    """
    ts = np.asarray(traj.ts)
    e = np.linalg.norm(np.asarray(traj.error), axis=-1)
    if e.ndim not in (1, 2):
        raise ValueError(
            "`traj` must be one trajectory (error of shape (T, n)) or a batch with one leading axis "
            f"((B, T, n)), got an error of shape {np.shape(traj.error)}."
        )
    status = _status_of(traj, e.shape[:-1])
    if e.ndim == 1:
        code = None if status is None else int(status)
        finite = np.isfinite(e)
        if (code is not None and code != 0) or not finite.all():
            what = (
                f"failed ({_status_text(code)})"
                if code
                else f"has a non-finite error at {int((~finite).sum())} of {e.size} save times"
            )
            if not finite.any():
                raise ValueError(
                    f"plot_error_norm: the trajectory {what} and its error is not finite at any save "
                    "time: there is nothing to draw."
                )
            warnings.warn(
                f"plot_error_norm: the trajectory {what}; only its finite values are drawn (last at "
                f"t = {ts[np.flatnonzero(finite)[-1]]:g}), and its rows after the failure are not "
                "meaningful.",
                UserWarning,
                stacklevel=2,
            )
        ax = _ax(ax)
        ax.plot(ts, e, label=label, **kw)
    else:
        t = ts if ts.ndim == 1 else ts[0]
        B = e.shape[0]
        ok = np.all(np.isfinite(e), axis=1)
        if status is not None:
            ok &= status == 0
        n_out = int(B - ok.sum())
        if n_out:
            if status is None:
                why = "have a non-finite error (the batch carries no status)"
            else:
                codes, counts = np.unique(status[~ok], return_counts=True)
                why = "failed (" + ", ".join(
                    f"{c} with {_status_text(int(k))}" for k, c in zip(codes, counts)
                ) + ")"
            if n_out == B:
                raise ValueError(
                    f"plot_error_norm: every one of the {B} members of the batch {why}: there are no "
                    "successful members to draw the median and band of."
                )
            warnings.warn(
                f"plot_error_norm: {n_out} of the {B} members of the batch {why} and are left out: "
                f"the median and the 10–90 % band are over the {B - n_out} successful members.",
                UserWarning,
                stacklevel=2,
            )
        lo, med, hi = np.quantile(e[ok], [0.1, 0.5, 0.9], axis=0)
        note = f" of {B - n_out}/{B} ({n_out} failed, left out)" if n_out else ""
        if label is None:
            med_label = f"median{note}" if n_out else None
            band = None
        else:
            med_label, band = f"{label}: median{note}", f"{label}: 10–90 %"
        ax = _ax(ax)
        (line,) = ax.plot(t, med, label=med_label, **kw)
        ax.fill_between(t, lo, hi, alpha=0.25, color=line.get_color(), lw=0, label=band)
        label = label if label is not None else med_label
    if log:
        ax.set_yscale("log")
    ax.set_xlabel(_time_label(time_unit))
    ax.set_ylabel(r"estimation error $\|\hat x(t) - x(t)\|$")
    ax.grid(True, which="both", alpha=0.3)
    if label is not None:
        ax.legend()
    return ax


def _state_indices(indices, n: int) -> list[int]:
    """`indices` as state indices in 0..n-1 (negative ones counted from the end, as in NumPy)."""
    if indices is None:
        return list(range(n))
    out = []
    for i in np.atleast_1d(np.asarray(indices, dtype=object)).tolist():
        try:
            if isinstance(i, (bool, np.bool_)) or np.asarray(i).dtype == bool:
                raise TypeError
            i = operator.index(i)
        except TypeError:
            raise ValueError(f"`indices` must hold integer state indices, got {indices!r}.") from None
        if not -n <= i < n:
            raise ValueError(
                f"`indices` holds {i}, but the state has n = {n} components: valid indices are "
                f"0..{n - 1} (or -{n}..-1 from the end)."
            )
        out.append(int(i) % n)
    return out


def plot_states(traj, ax=None, indices=None, time_unit="s"):
    """True states x_i(t) (solid) and their estimates x̂_i(t) (dashed, same colour).

    **Arguments:**

    - `traj`: one :class:`obsjax.Trajectory` (no batch axis: a batch, x of shape (B, T, n), raises
      ``ValueError``; draw one member, ``jax.tree_util.tree_map(lambda a: a[b], batch)``).
    - `ax`: the matplotlib axes to draw on (a new figure when ``None``).
    - `indices`: the state components to draw (all when ``None``), as integers in 0..n−1 or, counted
      from the end, −n..−1 (``-1`` is x_n).  Each curve is labelled with the component it draws,
      x_{i+1} for index i; an index out of range raises ``ValueError``.
    - `time_unit`: unit of t shown on the x axis (``""`` for none).

    A failed trajectory (``traj.status`` ≠ 0: its rows after the failure are not meaningful), or one
    whose drawn states or estimates are not all finite, is drawn with a ``UserWarning`` naming the
    status and the last save time with finite values (matplotlib leaves out NaN and inf).

    **Returns:** the axes.
    """
    ts = np.asarray(traj.ts)
    x, xh = np.asarray(traj.x), np.asarray(traj.xhat)
    if x.ndim != 2 or ts.ndim != 1:
        raise ValueError(
            "plot_states draws one trajectory, x of shape (T, n), but `traj` has x of shape "
            f"{x.shape}" + (
                f": a batch of {x.shape[0]} members on its leading (batch) axis 0. Draw one member, "
                "e.g. jax.tree_util.tree_map(lambda a: a[0], traj), or plot_error_norm for the batch."
                if x.ndim == 3
                else "."
            )
        )
    idx = _state_indices(indices, x.shape[-1])
    status = _status_of(traj, ())
    code = None if status is None else int(status)
    drawn = [x[:, idx]] + ([xh[:, idx]] if xh.shape == x.shape else [])
    finite_rows = np.all(np.isfinite(np.concatenate(drawn, axis=1)), axis=1)
    if code or not finite_rows.all():
        what = f"failed ({_status_text(code)})" if code else "holds non-finite states or estimates"
        last = (
            f"the last save time with finite values is t = {ts[np.flatnonzero(finite_rows)[-1]]:g}"
            if finite_rows.any()
            else "no save time has finite values"
        )
        warnings.warn(
            f"plot_states: the trajectory {what}: its rows after the failure are not meaningful "
            f"and non-finite values are not drawn ({last}).",
            UserWarning,
            stacklevel=2,
        )
    ax = _ax(ax)
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
