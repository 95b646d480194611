"""The observer protocol."""

from __future__ import annotations

import abc

import equinox as eqx
import numpy as np

from .._checks import concrete_value


class AbstractObserver(eqx.Module):
    """An observer: a pure vector field over its own state pytree ``z``.

    Subclasses implement

    - ``init(t0, xhat0, y0) -> z0``: the observer state at t0 from an initial guess x̂(t0) and y(t0);
    - ``vector_field(t, z, y, u) -> dz/dt``: the law, pure and jit/vmap/grad-safe; ``y`` is the
      measurement (noise included) and ``u`` the plant input;
    - ``estimate(t, z, y) -> x̂(t)`` (reduced-order observers use ``y``).

    Hybrid observers (covariance reset, windows) also override

    - ``reset_period`` (a property returning the period T, itself a differentiable leaf), and
    - ``reset(t, z) -> z⁺``, the jump applied at t = t0 + kT (k ≥ 1, t < t1).

    Sampled-data observers (a continuous–discrete Kalman filter, an observer corrected at measurement
    instants) override

    - ``event_times(t0, t1)``: the instants of their discrete updates on the horizon [t0, t1], and
    - ``update(t, z, y, u) -> z⁺``, the update applied at each of them with the measurement y(t).

    :func:`obsjax.simulate` integrates segment by segment between all breakpoints (reset instants, the
    plant's ``jump_ts``, event times), so no solve ever steps across a discontinuity of the joint system.
    At a breakpoint the reset comes first, then the event update; the state saved at a save time that
    coincides with a breakpoint is the state after it (right-continuous).

    ``prepare()`` is called once per :func:`obsjax.simulate` before the solve; observers whose gains are
    derived from design parameters (poles → gain by :func:`obsjax.design.place`) compute them there, so the
    design is done once per solve, inside the differentiated graph, and not at every step.

    Gains are array leaves (never static): ``eqx.filter_grad``, ``jax.vmap`` and :func:`obsjax.tune` see
    them.  Only dimensions and flags are static.
    """

    @abc.abstractmethod
    def init(self, t0, xhat0, y0):
        raise NotImplementedError

    @abc.abstractmethod
    def vector_field(self, t, z, y, u):
        raise NotImplementedError

    @abc.abstractmethod
    def estimate(self, t, z, y):
        raise NotImplementedError

    @property
    def reset_period(self):
        """Period T of the resets at t0 + kT, or ``None`` for a smooth observer."""
        return None

    def target(self, t, x):
        """The quantity the estimate tracks: x itself, or a functional of it (``Trajectory.error`` is
        ``estimate − target``)."""
        return x

    def reset(self, t, z):
        """State just after a reset at time t (identity for smooth observers)."""
        return z

    def event_times(self, t0, t1):
        """Instants of this observer's discrete updates on the horizon [t0, t1], or ``None`` (no events).

        **Arguments:** `t0`, `t1`: the horizon (Python floats when the save times are concrete, traced
        scalars inside ``jit``).

        **Returns:** ``None`` or a 1-D array of non-decreasing times.  Its length must be known before
        tracing (it sets the number of segments; with a traced horizon return a fixed number of times, those
        past t1 are ignored).  Return NumPy values when the horizon is concrete: times known before tracing
        let ``simulate`` use the fixed-step scan and size its save windows; traced times (JAX arrays, or
        values that depend on traced leaves) are merged at run time by the diffrax back-end, whose segment
        ends then follow them (differentiably).  Times outside [t0, t1] are ignored; an event at t0 is
        applied right after ``init``, one at t1 before the last save; a time listed twice is applied twice.
        """

    def update(self, t, z, y, u):
        """Discrete update z⁺ at an event time t (identity by default).

        `y` is the measurement at t (h(t, x, u) plus band-limited noise; white noise has no pointwise
        value, so under :class:`obsjax.noise.WhiteNoise` the update sees the noise-free output), `u` the
        plant input at t (open loop plus ``controller(t, x̂)`` with x̂ from the state before the update).  Pure and jit/vmap/grad-safe, like
        ``vector_field``.
        """
        return z

    def prepare(self) -> "AbstractObserver":
        """Precompute gains from design parameters (once per simulation)."""
        return self

    def check_span(self, t0: float, t1: float) -> "AbstractObserver":
        """Validate the observer on the span [t0, t1] of one simulation (called by :func:`obsjax.simulate`,
        :func:`obsjax.simulate_batch` and :func:`obsjax.estimate` after :meth:`prepare`, when the save
        times are concrete), returning the observer to simulate.  Nothing by default; observers whose
        validity depends on time (the Lovass-Nagy observers' T(t), invertible and solving their
        condition) raise ``ValueError`` there, or return themselves guarded by ``eqx.error_if`` when
        their values are traced."""
        return self

    def check(self) -> "AbstractObserver":
        """Re-validate invariants (``tune`` calls it after updating leaves with ``eqx.tree_at``)."""
        return self


def feedthrough(model, u):
    """D u of a model with a feedthrough matrix ``D`` (an LTI plant), 0 otherwise (LTV plants have none).

    The observers written with y = C x (Kalman–Bucy, the least-squares observer, the continuous-discrete
    filter) compare y with C x̂ + D u: without it a plant with D ≠ 0 left a constant bias in the estimate
    (1.40 for D = 1, u = 1 in the Kalman–Bucy filter), reported as a success."""
    D = getattr(model, "D", None)
    if D is None or u is None or getattr(model, "p", 0) == 0:
        return 0.0
    return D @ u


def require_no_feedthrough(model, who):
    """Refuse an LTI model with feedthrough D ≠ 0 for an observer built on y = C x alone, whose estimate
    would otherwise carry a bias of D u without a word (the Lovass-Nagy observers and the LTV
    finite-window observer read y where C x is meant).  A traced D is not checked."""
    D = getattr(model, "D", None)
    Dv = None if D is None else concrete_value(D)
    if Dv is not None and np.any(np.asarray(Dv) != 0):
        raise ValueError(
            f"{who} needs a model without feedthrough: `D` must be 0, got max |D| = "
            f"{float(np.max(np.abs(Dv))):.3g}. Give it the measurement y − D u and a model with D = 0."
        )
