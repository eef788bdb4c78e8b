"""Frame poses anchored to keyframes.

Every tracked frame is stored relative to its keyframe, ``world_from_cam = world_from_kf[kf] @
kf_from_cam``, so a keyframe correction moves all of its frames rigidly. A frame given only as
``world_from_cam`` anchors itself (a pseudo-keyframe with a negative id), so an offline
trajectory is stored the same way.

Whatever depends on frame poses (the laser stripes of :class:`~loopmodel.mapping.stripe_map.StripeMap`)
registers as a :class:`PoseWatcher` and is told which frames were added or moved.

Units: metres, nanoseconds. Frames: camera = left camera (x right, y down, z forward).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from loopmodel.errors import EstimationError, InputError
from loopmodel.geometry.se3 import invert_pose, is_rotation, so3_exp, so3_log
from loopmodel.types import Trajectory

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class Rows:
    """Growable array of rows (amortised O(1) append)."""

    def __init__(self, shape: tuple[int, ...], dtype: type | np.dtype) -> None:  # type: ignore[type-arg]
        self._buf = np.zeros((16, *shape), dtype=dtype)
        self.n = 0

    def append(self, rows: NDArray) -> tuple[int, int]:  # type: ignore[type-arg]
        """Append rows; returns their ``[start, stop)`` indices."""
        k = rows.shape[0]
        if self.n + k > self._buf.shape[0]:
            cap = max(2 * self._buf.shape[0], self.n + k)
            grown = np.zeros((cap, *self._buf.shape[1:]), dtype=self._buf.dtype)
            grown[: self.n] = self._buf[: self.n]
            self._buf = grown
        self._buf[self.n : self.n + k] = rows
        self.n += k
        return self.n - k, self.n

    @property
    def a(self) -> NDArray:  # type: ignore[type-arg]
        """The filled rows (a view; writes go to the buffer)."""
        return self._buf[: self.n]


def check_pose(T: ArrayLike, what: str) -> F64:
    """``T`` as a float 4x4 rigid transform, or an :class:`InputError` naming ``what``."""
    M = np.asarray(T, dtype=float)
    if M.shape != (4, 4) or not np.all(np.isfinite(M)) or not is_rotation(M[:3, :3], 1e-5):
        raise InputError(None, f"{what} must be a finite 4x4 rigid transform")
    return M


class PoseWatcher(Protocol):
    """Something placed with the frame poses, told when they change."""

    def frames_added(self) -> None:
        """New frames were appended (times increasing)."""

    def frames_moved(self, frames: I64) -> None:
        """The world poses of these frames (indices) changed."""


class AnchoredTrajectory:
    """Tracked frames stored relative to their keyframes; corrections move the keyframes."""

    def __init__(self) -> None:
        self._world_from_kf: dict[int, F64] = {}
        self._t = Rows((), np.int64)
        self._kf = Rows((), np.int64)
        self._kf_from_cam = Rows((4, 4), np.float64)
        self._next_anchor = -1  # pseudo-keyframe ids of self-anchored frames are negative
        self._watchers: list[PoseWatcher] = []

    @classmethod
    def from_trajectory(cls, trajectory: Trajectory) -> AnchoredTrajectory:
        """Every pose of ``trajectory`` anchors its own frame."""
        trajectory.check("trajectory")
        out = cls()
        n = len(trajectory)
        anchors = -1 - np.arange(n, dtype=np.int64)
        out._t.append(np.asarray(trajectory.timestamps_ns, dtype=np.int64))
        out._kf.append(anchors)
        out._kf_from_cam.append(np.broadcast_to(np.eye(4), (n, 4, 4)))
        poses = np.asarray(trajectory.world_from_cam, dtype=float)
        out._world_from_kf = {int(k): T for k, T in zip(anchors, poses, strict=True)}
        out._next_anchor = -1 - n
        return out

    def watch(self, watcher: PoseWatcher) -> None:
        """Tell ``watcher`` about every frame added or moved from now on."""
        self._watchers.append(watcher)

    def unwatch(self, watcher: PoseWatcher) -> None:
        """Stop telling ``watcher`` (no-op when it was not watching)."""
        if watcher in self._watchers:
            self._watchers.remove(watcher)

    # ------------------------------------------------------------------ reading
    @property
    def frame_count(self) -> int:
        return self._t.n

    @property
    def frame_times_ns(self) -> I64:
        """Frame times (read-only view, increasing)."""
        v = self._t.a.view()
        v.flags.writeable = False
        return v

    def frame_keyframes(self) -> I64:
        """Keyframe id of every frame (negative ids: self-anchored frames)."""
        return self._kf.a.copy()

    def has_keyframe(self, kf_id: int) -> bool:
        return int(kf_id) in self._world_from_kf

    @property
    def keyframe_poses(self) -> dict[int, F64]:
        """Current ``world_from_kf`` of every declared keyframe (copies; ids >= 0)."""
        return {k: T.copy() for k, T in self._world_from_kf.items() if k >= 0}

    def poses_of(self, frames: I64) -> F64:
        """``world_from_cam`` of these frames (N x 4 x 4)."""
        frames = np.asarray(frames, dtype=np.int64)
        kf = self._kf.a[frames]
        rel = self._kf_from_cam.a[frames]
        out = np.empty((frames.shape[0], 4, 4))
        for k in np.unique(kf):
            sel = kf == k
            out[sel] = np.einsum("ij,njk->nik", self._world_from_kf[int(k)], rel[sel])
        return out

    def frame_poses(self) -> F64:
        """``world_from_cam`` of every frame (N x 4 x 4)."""
        return self.poses_of(np.arange(self._t.n, dtype=np.int64))

    def trajectory(self) -> Trajectory:
        """Every frame's ``world_from_cam`` recomposed with the current keyframe poses."""
        return Trajectory(self._t.a.copy(), self.frame_poses())

    def bridged_trajectory(
        self, keyframe_times_ns: Mapping[int, int], tracked_links: Mapping[int, tuple[int, F64]]
    ) -> Trajectory:
        """Like :meth:`trajectory`, with each keyframe interval's tracking error taken out of its frames.

        ``tracked_links[B] = (A, A_from_B_tracked)``: keyframe B was made from a frame tracked
        against keyframe A at the tracker's pose ``A_from_B_tracked``; the estimated ``A_from_B``
        (current keyframe poses) disagrees with it by the interval's tracking error. The frames
        between A and B are corrected as that error would have moved them (:func:`bridge_interval`):
        first as a scale (depth) error, then the rest in proportion to the tracked path. Frames of a
        keyframe without a linked successor are recomposed as in :meth:`trajectory`.
        """
        base = self.trajectory()
        known = self._world_from_kf.keys() & keyframe_times_ns.keys()
        out = base.world_from_cam.copy()
        t, kf = self._t.a, self._kf.a
        for b, (a, a_from_b_tracked) in tracked_links.items():
            if a not in known or b not in known:
                continue
            t_a, t_b = keyframe_times_ns[int(a)], keyframe_times_ns[int(b)]
            frames = np.flatnonzero((kf == int(a)) & (t > t_a) & (t < t_b))
            if frames.size == 0:
                continue
            world_from_a = self._world_from_kf[int(a)]
            a_from_b = invert_pose(world_from_a) @ self._world_from_kf[int(b)]
            a_from_cam = bridge_interval(
                self._kf_from_cam.a[frames],
                (t[frames] - t_a) / (t_b - t_a),
                np.asarray(a_from_b_tracked, dtype=float).reshape(4, 4),
                a_from_b,
            )
            out[frames] = np.einsum("ij,njk->nik", world_from_a, a_from_cam)
        return Trajectory(base.timestamps_ns, out)

    # ------------------------------------------------------------------ changing
    def set_keyframe(self, kf_id: int, world_from_kf: ArrayLike) -> None:
        """Declare keyframe ``kf_id`` (>= 0) with its pose; a known keyframe is corrected instead."""
        if kf_id < 0:
            raise InputError(None, f"keyframe id must be >= 0, got {kf_id}")
        if int(kf_id) in self._world_from_kf:
            self.update_keyframes({int(kf_id): world_from_kf})
            return
        self._world_from_kf[int(kf_id)] = check_pose(world_from_kf, f"world_from_kf[{kf_id}]")

    def add_frame(
        self,
        timestamp_ns: int,
        world_from_cam: ArrayLike | None = None,
        *,
        kf_id: int | None = None,
        kf_from_cam: ArrayLike | None = None,
    ) -> int:
        """Add a tracked frame (times strictly increasing); returns its index.

        Give either ``world_from_cam`` (the frame anchors itself) or ``kf_id`` and ``kf_from_cam``
        (the keyframe must be set).
        """
        t = int(timestamp_ns)
        if self._t.n and t <= int(self._t.a[-1]):
            raise EstimationError(f"frames must arrive in time order: {t} ns after {int(self._t.a[-1])} ns")
        if kf_id is None:
            if world_from_cam is None:
                raise InputError(None, "add_frame needs world_from_cam or kf_id and kf_from_cam")
            anchor = self._next_anchor
            self._world_from_kf[anchor] = check_pose(world_from_cam, "world_from_cam")
            self._next_anchor -= 1
            rel = np.eye(4)
        else:
            if int(kf_id) not in self._world_from_kf:
                raise EstimationError(f"keyframe {kf_id} was not declared with set_keyframe")
            if kf_from_cam is None:
                raise InputError(None, "add_frame with kf_id needs kf_from_cam")
            anchor = int(kf_id)
            rel = check_pose(kf_from_cam, "kf_from_cam")
        self._t.append(np.array([t], dtype=np.int64))
        self._kf.append(np.array([anchor], dtype=np.int64))
        self._kf_from_cam.append(rel[None])
        for w in self._watchers:
            w.frames_added()
        return self._t.n - 1

    def update_keyframes(self, world_from_kf: Mapping[int, ArrayLike]) -> I64:
        """Correct keyframe poses; returns the indices of the frames that moved with them."""
        checked = {}
        for k, T in world_from_kf.items():
            if int(k) not in self._world_from_kf:
                raise EstimationError(f"keyframe {k} was not declared with set_keyframe")
            checked[int(k)] = check_pose(T, f"world_from_kf[{k}]")
        self._world_from_kf.update(checked)
        frames = np.flatnonzero(np.isin(self._kf.a, np.fromiter(checked, dtype=np.int64)))
        return self._moved(frames)

    def update_poses(self, trajectory: Trajectory, atol_m: float = 0.0) -> I64:
        """Replace frame poses by those of ``trajectory``; returns the indices of the changed frames.

        Frames are matched by exact timestamp; unmatched frames keep theirs. A frame changes when
        an element of its pose moves by more than ``atol_m``.
        """
        trajectory.check("update_poses trajectory")
        idx = np.searchsorted(trajectory.timestamps_ns, self._t.a)
        idx = np.clip(idx, 0, max(len(trajectory) - 1, 0))
        hit = trajectory.timestamps_ns[idx] == self._t.a if len(trajectory) else idx < 0
        frames = np.flatnonzero(hit)
        if frames.size == 0:
            return frames
        new = trajectory.world_from_cam[idx[frames]]
        changed = np.abs(new - self.poses_of(frames)).max(axis=(1, 2)) > atol_m
        frames = frames[changed]
        for f, T in zip(frames, new[changed], strict=True):
            self._kf_from_cam.a[f] = invert_pose(self._world_from_kf[int(self._kf.a[f])]) @ T
        return self._moved(frames)

    def _moved(self, frames: I64) -> I64:
        if frames.size:
            for w in self._watchers:
                w.frames_moved(frames)
        return frames


