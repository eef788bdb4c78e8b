"""Benchmark ``scale``: cost growth of the pipeline over a long realistic multi-loop scan (issue 17).

Full run: a 5,000-frame realistic scan (the ``modeler`` preset stretched to 200 s at 25 Hz: four
sweeps, a loop closure, a second orbit that revisits both; generated once into
``~/.cache/loopmodel``: slow, about 0.35 CPU-s per frame, 36 min at load 6-11); ``--quick``: the 1,200-frame realistic
modeler scan of ``sim-loop --quick`` at every 3rd frame, as there. The pipeline runs with its own
configuration (iSAM2 back end, loop stage with its worker thread, live and final meshes, session map).

Keys: ``frames``, ``keyframes``; ``frame_ms_last_over_first``: median per-frame time over the last
N frames divided by that over the first N (N = 500, quick 200; a frame's time is the interval
between the pipeline's requests for consecutive frames, so it includes reading, the loop stage and
the back end); ``frame_ms_by_frames``: that median per block of N frames;
``frame_cpu_ms_last_over_first`` and ``frame_cpu_ms_by_frames``: the same for the tracking thread's
CPU time per frame (``time.thread_time``: what the load does not change; worker threads excluded);
``backend_ms_by_keyframes``: the back end's time per keyframe (every call the pipeline makes on
it: ``add_keyframe``, loop constraints, ``estimate``), median per block of 5 keyframes (the
modeler path makes about 35, whatever the frame count), as [keyframes, ms] pairs;
``loop_stage_ms_by_keyframes``: the same for the loop stage's ``on_keyframe`` on the tracking
thread; ``loop_opt_ms_by_keyframes``: each verified loop's optimisation (the back end's update with
the loop constraint) with the number of keyframes at that moment; ``loop_gate_ms_by_keyframes``: its
robust-gate solve; ``peak_rss_mib``; ``write_s``: writing the results folder
(``write_results``); ``finish_s``: the end of the run before it (drain, final refinement, final mesh,
session map). The curves are also drawn in ``results/bench_scale/scale.png`` (with ``scale.json``).
"""

from __future__ import annotations

import json
import logging
import resource
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from loopmodel.config import Config

ROOT = Path(__file__).resolve().parents[1]
CACHE = Path.home() / ".cache" / "loopmodel"
OUT = ROOT / "results" / "bench_scale"


class _Timed:
    """A sequence whose ``frames()`` records the time at which each frame is requested."""

    def __init__(self, seq: Any, stride: int) -> None:
        self._seq, self._stride = seq, stride
        self.stamps: list[float] = []
        self.cpu_s: list[float] = []  # the tracking (main) thread's CPU time: independent of the load

    def __getattr__(self, name: str) -> Any:
        return getattr(self._seq, name)

    def __len__(self) -> int:
        return (len(self._seq) + self._stride - 1) // self._stride

    def frames(self) -> Any:
        for i, f in enumerate(self._seq.frames()):
            if i % self._stride == 0:
                self.stamps.append(time.perf_counter())
                self.cpu_s.append(time.thread_time())
                yield f


class _Clock:
    """Time spent in an object's methods, charged to the keyframe count at the call."""

    def __init__(self) -> None:
        self.keyframes = 0
        self.ms: dict[int, float] = {}

    def add(self, t0: float) -> None:
        self.ms[self.keyframes] = self.ms.get(self.keyframes, 0.0) + (time.perf_counter() - t0) * 1e3

    def curve(self, block: int = 5) -> list[list[float]]:
        """Median ms per keyframe over blocks of ``block`` keyframes, as [keyframes, ms]."""
        if not self.ms:
            return []
        k = np.array(sorted(self.ms))
        v = np.array([self.ms[i] for i in k])
        out = []
        for start in range(0, int(k.max()), block):
            sel = (k > start) & (k <= start + block)
            if np.any(sel):
                out.append([start + block, round(float(np.median(v[sel])), 2)])
        return out


class _TimedBackend:
    """A back end whose every method call is timed by ``clock`` (the pipeline's calls, nothing else)."""

    def __init__(self, inner: Any, clock: _Clock) -> None:
        self._inner, self._clock = inner, clock

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._inner, name)
        if not callable(attr):
            return attr

        def timed(*args: Any, **kwargs: Any) -> Any:
            if name == "add_keyframe":
                self._clock.keyframes += 1
            t0 = time.perf_counter()
            try:
                return attr(*args, **kwargs)
            finally:
                self._clock.add(t0)

        return timed


def _blocks(dt_ms: np.ndarray, n: int) -> list[list[float]]:
    """Median frame time per block of ``n`` frames, as [last frame of the block, ms]."""
    return [
        [int(min(s + n, dt_ms.size)), round(float(np.median(dt_ms[s : s + n])), 2)] for s in range(0, dt_ms.size, n)
    ]


