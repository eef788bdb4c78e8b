"""Help and flags (issue 35 items 6 and 11): the flow's order, panels, examples, choices, layered configs."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from loopmodel.cli import app, main
from loopmodel.cli.help import EXAMPLES, FLOW


@pytest.fixture(autouse=True)
def _wide_help(monkeypatch: pytest.MonkeyPatch) -> None:
    """Help as on a 160-column terminal (no option column wrapped)."""
    from typer import rich_utils

    monkeypatch.setattr(rich_utils, "MAX_WIDTH", 160)


def _help(capsys: pytest.CaptureFixture[str], *args: str) -> str:
    assert main([*args, "--help"]) == 0
    return capsys.readouterr().out


def _commands(text: str) -> list[str]:
    return re.findall(r"^│ ([a-z][a-z-]+) ", text, flags=re.MULTILINE)


def test_top_level_help_follows_the_flow(capsys: pytest.CaptureFixture[str]) -> None:
    text = _help(capsys)
    assert _commands(text) == [name for name, _ in FLOW]
    panels = re.findall(r"╭─ ([A-Za-z ]+?) ─", text)
    assert panels == ["Options", "Workflow", "Calibration", "Settings", "Research tools"]
    workflow = text.split("Workflow")[1].split("╰")[0]
    assert "bound" not in workflow and "givens-sim" not in workflow
    assert "<bool>" not in text


def _all_commands() -> list[str]:
    """Every command path (``run``, ``map info``, ...)."""
    out: list[str] = []

    def walk(t: object, prefix: str) -> None:
        for cmd in t.registered_commands:  # type: ignore[attr-defined]
            out.append(f"{prefix} {cmd.name or cmd.callback.__name__.replace('_', '-')}".strip())
        for g in t.registered_groups:  # type: ignore[attr-defined]
            walk(g.typer_instance, f"{prefix} {g.name}".strip())

    walk(app, "")
    return out


def test_every_command_has_an_example(capsys: pytest.CaptureFixture[str]) -> None:
    paths = _all_commands()
    assert set(paths) <= set(EXAMPLES), sorted(set(paths) - set(EXAMPLES))
    for path in ("run", "eval", "map info", "batch run", "simulate scan", "calibrate stereo"):
        text = _help(capsys, *path.split())
        example = EXAMPLES[path]
        assert "Example: " + example[:40] in text
        # the example's options exist on the command
        for opt in re.findall(r" (--[a-z-]+|-[a-z])\b", example):
            assert opt in text, (path, opt)


def test_choices_units_and_flags_in_help(capsys: pytest.CaptureFixture[str]) -> None:
    run = _help(capsys, "run")
    assert "<localize|extend>" in run and "close loops" in run and "-o" in run
    assert "<list[Path]>" not in run and "FILE" in run
    sim = _help(capsys, "simulate", "scan")
    for choices in ("<orbit|sweeps|browse|modeler|rounds>", "<clean|realistic>", "<bust|box|mix>"):
        assert choices in sim
    ev = _help(capsys, "eval")
    assert "<se3|sim3|origin|none>" in ev and "<auto|xy|xz|yz|xyz>" in ev and "--no-plots" in ev
    assert "Distance R [m]" in _help(capsys, "bound")  # a unit is not rich markup
    mesh = _help(capsys, "mesh")
    assert "--no-plots" in mesh and "--no-picture" not in mesh  # one spelling; the old one hidden
    assert "<ply|obj|stl|glb>" in mesh
    assert "--json " in _help(capsys, "info") and main(["info", "x", "--json", "true"]) == 2


def test_bad_choice_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "--ref", "a", "--est", "b", "--align", "affine"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err and "se3" in err and "eval --help" in err


def test_config_given_twice_is_layered(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a, b = tmp_path / "a.yaml", tmp_path / "b.yaml"
    a.write_text(yaml.safe_dump({"frontend": {"max_features": 321, "grid_cols": 5}, "backend": {"kind": "none"}}))
    b.write_text(yaml.safe_dump({"frontend": {"max_features": 654}}))
    assert main(["config", "dump", "-c", str(a), "-c", str(b)]) == 0
    cfg = yaml.safe_load(capsys.readouterr().out)
    assert cfg["frontend"]["max_features"] == 654  # the later file wins
    assert cfg["frontend"]["grid_cols"] == 5 and cfg["backend"]["kind"] == "none"  # the earlier one is kept
    bad = tmp_path / "bad.yaml"
    bad.write_text("frontend:\n  no_such_key: 1\n")
    assert main(["config", "dump", "-c", str(a), "-c", str(bad)]) == 2
    assert "bad.yaml" in capsys.readouterr().err


def test_scene_seed_keeps_the_object(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--scene-seed`` fixes the object; ``--seed`` then changes only the scan (issue 35 item 9)."""
    import numpy as np

    from loopmodel.sim import generate

    seen = []

    def fake_simulate(sim: object, out: Path, *args: object) -> object:
        seen.append(sim)
        raise KeyboardInterrupt  # stop before rendering

    monkeypatch.setattr(generate, "simulate_scan", fake_simulate)
    small = tmp_path / "small.yaml"  # small textures: the scene builds in a fraction of a second
    small.write_text("simulation:\n  scene:\n    texture_size_px: 128\n")
    out = ["-o", str(tmp_path / "s.mcap"), "-c", str(small)]
    for seed in ("7", "8"):
        assert main(["simulate", "scan", "--seed", seed, "--scene-seed", "3", *out]) == 130
    a, b = (generate.scene_of(s) for s in seen)  # type: ignore[arg-type]
    assert seen[0].seed == 7 and seen[1].seed == 8  # type: ignore[attr-defined]
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.textures[0], b.textures[0])
