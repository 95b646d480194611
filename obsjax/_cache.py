"""JAX's persistent compilation cache, turned on by one call.

A JAX program compiles each jitted function once per process; XLA's compilation of an adaptive solve
takes seconds.  With the persistent compilation cache, compiled executables are written to a
directory and read back by later processes that compile the same program (same jax/jaxlib version,
backend, flags and HLO).

Importing obsjax does not turn the cache on (no global side effect beyond float64).  The ``obsjax``
command, the test suite and the notebooks turn it on (the notebooks with a call in their first cell);
a library user calls :func:`enable_compilation_cache` once.  ``OBSJAX_NO_COMPILATION_CACHE=1`` turns
every one of these off.  (It was opt-in while two CI runs aborted inside ``executable.serialize()``
and ``deserialize_executable``; the causes were jaxlib 0.10.2's YNNPACK fusions crashing on an XLA
worker thread, see :data:`obsjax._config.BAD_CPU_JAXLIB`, and the memory mappings that compiled
programs accumulate in a long process, see the README's "Long processes": both dealt with.)

What is not cached: JAX writes no entry for a program that carries host callbacks
(``jax.debug.print``, progress bars, and ``eqx.error_if``'s checks, which ``throw=True`` adds), nor
for one that compiled in less than ``min_compile_time_secs``.  Tracing and lowering run in every
process; only XLA's compilation is saved.
"""

from __future__ import annotations

import os
import sys

import jax

#: environment variable that turns every obsjax-initiated use of the cache off
OPT_OUT = "OBSJAX_NO_COMPILATION_CACHE"
#: environment variable naming the cache directory (overrides the default)
DIR_ENV = "OBSJAX_COMPILATION_CACHE_DIR"
#: programs that compile faster than this are not written (JAX's own default is 1 s)
MIN_COMPILE_TIME_SECS = 0.2


def _flag(name: str):
    return getattr(jax.config, name)


def _opted_out() -> bool:
    return os.environ.get(OPT_OUT, "").strip().lower() not in ("", "0", "false", "no")


def default_cache_dir() -> str:
    """The directory :func:`enable_compilation_cache` uses when given none.

    ``$OBSJAX_COMPILATION_CACHE_DIR`` when set; else the user cache directory:
    ``$XDG_CACHE_HOME/obsjax/jax-compilation-cache`` (``~/.cache/obsjax/jax-compilation-cache``
    when ``XDG_CACHE_HOME`` is unset) on Linux, ``~/Library/Caches/obsjax/jax-compilation-cache`` on
    macOS, ``%LOCALAPPDATA%\\obsjax\\jax-compilation-cache`` on Windows.
    """
    given = os.environ.get(DIR_ENV, "").strip()
    if given:
        return os.path.abspath(os.path.expanduser(given))
    home = os.path.expanduser("~")
    if sys.platform == "win32":
        base = os.environ.get("LOCALAPPDATA") or os.path.join(home, "AppData", "Local")
    elif sys.platform == "darwin":
        base = os.path.join(home, "Library", "Caches")
    else:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(home, ".cache")
    return os.path.join(base, "obsjax", "jax-compilation-cache")


def enable_compilation_cache(
    path: str | os.PathLike | None = None, *, min_compile_time_secs: float = MIN_COMPILE_TIME_SECS
) -> str | None:
    """Turn on JAX's persistent compilation cache, so that later processes skip XLA's compilation.

    Sets JAX's ``jax_compilation_cache_dir`` and ``jax_persistent_cache_min_compile_time_secs``;
    call it once, before the first compilation whose result should be saved (programs compiled
    earlier in the process are not written back).  Calling it again with another directory switches
    to that directory.

    Opt out with the environment variable ``OBSJAX_NO_COMPILATION_CACHE=1``: this function then
    changes nothing and returns ``None`` (the ``obsjax`` command, the test suite and the notebooks
    call it, so the variable turns the cache off for all of them).  JAX's own ``JAX_ENABLE_COMPILATION_CACHE=false`` is
    respected the same way.

    The cache directory is trusted: an executable read from it runs in this process, so it must not
    be writable by other users.  It is not size-limited; delete it to free the space (nothing else
    is lost).

    **Arguments:**

    - `path`: cache directory.  ``None``: ``$OBSJAX_COMPILATION_CACHE_DIR`` if set, else a directory
      already given to JAX (``JAX_COMPILATION_CACHE_DIR``), else a directory under the user cache
      directory: ``$XDG_CACHE_HOME/obsjax/jax-compilation-cache`` (``~/.cache/...`` when unset) on
      Linux, ``~/Library/Caches/obsjax/jax-compilation-cache`` on macOS,
      ``%LOCALAPPDATA%\\obsjax\\...`` on Windows.
    - `min_compile_time_secs`: programs whose compilation took less are not written (JAX's default
      is 1 s, above the compile time of most single simulations; 0.2 s by default here).

    **Returns:** the cache directory in use, or ``None`` when opted out.

    **Example:**::

        import obsjax
        obsjax.enable_compilation_cache()   # e.g. ~/.cache/obsjax/jax-compilation-cache
    """
    if not min_compile_time_secs >= 0:
        raise ValueError(f"`min_compile_time_secs` must be >= 0, got {min_compile_time_secs}.")
    if _opted_out() or not _flag("jax_enable_compilation_cache"):
        return None
    if path is None:
        path = (
            os.environ.get(DIR_ENV, "").strip()
            or _flag("jax_compilation_cache_dir")
            or default_cache_dir()
        )
    path = os.path.abspath(os.path.expanduser(os.fspath(path)))
    os.makedirs(path, exist_ok=True)
    current = _flag("jax_compilation_cache_dir")
    if current and os.path.abspath(current) != path:
        # JAX opens its cache once per process; switching directories needs a reset.
        from jax.experimental.compilation_cache import compilation_cache as cc

        cc.reset_cache()
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_secs))
    return path


def cache_environment(path: str) -> dict[str, str]:
    """Environment variables that give a child process (a notebook kernel, a benchmark) the same
    cache: JAX reads them when it is imported."""
    return {
        "JAX_COMPILATION_CACHE_DIR": path,
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": repr(
            float(_flag("jax_persistent_cache_min_compile_time_secs"))
        ),
    }
