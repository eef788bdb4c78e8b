"""Benchmark ``peer`` (issue 36, item 5): our full pipeline beside ORB-SLAM3 stereo, alternating runs.

ORB-SLAM3 runs through the shared peer harness (``../shared/peers/orbslam3``: ``peer.py run`` in its
own venv; ``$LOOPMODEL_ORBSLAM3_PEER`` names another folder), our pipeline through the harness's
``ours_timing.py`` (our CLI plus per-frame CPU time), each as a subprocess, ours then the peer in
every round. Both trajectories (``trajectory_final.tum``) are scored by the harness's own
``peer.py eval`` routine: one routine for both systems.

Sequences: ``kitti_clip`` (the shared KITTI clip, ``configs/kitti.yaml``), ``orbit`` and ``modeler``
(the realistic simulated scans of ``bench sim-loop``: ``datasets/sample/scan.mcap`` and the
1,200-frame modeler ``~/.cache/loopmodel/modeler_1200.mcap``, generated when missing; ours with the
code defaults and the live mesh as ``configs/sim.yaml`` has it, as the issue's orbit target
says (``ours_live_mesh_every_kf``), the final mesh not written). The peer sees the scans through ``peer.py export-mcap``
(plain OpenCV rectification, cached in ``~/.cache/loopmodel``) with ORB-SLAM3's EuRoC values for 640x480
images (1,200 features, FAST 20/7, ThDepth 60); its rectified-camera poses are evaluated with
``--right-mult rect_from_cam0.txt``.

One object per sequence with ``ours_<k>`` and ``peer_<k>`` (medians over the rounds) for ``k`` in
:data:`KEYS`, ``rounds`` and ``load`` (the 1-min load average before each run: min, median, max);
on the KITTI clip also the drift and rotation error after the ground truth's constant-rate first
steps (``*_after_gt_segment``, as ``bench pipeline``) and our front end alone
(``ours_frontend_cpu_ms_per_frame``, ``ours_frontend_frame_ms_mean``). ``cpu_ms_per_frame`` is the
harness's figure, our main process only; ``ours_cpu_ms_per_frame_with_workers`` and
``cpu_ratio_with_workers_ours_over_peer`` add our worker processes over the same frames (back end,
loop detection, live mesh), which the peer's figure has as threads. ``--quick``: one round and
the first 150 frames of the scans. ``$LOOPMODEL_BENCH_PEER_ROUNDS`` sets the rounds,
``$LOOPMODEL_BENCH_PEER_ONLY`` (comma-separated names) the sequences, ``$LOOPMODEL_BENCH_PEER_OURS_CONFIG``
a YAML file layered over our configuration on every sequence (e.g. ``frontend.local_ba_keyframes``).
``street`` (only when named there): the seeded street scene of ``tests/test_street_scale.py``
(repetitive texture, cars, a 0.5 px right principal-point error; ``loopmodel.sim.street``) exported
to KITTI layout in ``~/.cache/loopmodel``, ``configs/kitti.yaml``; adds ``*_step_scale_last_over_first``.
Skips with one line when the peer is not set up.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from shared_data import SHARED_DATA

ROOT = Path(__file__).resolve().parents[1]
CACHE = Path.home() / ".cache" / "loopmodel"
KEYS = (
    "ate_se3_m", "ate_sim3_m", "sim3_scale", "drift_pct", "rot_err_deg",
    "frame_ms_mean", "frame_ms_p95", "cpu_ms_per_frame",
)
QUICK_FRAMES = 150
# ORB-SLAM3's EuRoC example values, for 640x480 images (the harness README)
SCAN_PEER_ARGS = ["--features", "1200", "--ini-fast", "20", "--th-depth", "60"]


def scan_live_mesh_every_kf() -> int:
    """How often our runs on the simulated scans re-mesh the live mesh: ``configs/sim.yaml``'s value (keyframes)."""
    from loopmodel.config import load_config

    return load_config(ROOT / "configs" / "sim.yaml").mapping.live_mesh_every_kf


