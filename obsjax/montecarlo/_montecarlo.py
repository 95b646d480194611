"""Monte-Carlo studies of an observer: chunked, vmapped, sharded over devices, resumable."""

from __future__ import annotations

import dataclasses
import inspect
import math
import os
import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

from .. import _trace_cache
from .._checks import as_float_array, runtime_checks_as_nan
from .._config import require_x64
from .._integrate import _masked, _validate
from .._integrate._schedule import reset_segments
from .._simulate import NONFINITE, SUCCESS, _check_ts, num_segments, simulate
from .._simulate_batch import simulate_batch, simulate_plants
from ._checkpoint import _read_chunk, write_chunk
from ._checkpoint import chunk_path as _chunk_path
from ._checkpoint import read_checkpoint as _resume
from ._fingerprint import fingerprint
from ..tuning._losses import cvar_level, tail_count
from ._streaming import DEFAULT_SKETCH_RTOL, LogHistogram

DEFAULT_QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)


# ----------------------------------------------------------------------------------------------------------
# Samplers
# ----------------------------------------------------------------------------------------------------------


def _n_positional(fn) -> int:
    """The number of *required* positional parameters of `fn` (99 for ``*args``): a parameter with a
    default (``def s(k, sigma=0.5)``) is the user's own setting, never the slot for x0."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return 1
    count = 0
    for p in sig.parameters.values():
        if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD):
            if p.default is p.empty:
                count += 1
        elif p.kind == p.VAR_POSITIONAL:
            return 99
    return count


def _real_draw(value, name):
    """A sampler's output as a float array; complex output is refused (its imaginary part would be
    dropped), at trace time, as ``simulate`` refuses a complex x0 or x̂0."""
    arr = jnp.asarray(value)
    if jnp.issubdtype(arr.dtype, jnp.complexfloating):
        raise ValueError(
            f"`{name}` must return a real (n,) array, got an array of dtype {arr.dtype} "
            "(complex values are not a state)."
        )
    return jnp.asarray(arr, dtype=float)


class _Fixed:
    """A constant 'sampler' (an array given in place of a callable); hashable through its bytes."""

    def __init__(self, value, name):
        arr = np.asarray(as_float_array(value, name))
        if np.iscomplexobj(arr):
            raise ValueError(
                f"`{name}` given as an array must be real, got an array of dtype {arr.dtype}."
            )
        if arr.ndim != 1:
            raise ValueError(
                f"`{name}` given as an array must be a vector (n,), got shape {arr.shape}."
            )
        self.value = arr
        self._key = (arr.shape, arr.tobytes())

    def __call__(self, key, *args):
        return jnp.asarray(self.value)

    def __hash__(self):
        return hash(self._key)

    def __eq__(self, other):
        return isinstance(other, _Fixed) and other._key == self._key


def _sampler(s, name):
    if s is None:
        raise ValueError(
            f"`{name}` is required: a callable key -> (n,) array, or a fixed (n,) array."
        )
    if callable(s):
        return s
    return _Fixed(s, name)


# ----------------------------------------------------------------------------------------------------------
# The result
# ----------------------------------------------------------------------------------------------------------


class _PerTrajectory(NamedTuple):
    error_norm: np.ndarray
    status: np.ndarray
    convergence_time: np.ndarray
    ise: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class MonteCarloResult:
    """Outcome of :func:`obsjax.monte_carlo` (host NumPy arrays; a plain container, not a pytree).

    - `ts`: (T,) save times.
    - `error_norm`: (N, T) ‖x̃(t)‖ of every completed trajectory (NaN rows for failed ones).
    - `status`: (N,) int, 0 = success, 1 = solver failure, 2 = non-finite values (see
      :func:`obsjax.simulate`); −1 marks trajectories not yet computed (an interrupted, resumable
      run). A row whose ‖x̃(t)‖ or ISE is not finite (an overflowing error) is reported with status
      2 here even if the solver reported success: it is a failure, never a statistic.
    - `quantiles`: the quantile levels of `bands`.
    - `bands`: (Q, T) quantiles of ‖x̃(t)‖ over the *successful* trajectories at each save time.
    - `error_norm_mean`: (T,) mean of ‖x̃(t)‖ over the successful trajectories.
    - `convergence_time`: (N,) time (relative to ``ts[0]``) after which ‖x̃‖ stays at or below the
      convergence threshold: the crossing of the threshold after the last save time above it,
      interpolated between that save time and the next one (log-linearly: exact for an exponential
      decay between two save times), so it is not quantised by the save grid; ``0`` if ‖x̃‖ is never
      above the threshold, ``inf`` if it is still above at the last save time, NaN for failures.
    - `ise`: (N,) ∫‖x̃‖² dt on the save grid (trapezoid), NaN for failures.
    - `conv_tol`, `conv_relative`: the convergence threshold (relative to ‖x̃(t0)‖ when ``conv_relative``).
    - `n`: requested number of trajectories; `n_done`: number computed so far (``complete`` when equal).
    - `elapsed`: wall-clock seconds spent computing in this call (excludes chunks loaded from a
      checkpoint); `n_computed`: trajectories computed in this call.
    - `keep`: ``"all"`` (the per-trajectory arrays are in memory) or ``"summary"`` (a streaming
      study: see below).
    - `sketch_rtol`: the relative accuracy α of the quantile sketches of a streaming study (None
      when ``keep="all"``).

    Failures are *counted* (`n_failed`, `failure_fraction`), never averaged into the statistics: the
    bands, convergence times, ISE and :meth:`summary` use the successful rows only (`ok`), so every
    statistic is finite whenever at least one trajectory succeeded.

    **Streaming results** (``monte_carlo(..., keep="summary")``).  The per-trajectory arrays
    `error_norm`, `status`, `convergence_time`, `ise` and the mask `ok` are not kept: reading one
    raises ``AttributeError`` naming what to do instead (:meth:`iter_chunks` reads them back from
    the checkpoint directory, chunk by chunk).  Everything else is available:

    - exact (equal to the in-memory result up to the order of floating-point sums): `n_done`,
      `n_failed`, `failure_fraction`, `converged_fraction`, `error_norm_mean`, the ``"n"``,
      ``"failed"``, ``"failure_fraction"``, ``"converged_fraction"`` and ``"ise_mean"`` entries of
      :meth:`summary`;
    - from relative-accuracy sketches (:class:`obsjax.montecarlo.LogHistogram`): `bands`,
      :meth:`band`, :meth:`convergence_quantiles`, the final-error and convergence-time quantiles
      and the ISE CVaR of :meth:`summary`, and :meth:`plot`.  Each such value v̂ satisfies
      |v̂ − v| ≤ `sketch_rtol`·|v| + floor against the value v of the in-memory study, floor being
      2.2e-308 (values below it count as zero) unless the sketch had to fold its lowest bins
      (:attr:`sketch_floor`).
    """

    ts: np.ndarray
    quantiles: tuple
    bands: np.ndarray
    error_norm_mean: np.ndarray
    conv_tol: float
    conv_relative: bool
    n: int
    n_done: int
    elapsed: float
    n_computed: int
    keep: str = "all"
    sketch_rtol: float | None = None
    _per_trajectory: _PerTrajectory | None = dataclasses.field(default=None, repr=False)
    _stream: Any = dataclasses.field(default=None, repr=False)
    _store: tuple | None = dataclasses.field(default=None, repr=False)

    # -- per-trajectory arrays (keep="all") ----------------------------------------------------------

    def _rows(self, name: str, field: str | None = None):
        if self._per_trajectory is None:
            raise AttributeError(
                f"MonteCarloResult.{name} is not available: this study ran with keep='summary' "
                "(streaming statistics; the per-trajectory results were not kept in memory). Read "
                "them back chunk by chunk with result.iter_chunks() (needs `checkpoint`), or run "
                "with keep='all'."
            )
        return getattr(self._per_trajectory, field or name)

    @property
    def error_norm(self) -> np.ndarray:
        return self._rows("error_norm")

    @property
    def status(self) -> np.ndarray:
        return self._rows("status")

    @property
    def convergence_time(self) -> np.ndarray:
        return self._rows("convergence_time")

    @property
    def ise(self) -> np.ndarray:
        return self._rows("ise")

    @property
    def ok(self) -> np.ndarray:
        """(N,) mask of the successful trajectories."""
        return self._rows("ok", "status") == 0

    # -- statistics (both modes) ----------------------------------------------------------------------

    @property
    def complete(self) -> bool:
        return self.n_done == self.n

    @property
    def n_failed(self) -> int:
        if self._stream is not None:
            return self._stream.n_failed
        return int(np.sum(self.status > 0))

    @property
    def failure_fraction(self) -> float:
        """Failed trajectories ÷ computed trajectories."""
        return self.n_failed / max(self.n_done, 1)

    @property
    def sketch_floor(self) -> float:
        """The absolute part of the sketches' error bound (0 for ``keep="all"``): 2.2e-308, or the
        lower edge of the lowest bin kept where a sketch folded its lowest bins."""
        if self._stream is None:
            return 0.0
        return self._stream.floor

    @property
    def converged_fraction(self) -> float:
        """Share of the successful trajectories that settle below the threshold within the horizon."""
        if self._stream is not None:
            return self._stream.converged_fraction
        ct = self.convergence_time[self.ok]
        return float(np.mean(np.isfinite(ct))) if ct.size else float("nan")

    @property
    def throughput(self) -> float:
        """Trajectories per second computed in this call."""
        return self.n_computed / self.elapsed if self.elapsed > 0 else float("nan")

    def band(self, q: float) -> np.ndarray:
        """The q-quantile of ‖x̃(t)‖ over successful trajectories, (T,)."""
        if q in self.quantiles:  # computed with the result (the same quantile of the same rows)
            return np.array(self.bands[self.quantiles.index(q)], copy=True)
        if self._stream is not None:
            return self._stream.norms.quantile((q,))[0]
        return _quantiles(self.error_norm[self.ok], (q,))[0]

    def convergence_quantiles(self, qs: Sequence[float] = (0.5, 0.95)) -> np.ndarray:
        """Quantiles of the convergence time over successful trajectories (``inf`` counts as slowest)."""
        if self._stream is not None:
            return self._stream.conv.quantile(qs, method="lower")[:, 0]
        ct = self.convergence_time[self.ok]
        if ct.size == 0:
            return np.full(len(qs), np.nan)
        return np.quantile(ct, qs, method="lower")

    def _final_quantiles(self, qs) -> np.ndarray:
        if self._stream is not None:
            return self._stream.norms.quantile(qs)[:, -1]
        fin = self.error_norm[self.ok, -1]
        return np.quantile(fin, qs) if fin.size else np.full(len(qs), np.nan)

    def _ise_mean_cvar(self, cvar_alpha: float):
        if self._stream is not None:
            st = self._stream
            k = tail_count(cvar_alpha, st.n_ok) if st.n_ok else 0
            mean = st.ise_sum / st.n_ok if st.n_ok else float("nan")
            return mean, (st.ise.top_mean(k) if k else float("nan"))
        ise = self.ise[self.ok]
        k = tail_count(cvar_alpha, ise.size) if ise.size else 0
        mean = float(np.mean(ise)) if ise.size else float("nan")
        return mean, (float(np.mean(np.sort(ise)[-k:])) if k else float("nan"))

    def summary(self, cvar_alpha: float = 0.95) -> dict:
        """Headline numbers: counts, final-error quantiles, convergence-time quantiles, ISE mean and CVaR
        at level `cvar_alpha` ∈ [0, 1) (the mean of the worst ⌈(1 − α) N⌉ ISEs of the successful
        trajectories), under the key ``"ise_cvar<100 α>"`` (``ise_cvar95``; ``ise_cvar99.5`` for 0.995)."""
        cvar_alpha = cvar_level(cvar_alpha)
        fin = self._final_quantiles((0.5, 0.95))
        cq = self.convergence_quantiles((0.5, 0.95))
        ise_mean, ise_cvar = self._ise_mean_cvar(cvar_alpha)
        return {
            "n": self.n_done,
            "failed": self.n_failed,
            "failure_fraction": self.failure_fraction,
            "final_median": float(fin[0]),
            "final_p95": float(fin[1]),
            "conv_median": float(cq[0]),
            "conv_p95": float(cq[1]),
            "converged_fraction": self.converged_fraction,
            "ise_mean": ise_mean,
            cvar_key(cvar_alpha): ise_cvar,
        }

    def iter_chunks(self):
        """The per-trajectory results of a checkpointed study, read back from its directory one
        chunk at a time (memory bounded by a chunk, also for ``keep="summary"``): yields
        ``(start, error_norm, status)``, the rows ``start, start + 1, …`` as `error_norm` and
        `status` hold them in memory (failed rows NaN, overflowing rows status 2).  Each chunk is
        verified (checksum, fingerprint, index) as on resume; a chunk missing or damaged since the
        study ran raises ``ValueError``.  Needs ``monte_carlo(..., checkpoint=...)``."""
        if self._store is None:
            raise ValueError(
                "iter_chunks() reads the checkpoint directory, but this study ran without "
                "`checkpoint`: pass checkpoint=<directory> to monte_carlo."
            )
        ckpt, fp, chunk, done = self._store
        T = self.ts.shape[0]
        for c in np.flatnonzero(done):
            lo, hi = int(c) * chunk, min((int(c) + 1) * chunk, self.n)
            path = _chunk_path(ckpt, int(c))
            en, st, why = _read_chunk(path, fp, int(c), hi - lo, T)
            if why is not None:
                raise ValueError(f"checkpoint file {path!r} cannot be read back: {why}.")
            norms, status, _, _ = _process_rows(self.ts, en, st, self.conv_tol, self.conv_relative)
            yield lo, norms, status

    def plot(self, axes=None, label: str | None = None, color=None, time_unit: str = "s"):
        """Quantile bands of ‖x̃(t)‖ (log scale: median, 25–75 % and 5–95 % shaded, or the outermost
        levels available) and the histogram of convergence times.  Returns the matplotlib figure.

        `time_unit` labels the time axes (``"s"`` by default; ``""`` for a dimensionless time); the
        error norm carries the unit of the state.

        The bands and the histogram are over the successful trajectories only; the title of the left
        panel gives the number of failed ones.  A result without any successful trajectory (every
        computed one failed, or none computed yet) raises ``ValueError`` saying so."""
        import matplotlib.pyplot as plt

        n_ok = self.n_done - self.n_failed
        if n_ok <= 0:
            why = (
                "no trajectory has been computed yet (an interrupted study: resume it)"
                if self.n_done == 0
                else f"every one of the {self.n_done} computed trajectories failed "
                f"(failed {self.n_failed}, {self.failure_fraction:.0%})"
            )
            raise ValueError(
                f"MonteCarloResult.plot: {why}, so there are no error bands or convergence times to "
                "draw; see n_failed and status."
            )
        if axes is None:
            fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
        else:
            fig = axes[0].figure
        ax0, ax1 = axes
        ts = self.ts
        qs = list(self.quantiles)
        color = color or "C0"
        pairs = [(qs[i], qs[-1 - i]) for i in range(len(qs) // 2)]
        for j, (lo, hi) in enumerate(pairs):
            ax0.fill_between(
                ts,
                self.bands[qs.index(lo)],
                self.bands[qs.index(hi)],
                color=color,
                alpha=0.15 + 0.15 * j,
                lw=0,
                label=None if label is not None else f"{lo:.0%}–{hi:.0%}",
            )
        if 0.5 in qs:
            ax0.plot(ts, self.bands[qs.index(0.5)], color=color, lw=1.8, label=label or "median")
        ax0.set_yscale("log")
        unit = f" ({time_unit})" if time_unit else ""
        ax0.set_xlabel(f"time t{unit}")
        ax0.set_ylabel(r"estimation error $\|\tilde x(t)\|$")
        ax0.set_title(f"N = {self.n_done}, failed {self.n_failed} ({self.failure_fraction:.2%})")
        ax0.legend(fontsize=8)
        if self._stream is not None:
            finite, weights = self._stream.conv.histogram()  # bin representatives and counts
        else:
            ct = self.convergence_time[self.ok]
            finite, weights = ct[np.isfinite(ct)], None
        if finite.size:
            n_fin = int(finite.size if weights is None else weights.sum())
            ax1.hist(
                finite,
                weights=weights,
                bins=min(50, max(5, int(np.sqrt(n_fin)))),
                color=color,
                alpha=0.6,
                label=label,
            )
        thr = f"{self.conv_tol:g}·" + r"$\|\tilde x(t_0)\|$" if self.conv_relative else f"{self.conv_tol:g}"
        ax1.set_xlabel(f"convergence time{unit}: " + r"$\|\tilde x\|$" + f" ≤ {thr} from then on")
        ax1.set_ylabel("trajectories per bin")
        ax1.set_title(f"not converged within horizon: {1 - self.converged_fraction:.2%}")
        fig.tight_layout()
        return fig

    def __repr__(self) -> str:
        s = self.summary()
        state = "" if self.complete else f", INCOMPLETE {self.n_done}/{self.n}"
        kept = "" if self.keep == "all" else f", streamed (sketch rtol {self.sketch_rtol:g})"
        return (
            f"MonteCarloResult(n={s['n']}{state}, failed={s['failed']} ({s['failure_fraction']:.2%}), "
            f"final ‖x̃‖ median={s['final_median']:.3e} p95={s['final_p95']:.3e}, "
            f"convergence time median={s['conv_median']:.3g} p95={s['conv_p95']:.3g}{kept})"
        )


def _quantiles(norms: np.ndarray, qs) -> np.ndarray:
    if norms.shape[0] == 0:
        return np.full((len(qs), norms.shape[1]), np.nan)
    return np.quantile(norms, qs, axis=0)


def _convergence_time(ts, norms, tol, relative):
    """Time after which every later norm is ≤ threshold: the threshold crossing after the last save
    time above it, interpolated (log-linearly where both norms are positive, else linearly) up to
    the next save time; 0 when no norm is above, inf when the last one is."""
    thr = tol * norms[:, :1] if relative else np.full((norms.shape[0], 1), float(tol))
    above = norms > thr
    T = ts.shape[0]
    any_above = above.any(axis=1)
    last = T - 1 - np.argmax(above[:, ::-1], axis=1)  # last save index above the threshold
    nxt = np.minimum(last + 1, T - 1)
    rows = np.arange(norms.shape[0])
    a, b, th = norms[rows, last], norms[rows, nxt], thr[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        frac_log = (np.log(a) - np.log(th)) / (np.log(a) - np.log(b))
        frac_lin = (a - th) / (a - b)
    frac = np.where((b > 0) & (th > 0), frac_log, frac_lin)
    frac = np.clip(np.nan_to_num(frac, nan=1.0), 0.0, 1.0)
    t_cross = ts[last] + frac * (ts[nxt] - ts[last]) - ts[0]
    out = np.where(last == T - 1, np.inf, t_cross)
    return np.where(any_above, out, 0.0)


def _trapz_sq(ts, norms):
    """∫ ‖x̃‖² dt per row by the trapezoidal rule, Σ_k w_k ‖x̃(t_k)‖² with w_k = (t_{k+1} − t_{k−1})/2
    (half steps at the ends): one pass over the (N, T) norms, no temporary of their size (a study's
    norms are tens of MB, and the first touch of every new page of such a temporary costs more than
    the arithmetic)."""
    ts = np.asarray(ts, dtype=float)
    dt = np.diff(ts)
    w = np.zeros(ts.shape[0])
    w[:-1] += 0.5 * dt
    w[1:] += 0.5 * dt
    with np.errstate(over="ignore", invalid="ignore"):
        return np.einsum("ij,ij,j->i", norms, norms, w)


def _rows_of(ok):
    """An index of the rows where `ok`: all of them as a slice (a view, no copy of the study's (N, T)
    arrays), else the mask."""
    return slice(None) if ok.all() else ok


def _process_rows(ts, error_norm, status, conv_tol, conv_relative):
    """Per-trajectory rows as a result holds them: (norms with failed rows NaN, status with
    overflowing rows re-labelled 2, convergence time, ISE), NaN for failures (and for rows not yet
    computed, status −1)."""
    norms = np.array(error_norm, dtype=float, copy=True)
    status = np.array(status, copy=True).astype(np.int32)
    ise_all = _trapz_sq(ts, norms)
    overflow = (status == SUCCESS) & ~(np.all(np.isfinite(norms), axis=1) & np.isfinite(ise_all))
    status[overflow] = NONFINITE  # the solver finished, the error did not stay finite
    ok = status == SUCCESS
    norms[~ok] = np.nan
    ct = np.full(status.shape, np.nan)
    ise = np.full(status.shape, np.nan)
    if ok.any():
        rows = _rows_of(ok)
        ct[rows] = _convergence_time(ts, norms[rows], conv_tol, conv_relative)
        ise[rows] = ise_all[rows]
    return norms, status, ct, ise


class _Streaming:
    """The streaming statistics of a study (``keep="summary"``), fed one chunk at a time: exact
    counts and sums, and relative-accuracy sketches for the quantiles."""

    def __init__(self, ts, conv_tol, conv_relative, rtol):
        self.ts = np.asarray(ts, dtype=float)
        self.conv_tol, self.conv_relative = conv_tol, conv_relative
        self.n_done = 0
        self.status_counts: dict[int, int] = {}
        self.n_ok = 0
        self.n_converged = 0
        self.norm_sum = np.zeros(self.ts.shape[0])
        self.ise_sum = 0.0
        self.norms = LogHistogram(self.ts.shape[0], rtol)
        self.conv = LogHistogram(1, rtol)
        self.ise = LogHistogram(1, rtol)

    def add(self, error_norm, status) -> None:
        norms, status, ct, ise = _process_rows(
            self.ts, error_norm, status, self.conv_tol, self.conv_relative
        )
        done = status >= 0
        self.n_done += int(done.sum())
        for code, cnt in zip(*np.unique(status[done], return_counts=True)):
            self.status_counts[int(code)] = self.status_counts.get(int(code), 0) + int(cnt)
        ok = status == 0
        if not ok.any():
            return
        self.n_ok += int(ok.sum())
        self.n_converged += int(np.isfinite(ct[ok]).sum())
        self.norm_sum += norms[ok].sum(axis=0)
        self.ise_sum += float(ise[ok].sum())
        self.norms.add(norms[ok])
        self.conv.add(ct[ok])
        self.ise.add(ise[ok])

    @property
    def n_failed(self) -> int:
        return int(sum(c for code, c in self.status_counts.items() if code > 0))

    @property
    def converged_fraction(self) -> float:
        return self.n_converged / self.n_ok if self.n_ok else float("nan")

    @property
    def floor(self) -> float:
        return max(float(np.finfo(np.float64).tiny), self.norms.floor, self.conv.floor, self.ise.floor)

    @property
    def mean(self) -> np.ndarray:
        if not self.n_ok:
            return np.full(self.ts.shape[0], np.nan)
        return self.norm_sum / self.n_ok


def _summarise_inputs(ts, error_norm, status, quantiles, conv_tol, n):
    """The arguments of :func:`summarise` checked and converted (``ValueError`` naming the argument):
    ts (T,) float, norms (N, T) float, status (N,) int32, the quantile levels, conv_tol, n."""
    ts = np.asarray(ts)
    if ts.dtype.kind not in "biuf":
        raise ValueError(f"`ts` must hold real save times, got an array of dtype {ts.dtype}.")
    ts = ts.astype(float)
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"`ts` must be a 1-D array of at least 2 save times, got shape {ts.shape}.")
    _validate.check_ts_values(ts)
    shape_n, shape_s = np.shape(error_norm), np.shape(status)
    if len(shape_n) != 2 or shape_s != (shape_n[0],) or shape_n[1] != ts.shape[0]:
        raise ValueError(
            f"`error_norm` must be (N, T) with T = len(ts) = {ts.shape[0]} and `status` (N,), got "
            f"{shape_n} and {shape_s}."
        )
    norms = np.asarray(error_norm)
    if norms.dtype.kind not in "biuf":
        raise ValueError(
            f"`error_norm` must hold real norms ‖x̃(t)‖ ≥ 0, got an array of dtype {norms.dtype}."
        )
    norms = norms.astype(float, copy=False)  # _process_rows copies it before writing
    st = np.asarray(status)
    if st.dtype.kind == "f":
        bad = ~np.isfinite(st) | (st != np.round(st))
        if bad.any():
            raise ValueError(
                "`status` must hold integer status codes, got "
                f"{st[bad][:3].tolist()} (at rows {np.flatnonzero(bad)[:3].tolist()})."
            )
    elif st.dtype.kind not in "iu":
        raise ValueError(f"`status` must hold integer status codes, got an array of dtype {st.dtype}.")
    bad = ~np.isin(st, (-1, SUCCESS, 1, NONFINITE))
    if bad.any():
        raise ValueError(
            "`status` codes must be 0 (success), 1 (solver failure), 2 (non-finite values) or −1 (not "
            f"computed), got {st[bad][:3].tolist()} (at rows {np.flatnonzero(bad)[:3].tolist()})."
        )
    st = st.astype(np.int32)
    neg = (st[:, None] == SUCCESS) & (norms < 0)
    if neg.any():
        r, k = (int(v[0]) for v in np.nonzero(neg))
        raise ValueError(
            f"`error_norm` must hold norms ≥ 0 where `status` is 0, got error_norm[{r}, {k}] = "
            f"{norms[r, k]}."
        )
    qs = tuple(float(q) for q in quantiles)
    if not qs or any(not 0.0 <= q <= 1.0 for q in qs) or list(qs) != sorted(qs):
        raise ValueError(f"`quantiles` must be increasing levels in [0, 1], got {quantiles!r}.")
    try:
        tol = float(conv_tol)
    except (TypeError, ValueError):
        raise ValueError(f"`conv_tol` must be a real number > 0, got {conv_tol!r}.") from None
    if not tol > 0:
        raise ValueError(f"`conv_tol` must be > 0, got {conv_tol}.")
    if n is None:
        n = st.shape[0]
    elif isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)) or n < st.shape[0]:
        raise ValueError(
            f"`n` (the requested number of trajectories) must be an integer ≥ the number of rows "
            f"N = {st.shape[0]}, got {n!r}."
        )
    return ts, norms, st, qs, conv_tol, int(n)


def summarise(
    ts,
    error_norm,
    status,
    *,
    quantiles=DEFAULT_QUANTILES,
    conv_tol=0.05,
    conv_relative=True,
    n=None,
    elapsed=0.0,
    n_computed=0,
) -> MonteCarloResult:
    """Build a :class:`MonteCarloResult` from per-trajectory error norms (N, T) and statuses (N,).

    **Arguments** (each checked; a bad one raises ``ValueError`` naming it):

    - `ts`: (T,) save times: real, finite, strictly increasing, T ≥ 2 (as :func:`obsjax.monte_carlo`).
    - `error_norm`: (N, T) ‖x̃_i(t_k)‖: real (a complex array is refused), ≥ 0 in every row whose
      status is 0 (a negative value is refused).  Rows of failed trajectories may hold anything (NaN,
      inf): they are replaced by NaN.
    - `status`: (N,) integer codes of :class:`obsjax.Trajectory`: 0 success, 1 solver failure, 2
      non-finite values, −1 not yet computed.  A float array is accepted only when its values are
      such integers (0.7 or NaN is refused); any other code is refused.
    - `quantiles`: increasing levels in [0, 1] of the bands.
    - `conv_tol`, `conv_relative`: the convergence threshold (> 0), as in :func:`obsjax.monte_carlo`.
    - `n`: the requested number of trajectories, an integer ≥ N (default N; ``complete`` when all N
      rows are computed and n = N).
    - `elapsed`, `n_computed`: wall-clock seconds and trajectories computed, for the throughput.

    Defence in depth: a row with status 0 whose norms or ISE are not finite (an overflowing ‖x̃‖) is
    re-labelled status 2 (non-finite) and counted as failed; the statistics use the other rows only.
    """
    ts, norms, status, quantiles, conv_tol, n = _summarise_inputs(
        ts, error_norm, status, quantiles, conv_tol, n
    )
    norms, status, ct, ise = _process_rows(ts, norms, status, conv_tol, conv_relative)
    ok = status == 0
    good = norms[_rows_of(ok)]
    mean = np.mean(good, axis=0) if ok.any() else np.full(ts.shape[0], np.nan)
    return MonteCarloResult(
        ts=ts,
        quantiles=quantiles,
        bands=_quantiles(good, quantiles),
        error_norm_mean=mean,
        conv_tol=float(conv_tol),
        conv_relative=bool(conv_relative),
        n=n,
        n_done=int((status >= 0).sum()),
        elapsed=float(elapsed),
        n_computed=int(n_computed),
        _per_trajectory=_PerTrajectory(norms, status, ct, ise),
    )


def _streamed_result(acc: _Streaming, quantiles, n, elapsed, n_computed, store, rtol):
    """The :class:`MonteCarloResult` of a streaming study."""
    return MonteCarloResult(
        ts=acc.ts,
        quantiles=tuple(float(q) for q in quantiles),
        bands=acc.norms.quantile(quantiles),
        error_norm_mean=acc.mean,
        conv_tol=float(acc.conv_tol),
        conv_relative=bool(acc.conv_relative),
        n=int(n),
        n_done=acc.n_done,
        elapsed=float(elapsed),
        n_computed=int(n_computed),
        keep="summary",
        sketch_rtol=float(rtol),
        _stream=acc,
        _store=store,
    )


# ----------------------------------------------------------------------------------------------------------
# The batched kernel: one chunk of trajectories (vmap), sharded across a device mesh with shard_map
# ----------------------------------------------------------------------------------------------------------


class _Config(eqx.Module):
    """Everything static about a study (hashable: the jit cache key of the chunk kernel)."""

    static: object
    ts: tuple
    x0_sampler: Callable
    xhat0_sampler: Callable
    xhat0_takes_x0: bool
    param_sampler: Callable | None
    sim_kwargs: tuple
    max_segments: int | None
    key_impl: str | None
    mesh: object
    lockstep: bool
    masked: bool  # independent steps on the masked adaptive Runge–Kutta loop (simulate_batch(lockstep=False))
    # content fingerprint of the samplers and the static part: the compiled kernels are keyed on this
    # config, and a sampler that reads a global (or a settings module) changed since the last call must
    # be traced again, not served from the kernel compiled with the old value
    content: str = ""


def _draw(dyn, cfg: _Config, key, i):
    """Trajectory i's plant, initial state, initial estimate and noise key, all from fold_in(key, i)."""
    plant, observer, noise, _ = eqx.combine(dyn, cfg.static)
    k = jr.fold_in(key, i)
    kx, kh, kn, kp = jr.split(k, 4)
    if cfg.param_sampler is not None:
        plant = cfg.param_sampler(kp, plant)
    x0 = _real_draw(cfg.x0_sampler(kx), "x0_sampler")
    xhat0 = cfg.xhat0_sampler(kh, x0) if cfg.xhat0_takes_x0 else cfg.xhat0_sampler(kh)
    return plant, x0, _real_draw(xhat0, "xhat0_sampler"), kn


