"""Run a plan's tasks on a Dask cluster.

Skip the finished ones, submit the rest, follow them, record what a dead worker or a failing run
leaves, and cancel cleanly on Ctrl-C.

The results folder ``OUT`` (shared by the client and every worker) holds ``plan.yaml`` (a copy),
``batch.json`` (the expanded tasks), ``running.json`` while a client follows the batch,
``tasks/<task>/`` (finished results, renamed into place complete), ``failed/<task>.json``
(one-line errors) and ``.tmp/`` (tasks being run).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import socket
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from loopmodel.batch.execute import FAILED_DIR, TMP_DIR, read_record
from loopmodel.batch.plan import Plan, TaskSpec
from loopmodel.errors import InputError
from loopmodel.io.atomic import pid_alive, write_text_atomic

logger = logging.getLogger(__name__)

BATCH_FILE = "batch.json"
RUNNING_FILE = "running.json"


@dataclass
class BatchState:
    """Counts of a batch while it runs (for a progress bar)."""

    total: int
    skipped: int = 0
    done: int = 0
    failed: int = 0
    running: int = 0
    running_tmp: dict[str, Path] = field(default_factory=dict)

    @property
    def finished(self) -> int:
        """Tasks that will not run again in this batch."""
        return self.skipped + self.done + self.failed


@dataclass
class BatchOutcome:
    """What a batch did: every task's record in plan order, and timings (s)."""

    records: list[dict[str, Any]]
    skipped: int
    wall_s: float
    submit_wall_s: float = 0.0
    interrupted: bool = False


ProgressFn = Callable[[BatchState], None]


def running_tmp(out_dir: Path) -> dict[str, Path]:
    """Temporary folders of tasks being run, by task id (dead ones on this host left out)."""
    root = out_dir / TMP_DIR
    out: dict[str, Path] = {}
    if not root.is_dir():
        return out
    host = socket.gethostname()
    for d in root.iterdir():
        parts = d.name.rsplit(".", 3)
        if len(parts) != 4:
            continue
        task, h, pid, _ = parts
        if h == host and pid.isdigit() and not pid_alive(int(pid)):
            continue
        out[task] = d
    return out


def clean_stale(out_dir: Path) -> int:
    """Remove temporary folders left by runs on this host whose process is gone."""
    root = out_dir / TMP_DIR
    n = 0
    if not root.is_dir():
        return n
    live = set(running_tmp(out_dir).values())
    for d in root.iterdir():
        if d not in live:
            shutil.rmtree(d, ignore_errors=True)
            n += 1
    return n


def task_status(spec: TaskSpec, running: dict[str, Path]) -> tuple[str, dict[str, Any] | None]:
    """``done``, ``failed``, ``running`` or ``pending``, with the record where there is one."""
    rec = read_record(spec.folder)
    if rec is not None:
        return "done", rec
    if spec.task_id in running:
        return "running", None
    try:
        failed = json.loads((Path(spec.out_dir) / FAILED_DIR / f"{spec.task_id}.json").read_text())
        return "failed", dict(failed)
    except (OSError, ValueError):
        return "pending", None


def write_manifest(plan: Plan, tasks: list[TaskSpec], out_dir: Path) -> None:
    """``plan.yaml`` (a copy of the plan file) and ``batch.json`` (every task) in ``out_dir``."""
    write_text_atomic(out_dir / "plan.yaml", plan.source.read_text())
    manifest = {
        "plan": str(plan.source),
        "name": plan.name,
        "tasks": [
            {
                "task": t.task_id,
                "sequence": t.sequence_name,
                "sequence_path": t.sequence_path,
                "variant": t.variant,
                "overrides": t.overrides,
                "max_frames": t.max_frames,
                "threads": t.threads,
                "version": t.version,
                "config": t.config,
            }
            for t in tasks
        ],
    }
    write_text_atomic(out_dir / BATCH_FILE, json.dumps(manifest, indent=1) + "\n")


