"""The one formatter of tables and reports (issue 35 item 1) and the run summary (item 2)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from loopmodel.cli.summary import run_summary_rows
from loopmodel.display import MM, Formatter, M, label, length_unit, num, quantity

# metrics.json of a 60-frame simulated orbit scan (loopmodel simulate scan --preset orbit --frames 60)
ORBIT_METRICS = {
    "frames": 60,
    "lost_frames": 0,
    "keyframes": 27,
    "landmarks": 3705,
    "fps": 3.32873068908772,
    "backend": "isam2",
    "backend_ms_median": 75.69901300001902,
    "loop_closure_count": 1,
    "relocalization_count": 0,
    "loop_candidates_rejected": 44,
    "ate_rmse_m_online": 0.012212588787329896,
    "ate_rmse_m": 0.0023082181861411497,
    "drift_pct": 0.03371082728975339,
    "mesh_vertices": 48469,
    "mesh_err_after_mm": 1.9752982689234637,  # the run's mesh (keys of the evaluation after the run, issue 32)
    "mesh_err_after_mm_p95": 3.458851494360715,
    "mesh_completeness_after": 0.290345,
    "mesh_err_gt_mm": 0.61,  # the reference mesh (stripes on ground-truth poses): not the product's error
}


def test_num_has_four_significant_digits_and_no_none() -> None:
    assert num(2.88609) == "2.886"
    assert num(1.01036) == "1.010"
    assert num(53.9056) == "53.91"
    assert num(469.367) == "469.4"
    assert num(0.0004126) == "0.0004126"
    assert num(99022.0) == "99022"
    assert num(99022) == "99022"
    assert num(None) == "–"
    assert num(float("nan")) == "–"
    assert num(0.0) == "0"
    assert num(2.11e-23) == "2.110e-23"
    assert num(-12.345) == "-12.35"
    assert num(True) == "yes"


def test_unit_chosen_from_the_scale() -> None:
    assert length_unit(2.04) is MM  # the simulated orbit scan
    assert length_unit(59.9) is M  # the KITTI clip
    assert length_unit(None) is M
    close = Formatter.for_positions(np.array([[0.0, 0, 0], [1.0, 1.0, 0.5]]))
    assert close.header("ate_rmse_m") == "ATE RMSE [mm]"
    assert close.value("ate_rmse_m", 0.0004126) == "0.4126"
    assert close.value("mesh_err_gt_mm", 1.9753) == "1.975"  # stored in mm, shown in mm
    far = Formatter.for_scale(60.0)
    assert far.header("ate_rmse_m") == "ATE RMSE [m]"
    assert far.value("mesh_err_gt_mm", 1.9753) == "0.001975"
    assert far.value("mesh_completeness_gt", 0.290345) == "29.03"
    assert far.header("mesh_completeness_gt") == "mesh completeness with true poses [%]"  # the reference mesh


def test_labels_and_quantities_from_the_key() -> None:
    assert quantity("mesh_err_gt_mm_p95") == "length_mm"
    assert quantity("kitti_r_err_deg_per_100m") == "deg_per_100m"
    assert quantity("backend_ms_median") == "ms"
    assert quantity("mesh_vertices") == "count"
    assert label("mesh_completeness_swept_before") == "mesh completeness of the swept truth before closing"
    assert "_" not in label("klt_inliers")


def test_run_summary_shows_the_product(tmp_path: Path) -> None:
    (tmp_path / "mesh.ply").write_bytes(b"ply\n")
    rrd = tmp_path / "run.rrd"
    rows = run_summary_rows(ORBIT_METRICS, tmp_path, Formatter.for_scale(2.04), rrd)
    assert rows == [
        ("frames", "60 (0 lost)"),
        ("keyframes", "27"),
        ("landmarks", "3705"),
        ("speed [fps]", "3.329"),
        ("back end", "isam2, 75.70 ms per keyframe (median)"),
        ("loops / relocalizations", "1 / 0 (44 candidates rejected)"),
        ("ATE RMSE online [mm]", "12.21"),
        ("ATE RMSE final [mm]", "2.308"),
        ("drift final [%]", "0.03371"),
        ("mesh", f"{tmp_path / 'mesh.ply'} (48469 vertices)"),
        ("mesh error vs truth [mm]", "mean 1.975, p95 3.459"),
        ("mesh completeness vs truth [%]", "29.03"),
        ("rerun recording", f"{rrd} (open with: rerun {rrd})"),
    ]


def test_localize_summary_has_no_empty_rows() -> None:
    m = {
        "frames": 40,
        "lost_frames": 0,
        "keyframes": 12,
        "landmarks": 0,
        "fps": 9.1234,
        "backend": "none",
        "backend_ms_median": 0.0400195,
        "localized_frames": 0,
        "map_first_localized_frame": None,
        "map_localized": False,
    }
    text = "\n".join(f"{a} {b}" for a, b in run_summary_rows(m, None, Formatter()))
    assert "None" not in text
    assert "landmarks" not in text
    assert "0.04" not in text
    assert "localized in the map 0 frames\n" in text


def test_batch_summary_per_sequence_in_its_unit() -> None:
    """Variants compared within each sequence (mm for a scan, m for a drive), mesh columns kept."""
    from loopmodel.batch.summary import summary_markdown

    head = [
        "task",
        "sequence",
        "variant",
        "status",
        "error",
        "task_s",
        "run_s",
        "peak_rss_mib",
        "ate_rmse_m",
        "rpe_frames_rmse_m",
        "ground_truth_extent_m",
        "mesh_err_after_mm",
    ]
    rows = [
        ["o1", "orbit", "backend.kind=isam2", "done", None, 35.04, 25.6924, 812.3, 0.0023082, 0.00196, 2.04, 2.5488],
        ["o2", "orbit", "backend.kind=none", "done", None, 30.1, 20.2, 700.0, 0.0122126, 0.00227, 2.04, 5.9412],
        ["k1", "kitti", "backend.kind=isam2", "done", None, 80.0, 70.0, 900.0, 0.1042, 0.0301, 59.86, None],
        ["k2", "kitti", "backend.kind=none", "done", None, 60.0, 50.0, 850.0, 0.0998, 0.0352, 59.86, None],
    ]
    md = summary_markdown(head, rows, plots=False)
    orbit = md.split("## orbit (lengths in mm)")[1].split("##")[0]
    kitti = md.split("## kitti (lengths in m)")[1].split("##")[0]
    assert "| 1 | backend.kind=isam2 | done | 2.308 | 1.960 |" in orbit
    assert "mesh error after closing, mean [mm]" in orbit and "| 2.549 |" in orbit
    assert "mesh error" not in kitti  # no empty mesh column for a drive
    assert "| 1 | backend.kind=none | done | 0.09980 |" in kitti
    assert "run time [s]" in orbit and "| 25.69 | 35.04 |" in orbit
    assert "None" not in md and "median |" not in md
    across = md.split("## Variants across sequences")[1]
    assert "| backend.kind=isam2 | 1.500 | 1.022 | 1 | 2 |" in across  # mean rank; median of 1.0 and 1.044


def test_info_prints_labels_and_units(shared_data: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from loopmodel.cli import main

    assert main(["info", str(shared_data / "kitti_clip")]) == 0
    out = capsys.readouterr().out
    assert "fx 707.1 px" in out and "baseline 0.5372 m" in out and "duration [s]" in out
    assert "fx_px" not in out and "=" not in out and "True" not in out


def test_info_of_a_close_range_sequence_in_mm(capsys: pytest.CaptureFixture[str]) -> None:
    """The unit from the sequence's scale (its ground truth spans 0.14 m): the baseline in mm, as in a run's summary."""
    from loopmodel.cli import main

    root = Path(__file__).resolve().parents[1]
    assert main(["info", str(root / "datasets" / "tiny_kitti")]) == 0
    out = capsys.readouterr().out
    assert "baseline 60.00 mm" in out and "0.06" not in out  # was "baseline 0.06000 m"


def test_key_values_one_spelling() -> None:
    from loopmodel.display import describe_rows, key_values

    cal = {"fx_px": 469.367, "baseline_m": 0.0599392, "image_size": [640, 480], "rectified": True}
    assert key_values(cal, Formatter(MM)) == "fx 469.4 px, baseline 59.94 mm, image size 640 x 480, rectified yes"
    rows = dict(
        describe_rows({"keyframe_extent_m": [1.4324301096263707, 0.414, 1.387], "size_mib": 7.8649}, Formatter(MM))
    )
    assert rows == {"keyframe extent [mm]": "1432 x 414.0 x 1387", "size [MiB]": "7.865"}


def test_trajectory_files_write_the_origin_as_zero(tmp_path: Path) -> None:
    """The run's first pose (the world's origin) reads 0.0, not 2.11e-23 (issue 35 item 12)."""
    from loopmodel.io.trajectory_io import read_trajectory, write_trajectory
    from loopmodel.types import Trajectory

    T = np.repeat(np.eye(4)[None], 2, axis=0)
    T[0, :3, 3] = [2.11e-23, -3.6e-24, 6.2e-23]
    T[1, :3, 3] = [0.123456789012345, 1e-9, 0.0]
    write_trajectory(tmp_path / "t.tum", Trajectory(np.array([0, 10**8], dtype=np.int64), T))
    first = (tmp_path / "t.tum").read_text().splitlines()[1].split()
    assert first[1:4] == ["0.0", "0.0", "0.0"] and "e-2" not in " ".join(first)
    back = read_trajectory(tmp_path / "t.tum")
    assert back.world_from_cam[1, 0, 3] == 0.123456789012345 and back.world_from_cam[1, 1, 3] == 1e-9  # full precision


def test_map_info_in_units_with_labels(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``map info``: extent in the map's unit, labels not keys, no 16-digit floats (issue 35 item 1)."""
    import re

    import loopmodel
    from loopmodel.cli import main

    root = Path(__file__).resolve().parents[1]
    loopmodel.run(root / "datasets" / "tiny_kitti", {"backend": {"kind": "none"}}, tmp_path, name="m")
    capsys.readouterr()
    assert main(["map", "info", str(tmp_path / "m")]) == 0
    out = capsys.readouterr().out
    assert "keyframe extent [mm]" in out and "session 0: " in out and "size [MiB]" in out
    assert "keyframe_extent_m" not in out and "fx_px" not in out
    for x in re.findall(r"(?<![\w/.-])\d+\.\d+(?![\w/])", out):  # numbers, not parts of paths
        assert len(x.replace(".", "").lstrip("0")) <= 4, x  # 4 significant digits at most
