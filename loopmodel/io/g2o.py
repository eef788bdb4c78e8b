"""g2o pose-graph files (``VERTEX_SE2``/``EDGE_SE2``, ``VERTEX_SE3:QUAT``/``EDGE_SE3:QUAT``).

The file is read here; its text becomes a :class:`~loopmodel.backend.robust_posegraph.PoseGraph` by
:func:`~loopmodel.backend.robust_posegraph.parse_g2o`.
"""

from __future__ import annotations

from pathlib import Path

from loopmodel.backend.robust_posegraph import PoseGraph, parse_g2o
from loopmodel.errors import FormatError, InputError


def read_g2o(path: str | Path) -> PoseGraph:
    """Read a 2-D or 3-D g2o pose graph (raises :class:`FormatError` on a bad line, :class:`InputError` unreadable)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise FormatError(p, "not a text g2o pose graph (undecodable bytes)") from None
    except OSError as exc:
        raise InputError(p, f"cannot read a g2o pose graph ({exc.strerror or exc.__class__.__name__})") from None
    return parse_g2o(text, p)
