"""Benchmark ``scale``: cost growth of the pipeline over a long realistic multi-loop scan (issues 17, 33).

Full run: a 5,400-frame realistic ``rounds`` scan (216 s at 25 Hz: 18 rounds around the object,
each at its own height and distance, each running past its own start; every round passes the
views of the earlier ones from another height, so the path keeps finding new views); the quick
scan's pace (about 19 keyframes a round), 3 times as long. The ``rounds`` preset's 10,000 frames
(16 rounds, slower) would take twice as long to generate (0.2-0.25 CPU-s a frame) and to run.
Generated once into ``~/.cache/loopmodel``. ``--quick``: the same kind of scan with 6 rounds in
1,800 frames (about 120 keyframes). The pipeline runs with its own configuration (iSAM2 back
end in its worker, loop stage with its worker, live and final meshes, session map).

Keys: ``frames``, ``keyframes``, ``loops``, ``loops_old_features_resumed`` (loops whose old features the
front end tracked on); ``frame_ms_last_over_first``: median per-frame time over
the last N frames divided by that over the first N (N = 500, quick 200; a frame's time is the
interval between the pipeline's requests for consecutive frames, so it includes reading, the loop
stage and the back end's queueing); ``frame_ms_by_frames``: that median per block of N frames;
``frame_cpu_ms_last_over_first`` and ``frame_cpu_ms_by_frames``: the same for the tracking thread's
CPU time per frame (``time.thread_time``: what the load does not change; worker threads excluded);
``backend_ms_by_keyframes``: the back end's CPU time per keyframe (every call the pipeline makes
on it, as its worker thread measures it: ``add_keyframe``, late observations, loop constraints,
``estimate``, charged to the number of keyframes it holds), median per block of B keyframes (B = 20),
as [keyframes, ms] pairs; ``backend_ms_last_over_first``: the last block's median over the first's;
``backend_cpu_s_by_call``: the back end's CPU s per kind of call (kf, obs, loop, remove, estimate);
``backend_factors_by_keyframes``: the factors each keyframe's update (and its late observations) added,
median per block; ``backend_us_per_factor_by_keyframes`` and ``backend_us_per_factor_last_over_first``:
the back end's CPU per keyframe divided by those factors (what the map's size costs apart from how
many observations each keyframe brings);
``frame_ms_p95`` and ``frame_ms_max_after_first``: over the frames after the first (wall);
``loop_stage_ms_by_keyframes``: the loop stage's ``on_keyframe`` on the tracking thread, the same
way; ``loop_stage_s``: all its time on the tracking thread (``on_keyframe`` and ``between_frames``);
``loop_opt_ms_by_keyframes``: each loop constraint's optimisation in the back end (its
``add_loop_constraint``: the update and the relinearisation after it) with the keyframes at that
moment (with ``backend.local_defer_loop``, be15, the loop's update runs in the next keyframe's, which
``backend_ms_by_keyframes`` counts: what is left here is recording the constraint);
``loop_gate_ms_by_keyframes``: each verified loop's robust-gate solve; ``ate_rmse_before_m``
and ``ate_rmse_after_m``: every tracked frame's position (dead reckoning through the keyframes'
measured links, and the final trajectory) against the ground truth after a rigid alignment;
``peak_rss_mib``; ``write_s``: writing the results folder (``write_results``); ``finish_s``: the end
of the run before it (drain, final refinement, final mesh, session map). The curves are also drawn
in ``results/bench_scale/scale.png`` (with ``scale.json``).

The back end alone: ``python tools/bench_scale.py record SCAN OUT`` runs the pipeline once and keeps
the calls its back-end worker made; ``python tools/bench_scale.py replay OUT ['{"key": value}']``
replays them on a fresh iSAM2 back end (with those ``backend`` keys) in minutes instead of a pipeline
run, printing the back end's cost per keyframe and its keyframe accuracy. The worker process runs on
jemalloc (``backend.worker_allocator``); run the replay with
``LD_PRELOAD=/usr/lib/x86_64-linux-gnu/libjemalloc.so.2`` to match it (on glibc's allocator the later
blocks cost more, be17/be19).
"""

