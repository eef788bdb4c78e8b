"""Diagnostic (issue 33, fr16): where a long scan's frame time goes, by part, first block against last.

``python tools/frame_parts.py [SCAN] [--block N] [--gc-freeze]``: runs the scale bench's
measurement (:func:`bench_scale.measure`) over ``SCAN`` (default the quick ``rounds_1800`` scan) with
the pipeline's per-frame parts timed (wall ms and the tracking thread's CPU ms, summed per frame):
the frame's step and the work between steps, the front end's parts, the loop stage, the back end's
calls as the tracking thread sees them, the corrections, the live mesh's hand-over; the garbage
collector's pauses (``gc.callbacks``: per block, their count and the longest), the local map's size,
and each thread's and worker process's CPU per frame (psutil, sampled every 10 frames). Prints the
scale keys, then each part's mean per frame (wall, CPU) in the first and last blocks of ``N`` frames
(N = 200).
"""

from __future__ import annotations

import functools
import gc
import json
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

FRAME: list[int] = [0]
WALL: dict[str, dict[int, float]] = {}
CPU: dict[str, dict[int, float]] = {}
SIZES: dict[str, dict[int, float]] = {}
MAIN = threading.main_thread()


def _add(table: dict[str, dict[int, float]], label: str, value: float) -> None:
    row = table.setdefault(label, {})
    row[FRAME[0]] = row.get(FRAME[0], 0.0) + value


def wrap(owner: Any, name: str, label: str) -> None:
    """Time ``owner.name`` (a class's method or a module's function) when called on the tracking thread."""
    inner = getattr(owner, name)

    @functools.wraps(inner)
    def timed(*args: Any, **kwargs: Any) -> Any:
        if threading.current_thread() is not MAIN:
            return inner(*args, **kwargs)
        t0, c0 = time.perf_counter(), time.thread_time()
        try:
            return inner(*args, **kwargs)
        finally:
            _add(WALL, label, (time.perf_counter() - t0) * 1e3)
            _add(CPU, label, (time.thread_time() - c0) * 1e3)

    setattr(owner, name, timed)


_gc_t0: list[float] = [0.0]
GC_MAX: dict[int, float] = {}  # generation -> longest pause (ms) on the tracking thread
GC_COUNT: dict[int, int] = {}
GC_FULL: list[tuple[int, float, int]] = []  # each full pass: (frames so far, ms, objects frozen then)
THREAD_CPU: dict[int, dict[str, float]] = {}  # frame -> thread or child name -> cumulative CPU s


def _sample_threads() -> None:
    """Every thread's and child process's CPU so far (psutil, when installed: not a dependency), by name."""
    try:
        import psutil
    except ImportError:
        return

    me = psutil.Process()
    names = {t.native_id: t.name for t in threading.enumerate()}
    row: dict[str, float] = {}
    for t in me.threads():
        name = names.get(t.id, "other")
        row[name] = row.get(name, 0.0) + t.user_time + t.system_time
    for c in me.children(recursive=True):
        try:
            ct = c.cpu_times()
            key = "child:" + " ".join(c.cmdline()[-1:])[-30:]
            row[key] = row.get(key, 0.0) + ct.user + ct.system
        except psutil.Error:
            pass
    THREAD_CPU[FRAME[0]] = row


def _gc(phase: str, info: dict[str, Any]) -> None:
    if threading.current_thread() is not MAIN:
        return
    if phase == "start":
        _gc_t0[0] = time.perf_counter()
    else:
        ms = (time.perf_counter() - _gc_t0[0]) * 1e3
        _add(WALL, f"gc{info['generation']}", ms)
        GC_MAX[info["generation"]] = max(GC_MAX.get(info["generation"], 0.0), ms)
        GC_COUNT[info["generation"]] = GC_COUNT.get(info["generation"], 0) + 1
        if info["generation"] == 2:
            GC_FULL.append((FRAME[0], round(ms, 1), gc.get_freeze_count()))


