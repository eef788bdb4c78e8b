"""Benchmark ``kitti-rotation``: where the front end's rotation error on the KITTI clip comes from.

Per frame pair (step k-1 -> k) the relative rotation of three estimates is compared with the
clip's ground truth (``poses.txt``), as rotation vectors in the camera frame (x right: pitch,
y down: yaw, z forward: roll; degrees):

* ``vo``: the stereo front end (``configs/kitti.yaml``), as the pipeline runs it;
* ``epi``: a structure-free estimate in plain OpenCV + SciPy, independent of the front end:
  Shi-Tomasi corners, pyramidal LK (forward-backward checked) between the two left images,
  the rotation and translation direction minimising a robust (Cauchy, 0.5 px) Sampson
  epipolar error. It depends only on the intrinsics and the flow, not on stereo, depths,
  keyframes or the pose solver's weighting;
* ``gt``: the ground truth itself, scored with the same epipolar cost (rotation fixed,
  translation direction optimised) to say which rotation the images support;
* the direction of travel (``*_travel_deg_x`` / ``_y``: degrees of x/z and y/z of the camera's
  motion in its own frame) of ``epi`` and ``vo`` against the truth's: a constant difference makes
  an end-point drift that grows with the path (issue 36: after the segment the images' direction
  differs from the truth's by about -0.32 / +0.15 deg, ORB-SLAM3's drift shares it).

The clip's ground truth turns at a constant rate over its first steps (the per-step rotations
agree to 1e-3 deg, as an interpolated segment would; elsewhere they vary by ~0.05 deg a step):
``gt_constant_rate_steps`` counts them and the ``*_after_gt_segment`` keys align the
trajectories at the first frame after that segment instead.

Keys: ``steps``, ``gt_constant_rate_steps``, ``vo_step_err_deg_<axis>`` (mean, and ``_sem``),
``epi_step_err_deg_<axis>``, ``vo_minus_epi_deg_<axis>`` (mean and sem of the per-step
difference), ``gt_lower_epipolar_cost_steps`` (steps where the ground-truth rotation explains
the flow better than the front end's), the same means over the steps after the segment
(``*_after_gt_segment``), ``vo_rot_err_final_deg`` (first poses aligned) and
``vo_rot_err_final_deg_after_gt_segment``, ``vo_drift_pct``, ``vo_drift_pct_after_gt_segment``.
``--quick``: the first 30 frames.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from shared_data import SHARED_DATA

ROOT = Path(__file__).resolve().parents[1]
KITTI = SHARED_DATA / "kitti_clip"
AXES = ("pitch", "yaw", "roll")  # rotation about camera x, y, z


def _rotvec_deg(R: np.ndarray) -> np.ndarray:
    return np.degrees(Rotation.from_matrix(R).as_rotvec())


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def _direction(a: np.ndarray) -> np.ndarray:
    th, ph = a
    return np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])


def _angles(t: np.ndarray) -> np.ndarray:
    t = t / np.linalg.norm(t)
    return np.array([np.arccos(np.clip(t[2], -1.0, 1.0)), np.arctan2(t[1], t[0])])


def _travel_deg(cur_t_prev: np.ndarray) -> np.ndarray:
    """Direction of travel (degrees: atan of x/z and of y/z) of the translation ``-cur_t_prev``."""
    t = -cur_t_prev
    return np.degrees(np.arctan2(t[:2], t[2]))


def _sampson_px(E: np.ndarray, x0: np.ndarray, x1: np.ndarray, f_px: float) -> np.ndarray:
    """Sampson distances (pixels) of normalised homogeneous matches x0 -> x1 under ``x1' E x0 = 0``."""
    Ex0 = x0 @ E.T
    Etx1 = x1 @ E
    num = np.einsum("ij,ij->i", x1, Ex0)
    den = np.sqrt(Ex0[:, 0] ** 2 + Ex0[:, 1] ** 2 + Etx1[:, 0] ** 2 + Etx1[:, 1] ** 2)
    return f_px * num / np.maximum(den, 1e-12)


def _epipolar_fit(
    cur_from_prev: np.ndarray, x0: np.ndarray, x1: np.ndarray, f_px: float, rotation_free: bool
) -> tuple[np.ndarray, float, np.ndarray]:
    """Epipolar fit from ``cur_from_prev``: rotation, Cauchy cost, unit translation; R fixed unless free."""
    R0 = cur_from_prev[:3, :3]

    def res(p: np.ndarray) -> np.ndarray:
        R = Rotation.from_rotvec(p[:3]).as_matrix() @ R0 if rotation_free else R0
        return _sampson_px(_skew(_direction(p[-2:])) @ R, x0, x1, f_px)

    t0 = _angles(cur_from_prev[:3, 3])
    p0 = np.concatenate([np.zeros(3), t0]) if rotation_free else t0
    sol = least_squares(res, p0, loss="cauchy", f_scale=0.5, x_scale=1e-3, xtol=1e-12, ftol=1e-12)
    R = Rotation.from_rotvec(sol.x[:3]).as_matrix() @ R0 if rotation_free else R0
    return R, float(2.0 * sol.cost), _direction(sol.x[-2:])


def _flow(prev: np.ndarray, cur: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p0 = cv2.goodFeaturesToTrack(prev, 2000, 0.01, 8)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, None, winSize=(21, 21), maxLevel=3)
    pb, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, None, winSize=(21, 21), maxLevel=3)
    ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm((pb - p0).reshape(-1, 2), axis=1) < 0.5)
    return p0.reshape(-1, 2)[ok].astype(float), p1.reshape(-1, 2)[ok].astype(float)


