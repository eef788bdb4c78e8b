"""Laser-stripe integration.

Profiles kept in the sensor frame, placed in the world with the pose interpolated on SE(3) at each
stripe's time, re-placed when frame poses change.

The frame poses live in an :class:`~loopmodel.mapping.anchored.AnchoredTrajectory` (keyframe-relative
bookkeeping); the map watches it. A stripe taken between frames ``f0`` and ``f1`` moves exactly when
one of those two frames moves (for instance with the keyframe it is anchored to).

Units: metres, nanoseconds. Frames: ``points_in_cam`` in the left-camera frame (x right,
y down, z forward), world points in the run's world frame.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import MappingConfig
from loopmodel.errors import InputError
from loopmodel.geometry.se3 import interpolate_poses
from loopmodel.mapping.anchored import AnchoredTrajectory, Rows
from loopmodel.types import StripeProfile, Trajectory

if TYPE_CHECKING:
    import open3d as o3d

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class StripeMap:
    """Stripes in the sensor frame, placed in the world by the frame poses of an anchored trajectory.

    Typical live use (pipeline): the run's :class:`AnchoredTrajectory` gets every tracked frame
    and every keyframe correction; the map, built on it, places each stripe (``add``) once frames
    bracket its time and re-places it when those frames move; ``mesh`` / ``update_live_mesh`` give
    surfaces. Offline: ``from_trajectory``.
    """

    def __init__(
        self,
        config: MappingConfig | None = None,
        poses: AnchoredTrajectory | None = None,
        place_when_read: bool = False,
    ) -> None:
        self.config = config or MappingConfig()
        #: new stripes placed when the map is next read, in one batch, not as they and their frames come
        self.place_when_read = place_when_read
        #: the frame poses the stripes are placed with (the map follows its changes)
        self.poses = poses if poses is not None else AnchoredTrajectory()
        self.poses.watch(self)
        # stripes
        self._s_t = Rows((), np.int64)
        self._s_start = Rows((), np.int64)
        self._s_count = Rows((), np.int64)
        self._s_f0 = Rows((), np.int64)  # -1 while not placed
        self._s_f1 = Rows((), np.int64)
        self._s_alpha = Rows((), np.float64)
        self._s_world_from_cam = Rows((4, 4), np.float64)
        # points
        self._p_cam = Rows((3,), np.float64)
        self._p_world = Rows((3,), np.float64)
        self._p_stripe = Rows((), np.int64)
        self._pending: list[int] = []
        self._moved: list[I64] = []  # frames moved since their stripes were last re-placed (see frames_moved)
        # live mesh state
        self._dirty: set[tuple[int, int, int]] = set()
        self._blocks: dict[tuple[int, int, int], o3d.geometry.TriangleMesh] = {}
        self._live = False  # dirty-block tracking starts with the first live mesh

    # ------------------------------------------------------------- pose events
    def frames_added(self) -> None:
        """Place the waiting stripes that the new frames bracket (with :attr:`place_when_read`: when next read)."""
        if self._pending and not self.place_when_read:
            self._place_pending()

    def frames_moved(self, frames: I64) -> None:
        """Re-place the stripes next to these frames, when the map's world points are next read.

        finish9 (issue 32): the corrections come on the tracking thread and the live mesh reads the
        points every few keyframes; re-placed at once, the 300-frame realistic orbit's 36 corrections
        cost up to 51 ms of a frame (p95 19 ms). Stripes placed later take the poses of then.
        """
        if frames.size and self._s_t.n:
            self._moved.append(np.array(frames, dtype=np.int64))
            if len(self._moved) > 64:  # a long run between reads: one array
                self._moved = [np.unique(np.concatenate(self._moved))]

    def _settle(self) -> None:
        """Before a read: the moves since the last one applied, then the waiting stripes placed."""
        self._apply_moves()
        if self._pending and self.place_when_read:
            self._place_pending()

    def _apply_moves(self) -> None:
        """Re-place the stripes of the frames moved since the last read (their net move: dirty blocks)."""
        if self._moved:
            frames = np.unique(np.concatenate(self._moved))
            self._moved = []
            self._retransform(self.stripes_of_frames(frames))

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
        self._settle()
        return self._placed()

    def _placed(self) -> NDArray[np.bool_]:
        return self._s_f0.a >= 0

    def add(self, stripe: StripeProfile) -> int:
        """Add a profile (times need not be ordered).

        It is placed in the world as soon as frames bracket its time; returns the stripe index.
        """
        self.add_many([stripe])
        return self._s_t.n - 1

    def add_many(self, stripes: Iterable[StripeProfile]) -> None:
        """Add several profiles (placement is batched; a bad one raises after those before it are added)."""
        times: list[int] = []
        arrays: list[F64] = []
        try:
            for st in stripes:
                pts = np.asarray(st.points_in_cam, dtype=float)
                if pts.ndim != 2 or pts.shape[1] != 3:
                    raise InputError(None, f"stripe at {st.timestamp_ns} ns: points must be N x 3, got {pts.shape}")
                if pts.shape[0] == 0:
                    raise InputError(None, f"stripe at {st.timestamp_ns} ns has no points")
                if not np.all(np.isfinite(pts)):
                    raise InputError(None, f"stripe at {st.timestamp_ns} ns has non-finite points")
                times.append(int(st.timestamp_ns))
                arrays.append(pts)
        finally:
            self._append_stripes(times, arrays)
            if not self.place_when_read:
                self._place_pending()

    def _append_stripes(self, times: list[int], arrays: list[F64]) -> None:
        """The rows of these stripes and their points, appended at once (live19: one append a column, not a stripe)."""
        n = len(arrays)
        if n == 0:
            return
        s0 = self._s_t.n
        counts = np.fromiter((a.shape[0] for a in arrays), dtype=np.int64, count=n)
        pts = np.concatenate(arrays)
        a, _ = self._p_cam.append(pts)
        self._p_world.append(np.full_like(pts, np.nan))
        self._p_stripe.append(np.repeat(np.arange(s0, s0 + n, dtype=np.int64), counts))
        self._s_t.append(np.asarray(times, dtype=np.int64))
        self._s_start.append(a + np.cumsum(counts) - counts)
        self._s_count.append(counts)
        self._s_f0.append(np.full(n, -1, dtype=np.int64))
        self._s_f1.append(np.full(n, -1, dtype=np.int64))
        self._s_alpha.append(np.zeros(n))
        self._s_world_from_cam.append(np.full((n, 4, 4), np.nan))
        self._pending.extend(range(s0, s0 + n))

    def stripes(self) -> list[StripeProfile]:
        """All profiles as given (sensor frame), in insertion order."""
        out = []
        for t, a, n in zip(self._s_t.a, self._s_start.a, self._s_count.a, strict=True):
            out.append(StripeProfile(int(t), self._p_cam.a[a : a + n].copy()))
        return out

    def stripes_governed_by(self, kf_ids: Iterable[int]) -> I64:
        """Indices of placed stripes whose neighbouring frames belong to these keyframes."""
        self._settle()
        ids = np.fromiter((int(k) for k in kf_ids), dtype=np.int64)
        return self.stripes_of_frames(np.flatnonzero(np.isin(self.poses.frame_keyframes(), ids)))

    def stripes_of_frames(self, frames: I64) -> I64:
        """Indices of placed stripes next to (bracketed by) any of these frames."""
        placed = self._placed()
        hit = placed & (np.isin(self._s_f0.a, frames) | np.isin(self._s_f1.a, frames))
        return np.flatnonzero(hit)

    def stripe_poses(self) -> F64:
        """``world_from_cam`` at every stripe's time (S x 4 x 4; NaN while unplaced)."""
        self._settle()
        return self._s_world_from_cam.a.copy()

    def world_points(self, stripe: int | None = None) -> F64:
        """World points (metres) of one stripe, or of all placed stripes (P x 3)."""
        self._settle()
        if stripe is not None:
            a, n = int(self._s_start.a[stripe]), int(self._s_count.a[stripe])
            return self._p_world.a[a : a + n].copy()
        return self._p_world.a[self._point_placed_mask()].copy()

    def sensor_positions(self) -> F64:
        """Camera centre (world, metres) at the capture time of each placed point (P x 3)."""
        self._settle()
        centres = self._s_world_from_cam.a[:, :3, 3]
        return centres[self._p_stripe.a[self._point_placed_mask()]]

    def _point_placed_mask(self) -> NDArray[np.bool_]:
        return self._placed()[self._p_stripe.a]

    def _place_pending(self) -> None:
        nf = self.poses.frame_count
        if not self._pending or nf == 0:
            return
        pend = np.asarray(self._pending, dtype=np.int64)
        ts = self._s_t.a[pend]
        ft = self.poses.frame_times_ns
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
        poses = self.poses.poses_of(frames)  # world_from_cam of these frames
        i0, i1 = np.searchsorted(frames, f0), np.searchsorted(frames, f1)
        T = interpolate_poses(poses[i0], poses[i1], self._s_alpha.a[stripes])
        pw = self._p_world.a
        pc = self._p_cam.a
        starts, counts = self._s_start.a[stripes], self._s_count.a[stripes]
        self._s_world_from_cam.a[stripes] = T
        has = counts > 0
        if not has.any():
            return stripes
        starts, counts, T = starts[has], counts[has], T[has]
        # every point of these stripes at once (issue 33: a loop over stripes cost up to 235 ms of a
        # frame on the tracking thread when a correction moved a few hundred of them)
        first = np.cumsum(counts) - counts
        owner = np.repeat(np.arange(counts.size), counts)
        idx = np.repeat(starts, counts) + (np.arange(owner.size) - first[owner])
        new = np.einsum("pij,pj->pi", T[:, :3, :3][owner], pc[idx]) + T[:, :3, 3][owner]
        if self._live:
            # the live mesh only re-meshes where a stripe moved by a quarter voxel or more; live20: the
            # reductions over a point's 3 coordinates column by column (numpy's reduce along a row of 3
            # took 6.5 ms for 25,000 not yet placed points, 0.02 ms so; 23 ms turns on the tracking thread)
            tol_m = 0.25 * self.config.voxel_m
            old = pw[idx]
            known = np.isfinite(old[:, 0]) & np.isfinite(old[:, 1]) & np.isfinite(old[:, 2])
            finite = np.logical_and.reduceat(known, first)
            with np.errstate(invalid="ignore"):
                d = np.abs(new - old)
                moved = np.maximum.reduceat(np.maximum(np.maximum(d[:, 0], d[:, 1]), d[:, 2]), first) >= tol_m
            fresh, both = ~finite[owner], (finite & moved)[owner]
            self._mark_dirty(np.concatenate([new[fresh | both], old[both]]))
        pw[idx] = new
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
        m = cls(config, AnchoredTrajectory.from_trajectory(trajectory))
        m.add_many(s for s in stripes if np.asarray(s.points_in_cam).size)
        return m

    # ------------------------------------------------------------------ meshes
    def _mark_dirty(self, pts: F64) -> None:
        if pts.size == 0:
            return
        keys = np.floor(pts / self.config.chunk_m).astype(np.int64)
        # one int64 per block (21 bits a coordinate): a 1-D unique, 1.3 vs 6.8 ms for 3,000 points
        # on the tracking thread (issue 33); blocks beyond +-2^20 chunks fall back to the 2-D unique
        if np.abs(keys).max() < (1 << 20):
            off = keys + (1 << 20)
            code = np.unique((off[:, 0] << 42) | (off[:, 1] << 21) | off[:, 2])
            mask = (1 << 21) - 1
            keys = np.column_stack([code >> 42, (code >> 21) & mask, code & mask]) - (1 << 20)
        else:
            keys = np.unique(keys, axis=0)
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
        self._settle()
        if not self._live:
            self._live = True
            self._mark_dirty(self._p_world.a[self._point_placed_mask()])
        if not self._dirty:
            return None
        mask = self._point_placed_mask()
        pts = self._p_world.a[mask]  # (a copy: indexed by a mask)
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
        self._settle()
        return set(self._dirty)

    def check_nonempty(self) -> None:
        """Raise :class:`InputError` when nothing can be meshed."""
        if self._s_t.n == 0:
            raise InputError(None, "no laser stripes")
        if not np.any(self.placed_mask):
            raise InputError(None, "no laser stripe lies within the tracked frames' times")
