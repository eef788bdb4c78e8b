"""SURF (:mod:`loopmodel.loop.surf`, written here: OpenCV wheels lack the non-free module).

64 floats per feature (stored as float16) with the sign of the Laplacian; only features of the same
sign are matched.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import SurfConfig
from loopmodel.loop.descriptors.base import F64, Described, Descriptor
from loopmodel.loop.surf import Surf, SurfKeypoints


class SurfKind(Descriptor):
    """SURF by :class:`~loopmodel.loop.surf.Surf` with the ``loop.surf`` settings."""

    def extractor(self, n_features: int, surf: SurfConfig | None = None) -> Any:
        return Surf.from_config(surf, n_features)

    def detect(self, extractor: Any, grey: NDArray[np.uint8]) -> Described:
        kp, d = extractor.detect_and_describe(grey)
        return kp.xy, d, kp.sign

    def describe_at(
        self, extractor: Any, grey: NDArray[np.uint8], uv_px: F64, size_px: float
    ) -> tuple[Described, NDArray[np.int64]]:
        """The orientation and Laplacian sign at the scale of a ``size_px`` box filter (``1.2 size_px / 9``)."""
        ex: Surf = extractor
        h, w = grey.shape
        u, v = uv_px[:, 0], uv_px[:, 1]
        kept = np.flatnonzero((u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1))
        xy = uv_px[kept]
        scale = np.full(kept.size, 1.2 * size_px / 9.0)
        ii = ex.integral(grey)
        iid = ex.describe_integral(grey, ii)
        angle = ex.orient(grey, xy, scale, iid)
        sign = ex.laplacian_sign(grey, xy, scale, ii)
        kp = SurfKeypoints(xy, scale, angle, np.zeros(kept.size), sign)
        return (xy, ex.describe(grey, kp, iid), sign), kept.astype(np.int64)


SURF = SurfKind("surf", 64, binary=False, stored_dtype=np.float16)
