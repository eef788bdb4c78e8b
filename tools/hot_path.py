"""The functions a run calls on every frame and keyframe, traced (issue 32: each at ruff complexity <= 12).

Runs the pipeline in this one process (back end, live mesh, online calibration and loop detection in
threads; laser-line images extracted here instead of in a worker process) and records every
``loopmodel`` function called while frames ``--first`` to ``--last`` are processed (set-up before
them and the finishing steps after them are not counted). Python functions are seen by a profile
hook on every thread; a compiled (numba) kernel is recorded when called from Python (its class is
swapped for a subclass whose call records it), with the kernels it calls in turn (the dispatchers
its source names, followed to the end).

    python tools/hot_path.py [--write tests/hot_path.txt] [--first N] [--last N] [SEQUENCE[=CONFIG] ...]

Default sequences: the KITTI clip (``configs/kitti.yaml``, from ``$LOOPMODEL_SHARED_DATA``) and the
600-frame laser sample ``datasets/sample/scan.mcap`` (its loop closure: P3P and relocalization), each
from frame 10 to its end. The list (``path:function`` per line, sorted) is what
``tests/test_hot_path_complexity.py`` checks; trace again when a per-frame function is renamed or moved.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import threading
import types
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = str(ROOT / "loopmodel")

_active = False
_seen: set[tuple[str, str]] = set()  # (path relative to ROOT, function name)
_kernels: set[Any] = set()  # dispatchers called from Python during the window


def _record(code: types.CodeType) -> None:
    if code.co_filename.startswith(PACKAGE):
        _seen.add((os.path.relpath(code.co_filename, ROOT), code.co_name))


def _hook(frame: types.FrameType, event: str, arg: Any) -> None:
    if _active and event == "call":
        _record(frame.f_code)


def _trace_dispatchers() -> None:
    """Every numba dispatcher of the loaded ``loopmodel`` modules records its calls from Python."""
    from numba.core.registry import CPUDispatcher

    class Traced(CPUDispatcher):  # type: ignore[misc, valid-type]
        def __call__(self, *args: Any, **kwargs: Any) -> Any:
            if _active:
                _kernels.add(self)
            return super().__call__(*args, **kwargs)

    for name, module in list(sys.modules.items()):
        if not name.startswith("loopmodel"):
            continue
        for value in list(vars(module).values()):
            if type(value) is CPUDispatcher:
                value.__class__ = Traced


def _kernel_closure() -> None:
    """The recorded kernels and the kernels their sources call (compiled code calls them directly)."""
    from numba.core.registry import CPUDispatcher

    todo = list(_kernels)
    done: set[int] = set()
    while todo:
        d = todo.pop()
        if id(d) in done:
            continue
        done.add(id(d))
        func = d.py_func
        _record(func.__code__)
        codes = [func.__code__] + [c for c in func.__code__.co_consts if isinstance(c, types.CodeType)]
        for code in codes:
            for name in code.co_names:
                value = func.__globals__.get(name)
                if isinstance(value, CPUDispatcher):
                    todo.append(value)


def trace(source: str, config_path: str | None, first: int, last: int) -> None:
    """Run ``source`` for ``last`` frames, recording the calls of frames ``first`` .. ``last - 1``."""
    global _active
    import loopmodel
    from loopmodel.config import config_from_dict, load_config
    from loopmodel.io.sequence import open_sequence
    from loopmodel.kernels import warm_up

    cfg = load_config(config_path) if config_path else config_from_dict({})
    cfg = config_from_dict(
        _merge(
            cfg.model_dump(),
            {
                "backend": {"worker": "thread"},
                "mapping": {"live_mesh_worker": "thread"},
                "calibration": {"online_worker": "thread"},
            },
        )
    )
    sequence = open_sequence(source, cfg.sequence)
    last = min(last, len(sequence))  # (after the last frame the run finishes: not counted)
    warm_up()  # every kernel loaded before its class is swapped
    import loopmodel.pipeline  # noqa: F401

    _trace_dispatchers()

    def progress(done: int, total: int, fps: float, keyframes: int) -> None:
        global _active
        _active = first <= done < last

    threading.setprofile(_hook)
    sys.setprofile(_hook)
    try:
        loopmodel.run(sequence, cfg, max_frames=last, progress=progress, evaluate=False)
    finally:
        sys.setprofile(None)
        threading.setprofile(None)  # type: ignore[arg-type]
        _active = False


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="*", help="SEQUENCE or SEQUENCE=CONFIG (default: the KITTI clip and scan.mcap)")
    ap.add_argument("--first", type=int, default=10, help="first frame counted (after set-up)")
    ap.add_argument("--last", type=int, default=600, help="frames run (at most); frames before it counted")
    ap.add_argument("--write", type=Path, help="write the list here (else print it)")
    args = ap.parse_args(argv)
    shared = Path(os.environ.get("LOOPMODEL_SHARED_DATA", "/work/shared/data"))
    kitti = f"{shared / 'kitti_clip'}={ROOT / 'configs/kitti.yaml'}"
    runs = args.runs or [kitti, str(ROOT / "datasets/sample/scan.mcap")]
    # laser-line images extracted in this process (a daemonic process starts no extraction worker)
    mp.current_process()._config["daemon"] = True  # type: ignore[attr-defined]
    for run in runs:
        source, _, config = run.partition("=")
        trace(source, config or None, args.first, args.last)
    _kernel_closure()
    lines = sorted(f"{path}:{name}" for path, name in _seen if not name.startswith("<"))
    text = "".join(line + "\n" for line in lines)
    if args.write:
        args.write.parent.mkdir(parents=True, exist_ok=True)
        args.write.write_text(text)
        print(f"{len(lines)} functions -> {args.write}")
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
