"""open3d's import without its plotly/dash viewer, in processes that never draw (issue 32).

``import open3d`` imports ``open3d.visualization.draw_plotly``, hence dash, plotly and IPython: 0.7 of the
1.5 s CPU of a render worker's imports and 0.8 of the 1.85 s of the laser-extraction process that makes
the final mesh (bytecode written; fin19, gen20). :func:`without_plotly_viewer` puts a stand-in module of its
three names (they raise) in its place before open3d is loaded; :func:`start_without_plotly_viewer` is a
pool initializer that does so before it imports the initializer it is given.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import Any

__all__ = ["start_without_plotly_viewer", "without_plotly_viewer"]

_VIEWER = "open3d.visualization.draw_plotly"


def without_plotly_viewer() -> None:
    """open3d's later import in this process leaves out its plotly viewer; nothing when open3d is already loaded."""
    if "open3d" in sys.modules or _VIEWER in sys.modules:
        return

    def absent(*_args: Any, **_kwargs: Any) -> Any:
        raise RuntimeError("open3d's plotly viewer is not loaded in this process (loopmodel.open3d_import)")

    stand_in = types.ModuleType(_VIEWER, "open3d's plotly viewer, not loaded (loopmodel.open3d_import)")
    for attr in ("get_plotly_fig", "draw_plotly", "draw_plotly_server"):
        setattr(stand_in, attr, absent)
    sys.modules[_VIEWER] = stand_in


def start_without_plotly_viewer(target: str, *args: Any) -> None:
    """A pool process's start: :func:`without_plotly_viewer`, then ``target`` (``"module:function"``)(``*args``).

    This module imports neither open3d nor the target's module, so a spawned process that unpickles this
    initializer loads open3d only in the target's import.
    """
    without_plotly_viewer()
    module, name = target.split(":")
    getattr(importlib.import_module(module), name)(*args)
