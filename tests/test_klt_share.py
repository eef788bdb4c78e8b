"""KLT points sharing one search (``frontend.klt_share_px``, issue 33) against plain OpenCV per point."""

from __future__ import annotations

import cv2
import numpy as np
from frontend_scene import random_texture

from loopmodel.imaging.klt import shared_tracks, track_klt


def test_shared_tracks_pick_the_first_of_each_close_group() -> None:
    pts = np.array([[10.0, 10.0], [10.6, 10.3], [40.0, 40.0], [10.9, 9.5], [40.0, 41.5], [np.nan, 3.0]])
    guess = pts + [5.0, 0.0]
    guess[3] += [3.0, 0.0]  # next to point 0 but predicted to move 3 px further: its own search
    assert shared_tracks(pts, guess, 1.0, 2.0).tolist() == [0, 0, 2, 3, 4, 5]
    assert shared_tracks(pts, guess, 1.0, 4.0).tolist() == [0, 0, 2, 0, 4, 5]
    assert shared_tracks(pts, guess, 0.0, 2.0).tolist() == list(range(6))


def test_shared_tracks_against_brute_force(rng: np.random.Generator) -> None:
    """The compiled search equals the definition: each point takes the first earlier self-tracked point near it."""
    pts = rng.uniform(0, 40, (400, 2))
    guess = pts + rng.normal(0, 1.5, (400, 2))
    pts[7] = np.nan
    share = shared_tracks(pts, guess, 1.0, 2.0)
    ref = np.arange(400)
    d = guess - pts
    for j in range(400):
        for i in range(j):
            if (ref[i] == i and np.abs(pts[i] - pts[j]).max() <= 1.0 and np.abs(d[i] - d[j]).max() <= 2.0):
                ref[j] = i
                break
    np.testing.assert_array_equal(share, ref)
    assert (share != np.arange(400)).sum() > 50


def test_shared_klt_equals_opencv_per_point(rng: np.random.Generator) -> None:
    """Each twin moves with its first point.

    The searched points give OpenCV's own results, the twins theirs to 0.05 px (the true shift to 0.1).
    """
    prev = cv2.GaussianBlur(random_texture(rng, 240, 320), (0, 0), 1.5)
    shift = np.array([3.3, -1.7])
    cur = cv2.warpAffine(prev, np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]]]), (320, 240),
                         flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    base = rng.uniform(30, [290, 210], (40, 2))
    twins = base[:15] + rng.uniform(-0.6, 0.6, (15, 2))
    pts = np.vstack([base, twins])
    guess = pts + shift + rng.normal(0, 0.3, pts.shape)
    share = shared_tracks(pts, guess, 1.0, 2.0)
    own = np.flatnonzero(share == np.arange(len(pts)))
    assert own.size < len(pts) - 10  # most twins share
    uv, ok, fb = track_klt(prev, cur, pts, guess, 13, 3, 1.0, 30, (320, 240), share)
    uv_ref, ok_ref, fb_ref = track_klt(prev, cur, pts, guess, 13, 3, 1.0, 30, (320, 240))
    # the searched points: exactly what OpenCV gives for them
    np.testing.assert_array_equal(uv[own], uv_ref[own])
    np.testing.assert_array_equal(ok[own], ok_ref[own])
    # every point, shared or not, where OpenCV's own search puts it and where the image moved it
    assert ok.all() and ok_ref.all()
    np.testing.assert_allclose(uv, uv_ref, atol=0.05)
    np.testing.assert_allclose(uv, pts + shift, atol=0.1)
    twin = share != np.arange(len(pts))
    np.testing.assert_array_equal(fb[twin], fb_ref[share[twin]])  # a twin's check is its first point's
