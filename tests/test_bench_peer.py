"""``tools/bench.py peer`` without the ORB-SLAM3 peer: one clear line, no run (CI never has the peer)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_bench_peer_skips_when_the_peer_is_missing(tmp_path: Path) -> None:
    env = {"LOOPMODEL_ORBSLAM3_PEER": str(tmp_path / "no_peer"), "PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    r = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "bench.py"), "peer", "--quick"],
        capture_output=True, text=True, env=env, timeout=60,
    )
    assert r.returncode == 0
    assert "skipped" in r.stdout.strip().splitlines()[-1]
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "no peer harness" in lines[0], r.stderr


def test_street_step_growth_reads_tum_against_kitti_poses(tmp_path: Path) -> None:
    """``bench peer``'s street key: the step-scale growth of a TUM trajectory against KITTI poses."""
    import numpy as np

    sys.path.insert(0, str(ROOT / "tools"))
    from bench_peer import _step_growth

    n = 41  # 40 steps of 1 m along z; the estimate's steps grow from 1.00 to 1.10 of the truth
    z = np.arange(n, dtype=float)
    gt = np.zeros((n, 12))
    gt[:, [0, 5, 10]] = 1.0
    gt[:, 11] = z
    np.savetxt(tmp_path / "poses.txt", gt)
    steps = 1.0 + 0.1 * np.arange(n - 1) / (n - 2)
    ez = np.concatenate([[0.0], np.cumsum(steps)])
    tum = np.column_stack([np.arange(n) / 10.0, np.zeros(n), np.zeros(n), ez, np.zeros((n, 3)), np.ones(n)])
    np.savetxt(tmp_path / "est.tum", tum[::-1])  # order does not matter: frames by their stamps
    # independent: 10 steps a quarter, summed estimated / summed true step lengths, last over first
    expected = steps[-10:].sum() / steps[:10].sum()
    assert _step_growth(tmp_path / "est.tum", tmp_path / "poses.txt") == pytest.approx(expected, abs=1e-5)
