"""``apply_overrides``.

The one way flags change a configuration; the run's ``config.yaml`` holds only the pipeline's
sections; kinds are checked as literals.
"""

from __future__ import annotations

import pytest
import yaml

from loopmodel.config import Config, apply_overrides, dump_config, load_config, pipeline_sections
from loopmodel.errors import ConfigError


def test_overrides_set_dotted_keys_and_skip_none() -> None:
    cfg = Config()
    out = apply_overrides(cfg, {"eval.align": "sim3", "backend.kind": "both", "eval.first_n": None})
    assert out.eval.align == "sim3" and out.backend.kind == "both" and out.eval.first_n is None
    assert cfg.eval.align == "se3"  # a copy: the original is unchanged
    section = apply_overrides(cfg.eval, {"align": "origin"})
    assert type(section) is type(cfg.eval) and section.align == "origin"


@pytest.mark.parametrize(
    ("overrides", "named"),
    [
        ({"eval.align": "affine"}, "--align"),  # not one of the literals
        ({"frontend.max_features": -3}, "--max-features"),  # out of range
        ({"frontend.no_such_knob": 1}, "--no-such"),  # unknown key
        ({"nosection.x": 1}, "nosection.x"),  # no flag name given: the key
    ],
)
def test_bad_overrides_name_the_flag(overrides: dict[str, object], named: str) -> None:
    names = {"eval.align": "--align", "frontend.max_features": "--max-features", "frontend.no_such_knob": "--no-such"}
    with pytest.raises(ConfigError) as exc:
        apply_overrides(Config(), overrides, names)
    assert str(exc.value).startswith(named + ":")


def test_run_config_holds_only_pipeline_sections(tmp_path) -> None:
    text = dump_config(Config(), pipeline_sections())
    data = yaml.safe_load(text)
    assert set(data) == {
        "sequence", "output", "frontend", "mapping", "loop", "givens", "backend", "refine", "session", "calibration"
    }
    path = tmp_path / "config.yaml"
    path.write_text(text)
    assert load_config(path) == Config()  # the other sections come back as defaults
