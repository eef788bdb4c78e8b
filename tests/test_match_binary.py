"""The one-pass binary matcher against OpenCV's two passes (``knnMatch`` k=2 + reverse ``match``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from loopmodel.loop.features import FeatureSet, _match, match_descriptors


def _opencv_pairs(qd: np.ndarray, td: np.ndarray, ratio: float, mutual: bool) -> np.ndarray:
    """Ratio-test (and mutual) pairs by OpenCV's brute-force matcher, the way the loop stage made them before kf15."""
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    pairs = [
        (m[0].queryIdx, m[0].trainIdx)
        for m in matcher.knnMatch(qd, td, k=2)
        if len(m) == 1 or (len(m) == 2 and m[0].distance < ratio * m[1].distance)
    ]
    out = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    if mutual and out.shape[0]:
        best_q = np.full(td.shape[0], -1, np.int64)
        for bm in matcher.match(td, qd):
            best_q[bm.queryIdx] = bm.trainIdx
        out = out[best_q[out[:, 1]] == out[:, 0]]
    return out


@pytest.mark.parametrize("mutual", [True, False])
def test_same_pairs_as_opencv_with_many_ties(mutual: bool) -> None:
    """Low-entropy descriptors (few bits set: many equal distances), duplicated rows, several ratios."""
    for seed in range(120):
        rng = np.random.default_rng(seed)
        bits = int(rng.integers(1, 9))
        n1, n2 = int(rng.integers(2, 50)), int(rng.integers(2, 50))
        a = rng.integers(0, 2**bits, (n1, 32)).astype(np.uint8)
        b = rng.integers(0, 2**bits, (n2, 32)).astype(np.uint8)
        if seed % 3 == 0:
            b[: n2 // 2] = a[rng.integers(0, n1, n2 // 2)]
        if seed % 5 == 0:
            a[1::2] = a[0]
        ratio = (0.6, 0.8, 0.9, 1.0)[seed % 4]
        got = _match(a, b, True, ratio, None, mutual)
        assert np.array_equal(got, _opencv_pairs(a, b, ratio, mutual)), seed


def test_same_pairs_as_opencv_on_orb_features() -> None:
    """Real ORB descriptors of a textured image and of the same image shifted and noised."""
    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur((rng.random((240, 320)) * 255).astype(np.uint8), (5, 5), 1.5)
    moved = np.clip(np.roll(img, (3, 5), axis=(0, 1)).astype(int) + rng.integers(-6, 7, img.shape), 0, 255)
    orb = cv2.ORB_create(500)
    _, da = orb.detectAndCompute(img, None)
    _, db = orb.detectAndCompute(moved.astype(np.uint8), None)
    fa = FeatureSet(np.zeros((len(da), 2)), da, "orb")
    fb = FeatureSet(np.zeros((len(db), 2)), db, "orb")
    got = match_descriptors(fa, fb, ratio=0.8)
    want = _opencv_pairs(da, db, 0.8, True)
    assert want.shape[0] > 50 and np.array_equal(got, want)


def test_database_describes_a_scored_keyframe_once() -> None:
    """A keyframe scored, then stored: the words a fresh description gives, its descriptors walked down once."""
    from loopmodel.loop.database import KeyframeDatabase
    from loopmodel.loop.vocabulary import Vocabulary

    rng = np.random.default_rng(5)
    sets = [rng.integers(0, 256, (200, 32)).astype(np.uint8) for _ in range(4)]
    voc = Vocabulary.train(np.concatenate(sets), 4, 3, rng=np.random.default_rng(0), documents=sets)
    db = KeyframeDatabase(voc)
    calls = []
    transform = voc.transform
    voc.transform = lambda d: calls.append(len(d)) or transform(d)  # type: ignore[method-assign]
    for k, d in enumerate(sets):
        fs = FeatureSet(np.zeros((len(d), 2)), d, "orb")
        db.query(k, fs)
        db.add(k, fs)
        assert np.array_equal(db.words_of(k), transform(d))
    assert calls == [200] * 4
