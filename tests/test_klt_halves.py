"""A frame's KLT in two halves at once (``frontend.klt_split_min_points``, issue 33, orb13) against one call."""

from __future__ import annotations

import threading
import time

import cv2
import numpy as np
import pytest
from frontend_scene import random_texture

from loopmodel.config import FrontendConfig
from loopmodel.frontend import klt_halves
from loopmodel.frontend.klt_halves import track_klt_halves
from loopmodel.imaging.klt import track_klt


def _pair(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    prev = cv2.GaussianBlur(random_texture(rng, 240, 320), (0, 0), 1.5)
    shift = np.array([2.6, -1.2])
    cur = cv2.warpAffine(prev, np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]]]), (320, 240),
                         flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return prev, cur, shift


def test_halves_give_the_tracks_of_one_call(rng: np.random.Generator) -> None:
    """Bit-identical points and validity, the second half on another thread; the true shift to 0.1 px."""
    prev, cur, shift = _pair(rng)
    pts = rng.uniform(20, [300, 220], (151, 2))  # odd: unequal halves
    pts[-3:] = [-50.0, -50.0]  # outside the image: invalid in both
    guess = pts + shift + rng.normal(0, 0.3, pts.shape)
    cfg = FrontendConfig(klt_split_min_points=64)
    ref_uv, ref_ok, _ = track_klt(prev, cur, pts, guess, cfg.klt_window_px, cfg.klt_levels, cfg.fb_threshold_px,
                                  cfg.klt_iterations, (320, 240))
    threads: set[str] = set()
    real = klt_halves.track_klt

    caller = threading.current_thread().name

    def spy(*args: object) -> object:
        name = threading.current_thread().name
        threads.add(name)
        if name == caller:  # the caller's half waits a while: the thread beside has begun the other
            time.sleep(0.3)  # (one it has not begun by then the caller tracks itself: test_beside.py)
        return real(*args)  # type: ignore[arg-type]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(klt_halves, "track_klt", spy)
        uv, ok = track_klt_halves(prev, cur, pts, guess, cfg, (320, 240))
    assert len(threads) == 2  # the caller's and one beside
    np.testing.assert_array_equal(ok, ref_ok)
    np.testing.assert_array_equal(uv[ok], ref_uv[ok])
    assert ok[:-3].sum() >= 140 and not ok[-3:].any()
    np.testing.assert_allclose(uv[ok], pts[ok] + shift, atol=0.15)  # measured 0.104


def test_few_points_or_zero_keep_one_call(rng: np.random.Generator) -> None:
    """Below ``klt_split_min_points`` (and with 0) the caller's thread tracks every point."""
    prev, cur, shift = _pair(rng)
    pts = rng.uniform(20, [300, 220], (40, 2))
    calls: list[int] = []
    real = klt_halves.track_klt

    def spy(*args: object) -> object:
        calls.append(len(args[2]))  # type: ignore[arg-type]
        return real(*args)  # type: ignore[arg-type]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(klt_halves, "track_klt", spy)
        track_klt_halves(prev, cur, pts, pts + shift, FrontendConfig(klt_split_min_points=64), (320, 240))
        track_klt_halves(prev, cur, pts, pts + shift, FrontendConfig(klt_split_min_points=0), (320, 240))
        track_klt_halves(prev, cur, pts, pts + shift, FrontendConfig(klt_split_min_points=10), (320, 240))
    assert calls == [40, 40, 20, 20]


def test_opencv_threads_give_the_tracks_of_one_thread(rng: np.random.Generator) -> None:
    """The default KLT (orb21): one call's points over OpenCV's own two threads, bit-identical to one thread.

    ``frontend.opencv_threads`` 2 with the halves off; the true shift to 0.15 px.
    """
    assert FrontendConfig().klt_split_min_points == 0 and FrontendConfig().opencv_threads == 2
    prev, cur, shift = _pair(rng)
    pts = rng.uniform(20, [300, 220], (401, 2))
    guess = pts + shift + rng.normal(0, 0.3, pts.shape)
    cfg = FrontendConfig()
    klt = (cfg.klt_window_px, cfg.klt_levels, cfg.fb_threshold_px, cfg.klt_iterations, (320, 240))
    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(1)
        ref_uv, ref_ok, ref_fb = track_klt(prev, cur, pts, guess, *klt)
        cv2.setNumThreads(2)
        uv, ok, fb = track_klt(prev, cur, pts, guess, *klt)
    finally:
        cv2.setNumThreads(before)
    np.testing.assert_array_equal(ok, ref_ok)
    np.testing.assert_array_equal(uv, ref_uv)
    np.testing.assert_array_equal(fb, ref_fb)
    assert ok.sum() >= 395  # measured 401 of 401
    np.testing.assert_allclose(uv[ok], pts[ok] + shift, atol=0.15)  # measured 0.104
