"""The run's frames read and decoded on a thread of their own (``sequence.read_ahead_frames``, issue 33, orb13)."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from loopmodel.config import Config
from loopmodel.io.sequence import open_sequence
from loopmodel.pipeline import _ReadAhead, frontend_only, process

TINY = Path(__file__).resolve().parents[1] / "datasets" / "tiny_kitti"


def _counting(n: int, where: list[str], fail_at: int | None = None, closed: list[bool] | None = None) -> Iterator[int]:
    try:
        for i in range(n):
            where.append(threading.current_thread().name)
            if i == fail_at:
                raise ValueError(f"bad frame {i}")
            yield i
    finally:
        if closed is not None:
            closed.append(True)


def test_in_order_from_another_thread() -> None:
    where: list[str] = []
    ahead = _ReadAhead(_counting(20, where), 2)  # type: ignore[arg-type]
    assert list(ahead) == list(range(20))
    assert next(iter(ahead), None) is None  # stays ended
    assert set(where) == {"read-ahead"}
    assert ahead.close()


def test_depth_zero_reads_on_the_callers_thread() -> None:
    where: list[str] = []
    ahead = _ReadAhead(_counting(5, where), 0)  # type: ignore[arg-type]
    assert list(ahead) == list(range(5))
    assert set(where) == {threading.current_thread().name}


def test_an_error_comes_in_its_frames_place() -> None:
    ahead = _ReadAhead(_counting(10, [], fail_at=4), 3)  # type: ignore[arg-type]
    got = []
    with pytest.raises(ValueError, match="bad frame 4"):
        for i in ahead:
            got.append(i)
    assert got == [0, 1, 2, 3]


def test_close_stops_the_thread_before_the_source_is_closed() -> None:
    closed: list[bool] = []
    source = _counting(1000, [], closed=closed)
    ahead = _ReadAhead(source, 2)  # type: ignore[arg-type]
    assert [next(ahead), next(ahead)] == [0, 1]
    assert ahead.close(timeout_s=5.0)
    source.close()  # no "generator already executing": the thread is out of it
    assert closed == [True]


@pytest.mark.parametrize("depth", [0, 2])
def test_the_run_is_the_same_with_or_without_reading_ahead(depth: int) -> None:
    """The tiny KITTI folder, front end alone: every frame, the same online poses as read on the tracking thread."""
    config = frontend_only(Config())
    config.sequence.read_ahead_frames = 0
    ref = process(open_sequence(TINY), config)
    config.sequence.read_ahead_frames = depth
    res = process(open_sequence(TINY), config)
    assert len(res.online.positions_m) == len(ref.online.positions_m) == len(open_sequence(TINY))
    np.testing.assert_array_equal(res.online.positions_m, ref.online.positions_m)
    assert process(open_sequence(TINY), config, max_frames=3).metrics["frames"] == 3
