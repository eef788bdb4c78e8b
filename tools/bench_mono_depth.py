"""Benchmark ``mono_depth``.

Does ``frontend.mono_depth: observer`` (seed-003 depths of corners without a stereo match, from the
tracker's own poses) help the stereo front end on the real KITTI clip?

Conditions: the clip as recorded, and the clip with the left part of every right image
blanked (``mask`` = fraction of the width; a wall or a narrow right view: left-image
features there find no stereo match). Each condition runs with the option off and on;
keys ``<condition>_<off|on>_<metric>``: drift_pct, ate_rmse_m, lost_frames, keyframes,
mean stereo inliers per tracked frame, mean observer-depth points used per tracked frame,
and the depth error of the converged observer depths against stereo depths computed on the
*unmasked* right image (median relative error, count).
``python tools/bench.py mono_depth [--quick]`` (quick: first 25 frames).
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from shared_data import SHARED_DATA

ROOT = Path(__file__).resolve().parents[1]
KITTI = SHARED_DATA / "kitti_clip"
MASKS = {"normal": 0.0, "mask50": 0.5, "mask70": 0.7}


def masked(frame: Any, fraction: float) -> Any:
    """The stereo frame with the left ``fraction`` of the right image set to black."""
    if fraction <= 0:
        return frame
    right = frame.right.copy()
    right[:, : int(round(fraction * right.shape[1]))] = 0
    return replace(frame, right=right)


def run_condition(frames: list, calibration: Any, gt: Any, cfg: Any, fraction: float) -> dict[str, Any]:
    from loopmodel.eval.of_run import trajectory_errors
    from loopmodel.frontend import FrontEnd
    from loopmodel.frontend.stereo import match_stereo
    from loopmodel.pipeline import _online_trajectory

    fe = FrontEnd(calibration, cfg)
    t0 = time.perf_counter()
    res = [fe.process(masked(f, fraction)) for f in frames]
    wall = time.perf_counter() - t0
    ok = [r for r in res if r.ok and r.tracked > 0]  # frames tracked against a keyframe
    out: dict[str, Any] = {
        "lost_frames": sum(not r.ok for r in res),
        "keyframes": sum(r.is_keyframe for r in res),
        "stereo_inliers_mean": round(float(np.mean([r.inliers for r in ok])), 1) if ok else 0.0,
        "mono_points_mean": round(float(np.mean([r.mono_points for r in ok])), 1) if ok else 0.0,
        "wall_s": round(wall, 2),
    }
    err = trajectory_errors(_online_trajectory(res), gt)
    out["drift_pct"] = round(err.get("drift_pct", float("nan")), 3)
    out["ate_rmse_m"] = round(err.get("ate_rmse_m", float("nan")), 4)
    # observer depths (converged tracks) against stereo on the unmasked right image
    est = fe.mono_depth_estimates()
    if est is not None and len(est["depth_m"]):
        rel = []
        by_index = {f.index: f for f in frames}
        kf_frame = {r.keyframe.id: r.keyframe.frame_index for r in res if r.keyframe is not None}
        for k in np.unique(est["ref_kf"]):
            sel = np.flatnonzero((est["ref_kf"] == k) & est["converged"])
            if sel.size == 0:
                continue
            f = by_index[kf_frame[int(k)]]
            left, right = fe.rectifier.left(f.left), fe.rectifier.right(f.right)
            m = match_stereo(left, right, est["uv_ref"][sel], cfg)
            z = fe.calibration.fx_px * fe.calibration.baseline_m / m.disparity
            good = np.abs(est["uv_ref"][sel][m.index] - m.uv_left).max(axis=1) < 1.0
            rel += list(np.abs(est["depth_m"][sel][m.index] - z)[good] / z[good])
        out["depth_rel_err_median"] = round(float(np.median(rel)), 4) if rel else None
        out["depth_compared"] = len(rel)
    return out


def run(quick: bool = False) -> dict[str, Any]:
    from loopmodel.config import load_config
    from loopmodel.io.sequence import open_sequence

    seq = open_sequence(KITTI)
    base = load_config(ROOT / "configs" / "kitti.yaml").frontend
    frames = list(seq.frames())
    if quick:
        frames = frames[:25]
    out: dict[str, Any] = {"dataset": "kitti_clip" + (" first 25 frames" if quick else ""), "frames": len(frames)}
    for name, fraction in MASKS.items():
        for tag, mode in (("off", "none"), ("on", "observer")):
            cfg = base.model_copy(update={"mono_depth": mode})
            r = run_condition(frames, seq.calibration, seq.ground_truth, cfg, fraction)
            out.update({f"{name}_{tag}_{k}": v for k, v in r.items()})
            print(name, tag, r, flush=True)
    return out
