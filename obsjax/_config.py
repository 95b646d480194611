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


# --------------------------------------------------------------------------------------------------------
# jaxlib releases known to compute wrong results or crash on the CPU
# --------------------------------------------------------------------------------------------------------

#: jaxlib versions whose XLA:CPU YNNPACK fusions (``__ynn_fusion``) return wrong values without a word
#: (a jitted ``vmap`` of a matrix-vector product followed by a reduction, 16,385 rows: the last row off
#: by 0.8 % in float64 on this project's machines) and abort or crash the process on a worker thread, so
#: that the Python traceback points at whatever the main thread was doing (compiling, serialising a cache
#: entry, copying a result).  The project's pyproject.toml excludes them; this guard covers an
#: environment that installed one anyway.
BAD_CPU_JAXLIB = ("0.10.2",)
#: the XLA flag that keeps XLA:CPU from forming YNNPACK fusions (an empty list of fusion types)
YNN_OFF_FLAG = "--xla_cpu_experimental_ynn_fusion_type="


class JaxlibWarning(RuntimeWarning):
    """The installed jaxlib is known to compute wrong results or crash on the CPU."""


def _ynn_disabled(xla_flags: str) -> bool:
    return any(f == YNN_OFF_FLAG for f in xla_flags.split())


def check_jaxlib(version: str | None = None, xla_flags: str | None = None) -> str | None:
    """Warn (:class:`JaxlibWarning`) when ``jaxlib`` is a release in :data:`BAD_CPU_JAXLIB` and
    ``XLA_FLAGS`` does not turn its YNNPACK fusions off; returns the message, or None.

    Called once by ``import obsjax``.  It changes nothing: the remedy is another jaxlib (``pip install
    "jax!=0.10.2"``) or ``XLA_FLAGS=--xla_cpu_experimental_ynn_fusion_type=`` set before JAX starts.
    """
    import warnings

    if version is None:
        try:
            import jaxlib

            version = jaxlib.__version__
        except (ImportError, AttributeError):  # pragma: no cover - jax always ships jaxlib
            return None
    if xla_flags is None:
        xla_flags = os.environ.get("XLA_FLAGS", "")
    if version not in BAD_CPU_JAXLIB or _ynn_disabled(xla_flags):
        return None
    msg = (
        f"jaxlib {version} is known to return wrong values on the CPU (a jitted vmap of a "
        "matrix-vector product followed by a reduction) and to abort the process from XLA's YNNPACK "
        "fusions; obsjax's results on the CPU backend cannot be trusted with it. Install another "
        f"release (pip install \"jax!={version}\" \"jaxlib!={version}\") or set "
        f"XLA_FLAGS={YNN_OFF_FLAG} before JAX starts."
    )
    warnings.warn(msg, JaxlibWarning, stacklevel=3)
    return msg