def _one(dyn, cfg: _Config, key, i):
    _, observer, noise, sim_kwargs = eqx.combine(dyn, cfg.static)
    plant, x0, xhat0, kn = _draw(dyn, cfg, key, i)
    traj = simulate(
        plant,
        observer,
        x0,
        xhat0,
        np.asarray(cfg.ts),
        noise=noise,
        key=kn if noise is not None else None,
        throw=False,
        max_segments=cfg.max_segments,
        **dict(sim_kwargs),
    )
    return traj.error_norm, traj.status


def _batch(dyn, cfg: _Config, key, idx, lockstep: bool):
    """One shard's members as one ``simulate_batch``: in lock step, or each with its own steps (the masked
    adaptive Runge–Kutta loop where the problem allows it, else ``jax.vmap(simulate)``)."""
    plant, observer, noise, sim_kwargs = eqx.combine(dyn, cfg.static)
    kw = dict(noise=noise, throw=False, max_segments=cfg.max_segments, **dict(sim_kwargs))
    ts = np.asarray(cfg.ts)
    if cfg.param_sampler is not None:  # a plant per member (never in lock step)
        plants, x0s, xhat0s, kns = eqx.filter_vmap(lambda i: _draw(dyn, cfg, key, i))(idx)
        traj = simulate_plants(plants, observer, x0s, xhat0s, ts, keys=kns if noise is not None else None, **kw)
    else:
        x0s, xhat0s, kns = jax.vmap(lambda i: _draw(dyn, cfg, key, i)[1:])(idx)
        traj = simulate_batch(
            plant, observer, x0s, xhat0s, ts, keys=kns if noise is not None else None, lockstep=lockstep, **kw
        )
    return traj.error_norm, traj.status


