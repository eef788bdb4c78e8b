"""frontend.far_points = "bearing" on real KITTI frames.

With a tight depth gate (25 m) most far stereo matches are dropped; as bearings with an
inverse-depth prior they are tracked and enter the pose solve, and the per-frame rotation
against the clip's ground truth gets smaller (measured on frames 11-30, after the ground
truth's constant-rate first segment, configs/kitti.yaml: mean per-step rotation error
0.0378 deg dropped, 0.0329 deg as bearings; 46-100 bearings tracked per frame).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from loopmodel.config import load_config
from loopmodel.geometry.se3 import so3_log

ROOT = Path(__file__).resolve().parents[1]


def _step_rot_err_deg(T: np.ndarray, G: np.ndarray) -> np.ndarray:
    out = []
    for k in range(1, len(T)):
        Re = T[k - 1][:3, :3].T @ T[k][:3, :3]
        Rg = G[k - 1][:3, :3].T @ G[k][:3, :3]
        out.append(np.degrees(np.linalg.norm(so3_log(Rg.T @ Re))))
    return np.array(out)


def test_far_bearings_are_tracked_and_keep_the_rotation(shared_data: Path) -> None:
    from loopmodel.frontend import FrontEnd
    from loopmodel.io.sequence import open_sequence

    clip = shared_data / "kitti_clip"
    seq = open_sequence(clip)
    frames = list(seq.frames())[11:31]
    raw = np.loadtxt(clip / "poses.txt").reshape(-1, 3, 4)[11:31]
    G = np.tile(np.eye(4), (len(raw), 1, 1))
    G[:, :3, :] = raw
    base = load_config(ROOT / "configs" / "kitti.yaml").frontend.model_copy(update={"max_depth_m": 25.0})
    errs = {}
    for mode in ("drop", "bearing"):
        fe = FrontEnd(seq.calibration, base.model_copy(update={"far_points": mode}))
        T, far_tracked = [], []
        for f in frames:
            r = fe.process(f)
            assert r.ok
            T.append(r.world_from_cam)
            far_tracked.append(fe._far_idx.size)
        if mode == "drop":
            assert max(far_tracked) == 0
        else:
            # 100 bearings at each keyframe (far_max_points), 46-100 still tracked in the next frames
            assert min(far_tracked) > 40
        errs[mode] = float(np.mean(_step_rot_err_deg(np.array(T), G)))
    # measured before issue 36 (bearing below drop); with the local map and the disparity offset the
    # near points hold the rotation as well: 0.03279 (bearing) vs 0.03259 deg per step (drop)
    assert errs["bearing"] < 1.02 * errs["drop"]
    assert errs["bearing"] < 0.035
