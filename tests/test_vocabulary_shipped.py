"""The vocabularies shipped as package data (issue 26).

Load, provenance, retrieval on the real loop images (which they were not trained on).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from loopmodel.config import LoopConfig
from loopmodel.io.vocabulary_file import loop_vocabulary, read_vocabulary, shipped_path, shipped_vocabulary
from loopmodel.loop.closure import detector_from_config
from loopmodel.loop.database import KeyframeDatabase
from loopmodel.loop.features import detect_and_describe, make_extractor


@pytest.mark.parametrize("kind", ["orb", "sift", "surf"])
def test_shipped_vocabulary_loads_with_provenance(kind: str) -> None:
    voc = read_vocabulary(shipped_path(kind))
    assert voc.info["kind"] == kind
    assert "stereo_calib" in voc.info["source"]  # not the loop_images test set
    assert voc.binary == (kind == "orb")
    assert voc.n_words > 1000
    assert np.all(np.isfinite(voc.idf))


def test_detector_uses_shipped_vocabulary_unless_online() -> None:
    det = detector_from_config(LoopConfig(), None, 640.0, loop_vocabulary(LoopConfig()))
    assert det.database.vocabulary is shipped_vocabulary("orb")
    assert loop_vocabulary(LoopConfig(vocabulary_online=True)) is None  # trained from the keyframes
    online = detector_from_config(LoopConfig(vocabulary_online=True), None, 640.0)
    assert online.database.vocabulary is None


@pytest.mark.parametrize("kind", ["orb", pytest.param("sift", marks=pytest.mark.slow)])
def test_shipped_vocabulary_retrieves_true_revisits(shared_data: Path, kind: str) -> None:
    """Images 41-84 revisit 1-44: the best-scoring stored image of each revisit is a true match.

    With images 1-40 stored, the best-scoring stored image of each revisit with a true partner among
    them is a true match (samples_GT.bmp). Measured 42 of 44 for both ORB and SIFT; at least 40
    required.
    """
    folder = shared_data / "loop_images"
    gt = cv2.imread(str(folder / "samples_GT.bmp"), cv2.IMREAD_GRAYSCALE) > 128
    ex = make_extractor(kind, 1000)
    feats = [
        detect_and_describe(cv2.imread(str(folder / "samples" / f"{i + 1}.jpg"), cv2.IMREAD_GRAYSCALE), kind, 1000, ex)
        for i in range(84)
    ]
    db = KeyframeDatabase(shipped_vocabulary(kind))
    for i in range(40):
        db.add(i, feats[i])
    hits = total = 0
    for q in range(40, 84):
        if not gt[q, :40].any():
            continue
        ids, scores = db.score_all(feats[q])
        total += 1
        hits += bool(gt[q, int(ids[np.argmax(scores)])])
    assert total == 44
    assert hits >= 40