def _wrap_key(key_data, impl):
    return jr.wrap_key_data(key_data) if impl is None else jr.wrap_key_data(key_data, impl=impl)


@eqx.filter_jit
def _chunk_kernel(dyn, key_data, idx, cfg: _Config):
    def local(d, kd, ii):
        key = _wrap_key(kd, cfg.key_impl)
        if cfg.lockstep or cfg.masked:
            return _batch(d, cfg, key, ii, cfg.lockstep)
        return jax.vmap(lambda i: _one(d, cfg, key, i))(ii)

    if cfg.mesh is None:
        return local(dyn, key_data, idx)
    from jax.sharding import PartitionSpec as P

    # Each device integrates its own slice: no collective inside the adaptive while loops, so a shard
    # waits only for its own slowest trajectory (automatic sharding of the vmapped solve would synchronise
    # the batch at every step).
    sharded = jax.shard_map(
        local,
        mesh=cfg.mesh,
        in_specs=(P(), P(), P("batch")),
        out_specs=(P("batch"), P("batch")),
        check_vma=False,
    )
    return sharded(dyn, key_data, idx)


# The same kernel, its traced program saved across processes when the trace cache is on (the ``obsjax``
# command; see obsjax/_trace_cache.py; a mesh enters the key by its axes and devices).
_chunk_kernel_saved = _trace_cache.filter_jit(_chunk_kernel.__wrapped__, fast_compile=True)


