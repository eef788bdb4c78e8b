"""The front end's figures for ``metrics.json``: counts and timings of its frame results."""

from __future__ import annotations

from typing import Any

import numpy as np

from loopmodel.frontend.keyframe import FrameResult


def percentile_or_none(a: np.ndarray, p: float) -> float | None:
    """The ``p``-th percentile of ``a``, or None when it is empty."""
    return float(np.percentile(a, p)) if a.size else None


def frontend_metrics(frames: list[FrameResult], wall_s: float) -> dict[str, Any]:
    """Counts and timings of a front-end run (milliseconds, medians and 95th percentiles)."""
    track = np.array([f.track_ms for f in frames], dtype=float)
    kf_ms = np.array([f.keyframe_ms for f in frames if f.is_keyframe], dtype=float)
    total = np.array([f.track_ms + f.keyframe_ms for f in frames], dtype=float)
    busy_s = float(total.sum() / 1e3)
    return {
        "frames": len(frames),
        "ok_frames": sum(f.ok for f in frames),
        "lost_frames": sum(not f.ok for f in frames),
        "keyframes": sum(f.is_keyframe for f in frames),
        "segments": max((f.segment + 1 for f in frames), default=0),
        "track_ms_median": percentile_or_none(track, 50),
        "track_ms_p95": percentile_or_none(track, 95),
        "keyframe_ms_median": percentile_or_none(kf_ms, 50),
        "frame_ms_median": percentile_or_none(total, 50),
        "fps": len(frames) / busy_s if busy_s > 0 else None,
        "fps_with_io": len(frames) / wall_s if wall_s > 0 else None,
    }
