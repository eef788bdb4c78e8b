"""What users see of ``loopmodel eval`` (issue 35 item 3): the report's HTML, units, labels, plot mode."""

from __future__ import annotations

import json
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from loopmodel.cli import main
from loopmodel.config import EvalConfig
from loopmodel.eval import report as rep
from loopmodel.eval.plots import resolve_plot_mode
from loopmodel.eval.render import PLOT_RPE_TIME, PLOT_TOP, PLOT_XYZ_RPY, captions
from loopmodel.geometry.se3 import make_pose, so3_exp
from loopmodel.io.trajectory_io import write_trajectory
from loopmodel.types import Trajectory


class _Text(HTMLParser):
    """The visible text of an HTML page, and the tags it uses."""

    def __init__(self) -> None:
        super().__init__()
        self.text: list[str] = []
        self.tags: list[str] = []
        self._skip = 0

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append(tag)
        self._skip += tag in ("style", "title")

    def handle_endtag(self, tag: str) -> None:
        self._skip -= tag in ("style", "title")

    def handle_data(self, data: str) -> None:
        if not self._skip:
            self.text.append(data)


def _scan_run(folder: Path, rng: np.random.Generator, camera_frame: bool) -> Trajectory:
    """A 1.2 m close-range scan (results folder) with a loop closure; returns its ground truth.

    ``camera_frame``: the ground truth starts at the identity (KITTI convention, y down), else a
    z-up world.
    """
    n = 120
    t = 1_000_000_000 + np.arange(n, dtype=np.int64) * 50_000_000
    s = np.linspace(0, 2 * np.pi, n, endpoint=False)
    pos = np.stack([0.5 * np.sin(s), 0.02 * np.sin(2 * s), 0.5 - 0.5 * np.cos(s)], axis=1)
    gt_T = np.stack([make_pose(so3_exp([0.0, a, 0.0]), p) for a, p in zip(s, pos, strict=True)])
    if not camera_frame:  # the same path in a z-up world: x right, y forward, z up
        world_from_cam0 = make_pose(np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]), [1.0, 2.0, 0.3])
        gt_T = world_from_cam0 @ gt_T
    gt = Trajectory(t, gt_T)
    online_T = gt_T.copy()
    online_T[:, :3, 3] += np.linspace(0, 1, n)[:, None] * [0.01, 0.0, 0.0]
    final_T = gt_T.copy()
    final_T[:, :3, 3] += 0.0005 * rng.standard_normal((n, 3))
    folder.mkdir(parents=True)
    write_trajectory(folder / "trajectory_online.tum", Trajectory(t, online_T))
    write_trajectory(folder / "trajectory_final.tum", Trajectory(t, final_T))
    metrics = {
        "frames": n,
        "mesh_vertices": 99022.0,
        "mesh_err_before_mm": 3.5,
        "mesh_err_after_mm": 1.2,
        "mesh_completeness_swept_before": 0.4,
        "mesh_completeness_swept_after": 0.6,
        "loop_closures": [
            {
                "timestamp_ns": int(t[100]),
                "match_keyframe": 0,
                "inliers": 87,
                "correction_m": 0.0,
                "correction_deg": 0.0,
            }
        ],
    }
    (folder / "metrics.json").write_text(json.dumps(metrics))
    return gt


def test_report_html_is_rendered_markdown(
    tmp_path: Path, rng: np.random.Generator, capsys: pytest.CaptureFixture[str]
) -> None:
    gt = _scan_run(tmp_path / "scan", rng, camera_frame=True)
    write_trajectory(tmp_path / "gt.tum", gt)
    out = tmp_path / "eval"
    assert main(["eval", str(tmp_path / "scan"), "--gt", str(tmp_path / "gt.tum"), "-o", str(out)]) == 0
    assert f"report: {out / 'report.html'}" in capsys.readouterr().out  # the table points at the HTML
    page = _Text()
    page.feed((out / "report.html").read_text())
    text = "".join(page.text)
    assert "`" not in text and "**" not in text  # Markdown rendered, not shown
    assert {"strong", "code", "table", "img", "em"} <= set(page.tags)
    assert page.tags.count("img") == len([p for p in out.glob("*.png")])
    md = (out / "report.md").read_text()
    # one unit for the close-range scan (mm), stated in the headers; no raw keys, no None
    assert "ATE RMSE [mm]" in md and "[m]" not in md.replace("(100 m)", "")
    assert "None" not in md and "mesh_completeness_swept" not in md and "99022.0" not in md
    assert "| mesh vertices | 99022 |" in md
    # no empty KITTI-segment columns on a short path; the measured correction only, once
    assert "KITTI t error" not in md
    closures = md.split("## Loop closures")[1].split("##")[0]
    assert closures.count("correction [") == 2  # distance and angle, measured; the recorded copies dropped
    for name, caption in captions(
        rep.evaluate_run(
            rep.load_run(tmp_path / "scan"), rep.load_ground_truth(tmp_path / "gt.tum"), EvalConfig(plots=False)
        )
    ).items():
        if (out / name).is_file():
            assert f"*{caption}*" in md
    assert (out / PLOT_XYZ_RPY).is_file() and (out / PLOT_RPE_TIME).is_file()


