"""``Beside``: work on kept threads beside the caller (fe11)."""

from __future__ import annotations

import os
import threading
import time

import pytest

from loopmodel.frontend.beside import Beside


def test_result_error_and_inline() -> None:
    assert Beside(True, lambda a, b: a + b, 2, 3).result() == 5
    assert Beside(False, threading.get_ident).result() == threading.get_ident()  # inline: the caller's thread

    def fail() -> None:
        raise ValueError("boom")

    with pytest.raises(ValueError, match="boom"):
        Beside(True, fail).result()


def test_threads_are_reused_and_a_job_never_waits_behind_another() -> None:
    used = set()
    for _ in range(20):  # one job at a time: handed to the kept threads, not to a new thread each
        used.add(Beside(True, threading.get_ident).result())
        time.sleep(0.02)  # the worker back in the idle list
    assert threading.get_ident() not in used and len(used) <= 3

    def outer() -> int:  # a job that starts a job and waits for it (match_stereo_split inside _stereo_set)
        inner = [Beside(True, lambda k=k: k * k) for k in range(4)]
        return sum(b.result() for b in inner)

    jobs = [Beside(True, outer) for _ in range(3)]
    assert [j.result() for j in jobs] == [14, 14, 14]
    gate = threading.Event()
    blocked = Beside(True, gate.wait, 5.0)  # a busy thread: the next job gets another one
    assert Beside(True, lambda: 7).result() == 7
    gate.set()
    assert blocked.result() is True


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork")
def test_a_forked_child_starts_its_own_threads() -> None:
    Beside(True, int).result()  # a kept thread in this process
    pid = os.fork()
    if pid == 0:  # the child has none of the parent's threads: a job there still runs
        job = Beside(True, lambda: 4)
        os._exit(0 if job._done is not None and job._done.wait(10) and job.result() == 4 else 1)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0


def test_a_job_not_begun_runs_on_the_callers_thread_with_run_here(monkeypatch: pytest.MonkeyPatch) -> None:
    """cpu15: ``result(run_here=True)`` runs a job its thread has not begun on the caller's thread.

    The thread, when it comes to it, skips it: one run, the same value. A begun job is waited for.
    """
    from loopmodel.frontend import beside

    held: list[object] = []

    class _Late:  # a kept thread that has not come to its job yet
        def hand(self, job: object) -> None:
            held.append(job)

    runs: list[str] = []

    def job(k: int) -> int:
        runs.append(threading.current_thread().name)
        return k * k

    monkeypatch.setattr(beside, "_worker", _Late)
    late = Beside(True, job, 6)
    assert late.result(run_here=True) == 36 and late.ran_here
    held[0]()  # type: ignore[operator]  # the thread comes to it: skipped
    assert runs == [threading.current_thread().name]
    monkeypatch.undo()
    gate = threading.Event()
    begun = Beside(True, lambda: gate.wait(5.0) and threading.current_thread().name)
    time.sleep(0.2)  # begun on its thread (waiting at the gate): result(run_here=True) waits for it
    threading.Timer(0.2, gate.set).start()
    assert begun.result(run_here=True) not in (False, threading.current_thread().name) and not begun.ran_here
