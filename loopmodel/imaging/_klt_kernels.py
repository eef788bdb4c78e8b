"""Compiled helper of :func:`loopmodel.imaging.klt.shared_tracks` (numba, GIL released)."""

from __future__ import annotations

import numba
import numpy as np


def _share_py(x, order, radius, motion):  # type: ignore[no-untyped-def]
    """``share[j]``: the first earlier point ``i`` tracking itself within ``radius`` / ``motion`` of ``j``, else j.

    ``x`` (N, 4): position (u, v) and predicted displacement (du, dv), pixels; ``order``: the points
    sorted by u (non-finite rows left out). Chebyshev distances.
    """
    n = x.shape[0]
    share = np.arange(n)
    rank = np.full(n, -1)
    for k in range(order.shape[0]):
        rank[order[k]] = k
    for j in range(n):
        kj = rank[j]
        if kj < 0:
            continue
        best = j
        for step in (-1, 1):
            k = kj + step
            while 0 <= k < order.shape[0]:
                i = order[k]
                if abs(x[i, 0] - x[j, 0]) > radius:
                    break
                if (
                    i < best and share[i] == i and abs(x[i, 1] - x[j, 1]) <= radius
                    and abs(x[i, 2] - x[j, 2]) <= motion and abs(x[i, 3] - x[j, 3]) <= motion
                ):
                    best = i
                k += step
        share[j] = best
    return share


share_tracks = numba.njit(cache=True, nogil=True)(_share_py)


def warm_up() -> None:
    """Load (or compile) the kernel: its first call's cost, up front."""
    x = np.zeros((2, 4))
    share_tracks(x, np.arange(2), 1.0, 2.0)
