"""Sampled measurements y(t_k), u(t_k) of an experiment, and how an observer sees them between samples."""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value, real_array
from .._integrate import _schedule

#: how the continuous-time observer sees the samples between two sampling instants
HOLDS = ("zoh", "linear", "cubic")
MISSING = ("raise", "skip")


def _check_choice(value, name, choices):
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"`{name}` must be one of {', '.join(map(repr, choices))}, got {value!r}.")
    return value


#: Spacing of the padding samples of :meth:`Measurements.stack`, relative to the span t_K − t_0: a thousand
#: times the update schedule's tolerance, and short enough that the observer does not run past the data.
PAD_STEP = 1e-6


def _check_separated(ts):
    """Sample times farther apart than the update schedule's tolerance, 1e-9·(t_K − t_0) plus four ulp of
    max(|t_0|, |t_K|) (relative to the span: a change of time unit changes nothing).

    ``estimate`` applies the updates of the samples at the breakpoints of its schedule, and breakpoints
    closer than that tolerance are one instant: of two such samples one update was lost and a row of the
    result never written (zeros, with status 0).  Such a pair is refused instead (eagerly a ``ValueError``
    naming the two samples; traced, ``eqx.error_if``)."""
    v = concrete_value(ts)
    if v is None:
        tol = _schedule.tolerance_of(ts[0], ts[-1])
        return eqx.error_if(
            ts, jnp.any(jnp.diff(ts) <= tol),
            "`ts` holds two samples closer than 1e-9·(t_K − t_0), which the observer's update "
            "schedule takes as one instant: merge them (e.g. average the two samples) or drop one.",
        )
    v = np.asarray(v, dtype=np.float64)
    tol = _schedule.horizon_tolerance(v)
    close = np.flatnonzero(np.diff(v) <= tol)
    if close.size:
        i = int(close[0])
        raise ValueError(
            f"`ts` holds two samples closer than the update schedule's time tolerance 1e-9·(t_K − t_0) "
            f"= {tol:.3g}: ts[{i}] = {float(v[i])!r}, ts[{i + 1}] = {float(v[i + 1])!r} "
            f"(Δ = {float(v[i + 1] - v[i]):.3g}). The observer would take them as one instant (one update lost); "
            "merge them (e.g. average the two samples) or drop one."
        )
    _warn_time_resolution(v)
    return ts


#: relative resolution of the shortest sampling interval below which :class:`Measurements` warns
TIME_RESOLUTION_WARN = 1e-7


def _warn_time_resolution(v):
    """A UserWarning when float64 resolves the shortest sampling interval only coarsely: time stamps far
    from zero (epoch seconds, ~1e9) leave ulp(t)/Δt of every interval to rounding, in the holds and in the
    solver's steps alike."""
    dt = float(np.min(np.diff(v)))
    res = float(np.spacing(np.max(np.abs(v)))) / dt
    if res > TIME_RESOLUTION_WARN:
        import warnings

        big = float(np.max(np.abs(v)))
        warnings.warn(
            f"`ts` runs from {float(v[0])!r} to {float(v[-1])!r}: at |t| = {big:.3g}, float64 resolves "
            f"time to {float(np.spacing(big)):.2g}, {res:.1e} of the shortest sampling "
            f"interval ({dt:.3g}), and the holds and the solver lose that much relative accuracy. Subtract "
            "the first time stamp (ts − ts[0]) unless the model depends on absolute time.",
            UserWarning,
            stacklevel=_caller_level(),
        )


def _caller_level():
    """The stack level of the first frame outside obsjax and equinox (a Measurements is built through
    equinox's module machinery and, from a file, through the readers): the warning points at user code."""
    import inspect

    frame, level = inspect.currentframe(), 1
    while frame is not None:
        name = frame.f_globals.get("__name__", "")
        if level > 2 and not (name.startswith("obsjax.") or name.startswith("equinox")):
            return level - 1
        frame, level = frame.f_back, level + 1
    return 2


