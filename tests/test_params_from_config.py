"""Parameter classes read their defaults from ``config.py`` only (issue 32).

Every field of :class:`PlaceParams`, :class:`RelocParams` and :class:`LoopParams` (but the seed) is a
knob of :class:`LoopConfig`: the class default is the config default, and ``from_config`` passes a
changed config value on.
"""

from __future__ import annotations

import dataclasses

import pytest

from loopmodel.config import LoopConfig
from loopmodel.loop.closure import LoopParams, params_from_config
from loopmodel.loop.database import PlaceParams
from loopmodel.loop.reloc import RelocParams

# the parameter's name -> the LoopConfig knob's name where they differ
RENAMED = {"min_gap": "min_gap_keyframes", "branching": "vocabulary_branching", "levels": "vocabulary_levels"}
RENAMED["train_after"] = "vocabulary_train_after"


def _changed(value: object) -> object:
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value + 1
    assert isinstance(value, float)
    return value * 0.999 if value >= 0.99 else value * 1.01 + 0.001


@pytest.mark.parametrize(
    ("cls", "made"),
    [
        (PlaceParams, lambda c: PlaceParams.from_config(c)),
        (RelocParams, lambda c: RelocParams.from_config(c)),
        (LoopParams, params_from_config),
    ],
)
def test_every_parameter_comes_from_the_config(cls: type, made: object) -> None:
    default = LoopConfig()
    assert made(default) == cls()  # type: ignore[operator]
    for f in dataclasses.fields(cls):
        if f.name in ("seed", "place", "reloc"):
            continue
        knob = RENAMED.get(f.name, f.name)
        assert knob in LoopConfig.model_fields, f"{cls.__name__}.{f.name} has no LoopConfig knob"
        value = _changed(getattr(default, knob))
        got = getattr(made(default.model_copy(update={knob: value})), f.name)  # type: ignore[operator]
        assert got == value, (cls.__name__, f.name)
