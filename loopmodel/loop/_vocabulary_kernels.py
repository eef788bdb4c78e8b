"""Compiled descent of binary descriptors down the vocabulary tree (numba, GIL released).

Each descriptor goes from the root to the nearest child (Hamming distance, the first one on a tie,
as ``np.argmin`` picks it) until a node without children: the same words as the numpy descent in
:meth:`loopmodel.loop.vocabulary.Vocabulary.transform`, without its (N, k, D) temporaries (a
quarter of a KITTI keyframe's loop detection, issue 33).
"""

from __future__ import annotations

import numba
import numpy as np


def _popcount64_py(x):  # type: ignore[no-untyped-def]
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (x * np.uint64(0x0101010101010101)) >> np.uint64(56)


def _descend_py(desc, centers, children, word):  # type: ignore[no-untyped-def]
    """Word of each descriptor (N,): ``desc`` (N, W) and ``centers`` (nodes, W) as uint64 words."""
    n = desc.shape[0]
    k = children.shape[1]
    out = np.empty(n, np.int64)
    for i in range(n):
        node = 0
        while True:
            best = -1
            best_d = np.int64(0)
            for j in range(k):
                c = children[node, j]
                if c < 0:
                    continue
                d = np.int64(0)
                for w in range(desc.shape[1]):
                    d += np.int64(_popcount64(desc[i, w] ^ centers[c, w]))
                if best < 0 or d < best_d:
                    best = c
                    best_d = d
            if best < 0:
                break
            node = best
        out[i] = word[node]
    return out


_popcount64 = numba.njit(cache=True, nogil=True, inline="always")(_popcount64_py)
descend = numba.njit(cache=True, nogil=True)(_descend_py)


def warm_up() -> None:
    """Load (or compile) the descent: the first call's cost, before the first frame."""
    children = np.array([[1, 2], [-1, -1], [-1, -1]], np.int32)  # the vocabulary's own dtypes
    descend(np.zeros((1, 4), np.uint64), np.zeros((3, 4), np.uint64), children, np.arange(3, dtype=np.int32))