def check_times(ts, name="ts"):
    """Sample times: real, 1-D, at least 2, finite, strictly increasing (eagerly; ``eqx.error_if`` traced)."""
    v = concrete_value(ts)
    ts = real_array(ts, name)
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"`{name}` must be a 1-D array of at least 2 sample times, got shape {tuple(ts.shape)}.")
    if v is None:
        return eqx.error_if(
            ts, ~jnp.all(jnp.diff(ts) > 0) | ~jnp.all(jnp.isfinite(ts)),
            f"`{name}` must hold finite, strictly increasing sample times.",
        )
    v = np.asarray(v, dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(v))
    if bad.size:
        raise ValueError(f"`{name}` must hold finite times, got {v[bad[0]]} at sample {bad[0]}.")
    d = np.diff(v)
    if np.any(d <= 0):
        i = int(np.flatnonzero(d <= 0)[0])
        what = "a duplicate time" if d[i] == 0 else "a time that goes backwards"
        raise ValueError(
            f"`{name}` must be strictly increasing, got {what}: {name}[{i}] = {float(v[i])!r}, "
            f"{name}[{i + 1}] = {float(v[i + 1])!r}."
        )
    return ts


def _samples(x, name, K, what):
    """(K,) or (K, k) samples -> (K, k), naming the argument on a wrong shape."""
    arr = real_array(x, name)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise ValueError(f"`{name}` must have shape (K, {what}) (one row per sample), got {tuple(arr.shape)}.")
    if arr.shape[0] != K:
        raise ValueError(
            f"`{name}` has {arr.shape[0]} samples but `ts` has {K}: the lengths must agree (one row per time)."
        )
    return arr


def _bridge(v: np.ndarray, ts: np.ndarray, hold: str, name: str) -> np.ndarray:
    """Column by column, the non-finite entries of `v` (K, q) bridged from the finite ones as the hold
    would bridge a gap: the last value before it (``"zoh"``; the first value for a leading gap), or the
    straight line between its neighbours (``"linear"``, ``"cubic"``; constant beyond the ends)."""
    out = v.copy()
    for j in range(v.shape[1]):
        ok = np.isfinite(v[:, j])
        if ok.all():
            continue
        if not ok.any():
            raise ValueError(f"`missing='skip'`: column {j} of `{name}` holds no finite sample.")
        if hold == "zoh":
            idx = np.where(ok, np.arange(len(ok)), -1)
            idx = np.maximum.accumulate(idx)
            idx[idx < 0] = np.flatnonzero(ok)[0]
            out[:, j] = v[idx, j]
        else:
            out[:, j] = np.interp(ts, ts[ok], v[ok, j])
    return out


def _finite_rows(arrays, ts, missing):
    """Rows whose samples are all finite; ``missing="raise"`` refuses any NaN/inf, naming the argument."""
    keep = np.ones(len(ts), bool)
    for name, a in arrays:
        v = concrete_value(a)
        if v is None:
            if missing == "skip":
                raise ValueError(
                    f"`missing='skip'` needs concrete samples (it bridges and masks them): `{name}` is traced (inside jit)."
                )
            continue
        ok = np.all(np.isfinite(v), axis=1)
        if missing == "raise" and not np.all(ok):
            i = int(np.flatnonzero(~ok)[0])
            raise ValueError(
                f"`{name}` holds non-finite samples ({int((~ok).sum())} of them), the first at sample {i} "
                f"(t = {float(ts[i])!r}): clean the data, or pass missing='skip' to bridge and mask them."
            )
        keep &= ok
    return keep


def _traced_finite(a, name):
    if concrete_value(a) is not None:
        return a
    return eqx.error_if(a, ~jnp.all(jnp.isfinite(a)), f"`{name}` must hold finite samples (no NaN or inf).")


