"""A coming frame's left image rectified beside the current one (issue 33): the same image, taken by identity."""

from __future__ import annotations

import pickle
from collections.abc import Iterator

import cv2
import numpy as np
import pytest

from loopmodel.imaging.rectify import Rectifier
from loopmodel.pipeline import _one_ahead
from loopmodel.types import StereoCalibration


def _raw_rig() -> StereoCalibration:
    K = np.array([[500.0, 0, 318.0], [0, 502.0, 243.0], [0, 0, 1]])
    right_from_left = np.eye(4)
    right_from_left[:3, :3] = cv2.Rodrigues(np.array([0.002, -0.01, 0.003]))[0]
    right_from_left[0, 3] = -0.06
    dist = np.array([-0.12, 0.05, 0.001, -0.0005, 0.0])
    return StereoCalibration(K, K.copy(), right_from_left, (640, 480), dist, dist.copy(), rectified=False)


def test_left_ahead_gives_the_same_image_and_only_for_that_array() -> None:
    rng = np.random.default_rng(3)
    rect = Rectifier(_raw_rig())
    imgs = [rng.integers(0, 256, (480, 640), dtype=np.uint8) for _ in range(3)]
    fresh = Rectifier(_raw_rig())
    expected = [fresh.left(im) for im in imgs]
    assert not np.array_equal(expected[0], imgs[0])  # it does rectify
    rect.left_ahead(imgs[0])
    rect.left_ahead(imgs[1])  # two started: the current frame's and the coming one's
    np.testing.assert_array_equal(rect.left(imgs[0]), expected[0])
    # an equal array that is not the one started is rectified on the spot, the started one kept
    np.testing.assert_array_equal(rect.left(imgs[1].copy()), expected[1])
    assert len(rect._ahead) == 1
    np.testing.assert_array_equal(rect.left(imgs[1]), expected[1])
    assert rect._ahead == []
    rect.left_ahead(imgs[2])
    clone = pickle.loads(pickle.dumps(rect))  # a started rectification is not pickled
    assert clone._ahead == []
    np.testing.assert_array_equal(clone.left(imgs[2]), expected[2])
    np.testing.assert_array_equal(rect.left(imgs[2]), expected[2])
    # rectified input passes through, nothing started
    K = np.array([[500.0, 0, 320.0], [0, 500.0, 240.0], [0, 0, 1]])
    t = np.eye(4)
    t[0, 3] = -0.06
    same = Rectifier(StereoCalibration(K, K, t, (640, 480)))
    same.left_ahead(imgs[0])
    assert same._ahead == []
    assert same.left(imgs[0]) is imgs[0]


def test_one_ahead_pairs_each_item_with_the_next_and_a_read_error_comes_after_its_predecessor() -> None:
    assert list(_one_ahead(iter([1, 2, 3]))) == [(1, 2), (2, 3), (3, None)]  # type: ignore[arg-type]
    assert list(_one_ahead(iter([]))) == []

    def failing() -> Iterator[int]:
        yield 1
        yield 2
        raise OSError("bad frame 3")

    got = []
    with pytest.raises(OSError, match="bad frame 3"):
        for pair in _one_ahead(failing()):  # type: ignore[arg-type]
            got.append(pair)
    assert got == [(1, 2), (2, None)]


def test_left_ahead_then_runs_on_the_thread_and_left_and_hands_its_value() -> None:
    """cpu15: ``then`` (the front end's image check) runs after the rectification on the ahead thread.

    ``left_and`` hands its value with the image; another function, or an array not started, is run on the
    spot with the same result; images passed through unrectified are started too when a ``then`` is given.
    """
    import threading

    rng = np.random.default_rng(4)
    imgs = [rng.integers(0, 256, (480, 640), dtype=np.uint8) for _ in range(2)]
    where: list[str] = []

    def check(rect: np.ndarray) -> float:
        where.append(threading.current_thread().name)
        return float(rect.mean())

    rect = Rectifier(_raw_rig())
    expected = Rectifier(_raw_rig()).left(imgs[0])
    rect.left_ahead(imgs[0], check)
    got, value = rect.left_and(imgs[0], check)
    np.testing.assert_array_equal(got, expected)
    assert value == float(expected.mean()) and where == ["rectify-ahead_0"]
    rect.left_ahead(imgs[1], check)
    got, value = rect.left_and(imgs[1], lambda r: float(r.mean()))  # another function: run here
    assert value == float(got.mean()) and rect._ahead == []
    assert where == ["rectify-ahead_0"] * 2  # (the started check ran on the thread, its value unused)
    got, value = rect.left_and(imgs[1], check)  # nothing started: both on the spot
    assert value == float(got.mean()) and where[-1] == threading.current_thread().name
    assert rect.left_and(imgs[1])[1] is None
    K = np.array([[500.0, 0, 320.0], [0, 500.0, 240.0], [0, 0, 1]])
    t = np.eye(4)
    t[0, 3] = -0.06
    same = Rectifier(StereoCalibration(K, K, t, (640, 480)))
    same.left_ahead(imgs[0], check)  # rectified input: started for its check
    assert len(same._ahead) == 1
    got, value = same.left_and(imgs[0], check)
    assert got is imgs[0] and value == float(imgs[0].mean()) and where[-1] == "rectify-ahead_0"
