"""Progress of long commands (pipeline/progress.py): a bar on a terminal, a line every few seconds
to a log (and one when done), nothing with --quiet; the line says how many tasks are done, how
fast and about how long is left."""

import os
import re
import sys
import threading
import time

import dask
import pytest

from pipeline.progress import WARMUP, LocalLines, Pace, _every_s, follow, graph_keys, line, mode

LINE = re.compile(r"^(\w+): (\d+)/(\d+) tasks done(, \d+ % of the estimated work)?(, about \d+ (s|min) left)?$")


# ------------------------------------------------------------------ which display
def test_quiet_shows_nothing_a_terminal_a_bar_and_a_pipe_lines(monkeypatch, tmp_path):
    assert mode(True) == "off"
    master, slave = os.openpty()
    with open(slave, "w") as tty:
        monkeypatch.setattr(sys, "stdout", tty)
        assert mode(False) == "bar"
        assert mode(True) == "off"
    os.close(master)
    with open(tmp_path / "log", "w") as log:
        monkeypatch.setattr(sys, "stdout", log)
        assert mode(False) == "lines"
    read, write = os.pipe()
    with open(write, "w") as pipe:
        monkeypatch.setattr(sys, "stdout", pipe)
        assert mode(False) == "lines"
    os.close(read)


@pytest.mark.parametrize("text, seconds", [(None, 10.0), ("2.5", 2.5), ("60", 60.0), ("0", 10.0), ("-3", 10.0),
                                           ("soon", 10.0)])
def test_the_line_period_is_ten_seconds_unless_the_environment_gives_a_positive_number(monkeypatch, text, seconds):
    if text is None:
        monkeypatch.delenv("TWRAY_PROGRESS_EVERY_S", raising=False)
    else:
        monkeypatch.setenv("TWRAY_PROGRESS_EVERY_S", text)
    assert _every_s() == seconds


# ------------------------------------------------------------------ the line
def test_a_line_gives_tasks_done_the_share_of_the_work_and_the_time_left():
    assert line("study", 3, 10) == "study: 3/10 tasks done"
    assert line("study", 3, 10, 0.4, 14.0) == "study: 3/10 tasks done, 40 % of the estimated work, about 14 s left"
    # shown in minutes from 2 minutes on
    assert line("study", 1, 100, None, 1188.0) == "study: 1/100 tasks done, about 20 min left"
    assert line("trace", 1, 2, None, 119.0) == "trace: 1/2 tasks done, about 119 s left"
    assert line("trace", 1, 2, None, 120.0) == "trace: 1/2 tasks done, about 2 min left"


def test_the_time_left_comes_from_the_pace_of_the_work_not_from_a_cold_start():
    """A cold start spends a minute compiling before any work is done; the time left is then the
    work left at the pace measured since work was first seen done, and nothing is said before a
    share WARMUP of the work is done (counting tasks, the first line said 99 min for a 3-min run)."""
    pace = Pace(100.0)
    assert pace.left(0.0, 30.0) is None  # nothing done yet
    assert pace.left(1.0, 60.0) is None  # the first work seen: no pace yet
    assert pace.left(4.0, 63.0) is None  # under WARMUP of the work
    assert WARMUP * 100.0 <= 6.0
    assert pace.left(6.0, 70.0) == pytest.approx(94.0 * 10.0 / 5.0)  # 5 units in 10 s since the first
    assert pace.left(100.0, 90.0) is None  # all done


# ------------------------------------------------------------------ local schedulers
def _graph():
    """Four independent tasks and their sum: five tasks."""
    parts = [dask.delayed(lambda x: x + 1)(i) for i in range(4)]
    return dask.delayed(sum)(parts)


def test_graph_keys_are_every_task_of_the_collections():
    total = _graph()
    assert len(graph_keys([total])) == 5
    parts = [dask.delayed(lambda x: x)(i, dask_key_name=f"part-{i}") for i in range(3)]
    assert sorted(graph_keys(parts)) == ["part-0", "part-1", "part-2"]


def test_lines_count_every_task_and_the_last_line_is_all_of_them(capsys):
    with LocalLines("generate", "lines", every_s=0.0):
        assert dask.compute(_graph(), scheduler="sync") == (10,)
    out, err = capsys.readouterr()
    assert out == ""  # a log's lines go to stderr, the command's results alone to stdout
    lines = err.splitlines()
    parsed = [LINE.match(x) for x in lines]
    assert all(parsed), lines
    assert [(m[1], int(m[2]), int(m[3])) for m in parsed] == [("generate", k, 5) for k in range(1, 6)]
    # time left from the second line (a pace needs two) until the end
    assert parsed[-1][5] is None and parsed[0][5] is None and all(m[5] for m in parsed[1:-1])


def test_lines_come_no_oftener_than_the_period_but_the_last_always(capsys):
    with LocalLines("generate", "lines", every_s=3600.0):
        dask.compute(_graph(), scheduler="sync")
    err = capsys.readouterr().err
    assert err.splitlines() == ["generate: 5/5 tasks done"]


def test_a_failed_computation_has_no_done_line(capsys):
    def fail():
        raise RuntimeError("no")

    with pytest.raises(RuntimeError), LocalLines("generate", "lines", every_s=3600.0):
        dask.compute(dask.delayed(fail)(), scheduler="sync")
    assert capsys.readouterr().err == ""