def _numeric_column(values, name, source):
    """A 1-D float array from a column; datetime and timedelta columns are refused (their conversion to
    float gives tick counts: ns or µs, not seconds)."""
    a = np.asarray(values)
    if a.dtype.kind in "mM" or str(getattr(values, "dtype", "")).startswith(("datetime", "timedelta")):
        raise ValueError(
            f"column {name!r} of {source} holds dates or durations ({a.dtype}): convert it to seconds first, "
            "e.g. (t - t[0]) / np.timedelta64(1, 's') (or .dt.total_seconds() in pandas).  Read as a float "
            "it would be a count of nanoseconds or microseconds."
        )
    try:
        return np.asarray(a, dtype=float)
    except (TypeError, ValueError) as e:
        raise ValueError(f"column {name!r} of {source} is not numeric: {e}") from None


def hermite_slopes(ts, v):
    """Slopes at the samples for the cubic hold: the derivative of the parabola through three neighbouring
    samples (second-order accurate on irregular grids; one-sided at the ends, the secant for two samples)."""
    h = jnp.diff(ts)[:, None]
    delta = jnp.diff(v, axis=0) / h
    if ts.shape[0] == 2:
        return jnp.concatenate([delta, delta])
    h0, h1, d0, d1 = h[:-1], h[1:], delta[:-1], delta[1:]
    inner = (h1 * d0 + h0 * d1) / (h0 + h1)
    first = ((2 * h0[:1] + h1[:1]) * d0[:1] - h0[:1] * d1[:1]) / (h0[:1] + h1[:1])
    last = ((2 * h1[-1:] + h0[-1:]) * d1[-1:] - h1[-1:] * d0[-1:]) / (h0[-1:] + h1[-1:])
    return jnp.concatenate([first, inner, last])


def hermite_coefficients(ts, v):
    """(d, c, b, a), each (K − 1, k): the cubic Hermite pieces a + b s + c s² + d s³, s = t − t_k, in the
    layout of ``diffrax.CubicInterpolation``."""
    m = hermite_slopes(ts, v)
    h = jnp.diff(ts)[:, None]
    delta = jnp.diff(v, axis=0) / h
    m0, m1 = m[:-1], m[1:]
    c = (3 * delta - 2 * m0 - m1) / h
    d = (m0 + m1 - 2 * delta) / h**2
    return d, c, m0, v[:-1]


