"""SIFT (OpenCV): 128 floats per feature (whole numbers in [0, 255]: stored as uint8), L2 distance."""

from __future__ import annotations

from typing import Any

import cv2

from loopmodel.config import SurfConfig
from loopmodel.loop.descriptors.base import OpenCVDescriptor


class Sift(OpenCVDescriptor):
    """SIFT with OpenCV's default octave layers and thresholds."""

    def extractor(self, n_features: int, surf: SurfConfig | None = None) -> Any:
        return cv2.SIFT_create(nfeatures=n_features)  # type: ignore[attr-defined]


SIFT = Sift("sift", 128, binary=False)
