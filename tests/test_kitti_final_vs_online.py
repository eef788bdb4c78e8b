"""On the real KITTI clip the back end's final trajectory is no worse than the online one (issue 26).

Errors computed here in plain numpy against the clip's ``poses.txt``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from loopmodel.config import load_config
from loopmodel.io.sequence import open_sequence
from loopmodel.pipeline import run_pipeline

ROOT = Path(__file__).resolve().parents[1]


def _ate_and_drift(est: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    """ATE RMSE (m) after the SE(3) Umeyama alignment of positions.

    Drift (% of the path) of the last position with the first poses aligned.
    """
    a, b = est[:, :3, 3], gt[:, :3, 3]
    ma, mb = a.mean(0), b.mean(0)
    U, _, Vt = np.linalg.svd((b - mb).T @ (a - ma))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    ate = float(np.sqrt(np.mean(np.sum((a @ R.T + (mb - R @ ma) - b) ** 2, axis=1))))
    last = gt[0] @ np.linalg.inv(est[0]) @ est[-1]
    path = float(np.linalg.norm(np.diff(b, axis=0), axis=1).sum())
    return ate, float(np.linalg.norm(last[:3, 3] - b[-1])) / path * 100.0


@pytest.mark.slow
def test_final_trajectory_no_worse_than_online_on_kitti(shared_data: Path, tmp_path: Path) -> None:
    clip = shared_data / "kitti_clip"
    out = run_pipeline(open_sequence(clip), load_config(ROOT / "configs" / "kitti.yaml"), tmp_path, "kitti")
    gt_all = np.loadtxt(clip / "poses.txt").reshape(-1, 3, 4)
    gt_T = np.tile(np.eye(4), (gt_all.shape[0], 1, 1))
    gt_T[:, :3, :] = gt_all
    # the clip has no times.txt: frame i at i / 10 s (configs/kitti.yaml)
    idx = {round(i * 1e8): i for i in range(gt_T.shape[0])}
    res = {}
    for name, traj in (("online", out.online), ("final", out.final)):
        rows = [idx[int(t)] for t in traj.timestamps_ns]
        assert len(rows) == gt_T.shape[0]
        res[name] = _ate_and_drift(np.asarray(traj.world_from_cam), gt_T[rows])
    # measured (load 20): online 0.0998 m / 0.971 %, final equal (the batch refinement's
    # robust chi-square drop 23 is below its standard deviation 178: not applied);
    # tolerance 1 mm of ATE and 0.01 percentage points of drift
    assert res["final"][0] <= res["online"][0] + 1e-3
    assert res["final"][1] <= res["online"][1] + 0.01
    assert res["online"][0] < 0.2 and res["online"][1] < 1.5  # the run itself is sane
    # issue 36 (drift8): the final trajectory's drift after the ground truth's constant-rate first
    # steps (its leading steps with one relative rotation: 11 on the clip), first poses aligned there.
    # measured: 0.511-0.512 % (ridge9: a held common principal point held through the left camera;
    # 0.550-0.558 % before, the left camera's share of the principal-point difference turning the
    # frame; 0.588 % before the calibrating finish read every keyframe at the front end's latest
    # disparity offset; 0.531 % with refine none). Issue 36's target 0.54
    rel = [np.linalg.inv(gt_T[k - 1]) @ gt_T[k] for k in range(1, len(gt_T))]
    turn = [np.linalg.norm(cv2.Rodrigues(rel[0][:3, :3].T @ r[:3, :3])[0]) for r in rel]
    seg = int(np.argmax(np.degrees(turn) > 2e-3))
    assert seg == 11
    rows = [idx[int(t)] for t in out.final.timestamps_ns]
    _, drift_after = _ate_and_drift(np.asarray(out.final.world_from_cam)[seg:], gt_T[rows][seg:])
    assert drift_after < 0.53, drift_after
    m = out.metrics
    # the run's own noise: from the batch BA, or (refine final, the default, which skips the batch BA)
    # from the calibrating bundle adjustment's residuals
    if "calibration_pixel_sigma_px" in m:
        assert 0 < m["calibration_pixel_sigma_px"] < 2.0, m["calibration_pixel_sigma_px"]
    else:
        assert m["pixel_sigma_px"] > 0 and "residual" in m["pixel_sigma_source"]
