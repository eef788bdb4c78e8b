"""ORB (OpenCV): 256-bit binary descriptors, Hamming distance; the default kind."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from loopmodel.config import SurfConfig
from loopmodel.loop.descriptors.base import OpenCVDescriptor


class Orb(OpenCVDescriptor):
    """ORB: 8 pyramid levels, scale 1.2, FAST threshold 12."""

    def extractor(self, n_features: int, surf: SurfConfig | None = None) -> Any:
        return cv2.ORB_create(nfeatures=n_features, scaleFactor=1.2, nlevels=8, fastThreshold=12)  # type: ignore[attr-defined]


ORB = Orb("orb", 32, binary=True, stored_dtype=np.uint8)