def load_manifest(out_dir: Path) -> list[TaskSpec]:
    """The tasks of a batch folder (from ``batch.json``)."""
    p = out_dir / BATCH_FILE
    if not p.is_file():
        raise InputError(out_dir, f"not a batch results folder (no {BATCH_FILE})")
    try:
        data = json.loads(p.read_text())
        return [
            TaskSpec(
                t["task"],
                t["sequence_path"],
                t["sequence"],
                t["variant"],
                t["overrides"],
                t["config"],
                t["max_frames"],
                t["threads"],
                str(out_dir.resolve()),
                t["version"],
            )
            for t in data["tasks"]
        ]
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(p, f"not a valid batch manifest ({exc})") from None


def _failed_record(spec: TaskSpec, error: str) -> dict[str, Any]:
    rec = {
        "task": spec.task_id,
        "sequence": spec.sequence_name,
        "sequence_path": spec.sequence_path,
        "variant": spec.variant,
        "overrides": spec.overrides,
        "status": "failed",
        "error": error,
    }
    write_text_atomic(Path(spec.out_dir) / FAILED_DIR / f"{spec.task_id}.json", json.dumps(rec, indent=2) + "\n")
    return rec


@contextlib.contextmanager
def _running_marker(out_dir: Path, info: dict[str, Any]) -> Iterator[None]:
    path = out_dir / RUNNING_FILE
    write_text_atomic(path, json.dumps({"pid": os.getpid(), "host": socket.gethostname(), **info}) + "\n")
    try:
        yield
    finally:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def run_batch(
    plan: Plan,
    out_dir: str | Path,
    get_client: Callable[[], Any],
    progress: ProgressFn | None = None,
    poll_s: float = 0.25,
) -> BatchOutcome:
    """Run every unfinished task of ``plan`` into ``out_dir``.

    On the client ``get_client()`` returns (called only when something is left to run). Ctrl-C
    cancels what is not finished, keeps every finished result and re-raises ``KeyboardInterrupt``.
    """
    t_start = time.perf_counter()
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    tasks = plan.tasks(out)
    write_manifest(plan, tasks, out)
    clean_stale(out)
    records: dict[str, dict[str, Any]] = {}
    todo: list[TaskSpec] = []
    for t in tasks:
        rec = read_record(t.folder)
        if rec is not None:
            records[t.task_id] = rec
        else:
            todo.append(t)
    state = BatchState(len(tasks), skipped=len(records))
    if progress is not None:
        progress(state)
    submit_wall = 0.0
    if todo:
        client = get_client()
        info = {"scheduler": getattr(client, "scheduler", None) and client.scheduler.address}
        with _running_marker(out, info):
            t_submit = time.perf_counter()
            try:
                _follow(client, todo, records, state, progress, poll_s, plan.retries)
            except KeyboardInterrupt:
                logger.warning("interrupted: %d of %d tasks finished", len(records), len(tasks))
                raise
            submit_wall = time.perf_counter() - t_submit
        clean_stale(out)  # the temporary folders of attempts whose worker died
    ordered = [records[t.task_id] for t in tasks]
    return BatchOutcome(ordered, state.skipped, time.perf_counter() - t_start, submit_wall)


def _follow(
    client: Any,
    todo: list[TaskSpec],
    records: dict[str, dict[str, Any]],
    state: BatchState,
    progress: ProgressFn | None,
    poll_s: float,
    retries: int,
) -> None:
    from distributed import wait

    from loopmodel.batch.execute import run_task

    out = Path(todo[0].out_dir)
    futures = {
        client.submit(run_task, t, key=f"loopmodel-batch-{t.task_id}", pure=False, retries=retries): t for t in todo
    }
    remaining = set(futures)
    try:
        while remaining:
            try:
                finished, _ = wait(list(remaining), timeout=poll_s, return_when="FIRST_COMPLETED")
            except TimeoutError:
                finished = set()
            for fut in finished:
                spec = futures[fut]
                remaining.discard(fut)
                if fut.status == "finished":
                    rec = fut.result()
                else:  # a task that raised outside the pipeline, or whose workers kept dying
                    exc = fut.exception()
                    from loopmodel.batch.execute import one_line_error

                    rec = _failed_record(spec, one_line_error(exc) if exc is not None else fut.status)
                records[spec.task_id] = rec
                if rec.get("status") == "done":
                    state.done += 1
                else:
                    state.failed += 1
            pending_ids = {futures[f].task_id for f in remaining}
            state.running_tmp = {k: v for k, v in running_tmp(out).items() if k in pending_ids}
            state.running = len(state.running_tmp)
            if progress is not None:
                progress(state)
    except BaseException:
        client.cancel(list(remaining))
        raise