def install() -> None:
    """The wrappers on the pipeline's parts."""
    import loopmodel.frontend.tracker as tr
    import loopmodel.pipeline as pl
    from loopmodel.loop.stage import LoopClosingStage
    from loopmodel.mapping.anchored import AnchoredTrajectory
    from loopmodel.mapping.live import LiveMapping

    step = pl._Run.step

    def counted(self: Any, frame: Any) -> Any:
        FRAME[0] += 1
        fe = self.frontend
        SIZES.setdefault("local_sets", {})[FRAME[0]] = len(fe._local)
        SIZES.setdefault("local_points", {})[FRAME[0]] = float(sum(ls.idx.size for ls in fe._local))
        SIZES.setdefault("active_tracks", {})[FRAME[0]] = float(fe._track_idx.size)
        SIZES.setdefault("keyframes", {})[FRAME[0]] = float(len(self.keyframes))
        SIZES.setdefault("gc_objects", {})[FRAME[0]] = float(len(gc.get_objects(2))) if FRAME[0] % 50 == 0 else np.nan
        if FRAME[0] % 10 == 0:
            _sample_threads()
        return step(self, frame)

    pl._Run.step = counted  # type: ignore[method-assign]
    wrap(pl._Run, "step", "step")
    for name in ("_hand_waiting_keyframes", "_loops_between_frames", "_keyframe_step", "_correct", "_state"):
        wrap(pl._Run, name, name.strip("_"))
    wrap(LoopClosingStage, "on_keyframe", "loop.on_keyframe")
    wrap(LoopClosingStage, "between_frames", "loop.between_frames")
    for name in ("process", "prepare", "left_ahead", "finish_keyframes", "_match_ahead", "_track", "_klt_frame",
                 "_pose_terms", "_need_keyframe", "_keyframe_ahead", "_start_keyframe", "_finish_local_ba",
                 "_track_resumed", "apply_correction", "_commit_tracks", "_local_prediction", "tracked_features"):
        wrap(tr.FrontEnd, name, "fe." + name.strip("_"))
    wrap(tr, "build_pyramid", "fe.build_pyramid")
    for name in ("feed", "on_keyframe"):
        wrap(LiveMapping, name, "live." + name)
    for name in ("add_frame", "set_keyframe", "update_keyframes"):
        wrap(AnchoredTrajectory, name, "anchored." + name)
    wrap(pl._LaserFeed, "take", "laser.take")
    wrap(pl._LaserFeed, "new_profiles", "laser.new_profiles")
    start = pl.start_backend

    def started(*args: Any, **kwargs: Any) -> Any:
        backend = start(*args, **kwargs)
        for name in ("add_keyframe", "estimate", "add_loop_constraint", "add_observations"):
            if hasattr(type(backend), name):
                wrap(type(backend), name, "backend." + name)
        return backend

    pl.start_backend = started  # type: ignore[assignment]
    gc.callbacks.append(_gc)


def report(result: dict[str, Any], block: int) -> None:
    """Each part's mean ms per frame (wall, CPU) in the first and last blocks of ``block`` frames."""
    n = FRAME[0]
    first, last = range(2, block + 2), range(n - block + 1, n + 1)
    print(json.dumps({k: result[k] for k in ("frames", "keyframes", "loops", "frame_ms_last_over_first",
                                             "frame_cpu_ms_last_over_first", "frame_ms_by_frames",
                                             "frame_cpu_ms_by_frames", "ate_rmse_after_m")}))
    rows = []
    for label in sorted(set(WALL) | set(SIZES)):
        if label in SIZES:
            v = SIZES[label]
            a = np.nanmean([v.get(i, np.nan) for i in first])
            b = np.nanmean([v.get(i, np.nan) for i in last])
            rows.append((label, "size", a, b, np.nan, np.nan))
            continue
        w, c = WALL[label], CPU.get(label, {})
        rows.append((label, "ms", sum(w.get(i, 0.0) for i in first) / block, sum(w.get(i, 0.0) for i in last) / block,
                     sum(c.get(i, 0.0) for i in first) / block, sum(c.get(i, 0.0) for i in last) / block))
    print("gc on the tracking thread: collections", GC_COUNT, "longest ms", {k: round(v, 1) for k, v in GC_MAX.items()})
    print("full passes (frames so far, ms, frozen objects):", GC_FULL)
    fr = sorted(THREAD_CPU)
    if fr:
        a0 = THREAD_CPU[min(fr, key=lambda f: abs(f - first.start))]
        a1 = THREAD_CPU[min(fr, key=lambda f: abs(f - first.stop))]
        b0 = THREAD_CPU[min(fr, key=lambda f: abs(f - last.start))]
        b1 = THREAD_CPU[min(fr, key=lambda f: abs(f - last.stop))]
        print("thread/child CPU ms per frame, first block / last block")
        for k in sorted(set(a1) | set(b1)):
            x = (a1.get(k, 0.0) - a0.get(k, 0.0)) * 1e3 / block
            y = (b1.get(k, 0.0) - b0.get(k, 0.0)) * 1e3 / block
            print(f"  {k:40s} {x:8.2f} {y:8.2f}")
    print(f"{'part':32s} {'wall first':>10s} {'wall last':>10s} {'cpu first':>10s} {'cpu last':>10s}")
    for label, kind, a, b, ca, cb in rows:
        print(f"{label:32s} {a:10.3f} {b:10.3f} {ca:10.3f} {cb:10.3f}  {kind}")


def main() -> int:
    import argparse

    import bench_scale

    from loopmodel.config import Config

    p = argparse.ArgumentParser()
    p.add_argument("scan", nargs="?", type=Path, default=bench_scale.CACHE / "rounds_1800.mcap")
    p.add_argument("--block", type=int, default=200)
    p.add_argument("--gc-freeze", action="store_true", help="gc.freeze() once the run has started")
    p.add_argument("--config", default="{}", help="JSON of section -> {key: value} overrides")
    args = p.parse_args()
    install()
    config = Config()
    for section, keys in json.loads(args.config).items():
        setattr(config, section, getattr(config, section).model_copy(update=keys))
    if args.gc_freeze:
        import loopmodel.pipeline as pl

        step = pl._Run.step

        def freezing(self: Any, frame: Any) -> Any:
            if FRAME[0] == 30:
                gc.collect()
                gc.freeze()
            return step(self, frame)

        pl._Run.step = freezing  # type: ignore[method-assign]
    result = bench_scale.measure(args.scan, 1, args.block, config)
    report(result, args.block)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
