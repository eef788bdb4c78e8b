"""The compiled (numba) kernels: which are cached on disk, and compiling them all once up front.

numba compiles a kernel at its first call and keeps the machine code in a cache next to the
module (or in the user's cache folder when the package folder is read-only). Right after an
install or an update that cache is empty: the first run then compiled inside its frames and in
its worker processes (the KITTI clip: 35 s of frames instead of 3 s, single frames up to 1.6 s;
issue 33 item 2). :func:`cold_kernel_modules` tells, without compiling, which modules the cache
lacks; :func:`warm_up` compiles (or loads) them in this process, so later
processes, the workers included, only load them; :func:`compile_in_processes` compiles them in a
pool of processes, one per core (numba compiles in one thread). ``make setup`` and ``loopmodel run``
compile this way when the cache is cold.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import multiprocessing as mp
import os
import signal
import sys
from collections.abc import Callable, Hashable
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import Config

logger = logging.getLogger(__name__)

#: The modules holding ``numba.njit(cache=True)`` kernels.
KERNEL_MODULES = (
    "loopmodel.frontend._stereo_kernels",
    "loopmodel.frontend._affine_kernels",
    "loopmodel.frontend._ba_kernels",
    "loopmodel.pose._point_kernels",
    "loopmodel.imaging._klt_kernels",
    "loopmodel.loop._vocabulary_kernels",
    "loopmodel.loop.p3p_kernels",
    "loopmodel.loop.surf",
    "loopmodel.backend._givens_kernels",
    "loopmodel.mapping._peak_kernels",
    "loopmodel.mapping._sdf_kernels",
    "loopmodel.imaging._png_kernels",
    "loopmodel.calibration._rig_kernels",
)


#: Cold compile time of each module's warm-up (wall s, one after the other in one process, load ~8,
#: numba 0.6x; only their order matters): the pool starts the longest first, so its processes end close together.
COMPILE_COST_S = {
    "loopmodel.frontend._stereo_kernels": 5.5,
    "loopmodel.frontend._affine_kernels": 4.8,
    "loopmodel.frontend._ba_kernels": 14.5,
    "loopmodel.pose._point_kernels": 14.5,
    "loopmodel.imaging._klt_kernels": 0.6,
    "loopmodel.loop._vocabulary_kernels": 0.3,
    "loopmodel.loop.p3p_kernels": 16.7,
    "loopmodel.loop.surf": 14.0,
    "loopmodel.backend._givens_kernels": 2.0,
    "loopmodel.mapping._peak_kernels": 3.5,
    "loopmodel.mapping._sdf_kernels": 3.0,
    "loopmodel.imaging._png_kernels": 1.4,
    "loopmodel.calibration._rig_kernels": 5.2,
}


def _warm_surf() -> None:
    """One SURF detection and description on a small textured image (float64 integral image)."""
    from loopmodel.loop.surf import Surf

    image = (np.random.default_rng(0).random((96, 96)) * 255).astype(np.uint8)
    Surf(max_features=50).detect_and_describe(image)


def _warm_givens() -> None:
    """A two-parameter-block estimator with one local block, one observation added and removed."""
    from loopmodel.backend.givens import GivensEstimator

    est = GivensEstimator(local_block_max=3)
    est.add_parameters("g", 2)
    est.add_parameters("p", 3, local=True)
    rows: dict[Hashable, NDArray[np.float64]] = {"g": np.eye(3, 2), "p": np.eye(3)}
    obs = est.add_observation(rows, np.ones(3), sigma=np.ones(3))
    est.add_observation({"g": np.eye(2)}, np.ones(2), sigma=np.ones(2))
    est.solution()
    est.delete_observation(obs)
    est.refactorize()


def _warm_ups() -> dict[str, tuple[str, Callable[[], None]]]:
    """Per kernel module: (label, warm-up), each calling the module's kernels with small inputs."""
    from loopmodel.calibration._rig_kernels import warm_up as calibrating_ba
    from loopmodel.frontend._ba_kernels import warm_up as local_ba
    from loopmodel.frontend._stereo_kernels import warm_up as stereo
    from loopmodel.frontend.affine_klt import warm_up as affine
    from loopmodel.imaging._klt_kernels import warm_up as klt_share
    from loopmodel.imaging._png_kernels import warm_up as png
    from loopmodel.loop._vocabulary_kernels import warm_up as vocabulary
    from loopmodel.loop.pnp import warm_up as p3p
    from loopmodel.mapping._peak_kernels import warm_up as laser_peaks
    from loopmodel.mapping._sdf_kernels import warm_up as sdf_surface
    from loopmodel.pose._point_kernels import warm_up as pose

    return {
        "loopmodel.frontend._stereo_kernels": ("stereo matching", stereo),
        "loopmodel.frontend._affine_kernels": ("affine KLT", affine),
        "loopmodel.frontend._ba_kernels": ("local BA", local_ba),
        "loopmodel.pose._point_kernels": ("pose solve", pose),
        "loopmodel.imaging._klt_kernels": ("KLT share", klt_share),
        "loopmodel.loop._vocabulary_kernels": ("vocabulary", vocabulary),
        "loopmodel.loop.p3p_kernels": ("P3P bank", p3p),
        "loopmodel.loop.surf": ("SURF", _warm_surf),
        "loopmodel.backend._givens_kernels": ("Givens estimator", _warm_givens),
        "loopmodel.mapping._peak_kernels": ("laser peaks", laser_peaks),
        "loopmodel.mapping._sdf_kernels": ("sdf surface", sdf_surface),
        "loopmodel.imaging._png_kernels": ("PNG rows", png),
        "loopmodel.calibration._rig_kernels": ("calibrating BA", calibrating_ba),
    }


