"""The finish after the last frame (issue 32): Ctrl-C in it, and the final mesh in its own process.

A run through the API installs no signal handler, so a Ctrl-C raises ``KeyboardInterrupt`` wherever
it lands. Landing in the finish's workers step it must still end with a complete, consistent
results folder of what exists; a second one during the writes leaves no half-written files.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import process_ended

from loopmodel.io.trajectory_io import read_trajectory

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "datasets" / "tiny_kitti"

# the Ctrl-C lands in the finish's workers step (a real SIGINT while the step's start is told)
SCRIPT = """
import json, sys, time
import loopmodel
import loopmodel.pipeline as pipeline

def finishing(step, seconds):
    if step == "workers" and seconds is None:
        print("finishing", flush=True)
        time.sleep(60)

if sys.argv[3] == "twice":  # the second Ctrl-C lands in the writes
    write = pipeline.write_results
    def slow_write(folder, result, **kw):
        print("writing", flush=True)
        time.sleep(60)
        return write(folder, result, **kw)
    pipeline.write_results = slow_write
res = loopmodel.run(sys.argv[1], None, sys.argv[2], name="cut", finishing=finishing)
print(json.dumps({"interrupted": res.interrupted, "folder": str(res.folder)}), flush=True)
"""


def _start(out: Path, mode: str) -> subprocess.Popen[str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
    return subprocess.Popen(
        [sys.executable, "-c", SCRIPT, str(TINY), str(out), mode],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )


def _wait_for(proc: subprocess.Popen[str], line: str) -> None:
    assert proc.stdout is not None
    for got in proc.stdout:
        if got.strip() == line:
            return
    raise AssertionError(f"no {line!r}: {proc.wait()} {proc.stderr.read() if proc.stderr else ''}")


def test_ctrl_c_in_the_finish_keeps_a_complete_results_folder(tmp_path: Path) -> None:
    out = tmp_path / "out"
    proc = _start(out, "once")
    _wait_for(proc, "finishing")
    os.killpg(proc.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the whole process group
    stdout, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    said = json.loads(stdout.strip().splitlines()[-1])
    assert said["interrupted"] is True and Path(said["folder"]) == out / "cut"
    folder = out / "cut"
    m = json.loads((folder / "metrics.json").read_text())
    n = len(list((TINY / "image_0").iterdir()))
    assert m["interrupted"] is True and m["frames"] == n  # every frame was done before the finish
    online = read_trajectory(folder / "trajectory_online.tum")
    final = read_trajectory(folder / "trajectory_final.tum")
    assert len(online) == m["ok_frames"] == len(final)
    assert len(read_trajectory(folder / "keyframes.tum")) == m["keyframes"]
    assert "interrupted after" in (folder / "run.log").read_text()
    # the steps begun: the workers step, cut short; the evaluation of what exists
    assert set(m["finish_s"]) == {"workers", "evaluation"} and m["ate_rmse_m"] < 0.01
    assert m["wall_s"] == pytest.approx(m["frames_s"] + sum(m["finish_s"].values()))
    assert [p.name for p in out.iterdir()] == ["cut"]  # no staging folder, no lock
    assert not [p.name for p in folder.iterdir() if ".tmp-" in p.name]


def test_a_second_ctrl_c_in_the_writes_leaves_no_half_written_files(tmp_path: Path) -> None:
    out = tmp_path / "out"
    proc = _start(out, "twice")
    _wait_for(proc, "finishing")
    os.killpg(proc.pid, signal.SIGINT)
    _wait_for(proc, "writing")
    time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode != 0 and "KeyboardInterrupt" in err
    assert not out.exists() or not list(out.iterdir()), list(out.iterdir())  # nothing half-written


def _patch_of_a_sphere(n: int = 6000, seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Points on a 0.1 m sphere's cap seen from its centre (world, metres) and the sensor positions."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0.0, 0.9, n)
    phi = rng.uniform(0.0, 2 * np.pi, n)
    pts = 0.1 * np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)
    return pts, np.zeros_like(pts)


def test_the_final_mesh_in_its_process_is_the_mesh_made_here_and_a_dead_worker_is_replaced() -> None:
    from loopmodel.config import MappingConfig
    from loopmodel.mapping.final import FinalMeshJob, FinalMeshWorker
    from loopmodel.mapping.meshing import mesh_from_points

    pts, sensors = _patch_of_a_sphere()
    cfg = MappingConfig()
    here = mesh_from_points(pts, sensors, cfg)
    # the surface is the sphere: vertices within a voxel of its 0.1 m radius (measured 0.4 mm max)
    assert np.abs(np.linalg.norm(np.asarray(here.vertices), axis=1) - 0.1).max() < cfg.voxel_m
    worker = FinalMeshWorker()
    try:
        mesh, m = FinalMeshJob(pts, sensors, cfg, worker).result()
        assert m["mesh_vertices"] == len(here.vertices) == len(mesh.vertices) and m["final_mesh_s"] > 0
        assert m["final_mesh_in_worker"] is True
        np.testing.assert_array_equal(np.asarray(mesh.vertices), np.asarray(here.vertices))
        np.testing.assert_array_equal(np.asarray(mesh.triangles), np.asarray(here.triangles))
        # the worker process killed (as a Poisson crash would): meshed here instead, the same mesh
        procs = list(worker._pool._processes.values())  # noqa: SLF001
        assert len(procs) == 1
        os.kill(procs[0].pid, signal.SIGKILL)
        procs[0].join(10)
        mesh2, m2 = FinalMeshJob(pts, sensors, cfg, worker).result()
        np.testing.assert_array_equal(np.asarray(mesh2.vertices), np.asarray(here.vertices))
        assert m2["final_mesh_in_worker"] is False
    finally:
        worker.close()
    assert all(process_ended(p.pid, 10.0) for p in procs)


def test_the_live_mesh_hands_its_idle_worker_to_the_final_mesh() -> None:
    """The live mesh's worker process (open3d loaded) makes the final mesh when it is idle: the same mesh."""
    from loopmodel.config import MappingConfig
    from loopmodel.mapping.final import FinalMeshJob, FinalMeshWorker
    from loopmodel.mapping.live import LiveMapping
    from loopmodel.mapping.meshing import mesh_from_points
    from loopmodel.mapping.stripe_map import StripeMap
    from loopmodel.types import StripeProfile

    pts, sensors = _patch_of_a_sphere(3000)
    cfg = MappingConfig()
    live = LiveMapping(StripeMap(cfg), 1, "process")
    live.feed([StripeProfile(0, pts[:50])])  # its worker process starts with the first stripes
    pool = live.take_idle_worker()
    assert pool is not None and live.take_idle_worker() is None
    live.close(wait=False)  # nothing left to end: the pool is the final mesh's now
    worker = FinalMeshWorker(pool)
    try:
        mesh, m = FinalMeshJob(pts, sensors, cfg, worker).result()
        procs = list(pool._processes.values())  # noqa: SLF001
    finally:
        worker.close()
    here = mesh_from_points(pts, sensors, cfg)
    np.testing.assert_array_equal(np.asarray(mesh.vertices), np.asarray(here.vertices))
    assert m["mesh_vertices"] == len(here.vertices) and len(procs) == 1
    assert process_ended(procs[0].pid, 10.0)


