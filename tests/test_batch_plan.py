"""Batch plans: parsing, errors naming the key, task identities (no Dask needed)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from loopmodel.batch.plan import load_plan, task_hash
from loopmodel.cli import main
from loopmodel.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "datasets" / "tiny_kitti"


def _plan(tmp_path: Path, data: dict, name: str = "plan.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def test_grid_and_variants_expand_to_tasks_with_effective_configs(tmp_path):
    (tmp_path / "k.yaml").write_text("frontend:\n  grid_cols: 6\n")
    plan = load_plan(
        _plan(
            tmp_path,
            {
                "sequences": [str(TINY), {"path": str(TINY.parent / "tiny_*"), "config": "k.yaml", "name": "t2"}],
                "base": {"eval.plots": False},
                "grid": {"frontend.max_features": [300, 500], "backend.kind": ["isam2", "both"]},
                "variants": [{"name": "fast", "set": {"frontend.max_features": 100}}],
                "max_frames": 5,
            },
        )
    )
    tasks = plan.tasks(tmp_path / "out")
    assert len(tasks) == 2 * 5
    assert len({t.task_id for t in tasks}) == 10
    by = {(t.sequence_name, t.variant): t for t in tasks}
    t = by[("t2", "frontend.max_features=500,backend.kind=both")]  # the section is part of the label
    assert t.config["frontend"]["max_features"] == 500 and t.config["backend"]["kind"] == "both"
    assert t.config["frontend"]["grid_cols"] == 6  # the sequence's layer
    assert by[("tiny_kitti", "fast")].config["frontend"]["grid_cols"] == 8  # the default
    assert t.config["eval"]["plots"] is False and t.max_frames == 5
    assert t.folder == (tmp_path / "out").resolve() / "tasks" / t.task_id


def test_task_identity_follows_config_sequence_and_version(tmp_path):
    plan_a = load_plan(_plan(tmp_path, {"sequences": [str(TINY)], "grid": {"frontend.max_features": [300]}}, "a.yaml"))
    [a] = plan_a.tasks(tmp_path / "out1")
    [a2] = plan_a.tasks(tmp_path / "elsewhere")  # where results go does not matter
    assert a.task_id == a2.task_id
    plan_b = load_plan(_plan(tmp_path, {"sequences": [str(TINY)], "grid": {"frontend.max_features": [301]}}, "b.yaml"))
    [b] = plan_b.tasks(tmp_path / "out1")
    assert a.task_id.split("__")[-1] != b.task_id.split("__")[-1]
    copy = shutil.copytree(TINY, tmp_path / "copy" / "tiny_kitti")
    [c] = load_plan(_plan(tmp_path, {"sequences": [str(copy)], "grid": {"frontend.max_features": [300]}})).tasks(
        tmp_path / "out1"
    )
    assert c.task_id == a.task_id  # the same content elsewhere is the same sequence
    (copy / "poses.txt").write_text((copy / "poses.txt").read_text() + "\n")
    [d] = load_plan(_plan(tmp_path, {"sequences": [str(copy)], "grid": {"frontend.max_features": [300]}})).tasks(
        tmp_path / "out1"
    )
    assert d.task_id != a.task_id
    ident = {"x": 1}
    assert task_hash("s", ident, None, "0.1.0") != task_hash("s", ident, None, "0.1.1")
    assert task_hash("s", ident, None, "0.1.0") != task_hash("s", ident, 10, "0.1.0")


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        ({"sequences": []}, "'sequences' must be a non-empty list"),
        ({"sequences": ["x"], "gird": {}}, "unknown key(s) ['gird']"),
        ({"sequences": ["x"], "grid": {"frontend.max_features": 5}}, "grid key 'frontend.max_features'"),
        ({"sequences": ["x"], "grid": {"frontend.max_featurez": [5]}}, "unknown key 'frontend.max_featurez'"),
        ({"sequences": ["x"], "grid": {"backend.kind": ["isam3"]}}, "key 'backend.kind'"),
        ({"sequences": ["nothing_*"]}, "the glob 'nothing_*' matches nothing"),
        ({"sequences": ["x"], "max_frames": 0}, "'max_frames' must be a positive integer"),
        ({"sequences": ["x"], "variants": [{"name": "a"}, {"name": "a"}]}, "variant names must be distinct"),
    ],
)
def test_bad_plans_name_the_key(tmp_path, data, expected):
    p = _plan(tmp_path, data)
    with pytest.raises(InputError) as err:
        load_plan(p)
    assert expected in str(err.value) and str(p) in str(err.value)


def test_cli_bad_plan_is_one_line_and_exit_2(tmp_path, capsys):
    assert main(["batch", str(tmp_path / "missing.yaml")]) == 2
    assert main(["batch", "status", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "plan file does not exist" in err and "not a batch results folder" in err
    assert "Traceback" not in err
