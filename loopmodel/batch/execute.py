"""One batch task on a Dask worker.

Run the pipeline into a temporary folder, evaluate it against the sequence's ground truth,
record time and peak memory, rename it into place.

Tasks run in the worker process itself, not in a subprocess per task: a fresh Python with
loopmodel's imports (open3d, gtsam, cv2) costs about 2.5 s per task on this machine (measured
with ``/usr/bin/time python -c "import loopmodel.pipeline, ..."``: 2.2-2.6 s), five times the
0.5 s per-task overhead budget, while the worker imports them once (:func:`warm_up`, run by
``plugin.BatchWorkerPlugin``).
Isolation from crashes comes from Dask's nanny instead: a worker that dies (segfault, out of
memory, SIGKILL) is restarted and its task rescheduled, at most
``distributed.scheduler.allowed-failures`` times. Peak memory per task is the worker's peak
resident set during the task: Linux resets the peak (``VmHWM``) on writing 5 to
``/proc/self/clear_refs``; this needs one task at a time per worker process (``--nthreads 1``).
"""

from __future__ import annotations

import contextlib
import glob
import json
import logging
import os
import shutil
import socket
import sys
import time
import uuid
from pathlib import Path
from typing import Any

from loopmodel import __version__
from loopmodel.batch.plan import TaskSpec
from loopmodel.io.atomic import pid_alive, write_text_atomic

logger = logging.getLogger(__name__)

TASK_FILE = "task.json"
TMP_DIR = ".tmp"
FAILED_DIR = "failed"
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


def pin_threads(n: int) -> dict[str, Any]:
    """Limit OpenCV, numba and BLAS/OpenMP to ``n`` threads in this process; returns what was set.

    The environment variables reach libraries loaded later and the processes a task starts;
    cv2 and numba are also limited at run time (numba up to the pool it was started with).
    ``NUMBA_NUM_THREADS`` is left alone once numba is imported: numba re-reads its environment
    at every compilation and refuses a value that differs from the pool it launched.
    """
    for k in THREAD_ENV:
        if k == "NUMBA_NUM_THREADS" and "numba" in sys.modules:
            continue
        os.environ[k] = str(n)
    done: dict[str, Any] = {"threads": n}
    import cv2

    cv2.setNumThreads(n)
    done["cv2"] = cv2.getNumThreads()
    with contextlib.suppress(ImportError, ValueError):
        import numba

        numba.set_num_threads(min(n, int(numba.config.NUMBA_NUM_THREADS)))  # type: ignore[attr-defined]
        done["numba"] = numba.get_num_threads()
    with contextlib.suppress(ImportError):
        from threadpoolctl import threadpool_limits

        threadpool_limits(n)
        done["blas"] = n
    return done


def reset_peak_rss() -> bool:
    """Reset this process's peak resident set (Linux ``clear_refs``); False where unsupported."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def peak_rss_mib() -> float | None:
    """Peak resident set of this process since the last reset (MiB), from ``/proc/self/status``."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def warm_up(threads: int = 1) -> dict[str, Any]:
    """Pin threads and import what a task needs (once per worker process)."""
    pinned = pin_threads(threads)
    import matplotlib.backends.backend_agg  # noqa: F401  (evaluation pictures)

    import loopmodel.eval.report  # noqa: F401
    import loopmodel.io.sequence  # noqa: F401
    import loopmodel.pipeline  # noqa: F401

    return pinned


def run_sequence(source: str | Path, config: Any, out_dir: Path, name: str, max_frames: int | None) -> Path:
    """Run the pipeline on ``source`` into ``out_dir/name``; the one call into the run machinery.

    Returns the results folder. Through the public :func:`loopmodel.run` (no signal handlers:
    the worker owns them).
    """
    from loopmodel.pipeline import run

    result = run(source, config, out_dir, name=name, max_frames=max_frames)
    if result.folder is None:  # pragma: no cover - run() with out_dir always writes
        raise RuntimeError(f"no results folder for {source}")
    return Path(result.folder)


def evaluate_folder(folder: Path, source: str | Path, config: Any) -> dict[str, Any] | None:
    """``loopmodel eval`` of a results folder against the sequence's ground truth.

    Written into ``folder/eval``; None when the sequence has none.
    """
    from loopmodel.eval import report as rep
    from loopmodel.io.sequence import open_sequence

    gt = open_sequence(source, config.sequence).ground_truth
    if gt is None or len(gt) < 2:
        return None
    run = rep.load_run(folder, config.sequence.kitti_rate_hz)
    ev = rep.evaluate_run(run, rep.TimedTrajectory(gt, str(source), True), config.eval)
    rep.write_outputs(ev, folder / "eval")
    return dict(json.loads((folder / "eval" / "metrics.json").read_text()))


def one_line_error(exc: BaseException) -> str:
    """An exception as one line: loopmodel's own errors as they are, others with their type."""
    from loopmodel.errors import LoopmodelError

    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return text if isinstance(exc, LoopmodelError) else f"{type(exc).__name__}: {text}".rstrip(": ")


