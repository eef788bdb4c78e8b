"""``tools/bench.py peer`` without the ORB-SLAM3 peer: one clear line, no run (CI never has the peer)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

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
