"""Benchmark ``viz``: what rerun logging costs the pipeline.

The same run of the full pipeline (the real KITTI clip, ``configs/kitti.yaml``; and a short
simulated orbit with laser stripes and the live mesh when ``datasets/sample/scan.mcap``
exists) with and without ``--rerun FILE.rrd``, alternated (off, on, off, on, …) in one
process so load changes hit both alike. ``fps`` is frames / wall time of the frame loop, the
listener's work included (the pipeline's own ``metrics.json`` fps counts only its stages).

Keys (BENCHMARKS.md): fps_off, fps_rerun, overhead_pct (100 × (1 − fps_rerun / fps_off), of the
medians), rrd_mib; per sequence too (``kitti_*``, ``sim_*``).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from shared_data import SHARED_DATA

ROOT = Path(__file__).resolve().parents[1]
KITTI = SHARED_DATA / "kitti_clip"
SAMPLE = ROOT / "datasets" / "sample" / "scan.mcap"


def _one(seq_path: Path, config_path: Path, rrd: Path | None, max_frames: int | None) -> tuple[float, int]:
    from loopmodel.config import load_config
    from loopmodel.imaging.rectify import Rectifier
    from loopmodel.io.sequence import open_sequence
    from loopmodel.pipeline import process
    from loopmodel.viz.recorder import RerunListener, RerunRecorder, RerunSink

    cfg = load_config(config_path)
    seq = open_sequence(seq_path, cfg.sequence)
    listeners = []
    if rrd is not None:
        rect = Rectifier(seq.calibration).calibration
        listeners = [RerunListener(RerunRecorder(RerunSink(path=rrd)), rect.K_left, rect.image_size)]
    last: list[float] = [0.0]

    def progress(i: int, n: int, fps: float, kf: int) -> None:
        last[0] = fps

    res = process(seq, cfg, progress=progress, max_frames=max_frames, listeners=listeners)  # type: ignore[arg-type]
    return last[0], len(res.frames)


def _pair(name: str, seq_path: Path, config_path: Path, repeats: int, max_frames: int | None) -> dict[str, Any]:
    off, on, sizes = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        _one(seq_path, config_path, None, 5)  # warm-up (imports, numba, OpenCV)
        for r in range(repeats):
            off.append(_one(seq_path, config_path, None, max_frames)[0])
            rrd = Path(tmp) / f"{r}.rrd"
            fps, frames = _one(seq_path, config_path, rrd, max_frames)
            on.append(fps)
            sizes.append(rrd.stat().st_size / 2**20)
    f_off, f_on = float(np.median(off)), float(np.median(on))
    return {
        f"{name}_frames": frames,
        f"{name}_fps_off": round(f_off, 2),
        f"{name}_fps_rerun": round(f_on, 2),
        f"{name}_overhead_pct": round(100 * (1 - f_on / f_off), 1),
        f"{name}_rrd_mib": round(float(np.median(sizes)), 2),
        f"{name}_fps_off_runs": [round(x, 2) for x in off],
        f"{name}_fps_rerun_runs": [round(x, 2) for x in on],
    }


def run(quick: bool = False) -> dict[str, Any]:
    out: dict[str, Any] = {"load_1min": round(os.getloadavg()[0], 2)}
    datasets = []
    repeats = 1 if quick else 3
    if KITTI.is_dir():
        out.update(_pair("kitti", KITTI, ROOT / "configs" / "kitti.yaml", repeats, 30 if quick else None))
        datasets.append("kitti_clip")
    if SAMPLE.is_file():
        out.update(_pair("sim", SAMPLE, ROOT / "configs" / "sim.yaml", repeats, 60 if quick else 200))
        datasets.append("sample orbit (first 200 frames)")
    if not datasets:
        raise SystemExit("no data: needs ../shared/data/kitti_clip or datasets/sample/scan.mcap (make demo)")
    first = "kitti" if KITTI.is_dir() else "sim"
    for k in ("fps_off", "fps_rerun", "overhead_pct", "rrd_mib"):
        out[k] = out[f"{first}_{k}"]
    out["dataset"] = ", ".join(datasets)
    out["load_1min_end"] = round(os.getloadavg()[0], 2)
    return out
