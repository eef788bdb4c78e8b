"""Batch runs on Dask.

A two-worker LocalCluster, re-runs, failing tasks, a killed worker, and a separately started
``dask scheduler`` + ``dask worker`` pair.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

pytest.importorskip("distributed")

from loopmodel.batch import load_plan, open_client, run_batch  # noqa: E402
from loopmodel.batch.plan import sequence_identity  # noqa: E402
from loopmodel.batch.runner import BatchState  # noqa: E402
from loopmodel.cli import main  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "datasets" / "tiny_kitti"

pytestmark = pytest.mark.slow


def _tiny_copy(dst: Path, frames: int) -> Path:
    """The first ``frames`` frames of the bundled tiny KITTI sequence (another sequence)."""
    for d in ("image_0", "image_1"):
        (dst / d).mkdir(parents=True)
        for i in range(frames):
            shutil.copy(TINY / d / f"{i:06d}.png", dst / d)
    shutil.copy(TINY / "calib.txt", dst)
    for f in ("poses.txt", "times.txt"):
        (dst / f).write_text("".join((TINY / f).read_text().splitlines(keepends=True)[:frames]))
    return dst


def _write_plan(path: Path, sequences: list[object], max_frames: int, **extra: object) -> Path:
    plan = {"sequences": sequences, "grid": {"backend.kind": ["isam2", "none"]}, "max_frames": max_frames}
    plan.update(extra)
    path.write_text(yaml.safe_dump(plan))
    return path


@pytest.fixture(scope="module")
def client():
    with open_client("local", workers=2) as c:
        yield c


@pytest.fixture(scope="module")
def first_batch(tmp_path_factory, client):
    root = tmp_path_factory.mktemp("batch")
    short = _tiny_copy(root / "tiny6", 6)
    (root / "bad.mcap").write_bytes(b"not an mcap file at all")
    plan_path = _write_plan(root / "plan.yaml", [str(TINY), "tiny6", "bad.mcap"], 8)
    plan = load_plan(plan_path)
    out = root / "out"
    outcome = run_batch(plan, out, lambda: client)
    return plan, out, outcome, short


def _summary(out: Path) -> dict[str, dict[str, str]]:
    with open(out / "summary.csv") as f:
        return {r["task"]: r for r in csv.DictReader(f)}


def test_batch_one_folder_per_task_and_metrics_equal_single_runs(first_batch, tmp_path):
    from loopmodel.batch import load_manifest, write_summary

    plan, out, outcome, short = first_batch
    recs = outcome.records
    assert len(recs) == 6 and outcome.skipped == 0
    done = [r for r in recs if r["status"] == "done"]
    assert len(done) == 4
    assert sorted(p.name for p in (out / "tasks").iterdir()) == sorted(r["task"] for r in done)
    assert not list((out / ".tmp").iterdir())  # nothing half-written left behind
    assert {r["pid"] for r in done} and all(r["peak_rss_mib"] > 50 for r in done)
    write_summary(load_manifest(out), out)
    rows = _summary(out)
    assert (out / "summary.md").is_file() and (out / "ate_by_variant.png").is_file()
    # the same runs one by one through the CLI (`loopmodel run` then `loopmodel eval`)
    for spec in plan.tasks(out):
        if spec.sequence_name == "bad":
            continue
        cfg_path = tmp_path / f"{spec.task_id}.yaml"
        cfg_path.write_text(yaml.safe_dump(spec.config))
        args = ["run", spec.sequence_path, "--config", str(cfg_path), "--out", str(tmp_path), "--name", spec.task_id]
        assert main([*args, "--max-frames", "8"]) == 0
        assert main(["eval", str(tmp_path / spec.task_id), "--no-plots"]) == 0
        single = json.loads((tmp_path / spec.task_id / "eval" / "metrics.json").read_text())
        row = rows[spec.task_id]
        assert row["status"] == "done"
        final = single["trajectories"]["final"]
        assert float(row["ate_rmse_m"]) == pytest.approx(single["ate_rmse_m"], rel=1e-9, abs=1e-12)
        assert float(row["rpe_frames_rmse_m"]) == pytest.approx(final["rpe_frames"]["trans_m"]["rmse"], rel=1e-9)
        assert int(row["matched"]) == final["matched"]
        run_m = json.loads((tmp_path / spec.task_id / "metrics.json").read_text())
        assert int(row["frames"]) == run_m["frames"]


def test_failing_task_recorded_others_finish(first_batch):
    _, out, outcome, _ = first_batch
    failed = [r for r in outcome.records if r["status"] == "failed"]
    assert {r["variant"] for r in failed} == {"backend.kind=isam2", "backend.kind=none"}
    for r in failed:
        assert r["sequence"] == "bad"
        assert "bad.mcap" in r["error"] and "\n" not in r["error"]
        assert json.loads((out / "failed" / f"{r['task']}.json").read_text())["error"] == r["error"]


def test_status_of_a_finished_batch_lists_its_tasks(first_batch, capsys):
    """``batch status`` on a finished batch: a row per task and the counts (it printed an empty table; issue 35)."""
    import re

    from loopmodel.cli import main

    _, out, _, _ = first_batch
    capsys.readouterr()
    assert main(["batch", "status", str(out)]) == 0  # the failed tasks (to run again) and the counts
    text = capsys.readouterr().out
    assert "4 done, 0 running, 2 failed, 0 pending" in text
    assert len(re.findall(r"\bfailed\b", text)) == 3 and "bad" in text  # two rows and the counts
    assert main(["batch", "status", str(out), "--all"]) == 0  # every task
    text = capsys.readouterr().out
    assert len(re.findall(r"\bdone\b", text)) == 5 and len(re.findall(r"\bfailed\b", text)) == 3
    assert "tiny6" in text


def test_rerun_skips_every_finished_task(first_batch):
    plan, out, outcome, _ = first_batch
    stamps = {p.name: (p / "task.json").stat().st_mtime_ns for p in (out / "tasks").iterdir()}

    def no_client() -> None:
        raise AssertionError("a re-run with nothing left must not need a cluster")

    good = load_plan(_write_plan(out.parent / "plan_good.yaml", [str(TINY), "tiny6"], 8))
    again = run_batch(good, out, no_client)
    assert again.skipped == 4 and [r["status"] for r in again.records] == ["done"] * 4
    assert {p.name: (p / "task.json").stat().st_mtime_ns for p in (out / "tasks").iterdir()} == stamps
    # the identity follows the content, not the place: a copy of a sequence is the same sequence
    assert sequence_identity(TINY) == sequence_identity(shutil.copytree(TINY, out.parent / "tiny_copy"))
    assert sequence_identity(TINY) != sequence_identity(out.parent / "tiny6")


def test_killed_worker_loses_nothing(client, tmp_path):
    plan = load_plan(_write_plan(tmp_path / "plan.yaml", [str(_tiny_copy(tmp_path / "tiny7", 7))], 8))
    killed: list[tuple[str, int]] = []

    def kill_first_running(state: BatchState) -> None:
        for task, tmp in state.running_tmp.items():
            if not killed:
                pid = int(tmp.name.rsplit(".", 3)[2])
                os.kill(pid, signal.SIGKILL)
                killed.append((task, pid))

    outcome = run_batch(plan, tmp_path / "out", lambda: client, kill_first_running, poll_s=0.02)
    assert killed, "no task was seen running"
    assert [r["status"] for r in outcome.records] == ["done"] * 2
    again = {r["task"]: r for r in outcome.records}[killed[0][0]]
    assert again["pid"] != killed[0][1]  # re-run on the restarted worker
    assert (tmp_path / "out" / "tasks" / killed[0][0] / "trajectory_final.tum").is_file()
    assert not list((tmp_path / "out" / ".tmp").iterdir())


def test_external_scheduler_and_two_workers(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    dask_cli = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    sched_file = tmp_path / "scheduler.json"
    procs = [
        subprocess.Popen(
            [*dask_cli, "--host", "127.0.0.1", "--port", "0", "--no-dashboard", "--scheduler-file", str(sched_file)],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    ]
    try:
        for _ in range(300):
            if sched_file.is_file() and sched_file.stat().st_size:
                break
            time.sleep(0.1)
        address = json.loads(sched_file.read_text())["address"]
        for _ in range(2):
            procs.append(
                subprocess.Popen(
                    [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1"]
                    + ["--host", "127.0.0.1", "--no-dashboard"],
                    env=env,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
        plan = _write_plan(tmp_path / "plan.yaml", [str(_tiny_copy(tmp_path / "tiny5", 5))], 8)
        out = tmp_path / "out"
        args = ["batch", str(plan), "--scheduler", address, "--workers", "2", "--out", str(out), "--no-plots"]
        assert main(args) == 0
        recs = [json.loads(p.read_text()) for p in (out / "tasks").glob("*/task.json")]
        assert len(recs) == 2 and all(r["status"] == "done" for r in recs)
        assert main(["batch", "status", str(out)]) == 0
    finally:
        for p in reversed(procs):
            p.send_signal(signal.SIGINT)
        for p in reversed(procs):
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()



_CLUSTER_AFTER_NUMBA = """
import numba, numpy as np
@numba.njit(parallel=True)
def total(x):
    s = 0.0
    for i in numba.prange(x.shape[0]):
        s += x[i]
    return s
total(np.ones(8))
from loopmodel.batch.execute import pin_threads
from loopmodel.batch.runner import open_client
pinned = pin_threads(1)
if __name__ == "__main__":
    with open_client("local", workers=1, threads_per_task=1) as client:
        client.wait_for_workers(1, timeout=60)
    @numba.njit
    def plus_one(x):
        return x + 1
    print(pinned["numba"], plus_one(np.ones(3)).sum())
"""


def test_numba_keeps_compiling_after_pinning_and_a_local_cluster(tmp_path: Path) -> None:
    """A process whose numba pool runs pins its threads and starts a local cluster, then compiles.

    numba re-reads ``NUMBA_NUM_THREADS`` at every compilation and raises when it differs from the
    launched pool; Dask's nanny writes its pre-spawn environment into this process's ``os.environ``
    (the CI failure of stop 40: a later test of the same pytest worker compiled a SURF kernel).
    """
    script = tmp_path / "cluster_after_numba.py"
    script.write_text(_CLUSTER_AFTER_NUMBA)
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_NUM_THREADS"}
    env["PYTHONPATH"] = str(ROOT)
    out = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split()[-2:] == ["1", "6.0"]
