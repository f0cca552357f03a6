"""A mission's section results sent to the client as soon as each task has them.

A dask future's result reaches its client in several steps: the worker tells the scheduler
that the task is done (on its batched stream, at most every 2 ms), the scheduler tells the
client (the same), then the client asks a worker for the data and waits for it: several
milliseconds after the task ended, on a LocalCluster.

So each section task also posts its result, pickled, to a queue on the scheduler: the queue
routes of ``distributed.Queue`` (``queue_put``, ``queue_get``), one request from the worker
that the scheduler answers at once to the client waiting on that queue, which asks for all the
posts it still lacks in one request: about a quarter of the time (CHANGELOG.md,
"Measurements"; ``benchmarks/bench_latency.py`` measures a mission's latency). The futures stay
the ground truth:

- a task that fails posts a note saying so, and the client gathers the futures, which raise
  the task's error as before;
- a task that posts nothing (its worker lost, or the post failed) is seen by its future: while
  the client waits, a watch on its event loop looks at the futures every :data:`POLL` seconds,
  and once one has failed, or all are done, posts the client a note to gather them;
- a scheduler without the queue routes (it answers None, and logs a warning) makes the client
  gather the futures, and not try the queues again on that client; any other error of the
  queue's makes that run gather its futures, and the queue is not used again.

A client keeps its queues and uses each again for its next mission (one per mission planned at
the same time): creating one is a round trip, and releasing one a message on the client's
batched stream, which then holds back the next mission's tasks (``mcpc._HELD``). A post
carries its run's token, so a late one from an earlier run is passed over.
"""

from __future__ import annotations

import asyncio
import pickle
import threading
import uuid
import weakref

# a larger result goes by its future only (a queue's items pass through the scheduler)
MAX_BYTES = 1 << 20

# how often a client waiting on its inbox looks at the futures (seconds): how late a task that
# failed without posting is seen. (A done callback on each future would see it at once, but
# costs every mission a coroutine and a thread hand-off per task on the client; a queue wait
# with a timeout logs an error on the scheduler each time it runs out.)
POLL = 0.25
_IDLE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # client -> idle queue names
_NONE: weakref.WeakSet = weakref.WeakSet()  # clients whose scheduler has no queue routes
_LOCK = threading.Lock()


class Inbox:
    """A queue on ``client``'s scheduler that one run of section tasks posts its results to.
    :meth:`take` one, pass its ``name`` to the tasks (they call :func:`post`), :meth:`collect`
    the results, then :meth:`give_back`."""

    def __init__(self, client, name: str):
        self.client = client
        self.name = name
        self.broken = False

    @classmethod
    def take(cls, client) -> Inbox | None:
        """An idle queue of ``client``'s, or a new one; None when its scheduler has none."""
        with _LOCK:
            if client in _NONE:
                return None
            idle = _IDLE.setdefault(client, [])
            if idle:
                return cls(client, idle.pop())
        name = f"auv-pipeline-sections-{uuid.uuid4().hex}"
        try:
            client.sync(client.scheduler.queue_create, name=name, maxsize=0)
        except Exception:  # noqa: BLE001 - no queue routes, or they failed: use the futures
            _no_queues(client)
            return None
        return cls(client, name)

    def collect(self, futures: list, token: str, k: int) -> list | None:
        """The payloads posted by the ``k`` tasks of run ``token`` (task ``me``'s at ``me``),
        or None when the futures must be gathered instead."""
        watch = _Watch()
        handle = asyncio.run_coroutine_threadsafe(
            self._watch(futures, token, watch), self.client.loop.asyncio_loop
        )
        got: dict = {}
        try:
            while len(got) < k:
                try:  # the posts still missing, in one request (the scheduler waits for them)
                    recs = self.client.sync(
                        self.client.scheduler.queue_get, name=self.name, batch=k - len(got)
                    )
                except Exception:  # noqa: BLE001 - the queue failed: the futures have it all
                    self.broken = True
                    return None
                if not isinstance(recs, (list, tuple)):  # no queue routes: the answer is None
                    self.broken = True
                    _no_queues(self.client)
                    return None
                gather = False
                for rec in recs:
                    try:
                        run, me, payload = pickle.loads(rec["value"])
                    except Exception:  # noqa: BLE001 - not a post of ours
                        continue
                    if run != token:
                        continue  # a late post of an earlier run
                    if payload is None:
                        gather = True  # a task failed, or was done without posting
                    else:
                        got[me] = payload
                if gather:
                    return None
        finally:
            watch.done = True
            handle.cancel()
        return [got[j] for j in range(k)]

    async def _watch(self, futures: list, token: str, watch: _Watch) -> None:
        """On the client's event loop, every :data:`POLL` seconds while the client waits: once
        one of the futures has failed, or all are done, post "gather the futures" (a task that
        posted nothing: its worker lost, or its post failed)."""
        while not watch.done:
            await asyncio.sleep(POLL)
            states = [f.status for f in futures]
            if watch.done or not (
                any(s in ("error", "cancelled") for s in states)
                or all(s == "finished" for s in states)
            ):
                continue
            # one note for each task: the client waits for as many posts as tasks it lacks
            data = _message(token, -1, None)
            try:
                for _ in futures:
                    await self.client.scheduler.queue_put(name=self.name, data=data)
            except Exception:  # noqa: BLE001 - then the client's wait fails: it gathers
                pass
            return

    def give_back(self) -> None:
        """Keep the queue for the client's next run (unless it failed)."""
        if self.broken:
            return
        with _LOCK:
            _IDLE.setdefault(self.client, []).append(self.name)


def _message(token: str, me: int, payload) -> bytes:
    """A post's bytes, as :meth:`Inbox.collect` reads them: task ``me`` of run ``token``, its
    payload (None: "gather the futures")."""
    return pickle.dumps((token, me, payload), protocol=pickle.HIGHEST_PROTOCOL)


def _no_queues(client) -> None:
    """Use ``client``'s futures alone from now on."""
    with _LOCK:
        _NONE.add(client)


class _Watch:
    """Whether :meth:`Inbox.collect` is done waiting."""

    done = False


def post(name: str | None, token: str, me: int, payload) -> None:
    """In task ``me`` of run ``token``: send ``payload`` (None: "gather the futures") to inbox
    ``name`` through the scheduler. Never raises: the task's future carries its result anyway."""
    if not name:
        return
    try:
        from distributed import get_worker
        from distributed.utils import sync

        worker = get_worker()
        data = _message(token, me, payload)
        if payload is not None and len(data) > MAX_BYTES:
            data = _message(token, me, None)
        sync(worker.loop, worker.scheduler.queue_put, name=name, data=data)
    except Exception:  # noqa: BLE001 - the client then gathers the futures
        pass
