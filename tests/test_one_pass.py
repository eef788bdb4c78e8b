"""One pass over the data (issue 32).

The run reads each frame and each laser image once, meshes the stripes it extracted while it ran,
grades nothing itself (the evaluation is a separate step after it), and shows each finishing step.
"""

from __future__ import annotations

import json
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from loopmodel.config import Config, config_from_dict
from loopmodel.io.sequence import open_sequence
from loopmodel.sim import generate as gen

N_FRAMES = 6


@pytest.fixture(scope="module")
def laser_scan(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Config]:
    """A small clean scan whose laser data are laser-line images only (the stripe topic is not read)."""
    cfg = config_from_dict(
        {
            "simulation": {
                "seed": 3,
                "camera": {"width_px": 320, "height_px": 240, "fx_px": 250.0},
                "trajectory": {"frames": N_FRAMES},
                "laser": {"image": True, "range_noise_m": 0.0},
            },
            "sequence": {"topics": {"stripe": "/not/recorded"}},
            "loop": {"enabled": False},
        }
    )
    path = tmp_path_factory.mktemp("onepass") / "laser.mcap"
    gen.simulate_scan(cfg.simulation, path)
    return path, cfg


def _counted(seq: Any, calls: Counter[str], items: Counter[str]) -> None:
    """Count, on this sequence object, the calls of its streaming readers and the items they yield."""

    def wrap(name: str, read: Callable[[], Iterator[Any]]) -> Callable[[], Iterator[Any]]:
        def counting() -> Iterator[Any]:
            calls[name] += 1
            for item in read():
                items[name] += 1
                yield item

        return counting

    for name in ("frames", "laser_images", "stripes"):
        setattr(seq, name, wrap(name, getattr(seq, name)))


@pytest.mark.slow  # the scan's generation: 18-23 s at load 10
def test_a_run_reads_each_frame_and_laser_image_once(laser_scan: tuple[Path, Config]) -> None:
    from loopmodel.mapping.extraction import LightPlane, stripe_from_image
    from loopmodel.pipeline import process

    path, cfg = laser_scan
    seq = open_sequence(path, cfg.sequence)
    assert seq.stripe_count() == 0 and seq.laser_image_count() == N_FRAMES
    calls: Counter[str] = Counter()
    items: Counter[str] = Counter()
    _counted(seq, calls, items)
    result = process(seq, cfg)
    assert len(result.frames) == N_FRAMES
    # one pass: one call of each reader, each frame and laser image read once, no stripe messages
    assert calls == Counter({"frames": 1, "laser_images": 1}), calls
    assert items == Counter({"frames": N_FRAMES, "laser_images": N_FRAMES}), items
    # the stripes meshed at the end are the ones extracted during the run: the same profiles as
    # plain extraction of every image of a fresh reader (the camera's intrinsics, the light plane)
    fresh = open_sequence(path, cfg.sequence)
    cal = fresh.calibration
    plane = LightPlane.from_config(cfg.mapping)
    dist = None if cal.rectified else cal.dist_left
    expected = [stripe_from_image(im, t, cal.K_left, plane, cfg.mapping, dist) for t, im in fresh.laser_images()]
    expected = [p for p in expected if p.points_in_cam.shape[0]]
    assert len(result.stripes) == len(expected) >= N_FRAMES - 2
    for got, want in zip(result.stripes, expected, strict=True):
        assert got.timestamp_ns == want.timestamp_ns
        np.testing.assert_array_equal(got.points_in_cam, want.points_in_cam)
    # the run graded nothing: no error against the ground truth in its metrics
    assert not [k for k in result.metrics if k.startswith(("ate_", "drift_", "mesh_err", "mesh_completeness"))]
    assert set(result.metrics["finish_s"]) == {"workers", "final_refinement", "mesh", "map"}
    cpu = result.metrics["finish_cpu_s"]  # this process's CPU seconds in each step
    assert set(cpu) == set(result.metrics["finish_s"]) and all(v >= 0 for v in cpu.values())
    assert cpu["mesh"] > 0.01  # the final mesh is made in this process (no mesh worker by default)
    assert result.metrics["wall_s"] == pytest.approx(
        result.metrics["frames_s"] + sum(result.metrics["finish_s"].values())
    )
    # finish10: the idle extraction process kept as the re-solve's helper (any run length here) is ended
    # with the finish (this scan's few keyframes give no re-solve: tests/test_retrack.py has the helper's)
    import multiprocessing as mp

    helped = cfg.model_copy(deep=True)
    helped.calibration.retrack_helper_min_frames = 0
    # only this run's processes: earlier tests of the same pytest worker may have left daemons of their own
    before = {p.pid for p in mp.active_children()}
    again = process(open_sequence(path, cfg.sequence), helped)
    m = again.metrics
    assert m.get("calibration_retrack_helper_frames", 0) <= m.get("calibration_retrack_resolved", 0)
    assert len(again.frames) == N_FRAMES and set(m["finish_s"]) == set(result.metrics["finish_s"])

    def left() -> list[str]:
        return [p.name for p in mp.active_children() if p.pid not in before]

    deadline = time.monotonic() + 10
    while left() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not left()


