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
(``jax.debug.print``, progress bars, and ``eqx.error_if``'s checks traced into the program: an observer's
checks inside its vector field; diffrax's two checks of the save times are left out of obsjax's solves, see
:func:`obsjax._checks.without_diffrax_save_time_checks`, and the ``throw=True`` checks, and ``estimate``'s
check of traced sample times, run outside the program), nor
for one that compiled in less than ``min_compile_time_secs`` (0.2 s by default; the ``obsjax`` command
uses 0, so its second run compiles nothing).  Tracing and lowering run in every
process; only XLA's compilation is saved here (:mod:`obsjax._trace_cache` saves the traced programs of
``tune`` and ``monte_carlo`` beside it, when turned on).
"""

from __future__ import annotations

import os
import re
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


def host_tag(cpuinfo: str | None = None) -> str:
    """A short name of this machine's instruction set, the last component of the default directory.

    XLA:CPU compiles for the host it runs on (its instruction-set extensions: AVX-512, …), and jaxlib
    loads a cached executable compiled on another CPU with no more than a logged error: on a home
    directory shared by machines of different kinds (a cluster's login and compute nodes) a program
    compiled on one could stop with an illegal instruction on another.  The default directory is
    therefore one per kind of CPU: ``<machine>-<12 hex digits>``, a hash of the CPU's vendor, family,
    model and feature flags (``/proc/cpuinfo`` on Linux; ``platform.processor()`` elsewhere), with the
    jaxlib version beside them.  `cpuinfo`: the text of ``/proc/cpuinfo`` to use instead of the
    file's.
    """
    import hashlib
    import platform

    parts = [platform.machine(), platform.system()]
    try:
        import jaxlib

        parts.append(getattr(jaxlib, "__version__", ""))
    except ImportError:  # pragma: no cover - jax always brings jaxlib
        pass
    keys = ("vendor_id", "cpu family", "model", "flags", "features", "cpu implementer", "cpu part")
    seen: dict[str, str] = {}
    if cpuinfo is None:
        try:
            with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
                cpuinfo = f.read()
        except OSError:
            cpuinfo = ""
    for line in cpuinfo.splitlines():
        k, _, v = line.partition(":")
        k = k.strip().lower()
        if k in keys and k not in seen:  # the first processor's entry
            seen[k] = " ".join(sorted(v.split())) if k in ("flags", "features") else v.strip()
    if not seen:
        seen["processor"] = platform.processor()
    parts += [f"{k}={seen[k]}" for k in sorted(seen)]
    digest = hashlib.sha256("\n".join(parts).encode()).hexdigest()[:12]
    return f"{platform.machine() or 'cpu'}-{digest}"


def default_cache_dir() -> str:
    """The directory :func:`enable_compilation_cache` uses when given none.

    ``$OBSJAX_COMPILATION_CACHE_DIR`` when set (used as given); else, under the user cache directory,
    ``obsjax/jax-compilation-cache/<host>``: ``$XDG_CACHE_HOME/obsjax/...`` (``~/.cache/obsjax/...``
    when ``XDG_CACHE_HOME`` is unset) on Linux, ``~/Library/Caches/obsjax/...`` on macOS,
    ``%LOCALAPPDATA%\\obsjax\\...`` on Windows, where ``<host>`` is :func:`host_tag` (one directory
    per kind of CPU, so that a home directory shared by different machines never hands one machine's
    compiled code to another).
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
    return os.path.join(base, "obsjax", "jax-compilation-cache", host_tag())


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
    is lost).  A directory given explicitly (`path`, ``$OBSJAX_COMPILATION_CACHE_DIR``,
    ``$JAX_COMPILATION_CACHE_DIR``) should be used by one kind of CPU only (see :func:`host_tag`); the
    default directory is one per kind.

    On some x86 CPUs (AMD Zen 4, some Intel Xeons) jaxlib 0.9-0.10 logs an error line at every
    executable it reads from the cache, ``Target machine feature +prefer-no-gather is not supported on
    the host machine``: ``prefer-no-gather``/``prefer-no-scatter`` are LLVM tuning preferences, not
    instructions, and the executable, compiled on this machine, runs correctly (jax-ml/jax issue
    #38445).  The ``obsjax`` command drops exactly these lines from its error output; elsewhere
    ``TF_CPP_MIN_LOG_LEVEL=3`` set before importing jax silences them (with every other XLA log line).

    **Arguments:**

    - `path`: cache directory.  ``None``: ``$OBSJAX_COMPILATION_CACHE_DIR`` if set, else a directory
      already given to JAX (``JAX_COMPILATION_CACHE_DIR``), else :func:`default_cache_dir`:
      ``$XDG_CACHE_HOME/obsjax/jax-compilation-cache/<host>`` (``~/.cache/...`` when unset) on
      Linux, ``~/Library/Caches/obsjax/jax-compilation-cache/<host>`` on macOS,
      ``%LOCALAPPDATA%\\obsjax\\...`` on Windows, ``<host>`` naming the kind of CPU.
    - `min_compile_time_secs`: programs whose compilation took less are not written (JAX's default
      is 1 s, above the compile time of most single simulations; 0.2 s by default here).

    **Returns:** the cache directory in use, or ``None`` when opted out.

    **Example:**::

        import obsjax
        obsjax.enable_compilation_cache()   # e.g. ~/.cache/obsjax/jax-compilation-cache/x86_64-3f…
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


#: XLA:CPU's complaint, at every executable read from the cache on some x86 CPUs, about LLVM *tuning*
#: preferences recorded at compilation (not instruction-set extensions): harmless on the machine that
#: compiled it (jax-ml/jax issue #38445, openxla/xla issue #44565).  A line naming a real feature is
#: not matched.
_BENIGN_LOG = re.compile(
    rb"cpu_aot_loader\.cc:\d+\] Loading XLA:CPU AOT result\. Target machine feature "
    rb"\+(prefer-no-gather|prefer-no-scatter) is not +supported on the host machine"
)
#: the start of an absl/glog line (``E1123 09:06:28.463150   23527 file.cc:195] ...``), possibly cut
_LOG_PREFIX = re.compile(rb"^[IWEF](\d{0,4}|\d{4} [\d:.]*( +\d*)?)$|^[IWEF]\d{4} [\d:.]+ +\d+ ")


class quiet_benign_cache_log:
    """Context manager: drop XLA's harmless ``+prefer-no-gather``/``+prefer-no-scatter`` lines (see
    :func:`enable_compilation_cache`) from what this process, and the processes it starts, write to
    file descriptor 2; everything else passes unchanged and in order.  Used by the ``obsjax`` command.

    File descriptor 2 is pointed at a pipe read by a thread that forwards to the original standard
    error: complete lines unless they match exactly the benign message, and an unfinished line at
    once unless it may be the start of a log line (progress bars that redraw with ``\\r`` are not
    held back).  Where the pipe cannot be set up it does nothing.
    """

    def __init__(self, fd: int = 2):
        self.fd = fd
        self._saved = None

    def __enter__(self):
        import threading

        try:
            sys.stderr.flush()
            saved = os.dup(self.fd)
            r, w = os.pipe()
            os.dup2(w, self.fd)
            os.close(w)
        except (OSError, ValueError, AttributeError):
            return self
        self._saved, self._r = saved, r
        self._thread = threading.Thread(target=self._pump, name="obsjax-stderr", daemon=True)
        self._thread.start()
        return self

    def _write(self, data: bytes) -> None:
        while data:
            try:
                n = os.write(self._saved, data)
            except OSError:
                return
            data = data[n:]

    def _pump(self) -> None:
        buf = b""
        while True:
            try:
                chunk = os.read(self._r, 65536)
            except OSError:
                chunk = b""
            if not chunk:
                break
            buf += chunk
            *lines, buf = buf.split(b"\n")
            out = b"".join(line + b"\n" for line in lines if not _BENIGN_LOG.search(line))
            if buf and not _LOG_PREFIX.match(buf):
                out, buf = out + buf, b""
            self._write(out)
        if buf and not _BENIGN_LOG.search(buf):
            self._write(buf)

    def __exit__(self, *exc):
        if self._saved is None:
            return False
        try:
            sys.stderr.flush()
        except (OSError, ValueError):
            pass
        os.dup2(self._saved, self.fd)  # closes the pipe's last write end in this process
        self._thread.join(timeout=10.0)
        os.close(self._r)
        os.close(self._saved)
        self._saved = None
        return False
