"""Stereo pairs from two unsynchronised image streams, matched by header stamp.

Each stream's stamps must increase. The heads of the two queues pair when their stamps are
within the tolerance; otherwise the older head has no partner and is dropped (counted), so
a missing frame on one side never pairs its neighbours across the gap. Queues are bounded:
when one stream stops, the other's old messages are dropped, never accumulated.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Generic, TypeVar

from loopmodel.errors import InputError

T = TypeVar("T")


@dataclass
class PairingStats:
    """Counts of one pass: pairs made, images without a partner, repeated stamps skipped."""

    pairs: int = 0
    unmatched_left: int = 0
    unmatched_right: int = 0
    repeated: int = 0

    @property
    def unmatched(self) -> int:
        """Images of either side dropped for want of a partner."""
        return self.unmatched_left + self.unmatched_right


@dataclass
class StereoPair(Generic[T]):
    """Two matched messages: stamps (ns) and payloads."""

    left_ns: int
    right_ns: int
    left: T
    right: T


def pair_by_stamp(
    items: Iterable[tuple[bool, int, T]],
    tolerance_ns: int,
    stats: PairingStats | None = None,
    names: tuple[str, str] = ("left", "right"),
    max_queue: int = 64,
) -> Iterator[StereoPair[T]]:
    """Pairs of ``items`` = ``(is_left, stamp_ns, payload)`` in arrival order.

    ``stats`` (updated as pairs are yielded) counts what was dropped. ``names`` name the streams in
    errors (stamps going backwards).
    """
    st = stats if stats is not None else PairingStats()
    queues: tuple[deque[tuple[int, T]], deque[tuple[int, T]]] = (deque(), deque())
    last = [-1, -1]
    for is_left, t, payload in items:
        side = 0 if is_left else 1
        if t < last[side]:
            raise InputError(names[side], f"header stamps go backwards: {t} ns after {last[side]} ns")
        if t == last[side]:
            st.repeated += 1
            continue
        last[side] = t
        q = queues[side]
        q.append((t, payload))
        if len(q) > max_queue:
            q.popleft()
            if side == 0:
                st.unmatched_left += 1
            else:
                st.unmatched_right += 1
        lq, rq = queues
        while lq and rq:
            tl, pl = lq[0]
            tr, pr = rq[0]
            if abs(tl - tr) <= tolerance_ns:
                lq.popleft()
                rq.popleft()
                st.pairs += 1
                yield StereoPair(tl, tr, pl, pr)
            elif tl < tr:
                lq.popleft()
                st.unmatched_left += 1
            else:
                rq.popleft()
                st.unmatched_right += 1
    st.unmatched_left += len(queues[0])
    st.unmatched_right += len(queues[1])


def stamp_offset_ns(left_ns: list[int], right_ns: list[int]) -> int | None:
    """Median of each left stamp's distance to the nearest right stamp (None without both)."""
    if not left_ns or not right_ns:
        return None
    import numpy as np

    r = np.sort(np.asarray(right_ns, dtype=np.int64))
    lv = np.asarray(left_ns, dtype=np.int64)
    k = np.clip(np.searchsorted(r, lv), 1, len(r) - 1) if len(r) > 1 else np.zeros(len(lv), dtype=np.int64)
    d = np.abs(r[k] - lv)
    if len(r) > 1:
        d = np.minimum(d, np.abs(r[k - 1] - lv))
    return int(np.median(d))
