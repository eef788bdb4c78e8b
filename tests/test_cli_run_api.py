"""Issue 32 item 5: ``loopmodel run`` calls the public API (``loopmodel.run``), not a use case of its own."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("frontend_only", [False, True])
def test_cli_run_goes_through_loopmodel_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, frontend_only: bool
) -> None:
    import loopmodel
    from loopmodel.cli import main

    real = loopmodel.run
    calls: list[dict[str, Any]] = []

    def recorded(source: Any, config: Any = None, out_dir: Any = None, **kwargs: Any) -> Any:
        calls.append({"config": config, "out_dir": out_dir, **kwargs})
        return real(source, config, out_dir, **kwargs)

    monkeypatch.setattr(loopmodel, "run", recorded)
    args = ["run", str(ROOT / "datasets" / "tiny_kitti"), "--out", str(tmp_path), "--name", "r", "--max-frames", "4"]
    assert main([*args, "--frontend-only"] if frontend_only else args) == 0
    assert len(calls) == 1
    call = calls[0]
    assert call["out_dir"] == tmp_path and call["name"] == "r" and call["max_frames"] == 4
    assert call["handle_signals"] and call["evaluate"]
    # --frontend-only: the front end's configuration (no back end, no loop closing, no mesh)
    assert (call["config"].backend.kind == "none") == frontend_only
    if frontend_only:
        assert not call["config"].loop.enabled and not call["config"].mapping.write_mesh
    m = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert m["frames"] == 4 and "finish_s" in m


def test_the_returned_metrics_hold_the_write_time(tmp_path: Path) -> None:
    """Issue 32: the results' write is the last finishing step; its time is in the returned metrics.

    ``metrics.json`` is written during that step, so it has the steps before it only; the returned
    ``wall_s`` is the frame loop and every finishing step, the write included.
    """
    import loopmodel

    result = loopmodel.run(ROOT / "datasets" / "tiny_kitti", None, tmp_path, name="w", max_frames=4)
    steps = result.metrics["finish_s"]
    assert steps["write"] > 0
    assert result.metrics["wall_s"] == pytest.approx(result.metrics["frames_s"] + sum(steps.values()))
    written = json.loads((tmp_path / "w" / "metrics.json").read_text())
    assert "write" not in written["finish_s"]
    assert written["wall_s"] == pytest.approx(written["frames_s"] + sum(written["finish_s"].values()))