from __future__ import annotations

import gc
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

    def scan(self) -> Any:
        """The pipeline's one pass (frames with what rides along): stamped like :meth:`frames`."""
        for i, item in enumerate(self._seq.scan()):
            if i % self._stride == 0:
                self.stamps.append(time.perf_counter())
                self.cpu_s.append(time.thread_time())
                yield item


class _Clock:
    """Time spent in an object's methods, charged to the keyframe count at the call."""

    def __init__(self) -> None:
        self.keyframes = 0
        self.ms: dict[int, float] = {}

    def add(self, t0: float) -> None:
        self.ms[self.keyframes] = self.ms.get(self.keyframes, 0.0) + (time.perf_counter() - t0) * 1e3

    def curve(self, block: int = 5) -> list[list[float]]:
        """Median ms per keyframe over blocks of ``block`` keyframes, as [keyframes, ms]."""
        return _curve(self.ms, block)


def _curve(ms: dict[int, float], block: int) -> list[list[float]]:
    """Median of ``ms`` (keyframes -> ms) per block of ``block`` keyframes, as [keyframes, ms]."""
    if not ms:
        return []
    k = np.array(sorted(ms))
    v = np.array([ms[i] for i in k])
    out = []
    for start in range(0, int(k.max()), block):
        sel = (k > start) & (k <= start + block)
        if np.any(sel):
            out.append([start + block, round(float(np.median(v[sel])), 2)])
    return out


class _TimedBackend:
    """An inline back end whose every call is recorded as the worker records them: (kind, keyframes, CPU ms)."""

    KINDS = {"add_keyframe": "kf", "add_observations": "obs", "add_loop_constraint": "loop",
             "remove_observations": "remove", "estimate": "estimate"}

    def __init__(self, inner: Any) -> None:
        self._inner = inner
        self.call_ms: list[tuple[str, int, float, int]] = []
        self._n_kf = 0

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._inner, name)
        if name not in self.KINDS:
            return attr

        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = time.thread_time()
            out = None
            try:
                out = attr(*args, **kwargs)
                return out
            finally:
                self._n_kf += name == "add_keyframe"
                factors = int(getattr(out, "new_factors", 0) or 0)
                self.call_ms.append((self.KINDS[name], self._n_kf, (time.thread_time() - t0) * 1e3, factors))

        return timed


def _blocks(dt_ms: np.ndarray, n: int) -> list[list[float]]:
    """Median frame time per block of ``n`` frames, as [last frame of the block, ms]."""
    return [
        [int(min(s + n, dt_ms.size)), round(float(np.median(dt_ms[s : s + n])), 2)] for s in range(0, dt_ms.size, n)
    ]


def _ate_m(est: np.ndarray, gt: np.ndarray) -> float:
    """RMS position error (m) of ``est`` against ``gt`` (N x 4 x 4) after a rigid alignment."""
    from loopmodel.geometry.align import umeyama_alignment

    R, t, _ = umeyama_alignment(est[:, :3, 3], gt[:, :3, 3], with_scale=False)
    p = est[:, :3, 3] @ np.asarray(R).T + t
    return float(np.sqrt(np.mean(np.sum((p - gt[:, :3, 3]) ** 2, axis=1))))


