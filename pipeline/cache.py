"""Verified cache entries: each carries the key that produced it and a digest of its content.

A study's and the camera's cache holds three kinds of files besides wood
chunk stores (whose chunks carry their own digests, see
:class:`~pipeline.microstructure.volume.ChunkFiles`):

``.npz``
    Arrays (ray shards, camera images) plus ``_key``, the cache key they were
    computed for, ``_record``, what that key hashes (the provenance, as JSON),
    and ``_digest``, a hash of every array's name, dtype, shape and bytes.
``.json``
    ``{"key": ..., "record": ..., "digest": ..., "value": ...}``, the digest
    hashing the value's canonical JSON.

A read returns None, and logs one warning naming the file and what is wrong,
when an entry is missing, no longer decodes, was computed for another key
(say two ray files swapped) or no longer matches its digest (an edited
summary): the caller recomputes it, and because every entry is a pure
function of its key the numbers are those of an undamaged run.

Files are written to a temporary name and renamed into place
(:func:`atomic_write`).  Temporary and staged names carry the host and the
process id, so that :func:`sweep_leftovers` removes what an interrupted run
left without touching what a live run is writing.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import logging
import os
import re
import shutil
import socket
import sys
import time
import uuid
import zipfile
import zlib
from pathlib import Path

import numpy as np

log = logging.getLogger("twray.cache")


class _StderrHandler(logging.StreamHandler):
    """Log records as ``twray: warning: ...`` lines on the current ``sys.stderr``."""

    def __init__(self):
        super().__init__()
        self.setFormatter(logging.Formatter("twray: %(levelname)s: %(message)s"))

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _):
        pass

    def format(self, record):
        record = logging.makeLogRecord({**record.__dict__, "levelname": record.levelname.lower()})
        return super().format(record)


def log_to_stderr() -> None:
    """twray's warnings (a damaged cache entry recomputed, ...) on stderr, one line each: in the
    command, and in each worker process, whose tasks call it too."""
    logger = logging.getLogger("twray")
    if not any(isinstance(h, _StderrHandler) for h in logger.handlers):
        logger.addHandler(_StderrHandler())
    logger.setLevel(logging.INFO)


HOST = re.sub(r"[^A-Za-z0-9]", "", socket.gethostname())[:32] or "host"
# Leftovers of another host's runs are removed only once they are this old [s]:
# whether that process still lives cannot be asked from here.
FOREIGN_LEFTOVER_AGE_S = 24 * 3600


def temp_name(path: Path, kind: str) -> Path:
    """A hidden sibling of ``path`` for work in progress: ``.<name>.<kind>-<host>-<pid>-<random>``."""
    path = Path(path)
    return path.with_name(f".{path.name}.{kind}-{HOST}-{os.getpid()}-{uuid.uuid4().hex[:8]}")


_LEFTOVER = re.compile(r"^\..+\.(partial|old|tmp)-([A-Za-z0-9]+)-(\d+)-[0-9a-f]{8}$")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def is_leftover(path: Path, now: float | None = None) -> bool:
    """Whether ``path`` is work in progress of a run that has ended (see :func:`temp_name`)."""
    m = _LEFTOVER.match(Path(path).name)
    if m is None:
        return False
    if m.group(2) == HOST:
        return not _alive(int(m.group(3)))
    try:
        age = (now or time.time()) - Path(path).lstat().st_mtime
    except FileNotFoundError:
        return False
    return age > FOREIGN_LEFTOVER_AGE_S


def sweep_leftovers(*folders, deep: bool = False) -> list[Path]:
    """Remove what interrupted runs left in ``folders`` (and below them with ``deep``)."""
    removed = []
    for folder in folders:
        folder = Path(folder)
        if not folder.is_dir():
            continue
        walker = os.walk(folder)
        for dirpath, dirs, files in (walker if deep else [next(walker)]):
            for name in list(dirs) + list(files):
                p = Path(dirpath) / name
                if is_leftover(p):
                    if p.is_dir() and not p.is_symlink():
                        shutil.rmtree(p, ignore_errors=True)
                        if name in dirs:
                            dirs.remove(name)
                    else:
                        p.unlink(missing_ok=True)
                    removed.append(p)
    return removed


FAULT_ENV = "TWRAY_FAULT_ENOSPC"  # "<stage>:<bytes>": writes of that stage fail as on a full disk (fault tests)
_fault_written: dict = {}


def _size_of(path: Path) -> int:
    if path.is_dir():
        return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    return path.stat().st_size if path.exists() else 0


@contextlib.contextmanager
def writing(path: Path, stage: str, staged: Path | None = None):
    """Around the writing of ``path`` (a cache entry of ``stage``, or "dataset"): an OSError that
    names no file (a full disk fails ``write``, not ``open``) is raised again naming ``path``;
    with :data:`FAULT_ENV` set for this stage, the bytes of ``staged`` count towards a budget past
    which the write fails with ENOSPC, as a full disk would (counted per process)."""
    try:
        yield
        spec = os.environ.get(FAULT_ENV, "")
        kind, _, budget = spec.partition(":")
        if kind in (stage, "any") and staged is not None:
            _fault_written[kind] = _fault_written.get(kind, 0) + _size_of(Path(staged))
            if _fault_written[kind] > int(budget or 0):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
    except OSError as exc:
        if exc.filename is None and exc.errno is not None:
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
        raise


def atomic_write(path: Path, write) -> None:
    """``write(tmp)`` then rename ``tmp`` onto ``path``: readers see the old file or the new one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_name(path, "tmp")
    try:
        with writing(path, path.parent.name, tmp):
            write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


