"""A frame's KLT in two halves at once, one on a thread beside the tracking thread (issue 33, orb13).

OpenCV's pyramidal Lucas-Kanade releases the interpreter lock and searches each point on its own, so
the second half of the points is tracked on a :class:`~loopmodel.frontend.beside.Beside` thread while
the caller tracks the first: the same tracks as one call, in about half the wall time when the second
core is free (each half builds its own pyramids: about 0.7 ms of CPU more a frame at 640x480). A
second half the thread has not begun when the first is done (the other core busy: a keyframe's loop
detection, the back-end process) is tracked on the caller's thread, not waited for (cpu15).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import FrontendConfig
from loopmodel.frontend.beside import Beside
from loopmodel.imaging.klt import Pyramid, track_klt

F64 = NDArray[np.float64]


def track_klt_halves(
    prev: Pyramid,
    cur: Pyramid,
    start: F64,
    guess: F64,
    cfg: FrontendConfig,
    image_size: tuple[int, int],
    share: NDArray[np.int64] | None = None,
) -> tuple[F64, NDArray[np.bool_]]:
    """:func:`~loopmodel.imaging.klt.track_klt` (``frontend.klt_*``) of ``start`` (N, 2 pixels) predicted at ``guess``.

    With ``frontend.klt_split_min_points`` <= N (0: never) and no ``share`` (points searched once for
    their twins), the second half runs on a thread beside. Returns the tracked points and their
    validity (forward-backward check, inside the ``image_size`` (width, height) image).
    """
    klt = (cfg.klt_window_px, cfg.klt_levels, cfg.fb_threshold_px, cfg.klt_iterations, image_size)
    n = start.shape[0]
    if share is not None or not 0 < cfg.klt_split_min_points <= n or n < 2:
        uv, ok, _fb = track_klt(prev, cur, start, guess, *klt, share)
        return uv, ok
    h = n // 2
    other = Beside(True, track_klt, prev, cur, start[h:], guess[h:], *klt)
    uv0, ok0, _fb0 = track_klt(prev, cur, start[:h], guess[:h], *klt)
    uv1, ok1, _fb1 = other.result(run_here=True)  # not begun yet (its core busy): tracked here
    return np.vstack([uv0, uv1]), np.concatenate([ok0, ok1])