def measure(path: Path, stride: int, window: int, config: Config | None = None, block: int = 20) -> dict[str, Any]:
    """The pipeline over ``path`` (every ``stride``-th frame) with its cost recorded as above."""
    import loopmodel.pipeline as pl
    from loopmodel.backend.worker import BackgroundBackend
    from loopmodel.io.sequence import open_sequence
    from loopmodel.io.trajectory_io import read_trajectory
    from loopmodel.listener import RunListener
    from loopmodel.loop.stage import LoopClosingStage

    config = config if config is not None else Config()
    seq = _Timed(open_sequence(path, config.sequence), stride)
    loop_clock = _Clock()
    backends: list[Any] = []
    start, write, on_keyframe = pl.start_backend, pl.write_results, LoopClosingStage.on_keyframe
    between = LoopClosingStage.between_frames
    between_ms: list[float] = []
    write_s = [0.0]
    chain: dict[int, tuple[int | None, np.ndarray | None, bool, np.ndarray]] = {}

    class _Chain(RunListener):
        def on_keyframe(self, keyframe: Any, result: Any) -> None:
            kf = keyframe
            chain[kf.id] = (kf.prev_keyframe_id, kf.kf_prev_from_kf, kf.connected, kf.world_from_kf.copy())
            loop_clock.keyframes = len(chain)

    def recorded_backend(*args: Any, **kwargs: Any) -> Any:
        backend = start(*args, **kwargs)
        backends.append(backend if isinstance(backend, BackgroundBackend) else _TimedBackend(backend))
        return backends[-1]

    def timed_write(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return write(*args, **kwargs)
        finally:
            write_s[0] = time.perf_counter() - t0

    def timed_on_keyframe(self: Any, keyframe: Any, state: Any) -> Any:
        loop_clock.keyframes = len(chain) + 1
        t0 = time.perf_counter()
        try:
            return on_keyframe(self, keyframe, state)
        finally:
            loop_clock.add(t0)

    def timed_between(self: Any, state: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return between(self, state)
        finally:
            between_ms.append((time.perf_counter() - t0) * 1e3)

    pl.start_backend = recorded_backend  # type: ignore[assignment]
    pl.write_results = timed_write  # type: ignore[assignment]
    LoopClosingStage.on_keyframe = timed_on_keyframe  # type: ignore[method-assign]
    LoopClosingStage.between_frames = timed_between  # type: ignore[method-assign]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            out = pl.run_pipeline(seq, config, tmp, "scale", listeners=[_Chain()])
            t_end = time.perf_counter()
            final = read_trajectory(out.folder / "trajectory_final.tum")
    finally:
        pl.start_backend, pl.write_results = start, write  # type: ignore[assignment]
        LoopClosingStage.on_keyframe = on_keyframe  # type: ignore[method-assign]
        LoopClosingStage.between_frames = between  # type: ignore[method-assign]
    stamps = np.array(seq.stamps)
    dt = np.diff(stamps) * 1e3
    cpu = np.diff(np.array(seq.cpu_s)) * 1e3
    n = min(window, dt.size // 2)
    ratio = float(np.median(dt[-n:]) / np.median(dt[:n])) if n > 0 else None
    cpu_ratio = float(np.median(cpu[-n:]) / np.median(cpu[:n])) if n > 0 else None
    loops = [e for e in out.metrics.get("loop_events", []) if e.get("type") == "loop"]
    kf_number = {int(k): i + 1 for i, k in enumerate(out.keyframe_ids.tolist())}
    finish_s = t_end - stamps[-1] - write_s[0] if stamps.size else 0.0
    # the back end's CPU ms per keyframe (every call charged to the keyframes it held then)
    calls = list(backends[0].call_ms) if backends else []
    per_kf: dict[int, float] = {}
    factors_kf: dict[int, float] = {}
    for c in calls:  # (kind, keyframes, CPU ms[, factors]: a worker of before window9 has no count)
        per_kf[c[1]] = per_kf.get(c[1], 0.0) + c[2]
        factors_kf[c[1]] = factors_kf.get(c[1], 0.0) + (c[3] if len(c) > 3 else 0)
    curve = _curve(per_kf, block)
    fcurve = _curve(factors_kf, block)
    # the back end's CPU per factor it was given (window9): what the map's size costs, apart from
    # how many observations each keyframe brings
    us_per_factor = {k: 1e3 * ms / factors_kf[k] for k, ms in per_kf.items() if factors_kf.get(k)}
    ucurve = _curve(us_per_factor, block)
    # accuracy: dead reckoning through the measured keyframe links, and the final trajectory
    from bench_sim_loop import dead_reckoning  # tools/ is on sys.path (run() puts it there)

    dr = dead_reckoning(chain)
    by_time = dict(zip(final.timestamps_ns.tolist(), final.world_from_cam, strict=True))
    gt = seq.ground_truth
    ate_before = ate_after = None
    if gt is not None:
        gt_index = {t: i for i, t in enumerate(gt.timestamps_ns.tolist())}
        ok = [f for f in out.frames if f.ok and f.timestamp_ns in by_time and f.timestamp_ns in gt_index
              and f.keyframe_id in dr]
        if len(ok) >= 3:
            g = gt.world_from_cam[np.array([gt_index[f.timestamp_ns] for f in ok])]
            ate_before = _ate_m(np.array([dr[f.keyframe_id] @ f.kf_from_cam for f in ok]), g)
            ate_after = _ate_m(np.array([by_time[f.timestamp_ns] for f in ok]), g)
    return {
        "dataset": f"realistic {path.stem} scan" + (f", one frame in {stride}" if stride > 1 else ""),
        "frames": len(out.frames),
        "keyframes": int(out.keyframe_ids.size),
        "loops": len(loops),
        "loops_old_features_resumed": sum(int(e.get("old_features_resumed") or 0) > 0 for e in loops),
        "frame_ms_first_median": round(float(np.median(dt[:n])), 2) if n > 0 else None,
        "frame_ms_last_median": round(float(np.median(dt[-n:])), 2) if n > 0 else None,
        "frame_ms_last_over_first": round(ratio, 3) if ratio is not None else None,
        "frame_ms_by_frames": _blocks(dt, max(n, 1)),
        "frame_ms_p95": round(float(np.percentile(dt[1:], 95)), 1) if dt.size > 1 else None,
        "frame_ms_max_after_first": round(float(dt[1:].max()), 1) if dt.size > 1 else None,
        "loop_stage_s": round((sum(loop_clock.ms.values()) + sum(between_ms)) / 1e3, 2),
        "frame_cpu_ms_last_over_first": round(cpu_ratio, 3) if cpu_ratio is not None else None,
        "frame_cpu_ms_by_frames": _blocks(cpu, max(n, 1)),
        "backend_ms_by_keyframes": curve,
        "backend_ms_last_over_first": round(curve[-1][1] / curve[0][1], 3) if len(curve) > 1 and curve[0][1] else None,
        "backend_block_keyframes": block,
        "backend_factors_by_keyframes": fcurve,
        "backend_us_per_factor_by_keyframes": ucurve,
        "backend_us_per_factor_last_over_first": (
            round(ucurve[-1][1] / ucurve[0][1], 3) if len(ucurve) > 1 and ucurve[0][1] else None
        ),
        "backend_cpu_s_by_call": {
            kind: round(sum(c[2] for c in calls if c[0] == kind) / 1e3, 2) for kind in sorted({c[0] for c in calls})
        },
        "loop_stage_ms_by_keyframes": loop_clock.curve(block),
        "loop_opt_ms_by_keyframes": [[c[1], round(c[2], 1)] for c in calls if c[0] == "loop"],
        "loop_gate_ms_by_keyframes": [
            [kf_number.get(int(e["keyframe"]), 0), round(float(e.get("robust_gate_ms") or 0.0), 1)] for e in loops
        ],
        "ate_rmse_before_m": round(ate_before, 5) if ate_before is not None else None,
        "ate_rmse_after_m": round(ate_after, 5) if ate_after is not None else None,
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
    b.set(xlabel="keyframes", ylabel="ms per keyframe (block median) / per loop", title="cost against keyframes")
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

    if quick:  # 6 rounds in 1,800 frames (4 rounds in 1,200 made 79 keyframes)
        path, window = sl._ensure(CACHE / "rounds_1800.mcap", "rounds", frames=1800, sweeps=6), 200
    else:  # 18 rounds in 5,400 frames: the quick scan's pace (about 19 keyframes a round), 3 times as long
        path, window = sl._ensure(CACHE / "rounds_5400.mcap", "rounds", frames=5400, sweeps=18), 500
    result = measure(path, 1, window)
    name = "scale_quick" if quick else "scale"
    plot(result, OUT / f"{name}.png")
    (OUT / f"{name}.json").write_text(json.dumps(result, indent=1))
    result["plot"] = str(OUT / f"{name}.png")
    return result


# --------------------------------------------------------------------------- the back end alone (issue 33)
_RECORDED = ("add_keyframe", "add_observations", "add_loop_constraint", "remove_observations")


class _Recorder:
    """A back end whose calls that change it are appended to ``log`` as (method, args, kwargs)."""

    def __init__(self, inner: Any, log: list[tuple[str, tuple[Any, ...], dict[str, Any]]]) -> None:
        self._inner, self._log = inner, log

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._inner, name)
        if name not in _RECORDED:
            return attr

        def recorded(*args: Any, **kwargs: Any) -> Any:
            self._log.append((name, args, kwargs))
            return attr(*args, **kwargs)

        return recorded


def record_backend_calls(path: Path, out: Path, config: Config | None = None) -> int:
    """Run the pipeline over ``path`` and pickle the back end's calls as its worker made them into ``out``.

    The worker runs as a thread (the calls are recorded where the worker hands them on, keyframe
    poses re-based as the back end received them); with the calibration and the scan's ground
    truth. Returns the number of calls.
    """
    import pickle

    import loopmodel.pipeline as pl
    from loopmodel.io.sequence import open_sequence

    config = (config or Config()).model_copy(deep=True)
    config.backend.worker = "thread"
    log: list[tuple[str, tuple[Any, ...], dict[str, Any]]] = []
    calibration: list[Any] = []
    start = pl.start_backend

    def recording(backend_config: Any, factory: Any) -> Any:
        calibration.append(factory.args[1])  # functools.partial(create_backend, config, calibration, ...)
        return start(backend_config, lambda: _Recorder(factory(), log))

    seq = open_sequence(path, config.sequence)
    pl.start_backend = recording  # type: ignore[assignment]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            pl.run_pipeline(seq, config, tmp, "record")
    finally:
        pl.start_backend = start  # type: ignore[assignment]
    out.write_bytes(pickle.dumps({"calls": log, "calibration": calibration[0], "ground_truth": seq.ground_truth}))
    return len(log)


def replay_backend_calls(
    recorded: Path, config: Config | None = None, block: int = 20, final: bool = False
) -> dict[str, Any]:
    """Replay :func:`record_backend_calls`' calls on a fresh iSAM2 back end in this thread.

    As the worker does: one ``estimate(landmarks=False)`` after each keyframe and the calls that
    follow it. Keys: ``backend_ms_by_keyframes`` (CPU ms per keyframe, median per block of ``block``
    keyframes, as [keyframes, ms]), ``backend_ms_last_over_first``, ``loop_ms_by_keyframes``,
    ``cpu_s_by_call`` (per method), ``keyframe_ate_m`` (the iSAM2 estimate's keyframe positions
    against the ground truth after a rigid alignment), ``factors``, ``landmarks``. With ``final``
    also ``final_keyframe_ate_m`` and ``final_s``: the run's final estimate (``final_estimate`` with
    the configuration's ``refine`` section: extra iterations, batch bundle adjustment, loops spread)
    and its CPU time.
    """
    import pickle

    from loopmodel.backend.isam2 import Isam2Backend

    data = pickle.loads(recorded.read_bytes())  # noqa: S301 - a file this tool wrote
    calls = data["calls"]
    config = config or Config()
    backend = Isam2Backend(data["calibration"], config.backend)
    per_kf: dict[int, float] = {}
    by_call: dict[str, float] = {}
    loop_ms: list[list[float]] = []
    keyframes: list[Any] = []
    for i, (name, args, kwargs) in enumerate(calls):
        t0 = time.thread_time()
        getattr(backend, name)(*args, **kwargs)
        batch_end = i + 1 == len(calls) or calls[i + 1][0] == "add_keyframe"
        if batch_end:
            backend.estimate(landmarks=False)
        ms = (time.thread_time() - t0) * 1e3
        if batch_end:
            # as the worker process after each batch (be16's freeze_gc): else the collector's full passes over the
            # back end's records grow the replay's Python cost 3-5x over rounds_1800 (be19); undone below
            gc.freeze()
        if name == "add_keyframe":
            keyframes.append(args[0])
        per_kf[len(keyframes)] = per_kf.get(len(keyframes), 0.0) + ms
        by_call[name] = by_call.get(name, 0.0) + ms / 1e3
        if name == "add_loop_constraint":
            loop_ms.append([len(keyframes), round(ms, 1)])
    gc.unfreeze()
    curve = _curve(per_kf, block)
    gt = data["ground_truth"]

    def keyframe_ate(est: dict[int, Any]) -> float | None:
        if gt is None:
            return None
        index = {t: i for i, t in enumerate(gt.timestamps_ns.tolist())}
        kfs = [kf for kf in keyframes if kf.timestamp_ns in index]
        g = gt.world_from_cam[np.array([index[kf.timestamp_ns] for kf in kfs])]
        return _ate_m(np.array([est[kf.id] for kf in kfs]), g)

    ate = keyframe_ate(backend.estimate(landmarks=False).world_from_kf)
    extra: dict[str, Any] = {}
    if final:
        t0 = time.thread_time()
        final_ate = keyframe_ate(backend.final_estimate(config.refine).world_from_kf)
        extra = {"final_keyframe_ate_m": round(final_ate, 5) if final_ate is not None else None,
                 "final_s": round(time.thread_time() - t0, 1)}
    return {
        "keyframes": len(keyframes),
        "loops": len(loop_ms),
        "backend_ms_by_keyframes": curve,
        "backend_ms_last_over_first": round(curve[-1][1] / curve[0][1], 3) if len(curve) > 1 and curve[0][1] else None,
        "loop_ms_by_keyframes": loop_ms,
        "cpu_s_by_call": {k: round(v, 2) for k, v in by_call.items()},
        "keyframe_ate_m": round(ate, 5) if ate is not None else None,
        "factors": backend.num_factors,
        "landmarks": backend.num_landmarks,
        **extra,
    }


def main(argv: list[str] | None = None) -> int:
    """``record SCAN OUT``: the back end's calls over a scan; ``replay CALLS [JSON backend keys]``: them again."""
    import argparse

    parser = argparse.ArgumentParser(description="the back end's calls of a scale scan, recorded and replayed")
    sub = parser.add_subparsers(dest="cmd", required=True)
    rec = sub.add_parser("record")
    rec.add_argument("scan", type=Path)
    rec.add_argument("out", type=Path)
    rep = sub.add_parser("replay")
    rep.add_argument("calls", type=Path)
    rep.add_argument("backend", nargs="?", default="{}", help='backend keys as JSON, e.g. \'{"relinearize_skip": 10}\'')
    rep.add_argument("--final", action="store_true", help="also the final estimate's keyframe ATE")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    if args.cmd == "record":
        print(record_backend_calls(args.scan, args.out), "calls")
        return 0
    config = Config()
    config.backend = config.backend.model_copy(update=json.loads(args.backend))
    print(json.dumps(replay_backend_calls(args.calls, config, final=args.final)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
