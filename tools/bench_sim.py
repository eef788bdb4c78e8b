"""Benchmark ``sim``: generation speed and size of the synthetic orbit scan (issues 3, 17).

Full run: the bundled sample's parameters (orbit preset, realistic world, 600 frames,
640x480 stereo, laser image, two render processes), then the clean world's orbit for
comparison (``clean_*`` keys); ``--quick``: the first 60 frames of each. Keys: ``frames``,
``total_s``, ``setup_s``, ``ms_per_frame`` (wall, setup included), ``render_ms_median``
(per stereo frame in one worker: two ray casts, shading, blur, noise), ``cpu_s`` and
``cpu_ms_per_frame`` (CPU time of this process and its render processes: independent of the
machine's load), ``est_wall_s_2_idle_cores`` (cpu_s / 2), ``size_mib``, ``kib_per_frame``,
``workers``.
"""

from __future__ import annotations

import resource
import tempfile
from pathlib import Path

from loopmodel.config import SimulationConfig
from loopmodel.sim.generate import resolve_config, simulate_scan


def run(quick: bool) -> dict:
    frames = 60 if quick else 600
    out = {"dataset": f"synthetic orbit preset, {frames} frames, 640x480 stereo (realistic; clean_*: clean world)"}
    for level in ("realistic", "clean"):
        res = _one(frames, level)
        out.update(res if level == "realistic" else {"clean_" + k: v for k, v in res.items()})
    return out


def _one(frames: int, level: str) -> dict:
    cfg = resolve_config(
        SimulationConfig(), preset="orbit", overrides={"trajectory": {"frames": frames}}, realism=level
    )
    cfg = cfg.model_copy(update={"write_scene_ply": False})
    before = _cpu_s()
    with tempfile.TemporaryDirectory() as tmp:
        res = simulate_scan(cfg, Path(tmp) / "scan.mcap", preset="orbit")
    cpu_s = _cpu_s() - before
    return {
        "frames": frames,
        "workers": cfg.workers,
        "total_s": round(res.seconds, 2),
        "setup_s": round(res.setup_seconds, 2),
        "ms_per_frame": round(res.ms_per_frame, 1),
        "render_ms_median": round(res.render_ms_median, 1),
        "cpu_s": round(cpu_s, 1),
        "cpu_ms_per_frame": round(1000 * cpu_s / frames, 1),
        "est_wall_s_2_idle_cores": round(cpu_s / 2, 1),
        "est_ms_per_frame_2_idle_cores": round(1000 * cpu_s / 2 / frames, 1),
        "size_mib": round(res.size_bytes / 2**20, 1),
        "kib_per_frame": round(res.size_bytes / 1024 / frames, 1),
    }


def _cpu_s() -> float:
    """User + system CPU seconds of this process and its finished children."""
    tot = 0.0
    for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
        r = resource.getrusage(who)
        tot += r.ru_utime + r.ru_stime
    return tot