def test_a_busy_live_worker_is_handed_over_only_when_asked() -> None:
    """finish11: ``take_idle_worker(busy=True)`` drops the unfinished update; the final mesh runs after it."""
    import time

    from loopmodel.config import MappingConfig
    from loopmodel.mapping.final import FinalMeshJob, FinalMeshWorker
    from loopmodel.mapping.live import LiveMapping
    from loopmodel.mapping.meshing import mesh_from_points
    from loopmodel.mapping.stripe_map import StripeMap
    from loopmodel.types import StripeProfile

    pts, sensors = _patch_of_a_sphere(3000)
    cfg = MappingConfig()
    live = LiveMapping(StripeMap(cfg), 1, "process")
    live.feed([StripeProfile(0, pts[:50])])  # its worker process starts with the first stripes
    live._job = live._pool.submit(time.sleep, 1.0)  # noqa: SLF001 - an update still running
    assert live.take_idle_worker() is None
    pool = live.take_idle_worker(busy=True)
    assert pool is not None and live.updates_abandoned == 1 and live.take_idle_worker(busy=True) is None
    worker = FinalMeshWorker(pool)
    try:
        mesh, m = FinalMeshJob(pts, sensors, cfg, worker).result()
    finally:
        worker.close()
    assert m["final_mesh_in_worker"] is True
    np.testing.assert_array_equal(np.asarray(mesh.vertices), np.asarray(mesh_from_points(pts, sensors, cfg).vertices))


