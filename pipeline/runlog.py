"""Where a run's logs and tracebacks go, and the one line a failure shows (docs/guide.md#when-a-run-fails).

The terminal shows twray's own lines; Dask's worker, nanny and scheduler logs
and every traceback go to one log file per day under the cache folder,
``<cache>/logs/twray-YYYYMMDD.log`` (or the temporary folder when a command has
no cache).  A failure inside a Dask task reaches the user as one line naming
what failed (the study, value and realisation, or the file), what to do, and
where its traceback is (:func:`task_failure`).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import tempfile
import time
import traceback
from pathlib import Path

FORMAT = "%(asctime)s pid %(process)d %(name)s %(levelname)s: %(message)s"
TASK_NOTE = "twray task: "  # the note a failing task adds to its exception: the task's key
FAULT_MEMORY_ENV = "TWRAY_FAULT_MEMORY_MB"  # fault tests: each graph task first holds this much memory
_state = {"path": None, "log_failed": None}


class RunFailed(Exception):
    """A run stopped by its environment (a full disk, a dying worker, memory): its one line, exit 1."""


def _temp_log() -> Path:
    return Path(tempfile.gettempdir()) / f"twray-{time.strftime('%Y%m%d')}.log"


def log_file() -> Path:
    """This run's log file (the temporary folder's until :func:`start` names a cache)."""
    return _state["path"] or _temp_log()


def _log_failed(exc: BaseException, path) -> None:
    """Remember the first failure to write the log (the error line says it once)."""
    if _state["log_failed"] is None:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else type(exc).__name__
        _state["log_failed"] = f"the log {path} could not be written ({why})"


class _LazyFile(logging.FileHandler):
    """A log file made, with its folder, on the first record only (nothing logged, nothing written).
    A record it cannot write is dropped silently (a full disk: Python's logging would print a
    traceback to the terminal for every record); the failure is remembered for the error line."""

    def _open(self):
        Path(self.baseFilename).parent.mkdir(parents=True, exist_ok=True)
        return super()._open()

    def handleError(self, record):
        import sys

        _log_failed(sys.exc_info()[1], self.baseFilename)

    def close(self):
        try:
            super().close()
        except OSError as exc:  # the last records' flush, on a full disk
            _log_failed(exc, self.baseFilename)


def _file_handler(path: Path) -> logging.Handler:
    h = _LazyFile(path, delay=True)
    h.setFormatter(logging.Formatter(FORMAT))
    h.setLevel(logging.INFO)
    return h


def route_dask_logs(path: Path) -> None:
    """Send this process's ``distributed`` logs to ``path`` instead of the terminal."""
    logger = logging.getLogger("distributed")
    for h in list(logger.handlers):
        if isinstance(h, _LazyFile) and Path(h.baseFilename) == path.absolute():
            return
        if isinstance(h, (logging.StreamHandler, _LazyFile)):  # the terminal's, or an earlier run's file
            logger.removeHandler(h)
            h.close()
    logger.addHandler(_file_handler(path))
    logger.propagate = False


def start(cache=None) -> Path:
    """Log this run under ``cache``/logs (None: the temporary folder) and send Dask's logs there;
    returns the file.  Every command starts here."""
    _state["log_failed"] = None
    _state["path"] = None if cache is None else (Path(cache) / "logs" / f"twray-{time.strftime('%Y%m%d')}.log").absolute()
    route_dask_logs(log_file())
    return log_file()


class QuietWorkers:
    """A Dask worker plugin: each worker process logs to the run's file, not to the terminal."""

    name = "twray-logs"

    def __init__(self, path: Path):
        self.path = Path(path)

    def setup(self, worker):
        route_dask_logs(self.path)


def quiet_workers(client) -> None:
    """Install :class:`QuietWorkers` on ``client``'s workers (and those that join later)."""
    from distributed.diagnostics.plugin import WorkerPlugin

    plugin = type("TwrayLogs", (QuietWorkers, WorkerPlugin), {})(log_file())
    client.register_plugin(plugin, name=QuietWorkers.name)


def record(exc: BaseException, what: str = "") -> Path | None:
    """Append ``exc``'s traceback to the log file (the temporary folder's when that fails); returns
    the file, or None when neither could take it."""
    text = (f"{time.strftime('%Y-%m-%d %H:%M:%S')} pid {os.getpid()} twray ERROR: {what or 'failure'}\n"
            + "".join(traceback.format_exception(exc)))
    for path in dict.fromkeys((log_file(), _temp_log())):  # the disk that failed may hold the log too
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with open(path, "a") as f:
                f.write(text)
            return path
        except OSError as err:
            _log_failed(err, path)
    return None


