"""The observer protocol."""

from __future__ import annotations

import abc

import equinox as eqx


class AbstractObserver(eqx.Module):
    """An observer: a pure vector field over its own state pytree ``z``.

    Subclasses implement

    - ``init(t0, xhat0, y0) -> z0``: the observer state at t0 from an initial guess x̂(t0) and y(t0);
    - ``vector_field(t, z, y, u) -> dz/dt``: the law, pure and jit/vmap/grad-safe; ``y`` is the
      measurement (noise included) and ``u`` the plant input;
    - ``estimate(t, z, y) -> x̂(t)`` (reduced-order observers use ``y``).

    Hybrid observers (covariance reset, windows) also override

    - ``reset_period`` (a property returning the period T, itself a differentiable leaf), and
    - ``reset(t, z) -> z⁺``, the jump applied at t = t0 + kT.

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

    def prepare(self) -> "AbstractObserver":
        """Precompute gains from design parameters (once per simulation)."""
        return self

    def check(self) -> "AbstractObserver":
        """Re-validate invariants (``tune`` calls it after updating leaves with ``eqx.tree_at``)."""
        return self
