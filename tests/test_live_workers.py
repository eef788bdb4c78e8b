"""Live mapping off the tracking thread (issue 33): stripes made in a process, meshing in a process."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from conftest import process_ended

from loopmodel.config import MappingConfig
from loopmodel.mapping.live import LiveMapping
from loopmodel.mapping.stripe_map import StripeMap
from loopmodel.types import StripeProfile


def _sphere_map(config: MappingConfig) -> StripeMap:
    """Stripes of a 0.25 m sphere seen from a sensor at the origin-facing poses (seeded)."""
    rng = np.random.default_rng(11)
    smap = StripeMap(config)
    poses = smap.poses
    poses.set_keyframe(0, np.eye(4))
    n = 20
    for i in range(n):
        poses.add_frame(1_000_000 * i, kf_id=0, kf_from_cam=np.eye(4))
    stripes = []
    for i in range(n):
        d = rng.normal(size=(400, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d = d[d[:, 2] < 0]  # the half facing the sensor, at z = 1 m
        stripes.append(StripeProfile(1_000_000 * i, np.array([0.0, 0.0, 1.0]) + 0.25 * d))
    smap.add_many(stripes)
    return smap


@pytest.mark.parametrize("worker", ["process", "thread"])
def test_live_mesh_worker_meshes_the_same_blocks(worker: str) -> None:
    """A process gives the same block meshes as meshing in this process; the tracker's thread keeps its pace."""
    from loopmodel.mapping.meshing import live_mesh_config, mesh_blocks

    cfg = MappingConfig(chunk_m=0.1)
    smap = _sphere_map(cfg)
    snap = smap.take_dirty_blocks()
    assert snap is not None
    reference = mesh_blocks(*snap, live_mesh_config(cfg))
    smap = _sphere_map(cfg)
    live = LiveMapping(smap, 1, worker)  # type: ignore[arg-type]
    live.on_keyframe()
    gaps = []
    last = time.perf_counter()
    while not live._job.done():
        sum(range(500))  # the tracking thread's Python work
        now = time.perf_counter()
        gaps.append(now - last)
        last = now
    live.close(wait=True)
    assert live.mesh() is not None  # installs the updated blocks
    assert live.update_ms and live.blocks_remeshed == len(reference)
    for key, ref in reference.items():
        got = smap._blocks.get(key)
        if ref is None:
            assert got is None
            continue
        assert got is not None
        assert np.allclose(np.asarray(got.vertices), np.asarray(ref.vertices))
        assert np.array_equal(np.asarray(got.triangles), np.asarray(ref.triangles))
    if worker == "process":
        # measured: longest pause of this thread 0.02 s with a process (a thread stalled it for the
        # whole reconstruction: 7.7 s for 60,000 points); generous for a loaded machine
        assert max(gaps) < 0.5, max(gaps)
    assert threading.active_count() >= 1


def _laser_image(shift_px: float) -> np.ndarray:
    """A bright Gaussian laser line (sigma 1.5 px) on a noisy dark 240 x 320 image (seeded)."""
    rng = np.random.default_rng(int(shift_px * 10))
    h, w = 240, 320
    cols = np.arange(w)[None, :]
    centre = 120.0 + shift_px + 0.2 * np.arange(h)[:, None]
    img = 10 + 200 * np.exp(-0.5 * ((cols - centre) / 1.5) ** 2) + rng.normal(0, 2, (h, w))
    return np.clip(img, 0, 255).astype(np.uint8)


def test_extraction_worker_gives_the_profiles_of_inline_extraction_in_order() -> None:
    from loopmodel.mapping.extraction import LightPlane, StripeExtractor, stripe_from_image
    from loopmodel.mapping.stripe_feed import ExtractionWorker
    from loopmodel.types import StereoCalibration

    cfg = MappingConfig()
    K = np.array([[250.0, 0, 160], [0, 250.0, 120], [0, 0, 1]])
    right_from_left = np.eye(4)
    right_from_left[0, 3] = -0.06
    images = [(1_000 * i, _laser_image(3.0 * i)) for i in range(6)]
    # the run's extractor, handed to the worker as it is (issue 32: no second light plane from K)
    worker = ExtractionWorker(StripeExtractor(StereoCalibration(K, K, right_from_left, (320, 240)), cfg))
    t0 = time.perf_counter()
    for t_ns, image in images:
        worker.submit(t_ns, image)
    assert time.perf_counter() - t0 < 0.5  # handing images over never waits for the worker
    got = worker.ready() + worker.wait()
    plane = LightPlane.from_config(cfg)
    expected = [stripe_from_image(image, t, K, plane, cfg) for t, image in images]
    expected = [p for p in expected if p.points_in_cam.shape[0]]
    assert len(expected) == 6
    assert [p.timestamp_ns for p in got] == [p.timestamp_ns for p in expected]
    assert all(np.allclose(a.points_in_cam, b.points_in_cam) for a, b in zip(got, expected, strict=True))