def read_record(folder: Path) -> dict[str, Any] | None:
    """The ``task.json`` of a finished results folder, or None."""
    try:
        return dict(json.loads((folder / TASK_FILE).read_text()))
    except (OSError, ValueError):
        return None


def tmp_name(spec: TaskSpec) -> str:
    """Temporary folder name of a running task: ``<task>.<host>.<pid>.<random>``."""
    return f"{spec.task_id}.{socket.gethostname()}.{os.getpid()}.{uuid.uuid4().hex[:6]}"


def remove_dead_attempts(tmp_root: Path, task_id: str) -> int:
    """Delete what earlier attempts of ``task_id`` on this host left when their worker died.

    Their task folder ``<task>.<host>.<pid>.*`` in ``tmp_root`` and the results folder's own
    staging and lock, ``.<task>.<host>.<pid>.*``. Returns how many entries went.
    """
    host = socket.gethostname()
    gone = 0
    for prefix in (f"{task_id}.{host}.", f".{task_id}.{host}."):
        for p in tmp_root.glob(glob.escape(prefix) + "*"):
            pid = p.name[len(prefix) :].split(".", 1)[0]
            if pid.isdigit() and int(pid) != os.getpid() and not pid_alive(int(pid)):
                if p.is_dir():
                    shutil.rmtree(p, ignore_errors=True)
                else:
                    with contextlib.suppress(FileNotFoundError):
                        p.unlink()
                gone += 1
    return gone


def run_task(spec: TaskSpec) -> dict[str, Any]:
    """Run one task (on a worker); returns its record.

    A failure of the run is recorded (with a one-line error in ``failed/<task>.json``), never
    raised.
    """
    from loopmodel.config import config_from_dict
    from loopmodel.errors import LoopmodelError

    final = spec.folder
    done = read_record(final)
    if done is not None:  # finished by an earlier attempt (e.g. before its worker was killed)
        return done
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    record: dict[str, Any] = {
        "task": spec.task_id,
        "sequence": spec.sequence_name,
        "sequence_path": spec.sequence_path,
        "variant": spec.variant,
        "overrides": spec.overrides,
        "max_frames": spec.max_frames,
        "version": __version__,
        "host": socket.gethostname(),
        "pid": os.getpid(),
    }
    tmp_root = Path(spec.out_dir) / TMP_DIR
    if tmp_root.is_dir():
        remove_dead_attempts(tmp_root, spec.task_id)
    tmp = tmp_root / tmp_name(spec)
    try:
        tmp.mkdir(parents=True)
        if spec.version != __version__:
            raise RuntimeError(f"worker has loopmodel {__version__}, the plan was expanded with {spec.version}")
        record["pinned"] = pin_threads(spec.threads)
        rss_reset = reset_peak_rss()
        cfg = config_from_dict(spec.config, spec.task_id)
        t_run = time.perf_counter()
        run_sequence(spec.sequence_path, cfg, tmp_root, tmp.name, spec.max_frames)
        record["run_s"] = time.perf_counter() - t_run
        t_eval = time.perf_counter()
        try:
            ev = evaluate_folder(tmp, spec.sequence_path, cfg)
        except LoopmodelError as exc:  # the run stands; say why it has no numbers
            ev = None
            record["eval_error"] = one_line_error(exc).replace(str(tmp), str(final))
        record["eval_s"] = time.perf_counter() - t_eval
        run_metrics = json.loads((tmp / "metrics.json").read_text())
        record.update(
            {
                "status": "done",
                "peak_rss_mib": peak_rss_mib(),
                "peak_rss_scope": "task" if rss_reset else "worker",
                "frames": run_metrics.get("frames"),
                "keyframes": run_metrics.get("keyframes"),
                "fps": run_metrics.get("fps"),
                "evaluated": ev is not None,
                "ate_rmse_m": ev.get("ate_rmse_m") if ev else None,
            }
        )
        record["task_s"] = time.perf_counter() - t0
        record["cpu_s"] = time.process_time() - cpu0  # every thread of the worker process
        write_text_atomic(tmp / TASK_FILE, json.dumps(record, indent=2) + "\n")
        final.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.rename(tmp, final)
        except OSError:
            if read_record(final) is None:  # not a twin attempt that finished first
                raise
            shutil.rmtree(tmp, ignore_errors=True)
        with contextlib.suppress(FileNotFoundError):
            (Path(spec.out_dir) / FAILED_DIR / f"{spec.task_id}.json").unlink()
        return read_record(final) or record
    except Exception as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        error = one_line_error(exc).replace(str(tmp), str(final))
        record.update({"status": "failed", "error": error, "task_s": time.perf_counter() - t0})
        logger.warning("task %s failed: %s", spec.task_id, record["error"])
        write_text_atomic(Path(spec.out_dir) / FAILED_DIR / f"{spec.task_id}.json", json.dumps(record, indent=2) + "\n")
        return record
