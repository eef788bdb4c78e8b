"""Frame poses anchored to keyframes (:class:`AnchoredTrajectory`) follow keyframe corrections."""

from __future__ import annotations

import numpy as np
import pytest

from loopmodel.errors import EstimationError
from loopmodel.geometry.se3 import make_pose, so3_exp
from loopmodel.mapping.anchored import AnchoredTrajectory


def test_recomposes_with_moved_keyframes(rng):
    traj = AnchoredTrajectory()
    kf0 = make_pose(so3_exp([0, 0.1, 0]), [1, 2, 3])
    kf1 = make_pose(so3_exp([0.05, 0, 0]), [2, 2, 3])
    traj.set_keyframe(0, kf0)
    traj.set_keyframe(1, kf1)
    rel = [make_pose(so3_exp(rng.normal(0, 0.1, 3)), rng.normal(0, 0.5, 3)) for _ in range(4)]
    for i, (k, r) in enumerate(zip([0, 0, 1, 1], rel, strict=True)):
        traj.add_frame(i * 10, kf_id=k, kf_from_cam=r)
    t = traj.trajectory()
    assert np.allclose(t.world_from_cam[1], kf0 @ rel[1])
    assert np.allclose(t.world_from_cam[3], kf1 @ rel[3])
    # move keyframe 1: its frames move rigidly with it, keyframe 0's frames stay
    new1 = make_pose(so3_exp([0, 0, 0.2]), [2.5, 1.5, 3.2])
    traj.update_keyframes({1: new1})
    t2 = traj.trajectory()
    assert np.allclose(t2.world_from_cam[:2], t.world_from_cam[:2])
    assert np.allclose(t2.world_from_cam[2], new1 @ rel[2])
    assert np.array_equal(t2.timestamps_ns, [0, 10, 20, 30])
    assert set(traj.keyframe_poses) == {0, 1} and np.allclose(traj.keyframe_poses[1], new1)


def test_unknown_keyframe_is_an_error():
    traj = AnchoredTrajectory()
    with pytest.raises(EstimationError, match="keyframe 3 was not declared"):
        traj.add_frame(0, kf_id=3, kf_from_cam=np.eye(4))
    assert len(traj.trajectory()) == 0


def test_a_map_that_stops_watching_keeps_its_points():
    """finish9: the finish unhooks the live stripe map; the trajectory still takes the corrections."""
    from loopmodel.mapping.stripe_map import StripeMap
    from loopmodel.types import StripeProfile

    traj = AnchoredTrajectory()
    traj.set_keyframe(0, np.eye(4))
    for i in range(3):
        traj.add_frame(i * 10, kf_id=0, kf_from_cam=make_pose(np.eye(3), [0.01 * i, 0, 0]))
    smap = StripeMap(poses=traj)
    smap.add(StripeProfile(15, np.array([[0.0, 0.0, 0.5], [0.01, 0.0, 0.5]])))
    before = smap.world_points()
    moved = make_pose(np.eye(3), [0.1, 0, 0])
    traj.update_keyframes({0: moved})
    np.testing.assert_allclose(smap.world_points(), before + [0.1, 0, 0])  # following
    traj.unwatch(smap)
    traj.update_keyframes({0: np.eye(4)})
    np.testing.assert_allclose(smap.world_points(), before + [0.1, 0, 0])  # no longer following
    assert np.allclose(traj.keyframe_poses[0], np.eye(4))
    traj.unwatch(smap)  # a second time: nothing to do


