"""Progress of long commands: a bar on a terminal (Dask's diagnostics), one line every
``TWRAY_PROGRESS_EVERY_S`` seconds (default 10) otherwise (a batch job's log) and one when
done, nothing with ``--quiet``."""

from __future__ import annotations

import os
import sys
import time


def _every_s() -> float:
    try:
        value = float(os.environ.get("TWRAY_PROGRESS_EVERY_S", "10"))
    except ValueError:
        value = 10.0
    return value if value > 0 else 10.0


PROGRESS_EVERY_S = _every_s()
POLL_S = 1.0  # how often a followed run looks for a failed task


def mode(quiet: bool) -> str:
    """"bar" on a terminal, "lines" when stdout is a pipe or a file, "off" when quiet."""
    if quiet:
        return "off"
    return "bar" if sys.stdout.isatty() else "lines"


def _eta(done: int, total: int, elapsed: float) -> str:
    if done == 0 or done >= total:
        return ""
    left = elapsed / done * (total - done)
    return f", about {left:.0f} s left" if left < 120 else f", about {left / 60:.0f} min left"


def line(label: str, done: int, total: int, elapsed: float) -> str:
    rate = done / elapsed if elapsed > 0 else 0.0
    return f"{label}: {done}/{total} tasks done ({rate:.2g} per s){_eta(done, total, elapsed)}"


def _pending(dask_scheduler, keys) -> tuple[list, list]:
    """Which of ``keys`` the scheduler holds, and which of those are finished (in memory,
    erred or forgotten)."""
    held, finished = [], []
    for k in keys:
        ts = dask_scheduler.tasks.get(k)
        if ts is not None:
            held.append(k)
            if ts.state in ("memory", "erred", "forgotten"):
                finished.append(k)
    return held, finished


def follow(client, futures, keys, label: str, how: str, every_s: float = PROGRESS_EVERY_S) -> None:
    """Show the progress of ``futures`` (whose graphs hold the task ``keys``) until they finish."""
    from distributed import wait

    if how == "bar":
        from distributed import progress

        progress(futures)
        return
    if how != "lines":
        return
    keys = list(keys)
    seen: set = set()
    done_keys: set = set()
    t0 = last = time.perf_counter()
    while True:
        try:
            wait(futures, timeout=min(every_s, POLL_S))
            break
        except TimeoutError:
            pass
        if any(f.status == "error" for f in futures):
            return  # a failed task ends the run now, as gathering would; no "all done" line
        if time.perf_counter() - last < every_s:
            continue
        last = time.perf_counter()
        held, ended = client.run_on_scheduler(_pending, keys=keys)
        # A key the scheduler has not held yet (a large graph is still arriving) is to do; one
        # that finished, or that it held and has dropped (its result used and released), is done.
        done_keys.update(ended)
        done_keys.update(seen.difference(held))
        seen.update(held)
        done = len(done_keys)
        print(line(label, done, len(keys), last - t0), file=sys.stderr, flush=True)
    print(line(label, len(keys), len(keys), time.perf_counter() - t0), file=sys.stderr, flush=True)


def graph_keys(collections) -> list:
    """Every task key of some Dask collections (delayed objects)."""
    keys = set()
    for c in collections:
        keys.update(c.__dask_graph__().keys())
    return [k for k in keys if isinstance(k, (str, tuple))]


class LocalLines:
    """A Dask callback for the local schedulers: a bar on a terminal, else periodic lines."""

    def __new__(cls, label: str, how: str, every_s: float = PROGRESS_EVERY_S):
        import contextlib

        if how == "bar":
            from dask.diagnostics import ProgressBar

            return ProgressBar()
        if how != "lines":
            return contextlib.nullcontext()
        from dask.callbacks import Callback

        class _Lines(Callback):
            def _start_state(self, dsk, state):
                self.total = sum(len(state[k]) for k in ("ready", "waiting", "running", "finished"))
                self.done, self.t0, self.last = 0, time.perf_counter(), time.perf_counter()

            def _posttask(self, key, result, dsk, state, worker_id):
                self.done += 1
                now = time.perf_counter()
                if now - self.last >= every_s and self.done < self.total:  # the last line: _finish
                    self.last = now
                    print(line(label, self.done, self.total, now - self.t0), file=sys.stderr, flush=True)

            def _finish(self, dsk, state, errored):
                if not errored:
                    print(line(label, self.total, self.total, time.perf_counter() - self.t0), file=sys.stderr,
                          flush=True)

        return _Lines()
