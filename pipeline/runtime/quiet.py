"""The command line's quiet workers: a task's error reaches the command, which prints it as its
one ``error:`` line; the worker's own report of the same error (distributed's "Compute Failed"
log, with the task's traceback) is left out of the command's stderr. Everything else the
workers log (memory warnings, lost connections) still shows. ``pipeline -v`` keeps it all."""

from __future__ import annotations

import logging

from distributed.diagnostics.plugin import WorkerPlugin

NAME = "auv-pipeline-quiet-task-errors"


class _NoComputeFailed(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Compute Failed")


class QuietTaskErrors(WorkerPlugin):
    """On each worker (and each worker a nanny restarts): drop the "Compute Failed" records of
    the ``distributed.worker`` logger."""

    idempotent = True

    def setup(self, worker) -> None:
        log = logging.getLogger("distributed.worker")
        if not any(isinstance(f, _NoComputeFailed) for f in log.filters):
            log.addFilter(_NoComputeFailed())
