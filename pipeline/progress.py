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
LOOK_S = 0.1  # how often the client's loop looks at a followed run's futures


def mode(quiet: bool) -> str:
    """"bar" on a terminal, "lines" when stdout is a pipe or a file, "off" when quiet."""
    if quiet:
        return "off"
    return "bar" if sys.stdout.isatty() else "lines"


WARMUP = 0.05  # no time left is said before this share of the work is done (a cold start compiles first)


class Pace:
    """The time left of a run whose work is ``total`` (the estimate's, or a count of tasks): at the
    rate measured since work was first seen done, and only once a share WARMUP of it is done, so
    that the workers' start (compiling kernels, building the first regions) does not count as the
    pace of the work."""

    def __init__(self, total: float):
        self.total = float(total)
        self.first = None  # (time, work done) when work was first seen done

    def left(self, done: float, now: float) -> float | None:
        if not 0.0 < done < self.total:
            return None
        if self.first is None:
            self.first = (now, done)
            return None
        t0, d0 = self.first
        if done < WARMUP * self.total or now <= t0 or done <= d0:
            return None
        return (self.total - done) * (now - t0) / (done - d0)


def line(label: str, done: int, total: int, share: float | None = None, left: float | None = None) -> str:
    """``label``: tasks done, the share of the estimated work done (when weighed), the time left."""
    out = f"{label}: {done}/{total} tasks done"
    if share is not None:
        out += f", {100.0 * share:.0f} % of the estimated work"
    if left is not None:
        out += f", about {left:.0f} s left" if left < 120 else f", about {left / 60:.0f} min left"
    return out


def _pending(dask_scheduler, keys) -> tuple[list, list]:
    """Which of ``keys`` the scheduler holds, and which of those are finished: in memory, erred,
    forgotten, or released after running (its result used by its dependents and dropped while
    the rest of the graph runs; a task not yet run has no size, ``nbytes`` -1)."""
    held, finished = [], []
    for k in keys:
        ts = dask_scheduler.tasks.get(k)
        if ts is not None:
            held.append(k)
            if ts.state in ("memory", "erred", "forgotten") or (ts.state == "released" and ts.nbytes >= 0):
                finished.append(k)
    return held, finished


async def _settled(futures, timeout_s: float) -> bool:
    """On the client's loop: whether every one of ``futures`` finished within ``timeout_s``; returns
    early when one fails. It looks at the futures every LOOK_S and leaves nothing behind, where a
    timed-out ``distributed.wait`` leaves a waiting task on the loop for every unfinished future
    (a long study's driving process grew by 60 MB a minute, docs/performance.md). The caller's
    thread blocks in ``client.sync`` meanwhile, so that Ctrl-C reaches it there, as it did in
    ``wait``."""
    import asyncio

    end = time.monotonic() + timeout_s
    while True:
        if all(f.done() for f in futures):
            return True
        if any(f.status == "error" for f in futures) or time.monotonic() >= end:
            return False
        await asyncio.sleep(LOOK_S)


def follow(client, futures, keys, label: str, how: str, every_s: float = PROGRESS_EVERY_S,
           weights: dict | None = None) -> None:
    """Show the progress of ``futures`` (whose graphs hold the task ``keys``) until they finish;
    ``weights``: the estimated CPU-seconds of some keys (the others weigh nothing), from which the
    share of the work done and the time left are told (else from the count of tasks)."""
    if how == "bar":
        from distributed import progress

        progress(futures)
        return
    if how != "lines":
        return
    keys = list(keys)
    weight = {k: 1.0 for k in keys}
    if weights and sum(weights.get(k, 0.0) for k in keys) > 0.0:
        weight = {k: float(weights.get(k, 0.0)) for k in keys}
    pace = Pace(sum(weight.values()))
    seen: set = set()
    done_keys: set = set()
    last = time.perf_counter()
    while not client.sync(_settled, futures, min(every_s, POLL_S)):
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
        work = sum(weight[k] for k in done_keys)
        print(line(label, len(done_keys), len(keys), work / pace.total if weights else None, pace.left(work, last)),
              file=sys.stderr, flush=True)
    print(line(label, len(keys), len(keys)), file=sys.stderr, flush=True)


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
                self.done, self.last, self.pace = 0, time.perf_counter(), Pace(self.total)

            def _posttask(self, key, result, dsk, state, worker_id):
                self.done += 1
                now = time.perf_counter()
                if now - self.last >= every_s and self.done < self.total:  # the last line: _finish
                    self.last = now
                    print(line(label, self.done, self.total, None, self.pace.left(self.done, now)), file=sys.stderr,
                          flush=True)

            def _finish(self, dsk, state, errored):
                if not errored:
                    print(line(label, self.total, self.total), file=sys.stderr, flush=True)

        return _Lines()
