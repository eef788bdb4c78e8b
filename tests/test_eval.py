"""Tests of loopmodel.eval: alignment, association, agreement with evo, reports, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from loopmodel.cli import main
from loopmodel.config import EvalConfig
from loopmodel.eval import report as rep
from loopmodel.eval.trajectory_metrics import align, associate, evaluate_pair
from loopmodel.geometry.se3 import make_pose, so3_exp
from loopmodel.io.trajectory_io import write_trajectory
from loopmodel.types import Trajectory


def _wiggly_path(n: int, rng: np.random.Generator) -> np.ndarray:
    """N x 4 x 4 poses along a 3-D loop (radius 2 m) with rotations varying along it."""
    s = np.linspace(0, 2 * np.pi, n, endpoint=False)
    pos = np.stack([2 * np.cos(s), 2 * np.sin(s), 0.3 * np.sin(3 * s)], axis=1)
    pos += 0.01 * rng.standard_normal(pos.shape)
    return np.stack([make_pose(so3_exp([0.1 * np.sin(a), 0.2 * np.cos(a), a]), p) for a, p in zip(s, pos, strict=True)])


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    return so3_exp(rng.uniform(-np.pi, np.pi, 3) / np.sqrt(3))


@pytest.mark.parametrize("mode", ["se3", "sim3"])
def test_alignment_recovers_random_transform(mode: str, rng: np.random.Generator) -> None:
    ref = _wiggly_path(200, rng)
    R, t = _random_rotation(rng), rng.uniform(-50, 50, 3)
    s = float(rng.uniform(0.2, 5.0)) if mode == "sim3" else 1.0
    # estimate = the reference seen in another frame: p_est = (R^T (p_ref - t)) / s
    est = ref.copy()
    est[:, :3, :3] = np.einsum("ji,njk->nik", R, ref[:, :3, :3])
    est[:, :3, 3] = ((ref[:, :3, 3] - t) @ R) / s
    al = align(ref, est, mode)
    np.testing.assert_allclose(al.rotation, R, atol=1e-10)
    np.testing.assert_allclose(al.translation_m, t, atol=1e-8)
    assert al.scale == pytest.approx(s, rel=1e-10)
    aligned = al.apply(est)
    np.testing.assert_allclose(aligned, ref, atol=1e-8)
    # with first N only, still exact (noise free), and origin alignment is exact for SE(3)
    al_n = align(ref, est, mode, first_n=10)
    assert al_n.poses_used == 10
    np.testing.assert_allclose(al_n.apply(est)[:, :3, 3], ref[:, :3, 3], atol=1e-7)
    if mode == "se3":
        np.testing.assert_allclose(align(ref, est, "origin").apply(est), ref, atol=1e-8)


def test_alignment_with_noise_matches_brute_force(rng: np.random.Generator) -> None:
    """Noisy SE(3) alignment.

    The Umeyama solution is a least-squares minimum (no small perturbation lowers the squared
    error).
    """
    ref = _wiggly_path(100, rng)
    est = ref.copy()
    est[:, :3, 3] += 0.05 * rng.standard_normal((100, 3))
    al = align(ref, est, "se3")

    def sse(R: np.ndarray, t: np.ndarray) -> float:
        return float(np.sum((ref[:, :3, 3] - est[:, :3, 3] @ R.T - t) ** 2))

    best = sse(al.rotation, al.translation_m)
    for _ in range(50):
        dR = so3_exp(1e-3 * rng.standard_normal(3))
        assert sse(dR @ al.rotation, al.translation_m + 1e-3 * rng.standard_normal(3)) >= best


def test_association_missing_and_jittered(rng: np.random.Generator) -> None:
    t_ref = np.arange(1000, dtype=np.int64) * 10_000_000 + 1_700_000_000_000_000_000  # 100 Hz
    keep = np.sort(rng.choice(1000, 600, replace=False))  # 40 % of the poses missing
    jitter = rng.integers(-2_000_000, 2_000_001, keep.size)  # +-2 ms
    far = np.sort(rng.choice(keep.size, 20, replace=False))
    jitter[far] = rng.integers(4_200_000, 5_800_000, 20)  # > 3 ms from every reference pose
    t_est = t_ref[keep] + jitter
    order = np.argsort(t_est, kind="stable")
    t_est, truth, is_far = t_est[order], keep[order], np.isin(np.arange(keep.size), far)[order]
    i_ref, i_est = associate(t_ref, t_est, 3_000_000)
    # brute force: nearest reference time within 3 ms
    expect_ref, expect_est = [], []
    for j, t in enumerate(t_est):
        k = int(np.argmin(np.abs(t_ref - t)))
        if abs(t_ref[k] - t) <= 3_000_000:
            expect_ref.append(k)
            expect_est.append(j)
    np.testing.assert_array_equal(i_ref, expect_ref)
    np.testing.assert_array_equal(i_est, expect_est)
    # every jittered pose lands on its own reference pose; the far ones are dropped
    np.testing.assert_array_equal(i_est, np.flatnonzero(~is_far))
    np.testing.assert_array_equal(i_ref, truth[~is_far])
    # a shorter reference is the side that is kept whole
    i_ref2, i_est2 = associate(t_ref[::50], t_ref, 1)
    np.testing.assert_array_equal(i_ref2, np.arange(20))
    np.testing.assert_array_equal(i_est2, np.arange(0, 1000, 50))


EVO_CASES = [
    ("KITTI_00_gt.txt", "KITTI_00_ORB.txt", "kitti", 100.0),
    ("V102_groundtruth.csv", "V102.txt", "euroc", 1.0),
    ("fr2_desk_groundtruth.txt", "fr2_desk_ORB.txt", "tum", 0.5),
]


@pytest.mark.parametrize("gt_name, est_name, kind, delta_m", EVO_CASES)
def test_agreement_with_evo(shared_data: Path, gt_name: str, est_name: str, kind: str, delta_m: float) -> None:
    import copy

    evo_fi = pytest.importorskip("evo.tools.file_interface")
    from evo.core import metrics as em
    from evo.core import sync

    folder = shared_data / "trajectories"
    gt_path, est_path = folder / gt_name, folder / est_name
    readers = {
        "kitti": (evo_fi.read_kitti_poses_file, evo_fi.read_kitti_poses_file),
        "euroc": (evo_fi.read_euroc_csv_trajectory, evo_fi.read_tum_trajectory_file),
        "tum": (evo_fi.read_tum_trajectory_file, evo_fi.read_tum_trajectory_file),
    }[kind]
    ref0, est0 = readers[0](str(gt_path)), readers[1](str(est_path))
    if kind != "kitti":
        ref0, est0 = sync.associate_trajectories(ref0, est0, max_diff=0.01)
    gt = rep.load_trajectory_file(gt_path)
    est = rep.load_trajectory_file(est_path)
    stats = em.StatisticsType
    for mode, first_n in (
        ("se3", None),
        ("sim3", None),
        ("se3", 100),
        ("origin", None),
        ("none", None),
    ):
        e = copy.deepcopy(est0)
        if mode in ("se3", "sim3"):
            e.align(ref0, correct_scale=(mode == "sim3"), n=first_n or -1)
        elif mode == "origin":
            e.align_origin(ref0)
        ape = em.APE(em.PoseRelation.translation_part)
        ape.process_data((ref0, e))
        rpe1 = em.RPE(em.PoseRelation.translation_part, 1, em.Unit.frames)
        rpe1.process_data((ref0, e))
        rped = em.RPE(em.PoseRelation.translation_part, delta_m, em.Unit.meters)
        rped.process_data((ref0, e))
        ours = evaluate_pair(
            gt.traj.timestamps_ns,
            gt.traj.world_from_cam,
            est.traj.timestamps_ns,
            est.traj.world_from_cam,
            max_dt_ns=10_000_000,
            align_mode=mode,
            first_n=first_n,
            rpe_delta_m=delta_m,
        ).metrics
        assert ours["matched"] == ref0.num_poses
        for key in ("rmse", "mean", "median", "max"):
            want = ape.get_statistic(getattr(stats, key))
            assert ours["ate_m"][key] == pytest.approx(want, rel=1e-6), (mode, "ATE", key)
        for key in ("rmse", "mean", "max"):
            assert ours["rpe_frames"]["trans_m"][key] == pytest.approx(
                rpe1.get_statistic(getattr(stats, key)), rel=1e-6
            ), (mode, "RPE frames", key)
            assert ours["rpe_distance"]["trans_m"][key] == pytest.approx(
                rped.get_statistic(getattr(stats, key)), rel=1e-6
            ), (mode, "RPE distance", key)
        assert ours["rpe_distance"]["trans_m"]["count"] == len(rped.error)


# ----------------------------------------------------------------- results folders


def _make_run(
    folder: Path, rng: np.random.Generator, closures: list[dict] | None, drift: float = 0.02
) -> tuple[Trajectory, Trajectory, Trajectory]:
    """A results folder.

    Ground truth (returned), an online trajectory that drifts, a final one close to the ground
    truth, keyframes every 5th final pose, metrics.json.
    """
    n = 300
    t = 1_000_000_000_000 + np.arange(n, dtype=np.int64) * 50_000_000  # 20 Hz
    gt_T = _wiggly_path(n, rng)
    online_T = gt_T.copy()
    online_T[:, :3, 3] += np.cumsum(drift * rng.standard_normal((n, 3)), axis=0) * 0.2 + np.linspace(0, 1, n)[
        :, None
    ] * [0.3, 0.0, 0.0]
    final_T = gt_T.copy()
    final_T[:, :3, 3] += 0.005 * rng.standard_normal((n, 3))
    gt, online, final = Trajectory(t, gt_T), Trajectory(t, online_T), Trajectory(t, final_T)
    folder.mkdir(parents=True, exist_ok=True)
    write_trajectory(folder / "trajectory_online.tum", online)
    write_trajectory(folder / "trajectory_final.tum", final)
    write_trajectory(folder / "keyframes.tum", final.slice(slice(0, None, 5)))
    metrics: dict = {"frames": n, "mesh_err_before_mm": 3.5, "mesh_err_after_mm": 1.2}
    if closures is not None:
        metrics["loop_closures"] = closures
    (folder / "metrics.json").write_text(json.dumps(metrics))
    return gt, online, final


def test_report_without_loop_closure(tmp_path: Path, rng: np.random.Generator) -> None:
    gt, _, final = _make_run(tmp_path / "run", rng, closures=[])
    write_trajectory(tmp_path / "gt.tum", gt)
    out = tmp_path / "out"
    assert main(["eval", str(tmp_path / "run"), "--gt", str(tmp_path / "gt.tum"), "--out", str(out)]) == 0
    md = (out / "report.md").read_text()
    assert "No loop closure was recorded in this run" in md
    html = (out / "report.html").read_text()
    assert "No loop closure was recorded in this run" in html
    assert html.count("data:image/png;base64,") == 5 and 'src="error_' not in html
    for name in (rep.PLOT_TOP, rep.PLOT_ERROR_TIME, rep.PLOT_ERROR_COLORED, rep.PLOT_XYZ_RPY, rep.PLOT_RPE_TIME):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    m = json.loads((out / "metrics.json").read_text())
    # independent ATE: Kabsch by hand on the (identical-time) positions
    P, Q = final.positions_m, gt.positions_m
    H = (P - P.mean(0)).T @ (Q - Q.mean(0))
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    err = np.linalg.norm(Q - (P - P.mean(0)) @ R.T - Q.mean(0), axis=1)
    assert m["ate_rmse_m"] == pytest.approx(float(np.sqrt(np.mean(err**2))), rel=1e-9)
    assert m["loop_closure_count"] == 0
    assert m["mesh"] == {"mesh_err_before_mm": 3.5, "mesh_err_after_mm": 1.2}
    assert set(m["trajectories"]) == {"final", "online", "keyframes"}
    assert m["trajectories"]["keyframes"]["matched"] == 60


def test_report_with_loop_closures_and_comparison(tmp_path: Path, rng: np.random.Generator) -> None:
    gt, online, final = _make_run(
        tmp_path / "a",
        rng,
        closures=[
            {
                "timestamp_ns": int(1_000_000_000_000 + 250 * 50_000_000),
                "match_keyframe": 2,
                "inliers": 87,
                "correction_m": 0.31,
            },
            {"query_frame": 290, "match_frame": 5, "inliers": 40},
        ],
    )
    _make_run(tmp_path / "b", rng, closures=None, drift=0.05)
    write_trajectory(tmp_path / "gt.csv", gt)  # EuRoC format ground truth
    out = tmp_path / "cmp"
    assert (
        main(
            [
                "eval",
                str(tmp_path / "a"),
                str(tmp_path / "b"),
                "--gt",
                str(tmp_path / "gt.csv"),
                "--out",
                str(out),
                "--no-plots",
            ]
        )
        == 0
    )
    m = json.loads((out / "a" / "metrics.json").read_text())
    assert m["loop_closure_count"] == 2
    c0, c1 = m["loop_closures"]
    assert c0["match_time_ns"] == int(1_000_000_000_000 + 10 * 50_000_000)
    assert c1["time_ns"] == int(1_000_000_000_000 + 290 * 50_000_000)
    want = np.linalg.norm(online.world_from_cam[250, :3, 3] - final.world_from_cam[250, :3, 3])
    assert c0["correction_m"] == pytest.approx(want, rel=1e-12)
    assert c0["recorded"]["inliers"] == 87
    ba = {r["key"]: r for r in m["before_after"]}
    assert ba["ate_m.rmse"]["after"] < ba["ate_m.rmse"]["before"]
    assert ba["mesh.mesh_err_before_mm"]["after"] == 1.2
    md = (out / "a" / "report.md").read_text()
    assert "2 loop closure(s)" in md and "| 87" in md.replace("87.0000", "87")
    mb = json.loads((out / "b" / "metrics.json").read_text())
    assert mb["loop_closures_recorded"] is False
    lines = (out / "comparison.csv").read_text().splitlines()
    assert lines[0].startswith("run,matched,ate_rmse_m,") and len(lines) == 3
    assert lines[1].split(",")[2] == repr(m["ate_rmse_m"])
    assert "| a |" in (out / "comparison.md").read_text()


def test_ref_est_mode_and_sim3(tmp_path: Path, rng: np.random.Generator) -> None:
    """--ref/--est with Sim(3): an estimate in another frame and scale has zero error."""
    n = 120
    t = np.arange(n, dtype=np.int64) * 100_000_000
    ref_T = _wiggly_path(n, rng)
    R, tr, s = _random_rotation(rng), np.array([3.0, -1.0, 2.0]), 0.37
    est_T = ref_T.copy()
    est_T[:, :3, :3] = np.einsum("ji,njk->nik", R, ref_T[:, :3, :3])
    est_T[:, :3, 3] = ((ref_T[:, :3, 3] - tr) @ R) / s
    write_trajectory(tmp_path / "ref.tum", Trajectory(t, ref_T))
    write_trajectory(tmp_path / "est.tum", Trajectory(t + 3_000_000, est_T))  # 3 ms late
    out = tmp_path / "o"
    assert (
        main(
            [
                "eval",
                "--ref",
                str(tmp_path / "ref.tum"),
                "--est",
                str(tmp_path / "est.tum"),
                "--align",
                "sim3",
                "--max-dt-ms",
                "5",
                "--out",
                str(out),
                "--no-plots",
            ]
        )
        == 0
    )
    m = json.loads((out / "metrics.json").read_text())
    fin = m["trajectories"]["final"]
    assert fin["matched"] == n and fin["alignment"]["scale"] == pytest.approx(s, rel=1e-9)
    assert fin["ate_m"]["max"] < 1e-8 and fin["rpe_frames"]["trans_m"]["max"] < 1e-8
    assert m["ate_rmse_m"] > 0.1  # SE(3) alignment cannot undo the scale
    assert "no before/after" in (out / "report.md").read_text()


# ----------------------------------------------------------------- bad input


def _one_line_error(capsys: pytest.CaptureFixture[str], *words: str) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err, err
    for w in words:
        assert w in err, err
    return err


def test_bad_input_exit_2(tmp_path: Path, rng: np.random.Generator, capsys: pytest.CaptureFixture[str]) -> None:
    T = _wiggly_path(50, rng)
    t = np.arange(50, dtype=np.int64) * 100_000_000
    write_trajectory(tmp_path / "ref.tum", Trajectory(t, T))
    write_trajectory(tmp_path / "late.tum", Trajectory(t + 3600 * 10**9, T))
    write_trajectory(tmp_path / "one.tum", Trajectory(t[:1], T[:1]))
    write_trajectory(tmp_path / "ref.kitti", Trajectory(t, T), "kitti")
    capsys.readouterr()
    ref = str(tmp_path / "ref.tum")
    # no overlap in time
    assert (
        main(
            [
                "eval",
                "--ref",
                ref,
                "--est",
                str(tmp_path / "late.tum"),
                "--out",
                str(tmp_path / "x"),
            ]
        )
        == 2
    )
    _one_line_error(capsys, "no poses overlap in time", "late.tum")
    # a trajectory with one pose
    assert main(["eval", "--ref", ref, "--est", str(tmp_path / "one.tum"), "--out", str(tmp_path / "x")]) == 2
    _one_line_error(capsys, "one.tum", "1 pose")
    # unequal formats: KITTI (no times) against TUM
    assert (
        main(
            [
                "eval",
                "--ref",
                str(tmp_path / "ref.kitti"),
                "--est",
                ref,
                "--out",
                str(tmp_path / "x"),
            ]
        )
        == 2
    )
    _one_line_error(capsys, "unequal formats", "ref.kitti")
    # results folder without trajectories, missing --est, bad --align
    (tmp_path / "empty").mkdir()
    assert main(["eval", str(tmp_path / "empty"), "--gt", ref]) == 2
    _one_line_error(capsys, "trajectory_final.tum")
    assert main(["eval", "--ref", ref]) == 2
    _one_line_error(capsys, "--est")
    assert main(["eval", "--ref", ref, "--est", ref, "--align", "affine"]) == 2
    _one_line_error(capsys, "--align")
    assert not (tmp_path / "x").exists()


def test_eval_config_defaults() -> None:
    cfg = EvalConfig()
    assert cfg.align == "se3" and cfg.max_dt_ms == 10.0 and cfg.kitti_segment_lengths_m[0] == 100.0


def test_ground_truth_from_sequence_folder(shared_data: Path, tmp_path: Path, rng: np.random.Generator) -> None:
    """``--gt SEQ``.

    The ground truth of a KITTI folder (poses.txt, 10 Hz) read by open_sequence; a noisy copy in a
    results folder is evaluated against it.
    """
    from loopmodel.io.trajectory_io import read_trajectory

    clip = shared_data / "kitti_clip"
    gt = read_trajectory(clip / "poses.txt", "kitti")
    noisy = gt.world_from_cam.copy()
    noisy[:, :3, 3] += 0.1 * rng.standard_normal((len(gt), 3))
    run = tmp_path / "clip_run"
    write_trajectory(run / "trajectory_final.tum", Trajectory(gt.timestamps_ns, noisy))
    out = tmp_path / "o"
    assert main(["eval", str(run), "--gt", str(clip), "--out", str(out), "--no-plots"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["trajectories"]["final"]["matched"] == len(gt) == 51
    # independent: evo on the same poses
    evo_traj = pytest.importorskip("evo.core.trajectory")
    from evo.core import metrics as em

    ref = evo_traj.PosePath3D(poses_se3=list(gt.world_from_cam))
    est = evo_traj.PosePath3D(poses_se3=list(noisy))
    est.align(ref)
    ape = em.APE(em.PoseRelation.translation_part)
    ape.process_data((ref, est))
    assert m["ate_rmse_m"] == pytest.approx(ape.get_statistic(em.StatisticsType.rmse), rel=1e-9)
    assert m["before_after"] is None  # no online trajectory in this folder


def test_pipeline_loop_events_are_read_as_closures(tmp_path: Path) -> None:
    """The pipeline's ``loop_events`` (type loop / relocalization) count as loop closures."""
    import json

    from loopmodel.eval.report import load_run
    from loopmodel.geometry.se3 import se3_exp
    from loopmodel.io.trajectory_io import write_trajectory
    from loopmodel.types import Trajectory

    traj = Trajectory(np.arange(5) * 100_000_000, np.array([se3_exp([0.1 * i, 0, 0, 0, 0, 0]) for i in range(5)]))
    write_trajectory(tmp_path / "trajectory_online.tum", traj)
    write_trajectory(tmp_path / "trajectory_final.tum", traj)
    events = [
        {"type": "loop", "frame": 4, "keyframe": 2, "match_frame": 0},
        {"type": "relocalization", "frame": 3, "keyframe": 1},
    ]
    (tmp_path / "metrics.json").write_text(json.dumps({"loop_events": events}))
    run = load_run(tmp_path)
    assert run.loop_closures_recorded and len(run.loop_closures) == 1


