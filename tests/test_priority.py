"""The run's scheduling settings (loopmodel.priority, issue 33)."""

from __future__ import annotations

import sys
from collections.abc import Iterator

import pytest

from loopmodel.priority import lower_switch_interval


@pytest.fixture
def switch_interval() -> Iterator[None]:
    before = sys.getswitchinterval()
    sys.setswitchinterval(0.005)  # Python's default
    yield
    sys.setswitchinterval(before)


def test_switch_interval_is_only_ever_lowered(switch_interval: None) -> None:
    lower_switch_interval(0.0)  # off
    assert sys.getswitchinterval() == pytest.approx(0.005)
    lower_switch_interval(0.5)
    assert sys.getswitchinterval() == pytest.approx(0.0005)
    lower_switch_interval(2.0)  # a later, larger setting leaves the lower one
    assert sys.getswitchinterval() == pytest.approx(0.0005)