class Measurements(eqx.Module):
    r"""Sampled outputs and inputs of one experiment (or a batch of them, see :meth:`stack`).

    Samples y_k = y(t_k) (K, m) and u_k = u(t_k) (K, p) at strictly increasing, possibly irregular times
    t_0 < … < t_{K−1}, and how a continuous-time observer sees them between samples (`hold`):

    - ``"zoh"``: zero-order hold, y(t) = y_k on [t_k, t_{k+1}) (causal; first order in the sampling
      interval h: |y(t) − y_true(t)| ≤ h max|ẏ|);
    - ``"linear"``: the straight line between y_k and y_{k+1} (second order, error ≤ h²/8 max|ÿ|;
      ``diffrax.LinearInterpolation``);
    - ``"cubic"``: the cubic Hermite piece whose slopes at the samples are those of the parabola through
      three neighbouring samples (third order; ``diffrax.CubicInterpolation``).

    The linear and cubic holds use the next sample: they suit recorded (offline) data, not a causal
    filter.  A discrete-time update (:class:`obsjax.observers.ContinuousDiscreteKalman`) sees the samples
    themselves.

    **Arguments:**

    - `ts`: (K,) sample times, K ≥ 2, finite and strictly increasing (a duplicate time is refused, and so
      are two samples closer than 1e-9·(t_K − t_0), which the update schedule would take as one).
    - `y`: (K, m) sampled outputs ((K,) for one output).
    - `u`: (K, p) sampled inputs, or ``None`` (p = 0).
    - `hold`: ``"zoh"`` (default), ``"linear"`` or ``"cubic"``.
    - `missing`: ``"raise"`` (default) refuses a NaN/inf sample, naming the argument and the first
      sample; ``"skip"`` keeps every sample and bridges each missing value from its column's
      neighbours as the hold bridges a gap (the last value for ``"zoh"``, the straight line between
      the neighbours otherwise), and masks a sample whose output (any channel) is missing: no
      discrete update and no loss term there, while the observer still sees the recorded input
      (needs concrete values).  A sample whose input alone is missing stays in use; a missing `x_ref`
      value (validation only, never fed to the observer) is bridged the same way and changes no
      estimate.
    - `x_ref`: optional (K, q) states measured for validation only (a tachometer in the lab), never fed to
      the observer; `x_index` (q integers) says which states of x they are.  :func:`obsjax.estimate` then
      returns ``state_error`` and :func:`obsjax.losses.state_error` can tune on it.
    - `mask`: optional (K,) booleans; False marks padding (:meth:`stack`): the observer runs over it, but
      discrete updates and the losses ignore it.

    Bad data raise ``ValueError`` naming the argument: non-increasing or duplicate times, NaN samples,
    lengths that disagree.  Values that are traced (a ``Measurements`` built inside ``jit``) are checked
    with ``eqx.error_if``.

    **Example:**::

        data = obsjax.Measurements(ts, y, u, hold="linear")
        data = obsjax.Measurements.from_csv("run1.csv", t="time", y=["theta"], u=["volts"])
        est = obsjax.estimate(obs, data, jnp.zeros(3))
    """

    ts: jax.Array
    y: jax.Array
    u: jax.Array
    mask: jax.Array
    x_ref: jax.Array | None
    x_index: tuple[int, ...] | None = eqx.field(static=True)
    hold: str = eqx.field(static=True)
    names: tuple | None = eqx.field(static=True)

    def __init__(
        self, ts, y, u=None, *, hold="zoh", missing="raise", x_ref=None, x_index=None, mask=None,
        names=None,
    ):
        self.hold = _check_choice(hold, "hold", HOLDS)
        _check_choice(missing, "missing", MISSING)
        tv = concrete_value(ts)
        ts_arr = real_array(ts, "ts")
        if ts_arr.ndim != 1:
            raise ValueError(f"`ts` must be a 1-D array of sample times, got shape {tuple(ts_arr.shape)}.")
        K = ts_arr.shape[0]
        y = _samples(y, "y", K, "m")
        if y.shape[1] < 1:
            raise ValueError("`y` must hold at least one output (m ≥ 1), got shape (K, 0).")
        u = jnp.zeros((K, 0), y.dtype) if u is None else _samples(u, "u", K, "p")
        x_ref, x_index = self._validation_states(x_ref, x_index, K)
        if tv is not None and np.any(~np.isfinite(np.asarray(tv, dtype=float))):
            bad = int(np.flatnonzero(~np.isfinite(np.asarray(tv, dtype=float)))[0])
            raise ValueError(f"`ts` must hold finite times, got {tv[bad]} at sample {bad}.")
        checked = [("y", y), ("u", u)] + ([("x_ref", x_ref)] if x_ref is not None else [])
        keep = _finite_rows(checked, np.asarray(tv) if tv is not None else np.zeros(K), missing)
        unmeasured = None
        if missing == "skip" and not np.all(keep):
            # every sample is kept (the estimate stays aligned with the recorded times); a missing value
            # is bridged by the hold from its column's neighbours, and a sample whose output is
            # missing is masked: no discrete update there, no loss term.  A missing input or x_ref
            # value alone leaves the measurement in use.
            tnp = np.asarray(tv, dtype=float)
            y_np, u_np = np.asarray(concrete_value(y), float), np.asarray(concrete_value(u), float)
            unmeasured = ~np.all(np.isfinite(y_np), axis=1)
            y = jnp.asarray(_bridge(y_np, tnp, self.hold, "y"))
            u = jnp.asarray(_bridge(u_np, tnp, self.hold, "u"))
            if x_ref is not None:  # validation only, never fed to the observer: bridged, not masked
                x_ref = jnp.asarray(_bridge(np.asarray(concrete_value(x_ref), float), tnp, self.hold, "x_ref"))
            if int((~unmeasured).sum()) < 2:
                raise ValueError(
                    f"`missing='skip'`: {int(unmeasured.sum())} of {K} samples lack an output value, "
                    f"{int((~unmeasured).sum())} remain, and at least 2 measured samples are needed."
                )
            keep = np.ones(K, bool)
        if mask is not None:
            mv = concrete_value(mask)
            if mv is not None and np.asarray(mv).dtype != bool and not np.all(np.isin(np.asarray(mv), (0, 1))):
                raise ValueError(
                    "`mask` must hold booleans (True: a sample the losses use, False: one they ignore, e.g. "
                    "padding; the observer still sees every sample through the hold), "
                    f"got values {np.unique(np.asarray(mv))[:6].tolist()}."
                )
            mask = jnp.asarray(mask, bool)
            if mask.shape != (K,):
                raise ValueError(f"`mask` must have shape ({K},) (one flag per sample), got {tuple(mask.shape)}.")
        if not np.all(keep):
            idx = np.flatnonzero(keep)
            ts_arr, y, u = ts_arr[idx], y[idx], u[idx]
            x_ref = None if x_ref is None else x_ref[idx]
            mask = None if mask is None else mask[idx]
        self.ts = _check_separated(check_times(ts_arr))
        self.y = _traced_finite(y, "y")
        self.u = _traced_finite(u, "u")
        self.x_ref = None if x_ref is None else _traced_finite(x_ref, "x_ref")
        self.x_index = x_index
        self.mask = jnp.ones(self.ts.shape, bool) if mask is None else mask
        if unmeasured is not None:
            self.mask = self.mask & jnp.asarray(~unmeasured)
        mv = concrete_value(self.mask)
        if mv is not None and not np.any(mv):
            raise ValueError(
                "`mask` marks every sample as padding: the experiment has no sample to fit or to score "
                "(a loss over it would be 0/0)."
            )
        self.names = None if names is None else tuple(tuple(n) if n is not None else None for n in names)

    @staticmethod
    def _validation_states(x_ref, x_index, K):
        if x_ref is None:
            if x_index is not None:
                raise ValueError("`x_index` is given but `x_ref` (the measured states) is not.")
            return None, None
        x_ref = _samples(x_ref, "x_ref", K, "q")
        if x_index is None:
            raise ValueError("`x_index` (which states `x_ref` holds, e.g. (1,)) is required with `x_ref`.")
        raw = np.atleast_1d(np.asarray(x_index, dtype=object)).ravel()
        if not all(isinstance(i, (int, np.integer)) and not isinstance(i, bool) for i in raw):
            raise ValueError(
                f"`x_index` must list integer state indices (one per column of `x_ref`), got {x_index!r}."
            )
        idx = tuple(int(i) for i in raw)
        if len(idx) != x_ref.shape[1] or any(i < 0 for i in idx):
            raise ValueError(
                f"`x_index` must list {x_ref.shape[1]} non-negative state indices (one per column of `x_ref`), "
                f"got {idx}."
            )
        return x_ref, idx

    # ------------------------------------------------------------------------------------------------
    # sizes

    @property
    def K(self) -> int:
        """Number of samples (including padding)."""
        return int(self.ts.shape[-1])

    @property
    def m(self) -> int:
        """Number of outputs."""
        return int(self.y.shape[-1])

    @property
    def p(self) -> int:
        """Number of inputs."""
        return int(self.u.shape[-1])

    @property
    def batched(self) -> bool:
        """True for a batch of experiments made by :meth:`stack` (leading axis on every array)."""
        return self.ts.ndim == 2

    # ------------------------------------------------------------------------------------------------
    # the held signals

    def _values(self):
        return jnp.concatenate([self.y, self.u], axis=-1)

    def path(self):
        """The held signal t ↦ [y(t); u(t)] as a diffrax path (``LinearInterpolation`` or
        ``CubicInterpolation``; ``None`` for the zero-order hold, which :meth:`evaluate` handles)."""
        v = self._values()
        if self.hold == "linear":
            return diffrax.LinearInterpolation(self.ts, v)
        if self.hold == "cubic":
            return diffrax.CubicInterpolation(self.ts, hermite_coefficients(self.ts, v))
        return None

    def evaluate(self, t):
        """(y(t), u(t)) as the observer sees them (right-continuous for the zero-order hold), for t in
        [t_0, t_{K−1}] (a concrete t outside it raises ``ValueError``: the holds would extrapolate)."""
        if self.batched:
            raise ValueError("`evaluate` works on one experiment: index or vmap a stacked Measurements first.")
        t = jnp.asarray(t, self.ts.dtype)
        tc, t0c, t1c = concrete_value(t), concrete_value(self.ts[0]), concrete_value(self.ts[-1])
        if tc is not None and t0c is not None and t1c is not None:
            lo, hi = float(t0c), float(t1c)
            tol = _schedule.tolerance(hi - lo, max(abs(lo), abs(hi)))
            tv = np.atleast_1d(np.asarray(tc, dtype=float))
            outside = ~((tv >= lo - tol) & (tv <= hi + tol))  # NaN is outside
            if outside.any():
                raise ValueError(
                    f"`evaluate` holds the samples on [{lo:g}, {hi:g}] only (outside it the linear and cubic "
                    f"holds would extrapolate), got t = {tv[outside][0]:g}."
                )
        if t.ndim:
            return jax.vmap(self.evaluate)(t)
        if self.hold == "zoh":
            k = jnp.clip(jnp.searchsorted(self.ts, t, side="right") - 1, 0, self.K - 1)
            v = self._values()[k]
        else:
            v = self.path().evaluate(t)
        return v[..., : self.m], v[..., self.m :]

    # ------------------------------------------------------------------------------------------------
    # constructors

    @classmethod
    def from_columns(cls, columns, *, t, y, u=None, x=None, x_index=None, source="the data", **kwargs):
        """Build from a mapping column name → 1-D values (used by :meth:`from_csv` and
        :meth:`from_dataframe`); a missing column raises ``ValueError`` listing those available."""
        names = list(columns)

        def take(arg, cols):
            if cols is None:
                return None, None
            cols = [cols] if isinstance(cols, str) else list(cols)
            if not cols:
                raise ValueError(f"`{arg}` must name at least one column, got an empty list.")
            for c in cols:
                if c not in columns:
                    raise ValueError(
                        f"column {c!r} (argument `{arg}`) is not in {source}; available columns: {names}."
                    )
            return np.stack([_numeric_column(columns[c], c, source) for c in cols], axis=1), tuple(cols)

        tv, _ = take("t", t)
        if tv.shape[1] != 1:
            raise ValueError(f"`t` must name one column, got {t!r}.")
        yv, yn = take("y", y)
        uv, un = take("u", u)
        xv, _ = take("x", x)
        return cls(tv[:, 0], yv, uv, x_ref=xv, x_index=x_index, names=(yn, un), **kwargs)

    @classmethod
    def from_csv(cls, path, *, t, y, u=None, x=None, x_index=None, hold="zoh", missing="raise", delimiter=","):
        """Read a CSV file with a header row (no pandas needed).

        **Arguments:** `path`; `t` the name of the time column; `y` (and `u`, `x`) the names of the output
        (input, validation-state) columns, a string or a list; `x_index` which states `x` holds; `hold`,
        `missing` as for :class:`Measurements`; `delimiter`.  An empty field reads as NaN (see `missing`).

        **Returns:** a :class:`Measurements`.
        """
        import csv

        # UTF-8, with or without the byte-order mark that spreadsheet programs write ("CSV UTF-8")
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.reader(fh, delimiter=delimiter))
        if not rows:
            raise ValueError(f"`path` {path!r} is empty: expected a header row and samples.")
        header = [h.strip() for h in rows[0]]
        dup = sorted({h for h in header if header.count(h) > 1})
        if dup:  # a column read by name would be one of them, and which one the user cannot tell
            where = ", ".join(f"{h!r} (columns {[j for j, g in enumerate(header) if g == h]})" for h in dup)
            raise ValueError(f"`path` {path!r}: the header names a column more than once: {where}; rename them.")
        # an empty line is no sample; a line of empty fields (",,") is a sample with every value missing,
        # which `missing` decides about (it was dropped silently, also with missing="raise")
        body = [r for r in rows[1:] if len(r) > 1 or (r and r[0].strip())]
        for i, r in enumerate(body):
            if len(r) != len(header):
                raise ValueError(
                    f"`path` {path!r}: line {i + 2} has {len(r)} fields but the header has {len(header)}."
                )

        def num(f, i, j):
            f = f.strip()
            if not f:
                return np.nan
            try:
                return float(f)
            except ValueError:
                raise ValueError(
                    f"`path` {path!r}: line {i + 2}, column {header[j]!r} is not a number: {f!r}."
                ) from None

        cols = {h: np.array([num(r[j], i, j) for i, r in enumerate(body)]) for j, h in enumerate(header)}
        if missing == "skip" and isinstance(t, str) and t in cols:  # a sample without its time: dropped too
            keep = np.isfinite(cols[t])
            cols = {h: v[keep] for h, v in cols.items()}
        return cls.from_columns(
            cols, t=t, y=y, u=u, x=x, x_index=x_index, hold=hold, missing=missing, source=f"{path!r}"
        )

    @classmethod
    def from_dataframe(cls, df, *, t, y, u=None, x=None, x_index=None, hold="zoh", missing="raise"):
        """Build from a pandas ``DataFrame`` (or any mapping of column names to 1-D values); ``t`` may be
        ``"index"`` to use the frame's index as the time (refused when a column is also named "index").
        Date and duration columns are refused: convert them to seconds first.  pandas itself is not
        required by obsjax.

        **Returns:** a :class:`Measurements`.
        """
        cols = {str(c): df[c] for c in list(getattr(df, "columns", df))}
        if t == "index":
            if "index" in cols:
                raise ValueError(
                    "`t='index'` names the frame's index, but the frame also has a column named 'index' (as "
                    "after df.reset_index()): rename that column and pass its new name, or set the index "
                    "with df.set_index(...)."
                )
            cols["index"] = df.index
        return cls.from_columns(cols, t=t, y=y, u=u, x=x, x_index=x_index, hold=hold, missing=missing,
                                source="the data frame")

    def to_dataframe(self):
        """A pandas ``DataFrame`` with columns t, the outputs and the inputs (names kept from the source;
        y0, y1, … and u0, … otherwise).  Imports pandas (an optional dependency)."""
        import pandas as pd

        if self.batched:
            raise ValueError("`to_dataframe` works on one experiment: index a stacked Measurements first.")
        yn, un = self.names if self.names is not None else (None, None)
        yn = yn or tuple(f"y{i}" for i in range(self.m))
        un = un or tuple(f"u{i}" for i in range(self.p))
        data = {"t": np.asarray(self.ts)}
        data.update({n: np.asarray(self.y[:, i]) for i, n in enumerate(yn)})
        data.update({n: np.asarray(self.u[:, i]) for i, n in enumerate(un)})
        return pd.DataFrame(data)

    @classmethod
    def stack(cls, datasets) -> Measurements:
        """A batch of experiments of possibly different lengths, padded to the longest.

        Each experiment is padded at its end by repeating its last sample at times 1e-6·(t_K − t_0)
        apart after its last sample, so that the observer runs no further than the experiment's data (an
        unstable model run open loop over the longest experiment's duration would overflow and fail a good
        short experiment); ``mask`` is False on the padding.  Every array gains a leading axis of
        length len(datasets), so ``jax.vmap``/``eqx.filter_vmap`` maps :func:`obsjax.estimate` over it
        and the losses ignore the padding.

        **Arguments:** `datasets`: a non-empty sequence of :class:`Measurements` with the same hold, m, p
        and validation states.

        **Returns:** a batched :class:`Measurements`.
        """
        datasets = list(datasets)
        if not datasets or not all(isinstance(d, Measurements) and not d.batched for d in datasets):
            raise ValueError("`datasets` must be a non-empty sequence of (unbatched) obsjax.Measurements.")
        first = datasets[0]
        for i, d in enumerate(datasets):
            if (d.hold, d.m, d.p, d.x_index) != (first.hold, first.m, first.p, first.x_index):
                raise ValueError(
                    f"`datasets`[{i}] has hold={d.hold!r}, m={d.m}, p={d.p}, x_index={d.x_index} but `datasets`[0] "
                    f"has hold={first.hold!r}, m={first.m}, p={first.p}, x_index={first.x_index}: they must agree."
                )
        K = max(d.K for d in datasets)
        padded = [d._padded(K) for d in datasets]
        return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *padded)

    def _padded(self, K):
        extra = K - self.K
        # relative to the span (a change of time unit changes nothing), and never within the schedule's
        # tolerance, which includes a few ulp of the times (e.g. of an epoch time stamp)
        scale = jnp.maximum(jnp.abs(self.ts[0]), jnp.abs(self.ts[-1]))
        # at most ~1e-3 of the span in all (many padded samples: 1e6 of them spanned the data once more),
        # never closer than 10 times the schedule's relative tolerance
        step = max(min(PAD_STEP, 1e-3 / max(extra, 1)), 10 * _schedule.TIME_RTOL) if extra else PAD_STEP
        dt = step * (self.ts[-1] - self.ts[0]) + 100 * _schedule.TIME_ULPS * jnp.finfo(self.ts.dtype).eps * scale
        ts = jnp.concatenate([self.ts, self.ts[-1] + dt * jnp.arange(1, extra + 1)])

        def rep(a, first=None):
            if a is None:
                return None
            pad = jnp.broadcast_to(a[-1] if first is None else first, (extra,) + a.shape[1:])
            return jnp.concatenate([a, pad])

        y, u = rep(self.y), rep(self.u)
        if self.hold == "cubic" and extra:
            # The cubic hold's slope at the last real sample is the one-sided end slope (the parabola
            # through the last three samples); after padding that sample is interior, and its slope comes
            # from its neighbours.  The padding value is put on that parabola, so the interior slope is the
            # same one and no real interval changes (repeating the last value gave a slope near 0 there:
            # estimates 1e-2 off on a short experiment's last interval).
            v = self._values()
            nxt = self.ts[-1] + dt
            if self.K >= 3:
                t0_, t1_, t2_ = self.ts[-3], self.ts[-2], self.ts[-1]
                l0 = (nxt - t1_) * (nxt - t2_) / ((t0_ - t1_) * (t0_ - t2_))
                l1 = (nxt - t0_) * (nxt - t2_) / ((t1_ - t0_) * (t1_ - t2_))
                l2 = (nxt - t0_) * (nxt - t1_) / ((t2_ - t0_) * (t2_ - t1_))
                w = l0 * v[-3] + l1 * v[-2] + l2 * v[-1]
            else:  # two samples: the secant, extended
                w = v[-1] + (v[-1] - v[-2]) * (dt / (self.ts[-1] - self.ts[-2]))
            y, u = rep(self.y, w[: self.m]), rep(self.u, w[self.m :])
        mask = jnp.concatenate([self.mask, jnp.zeros(extra, bool)])
        return Measurements(
            ts, y, u, hold=self.hold, x_ref=rep(self.x_ref), x_index=self.x_index, mask=mask
        )
