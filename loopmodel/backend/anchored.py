"""Frame poses anchored to keyframes, so that back-end corrections reach every frame.

Each frame is stored as ``kf_from_cam`` relative to its keyframe; the frame's world pose is
recomposed as ``world_from_kf[keyframe] @ kf_from_cam`` with the keyframe poses of the
moment, so moving a keyframe moves all of its frames.

:meth:`AnchoredTrajectory.bridged_trajectory` also uses the next keyframe: the tracker's
frames between keyframes A and B form a chain of relative motions from A whose end point
(the tracker's pose of B) disagrees with the estimated ``A_from_B`` by the drift of the
interval. The least-squares solution of that chain with equal noise per step and both
ends held at the estimated keyframes distributes the disagreement along it, i.e. each
frame's pose gets the fraction ``alpha = (t - t_A) / (t_B - t_A)`` of the end correction
(on SE(3), in the frame's own coordinates).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.se3 import invert_pose, se3_exp, se3_log
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

    def bridged_trajectory(
        self, keyframe_times_ns: Mapping[int, int], tracked_links: Mapping[int, tuple[int, F64]]
    ) -> Trajectory:
        """Like :meth:`trajectory`, with the drift of each keyframe interval distributed over
        its frames. ``tracked_links[B] = (A, A_from_B_tracked)``: keyframe B was made from a
        frame tracked against keyframe A, at the tracker's pose ``A_from_B_tracked``;
        ``keyframe_times_ns`` gives the keyframes' times. Frames of a keyframe without a
        linked successor (the last one, or before a tracking loss) are recomposed as in
        :meth:`trajectory`."""
        base = self.trajectory()
        if len(base) == 0:
            return base
        successor: dict[int, tuple[int, F64]] = {}
        for b, (a, a_from_b) in tracked_links.items():
            known = self._world_from_kf.keys() & keyframe_times_ns.keys()
            if a in known and b in known:
                successor[int(a)] = (int(b), np.asarray(a_from_b, dtype=float).reshape(4, 4))
        out = base.world_from_cam.copy()
        step: dict[int, F64] = {}
        for i, (t, k) in enumerate(zip(self._t_ns, self._kf, strict=True)):
            nxt = successor.get(k)
            if nxt is None:
                continue
            b, a_from_b_tracked = nxt
            t_a, t_b = keyframe_times_ns[k], keyframe_times_ns[b]
            if not t_a < t < t_b:
                continue
            if k not in step:  # the end correction, in B's tracked frame
                a_from_b = invert_pose(self._world_from_kf[k]) @ self._world_from_kf[b]
                step[k] = se3_log(invert_pose(a_from_b_tracked) @ a_from_b)
            alpha = (t - t_a) / (t_b - t_a)
            out[i] = self._world_from_kf[k] @ self._kf_from_cam[i] @ se3_exp(alpha * step[k])
        return Trajectory(base.timestamps_ns, out)