def traceback_note(exc: BaseException, what: str = "") -> str:
    """``exc``'s traceback appended to the log, as the end of an error line: where it is, and once
    whether a log could not be written."""
    path = record(exc, what)
    note = f"traceback in {path}" if path is not None else "no traceback kept"
    return note if _state["log_failed"] is None else f"{note}; {_state['log_failed']}"


def note_task(exc: BaseException) -> None:
    """Mark ``exc`` with the key of the Dask task raising it (inside a task; else nothing)."""
    try:
        from distributed import get_worker

        key = get_worker().get_current_task()
    except (ImportError, ValueError):
        return
    exc.add_note(f"{TASK_NOTE}{key}")


def task(fn):
    """A graph task: an exception it raises carries the task's key (the user's line names its scene)."""
    import functools

    @functools.wraps(fn)
    def run(*args, **kwargs):
        try:
            hog = os.environ.get(FAULT_MEMORY_ENV)
            held = bytearray(int(hog) << 20) if hog else None  # zero-filled: every page touched
            if held is not None:
                time.sleep(2.0)  # long enough for the nanny to see it
            return fn(*args, **kwargs)
        except Exception as exc:
            note_task(exc)
            raise
    return run


# Dask's errors for a task that lost its workers: killed while running it, or none left to run it.
WORKER_LOST = ("KilledWorker", "NoWorkerError", "NoValidWorkerError")


def task_key(exc: BaseException):
    """The task key :func:`note_task` or one of Dask's :data:`WORKER_LOST` errors gives ``exc``, or None."""
    for note in getattr(exc, "__notes__", ()):
        if note.startswith(TASK_NOTE):
            return note[len(TASK_NOTE):]
    if type(exc).__name__ in WORKER_LOST:
        return getattr(exc, "task", None) or (exc.args[0] if exc.args else None)
    return None


def os_error_line(exc: OSError) -> str:
    """What an OSError means to the user: the path, what happened and what to do."""
    where = exc.filename or "?"
    folder = Path(where).parent if exc.filename else None
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return (f"no space left writing {where}: free space on its disk (df {folder}) or point --cache/--results "
                "at a larger one, then run again (finished entries are kept)")
    if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return f"cannot write {where} ({exc.strerror}): make {folder} writable or choose another folder"
    return f"{exc.strerror or exc} ({where})"


def gather_graph(client, futures, keys, label: str, how: str, labels: dict, weights: dict | None = None) -> list:
    """The results of ``futures`` (computed from graphs of the task ``keys``), followed with
    progress ``how`` (:func:`pipeline.progress.follow`, its ``weights`` the tasks' estimated work).  A failed task ends the run: its other
    tasks are cancelled (a rerun on the same scheduler submits them anew) and the failure is
    raised as :func:`task_failure`'s one line, named by ``labels``."""
    from .progress import follow

    try:
        follow(client, futures, keys, label, how, weights=weights)
        return client.gather(futures)
    except Exception as exc:
        with contextlib.suppress(Exception):
            client.cancel(futures)
        raise task_failure(exc, labels) from exc


def task_failure(exc: BaseException, labels: dict) -> RunFailed | BaseException:
    """The one-line :class:`RunFailed` for ``exc`` raised by a Dask task (``labels``: task key →
    what it computes, e.g. "study-2 delta_ri=0.01 realisation 1, rays 0-250"); the traceback
    goes to the log.  Errors of the user's input (ParameterError) are returned as they are."""
    from .params import ParameterError

    if isinstance(exc, ParameterError):
        return exc
    key = task_key(exc)
    what = labels.get(key, str(key)) if key is not None else "a task"
    log = traceback_note(exc, what)
    if type(exc).__name__ == "KilledWorker":
        line = (f"a worker died running {what} (killed, or over its memory limit): run again (finished entries "
                "are kept) with fewer --workers or more memory per worker (--memory-limit)")
    elif type(exc).__name__ in WORKER_LOST:
        line = (f"no worker was left to run {what} (one died and none took its place within "
                f"{getattr(exc, 'timeout', 0):g} s): run again (finished entries are kept); if it recurs, "
                "give each worker more memory (--memory-limit)")
    elif isinstance(exc, MemoryError):
        line = f"out of memory running {what}: run again with fewer --workers or more memory per worker"
    elif isinstance(exc, OSError):
        line = f"{os_error_line(exc)} [{what}]"
    else:
        line = f"{what} failed: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
    return RunFailed(f"{line}; {log}")