def measure(path: Path, stride: int, window: int, config: Config | None = None) -> dict[str, Any]:
    """The pipeline over ``path`` (every ``stride``-th frame) with its cost recorded as above."""
    import loopmodel.pipeline as pl
    from loopmodel.io.sequence import open_sequence
    from loopmodel.loop.stage import LoopClosingStage

    config = config if config is not None else Config()
    seq = _Timed(open_sequence(path, config.sequence), stride)
    backend_clock, loop_clock = _Clock(), _Clock()
    make, write, on_keyframe = pl.create_backend, pl.write_results, LoopClosingStage.on_keyframe
    write_s = [0.0]

    def timed_backend(*args: Any, **kwargs: Any) -> Any:
        return _TimedBackend(make(*args, **kwargs), backend_clock)

    def timed_write(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return write(*args, **kwargs)
        finally:
            write_s[0] = time.perf_counter() - t0

    def timed_on_keyframe(self: Any, keyframe: Any, state: Any) -> Any:
        loop_clock.keyframes = backend_clock.keyframes + 1
        t0 = time.perf_counter()
        try:
            return on_keyframe(self, keyframe, state)
        finally:
            loop_clock.add(t0)

    pl.create_backend = timed_backend  # type: ignore[assignment]
    pl.write_results = timed_write  # type: ignore[assignment]
    LoopClosingStage.on_keyframe = timed_on_keyframe  # type: ignore[method-assign]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            out = pl.run_pipeline(seq, config, tmp, "scale")
            t_end = time.perf_counter()
    finally:
        pl.create_backend, pl.write_results = make, write  # type: ignore[assignment]
        LoopClosingStage.on_keyframe = on_keyframe  # type: ignore[method-assign]
    stamps = np.array(seq.stamps)
    dt = np.diff(stamps) * 1e3
    cpu = np.diff(np.array(seq.cpu_s)) * 1e3
    n = min(window, dt.size // 2)
    ratio = float(np.median(dt[-n:]) / np.median(dt[:n])) if n > 0 else None
    cpu_ratio = float(np.median(cpu[-n:]) / np.median(cpu[:n])) if n > 0 else None
    kf_number = {int(k): i + 1 for i, k in enumerate(out.keyframe_ids.tolist())}
    loops = [e for e in out.metrics.get("loop_events", []) if e.get("type") == "loop"]
    finish_s = t_end - stamps[-1] - write_s[0] if stamps.size else 0.0
    return {
        "dataset": f"realistic modeler scan {path.name}" + (f", one frame in {stride}" if stride > 1 else ""),
        "frames": len(out.frames),
        "keyframes": int(out.keyframe_ids.size),
        "loops_closed": len(loops),
        "frame_ms_first_median": round(float(np.median(dt[:n])), 2) if n > 0 else None,
        "frame_ms_last_median": round(float(np.median(dt[-n:])), 2) if n > 0 else None,
        "frame_ms_last_over_first": round(ratio, 3) if ratio is not None else None,
        "frame_ms_by_frames": _blocks(dt, max(n, 1)),
        "frame_cpu_ms_last_over_first": round(cpu_ratio, 3) if cpu_ratio is not None else None,
        "frame_cpu_ms_by_frames": _blocks(cpu, max(n, 1)),
        "backend_ms_by_keyframes": backend_clock.curve(),
        "loop_stage_ms_by_keyframes": loop_clock.curve(),
        "loop_opt_ms_by_keyframes": [
            [kf_number.get(int(e["keyframe"]), 0), round(float(e.get("optimise_ms") or 0.0), 1)] for e in loops
        ],
        "loop_gate_ms_by_keyframes": [
            [kf_number.get(int(e["keyframe"]), 0), round(float(e.get("robust_gate_ms") or 0.0), 1)] for e in loops
        ],
        "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "write_s": round(write_s[0], 2),
        "finish_s": round(finish_s, 2),
        "final_refine_s": round(float(out.metrics.get("final_refine_s") or 0.0), 2),
        "fps": round(float(out.metrics.get("fps") or 0.0), 1),
        "wall_s": round(t_end - t0, 1),
    }


def plot(result: dict[str, Any], png: Path) -> None:
    """Frame time against frames, back-end, loop-stage and loop-optimisation time against keyframes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    f = np.array(result["frame_ms_by_frames"], float).reshape(-1, 2)
    a.plot(f[:, 0], f[:, 1], "o-", label="wall")
    c = np.array(result["frame_cpu_ms_by_frames"], float).reshape(-1, 2)
    a.plot(c[:, 0], c[:, 1], "s-", label="tracking thread CPU")
    a.legend()
    a.set(xlabel="frames", ylabel="median frame time (ms)", title=result["dataset"])
    a.set_ylim(bottom=0)
    for key, style in (
        ("backend_ms_by_keyframes", "o-"),
        ("loop_stage_ms_by_keyframes", "s-"),
        ("loop_opt_ms_by_keyframes", "x"),
        ("loop_gate_ms_by_keyframes", "+"),
    ):
        c = np.array(result[key], float).reshape(-1, 2)
        if c.size:
            b.plot(c[:, 0], c[:, 1], style, label=key.replace("_by_keyframes", ""))
    b.set(xlabel="keyframes", ylabel="ms per keyframe (median of 5) / per loop", title="cost against keyframes")
    b.set_ylim(bottom=0)
    b.legend()
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    tmp = png.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(png)


def run(quick: bool = False) -> dict[str, Any]:
    import sys

    logging.basicConfig(level=logging.WARNING)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import bench_sim_loop as sl

    if quick:
        path, stride, window = sl._ensure(CACHE / "modeler_1200.mcap", "modeler", frames=1200), 3, 200
    else:
        path, stride, window = sl._ensure(CACHE / "modeler_5000.mcap", "modeler", frames=5000), 1, 500
    result = measure(path, stride, window)
    name = "scale_quick" if quick else "scale"
    plot(result, OUT / f"{name}.png")
    (OUT / f"{name}.json").write_text(json.dumps(result, indent=1))
    result["plot"] = str(OUT / f"{name}.png")
    return result
