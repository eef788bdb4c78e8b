"""The Dask worker plugin of a batch (imports ``distributed``: only where a cluster is used)."""

from __future__ import annotations

from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin

from loopmodel.batch.execute import warm_up


class BatchWorkerPlugin(WorkerPlugin):
    """Runs :func:`warm_up` on every worker, also on those that join or restart later."""

    name = "loopmodel-batch"

    def __init__(self, threads: int = 1) -> None:
        self.threads = threads

    def setup(self, worker: Any) -> None:
        """Called by Dask on each worker: pin threads, import the pipeline."""
        warm_up(self.threads)
