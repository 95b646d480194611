"""Checkpoint files of :func:`obsjax.monte_carlo`: atomic writes, per-file checksums, named damage.

Layout of a checkpoint directory::

    meta.json         format, fingerprint, study_id, n, chunk_size, n_chunks, checksum
    chunk_000000.npz  error_norm (rows, T), status (rows,), fingerprint, chunk, checksum
    ...

Every file is written to a temporary name in the same directory, flushed to disk and renamed over
its final name (``os.replace``), so a reader sees either the old file or the complete new one.  Each
file carries a SHA-256 checksum of its content, and each chunk also the fingerprint of the study
that computed it and its own index, so that a chunk is loaded only into the study and the slot it
belongs to.
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings

import numpy as np

from ._fingerprint import FORMAT


class CheckpointWarning(UserWarning):
    """A damaged checkpoint file was found (named in the message) and is being rebuilt."""


def chunk_path(ckpt: str, c: int) -> str:
    return os.path.join(ckpt, f"chunk_{c:06d}.npz")


def _fsync_dir(path: str) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover  (platforms without directory file descriptors)
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


def _atomic_write(path: str, write) -> None:
    """``write(fh)`` into a temporary file beside `path`, fsync, then rename over `path`."""
    tmp = f"{path}.tmp{os.getpid()}"
    try:
        with open(tmp, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    _fsync_dir(os.path.dirname(path) or ".")


def _chunk_checksum(fp: str, c: int, error_norm: np.ndarray, status: np.ndarray) -> str:
    h = hashlib.sha256()
    shapes = f"{error_norm.dtype.str}{error_norm.shape}|{status.dtype.str}{status.shape}"
    h.update(f"{fp}|chunk={c}|{shapes}|".encode())
    h.update(np.ascontiguousarray(error_norm).tobytes())
    h.update(np.ascontiguousarray(status).tobytes())
    return h.hexdigest()


def write_chunk(ckpt: str, c: int, fp: str, error_norm, status) -> None:
    en = np.asarray(error_norm, dtype=np.float64)
    st = np.asarray(status, dtype=np.int32)
    arrays = dict(
        error_norm=en,
        status=st,
        fingerprint=np.array(fp),
        chunk=np.array(c, dtype=np.int64),
        checksum=np.array(_chunk_checksum(fp, c, en, st)),
    )
    _atomic_write(chunk_path(ckpt, c), lambda fh: np.savez(fh, **arrays))


def _read_chunk(path: str, fp: str, c: int, rows: int, T: int):
    """(error_norm, status, problem): problem is None, ``"other study"`` or why the file is
    damaged."""
    try:
        with np.load(path, allow_pickle=False) as data:
            en = np.asarray(data["error_norm"])
            st = np.asarray(data["status"])
            file_fp = str(data["fingerprint"])
            file_c = int(data["chunk"])
            checksum = str(data["checksum"])
    except Exception as e:  # noqa: BLE001  (a truncated zip, a missing entry, a corrupt stream, ...)
        return None, None, f"unreadable: {type(e).__name__}: {e}"
    expected = (np.dtype(np.float64), np.dtype(np.int32), (rows, T), (rows,))
    if (en.dtype, st.dtype, en.shape, st.shape) != expected:
        why = (
            f"unexpected content: error_norm {en.dtype}{en.shape}, status {st.dtype}{st.shape}, "
            f"expected float64({rows}, {T}) and int32({rows},)"
        )
        return None, None, why
    if checksum != _chunk_checksum(file_fp, file_c, en, st):
        return None, None, "checksum mismatch (the file was altered or partly written)"
    if file_fp != fp:
        return None, None, "other study"
    if file_c != c:
        return None, None, f"it holds chunk {file_c}, not chunk {c} (a renamed file)"
    return en, st, None


def _meta_checksum(meta: dict) -> str:
    body = {k: v for k, v in meta.items() if k != "checksum"}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def _read_meta(path: str):
    """(meta, problem): meta is None when the file is missing (problem None) or damaged (problem
    says why)."""
    if not os.path.exists(path):
        return None, None
    try:
        with open(path, encoding="utf-8") as fh:
            meta = json.load(fh)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        return None, f"unreadable: {type(e).__name__}: {e}"
    if not isinstance(meta, dict):
        return None, f"unexpected content of type {type(meta).__name__}"
    if "format" not in meta and "version" in meta:
        raise ValueError(
            f"checkpoint directory {os.path.dirname(path)!r} was written by an earlier obsjax "
            f"(checkpoint format {meta.get('version')}), whose fingerprint did not cover the "
            "samplers' code and closures, the plant's callables or static fields: its chunks "
            "cannot be trusted to belong to this study. Delete it or choose another path."
        )
    if meta.get("checksum") != _meta_checksum(meta):
        return None, "checksum mismatch (the file was altered or partly written)"
    if meta.get("format") != FORMAT:
        raise ValueError(
            f"checkpoint directory {os.path.dirname(path)!r} has checkpoint format "
            f"{meta.get('format')!r}, this obsjax writes format {FORMAT}: delete it or choose "
            "another path."
        )
    return meta, None


def _write_meta(path: str, fp: str, study_id, n: int, chunk: int, n_chunks: int) -> None:
    meta = {
        "format": FORMAT,
        "fingerprint": fp,
        "study_id": study_id,
        "n": n,
        "chunk_size": chunk,
        "n_chunks": n_chunks,
    }
    meta["checksum"] = _meta_checksum(meta)
    data = json.dumps(meta, indent=1, sort_keys=True).encode()
    _atomic_write(path, lambda fh: fh.write(data))


def read_checkpoint(ckpt, fp, study_id, n, chunk, n_chunks, T, done, on_chunk) -> bool:
    """Hand the finished chunks of directory `ckpt` to ``on_chunk(c, lo, hi, error_norm, status)``
    one at a time (rows lo:hi of the study) and mark them in `done` (in place), or start the
    directory.  Returns True when it holds a different study (the caller raises).

    A damaged chunk (unreadable, wrong content, checksum mismatch, renamed) is named in a
    :class:`CheckpointWarning` and left to be recomputed (and atomically replaced).  A damaged
    ``meta.json`` is named likewise and rewritten once every chunk present has been verified to
    belong to this study (each chunk carries the study's fingerprint); a chunk of another study is
    refused.
    """
    os.makedirs(ckpt, exist_ok=True)
    meta_path = os.path.join(ckpt, "meta.json")
    meta, problem = _read_meta(meta_path)
    if meta is not None and meta.get("fingerprint") != fp:
        return True
    for c in range(n_chunks):
        path = chunk_path(ckpt, c)
        if not os.path.exists(path):
            continue
        lo, hi = c * chunk, min((c + 1) * chunk, n)
        en, st, why = _read_chunk(path, fp, c, hi - lo, T)
        if why == "other study":
            raise ValueError(
                f"checkpoint file {path!r} was computed by a different study (its fingerprint "
                "differs: gains, plant, samplers, noise, ts, key, n, chunk size or versions "
                "changed): delete the directory or choose another path."
            )
        if why is not None:
            warnings.warn(
                f"monte_carlo: checkpoint file {path!r} is damaged ({why}); chunk {c} will be "
                "recomputed.",
                CheckpointWarning,
                stacklevel=3,
            )
            continue
        on_chunk(c, lo, hi, en, st)
        done[c] = True
    if meta is None:
        if problem is not None:
            warnings.warn(
                f"monte_carlo: checkpoint file {meta_path!r} is damaged ({problem}); every chunk "
                "present carries this study's fingerprint, so it is rewritten.",
                CheckpointWarning,
                stacklevel=3,
            )
        _write_meta(meta_path, fp, study_id, n, chunk, n_chunks)
    return False