@contextlib.contextmanager
def open_client(
    scheduler: str = "local", workers: int | None = None, threads_per_task: int = 1, timeout_s: float = 30.0
) -> Iterator[Any]:
    """A Dask client, local or of a running cluster; registers :class:`BatchWorkerPlugin`.

    A new ``LocalCluster`` of ``workers`` single-thread worker processes (default: one per core) for
    ``scheduler="local"``, else the cluster at ``tcp://HOST:PORT`` (waiting for ``workers`` of them
    when given).
    """
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError:
        raise InputError(
            "--scheduler", "Dask is not installed: pip install 'loopmodel[batch]' (dask[distributed])"
        ) from None
    from loopmodel.batch.execute import THREAD_ENV
    from loopmodel.batch.plugin import BatchWorkerPlugin

    if logging.getLogger().getEffectiveLevel() > logging.INFO:  # Dask's own INFO lines only with -v
        logging.getLogger("distributed").setLevel(logging.WARNING)
        # "worker process still alive after 4 s, killing" at the end: the workers' interpreter
        # teardown (open3d's destructors) is slow, and every result is in by then
        logging.getLogger("distributed.nanny").setLevel(logging.ERROR)
    if scheduler == "local":
        n = workers or os.cpu_count() or 1
        env = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
        # The nanny applies this to the os.environ of THIS process before each spawn. numba re-reads
        # NUMBA_NUM_THREADS at every compilation and raises when it differs from its launched pool,
        # so it is left out: the worker's pin_threads limits numba itself.
        env.update({k: str(threads_per_task) for k in THREAD_ENV if k != "NUMBA_NUM_THREADS"})
        settings = {
            "distributed.nanny.pre-spawn-environ": env,
            # a task may start processes of its own (loop closing's background BA)
            "distributed.worker.daemon": False,
        }
        with dask.config.set(settings):
            cluster = LocalCluster(
                n_workers=n,
                threads_per_worker=1,
                processes=True,
                dashboard_address=":0" if _has_bokeh() else None,
                silence_logs=logging.ERROR,
            )
            client = Client(cluster)
    elif scheduler.startswith(("tcp://", "tls://", "ucx://", "inproc://")):
        cluster = None
        try:
            client = Client(scheduler, timeout=timeout_s)
        except OSError as exc:
            raise InputError("--scheduler", f"cannot reach the Dask scheduler at {scheduler} ({exc})") from None
    else:
        raise InputError("--scheduler", f"expected 'local' or tcp://HOST:PORT, got '{scheduler}'")
    try:
        if cluster is None and workers:
            client.wait_for_workers(workers, timeout=timeout_s)
        client.register_plugin(BatchWorkerPlugin(threads_per_task))
        yield client
    except KeyboardInterrupt:
        if cluster is not None:  # their running tasks are discarded anyway: no slow, noisy shutdown
            _kill_local_workers(cluster)
        raise
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _kill_local_workers(cluster: Any) -> None:
    """SIGKILL the worker processes of a LocalCluster (their nannies told not to restart them)."""
    import signal

    for nanny in list(getattr(cluster, "workers", {}).values()):
        with contextlib.suppress(AttributeError):
            nanny.auto_restart = False
        pid = getattr(getattr(nanny, "process", None), "pid", None)
        if isinstance(pid, int):
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)


def _has_bokeh() -> bool:
    try:
        import bokeh  # noqa: F401
    except ImportError:
        return False
    return True


def dashboard_address(client: Any) -> str | None:
    """The Dask dashboard's address, None when the scheduler runs none (no bokeh)."""
    try:
        info = client.scheduler_info()
    except Exception:  # pragma: no cover - a scheduler that went away
        return None
    if "dashboard" not in info.get("services", {}):
        return None
    link = client.dashboard_link
    return str(link) if link else None
