"""Benchmark: front-end drift of an equidistant (fisheye) rig against the pinhole rig.

On the same simulated path (issue 25's target: fisheye drift within 1.5x the pinhole's).

For each seed, ``loopmodel simulate scan --preset orbit --realism clean`` renders the scan twice
(the realistic world has its own lens model and cannot render a fisheye rig), once with a
pinhole pair and once with raw Kannala-Brandt images (TUM-VI's room-sequence coefficients,
the same focal length and baseline), and ``loopmodel run --frontend-only -c configs/sim.yaml``
tracks each; the front end rectifies the fisheye pair with ``cv2.fisheye``. Keys:
``drift_pct_<rig>_seed<k>``, ``ate_mm_<rig>_seed<k>``, the means over seeds and
``drift_ratio_of_means`` (fisheye / pinhole).
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# TUM-VI (room sequences) cam0 equidistant coefficients k1..k4
TUMVI_K = [0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202, 0.00020293673591811182]


def _run(cmd: list[str]) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    subprocess.run([sys.executable, "-m", "loopmodel", *cmd], check=True, capture_output=True, env=env)


def run(quick: bool = False) -> dict:
    seeds = [0] if quick else [0, 1, 2]
    frames = 40 if quick else 150
    tmp = Path(tempfile.mkdtemp(prefix="bench_fisheye_"))
    out: dict[str, object] = {"frames": frames, "seeds": seeds, "fisheye_k": TUMVI_K}
    try:
        for rig, camera in (("pinhole", {}), ("fisheye", {"fisheye_k": TUMVI_K})):
            cfg = tmp / f"{rig}.yaml"
            cfg.write_text(json.dumps({"simulation": {"camera": camera, "laser": {"image": False}}}))
            drifts, ates = [], []
            for seed in seeds:
                scan = tmp / f"{rig}_{seed}.mcap"
                _run(
                    ["simulate", "scan", "--preset", "orbit", "--frames", str(frames), "--seed", str(seed)]
                    + ["--realism", "clean", "--workers", "1", "-c", str(cfg), "--out", str(scan)]
                )
                _run(
                    ["run", str(scan), "-c", str(ROOT / "configs" / "sim.yaml"), "--frontend-only"]
                    + ["--out", str(tmp / "runs"), "--name", f"{rig}_{seed}"]
                )
                m = json.loads((tmp / "runs" / f"{rig}_{seed}" / "metrics.json").read_text())
                out[f"drift_pct_{rig}_seed{seed}"] = m["drift_pct"]
                out[f"ate_mm_{rig}_seed{seed}"] = m["ate_rmse_m"] * 1e3
                out[f"lost_frames_{rig}_seed{seed}"] = m["lost_frames"]
                drifts.append(m["drift_pct"])
                ates.append(m["ate_rmse_m"] * 1e3)
                scan.unlink()
            out[f"drift_pct_{rig}_mean"] = statistics.mean(drifts)
            out[f"ate_mm_{rig}_mean"] = statistics.mean(ates)
        out["drift_ratio_of_means"] = float(out["drift_pct_fisheye_mean"]) / float(out["drift_pct_pinhole_mean"])  # type: ignore[arg-type]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


if __name__ == "__main__":
    print(json.dumps(run("--quick" in sys.argv)))
