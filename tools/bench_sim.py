"""Benchmark ``sim``: generation speed and size of the synthetic orbit scan (issue 3).

Full run: the bundled sample's parameters (orbit preset, 600 frames, 640x480 stereo, two
render processes); ``--quick``: the first 120 frames of the same kind. Keys: ``frames``,
``total_s``, ``setup_s``, ``ms_per_frame`` (wall, setup included), ``render_ms_median``
(per stereo frame in one worker: two ray casts, shading, blur, noise), ``size_mib``,
``kib_per_frame``, ``workers``.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from loopmodel.config import SimulationConfig
from loopmodel.sim.generate import resolve_config, simulate_scan


def run(quick: bool) -> dict:
    frames = 120 if quick else 600
    cfg = resolve_config(SimulationConfig(), preset="orbit", overrides={"trajectory": {"frames": frames}})
    cfg = cfg.model_copy(update={"write_scene_ply": False})
    with tempfile.TemporaryDirectory() as tmp:
        res = simulate_scan(cfg, Path(tmp) / "scan.mcap", preset="orbit")
    return {
        "dataset": f"synthetic orbit preset, {frames} frames, 640x480 stereo",
        "frames": frames,
        "workers": cfg.workers,
        "total_s": round(res.seconds, 2),
        "setup_s": round(res.setup_seconds, 2),
        "ms_per_frame": round(res.ms_per_frame, 1),
        "render_ms_median": round(res.render_ms_median, 1),
        "size_mib": round(res.size_bytes / 2**20, 1),
        "kib_per_frame": round(res.size_bytes / 1024 / frames, 1),
    }