def bridge_interval(
    a_from_cam_tracked: F64,
    time_fraction: F64,
    a_from_b_tracked: F64,
    a_from_b: F64,
    min_chord_over_path: float = 0.5,
    max_scale_change: float = 0.1,
) -> F64:
    """The frames of one keyframe interval A -> B moved onto the estimated ``a_from_b`` (N x 4 x 4).

    ``a_from_cam_tracked``: the tracker's frame poses in keyframe A (metres, in time order);
    ``time_fraction``: (t - t_A) / (t_B - t_A) of each. The tracker measured the interval with the
    recorded calibration, so its translations carry that calibration's depth error, a scale about A.
    1. Scale: every tracked translation times ``s = |t_AB estimated| / |t_AB tracked|`` (frame and
       keyframe positions seen by the same biased stereo rig scale together; rotations do not).
       Only where the tracked path heads somewhere (chord >= ``min_chord_over_path`` of its length):
       on a path that turns back the chord does not measure the scale. Nor beyond
       ``max_scale_change`` (a calibration's depth error is a few tenths of a percent; the selfcal
       bench's links 0.2-0.5 %): a larger change is a tracking failure, not a scale.
    2. The remaining end correction grows with the motion, not with the clock: a frame gets the
       fraction of the tracked path (arc length of the positions A, frames, B; the rotation angle
       where the path has no length; the time fraction where neither moved) of it. The least-squares
       chain with noise per metre moved, both ends held at the estimated keyframes. The position
       residual ``t_AB - t_AB scaled`` is added in A's coordinates (the tracker measured every
       position against A's landmarks: their error is in A's frame; right-multiplied in each
       frame's coordinates it would turn with the camera, 20-30 deg per interval on an orbit); the
       rotation residual is right-multiplied in the frame's coordinates.
    """
    rel = np.array(a_from_cam_tracked, dtype=float).reshape(-1, 4, 4)
    end = np.array(a_from_b_tracked, dtype=float)
    chain = np.concatenate([np.eye(4)[None], rel, end[None]])
    step_m = np.linalg.norm(np.diff(chain[:, :3, 3], axis=0), axis=1)
    path_m = float(step_m.sum())
    chord_m = float(np.linalg.norm(end[:3, 3]))
    s = float(np.linalg.norm(a_from_b[:3, 3])) / chord_m if chord_m > 0.0 else 1.0
    if chord_m >= min_chord_over_path * path_m and abs(s - 1.0) <= max_scale_change:
        rel[:, :3, 3] *= s
        end[:3, 3] *= s
    step = step_m
    if path_m <= 1e-9:
        turns = [so3_log(p[:3, :3].T @ q[:3, :3]) for p, q in zip(chain[:-1], chain[1:], strict=True)]
        step = np.linalg.norm(turns, axis=1)
    total = float(step.sum())
    fraction = np.cumsum(step)[:-1] / total if total > 1e-12 else np.asarray(time_fraction, dtype=float)
    turn = so3_log(end[:3, :3].T @ a_from_b[:3, :3])
    shift_m = a_from_b[:3, 3] - end[:3, 3]
    out = rel.copy()
    for k, f in enumerate(fraction):
        out[k, :3, :3] = rel[k, :3, :3] @ so3_exp(f * turn)
        out[k, :3, 3] = rel[k, :3, 3] + f * shift_m
    return out
