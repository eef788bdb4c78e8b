"""The one formatter of tables and reports (issue 35 item 1) and the run summary (item 2)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

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
    "mesh_err_gt_mm": 1.9752982689234637,
    "mesh_err_gt_mm_p95": 3.458851494360715,
    "mesh_completeness_gt": 0.290345,
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
    assert far.header("mesh_completeness_gt") == "mesh completeness vs truth [%]"


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
