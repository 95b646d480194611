"""The breakpoints of a simulation: where the state may jump or the vector field may be discontinuous.

Three sources, merged into one sorted list:

- (a) the observer's resets at t0 + kT, k = 1, 2, … while t0 + kT < t1 (T = ``observer.reset_period``, a
  differentiable, possibly traced leaf: the reset instants move with it);
- (b) the plant's declared ``jump_ts`` inside (t0, t1): a boundary and nothing else (a segment that ends at a
  jump τ ends one float before it, the next starts at τ, so no stage of any solve sees both sides);
- (c) the observer's ``event_times(t0, t1)`` in [t0, t1], where ``observer.update`` is applied.

The back-ends integrate segment by segment between consecutive breakpoints, so no solve ever steps across a
discontinuity.  Segment k ≥ 1 starts at breakpoint k − 1 and applies its jump there (reset first, then
update).  A save time belongs to the segment that starts at or before it, with a tolerance of
1e-9·(t1 − t0) (plus four units in the last place of max(|t0|, |t1|)): a save time at a breakpoint sees the
state after the jump (right-continuous).  The tolerance is relative to the horizon, so a change of time
unit changes nothing.

Number of segments.  The reset count is ⌈(t1 − t0)/T⌉ when T and the horizon are concrete, else
``max_segments``; more than :data:`MAX_RESET_SEGMENTS` is refused (a reset period far below the horizon
would otherwise build millions of segments).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value, device_array, static_value

MAX_RESET_SEGMENTS = 100_000


#: relative time tolerance of the schedule (of the horizon t1 − t0)
TIME_RTOL = 1e-9
#: and the units in the last place of max(|t0|, |t1|) added to it, so that it never falls below rounding
TIME_ULPS = 4


def tolerance(span, scale=0.0) -> float:
    """Time tolerance of the schedule: save times this close to a breakpoint are taken at it.

    ``1e-9·|span| + 4 ulp(scale)``, `span` the horizon t1 − t0 and `scale` max(|t0|, |t1|): relative to the
    horizon, so that it scales with the time unit (an absolute floor would merge the samples of a
    nanosecond-sampled record given in seconds), and never below the rounding of the times themselves."""
    eps = float(np.finfo(np.float64).eps)
    return TIME_RTOL * abs(float(span)) + TIME_ULPS * eps * abs(float(scale))


def tolerance_of(t0, t1):
    """:func:`tolerance` of the horizon [t0, t1], traced or not (a JAX scalar; elementwise for arrays)."""
    t0, t1 = jnp.asarray(t0), jnp.asarray(t1)
    dtype = jnp.result_type(t0, t1)
    eps = jnp.finfo(dtype if jnp.issubdtype(dtype, jnp.floating) else jnp.float64).eps
    return TIME_RTOL * jnp.abs(t1 - t0) + TIME_ULPS * eps * jnp.maximum(jnp.abs(t0), jnp.abs(t1))


def horizon_tolerance(ts_np) -> float:
    """:func:`tolerance` of the horizon of concrete save times `ts_np`."""
    a, b = float(ts_np[0]), float(ts_np[-1])
    return tolerance(b - a, max(abs(a), abs(b)))


def num_segments(T, t0, t1) -> int | None:
    """ceil((t1 − t0)/T) for concrete values (a relative slack of 1e-9 absorbs rounding), else ``None``."""
    Tv, a, b = concrete_value(T), concrete_value(t0), concrete_value(t1)
    if Tv is None or a is None or b is None:
        return None
    Tv = float(np.asarray(Tv).reshape(()))
    if not Tv > 0 or not math.isfinite(Tv):
        raise ValueError(f"the reset period `T` must be finite and > 0, got {Tv}.")
    r = (float(b) - float(a)) / Tv
    if r > MAX_RESET_SEGMENTS:
        raise ValueError(
            f"the reset period T = {Tv:g} gives {math.ceil(r)} reset segments on [{float(a):g}, {float(b):g}]; "
            f"obsjax.simulate integrates at most {MAX_RESET_SEGMENTS} (T ≥ (t1 − t0)/{MAX_RESET_SEGMENTS} = "
            f"{(float(b) - float(a)) / MAX_RESET_SEGMENTS:.3g}). Raise T or shorten the horizon."
        )
    return max(1, math.ceil(r - 1e-9 * max(1.0, r)))


def reset_segments(T, ts, ts_np, max_segments, name="`max_segments`") -> int:
    """Number of reset segments (resets + 1): from `max_segments` when given (checked, and against the
    concrete period when `ts_np` is given; `name` is how errors call it), else from concrete T and ts."""
    if max_segments is not None:
        if isinstance(max_segments, bool) or not isinstance(max_segments, (int, np.integer)):
            raise ValueError(f"{name} must be a positive integer, got {max_segments!r}.")
        if not 1 <= max_segments <= MAX_RESET_SEGMENTS:
            raise ValueError(f"{name} must be in [1, {MAX_RESET_SEGMENTS}], got {max_segments}.")
        n = int(max_segments)
        if ts_np is not None:  # a concrete period must be covered by the bound
            need = num_segments(T, ts_np[0], ts_np[-1])
            if need is not None and need > n:
                raise ValueError(
                    f"{name} = {n} is below the {need} reset segments that the reset period "
                    f"T = {float(np.asarray(concrete_value(T)).reshape(())):g} needs on "
                    f"[{float(ts_np[0]):g}, {float(ts_np[-1]):g}]; give at least {need} (or leave it out)."
                )
        return n
    n = None if ts_np is None else num_segments(T, ts_np[0], ts_np[-1])
    if n is None:
        raise ValueError(
            "The number of reset segments ceil((ts[-1] − ts[0]) / T) cannot be computed because the reset "
            "period T or the save times ts are traced (inside jit): pass `max_segments` (≥ (t1 − t0)/T) to "
            "obsjax.simulate."
        )
    return n


@dataclasses.dataclass(frozen=True)
class Schedule:
    """Sorted breakpoints (Nb,) with what happens at each, and where the save times fall.

    - `t0`, `t1`: the horizon; `times`: (Nb,) breakpoints in [t0, t1] (differentiable in T);
    - `reset`, `event`, `jump`: (Nb,) bool, what the breakpoint is;
    - `first_save`: (Nb + 2,) int, index of the first save time of segment k (k = 0 … Nb), then len(ts);
    - `window`: the largest number of save times in one segment (len(ts) when not known before tracing);
    - `has_reset`, `has_event`: whether any breakpoint is a reset / an event (static);
    - `concrete`: NumPy copies (times, reset, event, jump) when every breakpoint is known before tracing
      (the fixed-step grid needs them), else ``None``.
    """

    t0: jax.Array
    t1: jax.Array
    times: jax.Array
    reset: jax.Array
    event: jax.Array
    jump: jax.Array
    first_save: jax.Array
    window: int
    has_reset: bool
    has_event: bool
    concrete: tuple | None

    @property
    def size(self) -> int:
        return int(self.times.shape[0])


def _events(event_times, t0, t1, ts_np, checked=False):
    """The observer's event times: (a 1-D float array, its concrete value or None), or None.  `checked`:
    traced times the caller has already checked (finite, non-decreasing) outside the compiled program."""
    if ts_np is not None:
        raw = event_times(float(ts_np[0]), float(ts_np[-1]))
    else:
        raw = event_times(t0, t1)
    if raw is None:
        return None
    v = static_value(raw)  # times that depend on a differentiated leaf stay traced
    ev = jnp.asarray(raw, dtype=jnp.result_type(float))
    if ev.ndim != 1:
        raise ValueError(f"`observer.event_times(t0, t1)` must return a 1-D array, got shape {ev.shape}.")
    if v is not None:
        v = np.asarray(v, dtype=np.float64)
        if not np.all(np.isfinite(v)):
            raise ValueError("`observer.event_times(t0, t1)` must return finite times.")
        if np.any(np.diff(v) < 0):
            raise ValueError("`observer.event_times(t0, t1)` must return non-decreasing times.")
    elif ev.shape[0] >= 1 and not checked:
        ev = eqx.error_if(
            ev, jnp.any(jnp.diff(ev) < 0) | jnp.any(~jnp.isfinite(ev)),
            "`observer.event_times(t0, t1)` must return finite, non-decreasing times.",
        )
    return ev, v


@dataclasses.dataclass(frozen=True)
class _Part:
    kind: str  # "reset" | "jump" | "event"
    times: jax.Array  # clipped to [t0, t1]
    active: jax.Array  # bool: the breakpoint lies inside the horizon and acts
    values: np.ndarray | None  # the times, when known before tracing (then every entry is active)


def build(ts, ts_np, T, n_reset, jumps, event_times, events_checked=False) -> Schedule:
    """Merge resets (n_reset − 1 of them), plant jumps and observer events into a :class:`Schedule`.

    `events_checked`: the event times, when traced, were checked (finite, non-decreasing) by the caller
    outside the compiled program (``estimate``'s sample times), so no run-time check is traced here."""
    tol = horizon_tolerance(ts_np) if ts_np is not None else None
    tol_rt = tol if tol is not None else tolerance_of(ts[0], ts[-1])
    if T is not None and (ts_np is None or static_value(T) is None):
        # A traced period must be covered by the bound (n_reset segments of length T reach t1), or the last
        # resets would silently be dropped: checked under jit.
        Tt = jnp.asarray(T, dtype=ts.dtype)
        ts = eqx.error_if(
            ts, ~(ts[0] + n_reset * Tt >= ts[-1] - tol_rt),
            f"the reset period T (traced) needs more than `max_segments` = {n_reset} reset segments to "
            "cover [ts[0], ts[-1]] (max_segments·T < t1 − t0, or T is not finite and > 0): raise "
            "`max_segments`.",
        )
    parts = [
        _resets(ts, ts_np, T, n_reset, tol, tol_rt),
        _jumps(ts, ts_np, jumps, tol, tol_rt),
        _event_part(ts, ts_np, event_times, tol, tol_rt, events_checked),
    ]
    return _merge(ts, ts_np, tol, tol_rt, [p for p in parts if p is not None])


def _resets(ts, ts_np, T, n_reset, tol, tol_rt):
    if T is None or n_reset <= 1:
        return None
    k = np.arange(1, n_reset)
    Tv = static_value(T)  # a T being differentiated (even eagerly) keeps its traced instants
    if ts_np is not None and Tv is not None:
        # concrete instants (NumPy, so also inside jit): drop those on or after t1.  ts and T are then
        # constants, and t0 + k·T in NumPy is the same product and sum as in JAX (run eagerly, each JAX
        # operation would compile a program on its first call)
        rv = ts_np[0] + k * float(np.asarray(Tv).reshape(()))
        keep = rv < ts_np[-1] - tol
        if not np.any(keep):
            return None
        return _Part("reset", device_array(rv[keep]), device_array(np.ones(int(keep.sum()), bool)), rv[keep])
    t0, t1 = ts[0], ts[-1]
    r = t0 + jnp.asarray(k, ts.dtype) * jnp.asarray(T, dtype=ts.dtype)
    # A reset on or after t1 (a bound larger than needed) is clipped to t1 and not applied; the tie resolves
    # to the fixed t1, so the end of the horizon carries no T-derivative.
    return _Part("reset", jnp.where(r < t1, r, t1), r < t1 - tol_rt, None)


def _jumps(ts, ts_np, jumps, tol, tol_rt):
    if jumps is None or not len(jumps):
        return None
    jv = np.asarray(jumps, dtype=float)
    if ts_np is not None:
        jv = jv[(jv > ts_np[0] + tol) & (jv < ts_np[-1] - tol)]
        if not jv.size:
            return None
        return _Part("jump", device_array(jv), device_array(np.ones(jv.shape, bool)), jv)
    j = jnp.asarray(jv, ts.dtype)
    t0, t1 = ts[0], ts[-1]
    return _Part("jump", jnp.clip(j, t0, t1), (j > t0 + tol_rt) & (j < t1 - tol_rt), None)


def _event_part(ts, ts_np, event_times, tol, tol_rt, checked=False):
    t0, t1 = (ts[0], ts[-1]) if ts_np is None else (None, None)  # (_events reads them when traced only)
    got = _events(event_times, t0, t1, ts_np, checked)
    if got is None or not got[0].shape[0]:
        return None
    ev, evv = got
    if ts_np is not None and evv is not None:
        keep = (evv >= ts_np[0] - tol) & (evv <= ts_np[-1] + tol)
        if not np.any(keep):
            return None
        vals = np.clip(evv[keep], ts_np[0], ts_np[-1])
        return _Part("event", device_array(vals), device_array(np.ones(vals.shape, bool)), vals)
    if t0 is None:
        t0, t1 = ts[0], ts[-1]
    return _Part("event", jnp.clip(ev, t0, t1), (ev >= t0 - tol_rt) & (ev <= t1 + tol_rt), None)


def _refuse_saves_just_before(ts_np, vals, is_reset, is_event, tol):
    """``ValueError`` for a save time less than `tol` before a reset or an observer event (an update),
    but not at it to rounding (4 ulp): the schedule takes such a save time at the instant, where the
    state is the one after the jump, so the saved value would be that of a later time (an update 0.5 µs
    after a save time of a 1000 s horizon was seen in it).  A plant jump (a discontinuity of the vector
    field) leaves the state continuous, and is not refused."""
    jump = is_reset | is_event
    if not np.any(jump):
        return
    eps = float(np.finfo(np.float64).eps)
    ulps = TIME_ULPS * eps * max(abs(float(ts_np[0])), abs(float(ts_np[-1])))
    tau = vals[jump]
    lo = np.searchsorted(ts_np, tau - tol, side="left")
    hi = np.searchsorted(ts_np, tau - ulps, side="left")  # save times below τ − 4 ulp
    bad = np.flatnonzero(hi > lo)
    if bad.size:
        k = int(bad[0])
        i = int(lo[k])
        what = "reset" if is_reset[jump][k] else "observer update (event)"
        raise ValueError(
            f"save time ts[{i}] = {float(ts_np[i])!r} lies {tau[k] - ts_np[i]:.2e} before the {what} at "
            f"t = {float(tau[k])!r}, within the schedule's time tolerance {tol:.2e} (1e-9 of the horizon): it "
            "would be taken at that instant and show the state after the jump.  Put it onto the instant "
            f"(the state after it) or at least {tol:.2e} before it (the state before)."
        )


def _merge(ts, ts_np, tol, tol_rt, parts) -> Schedule:
    # (with constant save times, every array that is a constant too is made by NumPy and moved by
    # device_put: run eagerly, each JAX operation compiles a program on its first call in a process)
    if ts_np is None:
        t0, t1 = ts[0], ts[-1]
    else:
        t0, t1 = device_array(ts_np[0]), device_array(ts_np[-1])
    N = ts.shape[0]
    has_reset = any(p.kind == "reset" for p in parts)
    has_event = any(p.kind == "event" for p in parts)
    if not parts:
        no = device_array(np.zeros((0,), bool))
        concrete = None if ts_np is None else (np.zeros(0), *(np.zeros(0, bool),) * 3)
        first = device_array(np.asarray([0, N], np.int32))
        return Schedule(t0, t1, device_array(np.zeros((0,), ts.dtype)), no, no, no, first, N, False, False, concrete)
    # Breakpoints at one instant are ordered plant jumps first, then the rest in the order resets, events:
    # the segment before the instant then ends one float before it (the jump's rule), whatever else happens
    # there.  Were a reset first, the segment before would end exactly at the jump and its last stage would
    # see the vector field after it.
    is_jump_part = np.concatenate([np.full(p.times.shape, p.kind == "jump") for p in parts])
    if ts_np is not None and all(p.values is not None for p in parts):
        vals = np.concatenate([p.values for p in parts])
        order = np.lexsort((~is_jump_part, vals))  # stable; at a tie, a plant jump first (see below)
        np_flags = [
            np.concatenate([np.full(p.values.shape, p.kind == kind) for p in parts])[order]
            for kind in ("reset", "event", "jump")
        ]
        vals = vals[order]
        _refuse_saves_just_before(ts_np, vals, np_flags[0], np_flags[1], tol)
        first = np.concatenate([[0], np.searchsorted(ts_np, vals - tol, side="left"), [N]])
        window = max(1, int(np.max(np.diff(first))))
        # every breakpoint known: the times are the values and all of them act (see _Part)
        return Schedule(
            t0, t1, device_array(vals), *(device_array(f) for f in np_flags),
            device_array(first.astype(np.int32)), window, has_reset, has_event, (vals, *np_flags),
        )  # fmt: skip
    times = jnp.concatenate([p.times for p in parts])
    flags = [
        jnp.concatenate([p.active if p.kind == kind else jnp.zeros(p.active.shape, bool) for p in parts])
        for kind in ("reset", "event", "jump")
    ]
    order = jnp.lexsort((jnp.arange(times.shape[0]), ~jnp.asarray(is_jump_part), jax.lax.stop_gradient(times)))
    starts = jax.lax.stop_gradient(times[order])
    inner = jnp.searchsorted(ts, starts - tol_rt, side="left").astype(jnp.int32)
    first_save = jnp.concatenate([jnp.zeros(1, jnp.int32), inner, jnp.full(1, N, jnp.int32)])
    reset, event, jump = (f[order] for f in flags)
    return Schedule(t0, t1, times[order], reset, event, jump, first_save, N, has_reset, has_event, None)