def _is_hashable(v) -> bool:
    try:
        hash(v)
    except TypeError:
        return False
    return True


def _hashable_kwargs(kw: dict) -> tuple:
    items = []
    for k, v in sorted(kw.items()):
        if not _is_hashable(v):
            raise ValueError(
                f"`simulate_kwargs[{k!r}]` must be hashable once its arrays are taken out (a number, a diffrax "
                f"solver, an eqx.Module such as obsjax.signals.multisine(...)), got {type(v).__name__}."
            )
        items.append((k, v))
    return tuple(items)


def _study_fingerprint(study_id, **parts) -> str:
    """The content fingerprint of a study (see ``_fingerprint``); refuses what it cannot hash
    unless the study is named by `study_id`."""
    fp, opaque = fingerprint(dict(parts, study_id=study_id))
    if opaque and study_id is None:
        listed = "; ".join(opaque[:5]) + ("; ..." if len(opaque) > 5 else "")
        raise ValueError(
            "monte_carlo cannot fingerprint everything that determines this study, so a checkpoint "
            f"could be reused by another study without notice: {listed}. Pass `study_id` (a name "
            "you change whenever any of these changes) to checkpoint it anyway, or make the object "
            "hashable by content (a dataclass / eqx.Module, a function, an array)."
        )
    return fp


