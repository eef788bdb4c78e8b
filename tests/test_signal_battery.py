"""Ctrl-C and SIGTERM at 20 seeded moments across a run (frames, keyframes, the final writes;
every fourth time a second signal follows): `loopmodel run` exits 130 (0 when the signal
came after the run had finished its work), and every time every result file is complete
and parseable, ``metrics.json`` saying how many frames it covers, with nothing left behind
(no staging folder, no lock, no temporary file)."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from frontend_scene import write_kitti_folder

from loopmodel.cli import main
from loopmodel.io.trajectory_io import read_trajectory

N_FRAMES = 12
CONFIG = "frontend:\n  max_disparity_px: 64\n  max_features: 300\n  min_tracked_fraction: 0.95\n"


def _check(out: Path) -> dict[str, object]:
    m = json.loads((out / "metrics.json").read_text())
    online = read_trajectory(out / "trajectory_online.tum")
    final = read_trajectory(out / "trajectory_final.tum")
    kfs = read_trajectory(out / "keyframes.tum")
    z = np.load(out / "map.npz")
    interrupted = bool(m["interrupted"])
    assert 1 <= int(m["frames"]) <= N_FRAMES and len(online) == m["ok_frames"] and len(final) == len(online)
    assert z["keyframe_ids"].size == len(kfs) == m["keyframes"]
    log = (out / "run.log").read_text()
    assert ("interrupted after" in log) is interrupted
    leftovers = [p.name for p in out.parent.iterdir() if p.name.startswith(".")] + [
        p.name for p in out.iterdir() if ".tmp-" in p.name
    ]
    assert not leftovers, leftovers
    return m


@pytest.mark.slow
def test_signals_at_seeded_times_leave_complete_results(tmp_path: Path) -> None:
    seq = tmp_path / "seq"
    write_kitti_folder(seq, N_FRAMES, np.random.default_rng(11))
    cfg = tmp_path / "c.yaml"
    cfg.write_text(CONFIG)
    args = ["run", str(seq), "--config", str(cfg), "--out", str(tmp_path / "out")]
    assert main([*args, "--name", "warm"]) == 0  # imports and caches
    t0 = time.perf_counter()
    assert main([*args, "--name", "ref"]) == 0
    t_ref = time.perf_counter() - t0
    assert _check(tmp_path / "out" / "ref")["interrupted"] is False
    rng = np.random.default_rng(24)
    outcomes = []
    for k in range(20):
        signum = signal.SIGINT if k % 2 == 0 else signal.SIGTERM
        delay = float(rng.uniform(0.0, 0.9 * t_ref))
        done = threading.Event()

        def fire(signum: int = signum, twice: bool = k % 4 == 3, done: threading.Event = done) -> None:
            for _ in range(2 if twice else 1):  # a second Ctrl-C during the writes
                if done.is_set():
                    return
                os.kill(os.getpid(), signum)
                time.sleep(0.2)

        timer = threading.Timer(delay, fire)
        name = f"cut{k}"
        timer.start()
        try:
            rc = main([*args, "--name", name])
        finally:
            done.set()
            timer.cancel()
            timer.join()
        assert rc in (0, 130), (k, delay, rc)
        folder = tmp_path / "out" / name
        if rc == 130 and not folder.exists():  # stopped before the run had started
            outcomes.append((rc, 0))
            continue
        m = _check(folder)
        assert rc == 130 or not m["interrupted"], (k, delay)
        outcomes.append((rc, int(m["frames"]) if m["interrupted"] else N_FRAMES))
    # the seeded times cover the run: most runs are cut, at different frames
    cut = [f for rc, f in outcomes if rc == 130 and 0 < f < N_FRAMES]
    assert len(cut) >= 10 and len(set(cut)) >= 4, outcomes
