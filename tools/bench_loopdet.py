"""Benchmark ``loopdet``: loop detection on RTAB-Map's 84 real corridor images.

Images are processed in order; each queries the keyframe database (the vocabulary shipped
for the descriptor kind, trained on other images, as the pipeline uses it; the
``trained_on_test_*`` keys: a vocabulary trained on the fly from the test images already
seen, for comparison), temporally consistent candidates are
verified with a fundamental matrix, and the accepted loop (at most one per image) is
compared with ``samples_GT.bmp``. Pairs within 5 frames never count (the database does not
offer them). ``precision`` = correct loops / loops; ``recall`` = images with a correct loop
/ images that have a true partner more than 5 frames back; ``pairs_true`` = number of such
true pairs in the matrix. The top-level keys are ORB's (the default descriptor); the run
repeats for SIFT and SURF (``<kind>_precision``, ``<kind>_recall``, ...), each with the
vocabulary shipped for its kind.
"""

from __future__ import annotations

import statistics
import time

import cv2
import numpy as np
from shared_data import SHARED_DATA

from loopmodel.io.vocabulary_file import shipped_vocabulary
from loopmodel.loop.closure import LoopDetector, LoopParams
from loopmodel.loop.database import PlaceParams
from loopmodel.loop.features import detect_and_describe, make_extractor

DATA = SHARED_DATA / "loop_images"
EXCLUDE = 5


def evaluate(kind: str) -> dict:
    """Loop detection over the images with one descriptor kind.

    With the shipped vocabulary, and one trained on the fly from the test images
    (``trained_on_test_*``) for comparison.
    """
    shipped = _run(kind, online=False)
    trained = _run(kind, online=True)
    for k in ("precision", "recall", "detections", "query_ms_median"):
        shipped[f"trained_on_test_{k}"] = trained[k]
    return shipped


def run(quick: bool = False) -> dict:
    out = evaluate("orb")
    for kind in ("surf",) if quick else ("sift", "surf"):
        res = evaluate(kind)
        for k in ("detections", "true_positives", "precision", "recall", "query_ms_median"):
            out[f"{kind}_{k}"] = res[k]
            out[f"{kind}_trained_on_test_{k}"] = res.get(f"trained_on_test_{k}")
    for k in ("detections", "true_positives", "precision", "recall", "query_ms_median"):
        out[f"orb_{k}"] = out[k]
    return out


def _run(kind: str, online: bool) -> dict:
    gt_img = cv2.imread(str(DATA / "samples_GT.bmp"), cv2.IMREAD_GRAYSCALE)
    if gt_img is None:
        raise FileNotFoundError(DATA / "samples_GT.bmp")
    gt = np.asarray(gt_img) > 128
    n = gt.shape[0]
    n_features = 1000
    ex = make_extractor(kind, n_features)
    feats = []
    for i in range(n):
        img = cv2.imread(str(DATA / "samples" / f"{i + 1}.jpg"), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise FileNotFoundError(DATA / "samples" / f"{i + 1}.jpg")
        feats.append(detect_and_describe(img, kind, n_features, ex))
        width = img.shape[1]
    params = LoopParams(place=PlaceParams(min_gap=EXCLUDE + 1, train_after=8))
    voc = None if online else shipped_vocabulary(kind)
    det = LoopDetector(None, params, voc, image_width_px=width)
    detections: dict[int, int] = {}
    q_ms = []
    for i in range(n):
        t0 = time.perf_counter()
        ev = det.process(i, feats[i])
        q_ms.append((time.perf_counter() - t0) * 1e3)
        if ev is not None:
            detections[i] = ev.match_id
            mark = "ok" if gt[i, ev.match_id] else "FALSE"
            tag = "trained" if online else "shipped"
            print(f"[{kind} {tag}] image {i + 1}: loop with {ev.match_id + 1} ({ev.n_inliers} inliers) {mark}")
    far = np.tril(gt, -(EXCLUDE + 1))
    pairs_true = int(far.sum())
    queries_true = int(np.any(far, axis=1).sum())
    tp = sum(1 for i, j in detections.items() if far[i, j])
    precision = tp / len(detections) if detections else 1.0
    recall = tp / queries_true if queries_true else 0.0
    return {
        "dataset": "RTAB-Map loop_images (84 real 512x384 images)",
        "descriptor": kind,
        "pairs_true": pairs_true,
        "queries_true": queries_true,
        "detections": len(detections),
        "true_positives": tp,
        "rejected_candidates": len(det.rejected),
        "precision": round(precision, 4),
        "recall": round(recall, 4),
        "query_ms_median": round(statistics.median(q_ms), 2),
        "query_ms_p95": round(float(np.percentile(q_ms, 95)), 2),
        "vocabulary_words": det.database.vocabulary.n_words if det.database.vocabulary else 0,
    }
