"""Issue 32: every function on the per-frame and per-keyframe path at ruff complexity (C901) <= 12.

The modules of the run's recipe, the back-end worker, the live mapping and the local hybrid BA run at
every keyframe, checked by ruff's McCabe rule (the issue's measure) at the limit 12.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HOT = [
    "loopmodel/pipeline.py",
    "loopmodel/frontend/hybrid_ba.py",
    "loopmodel/backend/worker.py",
    "loopmodel/mapping/live.py",
    "loopmodel/mapping/anchored.py",
    "loopmodel/mapping/stripe_map.py",
]


def _ruff() -> str | None:
    here = Path(sys.executable).parent / "ruff"
    return str(here) if here.is_file() else shutil.which("ruff")


def _c901(paths: list[Path], limit: int) -> subprocess.CompletedProcess[str]:
    ruff = _ruff()
    if ruff is None:
        pytest.skip("ruff is not installed")
    cmd = [ruff, "check", "--no-cache", "--isolated", "--select", "C901",
           "--config", f"lint.mccabe.max-complexity={limit}", *map(str, paths)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60)


def test_the_check_finds_a_complex_function(tmp_path: Path) -> None:
    branches = "".join(f"    if a == {i}:\n        return {i}\n" for i in range(13))
    (tmp_path / "m.py").write_text(f"def f(a):\n{branches}    return -1\n")
    out = _c901([tmp_path / "m.py"], 12)
    assert out.returncode == 1 and "C901" in out.stdout  # 14 > 12


def test_hot_path_functions_are_at_most_12() -> None:
    out = _c901([ROOT / m for m in HOT], 12)
    assert out.returncode == 0, out.stdout
