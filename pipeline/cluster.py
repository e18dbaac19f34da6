"""Where Dask graphs run: a running scheduler, or a local ``dask.distributed`` cluster."""

from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path

from .params import ParameterError

CONNECT_TIMEOUT = "5s"  # a scheduler that does not answer by then is unreachable
# A local cluster whose last worker died and was not restarted fails its waiting tasks after this
# (a local worker starts in seconds), instead of waiting for ever.
NO_WORKERS_TIMEOUT = "60s"

# glibc settings of the local cluster's worker processes, over Dask's own.
# Dask sets the trim threshold to 64 KiB, which also freezes the mmap
# threshold at 128 KiB: every chunk-sized array is then a fresh mmap whose
# pages fault in on first touch (Table 1 at paper scale: 43 million page
# faults, 15 % of its CPU time in the kernel).  Keep freed memory for reuse
# instead, up to 256 MiB.
WORKER_MALLOC = {"MALLOC_TRIM_THRESHOLD_": 256 << 20, "MALLOC_MMAP_THRESHOLD_": 64 << 20}


def connect(address=None, scheduler_file=None):
    """A client of a running Dask scheduler, or one line (ParameterError) if it cannot be reached."""
    from distributed import Client

    name, value = ("scheduler_file", scheduler_file) if scheduler_file is not None else ("scheduler", address)
    if scheduler_file is not None and not Path(scheduler_file).is_file():
        raise ParameterError(f"`scheduler_file` must be an existing scheduler file, got {scheduler_file!r}")
    try:
        if scheduler_file is not None:
            return Client(scheduler_file=scheduler_file, timeout=CONNECT_TIMEOUT)
        return Client(address, timeout=CONNECT_TIMEOUT)
    except (OSError, TimeoutError, ValueError) as exc:
        reason = (str(exc).splitlines() or [type(exc).__name__])[0]
        raise ParameterError(f"`{name}` must be a Dask scheduler that answers within {CONNECT_TIMEOUT}, "
                             f"got {name}={value!r} ({reason})") from None


@contextlib.contextmanager
def generate_client(workers: int | None, scheduler: str | None):
    """A client of ``scheduler``, of a local cluster of ``workers`` processes, or None (the
    thread pool); the client and its local cluster are closed on leaving, workers stopped."""
    client = cluster = None
    if scheduler:
        client = connect(scheduler)
    elif workers is not None:
        from distributed import Client, LocalCluster

        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
    try:
        yield client
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()


def memory_limit(text: str | None):
    """``--memory-limit`` as bytes (None: Dask's default, the machine's memory over the workers)."""
    if text is None:
        return None
    from dask.utils import parse_bytes

    try:
        value = parse_bytes(text)
    except (ValueError, TypeError):
        value = None
    if not value or value < 64 << 20:
        raise ParameterError(f"`memory_limit` must be a size of at least 64MB such as 2GB, got memory_limit={text!r}")
    return value


def graph_client(command: str, *, workers: int | None = None, threads: int | None = None, memory=None,
                 scheduler: str | None = None, scheduler_file: str | None = None):
    """(client, local cluster or None) for a study's or the camera's graph."""
    import dask
    from distributed import Client, LocalCluster

    if scheduler and scheduler_file:
        raise ParameterError("give either `--scheduler` or `--scheduler-file`, not both")
    if scheduler:
        return connect(scheduler), None
    if scheduler_file:
        return connect(scheduler_file=scheduler_file), None
    cores = os.cpu_count() or 1
    workers = local_workers(command, workers)
    threads = threads if threads is not None else max(1, cores // workers)
    environ = {**dask.config.get("distributed.nanny.pre-spawn-environ", {}), **WORKER_MALLOC}
    # A worker near its memory limit is not paused: twray's tasks hold no data Dask could spill, so
    # a paused worker would wait for ever; past the limit the nanny restarts it and the task is retried.
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ, "distributed.worker.memory.pause": False,
                          "distributed.scheduler.no-workers-timeout":
                              dask.config.get("distributed.scheduler.no-workers-timeout") or NO_WORKERS_TIMEOUT}):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=threads, processes=True,
                               **({"memory_limit": memory} if memory is not None else {}))
    return Client(cluster), cluster


def local_workers(command: str, workers: int | None) -> int:
    """Worker processes of the local cluster ``command`` starts (``workers``: the user's number)."""
    from distributed.deploy.utils import nprocesses_nthreads

    if workers is not None:
        return workers
    # A study's shards hold the GIL between kernel calls (chunk reads, the tracer's loop):
    # Table 1 small ran 1.6x faster on 2 processes than on 1 process of 2 threads
    # (results/BENCH.md), so a study starts dask's split of the cores into processes.
    # The camera's row tasks share wood chunks in one process's memory and keep one worker.
    return nprocesses_nthreads(os.cpu_count() or 1)[0] if command in ("study", "wave") else 1


@contextlib.contextmanager
def cluster(command: str, quiet: bool = False, **where):
    """A Dask client for ``command`` ("study" or "camera"; ``where``: :func:`graph_client`'s
    options), printing its dashboard unless ``quiet``, closed with its local cluster."""
    from . import runlog

    runlog.route_dask_logs(runlog.log_file())  # the nannies and scheduler of a local cluster live here
    client, local = graph_client(command, **where)
    try:
        runlog.quiet_workers(client)
        if not quiet:
            print(f"twray {command}: dashboard {client.dashboard_link}; logs in {runlog.log_file()}", file=sys.stderr)
        yield client
    finally:
        client.close()
        if local is not None:
            local.close()