def test_the_live_map_re_places_moved_stripes_when_read():
    """finish9: corrections are applied to the stripes when the live mesh reads them: their net move."""
    from loopmodel.config import MappingConfig
    from loopmodel.mapping.stripe_map import StripeMap
    from loopmodel.types import StripeProfile

    traj = AnchoredTrajectory()
    traj.set_keyframe(0, np.eye(4))
    for i in range(3):
        traj.add_frame(i * 10, kf_id=0, kf_from_cam=np.eye(4))
    smap = StripeMap(MappingConfig(chunk_m=0.05), poses=traj)
    pts = np.array([[0.01, 0.01, 0.51], [0.02, 0.01, 0.51]])
    smap.add(StripeProfile(15, pts))
    assert smap.take_dirty_blocks() is not None  # the first live snapshot: every block, then clean
    far = make_pose(np.eye(3), [0.2, 0, 0])
    traj.update_keyframes({0: far})
    traj.update_keyframes({0: np.eye(4)})  # and back before the live mesh looked: nothing to re-mesh
    assert smap.dirty_blocks == set()
    traj.update_keyframes({0: far})
    assert smap.dirty_blocks == {(0, 0, 10), (4, 0, 10)}  # where the surface was and where it is now
    np.testing.assert_allclose(smap.world_points(), pts + [0.2, 0, 0])
    np.testing.assert_allclose(smap.stripe_poses()[0], far)


def test_stripes_placed_when_read_equal_stripes_placed_as_they_come(rng):
    """orbit10 (issue 33): the live map places new stripes in one batch when read, not each frame.

    Against a map on the same trajectory that places them as they come: the same world points,
    sensor positions and stripe poses at every read; its dirty blocks those of the stripes placed or
    moved since the last read (the other also marks where a stripe sat before a move it was never
    meshed at).
    """
    from loopmodel.config import MappingConfig
    from loopmodel.mapping.stripe_map import StripeMap
    from loopmodel.types import StripeProfile

    traj = AnchoredTrajectory()
    cfg = MappingConfig(chunk_m=0.05)
    now, later = StripeMap(cfg, poses=traj), StripeMap(cfg, poses=traj, place_when_read=True)
    kf_pose = {0: np.eye(4)}
    traj.set_keyframe(0, kf_pose[0])
    fresh: list[np.ndarray] = []
    for i in range(60):
        kf = i // 15
        if kf not in kf_pose:
            kf_pose[kf] = make_pose(so3_exp(rng.normal(0, 0.05, 3)), rng.normal(0, 0.1, 3))
            traj.set_keyframe(kf, kf_pose[kf])
        traj.add_frame(i * 10, kf_id=kf, kf_from_cam=make_pose(so3_exp(rng.normal(0, 0.02, 3)), [0.002 * i, 0, 0]))
        stripes = [StripeProfile(i * 10 + d, rng.normal([0, 0, 0.5], 0.05, (int(rng.integers(1, 30)), 3)))
                   for d in (3, 7, 12)]  # the last one after the newest frame: it waits for the next
        now.add_many(stripes)
        later.add_many(stripes)
        fresh += [s.points_in_cam for s in stripes]
        if i % 7 == 3:  # a correction of the older keyframes
            traj.update_keyframes({k: make_pose(so3_exp(rng.normal(0, 0.01, 3)), rng.normal(0, 0.01, 3)) @ p
                                   for k, p in kf_pose.items() if k < kf})
        if i % 11 == 10:
            assert later._s_f0.a.max() < 0 or (later._s_f0.a >= 0).sum() < (now._s_f0.a >= 0).sum()  # waiting
            a, b = now.take_dirty_blocks(), later.take_dirty_blocks()
            assert a is not None and b is not None
            np.testing.assert_array_equal(b[0], a[0])
            np.testing.assert_array_equal(b[1], a[1])
            assert b[2] <= a[2] and len(b[2]) > 0
            np.testing.assert_array_equal(later.stripe_poses(), now.stripe_poses())
    np.testing.assert_array_equal(later.world_points(), now.world_points())
    np.testing.assert_array_equal(later.sensor_positions(), now.sensor_positions())
    np.testing.assert_array_equal(later.placed_mask, now.placed_mask)
    assert later.stripe_count == now.stripe_count == len(fresh)
