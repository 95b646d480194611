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

from .._checks import (
    concrete_value,
    require_finite,  # the observers import the eager check from here
)
from .._checks import is_concrete as _tree_is_concrete


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
    """The magnitude the symmetry and semidefiniteness tolerances are relative to (no floor: a covariance
    of 1e-12 km² is checked as strictly as one of 1 m²)."""
    return jnp.max(jnp.abs(M))


def equilibrated(M, xp=jnp):
    """(M̂, d): M̂ = D⁻¹ M D⁻¹ with D = diag(√M_ii) (1 where M_ii ≤ 0), the matrix the symmetry and
    definiteness verdicts are taken on.  Positive (semi)definiteness and symmetry are invariant under
    M ↦ D M D (a change of state units), and so is M̂ (up to the sign of D); the raw matrix's smallest
    eigenvalue is not: a P0 with eigenvalues 0.6 … 22 read −4.8e-8 with states in units 1e-4 … 1e4."""
    diag = xp.diagonal(M)
    d = xp.sqrt(xp.where(diag > 0, diag, 1.0))
    return M / d[:, None] / d[None, :], diag


def _spd_verdict(M, semi: bool, xp):
    """Symmetric to 1e-10 of its largest entry and positive definite (semidefinite to 1e-12 of its
    largest eigenvalue), on M as given."""
    sym = xp.max(xp.abs(M - M.T)) <= 1e-10 * xp.max(xp.abs(M))
    lam = xp.linalg.eigvalsh(0.5 * (M + M.T))
    definite = lam.min() >= -1e-12 * xp.max(xp.abs(lam)) if semi else lam.min() > 0
    return sym & definite


def spd_ok(M, semi: bool, xp=jnp):
    """M (finite) passes as a symmetric positive (semi)definite matrix: on M as given, or on the
    equilibrated M̂ (:func:`equilibrated`).  Either suffices: the equilibrated test accepts what the raw
    one refuses only through the spread of the units (a P0 in units 1e-4 … 1e4), and the raw test
    accepts what the equilibrated one refuses only through rounding that equilibration magnifies (diag(0,
    1) rotated and back: off-diagonal residue 1e-17 against a diagonal entry 1e-17)."""
    Me, diag = equilibrated(M, xp)
    ok_eq = _spd_verdict(Me, semi, xp) & (xp.all(diag >= 0) if semi else xp.all(diag > 0))
    return _spd_verdict(M, semi, xp) | ok_eq


def spd_violation(M, *, semi: bool):
    """Traced predicate: M is not a finite symmetric positive (semi)definite matrix (:func:`spd_ok`)."""
    M = jnp.asarray(M)
    finite = jnp.all(jnp.isfinite(M))
    return ~(finite & spd_ok(jnp.where(finite, M, 0.0), semi))  # keep eigvalsh away from NaN


def traced_spd(M, name: str, *, semi: bool, what: str = ""):
    """``eqx.error_if`` guard that M is a finite symmetric positive (semi)definite matrix."""
    kind = "positive semidefinite" if semi else "positive definite"
    return eqx.error_if(
        M, spd_violation(M, semi=semi), f"`{name}`{what} must be a finite symmetric {kind} matrix."
    )


def is_concrete(*xs) -> bool:
    return _tree_is_concrete(xs)


def traced_finite(x, name: str):
    """``eqx.error_if`` guard (survives jit) that every entry of `x` is finite; concrete values
    raise ``ValueError`` at once."""
    if concrete_value(x) is not None:
        return require_finite(x, name)
    x = jnp.asarray(x)
    return eqx.error_if(x, ~jnp.all(jnp.isfinite(x)), f"`{name}` must be finite (no NaN or inf).")


def check_covariance_value(v, name: str, *, semi: bool) -> None:
    """Eager check of a concrete covariance: symmetric to 1e-10, and positive definite (or semidefinite
    to 1e-12 of its largest eigenvalue), on v as given or on the equilibrated matrix D⁻¹ v D⁻¹,
    D = diag(√v_ii) (:func:`spd_ok`): relative throughout, so neither an absolute floor (a non-symmetric
    or indefinite matrix of scale 1e-12 was accepted) nor the spread of the state units (a positive
    definite P0 in units 1e-4 … 1e4 was refused) decides."""
    v = np.asarray(v, dtype=float)
    if not v.size:
        raise ValueError(f"`{name}` must be a non-empty matrix, got shape {v.shape}.")
    if bool(spd_ok(v, semi, np)):
        return
    w, diag = equilibrated(v, np)
    big = float(np.max(np.abs(w)))
    if float(np.max(np.abs(w - w.T), initial=0.0)) > 1e-10 * big:
        raise ValueError(f"`{name}` must be symmetric, got {v.tolist()}.")
    ev = np.linalg.eigvalsh(0.5 * (w + w.T))
    raw = np.linalg.eigvalsh(0.5 * (v + v.T)).tolist()
    kind = "semidefinite" if semi else "definite"
    raise ValueError(
        f"`{name}` must be positive {kind}, got eigenvalues {raw} (of the equilibrated matrix "
        f"D⁻¹{name}D⁻¹, D = diag(√{name}_ii): {ev.tolist()})."
    )
