"""Benchmark of the sequence readers on the KITTI clip as a folder and as bags.

The KITTI clip (51 real 1226x370 stereo pairs) as a folder and written with ``rosbags``' writers as
a ROS 2 sqlite3 bag, a ROS 2 MCAP bag and a ROS 1 bag (mono8, lossless), plus PNG- and
JPEG-compressed variants and an unsynchronised MCAP bag (right stamps 2 ms late, two right images
missing): that one is compared with the folder without the two pairs the reader must drop
(``max_pose_diff_ros2_mcap_unsync``), and with the full folder at the common stamps
(``..._vs_full_folder``).

``read_ms_per_frame_<format>``: median over 3 passes (interleaved over the formats) of the
time to stream every stereo pair (decoded, as the pipeline gets them), per pair, and
``read_cpu_ms_per_frame_<format>`` the reading thread's CPU time; ``read_overhead_ms_<format>``
(``read_cpu_overhead_ms_<format>``) is that minus the folder reader's in the same run (goal
<= 2 ms). ``max_pose_diff_<format>``: the largest
difference of the final trajectory of ``loopmodel run`` (``configs/kitti.yaml``) on the
format against the run on the folder (metres for translation, radians for rotation; 0 for
lossless encodings). ``peak_rss_mib``: the peak resident memory of a child process that
streams a bag of ``bag_mib`` (2 GiB; 200 MiB with ``--quick``) made of the clip's frames.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from shared_data import SHARED_DATA

ROOT = Path(__file__).resolve().parents[1]
SHARED = SHARED_DATA
CLIP = (SHARED / "kitti_clip").resolve()
TINY = ROOT / "datasets" / "tiny_kitti"

# name -> (bag kind, image encoding)
FORMATS = {
    "ros2_sqlite3": ("ros2-sqlite3", "mono8"),
    "ros2_mcap": ("ros2-mcap", "mono8"),
    "ros1": ("ros1", "mono8"),
    "ros2_sqlite3_png": ("ros2-sqlite3", "png"),
    "ros1_jpeg": ("ros1", "jpeg"),
}
# unsynchronised: right stamps 2 ms late and two right images missing (frames 3 and 4 of 6 in --quick)
UNSYNC = ("ros2_mcap_unsync", "ros2-mcap", "mono8", 2_000_000, (3, 20))


def _bag_path(tmp: Path, name: str, kind: str) -> Path:
    return tmp / (f"{name}.bag" if kind == "ros1" else name)


def write_bag(
    src: object, dst: Path, kind: str, encoding: str, repeat: int = 1, offset_ns: int = 0, drop: tuple[int, ...] = ()
) -> Path:
    """Write the frames of ``src`` (a Sequence) ``repeat`` times as a bag.

    Right stamps ``offset_ns`` after the left ones, right images of the frames ``drop`` left out.
    """
    from loopmodel.io.rosbag_writer import BagSequenceWriter
    from loopmodel.types import StereoFrame

    with BagSequenceWriter(dst, src.calibration, kind, encoding=encoding) as w:  # type: ignore[attr-defined]
        if src.ground_truth is not None and repeat == 1:  # type: ignore[attr-defined]
            w.write_trajectory(src.ground_truth)  # type: ignore[attr-defined]
        n = len(src)  # type: ignore[arg-type]
        for r in range(repeat):
            for f in src.frames():  # type: ignore[attr-defined]
                t = f.timestamp_ns + r * (n + 1) * 100_000_000
                w.write_frame(StereoFrame(t, f.left, f.right, f.index + r * n), offset_ns, f.index not in drop)
    return dst


def read_ms_per_frame(path: Path) -> tuple[float, float]:
    """Wall and CPU time (ms) per stereo pair of one pass streaming every pair.

    The CPU time of the reading thread is what a loaded machine disturbs least.
    """
    from loopmodel.io.sequence import open_sequence

    seq = open_sequence(path)
    t0, c0 = time.perf_counter(), time.thread_time()
    n = max(sum(1 for _f in seq.frames()), 1)
    return (time.perf_counter() - t0) * 1e3 / n, (time.thread_time() - c0) * 1e3 / n


def final_trajectory(path: Path, out: Path, name: str, max_frames: int | None) -> object:
    """Final ``world_from_cam`` poses of ``loopmodel run -c configs/kitti.yaml``.

    Each in its own process (runs in one process differ by ~1e-8 m through process state).
    """
    from loopmodel.io.trajectory_io import read_trajectory

    cmd = [sys.executable, "-m", "loopmodel", "run", str(path), "-c", str(ROOT / "configs" / "kitti.yaml")]
    cmd += ["--out", str(out), "--name", name]
    if max_frames is not None:
        cmd += ["--max-frames", str(max_frames)]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    subprocess.run(cmd, check=True, capture_output=True, env=env)
    return read_trajectory(out / name / "trajectory_final.tum", "tum")


def pose_diff(a: object, b: object) -> float:
    """Largest translation (m) or rotation (rad) difference of two trajectories at common timestamps.

    Inf when one misses a time of the other beyond dropped frames.
    """
    ta, tb = a.timestamps_ns, b.timestamps_ns  # type: ignore[attr-defined]
    common, ia, ib = np.intersect1d(ta, tb, return_indices=True)
    if len(common) == 0:
        return float("inf")
    A, B = a.world_from_cam[ia], b.world_from_cam[ib]  # type: ignore[attr-defined]
    dt = np.linalg.norm(A[:, :3, 3] - B[:, :3, 3], axis=1)
    # rotation angle from |Ra - Rb|_F = 2 sqrt(2) sin(angle / 2): exactly 0 for equal matrices
    # (arccos of the trace has a floor of 2e-8 rad from rounding)
    fro = np.linalg.norm(A[:, :3, :3] - B[:, :3, :3], axis=(1, 2))
    dr = 2.0 * np.arcsin(np.clip(fro / (2.0 * np.sqrt(2.0)), 0.0, 1.0))
    return float(max(dt.max(), dr.max()))


def folder_without(src: Path, dst: Path, drop: tuple[int, ...]) -> Path:
    """A KITTI folder of ``src``'s pairs without the frames ``drop``.

    Links to the images; times.txt and poses.txt filtered: the folder counterpart of a bag missing
    those pairs.
    """
    from loopmodel.io.kitti import IMAGE_DIRS

    a, b = next((x, y) for x, y in IMAGE_DIRS if (src / x).is_dir())
    for d in (a, b):
        (dst / d).mkdir(parents=True)
        for i, f in enumerate(sorted((src / d).iterdir())):
            if i not in drop:
                (dst / d / f.name).symlink_to(f.resolve())
    shutil.copy(src / "calib.txt", dst / "calib.txt")
    for name in ("times.txt", "poses.txt"):
        if (src / name).is_file():
            lines = [x for x in (src / name).read_text().splitlines() if x.strip()]
            (dst / name).write_text("\n".join(x for i, x in enumerate(lines) if i not in drop) + "\n")
    if not (src / "times.txt").is_file():
        n = len(list((src / a).iterdir()))
        (dst / "times.txt").write_text("".join(f"{i * 0.1:.6f}\n" for i in range(n) if i not in drop))
    return dst


# VmHWM (the peak of this process's own memory map; ru_maxrss would carry the parent's peak
# across fork and exec)
_CHILD = """
import sys
sys.path.insert(0, {root!r})
from loopmodel.io.sequence import open_sequence
n = sum(1 for _ in open_sequence({path!r}).frames())
hwm = next(x for x in open("/proc/self/status") if x.startswith("VmHWM:")).split()[1]
print(n, int(hwm) / 1024.0)
"""


def streaming_rss_mib(path: Path) -> tuple[int, float]:
    """(frames, peak RSS MiB) of a child process streaming every frame of ``path``."""
    code = _CHILD.format(root=str(ROOT), path=str(path))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    return int(out[0]), float(out[1])


def run(quick: bool = False) -> dict:
    from loopmodel.io.sequence import open_sequence

    src_path = CLIP if CLIP.is_dir() else TINY
    src = open_sequence(src_path)
    tmp = Path(tempfile.mkdtemp(prefix="bench_readers_"))
    result: dict[str, object] = {
        "input": str(src_path),
        "frames": len(src),
        "image_size": list(src.calibration.image_size),
    }
    try:
        paths = {"folder": src_path}
        for name, (kind, enc) in FORMATS.items():
            paths[name] = write_bag(src, _bag_path(tmp, name, kind), kind, enc)
        uname, ukind, uenc, uoff, udrop = UNSYNC
        udrop = (3, 4) if quick else udrop
        paths[uname] = write_bag(src, _bag_path(tmp, uname, ukind), ukind, uenc, offset_ns=uoff, drop=udrop)
        # passes interleaved over the formats, so that a change of machine load hits all alike
        runs: dict[str, list[tuple[float, float]]] = {name: [] for name in paths}
        for _ in range(1 if quick else 3):
            for name, p in paths.items():
                runs[name].append(read_ms_per_frame(p))
        for name in paths:
            result[f"read_ms_per_frame_{name}"] = round(statistics.median(w for w, _c in runs[name]), 3)
            result[f"read_cpu_ms_per_frame_{name}"] = round(statistics.median(c for _w, c in runs[name]), 3)
        for name in (*FORMATS, uname):
            result[f"read_cpu_overhead_ms_{name}"] = round(
                float(result[f"read_cpu_ms_per_frame_{name}"]) - float(result["read_cpu_ms_per_frame_folder"]),  # type: ignore[arg-type]
                3,
            )
            result[f"read_overhead_ms_{name}"] = round(
                float(result[f"read_ms_per_frame_{name}"]) - float(result["read_ms_per_frame_folder"]),
                3,  # type: ignore[arg-type]
            )
        max_frames = 6 if quick else None
        ref = final_trajectory(src_path, tmp / "runs", "folder", max_frames)
        # the unsynchronised bag against the folder without the two pairs it cannot pair
        ref_unsync = final_trajectory(
            folder_without(src_path, tmp / "folder_drop", udrop), tmp / "runs", "fd", max_frames
        )
        for name, p in paths.items():
            if name != "folder":
                est = final_trajectory(p, tmp / "runs", name, max_frames)
                if name == uname:
                    result[f"max_pose_diff_{name}_vs_full_folder"] = pose_diff(ref, est)
                    result[f"max_pose_diff_{name}"] = pose_diff(ref_unsync, est)
                    result[f"poses_{name}"] = len(est)  # type: ignore[arg-type]
                    continue
                result[f"max_pose_diff_{name}"] = pose_diff(ref, est)
                result[f"poses_{name}"] = len(est)  # type: ignore[arg-type]
        frame_mib = (src.calibration.image_size[0] * src.calibration.image_size[1] * 2) / 2**20
        target_mib = 200 if quick else 2048
        repeat = max(1, int(np.ceil(target_mib / (frame_mib * len(src)))))
        big = write_bag(src, tmp / "big", "ros2-sqlite3", "mono8", repeat=repeat)
        shutil.rmtree(tmp / "runs", ignore_errors=True)
        result["bag_mib"] = round(sum(q.stat().st_size for q in big.rglob("*")) / 2**20, 1)
        frames, rss = streaming_rss_mib(big)
        result["bag_frames"] = frames
        result["peak_rss_mib"] = round(rss, 1)
        result["bench_process_peak_rss_mib"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return result


if __name__ == "__main__":
    print(json.dumps(run("--quick" in sys.argv)))
