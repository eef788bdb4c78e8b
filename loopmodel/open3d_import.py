"""open3d's import without its plotly/dash viewer, in processes that never draw (issue 32).

``import open3d`` imports ``open3d.visualization.draw_plotly``, hence dash, plotly and IPython: 0.7 of the
1.5 s CPU of a render worker's imports and 0.8 of the 1.85 s of the laser-extraction process that makes
the final mesh (bytecode written; fin19, gen20), 1.15-1.23 -> 0.31 s CPU in a process that already holds
numpy, numba and the pipeline (no bytecode written, fin21). :func:`without_plotly_viewer` puts a stand-in
module of its three names in its place before open3d is loaded: they load the real viewer when one of them
is called (fin21; its other names when read) and then call it, so nothing is lost where a caller draws after all;
:func:`load_open3d` imports open3d that way; :func:`start_without_plotly_viewer` is a pool initializer that
does so before it imports the initializer it is given.
"""

from __future__ import annotations

import importlib
import sys
import threading
import types
from collections.abc import Callable
from typing import Any

__all__ = ["load_open3d", "start_without_plotly_viewer", "without_plotly_viewer"]

_VIEWER = "open3d.visualization.draw_plotly"
_NAMES = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")
_STAND_IN = "__loopmodel_stand_in__"
_LOADING = threading.Lock()


def without_plotly_viewer() -> None:
    """open3d's later import in this process leaves out its plotly viewer; nothing when open3d is already loaded.

    The viewer's functions in ``open3d.visualization`` load it when first called (:func:`_real_viewer`).
    """
    if "open3d" in sys.modules or _VIEWER in sys.modules:
        return
    stand_in = types.ModuleType(_VIEWER, "open3d's plotly viewer, loaded when used (loopmodel.open3d_import)")
    for name in _NAMES:
        setattr(stand_in, name, _loading(name))
    setattr(stand_in, _STAND_IN, True)
    stand_in.__getattr__ = _other_name  # type: ignore[method-assign]  # its other names (``go``) load it too
    sys.modules[_VIEWER] = stand_in


def _other_name(name: str) -> Any:
    if name.startswith("__"):  # probes of a module's dunders (``__file__``, ``__path__``) do not load the viewer
        raise AttributeError(name)
    return getattr(_real_viewer(), name)


def _loading(name: str) -> Callable[..., Any]:
    def viewer(*args: Any, **kwargs: Any) -> Any:
        return getattr(_real_viewer(), name)(*args, **kwargs)

    viewer.__name__ = viewer.__qualname__ = name
    viewer.__doc__ = f"open3d.visualization.{name}, its module (plotly, dash) loaded on this first call."
    return viewer


def _real_viewer() -> types.ModuleType:
    """open3d's plotly viewer module, imported now in place of the stand-in (``open3d.visualization``'s names its)."""
    with _LOADING:
        module = sys.modules.get(_VIEWER)
        if module is None or getattr(module, _STAND_IN, False):
            sys.modules.pop(_VIEWER, None)
            module = importlib.import_module(_VIEWER)
            package = sys.modules["open3d.visualization"]
            for name in _NAMES:  # the submodule's import bound its name there to the module
                setattr(package, name, getattr(module, name))
        return module


def load_open3d() -> types.ModuleType:
    """open3d, imported without its plotly viewer (:func:`without_plotly_viewer`) when not loaded yet."""
    without_plotly_viewer()
    return importlib.import_module("open3d")


def start_without_plotly_viewer(target: str, *args: Any) -> None:
    """A pool process's start: :func:`without_plotly_viewer`, then ``target`` (``"module:function"``)(``*args``).

    This module imports neither open3d nor the target's module, so a spawned process that unpickles this
    initializer loads open3d only in the target's import.
    """
    without_plotly_viewer()
    module, name = target.split(":")
    getattr(importlib.import_module(module), name)(*args)
