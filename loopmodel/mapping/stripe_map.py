"""Laser-stripe integration.

Profiles kept in the sensor frame, placed in the world with the pose interpolated on SE(3) at each
stripe's time, re-placed when the backend corrects poses.

Pose bookkeeping is keyframe-relative: every frame pose is
``world_from_cam = world_from_kf[kf] @ kf_from_cam``. A stripe taken between frames ``f0`` and
``f1`` is governed by the keyframes of those two frames; correcting a keyframe re-transforms
exactly the stripes it governs. A frame given only as ``world_from_cam`` anchors itself (its
own pseudo-keyframe), so an offline trajectory works the same way.

Units: metres, nanoseconds. Frames: ``points_in_cam`` in the left-camera frame (x right,
y down, z forward), world points in the run's world frame.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from loopmodel.config import MappingConfig
from loopmodel.errors import EstimationError, InputError
from loopmodel.geometry.se3 import interpolate_poses, invert_pose, is_rotation
from loopmodel.types import StripeProfile, Trajectory

if TYPE_CHECKING:
    import open3d as o3d

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class _Rows:
    """Growable array of rows (amortised O(1) append)."""

    def __init__(self, shape: tuple[int, ...], dtype: type | np.dtype) -> None:  # type: ignore[type-arg]
        self._buf = np.zeros((16, *shape), dtype=dtype)
        self.n = 0

    def append(self, rows: NDArray) -> tuple[int, int]:  # type: ignore[type-arg]
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


def _check_pose(T: ArrayLike, what: str) -> F64:
    M = np.asarray(T, dtype=float)
    if M.shape != (4, 4) or not np.all(np.isfinite(M)) or not is_rotation(M[:3, :3], 1e-5):
        raise InputError(None, f"{what} must be a finite 4x4 rigid transform")
    return M


class StripeMap:
    """Stripes in the sensor frame plus the poses that place them in the world.

    Typical live use (pipeline): ``add_frame`` for every tracked frame (relative to its
    keyframe), ``add`` for every stripe, ``update_keyframes`` after the backend corrects
    keyframes, ``mesh`` / ``update_live_mesh`` for surfaces. Offline: ``from_trajectory``.
    """

    def __init__(self, config: MappingConfig | None = None) -> None:
        self.config = config or MappingConfig()
        self._world_from_kf: dict[int, F64] = {}
        self._frame_t = _Rows((), np.int64)
        self._frame_kf = _Rows((), np.int64)
        self._frame_kf_from_cam = _Rows((4, 4), np.float64)
        self._next_anchor = -1  # pseudo-keyframe ids of self-anchored frames are negative
        # stripes
        self._s_t = _Rows((), np.int64)
        self._s_start = _Rows((), np.int64)
        self._s_count = _Rows((), np.int64)
        self._s_f0 = _Rows((), np.int64)  # -1 while not placed
        self._s_f1 = _Rows((), np.int64)
        self._s_alpha = _Rows((), np.float64)
        self._s_world_from_cam = _Rows((4, 4), np.float64)
        # points
        self._p_cam = _Rows((3,), np.float64)
        self._p_world = _Rows((3,), np.float64)
        self._p_stripe = _Rows((), np.int64)
        self._pending: list[int] = []
        # live mesh state
        self._dirty: set[tuple[int, int, int]] = set()
        self._blocks: dict[tuple[int, int, int], o3d.geometry.TriangleMesh] = {}
        self._live = False  # dirty-block tracking starts with the first live mesh

    # ------------------------------------------------------------------ poses
    @property
    def frame_count(self) -> int:
        return self._frame_t.n

    @property
    def frame_times_ns(self) -> I64:
        return self._frame_t.a.copy()

    def frame_keyframes(self) -> I64:
        """Keyframe id of every frame (negative ids: self-anchored frames)."""
        return self._frame_kf.a.copy()

    def set_keyframe(self, kf_id: int, world_from_kf: ArrayLike) -> None:
        """Declare keyframe ``kf_id`` (>= 0) with its pose.

        Setting a known keyframe again corrects it like :meth:`update_keyframes` (its stripes are
        re-transformed).
        """
        if kf_id < 0:
            raise InputError(None, f"keyframe id must be >= 0, got {kf_id}")
        if int(kf_id) in self._world_from_kf:
            self.update_keyframes({int(kf_id): world_from_kf})
            return
        self._world_from_kf[int(kf_id)] = _check_pose(world_from_kf, f"world_from_kf[{kf_id}]")

    def add_frame(
        self,
        timestamp_ns: int,
        world_from_cam: ArrayLike | None = None,
        *,
        kf_id: int | None = None,
        kf_from_cam: ArrayLike | None = None,
    ) -> int:
        """Add a tracked frame (times strictly increasing).

        Give either ``world_from_cam`` (the frame anchors itself) or ``kf_id`` and ``kf_from_cam``
        (the keyframe must be set). Places every waiting stripe the new frame brackets; returns the
        frame index.
        """
        t = int(timestamp_ns)
        if self._frame_t.n and t <= int(self._frame_t.a[-1]):
            raise EstimationError(f"frames must arrive in time order: {t} ns after {int(self._frame_t.a[-1])} ns")
        if kf_id is None:
            if world_from_cam is None:
                raise InputError(None, "add_frame needs world_from_cam or kf_id and kf_from_cam")
            anchor = self._next_anchor
            self._next_anchor -= 1
            self._world_from_kf[anchor] = _check_pose(world_from_cam, "world_from_cam")
            rel = np.eye(4)
        else:
            if int(kf_id) not in self._world_from_kf:
                raise EstimationError(f"keyframe {kf_id} was not declared with set_keyframe")
            if kf_from_cam is None:
                raise InputError(None, "add_frame with kf_id needs kf_from_cam")
            anchor = int(kf_id)
            rel = _check_pose(kf_from_cam, "kf_from_cam")
        self._frame_t.append(np.array([t], dtype=np.int64))
        self._frame_kf.append(np.array([anchor], dtype=np.int64))
        self._frame_kf_from_cam.append(rel[None])
        if self._pending:
            self._place_pending()
        return self._frame_t.n - 1

    def frame_poses(self) -> F64:
        """``world_from_cam`` of every frame (N x 4 x 4)."""
        kf = self._frame_kf.a
        out = np.empty((kf.shape[0], 4, 4))
        if kf.shape[0] == 0:
            return out
        for k in np.unique(kf):
            sel = kf == k
            out[sel] = np.einsum("ij,njk->nik", self._world_from_kf[int(k)], self._frame_kf_from_cam.a[sel])
        return out

    def trajectory(self) -> Trajectory:
        """Every frame's ``world_from_cam`` recomposed with the current keyframe poses."""
        return Trajectory(self._frame_t.a.copy(), self.frame_poses())

    def bridged_trajectory(
        self, keyframe_times_ns: Mapping[int, int], tracked_links: Mapping[int, tuple[int, F64]]
    ) -> Trajectory:
        """Like :meth:`trajectory`, with each keyframe interval's tracking drift spread over its frames.

        ``tracked_links[B] = (A, A_from_B_tracked)``: keyframe B was made from a frame tracked
        against keyframe A at the tracker's pose ``A_from_B_tracked``; the estimated ``A_from_B``
        (current keyframe poses) disagrees with it by the interval's drift. The least-squares chain
        with equal noise per step and both ends held at the estimated keyframes gives a frame at
        time t the fraction ``(t - t_A) / (t_B - t_A)`` of the end correction (on SE(3),
        right-multiplied in the frame's coordinates). Frames of a keyframe without a linked
        successor are recomposed as in :meth:`trajectory`.
        """
        from loopmodel.geometry.se3 import se3_exp, se3_log

        base = self.trajectory()
        known = self._world_from_kf.keys() & keyframe_times_ns.keys()
        successor = {
            int(a): (int(b), np.asarray(rel, dtype=float).reshape(4, 4))
            for b, (a, rel) in tracked_links.items()
            if a in known and b in known
        }
        out = base.world_from_cam.copy()
        correction: dict[int, F64] = {}
        for i, (t, k) in enumerate(zip(self._frame_t.a, self._frame_kf.a, strict=True)):
            nxt = successor.get(int(k))
            if nxt is None:
                continue
            b, a_from_b_tracked = nxt
            t_a, t_b = keyframe_times_ns[int(k)], keyframe_times_ns[b]
            if not t_a < t < t_b:
                continue
            if k not in correction:
                a_from_b = invert_pose(self._world_from_kf[int(k)]) @ self._world_from_kf[b]
                correction[int(k)] = se3_log(invert_pose(a_from_b_tracked) @ a_from_b)
            out[i] = out[i] @ se3_exp((t - t_a) / (t_b - t_a) * correction[int(k)])
        return Trajectory(base.timestamps_ns, out)

    @property
    def keyframe_poses(self) -> dict[int, F64]:
        """Current ``world_from_kf`` of every declared keyframe (copies; ids >= 0)."""
        return {k: T.copy() for k, T in self._world_from_kf.items() if k >= 0}

    def update_keyframes(self, world_from_kf: Mapping[int, ArrayLike]) -> I64:
        """Correct keyframe poses.

        Re-transforms only the stripes these keyframes govern. Returns the indices of the
        re-transformed stripes.
        """
        ids = []
        for k, T in world_from_kf.items():
            if int(k) not in self._world_from_kf:
                raise EstimationError(f"keyframe {k} was not declared with set_keyframe")
            self._world_from_kf[int(k)] = _check_pose(T, f"world_from_kf[{k}]")
            ids.append(int(k))
        return self._retransform(self.stripes_governed_by(ids))

    def update_poses(self, trajectory: Trajectory, atol_m: float = 0.0) -> I64:
        """Replace frame poses by those of ``trajectory`` and re-transform the stripes of the changed frames.

        Frames are matched by exact timestamp; unmatched frames keep theirs.
        """
        trajectory.check("update_poses trajectory")
        idx = np.searchsorted(trajectory.timestamps_ns, self._frame_t.a)
        idx = np.clip(idx, 0, max(len(trajectory) - 1, 0))
        hit = trajectory.timestamps_ns[idx] == self._frame_t.a if len(trajectory) else idx < 0
        frames = np.flatnonzero(hit)
        if frames.size == 0:
            return np.zeros(0, dtype=np.int64)
        old = self.frame_poses()[frames]
        new = trajectory.world_from_cam[idx[frames]]
        changed = np.abs(new - old).max(axis=(1, 2)) > atol_m
        frames = frames[changed]
        kfs = self._frame_kf.a[frames]
        for f, k, T in zip(frames, kfs, new[changed], strict=True):
            self._frame_kf_from_cam.a[f] = invert_pose(self._world_from_kf[int(k)]) @ T
        if frames.size == 0:
            return np.zeros(0, dtype=np.int64)
        return self._retransform(self._stripes_of_frames(frames))

    # ---------------------------------------------------------------- stripes
    @property
    def stripe_count(self) -> int:
        return self._s_t.n

    @property
    def point_count(self) -> int:
        return self._p_cam.n

    @property
    def placed_mask(self) -> NDArray[np.bool_]:
        """Which stripes have a pose (bracketed by frames)."""
        return self._s_f0.a >= 0

    def add(self, stripe: StripeProfile) -> int:
        """Add a profile (times need not be ordered).

        It is placed in the world as soon as frames bracket its time; returns the stripe index.
        """
        self.add_many([stripe])
        return self._s_t.n - 1

    def add_many(self, stripes: Iterable[StripeProfile]) -> None:
        """Add several profiles (placement is batched)."""
        pend_before = self._pending
        self._pending = []
        try:
            for st in stripes:
                pts = np.asarray(st.points_in_cam, dtype=float)
                if pts.ndim != 2 or pts.shape[1] != 3:
                    raise InputError(None, f"stripe at {st.timestamp_ns} ns: points must be N x 3, got {pts.shape}")
                if pts.shape[0] == 0:
                    raise InputError(None, f"stripe at {st.timestamp_ns} ns has no points")
                if not np.all(np.isfinite(pts)):
                    raise InputError(None, f"stripe at {st.timestamp_ns} ns has non-finite points")
                s = self._s_t.n
                self._s_t.append(np.array([int(st.timestamp_ns)], dtype=np.int64))
                a, _ = self._p_cam.append(pts)
                self._p_world.append(np.full_like(pts, np.nan))
                self._p_stripe.append(np.full(pts.shape[0], s, dtype=np.int64))
                self._s_start.append(np.array([a], dtype=np.int64))
                self._s_count.append(np.array([pts.shape[0]], dtype=np.int64))
                self._s_f0.append(np.array([-1], dtype=np.int64))
                self._s_f1.append(np.array([-1], dtype=np.int64))
                self._s_alpha.append(np.zeros(1))
                self._s_world_from_cam.append(np.full((1, 4, 4), np.nan))
                pend_before.append(s)
        finally:
            self._pending = pend_before
            self._place_pending()

    def stripes(self) -> list[StripeProfile]:
        """All profiles as given (sensor frame), in insertion order."""
        out = []
        for t, a, n in zip(self._s_t.a, self._s_start.a, self._s_count.a, strict=True):
            out.append(StripeProfile(int(t), self._p_cam.a[a : a + n].copy()))
        return out

    def stripes_governed_by(self, kf_ids: Iterable[int]) -> I64:
        """Indices of placed stripes whose neighbouring frames belong to these keyframes."""
        ids = np.fromiter((int(k) for k in kf_ids), dtype=np.int64)
        placed = self.placed_mask
        f0 = np.where(placed, self._s_f0.a, 0)
        f1 = np.where(placed, self._s_f1.a, 0)
        if self._frame_kf.n == 0:
            return np.zeros(0, dtype=np.int64)
        kf = self._frame_kf.a
        hit = placed & (np.isin(kf[f0], ids) | np.isin(kf[f1], ids))
        return np.flatnonzero(hit)

    def _stripes_of_frames(self, frames: NDArray[np.int64]) -> I64:
        placed = self.placed_mask
        hit = placed & (np.isin(self._s_f0.a, frames) | np.isin(self._s_f1.a, frames))
        return np.flatnonzero(hit)

    def stripe_poses(self) -> F64:
        """``world_from_cam`` at every stripe's time (S x 4 x 4; NaN while unplaced)."""
        return self._s_world_from_cam.a.copy()

    def world_points(self, stripe: int | None = None) -> F64:
        """World points (metres) of one stripe, or of all placed stripes (P x 3)."""
        if stripe is not None:
            a, n = int(self._s_start.a[stripe]), int(self._s_count.a[stripe])
            return self._p_world.a[a : a + n].copy()
        return self._p_world.a[self._point_placed_mask()].copy()

    def sensor_positions(self) -> F64:
        """Camera centre (world, metres) at the capture time of each placed point (P x 3)."""
        centres = self._s_world_from_cam.a[:, :3, 3]
        return centres[self._p_stripe.a[self._point_placed_mask()]]

    def _point_placed_mask(self) -> NDArray[np.bool_]:
        return self.placed_mask[self._p_stripe.a]

    def _place_pending(self) -> None:
        nf = self._frame_t.n
        if not self._pending or nf == 0:
            return
        pend = np.asarray(self._pending, dtype=np.int64)
        ts = self._s_t.a[pend]
        ft = self._frame_t.a
        i1 = np.searchsorted(ft, ts, side="left")  # first frame with t >= ts
        exact = (i1 < nf) & (ft[np.minimum(i1, nf - 1)] == ts)
        inside = (i1 > 0) & (i1 < nf)
        ok = exact | inside
        f1 = np.where(exact, i1, np.minimum(i1, nf - 1))
        f0 = np.where(exact, i1, np.maximum(i1 - 1, 0))
        gap = ft[f1] - ft[f0]
        too_wide = ok & ~exact & (gap > self.config.max_stripe_gap_ns)
        before = (i1 == 0) & ~exact
        ok &= ~too_wide
        # waiting: stripes after the last frame (a later frame may bracket them)
        keep = [int(s) for s, w in zip(pend, ~ok & ~too_wide & ~before, strict=True) if w]
        dropped = int(np.count_nonzero(too_wide | before))
        if dropped:
            logger.warning("%d stripe(s) outside the tracked frames or in a gap; not placed", dropped)
        self._pending = keep
        if np.any(ok):
            sel = pend[ok]
            a0 = np.where(exact[ok], 0.0, (ts[ok] - ft[f0[ok]]) / np.maximum(gap[ok], 1))
            self._s_f0.a[sel] = f0[ok]
            self._s_f1.a[sel] = f1[ok]
            self._s_alpha.a[sel] = a0
            self._retransform(sel)

    def _retransform(self, stripes: NDArray[np.int64]) -> I64:
        """Recompute the pose and world points of these (placed) stripes."""
        stripes = np.asarray(stripes, dtype=np.int64)
        if stripes.size == 0:
            return stripes
        f0, f1 = self._s_f0.a[stripes], self._s_f1.a[stripes]
        frames = np.unique(np.concatenate([f0, f1]))
        poses = np.empty((frames.shape[0], 4, 4))  # world_from_cam of these frames
        kf = self._frame_kf.a[frames]
        rel = self._frame_kf_from_cam.a[frames]
        for k in np.unique(kf):
            sel = kf == k
            poses[sel] = np.einsum("ij,njk->nik", self._world_from_kf[int(k)], rel[sel])
        i0, i1 = np.searchsorted(frames, f0), np.searchsorted(frames, f1)
        T = interpolate_poses(poses[i0], poses[i1], self._s_alpha.a[stripes])
        live = self._live
        pw = self._p_world.a
        pc = self._p_cam.a
        starts, counts = self._s_start.a[stripes], self._s_count.a[stripes]
        # the live mesh only re-meshes where a stripe moved by a quarter voxel or more
        tol_m = 0.25 * self.config.voxel_m
        for s, a, n, M in zip(stripes, starts, counts, T, strict=True):
            b = a + n
            new = pc[a:b] @ M[:3, :3].T + M[:3, 3]
            if live:
                old = pw[a:b]
                if not np.isfinite(old).all():
                    self._mark_dirty(new)
                elif np.abs(new - old).max() >= tol_m:
                    self._mark_dirty(old)
                    self._mark_dirty(new)
            pw[a:b] = new
            self._s_world_from_cam.a[s] = M
        return stripes

    @classmethod
    def from_trajectory(
        cls,
        trajectory: Trajectory,
        stripes: Iterable[StripeProfile],
        config: MappingConfig | None = None,
    ) -> StripeMap:
        """Offline map.

        Every trajectory pose anchors its own frame; profiles without points (the laser hit nothing)
        are skipped.
        """
        trajectory.check("trajectory")
        m = cls(config)
        for t, T in zip(trajectory.timestamps_ns, trajectory.world_from_cam, strict=True):
            m._frame_t.append(np.array([int(t)], dtype=np.int64))
            m._frame_kf.append(np.array([m._next_anchor], dtype=np.int64))
            m._frame_kf_from_cam.append(np.eye(4)[None])
            m._world_from_kf[m._next_anchor] = T
            m._next_anchor -= 1
        m.add_many(s for s in stripes if np.asarray(s.points_in_cam).size)
        return m

    # ------------------------------------------------------------------ meshes
    def _mark_dirty(self, pts: F64) -> None:
        if pts.size == 0:
            return
        keys = np.unique(np.floor(pts / self.config.chunk_m).astype(np.int64), axis=0)
        self._dirty.update(map(tuple, keys.tolist()))

    def mesh(self) -> o3d.geometry.TriangleMesh:
        """Surface of all placed stripes, reconstructed in one piece (config method)."""
        from loopmodel.mapping.meshing import mesh_from_points

        if self.placed_mask.sum() == 0:
            raise InputError(None, "no placed laser stripes to mesh")
        return mesh_from_points(self.world_points(), self.sensor_positions(), self.config)

    def update_live_mesh(self) -> o3d.geometry.TriangleMesh:
        """Chunked live mesh.

        Re-mesh only the blocks (``chunk_m``) touched by stripes added or moved since the last call
        (one reconstruction for all of them, at ``live_voxel_m``), and return the union of all block
        meshes.
        """
        from loopmodel.mapping.meshing import live_mesh_config, mesh_blocks

        snap = self.take_dirty_blocks()
        if snap is not None:
            self.install_blocks(mesh_blocks(*snap, live_mesh_config(self.config)))
        return self.live_mesh()

    def take_dirty_blocks(self) -> tuple[F64, F64, set[tuple[int, int, int]]] | None:
        """Copies of the placed world points and their sensor positions, and the dirty blocks.

        The dirty blocks are then marked clean. The input of
        :func:`~loopmodel.mapping.meshing.mesh_blocks`, which may run in another thread. None when
        no block is dirty.
        """
        if not self._live:
            self._live = True
            self._mark_dirty(self._p_world.a[self._point_placed_mask()])
        if not self._dirty:
            return None
        mask = self._point_placed_mask()
        pts = self._p_world.a[mask].copy()
        sensors = self._s_world_from_cam.a[:, :3, 3][self._p_stripe.a[mask]]
        dirty, self._dirty = self._dirty, set()
        return pts, sensors, dirty

    def install_blocks(self, blocks: Mapping[tuple[int, int, int], o3d.geometry.TriangleMesh | None]) -> None:
        """Replace the live meshes of these blocks (None removes a block)."""
        for key, m in blocks.items():
            if m is None:
                self._blocks.pop(key, None)
            else:
                self._blocks[key] = m

    def live_mesh(self) -> o3d.geometry.TriangleMesh:
        """Union of the current block meshes (no re-meshing)."""
        import open3d as o3d

        out = o3d.geometry.TriangleMesh()
        for key in sorted(self._blocks):
            out += self._blocks[key]
        return out

    @property
    def dirty_blocks(self) -> set[tuple[int, int, int]]:
        """Blocks whose live mesh is out of date."""
        return set(self._dirty)

    def check_nonempty(self) -> None:
        """Raise :class:`InputError` when nothing can be meshed."""
        if self._s_t.n == 0:
            raise InputError(None, "no laser stripes")
        if not np.any(self.placed_mask):
            raise InputError(None, "no laser stripe lies within the tracked frames' times")
