"""Value checks of observer gains, eager and under ``jit``.

Each check comes in two tiers: a concrete value fails at once with a ``ValueError`` that names the
gain, what was expected and what was found; a traced value (inside ``jit``, ``grad``, ``vmap``) is
guarded by ``eqx.error_if``, whose message names the gain and what was expected (the value itself is
not known when the message is written).  ``check()`` and ``prepare()`` of the observers call these,
so leaves updated by ``eqx.tree_at`` (which skips ``__check_init__``), e.g. in :func:`obsjax.tune`,
are re-validated.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._checks import concrete_value


def require_finite(x, name: str):
    """``ValueError`` when the concrete value of `x` holds NaN or inf; traced values pass (see
    :func:`traced_finite`)."""
    v = concrete_value(x)
    if v is not None and not np.all(np.isfinite(v)):
        raise ValueError(f"`{name}` must be finite (no NaN or inf), got {np.asarray(v).tolist()}.")
    return x


def positive_scalar(x, name: str, what: str = ""):
    """A finite x > 0: ``ValueError`` when concrete, ``eqx.error_if`` when traced.  `what`
    describes the gain, e.g. ``" (the reset period)"``."""
    v = concrete_value(x)
    if v is not None:
        if not np.all(np.isfinite(v)):
            raise ValueError(
                f"`{name}` must be > 0 and finite{what}, got {np.asarray(v).tolist()}."
            )
        if not np.all(v > 0):
            raise ValueError(f"`{name}` must be > 0{what}, got {np.asarray(v).tolist()}.")
        return x
    x = jnp.asarray(x)
    return eqx.error_if(
        x, jnp.any(~(x > 0) | ~jnp.isfinite(x)), f"`{name}` must be > 0 and finite{what}."
    )


def _scale(M):
    return jnp.maximum(1.0, jnp.max(jnp.abs(M)))


def spd_violation(M, *, semi: bool):
    """Traced predicate: M is not a finite symmetric positive (semi)definite matrix."""
    M = jnp.asarray(M)
    finite = jnp.all(jnp.isfinite(M))
    Ms = jnp.where(finite, M, 0.0)  # keep eigvalsh away from NaN
    sym = jnp.max(jnp.abs(Ms - Ms.T)) <= 1e-10 * _scale(Ms)
    lam = jnp.linalg.eigvalsh(0.5 * (Ms + Ms.T))
    definite = lam.min() >= -1e-12 * _scale(lam) if semi else lam.min() > 0
    return ~(finite & sym & definite)


def traced_spd(M, name: str, *, semi: bool, what: str = ""):
    """``eqx.error_if`` guard that M is a finite symmetric positive (semi)definite matrix."""
    kind = "positive semidefinite" if semi else "positive definite"
    return eqx.error_if(
        M, spd_violation(M, semi=semi), f"`{name}`{what} must be a finite symmetric {kind} matrix."
    )


def is_concrete(*xs) -> bool:
    return all(concrete_value(x) is not None for x in xs)


def traced_finite(x, name: str):
    """``eqx.error_if`` guard (survives jit) that every entry of `x` is finite; concrete values
    raise ``ValueError`` at once."""
    if concrete_value(x) is not None:
        return require_finite(x, name)
    x = jnp.asarray(x)
    return eqx.error_if(x, ~jnp.all(jnp.isfinite(x)), f"`{name}` must be finite (no NaN or inf).")
