"""Moving-edge search in images (seed 002, section V; the ViSP method): for every sample of a
projected model edge, a 1-D search along the edge normal for the strongest grey-level step
of the expected orientation and polarity.

At each candidate offset ``s`` (whole pixels, within ``±range_px``) along the unit normal
``n`` of a sample ``p``, an oriented step mask measures the contrast
``c(s) = mean I(p + (s + a) n + b t) - mean I(p + (s - a) n + b t)`` over ``a = 1..half_depth``
(pixels on each side of the edge) and ``b = -half_width..half_width`` along the tangent ``t``
(bilinear samples; the mask is the ViSP convolution mask rotated to the edge's direction).
Candidates are the local maxima of ``|c|`` above ``min_contrast`` with the polarity the site
expects. The likelihood test keeps a candidate only when its contrast is within
``[ratio_low, ratio_high]`` of what the same model edge matched in the previous frame (the
sites' memory, per camera and model edge); among those the one closest in contrast wins, the
strongest at the first frame. The position is refined to sub-pixel by a parabola through
``|c|`` at the peak and its neighbours.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass
class MovingEdgeOptions:
    """Search settings (pixels; contrast in grey levels)."""

    range_px: int = 10
    half_depth_px: int = 2
    half_width_px: int = 2
    min_contrast: float = 6.0
    ratio_low: float = 0.5
    ratio_high: float = 1.5


@dataclass
class ImageMovingEdges:
    """The moving-edge ``measure`` of :func:`loopmodel.pose.tracking.track_frame` on one image
    shared by all cameras of a rig (the mirror discs of a catadioptric sensor), with the
    sites' memory carried from frame to frame (call :meth:`set_image` for each new frame)."""

    options: MovingEdgeOptions = field(default_factory=MovingEdgeOptions)
    image: NDArray[np.float32] | None = None
    memory: dict[tuple[int, int], tuple[float, float]] = field(default_factory=dict)  # (cam, line) -> (contrast, sign)
    last: dict[int, tuple[NDArray[np.int64], F64, F64]] = field(default_factory=dict)

    def set_image(self, image: NDArray[np.uint8]) -> None:
        """The next frame (8-bit grey, or float)."""
        self.image = np.asarray(image, dtype=np.float32)
        self.last = {}

    def profiles(self, uv: F64, normals: F64) -> F64:
        """Contrast ``c(s)`` of every sample at offsets ``-range..range`` (n x (2 range + 1))."""
        import cv2

        if self.image is None:
            raise ValueError("set_image first")
        o = self.options
        R, a, b = o.range_px, o.half_depth_px, o.half_width_px
        steps = np.arange(-R - a, R + a + 1, dtype=np.float64)  # along the normal
        across = np.arange(-b, b + 1, dtype=np.float64)
        n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
        t = np.column_stack([-n[:, 1], n[:, 0]])
        # (samples, steps, across) sample positions
        px = (
            uv[:, None, None, 0]
            + steps[None, :, None] * n[:, None, None, 0]
            + across[None, None, :] * t[:, None, None, 0]
        )
        py = (
            uv[:, None, None, 1]
            + steps[None, :, None] * n[:, None, None, 1]
            + across[None, None, :] * t[:, None, None, 1]
        )
        k = len(uv)
        vals = cv2.remap(
            self.image,
            px.reshape(k, -1).astype(np.float32),
            py.reshape(k, -1).astype(np.float32),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0.0,
        ).reshape(k, len(steps), len(across))
        line = vals.mean(axis=2)  # (samples, steps): the profile along the normal
        cs = np.concatenate([np.zeros((k, 1)), np.cumsum(line, axis=1)], axis=1)
        centre = np.arange(a, a + 2 * R + 1)  # index of offset s in `steps`
        ahead = (cs[:, centre + a + 1] - cs[:, centre + 1]) / a  # pixels s+1..s+a
        behind = (cs[:, centre] - cs[:, centre - a]) / a  # pixels s-a..s-1
        return np.asarray(ahead - behind)

    def measure(self, j: int, uv: F64, normals: F64, line_index: NDArray[np.int64]) -> tuple[NDArray[np.bool_], F64]:
        """Search every sample of camera ``j``; returns which found an edge and where (pixels)."""
        o = self.options
        R = o.range_px
        c = self.profiles(uv, normals)
        mag = np.abs(c)
        # local maxima of |c| (strict on one side) above the gradient threshold
        peak = np.zeros_like(mag, dtype=bool)
        peak[:, 1:-1] = (mag[:, 1:-1] >= mag[:, :-2]) & (mag[:, 1:-1] > mag[:, 2:])
        peak &= mag >= o.min_contrast
        exp_c = np.array([self.memory.get((j, int(m)), (np.nan, 0.0))[0] for m in line_index])
        exp_s = np.array([self.memory.get((j, int(m)), (np.nan, 0.0))[1] for m in line_index])
        known = np.isfinite(exp_c)
        sign_ok = np.where(known[:, None], np.sign(c) == exp_s[:, None], True)
        ratio = mag / np.where(known, exp_c, 1.0)[:, None]
        like = np.where(known[:, None], (ratio >= o.ratio_low) & (ratio <= o.ratio_high), True)
        cand = peak & sign_ok & like
        score = np.where(known[:, None], -np.abs(np.log(np.maximum(ratio, 1e-9))), mag)
        score = np.where(cand, score, -np.inf)
        best = np.argmax(score, axis=1)
        found = np.isfinite(score[np.arange(len(uv)), best])
        # sub-pixel: parabola through |c| at the peak and its neighbours
        i = np.clip(best, 1, 2 * R - 1)
        rows = np.arange(len(uv))
        y0, y1, y2 = mag[rows, i - 1], mag[rows, i], mag[rows, i + 1]
        den = y0 - 2 * y1 + y2
        frac = np.where(np.abs(den) > 1e-9, 0.5 * (y0 - y2) / np.where(np.abs(den) > 1e-9, den, 1.0), 0.0)
        s = (i - R) + np.clip(frac, -0.5, 0.5)
        s = np.where(best == i, s, best - R)
        n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
        out = uv + s[:, None] * n
        self.last[j] = (line_index[found], mag[rows, best][found], np.sign(c[rows, best])[found])
        return found, out

    def remember(self, j: int, keep: NDArray[np.bool_] | None = None) -> None:
        """Store what camera ``j``'s sites matched in this frame (median contrast and the
        majority polarity per model edge), leaving out matches ``keep`` rejects (the
        M-estimator's outliers), as ViSP suppresses such sites."""
        if j not in self.last:
            return
        li, cc, ss = self.last[j]
        good = np.ones(len(li), bool) if keep is None else np.asarray(keep, bool)
        for m in np.unique(li[good]):
            sel = good & (li == m)
            self.memory[(j, int(m))] = (float(np.median(cc[sel])), 1.0 if ss[sel].sum() >= 0 else -1.0)