def test_quiet_prints_nothing_and_a_terminal_gets_dasks_bar(capsys):
    with LocalLines("generate", "off"):
        dask.compute(_graph(), scheduler="sync")
    assert capsys.readouterr() == ("", "")
    with LocalLines("generate", "bar"):
        dask.compute(_graph(), scheduler="sync")
    out = capsys.readouterr().out
    assert "100% Completed" in out and "tasks done" not in out


# ------------------------------------------------------------------ a distributed client
def test_following_a_cluster_prints_lines_while_tasks_run_and_all_of_them_at_the_end(capsys):
    from distributed import Client

    def slow(x):
        time.sleep(0.5)
        return x

    with Client(processes=False, n_workers=1, threads_per_worker=2, dashboard_address=None) as client:
        jobs = [dask.delayed(slow)(i) for i in range(3)]  # two at a time: about 1 s
        keys = graph_keys(jobs)
        futures = client.compute(jobs)
        follow(client, futures, keys, "trace", "lines", every_s=0.2)
        assert all(f.done() for f in futures)
        err = capsys.readouterr().err.splitlines()
        parsed = [LINE.match(x) for x in err]
        assert all(parsed) and all(m[1] == "trace" and int(m[3]) == 3 for m in parsed), err
        done = [int(m[2]) for m in parsed]
        assert len(done) >= 2 and done == sorted(done) and done[0] < 3 and done[-1] == 3  # while running, then all
        assert parsed[-1][5] is None

        # Weighed by the estimate's work: the share of it done is said too.
        jobs = [dask.delayed(slow)(i, dask_key_name=f"job-{i}") for i in range(3)]
        futures = client.compute(jobs)
        follow(client, futures, graph_keys(jobs), "trace", "lines", every_s=0.2,
               weights={"job-0": 1.0, "job-1": 1.0, "job-2": 2.0})
        err = capsys.readouterr().err.splitlines()
        assert err[-1] == "trace: 3/3 tasks done" and any("% of the estimated work" in x for x in err[:-1]), err

        futures = client.compute([dask.delayed(slow)(i) for i in range(2)])
        follow(client, futures, keys, "trace", "off", every_s=0.2)
        assert capsys.readouterr() == ("", "")
        client.gather(futures)


_RELEASE = threading.Event()  # module-level: the tasks below are pickled by reference


def _held():
    _RELEASE.wait(30.0)


def _broken():
    raise ValueError("a broken scene")


def test_the_share_of_work_done_counts_tasks_whose_results_were_used_and_released(capsys):
    """A shard whose result its summary has used is "released" on the scheduler, not "forgotten",
    while the rest of the graph runs: it is done (Table 1's progress once said 13 % of the work
    until the last second).  Here three weighed tasks feed three others and a fourth is held."""
    from distributed import Client

    def slow(x):
        time.sleep(0.2)
        return x

    _RELEASE.clear()
    with Client(processes=False, n_workers=1, threads_per_worker=2, dashboard_address=None) as client:
        firsts = [dask.delayed(slow)(i, dask_key_name=f"first-{i}") for i in range(3)]
        jobs = [dask.delayed(slow)(f, dask_key_name=f"then-{i}") for i, f in enumerate(firsts)]
        jobs.append(dask.delayed(_held)(dask_key_name="held-last"))
        futures = client.compute(jobs)
        threading.Timer(2.5, _RELEASE.set).start()
        follow(client, futures, graph_keys(jobs), "trace", "lines", every_s=0.2,
               weights={"first-0": 1.0, "first-1": 1.0, "first-2": 1.0, "held-last": 1.0})
    err = capsys.readouterr().err.splitlines()
    assert any("75 % of the estimated work" in x for x in err), err


def test_following_a_cluster_returns_when_a_task_fails_without_waiting_for_the_others(capsys):
    from distributed import Client

    _RELEASE.clear()
    with Client(processes=False, n_workers=1, threads_per_worker=2, dashboard_address=None) as client:
        jobs = [dask.delayed(_held)(dask_key_name="slow"), dask.delayed(_broken)(dask_key_name="bad")]
        futures = client.compute(jobs)
        t0 = time.perf_counter()
        follow(client, futures, graph_keys(jobs), "trace", "lines", every_s=60.0)
        assert time.perf_counter() - t0 < 10  # not the 30 s of the other task
        assert futures[1].status == "error" and not futures[0].done()
        assert "tasks done" not in capsys.readouterr().err  # no line saying all is done
        _RELEASE.set()


def test_following_a_cluster_leaves_no_waiters_behind_on_the_clients_loop():
    """Following polls the futures: it adds no task to the client's event loop per look (a timed-out
    distributed.wait leaves one per unfinished future, which a long study piled up by the million)."""
    from distributed import Client

    _RELEASE.clear()
    seen = []
    with Client(processes=False, n_workers=1, threads_per_worker=1, dashboard_address=None) as client:
        futures = client.compute([dask.delayed(_held)(dask_key_name=f"held-{i}") for i in range(50)])
        loop = client.loop.asyncio_loop
        before = len(client.sync(_tasks))

        def release():
            time.sleep(1.5)  # about 7 looks at the futures
            seen.append(len(client.sync(_tasks)))
            _RELEASE.set()

        threading.Thread(target=release).start()
        follow(client, futures, [f"held-{i}" for i in range(50)], "trace", "lines", every_s=0.05)
        assert loop is client.loop.asyncio_loop and all(f.done() for f in futures)
    assert seen and seen[0] - before < 50, (before, seen)


async def _tasks():
    import asyncio

    return asyncio.all_tasks()
