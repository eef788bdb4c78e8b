"""Benchmark `depth`.

The seed-003 simulation (noiseless, gains of eq. 49) and the observer on KLT tracks of the real
KITTI clip against stereo depths.
"""

from __future__ import annotations

import time

import numpy as np
from shared_data import SHARED_DATA

from loopmodel.io import open_sequence
from loopmodel.observers.real_tracks import observe_sequence
from loopmodel.observers.simulation import simulate

KITTI = SHARED_DATA / "kitti_clip"


def run(quick: bool) -> dict:
    rate = 100.0 if quick else 1000.0
    t0 = time.perf_counter()
    res = simulate(duration_s=10.0, rate_hz=rate)
    sim_s = time.perf_counter() - t0
    print(f"simulation at {rate:.0f} Hz took {sim_s:.1f} s")
    out: dict = {
        "dataset": f"seed-003 simulation (12 features, {rate:.0f} Hz measurements, 1 kHz integration) + kitti_clip",
        "converge_s_5pct": round(res.converge_time_s(0.05), 3),
        "final_rel_err": float(res.rel_err[-1].max()),
        "final_rel_err_median": float(np.median(res.rel_err[-1])),
        "sim_wall_s": round(sim_s, 2),
    }
    if KITTI.is_dir():
        seq = open_sequence(KITTI)
        t0 = time.perf_counter()
        results, skipped = observe_sequence(seq.frames(), seq.calibration, window=6, stride=10)
        errs = np.concatenate([r.rel_err for r in results])
        out.update(
            {
                "kitti_depth_rel_err_median": float(np.median(errs)),
                "kitti_depth_rel_err_p90": float(np.percentile(errs, 90)),
                "kitti_features": int(errs.size),
                "kitti_windows": len(results),
                "kitti_windows_skipped": len(skipped),
                "kitti_wall_s": round(time.perf_counter() - t0, 2),
            }
        )
    else:
        out["kitti_depth_rel_err_median"] = None
    return out