def _final_errors(est: np.ndarray, gt: np.ndarray, start: int) -> tuple[float, float]:
    """Last-pose rotation error (deg) and drift (% of path) with the poses aligned at ``start``."""
    A = gt[start] @ np.linalg.inv(est[start])
    last = A @ est[-1]
    rot = float(np.linalg.norm(_rotvec_deg(gt[-1][:3, :3].T @ last[:3, :3])))
    path = float(np.sum(np.linalg.norm(np.diff(gt[start:, :3, 3], axis=0), axis=1)))
    return rot, float(np.linalg.norm(last[:3, 3] - gt[-1][:3, 3])) / path * 100.0


def constant_rate_steps(gt: np.ndarray, tol_deg: float = 2e-3) -> int:
    """Leading steps whose relative rotation equals the first step's within ``tol_deg``."""
    rel = [np.linalg.inv(gt[k - 1]) @ gt[k] for k in range(1, len(gt))]
    n = 0
    for r in rel:
        if np.linalg.norm(_rotvec_deg(rel[0][:3, :3].T @ r[:3, :3])) > tol_deg:
            break
        n += 1
    return n


def _mean_sem(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return a.mean(0), a.std(0, ddof=1) / np.sqrt(len(a))


def run(quick: bool = False) -> dict[str, Any]:
    from loopmodel.config import load_config
    from loopmodel.frontend import FrontEnd
    from loopmodel.io.sequence import open_sequence

    seq = open_sequence(KITTI)
    frames = list(seq.frames())[: 30 if quick else None]
    fe = FrontEnd(seq.calibration, load_config(ROOT / "configs" / "kitti.yaml").frontend)
    vo = np.array([fe.process(f).world_from_cam for f in frames])
    raw = np.loadtxt(KITTI / "poses.txt").reshape(-1, 3, 4)[: len(frames)]
    gt = np.tile(np.eye(4), (len(raw), 1, 1))
    gt[:, :3, :] = raw
    K = seq.calibration.K_left
    Ki = np.linalg.inv(K)
    f_px = float(K[0, 0])
    vo_err, epi_err, dir_err, gt_wins = [], [], [], 0
    for k in range(1, len(frames)):
        a, b = _flow(frames[k - 1].left, frames[k].left)
        x0 = np.column_stack([a, np.ones(len(a))]) @ Ki.T
        x1 = np.column_stack([b, np.ones(len(b))]) @ Ki.T
        g = np.linalg.inv(gt[k]) @ gt[k - 1]  # cur_from_prev
        v = np.linalg.inv(vo[k]) @ vo[k - 1]
        R_epi, _, t_epi = _epipolar_fit(v, x0, x1, f_px, rotation_free=True)
        _, cost_gt, _ = _epipolar_fit(g, x0, x1, f_px, rotation_free=False)
        _, cost_vo, _ = _epipolar_fit(v, x0, x1, f_px, rotation_free=False)
        # direction of travel (the previous camera's position in the current camera, negated) as
        # angles x/z and y/z: the images' (epi) and the front end's against the truth's
        d_gt, d_vo = _travel_deg(g[:3, 3]), _travel_deg(v[:3, 3])
        dir_err.append(np.concatenate([_travel_deg(t_epi) - d_gt, d_vo - d_gt]))
        gt_wins += cost_gt < cost_vo
        # error of the estimated prev_from_cur rotation against the truth's, in the previous camera
        Rg = g[:3, :3].T
        vo_err.append(_rotvec_deg(Rg.T @ v[:3, :3].T))
        epi_err.append(_rotvec_deg(Rg.T @ R_epi.T))
    vo_e, epi_e = np.array(vo_err), np.array(epi_err)
    seg = constant_rate_steps(gt)
    out: dict[str, Any] = {
        "load": os.getloadavg()[0],
        "dataset": "kitti_clip" + (" first 30 frames" if quick else ""),
        "steps": len(vo_e),
        "gt_constant_rate_steps": seg,
        "gt_lower_epipolar_cost_steps": int(gt_wins),
    }
    for suffix, sl in (("", slice(None)), ("_after_gt_segment", slice(seg, None))):
        for name, arr in (("vo", vo_e[sl]), ("epi", epi_e[sl]), ("vo_minus_epi", vo_e[sl] - epi_e[sl])):
            if len(arr) < 2:
                continue
            m, s = _mean_sem(arr)
            for i, ax in enumerate(AXES):
                out[f"{name}_step_err_deg_{ax}{suffix}"] = round(float(m[i]), 4)
                out[f"{name}_step_err_deg_{ax}{suffix}_sem"] = round(float(s[i]), 4)
        de = np.array(dir_err)[sl]
        if len(de) >= 2:
            m, s = _mean_sem(de)
            for i, key in enumerate(("epi_minus_gt_travel_deg_x", "epi_minus_gt_travel_deg_y",
                                     "vo_minus_gt_travel_deg_x", "vo_minus_gt_travel_deg_y")):
                out[f"{key}{suffix}"] = round(float(m[i]), 4)
                out[f"{key}{suffix}_sem"] = round(float(s[i]), 4)
    for suffix, start in (("", 0), ("_after_gt_segment", seg)):
        if start < len(vo) - 1:
            rot, drift = _final_errors(vo, gt, start)
            out[f"vo_rot_err_final_deg{suffix}"] = round(rot, 3)
            out[f"vo_drift_pct{suffix}"] = round(drift, 3)
    return out
