"""Where the benchmarks find the shared real data.

``$LOOPMODEL_SHARED_DATA`` when set (a git worktree, another machine), else ``../shared/data``
beside the project (as the tests do).
"""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("LOOPMODEL_SHARED_DATA", ROOT / ".." / "shared" / "data")).resolve()