def _broadcast_from_lead(tree):
    """Process 0's values of a pytree of host arrays, on every process (a collective: all must call it)."""
    from jax.experimental import multihost_utils

    return multihost_utils.broadcast_one_to_all(tree)


def _resolve_devices(devices):
    """The devices of a study: ``None`` (all of ``jax.devices()``), a positive integer (the first that
    many), or a sequence of distinct ``jax.Device``; anything else raises ``ValueError`` naming
    `devices`."""
    if devices is None:
        return list(jax.devices())
    if isinstance(devices, (bool, np.bool_)):
        raise ValueError(
            f"`devices` must be None, a positive integer number of devices or a list of devices, got "
            f"the boolean {devices!r}."
        )
    if isinstance(devices, (int, np.integer)):
        all_devs = jax.devices()
        if not 1 <= devices <= len(all_devs):
            raise ValueError(
                f"`devices` asks for {devices} devices, but {len(all_devs)} are available."
            )
        return list(all_devs[: int(devices)])
    if isinstance(devices, (str, bytes)) or not hasattr(devices, "__iter__"):
        raise ValueError(
            f"`devices` must be None, a positive integer number of devices or a list of devices, got "
            f"{devices!r} ({type(devices).__name__})."
        )
    devices = list(devices)
    if not devices:
        raise ValueError("`devices` must name at least one device.")
    bad = [d for d in devices if not isinstance(d, jax.Device)]
    if bad:
        raise ValueError(
            f"`devices` must hold jax devices (from jax.devices()), got {bad[0]!r} "
            f"({type(bad[0]).__name__})."
        )
    seen: set = set()
    dups = [d for d in devices if d in seen or seen.add(d)]
    if dups:
        raise ValueError(
            f"`devices` names {dups[0]} more than once: each device of the mesh must be distinct "
            f"(got {devices})."
        )
    return devices


