"""Compiled Hamming-distance kernels of binary descriptors (numba, GIL released).

:func:`descend`: each descriptor goes from the root of the vocabulary tree to the nearest child
(Hamming distance, the first one on a tie, as ``np.argmin`` picks it) until a node without
children: the same words as the numpy descent in :meth:`loopmodel.loop.vocabulary.Vocabulary.transform`,
without its (N, k, D) temporaries (a quarter of a KITTI keyframe's loop detection, issue 33).

:func:`nearest_both_ways`: one pass over the distance matrix of two descriptor sets gives what
OpenCV's brute-force ``knnMatch(k=2)`` and the reverse ``match`` gave in two (kf15, issue 33).
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


def _nearest_both_ways_py(query, train):  # type: ignore[no-untyped-def]
    """Nearest and second-nearest train row of each query row, and nearest query row of each train row.

    ``query`` (N, W) and ``train`` (M, W) uint64 words. Returns the nearest train index (N,), its
    distance (N,), the second-smallest distance (N,; equal to the first on a tie) and the nearest
    query index of each train row (M,); ties go to the first index, as in OpenCV's brute force.
    """
    n, m, w = query.shape[0], train.shape[0], query.shape[1]
    far = np.iinfo(np.int64).max
    best = np.full(n, -1, np.int64)
    d_best = np.full(n, far, np.int64)
    d_second = np.full(n, far, np.int64)
    back = np.full(m, -1, np.int64)
    d_back = np.full(m, far, np.int64)
    for i in range(n):
        b0, b1, j0 = far, far, -1
        for j in range(m):
            d = np.int64(0)
            for k in range(w):
                d += np.int64(_popcount64(query[i, k] ^ train[j, k]))
            if d < b0:
                b1, b0, j0 = b0, d, j
            elif d < b1:
                b1 = d
            if d < d_back[j]:
                d_back[j] = d
                back[j] = i
        best[i], d_best[i], d_second[i] = j0, b0, b1
    return best, d_best, d_second, back


_popcount64 = numba.njit(cache=True, nogil=True, inline="always")(_popcount64_py)
descend = numba.njit(cache=True, nogil=True)(_descend_py)
nearest_both_ways = numba.njit(cache=True, nogil=True)(_nearest_both_ways_py)


def warm_up() -> None:
    """Load (or compile) the descent and the matching: the first call's cost, before the first frame."""
    children = np.array([[1, 2], [-1, -1], [-1, -1]], np.int32)  # the vocabulary's own dtypes
    descend(np.zeros((1, 4), np.uint64), np.zeros((3, 4), np.uint64), children, np.arange(3, dtype=np.int32))
    nearest_both_ways(np.zeros((2, 4), np.uint64), np.ones((2, 4), np.uint64))
