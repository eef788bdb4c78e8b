"""Frame poses anchored to keyframes, so that back-end corrections reach every frame.

Each frame is stored as ``kf_from_cam`` relative to its keyframe; the frame's world pose is
recomposed as ``world_from_kf[keyframe] @ kf_from_cam`` with the keyframe poses of the
moment, so moving a keyframe moves all of its frames.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from loopmodel.types import Trajectory

F64 = NDArray[np.float64]


class AnchoredTrajectory:
    """Timed frame poses stored relative to keyframes (metres; 4x4 transforms)."""

    def __init__(self) -> None:
        self._t_ns: list[int] = []
        self._kf: list[int] = []
        self._kf_from_cam: list[F64] = []
        self._world_from_kf: dict[int, F64] = {}

    def __len__(self) -> int:
        return len(self._t_ns)

    def set_keyframe(self, kf_id: int, world_from_kf: F64) -> None:
        """Set (or move) keyframe ``kf_id``."""
        self._world_from_kf[int(kf_id)] = np.asarray(world_from_kf, dtype=float).reshape(4, 4).copy()

    def update_keyframes(self, world_from_kf: Mapping[int, F64]) -> None:
        """Move several keyframes at once (e.g. after a back-end update)."""
        for k, T in world_from_kf.items():
            self.set_keyframe(k, T)

    def add(self, timestamp_ns: int, kf_id: int, kf_from_cam: F64) -> None:
        """Append a frame at ``timestamp_ns`` with pose ``kf_from_cam`` in keyframe ``kf_id``."""
        if int(kf_id) not in self._world_from_kf:
            raise KeyError(f"frame at {timestamp_ns} ns refers to unknown keyframe {kf_id}")
        self._t_ns.append(int(timestamp_ns))
        self._kf.append(int(kf_id))
        self._kf_from_cam.append(np.asarray(kf_from_cam, dtype=float).reshape(4, 4).copy())

    @property
    def keyframe_poses(self) -> dict[int, F64]:
        """Current ``world_from_kf`` of every keyframe (copies)."""
        return {k: T.copy() for k, T in self._world_from_kf.items()}

    def trajectory(self) -> Trajectory:
        """Every frame's ``world_from_cam`` recomposed with the current keyframe poses."""
        n = len(self._t_ns)
        if n == 0:
            return Trajectory(np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4)))
        world_from_kf = np.stack([self._world_from_kf[k] for k in self._kf])
        return Trajectory(np.array(self._t_ns, dtype=np.int64), world_from_kf @ np.stack(self._kf_from_cam))