# ---------------------------------------------------------------------- digests
def cache_key(record: dict) -> str:
    """The key of what ``record`` describes (every input a cache entry depends on)."""
    text = json.dumps(record, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def _update_array(h, name: str, a) -> None:
    a = np.asarray(a)
    h.update(name.encode() + b"\0")
    if a.dtype.kind in "OUST":  # text: its characters, whatever the string dtype read back
        h.update(b"text" + repr(a.shape).encode() + b"\0")
        h.update("\0".join(str(x) for x in a.ravel()).encode())
    else:
        a = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))
        h.update(a.dtype.str.encode() + repr(a.shape).encode() + b"\0")
        h.update(a.tobytes())
    h.update(b"\1")


def arrays_digest(arrays: dict) -> str:
    """A hash of named arrays: names, dtypes, shapes and values."""
    h = hashlib.blake2b(digest_size=16)
    for name in sorted(arrays):
        _update_array(h, name, arrays[name])
    return h.hexdigest()


def dataset_digest(ds) -> str:
    """A hash of every variable and coordinate of an xarray Dataset (values, not attributes)."""
    return arrays_digest({str(k): v.values for k, v in {**ds.coords, **ds.data_vars}.items()})


def json_digest(value) -> str:
    text = json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


# ---------------------------------------------------------------------- entries
UNREADABLE = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error, TypeError)


def warn(message: str, *args) -> None:
    """A warning of twray's cache, on stderr even in a worker process where nobody set up logging."""
    if not logging.getLogger().handlers:
        log_to_stderr()
    log.warning(message, *args)


def _damaged(path: Path, why: str) -> None:
    warn("cache entry %s is damaged (%s): computing it again", path, why)


def write_npz(path: Path, record: dict, arrays: dict) -> None:
    """Store ``arrays`` as a verified entry of what ``record`` describes."""
    entry = {**arrays, "_key": np.str_(cache_key(record)), "_record": np.str_(json.dumps(record)),
             "_digest": np.str_(arrays_digest(arrays))}

    def write(tmp):
        with open(tmp, "wb") as f:
            np.savez(f, **entry)

    atomic_write(path, write)


def check_npz(path: Path, key: str) -> tuple[dict | None, str | None]:
    """(arrays, None) for a sound entry of ``key``, else (None, what is wrong); None, None if absent."""
    path = Path(path)
    if not path.exists():
        return None, None
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except UNREADABLE as exc:
        return None, f"unreadable: {type(exc).__name__}"
    stored_key, stored_digest = str(arrays.pop("_key", "")), str(arrays.pop("_digest", ""))
    record = str(arrays.pop("_record", "null"))
    why = _mismatch(key, stored_key, record, stored_digest, lambda: arrays_digest(arrays))
    return (None, why) if why else (arrays, None)


def _mismatch(key: str, stored_key: str, record_json: str, digest: str, content_digest) -> str | None:
    """What is wrong with an entry stored as ``stored_key`` (made of ``record_json``, whose
    content hashed to ``digest``) read for ``key``; None if nothing."""
    if stored_key != key:
        return f"computed for key {stored_key or 'none'!r}, expected {key!r}"
    if _key_of(record_json) != key:
        return "its record does not hash to its key"
    if digest != content_digest():
        return "content does not match its digest"
    return None


def sound(check, path: Path, key: str) -> bool:
    """Whether ``check`` (:func:`check_npz`, :func:`check_json`) finds a sound entry of ``key``
    at ``path``; a damaged one is logged."""
    return _read(check, path, key) is not None


def read_npz(path: Path, key: str) -> dict | None:
    """The arrays of a sound entry of ``key``, or None (a damaged one is logged)."""
    return _read(check_npz, path, key)


def _read(check, path: Path, key: str):
    value, why = check(path, key)
    if why:
        _damaged(path, why)
    return value


def _key_of(record_json: str) -> str | None:
    try:
        record = json.loads(record_json)
    except ValueError:
        return None
    return cache_key(record) if isinstance(record, dict) else None


def write_json(path: Path, record: dict, value) -> None:
    """Store ``value`` as a verified entry of what ``record`` describes."""
    text = json.dumps({"key": cache_key(record), "record": record, "digest": json_digest(value), "value": value})
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def check_json(path: Path, key: str):
    """(value, None) for a sound entry of ``key``, else (None, what is wrong); None, None if absent."""
    path = Path(path)
    if not path.exists():
        return None, None
    try:
        record = json.loads(path.read_text())
        stored_key, digest, value = record["key"], record["digest"], record["value"]
        made_of = json.dumps(record["record"])
    except (*UNREADABLE, UnicodeDecodeError) as exc:
        return None, f"unreadable: {type(exc).__name__}"
    why = _mismatch(key, str(stored_key), made_of, digest, lambda: json_digest(value))
    return (None, why) if why else (value, None)


def read_json(path: Path, key: str):
    """The value of a sound entry of ``key``, or None (a damaged one is logged)."""
    return _read(check_json, path, key)


def entry_record(path: Path) -> dict | None:
    """What a cache file says it was made from (its record), or None if it cannot say."""
    path = Path(path)
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                return json.loads(str(z["_record"]))
        return json.loads(path.read_text())["record"]
    except (*UNREADABLE, UnicodeDecodeError):
        return None


class DamagedEntry(OSError):
    """An entry that was sound when planned is damaged when read (changed during the run)."""
