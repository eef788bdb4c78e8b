"""Benchmark ``turntable``: the real laser-line turntable scan and the real calibrations.

* ``step_angle_err_deg_rms``: marker-based table steps against the motor's 1.125 deg,
  ``before`` (markers only) and ``after`` the loop-closed pose graph (whose motor factors have
  an assumed 0.05 deg sigma, so ``after`` leans on that prior);
* ``loop_closure_err_deg``: accumulated marker steps over all 320 steps minus 360 deg;
* ``table_plane_residual_mm``: the table-top laser points of the chosen plane against the
  markers' table plane (and every candidate's, under ``plane_candidates``);
* ``mesh_points``, ``mesh_err_self_mm`` (surfaces seen 180 deg apart), ``azimuth_coverage``;
* ``marker_pose_scatter``: single-marker pose scatter against the Cramér–Rao bound of the
  ``bound`` tool for the same marker, distance and measured corner noise;
* ``stereo_calib_rms_px`` (ours, joint), ``stereo_calib_rms_px_reference`` (plain OpenCV on the
  same corners), ``stereo_epipolar_err_px`` (RMS after rectification) on ``stereo_calib/``;
* ``laser_plane_rms_mm`` on the chessboard images ``laser_calibration/bcap*.jpg``.

``--quick`` scans every 4th frame (step 4.5 deg) and skips nothing else.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

from shared_data import SHARED_DATA

DATA = SHARED_DATA
LAYOUT = Path(__file__).resolve().parents[1] / "datasets" / "layouts" / "turntable_laser.yaml"


def run(quick: bool) -> dict:
    from loopmodel.calibration.laser import calibrate_laser_plane, read_laser_planes_json
    from loopmodel.calibration.stereo import calibrate_stereo, pair_images
    from loopmodel.io.camera_yaml import read_intrinsics
    from loopmodel.turntable.reader import open_turntable
    from loopmodel.turntable.run import scan_turntable

    data = DATA.resolve()
    out: dict = {}
    t0 = time.perf_counter()
    sc = data / "stereo_calib"
    st = calibrate_stereo(
        pair_images(sorted(sc.glob("left[0-9]*.jpg")), sorted(sc.glob("right[0-9]*.jpg"))), (9, 6), 1.0
    )
    out["stereo_calib_rms_px"] = {"left": st.rms_left_px, "right": st.rms_right_px, "stereo": st.rms_stereo_px}
    out["stereo_calib_rms_px_reference"] = {
        "left": st.reference_rms_left_px,
        "right": st.reference_rms_right_px,
        "stereo": st.reference_rms_stereo_px,
    }
    out["stereo_epipolar_err_px"] = st.epipolar_err_px_rms
    out["stereo_epipolar_err_px_max"] = st.epipolar_err_px_max
    out["stereo_views"] = len(st.views)
    t1 = time.perf_counter()
    tl = data / "turntable_laser"
    K, dist, size = read_intrinsics(tl / "calibration3.yaml")
    lp = calibrate_laser_plane(sorted((tl / "laser_calibration").glob("bcap*.jpg")), K, dist, (8, 6), 0.04, size)
    out["laser_plane_rms_mm"] = lp.rms_mm
    out["laser_plane_views"] = len(lp.views)
    out["laser_plane_line_angle_spread_deg"] = lp.line_angle_spread_deg
    out["laser_plane_vs_saved"] = lp.compare(read_laser_planes_json(tl / "laser_planes.json"))[0]
    t2 = time.perf_counter()
    scan = open_turntable(tl, LAYOUT)
    if quick:
        scan.frame_paths = scan.frame_paths[::4]
        scan.step_deg *= 4
    res = scan_turntable(scan)
    f = res.figures
    out["step_angle_err_deg_rms"] = {
        "before": f["step_angle_err_deg_rms_before"],
        "after": f["step_angle_err_deg_rms_after"],
    }
    for k in ("loop_closure_err_deg", "table_plane_residual_mm", "mesh_points", "mesh_err_self_mm", "azimuth_coverage"):
        out[k] = f[k]
    out["laser_plane"] = f["laser_plane"]
    # inf (no table-top ray meets that plane in front of the camera) as null: strict JSON
    out["plane_candidates"] = {
        k: (v["table_residual_mm"] if math.isfinite(v["table_residual_mm"]) else None)
        for k, v in f["plane_candidates"].items()
    }
    out["marker_pose_scatter"] = f["marker_pose_scatter"]
    out["frames"] = f["frames"]
    out["time_s"] = {"stereo": t1 - t0, "laser_plane": t2 - t1, "turntable": time.perf_counter() - t2}
    return out
