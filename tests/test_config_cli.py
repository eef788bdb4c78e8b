"""Configuration (unknown keys are errors naming the key) and the CLI's basic commands."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from loopmodel import __version__
from loopmodel.cli import main
from loopmodel.config import Config, load_config
from loopmodel.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def test_presets_load() -> None:
    for path in sorted((ROOT / "configs").glob("*.yaml")):
        assert isinstance(load_config(path), Config)


def test_unknown_key_names_the_key(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump({"sequence": {"topics": {"left_imag": "/x"}}}))
    with pytest.raises(ConfigError, match=r"unknown key 'sequence.topics.left_imag'"):
        load_config(p)
    p.write_text(yaml.safe_dump({"sequence": {"kitti_rate_hz": -1}}))
    with pytest.raises(ConfigError, match="sequence.kitti_rate_hz"):
        load_config(p)


def test_config_dump_round_trips(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["config", "dump"]) == 0
    text = capsys.readouterr().out
    p = tmp_path / "dumped.yaml"
    p.write_text(text)
    assert load_config(p) == Config()


def test_version_and_errors(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert main(["--version"]) == 0
    assert __version__ in capsys.readouterr().out
    assert main(["info", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert "nope" in err and "does not exist" in err and "Traceback" not in err
    bad = tmp_path / "bad.yaml"
    bad.write_text("sequence: {foo: 1}\n")
    assert main(["config", "dump", "--config", str(bad)]) == 2
    assert "unknown key 'sequence.foo'" in capsys.readouterr().err