def peer_dir() -> Path:
    """The ORB-SLAM3 peer harness folder."""
    env = os.environ.get("LOOPMODEL_ORBSLAM3_PEER")
    return Path(env) if env else SHARED_DATA.parent / "peers" / "orbslam3"


def peer_missing(folder: Path) -> str | None:
    """Why the peer cannot run (None when set up)."""
    if not (folder / "peer.py").is_file() or not (folder / "ours_timing.py").is_file():
        return f"no peer harness at {folder} (set LOOPMODEL_ORBSLAM3_PEER)"
    cache = Path(os.environ.get("ORBSLAM3_PEER_CACHE") or Path(
        os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "orbslam3-peer")
    if not (cache / "venv" / "bin" / "python").is_file():
        return f"ORB-SLAM3 peer not set up ({cache}/venv missing): run bash {folder}/setup.sh"
    return None


def _load() -> float:
    return os.getloadavg()[0]


def _check(cmd: list[str], what: str) -> str:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    if r.returncode != 0:
        tail = (r.stderr or r.stdout).strip().splitlines()[-3:]
        raise RuntimeError(f"{what} failed (exit {r.returncode}): " + " | ".join(tail))
    return r.stdout


def _eval(peer: Path, est: Path, gt: Path, extra: list[str]) -> dict[str, Any]:
    out = _check([sys.executable, str(peer / "peer.py"), "eval", str(est), str(gt), *extra], f"peer.py eval {est}")
    return dict(json.loads(out.strip().splitlines()[-1]))


def _export(peer: Path, scan: Path, name: str) -> Path:
    """``peer.py export-mcap`` of a scan, cached in ``~/.cache/loopmodel`` (redone when the scan is newer)."""
    folder = CACHE / f"{name}_peer_rect"
    stamp = folder / ".exported"
    if stamp.is_file() and stamp.stat().st_mtime >= scan.stat().st_mtime and stamp.read_text() == str(scan):
        return folder
    print(f"exporting {scan} -> {folder} ...", file=sys.stderr)
    _check([sys.executable, str(peer / "peer.py"), "export-mcap", str(scan), str(folder)], "peer.py export-mcap")
    stamp.write_text(str(scan))
    return folder


def _export_street(folder: Path) -> Path:
    """The street scene of ``tests/test_street_scale.py`` (seed 3, 40 frames at 1 m) in KITTI layout, cached."""
    import cv2

    from loopmodel.sim.street import StreetConfig, StreetScene

    if (folder / "poses.txt").is_file():
        return folder
    sc = StreetConfig(width_px=832, height_px=256, fx_px=480.0, frames=40, speed_m_per_frame=1.0, open_from_m=20.0,
                      supersample=1, right_cx_error_px=0.5, texture_size_px=512, seed=3, lead_speed_ratio=0.85,
                      lead_start_m=16.0)
    print(f"rendering the street scene -> {folder} ...", file=sys.stderr)
    scene = StreetScene.build(sc)
    tmp = folder.with_name(folder.name + ".tmp")
    for side in ("image_l", "image_r"):
        (tmp / side).mkdir(parents=True, exist_ok=True)
    for i in range(sc.frames):
        f = scene.render(i).frame
        cv2.imwrite(str(tmp / "image_l" / f"{i:06d}.png"), f.left)
        cv2.imwrite(str(tmp / "image_r" / f"{i:06d}.png"), f.right)
    p0 = np.hstack([scene.K, np.zeros((3, 1))])
    p1 = p0.copy()
    p1[0, 3] = -scene.K[0, 0] * sc.baseline_m  # the recorded calibration (the right image's cx is 0.5 px off)
    np.savetxt(tmp / "calib.txt", np.stack([p0.ravel(), p1.ravel()]), fmt="%.12e")
    gt = scene.ground_truth().world_from_cam
    np.savetxt(tmp / "poses.txt", gt[:, :3, :].reshape(len(gt), 12), fmt="%.9e")
    tmp.rename(folder)
    return folder


def _step_growth(tum: Path, gt: Path) -> float | None:
    """``step_scale_last_over_first`` of a TUM trajectory of 10 Hz frames against KITTI ``poses.txt``."""
    from bench_pipeline import read_kitti_poses, read_tum

    from loopmodel.eval.trajectory_metrics import step_scale_last_over_first

    ref = read_kitti_poses(gt)
    t, est = read_tum(tum)
    order = np.argsort(t)
    t, est = t[order], est[order]
    frame = np.rint(t * 10.0).astype(int)
    keep = (frame >= 0) & (frame < len(ref))
    if int(keep.sum()) < 3:
        return None
    return round(float(step_scale_last_over_first(ref[frame[keep]], est[keep])), 5)


def _trimmed(src: Path, first_frame: int, rate_hz: float, t0: float, dst: Path) -> Path:
    """The TUM file ``src`` from frame ``first_frame`` on (frame = round(rate (t - t0)))."""
    a = np.loadtxt(src, ndmin=2)
    keep = np.rint((a[:, 0] - t0) * rate_hz) >= first_frame
    np.savetxt(dst, a[keep], fmt="%.9f")
    return dst


class _Sequence:
    """One benchmark sequence: how to run each system on it and how to score the result."""

    def __init__(self, name: str, ours_input: Path, peer_input: Path, gt: Path, config: Path | None,
                 max_frames: int | None, scan: bool) -> None:
        self.name, self.ours_input, self.peer_input, self.gt = name, ours_input, peer_input, gt
        self.config, self.max_frames, self.scan = config, max_frames, scan

    def eval_args(self, ours: bool, tum: Path) -> list[str]:
        if not self.scan:
            return []  # KITTI clip: 10 Hz stamps from 0 on both sides
        args = ["--times", str(self.peer_input / "times.txt")]
        if ours:  # our stamps are the scan's (ns since its epoch)
            args += ["--t0", repr(float(np.loadtxt(tum, ndmin=2)[0, 0]))]
        else:  # rectified-camera poses -> raw camera
            args += ["--right-mult", str(self.peer_input / "rect_from_cam0.txt")]
        return args


def _run_ours(seq: _Sequence, peer: Path, tmp: Path, tag: str, frontend_only: bool = False) -> dict[str, Any]:
    # through tools/peer_ours.py: the harness's script has no __main__ guard, and our spawned
    # workers re-ran it and died
    cmd = [sys.executable, str(ROOT / "tools" / "peer_ours.py"), str(peer), "run", str(seq.ours_input),
           "--out", str(tmp), "--name", tag, "--overwrite"]
    if seq.config is not None:
        cmd += ["-c", str(seq.config)]
    extra = os.environ.get("LOOPMODEL_BENCH_PEER_OURS_CONFIG")
    if extra:
        cmd += ["-c", extra]
    if seq.max_frames:
        cmd += ["--max-frames", str(seq.max_frames)]
    if frontend_only:
        cmd.append("--frontend-only")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    _check(cmd, f"ours on {seq.name}")
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    folder = tmp / tag
    m = json.loads((folder / "metrics.json").read_text())
    ms = np.asarray(m.get("frame_total_ms_all", []), dtype=float)
    res: dict[str, Any] = {
        "frame_ms_mean": float(ms.mean()) if ms.size else None,
        "frame_ms_p95": float(np.percentile(ms, 95)) if ms.size else None,
        "cpu_ms_per_frame": m.get("cpu_ms_per_frame"),
        # our worker processes (back end, loop detection, live mesh) over the same frames: the peer's
        # figure has its local mapping and loop closing threads in it, ours (one process) does not
        "cpu_ms_per_frame_with_workers": (m["cpu_ms_per_frame"] + m["cpu_ms_per_frame_workers"])
        if m.get("cpu_ms_per_frame") is not None and m.get("cpu_ms_per_frame_workers") is not None else None,
        # the harness counts the main process during the frames; this is every process of the run
        # (back end, live mesh and extraction workers), start-up and finishing included
        "cpu_ms_per_frame_all_processes": 1e3
        * ((after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime))
        / max(int(m.get("frames") or ms.size or 1), 1),
        "keyframes": m.get("keyframes"),
        "tum": folder / "trajectory_final.tum",
    }
    return res


def _run_peer(seq: _Sequence, peer: Path, tmp: Path, tag: str) -> dict[str, Any]:
    cmd = [sys.executable, str(peer / "peer.py"), "run", str(seq.peer_input), "--out", str(tmp / tag)]
    if seq.max_frames:
        cmd += ["--max-frames", str(seq.max_frames)]
    if seq.scan:
        cmd += SCAN_PEER_ARGS
    _check(cmd, f"ORB-SLAM3 on {seq.name}")
    m = json.loads((tmp / tag / "metrics.json").read_text())
    return {
        "frame_ms_mean": m["frame_ms_mean"],
        "frame_ms_p95": m["frame_ms_p95"],
        "cpu_ms_per_frame": m["cpu_ms_per_frame"],
        "keyframes": m.get("keyframes"),
        "tum": tmp / tag / "trajectory_final.tum",
    }


def _score(seq: _Sequence, peer: Path, run: dict[str, Any], ours: bool, seg: int | None) -> dict[str, Any]:
    tum = run.pop("tum")
    e = _eval(peer, tum, seq.gt, seq.eval_args(ours, tum))
    run.update({k: e[k] for k in ("ate_se3_m", "ate_sim3_m", "sim3_scale", "drift_pct")})
    run["rot_err_deg"] = e["rot_err_final_deg"]
    if seq.name == "street":
        run["step_scale_last_over_first"] = _step_growth(tum, seq.gt)
    if seg is not None and seq.name == "kitti_clip":
        cut = _trimmed(tum, seg, 10.0, 0.0, tum.with_name("after_segment.tum"))
        e2 = _eval(peer, cut, seq.gt, [])
        run["drift_pct_after_gt_segment"] = e2["drift_pct"]
        run["rot_err_deg_after_gt_segment"] = e2["rot_err_final_deg"]
    return run


def _median(rows: list[dict[str, Any]], key: str) -> float | None:
    vals = [r[key] for r in rows if r.get(key) is not None]
    return round(float(np.median(vals)), 5) if vals else None


def _sequences(peer: Path, quick: bool, only: list[str]) -> list[_Sequence]:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_sim_loop import SAMPLE, _ensure

    clip = SHARED_DATA / "kitti_clip"
    n = QUICK_FRAMES if quick else None
    seqs = [_Sequence("kitti_clip", clip, clip, clip / "poses.txt", ROOT / "configs" / "kitti.yaml", None, False)]
    for name, make in (
        ("orbit", lambda: _ensure(SAMPLE / "scan.mcap", "orbit")),
        ("modeler", lambda: _ensure(CACHE / "modeler_1200.mcap", "modeler", frames=1200)),
    ):
        if only and name not in only:
            continue
        path = make()
        rect = _export(peer, path, name)
        seqs.append(_Sequence(name, path, rect, rect / "poses.txt", None, n, True))
    if "street" in only:  # opt-in: not one of issue 36's three sequences
        street = _export_street(CACHE / "street_seed3_kitti")
        seqs.append(_Sequence("street", street, street, street / "poses.txt", ROOT / "configs" / "kitti.yaml",
                              None, False))
    return seqs


def run(quick: bool = False) -> dict[str, Any]:
    peer = peer_dir()
    why = peer_missing(peer)
    if why is not None:
        print(f"bench peer: skipped: {why}", file=sys.stderr)
        return {"skipped": why}
    from bench_kitti_rotation import constant_rate_steps
    from bench_pipeline import read_kitti_poses

    rounds = int(os.environ.get("LOOPMODEL_BENCH_PEER_ROUNDS", 1 if quick else 3))
    only = [n for n in os.environ.get("LOOPMODEL_BENCH_PEER_ONLY", "").split(",") if n]
    seqs = [s for s in _sequences(peer, quick, only) if not only or s.name in only]
    seg = constant_rate_steps(read_kitti_poses(SHARED_DATA / "kitti_clip" / "poses.txt"))
    rows: dict[str, dict[str, list[dict[str, Any]]]] = {s.name: {"ours": [], "peer": [], "fe": []} for s in seqs}
    loads: dict[str, list[float]] = {s.name: [] for s in seqs}
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td)
        # a config that keeps our defaults but skips the final mesh (minutes after the last frame) and
        # keeps the live mesh on, as the orbit target says ("full pipeline with the live mesh";
        # every 5 keyframes as configs/sim.yaml and the pipeline bench's 300-frame orbit)
        live_every = scan_live_mesh_every_kf()
        nomesh = tmp / "nomesh.yaml"
        nomesh.write_text(f"mapping:\n  write_mesh: false\n  live_mesh_every_kf: {live_every}\n")
        for s in seqs:
            if s.scan:
                s.config = nomesh
        for r in range(rounds):
            for s in seqs:
                loads[s.name].append(_load())
                rows[s.name]["ours"].append(_score(s, peer, _run_ours(s, peer, tmp, f"{s.name}_ours{r}"), True, seg))
                loads[s.name].append(_load())
                rows[s.name]["peer"].append(_score(s, peer, _run_peer(s, peer, tmp, f"{s.name}_peer{r}"), False, seg))
                if s.name == "kitti_clip":  # our front end alone, for the front-end CPU target
                    loads[s.name].append(_load())
                    rows[s.name]["fe"].append(_run_ours(s, peer, tmp, f"{s.name}_fe{r}", frontend_only=True))
                loads[s.name].append(_load())
    out: dict[str, Any] = {"peer": str(peer), "quick": quick}
    for s in seqs:
        obj: dict[str, Any] = {}
        extra: tuple[str, ...] = ("keyframes",)
        if s.name == "kitti_clip":
            extra += ("drift_pct_after_gt_segment", "rot_err_deg_after_gt_segment")
        elif s.name == "street":
            extra += ("step_scale_last_over_first",)
        for who in ("ours", "peer"):
            for k in KEYS + extra:
                obj[f"{who}_{k}"] = _median(rows[s.name][who], k)
        obj["ours_cpu_ms_per_frame_all_processes"] = _median(rows[s.name]["ours"], "cpu_ms_per_frame_all_processes")
        obj["ours_cpu_ms_per_frame_with_workers"] = _median(rows[s.name]["ours"], "cpu_ms_per_frame_with_workers")
        if rows[s.name]["fe"]:
            obj["ours_frontend_cpu_ms_per_frame"] = _median(rows[s.name]["fe"], "cpu_ms_per_frame")
            obj["ours_frontend_frame_ms_mean"] = _median(rows[s.name]["fe"], "frame_ms_mean")
        # CPU ratios paired within each round, then the median
        for key, who, ours_key in (("cpu_ratio_ours_over_peer", "ours", "cpu_ms_per_frame"),
                                   ("cpu_ratio_with_workers_ours_over_peer", "ours", "cpu_ms_per_frame_with_workers"),
                                   ("frontend_cpu_ratio_ours_over_peer", "fe", "cpu_ms_per_frame")):
            pairs = zip(rows[s.name][who], rows[s.name]["peer"], strict=False)
            ratio = [o[ours_key] / p["cpu_ms_per_frame"] for o, p in pairs
                     if o.get(ours_key) and p.get("cpu_ms_per_frame")]
            if ratio:
                obj[key] = round(float(np.median(ratio)), 3)
        obj["frames"] = s.max_frames or "all"
        obj["rounds"] = rounds
        if s.scan:
            obj["ours_live_mesh_every_kf"] = live_every
        la = loads[s.name]
        obj["load"] = [round(min(la), 2), round(float(np.median(la)), 2), round(max(la), 2)]
        out[s.name] = obj
    return out