def monte_carlo(
    plant,
    observer,
    key,
    n,
    *,
    x0_sampler,
    xhat0_sampler,
    ts,
    noise=None,
    param_sampler=None,
    chunk_size=1024,
    checkpoint: str | os.PathLike | None = None,
    devices=None,
    quantiles=DEFAULT_QUANTILES,
    conv_tol=0.05,
    conv_relative=True,
    progress=True,
    max_chunks=None,
    simulate_kwargs=None,
    lockstep=False,
    study_id: str | None = None,
    keep: str = "all",
    sketch_rtol: float = DEFAULT_SKETCH_RTOL,
) -> MonteCarloResult:
    """Monte-Carlo study of an observer: N trajectories with random initial states, initial estimates,
    measurement noise and (optionally) plant parameters.

    Trajectory i draws everything from ``fold_in(key, i)`` (split into keys for x0, x̂0, the noise and the
    plant parameters), so its data do not depend on the chunk size, the number of devices or on
    interruptions: a sharded, chunked or resumed study solves the same problems as a single uninterrupted
    one, and gives the same numbers to the solver's accuracy.  Bit for bit only where the solve is
    insensitive to rounding: the batched solve's arithmetic depends at rounding level on how many members
    a device integrates together, and adaptive steps can amplify that to the tolerance's order.  With
    ``BandLimitedNoise`` and adaptive steps (whose error is 10²–10⁴ × `rtol` at the noise's kinks, see
    :mod:`obsjax.noise`), chunk sizes 1 and 2 differed by 7e-4 relative at the default rtol 1e-6; fixed
    steps whose grid holds the noise's nodes give rounding-level agreement.

    **Execution.**  The N trajectories are processed in chunks of ``chunk_size`` (device memory stays
    bounded by one chunk; the host keeps only ‖x̃(t)‖ on the save grid, N × T floats, so use a coarse
    ``ts`` for N = 10⁶, or ``keep="summary"`` beyond).  Within a chunk the trajectories are vmapped; with several devices the chunk is
    split across a 1-D device mesh with ``jax.shard_map``, each device running its own vmapped adaptive
    solve, so that a shard waits only for its own slowest trajectory (automatic sharding of a vmapped
    adaptive solve would synchronise every step of the while loop across devices).  One compiled kernel
    serves every chunk (the last one is padded) and every later study with the same structure, whatever
    the gain values.  A tqdm bar runs over the chunks.

    **Checkpoints.**  With ``checkpoint=<directory>``, each finished chunk is written there as
    ``chunk_<k>.npz`` beside a ``meta.json``.  Calling ``monte_carlo`` again with the same study
    loads the finished chunks and computes only the rest; ``max_chunks`` bounds the chunks computed
    in one call (a time-boxed run; the result then has ``complete == False``).  What a checkpoint
    guarantees:

    - *It is never mixed with another study.*  ``meta.json`` and every chunk carry a SHA-256
      fingerprint of everything that determines the result, by content: the plant, observer and
      noise model field by field (array leaves and static fields, such as a noise grid ``dt``), the
      samplers' and plant callables' bytecode, closure values, default arguments and the globals
      they read (recursively), the methods of user-defined classes, ``simulate_kwargs``, ``ts``, the
      key, N, the chunk size, the number of devices of a lock-step study and the Python, JAX, NumPy,
      SciPy, diffrax, equinox, lineax, optax and obsjax versions.  A directory or a chunk of a
      different study raises ``ValueError``.  An object that cannot be hashed by content (e.g. a
      ``numpy.random.Generator`` read by a sampler) is refused with its path, unless the study is
      named by ``study_id``, which then enters the fingerprint (change it whenever such an object
      changes).
    - *Files are whole or absent.*  Every file is written to a temporary name, flushed to disk and
      renamed (``os.replace``), and carries a checksum of its content.
    - *Damage is named and repaired.*  A chunk that cannot be read, fails its checksum or sits under
      another chunk's name is named in a :class:`obsjax.montecarlo.CheckpointWarning` and
      recomputed; a damaged ``meta.json`` is named likewise and rewritten once every chunk present
      has been verified to carry this study's fingerprint.  A checkpoint written by an earlier
      format is refused.

    **Streaming** (``keep="summary"``): studies larger than memory.  Each chunk is folded into
    streaming statistics as soon as it is computed (or loaded from the checkpoint) and then dropped,
    so host memory stays bounded by one chunk and the statistics, whatever N: exact counts and sums
    (failures, the converged fraction, the mean of ‖x̃(t)‖ and of the ISE) and, for the quantiles
    (the bands, the convergence-time quantiles, the final-error quantiles and the ISE CVaR of
    :meth:`MonteCarloResult.summary`), logarithmic histograms with relative accuracy
    ``sketch_rtol`` = α (:class:`obsjax.montecarlo.LogHistogram`): every such value is within
    α·|v| + 2.2e-308 of the in-memory study's.  The per-trajectory results are not kept in memory:
    with ``checkpoint`` they are on disk, in the checkpoint's chunk files (the same files, the same
    fingerprint, so a checkpoint written by either mode is resumed by either), and
    :meth:`MonteCarloResult.iter_chunks` reads them back chunk by chunk; without ``checkpoint`` they
    are discarded.  Reading a per-trajectory field of a streaming result (`error_norm`, `status`,
    `convergence_time`, `ise`, `ok`) raises ``AttributeError``.  A streaming study resumes like
    any other: the finished chunks are read back one at a time and folded in.

    **Several hosts.**  Call ``jax.distributed.initialize(coordinator_address, num_processes,
    process_id)`` in every process before anything else touches JAX (on CPU the cross-process
    collectives are gloo's, ``jax_cpu_collectives_implementation``, the default).  ``jax.devices()`` then
    lists the devices of every process and the mesh spans them.  Every process runs the same script with
    the same arguments; each process feeds the index slices of its own devices, each device computes its
    slice of each chunk, and the per-trajectory results are gathered to every process
    (``process_allgather``) before the host-side statistics, so every process returns the same result.
    Process 0 alone reads and writes the ``checkpoint`` directory and shows the progress bar; on resume it
    sends the list of finished chunks and their results to the other processes, so the directory needs
    to exist only on process 0's file system.  A mesh of several devices must include a device of every
    process.  Tested with two processes on one machine (``benchmarks/multihost_local.py``): the result
    equals the single-process one to 1e-12, and an interrupted study resumes.

    **Arguments:**

    - `plant`: the true plant (the truth; the observer carries its own model).
    - `observer`: any :class:`obsjax.AbstractObserver`.
    - `key`: a JAX PRNG key.
    - `n`: number of trajectories.
    - `x0_sampler`: ``key -> (n_x,)`` initial plant state (or a fixed array).  Real: a complex
      output (or fixed array) is refused with a ``ValueError`` naming the sampler, as for `xhat0_sampler`.
    - `xhat0_sampler`: ``key -> (n_x,)`` or ``(key, x0) -> (n_x,)`` initial estimate (or a fixed array).
      The form is decided by the sampler's *required* positional parameters only: two or more (or
      ``*args``) make it ``(key, x0)``; a parameter with a default is not counted, so
      ``def s(k, sigma=0.5)`` is the ``key`` form, called as ``s(k)``.
    - `ts`: (T,) save times (the statistics live on this grid).
    - `noise`: measurement noise (:class:`obsjax.noise.BandLimitedNoise` or ``WhiteNoise``), an independent
      realisation per trajectory (``simulate(..., noise=noise, key=k_noise)``).  For band-limited noise,
      fixed steps aligned with the noise grid (``simulate_kwargs=dict(adaptive=False, dt0=noise.dt / 4)``)
      are much faster than adaptive ones on its kinks.
    - `param_sampler`: ``(key, plant) -> plant``: draws the true plant of each trajectory (model
      uncertainty); the returned plant must have the same structure (e.g. ``eqx.tree_at`` on its leaves).
    - `chunk_size`: trajectories per chunk (rounded up to a multiple of the number of devices).
    - `checkpoint`: directory for resumable per-chunk results, or ``None``.
    - `devices`: ``None`` (all of ``jax.devices()``), a number of devices, or a list of devices (with
      several processes, several devices must include one of every process).
    - `quantiles`: levels of the ‖x̃(t)‖ bands.
    - `conv_tol`, `conv_relative`: the convergence threshold, conv_tol · ‖x̃(t0)‖ (or conv_tol when
      ``conv_relative=False``); the convergence time is the crossing of that threshold after the last
      save time above it, interpolated between save times (see ``MonteCarloResult.convergence_time``).  A
      trajectory with x̂(t0) = x(t0) has a relative threshold of 0, so any later error (noise) counts it
      as never converged: use an absolute `conv_tol` there.
    - `progress`: show a tqdm progress bar over chunks.
    - `max_chunks`: compute at most this many new chunks in this call.
    - `lockstep`: integrate each device's share of a chunk as one lock-step batch
      (:func:`obsjax.simulate_batch`: one adaptive solve whose step every member accepts) instead of
      independent solves.  By default (``lockstep=False``) each trajectory takes its own steps: the share
      is ``simulate_batch(..., lockstep=False)`` (the masked adaptive Runge–Kutta loop for explicit
      Runge–Kutta pairs, member by member the solve of :func:`obsjax.simulate`, to rounding for
      smooth inputs and noise — under ``BandLimitedNoise`` with adaptive steps the two differ at the
      level of their own error across the noise's kinks, see :mod:`obsjax.noise` —; with a
      `param_sampler`, the same loop with each member's own plant), otherwise ``jax.vmap`` of
      :func:`obsjax.simulate`.  Lock step
      is about as fast on the CPU for adaptive solves of alike trajectories (0.88–1.04× the default's
      throughput on the Chen & Yen study: benchmarks/results/d_sharding.md, g_numba_dopri5.md), and
      its steps depend on which trajectories share a batch, so results agree with
      the default only to the solver tolerance (not bitwise across chunk sizes or device counts).  A member
      that fails (or alone drags the shared step down) is integrated again alone, so only the members that
      fail on their own are counted failed.  Needs ``param_sampler=None``.
    - `study_id`: an optional name of the study, added to the checkpoint fingerprint; needed only to
      checkpoint a study whose samplers or plant read objects that cannot be fingerprinted by
      content.
    - `simulate_kwargs`: extra keyword arguments of :func:`obsjax.simulate` (``solver``, ``rtol``,
      ``atol``, ``dt0``, ``adaptive``, ``max_steps``, ``max_segments``, an input ``u`` such as
      ``obsjax.signals.multisine(...)`` or a ``controller``: an argument holding arrays passes them to
      the kernel as arrays, and they enter the checkpoint's fingerprint by value); ``throw`` is always ``False``
      (failures are counted from the per-trajectory ``status``).  Without ``max_segments`` a resetting
      observer's study holds exactly the ceil((t1 − t0)/T) reset segments of its period, so studies of
      two periods (a paper's gain against a tuned one) compile one program each; the same
      ``max_segments`` (at least either count, else a ``ValueError``) lets them share one.
    - `keep`: ``"all"`` (default: the per-trajectory arrays are returned) or ``"summary"``
      (streaming statistics in memory bounded by a chunk; see **Streaming**).
    - `sketch_rtol`: the relative accuracy α of the streaming quantiles (``keep="summary"``),
      default 10⁻³; the sketches take about T · ln(10)/(2α) · 8 bytes per decade that ‖x̃‖ spans.

    **Returns:** a :class:`MonteCarloResult`.

    **Example:**::

        plant = obsjax.LTI([[-2., 1.], [0., -1.]], [[0.], [1.]], [[1., 0.]])
        obs = obsjax.Luenberger.from_poles(plant, [-3., -3.])
        res = obsjax.monte_carlo(
            plant, obs, jax.random.PRNGKey(0), 10_000,
            x0_sampler=lambda k: jax.random.normal(k, (2,)),
            xhat0_sampler=lambda k: jnp.zeros(2),
            ts=jnp.linspace(0., 5., 26), chunk_size=2048,
        )
        res.plot()
    """
    require_x64("obsjax.monte_carlo")
    _validate.check_types(plant, observer, noise)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"`n` (the number of trajectories) must be a positive integer, got {n!r}.")
    n = int(n)
    if (
        isinstance(chunk_size, bool)
        or not isinstance(chunk_size, (int, np.integer))
        or chunk_size < 1
    ):
        raise ValueError(f"`chunk_size` must be a positive integer, got {chunk_size!r}.")
    if max_chunks is not None and (not isinstance(max_chunks, (int, np.integer)) or max_chunks < 0):
        raise ValueError(
            f"`max_chunks` must be a non-negative integer or None, got {max_chunks!r}."
        )
    if not conv_tol > 0:
        raise ValueError(f"`conv_tol` must be > 0, got {conv_tol}.")
    qs = tuple(float(q) for q in quantiles)
    if not qs or any(not 0.0 <= q <= 1.0 for q in qs) or list(qs) != sorted(qs):
        raise ValueError(f"`quantiles` must be increasing levels in [0, 1], got {quantiles!r}.")
    if param_sampler is not None and not callable(param_sampler):
        raise ValueError(
            f"`param_sampler` must be a callable (key, plant) -> plant, got {type(param_sampler).__name__}."
        )
    if keep not in ("all", "summary"):
        raise ValueError(f"`keep` must be 'all' or 'summary', got {keep!r}.")
    if not (isinstance(sketch_rtol, (float, int, np.floating)) and 0.0 < sketch_rtol < 0.5):
        raise ValueError(
            f"`sketch_rtol` (the relative accuracy of the streaming quantiles) must be in (0, 0.5), "
            f"got {sketch_rtol!r}."
        )
    sketch_rtol = float(sketch_rtol)
    if study_id is not None and (not isinstance(study_id, str) or not study_id):
        raise ValueError(f"`study_id` must be a non-empty string or None, got {study_id!r}.")
    if lockstep and param_sampler is not None:
        raise ValueError(
            "`lockstep=True` integrates one plant for the whole batch, so it cannot be combined with "
            "`param_sampler` (a plant per trajectory): use lockstep=False."
        )
    ts_arr = np.asarray(_check_ts(ts), dtype=float)
    x0_sampler = _sampler(x0_sampler, "x0_sampler")
    xhat0_sampler = _sampler(xhat0_sampler, "xhat0_sampler")
    takes_x0 = isinstance(xhat0_sampler, _Fixed) or _n_positional(xhat0_sampler) >= 2

    sim_kwargs = _validate.plain_int_kwargs(dict(simulate_kwargs or {}))
    for bad in ("throw", "noise", "key"):
        if bad in sim_kwargs:
            raise ValueError(f"`simulate_kwargs` must not contain {bad!r}: monte_carlo sets it.")
    given_segments = sim_kwargs.pop("max_segments", None)
    # an argument that holds arrays (an input signal u = multisine(...), an eqx.Module: not hashable as a
    # whole) travels with the plant and observer, its arrays as arguments of the kernel; the rest (numbers,
    # solvers, ...) is part of the kernel's static configuration, as before
    sim_items = tuple(sorted(sim_kwargs.items()))
    sim_spec = tuple((False, False) if _is_hashable(v) else (False, eqx.is_array) for _, v in sim_items)
    sim_kw = _hashable_kwargs(dict(eqx.partition(sim_items, sim_spec)[1]))

    # Key handling: raw key data travels through jit/shard_map; the implementation is static.
    if jnp.issubdtype(jnp.asarray(key).dtype, jax.dtypes.prng_key):
        key_impl = str(jr.key_impl(key))
        key_data = jr.key_data(key)
    else:
        key_data = jnp.asarray(key)
        if key_data.dtype != jnp.uint32 or key_data.ndim != 1:
            raise ValueError(
                f"`key` must be a JAX PRNG key (jax.random.key or PRNGKey), got dtype {key_data.dtype} "
                f"and shape {tuple(key_data.shape)}."
            )
        key_impl = None

    # Reset observers: the number of segments is computed once from the concrete period, unless given.
    T = observer.reset_period
    if given_segments is None:
        max_segments = None if T is None else num_segments(T, ts_arr[0], ts_arr[-1])
    else:
        max_segments = reset_segments(
            T, None, None if T is None else ts_arr, given_segments, name="`simulate_kwargs['max_segments']`"
        )

    devices = _resolve_devices(devices)
    D = len(devices)
    if D > 1 and jax.process_count() > 1:
        missing = set(range(jax.process_count())) - {d.process_index for d in devices}
        if missing:
            raise ValueError(
                f"`devices` spans {D} devices but none of processes {sorted(missing)}: in a multi-process "
                "run (jax.distributed) a mesh of several devices must include a device of every process."
            )
    chunk = int(math.ceil(chunk_size / D) * D)
    mesh = None
    if D > 1:
        mesh = jax.sharding.Mesh(np.array(devices), ("batch",))

    masked = _masked.eligible_options(observer, ts_arr, noise=noise, **sim_kwargs)
    dyn, static = eqx.partition(
        (plant, observer, noise, sim_items), (eqx.is_array, eqx.is_array, eqx.is_array, sim_spec)
    )
    cfg = _Config(
        static=static,
        ts=tuple(float(t) for t in ts_arr),
        x0_sampler=x0_sampler,
        xhat0_sampler=xhat0_sampler,
        xhat0_takes_x0=takes_x0,
        param_sampler=param_sampler,
        sim_kwargs=sim_kw,
        max_segments=max_segments,
        key_impl=key_impl,
        mesh=mesh,
        lockstep=bool(lockstep),
        masked=masked,
        content=fingerprint(
            dict(static=static, x0_sampler=x0_sampler, xhat0_sampler=xhat0_sampler, param_sampler=param_sampler,
                 sim_kwargs=sim_kw)  # fmt: skip
        )[0],
    )
    try:
        hash(cfg)
    except TypeError as e:
        raise ValueError(
            f"the static part of the study (samplers, plant callables, simulate_kwargs) must be hashable: {e}"
        ) from None

    n_chunks = int(math.ceil(n / chunk))
    T_len = ts_arr.shape[0]
    done = np.zeros(n_chunks, dtype=bool)
    if keep == "all":
        norms = np.full((n, T_len), np.nan)
        status = np.full((n,), -1, dtype=np.int32)

        def fold(c, lo, hi, en, st):
            norms[lo:hi], status[lo:hi] = en, st

        def n_failed():
            return int(np.sum(status > 0))
    else:  # streaming: memory bounded by a chunk (and the sketches)
        acc = _Streaming(ts_arr, conv_tol, conv_relative, sketch_rtol)

        def fold(c, lo, hi, en, st):
            acc.add(en, st)

        def n_failed():
            return acc.n_failed

    # Several processes (jax.distributed): process 0 alone reads and writes the checkpoint; the other
    # processes receive the list of finished chunks and their results from it (a collective), so all of
    # them skip the same chunks and return the same result, whether or not the disk is shared.
    n_proc = jax.process_count()
    lead = jax.process_index() == 0
    ckpt = None
    if checkpoint is not None:
        ckpt = os.fspath(checkpoint)
        fp = _study_fingerprint(
            study_id,
            plant=plant,
            observer=observer,
            noise=noise,
            x0_sampler=x0_sampler,
            xhat0_sampler=xhat0_sampler,
            xhat0_takes_x0=takes_x0,
            param_sampler=param_sampler,
            simulate_kwargs=sim_items if given_segments is None else (*sim_items, ("max_segments", max_segments)),
            ts=ts_arr,
            key_data=np.asarray(key_data),
            key_impl=key_impl,
            n=n,
            chunk=chunk,
            # lock-step results depend on which trajectories share a batch; the masked loop's agree with
            # independent diffrax solves to rounding, not bit for bit
            lockstep=(
                f"lockstep, {D} devices"
                if lockstep
                else ("independent, masked loop" if masked else "independent")
            ),
        )
        mismatch, failure = False, None
        # a streaming study with several processes folds the loaded chunks once they are broadcast
        load = fold if (n_proc == 1 or keep == "all") else (lambda *a: None)
        if lead:
            if n_proc == 1:
                mismatch = _resume(ckpt, fp, study_id, n, chunk, n_chunks, T_len, done, load)
            else:
                # any failure is told to the other processes before it is raised, or they would wait
                try:
                    mismatch = _resume(ckpt, fp, study_id, n, chunk, n_chunks, T_len, done, load)
                except Exception as e:  # noqa: BLE001
                    failure = e
        if n_proc > 1:
            flag = np.int32(2 if failure is not None else int(mismatch))
            flag, done = _broadcast_from_lead((flag, done.astype(np.int32)))
            if failure is not None:
                raise failure
            if flag == 2:
                raise RuntimeError(
                    f"process 0 could not read or start the checkpoint directory {ckpt!r} (see its error)."
                )
            mismatch, done = bool(flag), done.astype(bool)
        if mismatch:
            raise ValueError(
                f"checkpoint directory {ckpt!r} holds a different study (its fingerprint differs: "
                "gains, plant, samplers (code, closures, globals, the environment variables and the "
                "state of the random generators they read: a sampler that draws from a Python or "
                "NumPy generator while traced advances it), noise, ts, key, n, chunk size, "
                "simulate_kwargs, study_id, the number of devices of a lock-step study, library "
                "versions or the revision of obsjax's results changed): delete it or choose another path."
            )
        if n_proc > 1:
            for c in np.flatnonzero(done):
                lo, hi = c * chunk, min((c + 1) * chunk, n)
                if keep == "all":
                    norms[lo:hi], status[lo:hi] = _broadcast_from_lead((norms[lo:hi], status[lo:hi]))
                    continue
                en, st = np.full((hi - lo, T_len), np.nan), np.full(hi - lo, -1, np.int32)
                if lead:  # verified by _resume above; read again, one chunk in memory at a time
                    en, st, why = _read_chunk(_chunk_path(ckpt, int(c)), fp, int(c), hi - lo, T_len)
                    if why is not None:
                        raise ValueError(f"checkpoint chunk {c} changed while it was loaded: {why}.")
                fold(c, lo, hi, *_broadcast_from_lead((en, st)))

    todo = [c for c in range(n_chunks) if not done[c]]
    if max_chunks is not None:
        todo = todo[: int(max_chunks)]

    sharding_in = None
    if mesh is not None:
        sharding_in = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("batch"))
        if jax.process_count() == 1:
            # the study's arrays replicated on the mesh beside the sharded indices: one set of devices
            # for every argument (what a saved program, read back by the trace cache, requires)
            replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
            dyn, key_data = jax.device_put((dyn, key_data), replicated)
    # The outputs live on every process's devices only when the mesh spans several processes.
    gather = mesh is not None and len({d.process_index for d in devices}) > 1

    it = todo
    bar = None
    if progress and todo and lead:
        from tqdm.auto import tqdm

        bar = tqdm(todo, desc="monte_carlo", unit="chunk", leave=False)
        it = bar
    t_start = time.perf_counter()
    computed = 0
    for c in it:
        lo, hi = c * chunk, min((c + 1) * chunk, n)
        idx = np.minimum(np.arange(lo, lo + chunk), n - 1).astype(
            np.int32
        )  # pad with the last index
        if sharding_in is not None:
            idx_dev = jax.make_array_from_callback((chunk,), sharding_in, lambda s, idx=idx: idx[s])
        else:
            idx_dev = jnp.asarray(idx)
        with runtime_checks_as_nan():
            en, st = _chunk_kernel_saved(dyn, key_data, idx_dev, cfg)
        if gather:
            from jax.experimental import multihost_utils

            en, st = multihost_utils.process_allgather((en, st), tiled=True)
        en = np.asarray(jax.block_until_ready(en))[: hi - lo]
        st = np.asarray(st)[: hi - lo]
        fold(c, lo, hi, en, st)
        done[c] = True
        computed += hi - lo
        if ckpt is not None and lead:
            write_chunk(ckpt, c, fp, en, st)
        if bar is not None:
            bar.set_postfix(failed=n_failed())
    elapsed = time.perf_counter() - t_start
    if bar is not None:
        bar.close()
    store = None if ckpt is None else (ckpt, fp, chunk, done.copy())
    if keep == "summary":
        return _streamed_result(acc, qs, n, elapsed, computed, store, sketch_rtol)
    result = summarise(
        ts_arr,
        norms,
        status,
        quantiles=qs,
        conv_tol=conv_tol,
        conv_relative=conv_relative,
        n=n,
        elapsed=elapsed,
        n_computed=computed,
    )
    return dataclasses.replace(result, _store=store)


