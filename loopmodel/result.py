"""What a run produced (:class:`RunResult`).

Trajectories, keyframes, landmarks, stripes, the mesh and the metrics; written to a results folder
by :func:`loopmodel.io.results.write_results`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import Config
from loopmodel.frontend.keyframe import FrameResult
from loopmodel.types import StereoCalibration, StripeProfile, Trajectory

if TYPE_CHECKING:
    import open3d as o3d

    from loopmodel.loop.session_map import SessionMap


def _empty_trajectory() -> Trajectory:
    return Trajectory(np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4)))


@dataclass
class RunResult:
    """The outcome of one run of the pipeline over a sequence.

    ``frames``: every processed frame's front-end result (without its keyframe payload);
    ``online``: the poses as estimated live (OK frames); ``final``: every tracked frame
    recomposed with the final keyframe poses; ``keyframes``: the final keyframe poses
    (timestamps of the keyframes) with their ids in ``keyframe_ids``; ``landmark_ids`` and
    ``landmarks_in_world`` (N, 3, metres) from the back end's final estimate; ``stripes``:
    the laser profiles up to the last processed frame (sensor frame); ``mesh`` of the
    stripes placed with the final trajectory and ``live_mesh`` as the live mapping left it
    (open3d meshes, world frame, metres; None without); ``metrics`` for ``metrics.json``;
    ``interrupted``: stopped early on request; ``error``: the error that ended it early (the
result covers the frames before it); ``log``: the run's log lines (``run.log``); ``folder``: where it was written, if it
    was; ``session_map``: the map a later session can localize in (``output.write_map``; merged with the
    base map when extending one); ``localized``: the frames localized in a base map (its world).
    Poses are ``world_from_cam`` of the left camera, the world being the first
    keyframe's frame.
    """

    config: Config
    frames: list[FrameResult] = field(default_factory=list)
    online: Trajectory = field(default_factory=_empty_trajectory)
    final: Trajectory = field(default_factory=_empty_trajectory)
    keyframes: Trajectory = field(default_factory=_empty_trajectory)
    keyframe_ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    landmark_ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    landmarks_in_world: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    stripes: list[StripeProfile] = field(default_factory=list)
    mesh: o3d.geometry.TriangleMesh | None = None
    live_mesh: o3d.geometry.TriangleMesh | None = None
    metrics: dict[str, Any] = field(default_factory=dict)
    interrupted: bool = False
    error: Exception | None = None
    log: str = ""
    folder: Path | None = None
    session_map: SessionMap | None = None
    localized: Trajectory | None = None
    # issue 31 (calibration.refine: final): the refined raw calibration and its report
    # (per-parameter values and sigmas, the light plane) for calibration_refined.yaml
    calibration_refined: StereoCalibration | None = None
    calibration_report: dict[str, Any] = field(default_factory=dict)

    def __repr__(self) -> str:
        """One line: what the run did and where it went (not the whole configuration)."""
        from loopmodel.display import Formatter, num

        m = self.metrics
        fmt = Formatter.for_positions(self.final.world_from_cam[:, :3, 3])
        parts = [f"frames={len(self.frames)}", f"keyframes={len(self.keyframes)}"]
        if m.get("ate_rmse_m") is not None:
            parts.append(f"ate_rmse={fmt.length_text(m['ate_rmse_m'])}")
        if m.get("loop_closure_count") is not None:
            parts.append(f"loop_closures={m['loop_closure_count']}")
        if self.mesh is not None:
            parts.append(f"mesh_vertices={num(len(self.mesh.vertices))}")
        parts.append(f"folder={str(self.folder) if self.folder is not None else None!r}")
        if self.interrupted or self.error is not None:
            parts.append(f"interrupted={self.interrupted}, error={self.error!r}")
        return f"RunResult({', '.join(parts)})"

    def map_arrays(self) -> dict[str, NDArray[Any]]:
        """``map.npz`` content: keyframe ids, times and poses; landmark ids and world points."""
        return {
            "keyframe_ids": self.keyframe_ids,
            "keyframe_timestamps_ns": self.keyframes.timestamps_ns,
            "world_from_kf": self.keyframes.world_from_cam,
            "landmark_ids": self.landmark_ids,
            "landmarks_in_world": self.landmarks_in_world,
        }
