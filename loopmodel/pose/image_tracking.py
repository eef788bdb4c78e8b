"""Model-based tracking from images: moving edges (:mod:`loopmodel.pose.moving_edges`) feeding
the robust VVS of :func:`loopmodel.pose.tracking.track_frame`, frame after frame.

The first frame starts from an initial pose that may be several degrees and centimetres off:
it is tracked repeatedly on the same image (search, VVS, search again from the new pose) until
the pose stops moving, so the search range need not cover the whole initial error at once.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.se3 import invert_pose, so3_log
from loopmodel.pose.moving_edges import ImageMovingEdges, MovingEdgeOptions
from loopmodel.pose.rig import F64, CameraRig
from loopmodel.pose.tracking import PolyhedronModel, TrackerOptions, TrackResult, ValidFn, track_frame


@dataclass
class ImageTrackingOptions:
    """Tracker, moving-edge and start-up settings."""

    tracker: TrackerOptions = field(default_factory=TrackerOptions)
    edges: MovingEdgeOptions = field(default_factory=MovingEdgeOptions)
    first_frame_iterations: int = 10  # search + VVS repeated on the first image at most
    # the first rounds search wider (pixels), coarse to fine, then at ``edges.range_px``
    first_frame_ranges_px: tuple[int, ...] = (14,)
    converged_deg: float = 0.05  # ... until the pose moves less than this
    converged_m: float = 0.0005


@dataclass
class FrameTrack:
    """One tracked frame: pose, matched and inlier edge points, times (ms)."""

    rig_from_ref: F64
    ok: bool
    num_matched: int
    num_inliers: int
    search_ms: float
    frame_ms: float
    iter_ms: float


def _step(T_prev: F64, T: F64) -> tuple[float, float]:
    D = invert_pose(T_prev) @ T
    return float(np.degrees(np.linalg.norm(so3_log(D[:3, :3])))), float(np.linalg.norm(D[:3, 3]))


class ImageTracker:
    """Tracks a polyhedral model through images of a rig (all cameras in one image)."""

    def __init__(
        self,
        rig: CameraRig,
        model: PolyhedronModel,
        rig_from_ref_init: F64,
        valid: ValidFn | None = None,
        options: ImageTrackingOptions | None = None,
    ) -> None:
        self.rig = rig
        self.model = model
        self.pose = np.asarray(rig_from_ref_init, float).copy()
        self.valid = valid
        self.options = options or ImageTrackingOptions()
        self.edges = ImageMovingEdges(self.options.edges)
        self._frames = 0

    def _once(self) -> tuple[TrackResult, float]:
        t_search = [0.0]
        edges = self.edges

        def measure(j: int, uv: F64, normals: F64, line_index: NDArray[np.int64]) -> tuple[NDArray[np.bool_], F64]:
            t0 = time.perf_counter()
            out = edges.measure(j, uv, normals, line_index)
            t_search[0] += time.perf_counter() - t0
            return out

        res = track_frame(self.rig, self.model, self.pose, measure, self.options.tracker, self.valid)
        return res, t_search[0] * 1e3

    def _remember(self, res: TrackResult) -> None:
        w_all = res.vvs.weights[0] if res.vvs is not None else None
        start = 0
        for j in sorted(self.edges.last):
            n = len(self.edges.last[j][0])
            w = w_all[start : start + n] if w_all is not None else np.ones(n)
            start += n
            self.edges.remember(j, w > 0.5)

    def track(self, image: NDArray[np.uint8]) -> FrameTrack:
        """Track the next image; the pose carries over to the next frame (no motion model)."""
        t0 = time.perf_counter()
        self.edges.set_image(image)
        opt = self.options
        first = self._frames == 0
        rounds = opt.first_frame_iterations if first else 1
        search_ms = 0.0
        res: TrackResult | None = None
        base_range = opt.edges.range_px
        try:
            for r in range(rounds):
                wide = first and r < len(opt.first_frame_ranges_px)
                self.edges.options.range_px = opt.first_frame_ranges_px[r] if wide else base_range
                res, ms = self._once()
                search_ms += ms
                moved_deg, moved_m = _step(self.pose, res.rig_from_ref)
                if res.ok:
                    self.pose = res.rig_from_ref
                converged = moved_deg < opt.converged_deg and moved_m < opt.converged_m
                if not res.ok or (converged and not wide):
                    break
        finally:
            self.edges.options.range_px = base_range
        assert res is not None
        if res.ok:
            self._remember(res)
        self._frames += 1
        it = res.vvs.info.get("iter_ms", np.nan) if res.vvs is not None else np.nan
        return FrameTrack(
            self.pose.copy(),
            res.ok,
            res.num_matched,
            res.num_inliers,
            search_ms,
            (time.perf_counter() - t0) * 1e3,
            float(it),
        )


def track_images(
    rig: CameraRig,
    model: PolyhedronModel,
    images: Iterable[NDArray[np.uint8]],
    rig_from_ref_init: F64,
    valid: ValidFn | None = None,
    options: ImageTrackingOptions | None = None,
    progress: Callable[[int], None] | None = None,
) -> list[FrameTrack]:
    """Track the model through ``images`` from an initial pose (``rig_from_ref``, metres)."""
    tracker = ImageTracker(rig, model, rig_from_ref_init, valid, options)
    out = []
    for k, img in enumerate(images):
        out.append(tracker.track(img))
        if progress is not None:
            progress(k)
    return out


def mask_valid(mask: NDArray[np.uint8] | None, image_shape: tuple[int, int], margin_px: int = 0) -> ValidFn:
    """The ``valid`` of a label mask (pixel value ``j + 1``: usable by camera ``j``); without a
    mask every pixel inside the image is usable. ``margin_px``: samples closer than this to the
    border of their camera's region are not used (a search along the normal must not reach the
    rim or a masked zone, whose boundary is a strong edge of its own)."""
    import cv2

    h, w = image_shape
    if mask is not None and margin_px > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin_px + 1, 2 * margin_px + 1))
        eroded = np.zeros_like(mask)
        for label in np.unique(mask[mask > 0]):
            region = cv2.erode((mask == label).astype(np.uint8), kernel)
            eroded[region > 0] = label
        mask = eroded

    def valid(j: int, uv: F64) -> NDArray[np.bool_]:
        u, v = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
        inside = (u >= 0) & (v >= 0) & (u < w) & (v < h)
        if mask is None:
            return inside
        ok = np.zeros(len(uv), dtype=bool)
        ok[inside] = mask[v[inside], u[inside]] == j + 1
        return ok

    return valid