def test_a_busy_live_worker_leaves_the_final_mesh_to_the_extraction_process() -> None:
    """mesh14: ``_Run._mesh_in_helper`` gives the idle helper pool (no open3d yet) the final mesh: the same mesh.

    open3d is loaded there without its plotly viewer (fin19). The busy live worker is not taken (its update is
    abandoned when the live mesh closes); without a helper the busy worker is taken as before (finish11).
    """
    import multiprocessing as mp
    import time
    import types
    from concurrent.futures import ProcessPoolExecutor

    from loopmodel.config import MappingConfig
    from loopmodel.mapping.final import FinalMeshJob
    from loopmodel.mapping.live import LiveMapping
    from loopmodel.mapping.meshing import mesh_from_points
    from loopmodel.mapping.stripe_map import StripeMap
    from loopmodel.pipeline import _Run
    from loopmodel.types import StripeProfile

    pts, sensors = _patch_of_a_sphere(3000)
    cfg = MappingConfig()
    live = LiveMapping(StripeMap(cfg), 1, "process")
    live.feed([StripeProfile(0, pts[:50])])
    live._job = live._pool.submit(time.sleep, 120.0)  # noqa: SLF001 - an update still running
    helper = ProcessPoolExecutor(1, mp_context=mp.get_context("spawn"))  # stands for the extraction process
    run = types.SimpleNamespace(helper=helper, live=live, mesh_worker=None)
    _Run._mesh_in_helper(run)  # type: ignore[arg-type]
    assert run.helper is None and run.mesh_worker is not None and run.mesh_worker._pool is helper  # noqa: SLF001
    live_procs = list(live._pool._processes.values())  # noqa: SLF001
    live.close(wait=False)  # the busy update abandoned, its process ended
    assert live.updates_abandoned == 1 and all(process_ended(p.pid, 30.0) for p in live_procs)
    try:
        mesh, m = FinalMeshJob(pts, sensors, cfg, run.mesh_worker).result()
        # fin19: open3d loaded there without its plotly viewer (dash, plotly: 0.8 s CPU)
        loaded = helper.submit(eval, "[m in __import__('sys').modules for m in ('open3d', 'dash', 'plotly')]")
        assert loaded.result(60.0) == [True, False, False]
    finally:
        run.mesh_worker.close()
    assert m["final_mesh_in_worker"] is True
    np.testing.assert_array_equal(np.asarray(mesh.vertices), np.asarray(mesh_from_points(pts, sensors, cfg).vertices))

    # no helper process: the busy live worker is taken (its update dropped, the mesh runs after it)
    live = LiveMapping(StripeMap(cfg), 1, "process")
    live.feed([StripeProfile(0, pts[:50])])
    live._job = live._pool.submit(time.sleep, 0.5)  # noqa: SLF001
    run = types.SimpleNamespace(helper=None, live=live, mesh_worker=None)
    _Run._mesh_in_helper(run)  # type: ignore[arg-type]
    assert run.mesh_worker is not None and live.updates_abandoned == 1
    run.mesh_worker.close()