def cvar_key(alpha: float) -> str:
    """The summary key of the ISE CVaR at level α: ``ise_cvar95`` for 0.95, ``ise_cvar99.5`` for 0.995
    (100 α to the shortest decimal: two levels never share a key)."""
    return f"ise_cvar{float(repr(round(alpha * 100, 10))):g}"


def comparison_table(results: dict, cvar_alpha: float = 0.95) -> str:
    """A plain-text table comparing several :class:`MonteCarloResult` (label -> result)."""
    cvar_alpha = cvar_level(cvar_alpha)
    cols = [
        "n",
        "failed",
        "final_median",
        "final_p95",
        "conv_median",
        "conv_p95",
        "converged_fraction",
        "ise_mean",
        cvar_key(cvar_alpha),
    ]
    heads = [
        "N",
        "failed",
        "‖x̃(tf)‖ med",
        "‖x̃(tf)‖ p95",
        "t_conv med",
        "t_conv p95",
        "converged",
        "ISE mean",
        f"ISE CVaR{cvar_key(cvar_alpha)[len('ise_cvar'):]}",
    ]
    rows = []
    for label, res in results.items():
        s = res.summary(cvar_alpha)
        row = [label]
        for c in cols:
            v = s[c]
            if c in ("n", "failed"):
                row.append(f"{int(v)}")
            elif c == "converged_fraction":
                row.append(f"{v:.1%}")
            else:
                row.append(f"{v:.3g}" if np.isfinite(v) else str(v))
        rows.append(row)
    widths = [max(len(r[i]) for r in rows + [["observer"] + heads]) for i in range(len(heads) + 1)]
    fmt = lambda r: "  ".join(
        x.rjust(w) if i else x.ljust(w) for i, (x, w) in enumerate(zip(r, widths))
    )
    line = "-" * (sum(widths) + 2 * len(widths) - 2)
    return "\n".join([fmt(["observer"] + heads), line] + [fmt(r) for r in rows])
