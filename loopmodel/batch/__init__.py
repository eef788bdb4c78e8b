"""Batch processing.

Many (sequence, configuration) runs on Dask distributed, each into a results folder keyed by its
identity, evaluated against ground truth and summarised.

``plan`` parses plans into tasks, ``execute`` runs one task on a worker, ``runner`` submits
and follows tasks, ``summary`` writes the tables and plots. Dask is imported only by
``runner.open_client`` and on workers (the optional ``batch`` extra).
"""

from loopmodel.batch.plan import Plan, TaskSpec, load_plan
from loopmodel.batch.runner import BatchOutcome, BatchState, load_manifest, open_client, run_batch
from loopmodel.batch.summary import batch_status, write_summary

__all__ = [
    "BatchOutcome",
    "BatchState",
    "Plan",
    "TaskSpec",
    "batch_status",
    "load_manifest",
    "load_plan",
    "open_client",
    "run_batch",
    "write_summary",
]
