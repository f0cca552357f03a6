"""Worker processes of the clusters the pipeline starts end at once when they are closed.

A worker process that closed normally then spent a large part of a second in Python's own
shutdown (freeing every module and object it loaded: numba's compiled kernels, xarray,
dask.array) while its nanny, and the job behind it, waited; the LocalCluster of a job took
several times as long to close after the missions as idle (CHANGELOG.md, "Measurements").
Once the worker has closed (its tasks done, its results sent, its
scratch directory removed: distributed's own close), this plugin's exit handler flushes the
logs and standard streams and ends the process with ``os._exit(0)``. A process that did not
close normally (an error, a signal) ends as Python ends it."""

from __future__ import annotations

import atexit
import logging
import os
import sys

from distributed.diagnostics.plugin import WorkerPlugin

NAME = "auv-pipeline-prompt-exit"


def _ignore_interrupts() -> None:
    """Ctrl-C is the client's to answer: a terminal sends SIGINT to every process of the
    group, and each worker printed KeyboardInterrupt's tracebacks while the client was closing
    the cluster anyway (it ends the workers)."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


class PromptExit(WorkerPlugin):
    """On each worker of a cluster the pipeline starts
    (:func:`pipeline.runtime.cluster.local_cluster`): Ctrl-C is left to the client
    (:func:`_ignore_interrupts`), and once the worker has closed, its process skips Python's
    shutdown."""

    idempotent = True
    name = NAME

    def setup(self, worker) -> None:
        self._closed = False
        _ignore_interrupts()
        # registered last, run first: the handlers registered before it (logging's) are done
        # by hand
        atexit.register(self._exit)

    def teardown(self, worker) -> None:
        self._closed = True  # distributed's Worker.close tears the plugins down

    def _exit(self) -> None:
        if not self._closed:
            return
        logging.shutdown()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError, AttributeError):
                pass
        os._exit(0)
