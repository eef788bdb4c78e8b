"""Benchmark of ``loopmodel batch``: 4 short sequences x 3 variants = 12 tasks on Dask.

Sequences: the real KITTI clip (``../shared/data/kitti_clip``, configs/kitti.yaml), the bundled
``datasets/tiny_kitti`` and two small simulated scans (``loopmodel simulate scan``: browse and
orbit (16 and 120 frames), 320x240, seeds 1 and 2; generated once into ``results/bench_batch/data``). Variants: the
defaults, ``frontend.max_features: 400`` and ``backend.kind: none``. Every task stops after
``max_frames`` frames (10; 6 with ``--quick``).

In one run of this script:
- ``wall_1_worker_s`` / ``wall_2_workers_s``: the batch on a fresh LocalCluster of 1 and of 2
  single-thread workers, from the first submission to the last result (cluster start and the
  workers' one-time imports excluded, reported as ``cluster_start_*_s``);
  ``speedup_2_workers`` is their ratio;
- ``rerun_s``: ``loopmodel batch PLAN --out`` (a new process) on the finished 2-worker folder;
- ``killed_worker_tasks_lost``: a third fresh batch on 2 workers where the bench SIGKILLs the
  worker process of the first task it sees running; tasks not done at the end;
- ``overhead_s_per_task``: (1-worker wall - sum of the tasks' own times measured inside them) / tasks;
  ``subprocess_start_s_per_task`` is what a subprocess per task would add instead (a new
  interpreter importing the pipeline, median of 3).
The machine is shared: ``load_1min_*`` is ``/proc/loadavg`` before each timed part.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import yaml
from shared_data import SHARED_DATA

ROOT = Path(__file__).resolve().parents[1]
# the shared real data beside the project (``$LOOPMODEL_SHARED_DATA`` overrides, e.g. from a worktree)
SHARED = SHARED_DATA
WORK = ROOT / "results" / "bench_batch"


def _load() -> float:
    return float(Path("/proc/loadavg").read_text().split()[0])


def _sim(path: Path, preset: str, seed: int, frames: int) -> Path:
    if path.is_file():
        return path
    from loopmodel.config import Config
    from loopmodel.sim.generate import resolve_config, simulate_scan

    cfg = Config()
    sim = resolve_config(
        cfg.simulation, preset, {"trajectory": {"frames": frames}, "camera": {"width_px": 320, "height_px": 240}}
    )
    sim = resolve_config(sim.model_copy(update={"seed": seed, "workers": 1}))
    simulate_scan(sim, path, cfg.sequence.topics, None, preset)
    return path


def _plan(path: Path, max_frames: int) -> Path:
    data = WORK / "data"
    data.mkdir(parents=True, exist_ok=True)
    sim_a = _sim(data / "sim_browse.mcap", "browse", 1, 16)
    # the orbit preset turns once around the object over all its frames: 120 frames (3 deg per
    # frame, of which a task uses the first max_frames); at 16 frames the front end loses track
    sim_b = _sim(data / "sim_orbit120.mcap", "orbit", 2, 120)
    plan = {
        "name": "bench",
        "sequences": [
            {"path": str(SHARED / "kitti_clip"), "config": str(ROOT / "configs" / "kitti.yaml")},
            str(ROOT / "datasets" / "tiny_kitti"),
            {"path": str(sim_a), "config": str(ROOT / "configs" / "sim.yaml")},
            {"path": str(sim_b), "config": str(ROOT / "configs" / "sim.yaml")},
        ],
        "base": {"eval.plots": False},
        "variants": [
            {"name": "default", "set": {}},
            {"name": "features400", "set": {"frontend.max_features": 400}},
            {"name": "frontend-only", "set": {"backend.kind": "none"}},
        ],
        "max_frames": max_frames,
    }
    path.write_text(yaml.safe_dump(plan, sort_keys=False))
    return path


def _batch(plan_path: Path, out: Path, workers: int, kill: bool = False) -> dict:
    from loopmodel.batch import load_plan, open_client, run_batch
    from loopmodel.batch.runner import BatchState

    shutil.rmtree(out, ignore_errors=True)
    plan = load_plan(plan_path)
    killed: list[int] = []

    def on_progress(state: BatchState) -> None:
        if kill and not killed:
            for tmp in state.running_tmp.values():
                pid = int(tmp.name.rsplit(".", 3)[2])
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
                break

    load = _load()
    t0 = time.perf_counter()
    with open_client("local", workers=workers) as client:
        start_s = time.perf_counter() - t0
        outcome = run_batch(plan, out, lambda: client, on_progress, poll_s=0.1)
    recs = outcome.records
    return {
        "load": load,
        "cluster_start_s": start_s,
        "wall_s": outcome.submit_wall_s,
        "task_s_sum": sum(float(r.get("task_s") or 0.0) for r in recs),
        "cpu_s_sum": sum(float(r.get("cpu_s") or 0.0) for r in recs),
        "done": sum(r.get("status") == "done" for r in recs),
        "failed": [r.get("error") for r in recs if r.get("status") != "done"],
        "tasks": len(recs),
        "killed": killed,
        "peak_rss_mib_max": max((r.get("peak_rss_mib") or 0.0) for r in recs),
    }


def run(quick: bool = False) -> dict:
    from loopmodel.batch import load_manifest, write_summary

    WORK.mkdir(parents=True, exist_ok=True)
    plan_path = _plan(WORK / "plan.yaml", 6 if quick else 10)
    one = _batch(plan_path, WORK / "out_1", 1)
    two = _batch(plan_path, WORK / "out_2", 2)
    t0 = time.perf_counter()
    write_summary(load_manifest(WORK / "out_2"), WORK / "out_2")
    summary_s = time.perf_counter() - t0
    load_rerun = _load()
    t0 = time.perf_counter()
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run(
        [sys.executable, "-m", "loopmodel", "batch", str(plan_path), "--out", str(WORK / "out_2")],
        env=env,
        capture_output=True,
        text=True,
    )
    rerun_s = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"re-run failed: {proc.stderr.strip().splitlines()[-1:]}")
    rerun_skipped_all = "(12 already finished)" in proc.stdout or f"({one['tasks']} already finished)" in proc.stdout
    killed = _batch(plan_path, WORK / "out_kill", 2, kill=True)
    # what a subprocess per task would add: a fresh interpreter importing what a task needs
    # (median of 3), against the in-worker overhead above
    starts = []
    for _ in range(3):
        t0 = time.perf_counter()
        subprocess.run(
            [sys.executable, "-c", "import loopmodel.pipeline, loopmodel.io.sequence, loopmodel.eval.report"],
            env=env,
            check=True,
        )
        starts.append(time.perf_counter() - t0)
    n = one["tasks"]
    return {
        "tasks": n,
        "speedup_2_workers": round(one["wall_s"] / two["wall_s"], 3),
        "rerun_s": round(rerun_s, 2),
        "killed_worker_tasks_lost": killed["tasks"] - killed["done"],
        "overhead_s_per_task": round((one["wall_s"] - one["task_s_sum"]) / n, 3),
        "subprocess_start_s_per_task": round(sorted(starts)[1], 2),
        "wall_1_worker_s": round(one["wall_s"], 2),
        "wall_2_workers_s": round(two["wall_s"], 2),
        # the tasks' own time over workers x wall: near 1 when Dask keeps every worker busy; a
        # task_s_sum that grows with the worker count means the CPU (shared machine) is the limit
        "worker_busy_fraction_2_workers": round(two["task_s_sum"] / (2 * two["wall_s"]), 3),
        "task_s_sum_1_worker": round(one["task_s_sum"], 2),
        # CPU seconds per wall second of a task on 1 worker: above 1, a task already uses more
        # than one core (threads of its own), which caps what a second worker can add
        "task_cpu_per_wall_1_worker": round(one["cpu_s_sum"] / one["task_s_sum"], 3),
        "task_s_sum_2_workers": round(two["task_s_sum"], 2),
        "cluster_start_1_worker_s": round(one["cluster_start_s"], 2),
        "cluster_start_2_workers_s": round(two["cluster_start_s"], 2),
        "tasks_done_1_worker": one["done"],
        "tasks_done_2_workers": two["done"],
        "failed_errors": one["failed"] + two["failed"],
        "rerun_skipped_all": rerun_skipped_all,
        "workers_killed": len(killed["killed"]),
        "summary_s": round(summary_s, 2),
        "task_peak_rss_mib_max": round(max(one["peak_rss_mib_max"], two["peak_rss_mib_max"]), 1),
        "load_1min_1_worker": one["load"],
        "load_1min_2_workers": two["load"],
        "load_1min_rerun": load_rerun,
        "load_1min_kill": killed["load"],
        "cpu_count": os.cpu_count(),
    }
