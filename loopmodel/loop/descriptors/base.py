"""The interface every loop-closing descriptor kind implements (one module per kind, issue 32).

A :class:`Descriptor` makes its extractor from the ``loop`` settings, detects and describes a grey
image, describes given pixel positions, and says how its descriptors are compared (binary: Hamming,
else L2), stored in a map file and shaped when empty. Arrays in, arrays out: :mod:`loopmodel.loop.features`
wraps them into :class:`~loopmodel.loop.features.FeatureSet` values.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.config import SurfConfig

F64 = NDArray[np.float64]

#: What a detection or description gives: pixels (N, 2), descriptors (N, D), Laplacian signs (N,)
#: int8 or None (kinds without them)
Described = tuple[F64, NDArray[Any], NDArray[np.int8] | None]


@dataclass(frozen=True)
class Descriptor:
    """One descriptor kind: its name, length ``dim``, in-memory ``dtype`` and map-file ``stored_dtype``.

    ``binary``: bit strings compared by Hamming distance (else float vectors, L2). ``stored_dtype``
    None: uint8 when the values are whole numbers in [0, 255] (SIFT), else float32.
    """

    name: str
    dim: int
    binary: bool
    stored_dtype: Any = None

    @property
    def dtype(self) -> Any:
        """The in-memory descriptor dtype (uint8 binary strings, float32 vectors)."""
        return np.uint8 if self.binary else np.float32

    def empty(self) -> NDArray[Any]:
        """No descriptors: a (0, dim) array of :attr:`dtype`."""
        return np.zeros((0, self.dim), self.dtype)

    def extractor(self, n_features: int, surf: SurfConfig | None = None) -> Any:
        """The detector/descriptor keeping at most ``n_features`` (``surf``: SURF's settings)."""
        raise NotImplementedError

    def detect(self, extractor: Any, grey: NDArray[np.uint8]) -> Described:
        """Keypoints (pixels) and their descriptors in a grey image."""
        raise NotImplementedError

    def describe_at(
        self, extractor: Any, grey: NDArray[np.uint8], uv_px: F64, size_px: float
    ) -> tuple[Described, NDArray[np.int64]]:
        """Descriptors at given pixels (``size_px``: the keypoint size) and the indices of those kept."""
        raise NotImplementedError


class OpenCVDescriptor(Descriptor):
    """A kind whose extractor is an OpenCV ``Feature2D`` (``detectAndCompute``, ``compute``)."""

    def detect(self, extractor: Any, grey: NDArray[np.uint8]) -> Described:
        kps, desc = extractor.detectAndCompute(grey, None)
        if desc is None or len(kps) == 0:
            return np.zeros((0, 2)), self.empty(), None
        return np.array([kp.pt for kp in kps], dtype=float), desc, None

    def describe_at(
        self, extractor: Any, grey: NDArray[np.uint8], uv_px: F64, size_px: float
    ) -> tuple[Described, NDArray[np.int64]]:
        kps = [cv2.KeyPoint(float(u), float(v), size_px, -1, 0, 0, int(i)) for i, (u, v) in enumerate(uv_px)]
        kps_out, desc = extractor.compute(grey, kps)
        if desc is None or len(kps_out) == 0:
            return (np.zeros((0, 2)), self.empty(), None), np.zeros(0, np.int64)
        kept = np.array([kp.class_id for kp in kps_out], dtype=np.int64)
        return (uv_px[kept], desc, None), kept
