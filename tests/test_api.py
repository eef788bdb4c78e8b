"""The public Python API.

The README's notebook example runs on the bundled KITTI sample, writes nothing, installs no signal
handler, and its trajectory matches the ground truth.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _readme_example() -> str:
    text = (ROOT / "README.md").read_text()
    m = re.search(r"## Python API.*?```python\n(.*?)```", text, re.S)
    assert m, "README has no Python API example"
    return m.group(1)


def _files(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*")}


def _ate_rmse_m(est: np.ndarray, ref: np.ndarray) -> float:
    """RMSE of positions after the least-squares rigid alignment (Kabsch, no scale)."""
    ce, cr = est.mean(axis=0), ref.mean(axis=0)
    U, _, Vt = np.linalg.svd((ref - cr).T @ (est - ce))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    aligned = (est - ce) @ R.T + cr
    return float(np.sqrt(np.mean(np.sum((aligned - ref) ** 2, axis=1))))


def test_readme_notebook_example_writes_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "datasets").symlink_to(ROOT / "datasets")
    monkeypatch.chdir(tmp_path)
    before_data = _files(ROOT / "datasets")
    handlers = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM))
    ns: dict[str, object] = {}
    exec(compile(_readme_example(), "README.md", "exec"), ns)
    assert [p.name for p in tmp_path.iterdir()] == ["datasets"]
    assert _files(ROOT / "datasets") == before_data
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == handlers
    result = ns["result"]
    from loopmodel import RunResult

    assert isinstance(result, RunResult) and result.folder is None and not result.interrupted
    # 8 frames of the sample; each one a keyframe (fast forward motion), all tracked
    assert len(result.frames) == 8 and len(result.final) == 8 and len(result.online) == 8
    assert len(result.keyframes) == len(result.keyframe_ids) >= 2
    assert result.landmarks_in_world.shape == (result.landmark_ids.size, 3) and result.landmark_ids.size > 100
    # against the sample's ground truth (KITTI poses.txt), aligned here independently
    gt = np.loadtxt(ROOT / "datasets" / "tiny_kitti" / "poses.txt").reshape(-1, 3, 4)[:, :, 3]
    err = _ate_rmse_m(result.final.positions_m, gt)
    assert err < 0.01  # measured 2.4 mm (0.31 m path)
    assert ns["positions_m"] is not None
    assert result.metrics["ate_rmse_m"] == pytest.approx(err, rel=1e-3, abs=1e-5)


def test_run_with_out_dir_writes_the_results_folder(tmp_path: Path) -> None:
    import loopmodel

    result = loopmodel.run(ROOT / "datasets" / "tiny_kitti", {"backend": {"kind": "none"}}, tmp_path, name="api")
    assert result.folder == tmp_path / "api"
    names = {p.name for p in result.folder.iterdir()}
    assert {"config.yaml", "trajectory_online.tum", "trajectory_final.tum", "keyframes.tum", "map.npz"} <= names
    assert {"metrics.json", "run.log"} <= names
    text = repr(result)  # one line saying where it went, not the 51,000-character config (issue 35)
    assert len(text) < 300 and "\n" not in text and f"folder='{tmp_path / 'api'}'" in text and "frames=" in text
    # trajectory files from the API, as evo's file_interface (issue 35)
    loopmodel.write_trajectory(tmp_path / "final.kitti", result.final)
    back = loopmodel.read_trajectory(tmp_path / "final.kitti")
    np.testing.assert_allclose(back.world_from_cam, result.final.world_from_cam, atol=1e-15)


def test_import_is_light() -> None:
    """``import loopmodel`` loads none of the heavy stages (the API is imported on use)."""
    heavy = "('gtsam', 'cv2', 'open3d', 'loopmodel.pipeline')"
    code = f"import sys, loopmodel; print(sorted(m for m in {heavy} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("module", ["loopmodel", "loopmodel.cli"])
def test_module_entry_points_run_every_command_group(module: str) -> None:
    out = subprocess.run(
        [sys.executable, "-m", module, "vvs", "--help"], capture_output=True, text=True, cwd=ROOT, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert "track" in out.stdout and "render" in out.stdout