def test_step_scale_helpers_against_a_hand_computation() -> None:
    """Per-step scale and its growth on a 5-pose path whose steps are known by hand."""
    from loopmodel.eval.trajectory_metrics import scale_figures, step_scale_last_over_first, step_scales

    ref = np.tile(np.eye(4), (5, 1, 1))
    ref[:, 0, 3] = [0.0, 1.0, 2.0, 3.0, 4.0]  # four 1 m steps along x
    est = np.tile(np.eye(4), (5, 1, 1))
    # steps of 1.0, 1.1 (along y: direction does not matter), 1.2 and 1.5 m
    est[:, :3, 3] = [[0, 0, 0], [1.0, 0, 0], [1.0, 1.1, 0], [2.2, 1.1, 0], [2.2, 1.1, 1.5]]
    np.testing.assert_allclose(step_scales(ref, est), [1.0, 1.1, 1.2, 1.5])
    # quarter of 4 steps = 1 step: 1.5 / 1.0; half (2 steps each): (1.2 + 1.5) / 2 / ((1.0 + 1.1) / 2)
    assert step_scale_last_over_first(ref, est) == pytest.approx(1.5)
    assert step_scale_last_over_first(ref, est, 0.5) == pytest.approx(2.7 / 2.1)
    # a similarity of the estimate (scale 3, any rotation) leaves the growth unchanged
    est3 = est.copy()
    est3[:, :3, 3] = 3.0 * est[:, :3, 3] @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]).T
    assert step_scale_last_over_first(ref, est3) == pytest.approx(1.5)
    # a uniformly scaled estimate: Sim(3) scale (truth / estimate) 1 / 2, no growth
    t = np.arange(5, dtype=np.int64) * 100_000_000
    curve = np.tile(np.eye(4), (5, 1, 1))
    curve[:, :3, 3] = [[0, 0, 0], [1, 0.2, 0], [2, 0.1, 0.3], [3, 0.5, 0.1], [4, 0.0, 0.4]]
    half = curve.copy()
    half[:, :3, 3] *= 2.0
    fig = scale_figures(t, curve, t, half)
    assert fig["sim3_scale"] == pytest.approx(0.5)
    assert fig["step_scale_last_over_first"] == pytest.approx(1.0)