@pytest.mark.slow
def test_evaluation_after_the_run_against_an_independent_computation(laser_scan: tuple[Path, Config]) -> None:
    """:func:`loopmodel.evaluate` of a result placed with known poses: the truth moved by 2 mm of noise."""
    import open3d as o3d

    import loopmodel
    from loopmodel.io.laser import sequence_stripes
    from loopmodel.io.mesh_io import mesh_from_bytes
    from loopmodel.mapping.final import final_mesh
    from loopmodel.result import RunResult
    from loopmodel.types import Trajectory

    path, cfg = laser_scan
    seq = open_sequence(path, cfg.sequence)
    gt = seq.ground_truth
    assert gt is not None
    poses = gt.world_from_cam.copy()
    poses[:, :3, 3] += np.random.default_rng(0).normal(0.0, 0.002, (len(gt), 3))
    noisy = Trajectory(gt.timestamps_ns, poses)
    stripes = list(sequence_stripes(seq, cfg.mapping))
    mesh, _ = final_mesh(stripes, gt, cfg.mapping)
    result = RunResult(config=cfg, online=noisy, final=gt, stripes=stripes, mesh=mesh)
    ev = loopmodel.evaluate(result, seq)
    m = ev.metrics
    # ATE of the online poses, aligned here (Kabsch, no scale); the final ones are the truth
    est, ref = noisy.positions_m, gt.positions_m
    ce, cr = est.mean(axis=0), ref.mean(axis=0)
    U, _, Vt = np.linalg.svd((ref - cr).T @ (est - ce))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    ate = float(np.sqrt(np.mean(np.sum(((est - ce) @ R.T + cr - ref) ** 2, axis=1))))
    assert m["ate_rmse_m_online"] == pytest.approx(ate, rel=1e-6) and m["gt_frames_online"] == N_FRAMES
    assert m["ate_rmse_m"] < 1e-9 and m["drift_pct"] < 1e-6
    # the final mesh against the scene: mean vertex distance by plain open3d ray casting
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh_from_bytes(seq.read_attachment("scene.ply"))))
    v = o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32))
    d_mm = 1e3 * scene.compute_distance(v).numpy()
    assert m["mesh_err_after_mm"] == pytest.approx(float(d_mm.mean()), rel=1e-3)
    assert m["mesh_err_after_mm"] < 1.0  # measured 0.1 mm: the stripes' own noise
    # the two reference meshes only when asked
    assert "mesh_err_before_mm" not in m and "mesh_err_gt_mm" not in m
    assert 0.0 < m["mesh_completeness_after"] <= 1.0 and ev.seconds > 0
    refs = loopmodel.evaluate(result, seq, mesh_references=True).metrics
    assert refs["mesh_err_gt_mm"] == pytest.approx(m["mesh_err_after_mm"], rel=0.05)
    assert refs["mesh_err_before_mm"] > refs["mesh_err_gt_mm"]
    # nothing without ground truth
    seq._gt = None  # type: ignore[attr-defined]
    assert not loopmodel.evaluate(result, seq).graded


def test_run_shows_each_finishing_step_and_no_eval_skips_the_evaluation(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from loopmodel.cli import main

    tiny = Path(__file__).resolve().parents[1] / "datasets" / "tiny_kitti"
    base = ["run", str(tiny), "--out", str(tmp_path)]
    assert main([*base, "--name", "graded"]) == 0
    err = capsys.readouterr().err
    for label in ("final refinement", "final mesh", "session map", "evaluation against ground truth", "results"):
        assert any(label in line and line.rstrip().endswith(" s") for line in err.splitlines()), (label, err)
    m = json.loads((tmp_path / "graded" / "metrics.json").read_text())
    assert m["ate_rmse_m"] < 0.01 and m["finish_s"]["evaluation"] > 0
    assert m["wall_s"] == pytest.approx(m["frames_s"] + sum(m["finish_s"].values()))
    assert main([*base, "--name", "plain", "--no-eval"]) == 0
    assert "evaluation" not in capsys.readouterr().err
    m = json.loads((tmp_path / "plain" / "metrics.json").read_text())
    assert "ate_rmse_m" not in m and "evaluation" not in m["finish_s"]


class _Watched:
    """A sequence that records which functions read it: (module, function) of each attribute access."""

    def __init__(self, seq: Any, readers: set[tuple[str, str]]) -> None:
        self._seq = seq
        self._readers = readers

    def _note(self) -> None:
        caller = sys._getframe(2)
        self._readers.add((str(caller.f_globals.get("__name__")), caller.f_code.co_name))

    def __getattr__(self, name: str) -> Any:  # only names the proxy does not have itself
        self._note()
        return getattr(self._seq, name)

    def __len__(self) -> int:
        self._note()
        return len(self._seq)


def test_the_sequence_is_read_by_a_few_functions_and_by_no_stage(tmp_path: Path) -> None:
    """Issue 32: the walk of the sequence from ``run_pipeline`` climbs back up at most 6 times.

    The functions that read it below ``run_pipeline``: the run (its one pass and the calibration),
    the results' format and the evaluation after the run; no stage package sees it.
    """
    from loopmodel.pipeline import run_pipeline

    tiny = Path(__file__).resolve().parents[1] / "datasets" / "tiny_kitti"
    readers: set[tuple[str, str]] = set()
    seq = _Watched(open_sequence(tiny), readers)
    result = run_pipeline(seq, Config(), tmp_path, "watched", handle_signals=False)  # type: ignore[arg-type]
    assert result.metrics["ate_rmse_m"] < 0.01  # evaluated: the ground truth was read
    stages = {"frontend", "backend", "loop", "mapping", "pose"}
    assert not [r for r in readers if r[0].split(".")[1] in stages], readers
    # measured: process, _process_and_write, evaluated (loopmodel.pipeline), evaluate, mesh_errors
    assert len(readers) <= 6, sorted(readers)
    assert ("loopmodel.pipeline", "process") in readers