def test_corrections_move_every_stripe_point_and_mark_the_blocks_they_leave_and_enter() -> None:
    """A keyframe correction re-places the stripes and marks the blocks they leave and enter.

    Checked point by point from the stripe poses; exactly the blocks of the moved stripes' old and new points.
    """
    from loopmodel.geometry.se3 import make_pose

    cfg = MappingConfig(chunk_m=0.02)
    rng = np.random.default_rng(5)
    smap = StripeMap(cfg)
    poses = smap.poses
    poses.set_keyframe(0, np.eye(4))
    poses.set_keyframe(1, make_pose(np.eye(3), np.array([0.1, 0.0, 0.0])))
    for i in range(10):
        poses.add_frame(1_000_000 * i, kf_id=0 if i < 5 else 1, kf_from_cam=make_pose(np.eye(3), [0.01 * i, 0, 0]))
    stripes = [
        StripeProfile(1_000_000 * i + 500_000, rng.normal(size=(int(rng.integers(0, 30)), 3)) * 0.1 + [0, 0, 1])
        for i in range(9)
    ]
    smap.add_many(stripes)
    assert smap.take_dirty_blocks() is not None  # the live mesh starts: every block clean after this
    before = [smap.world_points(s) for s in range(len(stripes))]
    moved = make_pose(np.eye(3), np.array([0.1, 0.0, 0.03]))
    poses.update_keyframes({1: moved})
    T = smap.stripe_poses()
    expected_dirty: set[tuple[int, int, int]] = set()
    for s, st in enumerate(stripes):
        got = smap.world_points(s)
        want = np.asarray(st.points_in_cam) @ T[s, :3, :3].T + T[s, :3, 3]
        assert np.allclose(got, want)
        if got.size and np.abs(got - before[s]).max() >= 0.25 * cfg.voxel_m:
            for p in (before[s], got):
                expected_dirty |= {tuple(k) for k in np.floor(p / cfg.chunk_m).astype(int).tolist()}
    assert expected_dirty and smap.dirty_blocks == expected_dirty


def test_abandoned_live_update_ends_its_worker_process() -> None:
    """``close(wait=False)`` drops an unfinished update and ends the worker process at once (issue 32).

    The update stands for the live mesh's last one, which took a core beside the final refinement
    and the final mesh; a finished one is still installed.
    """
    smap = _sphere_map(MappingConfig(chunk_m=0.1))
    live = LiveMapping(smap, 1, "process")
    pool = live._workers()
    live._job = pool.submit(time.sleep, 120.0)  # an update that would hold its core for two minutes
    procs = list(pool._processes.values())  # type: ignore[attr-defined]
    assert procs
    t0 = time.perf_counter()
    live.close(wait=False)
    assert all(process_ended(proc.pid, 30.0) for proc in procs)
    assert time.perf_counter() - t0 < 30.0  # ended, not waited for (the sleep is 120 s)
    assert live.updates_abandoned == 1 and live.metrics()["live_mesh_updates_abandoned"] == 1
    assert live.mesh() is None  # no update ever finished

    # a finished update is installed even without waiting
    live = LiveMapping(_sphere_map(MappingConfig(chunk_m=0.1)), 1, "thread")
    live.on_keyframe()
    job = live._job
    assert job is not None
    job.result(timeout=120.0)
    live.close(wait=False)
    assert live.updates_abandoned == 0 and live.update_ms and live.mesh() is not None


def test_live_update_not_started_when_it_would_end_after_the_last_frame() -> None:
    """mesh14: with the frames left shorter than the last update took, no update starts; else one does.

    Such an update is abandoned for the final mesh, and held the final mesh's process up at the end.
    The dirty blocks are kept (a later turn with more time left takes them).
    """
    smap = _sphere_map(MappingConfig(chunk_m=0.1))
    live = LiveMapping(smap, 1, "process")
    live.wait_started()
    t0 = time.perf_counter()
    live.on_keyframe(seconds_left=0.0)  # no update measured yet: it starts
    job = live._job
    assert job is not None
    job.result(timeout=120.0)
    took_s = time.perf_counter() - t0
    smap.add_many([StripeProfile(19_000_000, np.array([[0.0, 0.3, 1.0], [0.01, 0.3, 1.0]]))])  # a dirty block
    live.on_keyframe(seconds_left=0.0)  # the last update took longer than 0 s: skipped
    assert live._job is None and live.updates_skipped == 1 and live._last_wall_s is not None
    assert 0.0 < live._last_wall_s <= took_s + 0.05
    assert smap.dirty_blocks  # left for later
    live.on_keyframe(seconds_left=live._last_wall_s + 60.0)  # time enough: it starts
    assert live._job is not None
    live.close(wait=True)
    assert live.metrics()["live_mesh_updates_skipped"] == 1 and len(live.update_ms) == 2
    # a thread's update is not ended at the finish: it is not skipped
    live = LiveMapping(_sphere_map(MappingConfig(chunk_m=0.1)), 1, "thread")
    live._last_wall_s = 10.0
    live.on_keyframe(seconds_left=0.0)
    assert live._job is not None and live.updates_skipped == 0
    live.close(wait=True)
