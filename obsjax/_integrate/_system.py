"""The joint plant–observer system that every back-end integrates.

    ẋ = f(t, x, u),   y = h(t, x, u) + v,   ż = observer.vector_field(t, z, y, u),
    x̂ = observer.estimate(t, z, y),   u = u(t) + controller(t, x̂),

with the state (x, z).  At a breakpoint of the schedule (``_schedule.py``) the state jumps:
``observer.reset`` at a reset instant, then ``observer.update`` at an event time (:func:`act`).
"""

from __future__ import annotations

from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from ..observers._base import AbstractObserver
from ..systems._plants import AbstractSystem


class Args(eqx.Module):
    """Everything the vector field reads besides (t, x, z).

    ``content`` (static) is a digest of the non-array part -- the plant's and observer's static fields,
    the input and controller functions with the globals they read (:func:`with_content`) -- so that every
    compiled solve keyed on these arguments (diffrax's ``diffeqsolve``, the fixed-step drift) is traced
    again when a function reads a global that changed since the last call, instead of being served the
    program traced with the old value (functions are otherwise keyed by identity)."""

    plant: AbstractSystem
    observer: AbstractObserver
    u: Callable | None
    controller: Callable | None
    noise_path: Callable | None
    content: str = eqx.field(static=True, default="")


def with_content(plant, observer, u, controller, noise_path) -> Args:
    """:class:`Args` with its content digest (see there)."""
    from ..montecarlo._fingerprint import content_key

    return Args(plant, observer, u, controller, noise_path, content_key((plant, observer, u, controller)))


def open_loop_input(args: Args, t):
    plant = args.plant
    return jnp.zeros((plant.p,)) if args.u is None else jnp.asarray(args.u(t)).reshape(plant.p)


def signals(args: Args, t, x, z):
    """Inputs, measurement and estimate at time t (the algebraic part of the loop): (u, y, x̂)."""
    plant, obs = args.plant, args.observer
    u_ol = open_loop_input(args, t)
    v = 0.0 if args.noise_path is None else args.noise_path(t)
    if args.controller is None:
        y = plant.h(t, x, u_ol) + v
        return u_ol, y, obs.estimate(t, z, y)
    # Output feedback: the estimate uses y at the open-loop input (exact when D = 0).
    y1 = plant.h(t, x, u_ol) + v
    xhat = obs.estimate(t, z, y1)
    u = u_ol + jnp.asarray(args.controller(t, xhat)).reshape(plant.p)
    y = plant.h(t, x, u) + v
    return u, y, obs.estimate(t, z, y)


def drift(t, state, args: Args):
    x, z = state
    u, y, _ = signals(args, t, x, z)
    return args.plant.f(t, x, u), args.observer.vector_field(t, z, y, u)


_BY_MODE: dict = {}


def for_check_mode(fn):
    """`fn`, or one function object per mode of equinox's runtime checks (``eqx.error_if``).

    diffrax caches the trace of ``diffeqsolve`` by its terms, i.e. by the vector field's function object.  A
    solve traced with the checks in another mode (``monte_carlo`` traces its kernels with the checks as NaN,
    so that a failing check marks a trajectory failed instead of raising, and no host callback serialises
    its shards) must neither reuse a trace made in raise mode nor leave its own to a later call in raise
    mode: outside raise mode each mode gets its own function object (created once, so traces are still
    shared within a mode).
    """
    try:
        import equinox._errors as E

        mode = E.EQX_ON_ERROR
    except (ImportError, AttributeError):  # pragma: no cover
        return fn
    if mode == "raise":
        return fn
    key = (fn, mode)
    if key not in _BY_MODE:
        _BY_MODE[key] = lambda t, y, a: fn(t, y, a)
    return _BY_MODE[key]


def initial_state(args: Args, t0, x0, xhat0):
    """(x0, z0) with z0 = observer.init(t0, x̂0, y(t0)) at the open-loop input."""
    plant = args.plant
    u0 = open_loop_input(args, t0)
    v0 = 0.0 if args.noise_path is None else args.noise_path(t0)
    return x0, args.observer.init(t0, xhat0, plant.h(t0, x0, u0) + v0)


def act(args: Args, t, state, do_reset, do_event, has_reset: bool, has_event: bool):
    """The jump of the state at a breakpoint t: ``reset`` if `do_reset`, then ``update`` if `do_event`.

    `has_reset`, `has_event` (static) say whether the schedule holds any such breakpoint at all, so a
    smooth observer's scan carries no branch for them.
    """
    x, z = state
    obs = args.observer
    if has_reset:
        z = jax.lax.cond(do_reset, lambda zz: obs.reset(t, zz), lambda zz: zz, z)
    if has_event:

        def upd(zz):
            u, y, _ = signals(args, t, x, zz)
            return obs.update(t, zz, y, u)

        z = jax.lax.cond(do_event, upd, lambda zz: zz, z)
    return x, z


class MeasurementNoiseTerm(diffrax.AbstractTerm):
    """Diffusion of white measurement noise: d(x, z) ⊃ (0, ∂ż/∂y · σ dW).

    ``vf_prod`` is a Jacobian-vector product of the observer's vector field in y (no Jacobian is formed).
    """

    sigma: jax.Array
    path: diffrax.AbstractPath

    def vf(self, t, state, args):
        x, z = state
        u, y, _ = signals(args, t, x, z)
        jac = jax.jacfwd(lambda yy: args.observer.vector_field(t, z, yy, u))(y)
        s = jnp.broadcast_to(self.sigma, y.shape)
        return jnp.zeros(x.shape + y.shape, x.dtype), jax.tree_util.tree_map(lambda j: j * s, jac)

    def contr(self, t0, t1, **kwargs):
        return self.path.evaluate(t0, t1, **kwargs)

    def prod(self, vf, control):
        return jax.tree_util.tree_map(lambda j: j @ control, vf)

    def vf_prod(self, t, state, args, control):
        x, z = state
        u, y, _ = signals(args, t, x, z)
        dy = jnp.broadcast_to(self.sigma, y.shape) * control
        _, dz = jax.jvp(lambda yy: args.observer.vector_field(t, z, yy, u), (y,), (dy,))
        return jnp.zeros_like(x), dz
