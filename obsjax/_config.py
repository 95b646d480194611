"""float64 policy.

obsjax computes control designs in float64.  JAX's x64 mode is a process-wide flag, so obsjax sets it
exactly once, when ``obsjax`` is imported (the one global side effect of the import, documented in the
README).  Set ``OBSJAX_NO_X64=1`` before importing to opt out; every public entry point then raises
instead of silently computing a design in float32.
"""

import os

import jax

_X64_ENABLED_BY_OBSJAX = False


def enable_x64() -> None:
    global _X64_ENABLED_BY_OBSJAX
    if os.environ.get("OBSJAX_NO_X64", "") not in ("", "0"):
        return
    if not jax.config.read("jax_enable_x64"):
        jax.config.update("jax_enable_x64", True)
        _X64_ENABLED_BY_OBSJAX = True


def require_x64(where: str) -> None:
    if not jax.config.read("jax_enable_x64"):
        raise RuntimeError(
            f"{where} needs float64: obsjax computes control designs in double precision. "
            "Run `jax.config.update('jax_enable_x64', True)` before using obsjax "
            "(or unset OBSJAX_NO_X64)."
        )