def modules_for(config: Config) -> tuple[str, ...]:
    """The kernel modules a run with ``config`` calls (SURF, the Givens estimator and the KLT share only when set)."""
    skip = set()
    if config.loop.descriptor != "surf":
        skip.add("loopmodel.loop.surf")
    if config.backend.kind not in ("givens", "both"):
        skip.add("loopmodel.backend._givens_kernels")
    if config.frontend.klt_share_px <= 0:
        skip.add("loopmodel.imaging._klt_kernels")
    if config.calibration.refine == "none":
        skip.add("loopmodel.calibration._rig_kernels")
    return tuple(m for m in KERNEL_MODULES if m not in skip)


def _dispatchers(module: ModuleType) -> list[Any]:
    from numba.core.registry import CPUDispatcher

    return [v for v in vars(module).values() if isinstance(v, CPUDispatcher) and getattr(v, "_cache", None) is not None]


def _is_cached(dispatcher: Any) -> bool:
    """Whether the on-disk cache holds a compiled version of ``dispatcher`` for its current source.

    numba's index is stamped with the source file's time and size; a stale or missing index loads
    as empty. Reads numba's cache object (numba 0.6x); an unexpected layout counts as cached, so a
    changed numba never makes every run compile up front.
    """
    try:
        index = dispatcher._cache._cache_file._load_index()
    except Exception:  # noqa: BLE001 - only a hint; see the docstring
        logger.debug("numba cache index not readable", exc_info=True)
        return True
    return bool(index)


def cold_kernel_modules(modules: tuple[str, ...] = KERNEL_MODULES) -> list[str]:
    """The kernel modules of which numba's cache holds nothing for the current source.

    A module's cache entries are stamped with its file, so an install or an edit leaves none of them
    valid; a module with at least one valid entry has been run since (a kernel called only from
    another kernel never has an entry of its own, and one that a run never needed compiles at its
    first call as before).
    """
    cold = []
    for name in modules:
        found = _dispatchers(importlib.import_module(name))
        if found and not any(_is_cached(d) for d in found):
            cold.append(name)
    return cold


def warm_up(modules: tuple[str, ...] = KERNEL_MODULES, on_step: Callable[[int, int, str], None] | None = None) -> None:
    """Compile (or load) the kernels of ``modules`` in this process; ``on_step(done, total, label)`` after each."""
    ups = _warm_ups()
    for i, name in enumerate(modules, 1):
        label, warm = ups[name]
        warm()
        if on_step is not None:
            on_step(i, len(modules), label)


def _cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _ignore_interrupts() -> None:
    """A pool process's start: Ctrl-C (sent to the whole process group) stops only the parent, which ends the pool."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _warm_one(name: str) -> str:
    """Compile (or load) one kernel module's kernels in this process; its label."""
    label, warm = _warm_ups()[name]
    warm()
    return label


def _exit_on_sigterm() -> None:
    """SIGTERM ends this process through ``SystemExit``: the compiling pool is terminated with it, none left running.

    (tools/demo.sh stops a compile it started beside the sample's generation when the generation fails.)
    """
    signal.signal(signal.SIGTERM, lambda signum, _frame: sys.exit(128 + signum))


def compile_in_processes(
    modules: tuple[str, ...], on_step: Callable[[int, int, str], None] | None = None, processes: int = 0
) -> None:
    """Compile the kernels of ``modules`` into numba's cache in a pool of ``processes`` (0: one per core).

    The longest (:data:`COMPILE_COST_S`) start first. This process only waits: it loads none of them
    (a run loads them from the cache in its warm-ups, before its first frame). One module, or one core:
    :func:`warm_up` in this process. ``on_step(done, total, label)`` as each module is done.
    """
    n = min(processes or _cores(), len(modules))
    if n <= 1:
        warm_up(modules, on_step)
        return
    order = sorted(modules, key=lambda m: -COMPILE_COST_S.get(m, 1.0))
    # spawn: a fresh interpreter, nothing of this process's threads or numba state copied
    with mp.get_context("spawn").Pool(n, initializer=_ignore_interrupts) as pool:
        for i, label in enumerate(pool.imap_unordered(_warm_one, order), 1):
            if on_step is not None:
                on_step(i, len(order), label)


def main(argv: list[str] | None = None) -> None:
    """``python -m loopmodel.kernels [--config FILE]``: compile what the cache lacks, one line per group.

    With ``--config`` only the modules a run with that configuration calls (:func:`modules_for`);
    the others compile when first needed (``loopmodel run`` before its first frame).
    """
    import time

    parser = argparse.ArgumentParser(prog="python -m loopmodel.kernels", description=main.__doc__)
    parser.add_argument("--config", help="only the kernels a run with this configuration file calls")
    parser.add_argument("--processes", type=int, default=0, help="compiling processes (0: one per core)")
    args = parser.parse_args(argv)
    wanted: tuple[str, ...] = KERNEL_MODULES
    if args.config:
        from loopmodel.config import load_config

        wanted = modules_for(load_config(args.config))
    cold = cold_kernel_modules(wanted)
    if not cold:
        print("loopmodel kernels: cached")
        return
    print(f"loopmodel kernels: compiling ({len(cold)} of {len(wanted)} modules not in numba's cache; "
          "once after an install or update)")
    t0 = time.perf_counter()
    _exit_on_sigterm()
    compile_in_processes(
        tuple(cold),
        lambda i, n, name: print(f"  {i}/{n} {name} ({time.perf_counter() - t0:.0f} s)", flush=True),
        args.processes,
    )
    left = cold_kernel_modules(wanted)
    tail = f"; still not cached: {', '.join(left)}" if left else ""
    print(f"loopmodel kernels: done in {time.perf_counter() - t0:.0f} s{tail}")


if __name__ == "__main__":
    main()
