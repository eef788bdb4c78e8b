"""Shared test fixtures: the shared real data folder (skipped when absent) and seeded RNGs."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
# LOOPMODEL_SHARED_DATA points elsewhere (e.g. from a git worktree); default ../shared/data
SHARED_DATA = Path(os.environ.get("LOOPMODEL_SHARED_DATA", ROOT / ".." / "shared" / "data")).resolve()

# A background job of a non-interactive shell (`make test &`, nohup) starts with SIGINT ignored, and an
# ignored signal stays ignored across exec: every process the Ctrl-C tests start would ignore their
# SIGINT and the tests would fail whatever the code does. A handler (unlike SIG_IGN) is reset to the
# default by exec, so the children start with Python's usual KeyboardInterrupt.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture
def shared_data() -> Path:
    """``../shared/data`` (real data); the test is skipped when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder {SHARED_DATA} is absent")
    return SHARED_DATA


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded random generator."""
    return np.random.default_rng(12345)


def process_ended(pid: int, timeout_s: float) -> bool:
    """Whether process ``pid`` has ended (gone, or a zombie) within ``timeout_s``.

    Not ``Process.is_alive()``: a ``ProcessPoolExecutor``'s manager thread joins its processes too, and
    when it reaps one first, the test's own ``waitpid`` fails and ``is_alive()`` stays True for good
    (seen under load: 1 run in ~15).
    """
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with open(f"/proc/{pid}/stat") as f:
                state = f.read().rsplit(")", 1)[1].split()[0]
        except FileNotFoundError:
            return True
        except OSError:  # no /proc: ask the kernel (a zombie still counts as running there)
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                return True
            state = "?"
        if state in ("Z", "X"):
            return True
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