def test_plot_mode_follows_the_ground_truth_frame(tmp_path: Path, rng: np.random.Generator) -> None:
    """Camera-frame ground truth (y down) is seen from above in xz; a z-up world in xy, as evo."""
    cam = _scan_run(tmp_path / "cam", rng, camera_frame=True)
    world = _scan_run(tmp_path / "world", rng, camera_frame=False)
    assert resolve_plot_mode("auto", cam.world_from_cam) == "xz"
    assert resolve_plot_mode("auto", world.world_from_cam) == "xy"
    assert resolve_plot_mode("yz", cam.world_from_cam) == "yz"
    # a KITTI-like drive: long along z, the road's bumps in y larger than the lateral x drift (the
    # plane of the two largest extents would be yz, a side view)
    n = 50
    drive = np.stack([make_pose(np.eye(3), [0.01 * np.sin(k), 0.3 * np.sin(0.5 * k), 2.0 * k]) for k in range(n)])
    drive[0] = np.eye(4)
    assert resolve_plot_mode("auto", drive) == "xz"
    ev = rep.evaluate_run(rep.load_run(tmp_path / "cam"), rep.TimedTrajectory(cam, "gt", True), EvalConfig(plots=False))
    assert "xz plane" in captions(ev)[PLOT_TOP]
    with pytest.raises(ValueError):
        resolve_plot_mode("top", cam.world_from_cam)


def test_plot_mode_option(tmp_path: Path, rng: np.random.Generator) -> None:
    gt = _scan_run(tmp_path / "scan", rng, camera_frame=True)
    write_trajectory(tmp_path / "gt.tum", gt)
    out = tmp_path / "e"
    args = ["eval", str(tmp_path / "scan"), "--gt", str(tmp_path / "gt.tum"), "-o", str(out), "--no-plots"]
    assert main([*args, "--plot-mode", "xyz"]) == 0
    assert json.loads((out / "metrics.json").read_text())["options"]["plot_mode"] == "xyz"
    ev = rep.evaluate_run(
        rep.load_run(tmp_path / "scan"),
        rep.load_ground_truth(tmp_path / "gt.tum"),
        EvalConfig(plots=False, plot_mode="xyz"),
    )
    assert "in 3-D" in captions(ev)[PLOT_TOP]
    assert main([*args, "--plot-mode", "top"]) == 2


def _not_blank(png: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(png))
    assert img is not None, png
    assert (
        float(img.std()) > 20 and len(np.unique((img.reshape(-1, 3) // 32).astype(np.int32) @ np.array([64, 8, 1]))) > 3
    ), png
    return img


def test_readme_shows_the_report_and_the_rerun_view() -> None:
    root = Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text()
    for name in ("docs/img/eval_report.png", "docs/img/rerun_view.png"):
        assert f"]({name})" in readme
        png = root / name
        assert png.stat().st_size < 300_000  # small, committed
        assert _not_blank(png).shape[1] >= 800


@pytest.mark.slow  # chromium's start-up: about 10 s
def test_screenshot_report_draws_the_page(tmp_path: Path, rng: np.random.Generator) -> None:
    import shutil
    import subprocess

    if shutil.which("chromium") is None:
        pytest.skip("tools/screenshot_report.sh needs Debian's chromium")
    gt = _scan_run(tmp_path / "scan", rng, camera_frame=True)
    write_trajectory(tmp_path / "gt.tum", gt)
    assert main(["eval", str(tmp_path / "scan"), "--gt", str(tmp_path / "gt.tum"), "-o", str(tmp_path / "e")]) == 0
    root = Path(__file__).resolve().parents[1]
    png = tmp_path / "page.png"
    subprocess.run(
        ["bash", str(root / "tools" / "screenshot_report.sh"), str(tmp_path / "e" / "report.html"), str(png)],
        check=True,
        capture_output=True,
        timeout=120,
        env={**__import__("os").environ, "HEIGHT": "1600"},
    )
    assert _not_blank(png).shape[:2] == (1600, 1200)
