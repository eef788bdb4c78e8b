"""The run's scheduling settings (loopmodel.priority, issue 33)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from loopmodel.priority import lower_switch_interval


@pytest.fixture
def switch_interval() -> Iterator[None]:
    before = sys.getswitchinterval()
    sys.setswitchinterval(0.005)  # Python's default
    yield
    sys.setswitchinterval(before)


def test_switch_interval_is_only_ever_lowered(switch_interval: None) -> None:
    lower_switch_interval(0.0)  # off
    assert sys.getswitchinterval() == pytest.approx(0.005)
    lower_switch_interval(0.5)
    assert sys.getswitchinterval() == pytest.approx(0.0005)
    lower_switch_interval(2.0)  # a later, larger setting leaves the lower one
    assert sys.getswitchinterval() == pytest.approx(0.0005)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread priorities are Linux's")
def test_queued_detections_leave_the_lowered_worker_in_order() -> None:
    """At the drain, detections the lowered worker has not started run at the caller's priority, after its last."""
    import os
    import threading
    from collections import deque

    from loopmodel.config import LoopConfig
    from loopmodel.loop.stage import LoopClosingStage
    from loopmodel.priority import low_priority_pool

    def priority() -> int:
        return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    base = priority()
    release = threading.Event()
    ran: list[tuple[int, int]] = []

    def detection(kf_id: int) -> Callable[[], Any]:
        def run() -> Any:
            if kf_id == 0:
                assert release.wait(10.0)
            ran.append((kf_id, priority()))
            return kf_id
        return run

    stage = LoopClosingStage.__new__(LoopClosingStage)
    stage.config = LoopConfig(worker_nice=4)
    worker = low_priority_pool("loop-detect", 4)
    calls = {k: detection(k) for k in range(3)}
    stage._inflight = deque((k, worker.submit(calls[k])) for k in range(3))
    stage._calls = dict(calls)
    deadline = time.perf_counter() + 10.0
    while not stage._inflight[0][1].running() and time.perf_counter() < deadline:  # the first one has started
        time.sleep(0.01)
    moved = stage._take_back_queued()
    assert moved is not None
    release.set()
    assert [fut.result(10.0) for _, fut in stage._inflight] == [0, 1, 2]
    assert ran == [(0, min(base + 4, 19)), (1, base), (2, base)]
    worker.shutdown()
    moved.shutdown()
