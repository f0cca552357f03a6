"""Where dask work runs: the one place that turns what a user gives (nothing, a scheduler
address, a scheduler file, a ``distributed.Client``, ``"synchronous"``, ``"threads"``) into a
client.

- :func:`get_client` serves the planning functions: the current default client if there is
  one, else for ``plan_missions`` a LocalCluster of :func:`local_workers` single-threaded
  workers started once per process (closed at exit, or by :func:`shutdown`), and for one
  ``plan()`` this process's threads (no cluster); an address is connected once per process.
- :func:`session` serves jobs and the command line: a client for the duration of a ``with``
  block, the default client meanwhile, closed (with its LocalCluster) at the end.

Both build a LocalCluster with :func:`local_cluster` and reach a scheduler with
:func:`connect`, so the errors are the same everywhere. The messages that carry a mission's
tasks wait at most :data:`STREAM_INTERVAL_S` to be batched: the client's (:func:`prompt`) and,
on a LocalCluster of this module, its scheduler's to the workers. A LocalCluster of this module
also wakes for dask's housekeeping less often (:data:`HOUSEKEEPING`).
"""

from __future__ import annotations

import atexit
import json
import logging
import os
import socket
import threading
from contextlib import contextmanager
from pathlib import Path

from ..exceptions import InvalidParameterError, SchedulerError, notice

log = logging.getLogger(__name__)

LOCAL_WORKERS = 2
DASHBOARD_PORT = 8787

# Set by the command line without ``-v``: the LocalClusters of :func:`session` leave a failed
# task's traceback out of stderr (:mod:`pipeline.runtime.quiet`; the command prints the error
# itself)
QUIET_TASK_ERRORS = False


# glibc's allocator in the workers of a local cluster (set before each worker process starts,
# so they also hold after a nanny restarts a worker). dask sets MALLOC_TRIM_THRESHOLD_ to 64 KiB,
# which also freezes glibc's mmap threshold at 128 KiB: every array above it (a section's window,
# its search state, a decoded chunk) is then a fresh mmap whose pages fault in on first touch, and
# a page fault is slow on a VM. Allocations up to 64 MiB from the heap and 256 MiB of free heap
# kept made the maps build, a mission and a batch of missions faster for slightly higher worker
# peaks (CHANGELOG.md, "Measurements"). A variable already in the environment wins.
WORKER_ENV = {
    "MALLOC_MMAP_THRESHOLD_": str(64 * 2**20),
    "MALLOC_TRIM_THRESHOLD_": str(256 * 2**20),
}


# How often the scheduler, nannies and workers of a LocalCluster of this module wake for their
# housekeeping (dask's defaults: 20 ms, 500 ms, 100 ms, 10 ms). The scheduler and the nannies
# live in the client's process; with dask's defaults an idle cluster kept several times more
# of a core busy there and in each worker (CHANGELOG.md, "Measurements"). These are the event
# loops' responsiveness check, the dashboard's system plots, the memory limits'
# check and the profile the dashboard shows (sampled 10 times a second instead of 100). A value
# the user set in dask's configuration (anything but dask's default) wins.
HOUSEKEEPING = {  # key: (ours, dask's default)
    "distributed.admin.tick.interval": ("200ms", "20ms"),
    "distributed.admin.system-monitor.interval": ("1s", "500ms"),
    "distributed.worker.memory.monitor-interval": ("200ms", "100ms"),
    "distributed.worker.profile.interval": ("100ms", "10ms"),
}


@contextmanager
def _interrupts_blocked():
    """SIGINT blocked in this thread while the workers are started: the processes started
    meanwhile inherit the mask and never see Ctrl-C, which is the client's to answer (the
    worker plugin ignores it too, in a worker a nanny restarts:
    :class:`pipeline.runtime.exit.PromptExit`); a Ctrl-C meanwhile is delivered here once the
    mask is lifted."""
    import signal

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def local_cluster(dashboard_address: str = ":0", workers: int | None = None):
    """A LocalCluster of :func:`local_workers` single-threaded worker processes (2 unless
    ``workers`` or dask's configuration says otherwise), their
    allocator set by :data:`WORKER_ENV`, their housekeeping by :data:`HOUSEKEEPING`, its
    scheduler's messages to them sent every :data:`STREAM_INTERVAL_S` at most
    (:func:`prompt`)."""
    import dask
    from distributed import LocalCluster

    from .exit import PromptExit

    key = "distributed.nanny.pre-spawn-environ"
    env = {**dask.config.get(key, {}), **WORKER_ENV}
    cfg = {k: v for k, (v, default) in HOUSEKEEPING.items() if dask.config.get(k, None) == default}
    # read when the scheduler and each nanny are made, inside LocalCluster(); each worker
    # process gets its nanny's configuration
    with dask.config.set({key: env, **cfg}), _interrupts_blocked():
        cluster = LocalCluster(
            n_workers=local_workers(workers),
            threads_per_worker=1,
            processes=True,
            dashboard_address=dashboard_address,
            plugins=(PromptExit(),),  # each worker, and each its nanny restarts
        )
    try:
        cluster.sync(_add_prompt_streams, cluster.scheduler)
    except Exception:  # noqa: BLE001 - a distributed without these hooks: its own intervals
        pass
    return cluster


# How long a message may wait to be batched with others, on the streams that carry a mission's
# tasks: the client's to the scheduler (distributed batches it every 10 ms) and, on a cluster
# this module starts, the scheduler's to each worker (every 5 ms). A mission that takes about
# 10 ms met the batches of the one before: its tasks waited behind the release of the previous
# mission's futures, sent a moment before, for up to 10 ms, then up to 5 ms more on the way to a
# worker. 1 ms on both cut a short mission's time by about a third (CHANGELOG.md,
# "Measurements").
STREAM_INTERVAL_S = 0.001


def prompt(client) -> None:
    """Send ``client``'s messages to its scheduler every :data:`STREAM_INTERVAL_S` at most
    (not every 10 ms): the planning functions call it on the client they are given."""
    try:
        _shorten(getattr(client, "scheduler_comm", None))
    except (AttributeError, TypeError):  # a distributed without it: its own interval
        pass


def _shorten(comm) -> None:
    """A distributed ``BatchedSend`` (or None) sent every :data:`STREAM_INTERVAL_S` at most."""
    if comm is not None and comm.interval > STREAM_INTERVAL_S:
        comm.interval = STREAM_INTERVAL_S


def _prompt_streams():
    """A scheduler plugin: the scheduler's messages to every worker, present and to come, sent
    every :data:`STREAM_INTERVAL_S` at most (not every 5 ms)."""
    from distributed.diagnostics.plugin import SchedulerPlugin

    class PromptStreams(SchedulerPlugin):
        name = "auv-pipeline-prompt-streams"

        def start(self, scheduler) -> None:
            for address in list(scheduler.stream_comms):
                self.add_worker(scheduler, address)

        def add_worker(self, scheduler, worker: str) -> None:
            _shorten(scheduler.stream_comms.get(worker))

    return PromptStreams()


async def _add_prompt_streams(scheduler) -> None:
    """On the scheduler's event loop: :func:`_prompt_streams` added, and applied to the
    workers already there."""
    plugin = _prompt_streams()
    scheduler.add_plugin(plugin, idempotent=True)
    plugin.start(scheduler)


def computing_client():
    """The distributed client dask computes on here, or None for a local scheduler (the maps
    build's and the banded writes' choice of how to send their work). Never makes one: inside
    a task, ``distributed.get_client()`` creates the worker's client and makes it the process's
    default scheduler, so that a build run in a task under ``scheduler="synchronous"`` (the
    first run's kernel warm-up) then sent its computations to the cluster whose threads its own
    tasks held, and waited (minutes, or for ever)."""
    from dask.base import get_scheduler

    try:
        get = get_scheduler()
    except (RuntimeError, ValueError):
        return None
    owner = getattr(get, "__self__", None)
    return owner if hasattr(owner, "scheduler_info") else None


# the least time between two progress lines of a computation (:func:`compute_told`)
TELL_S = 2.0


def prefixed(tell, prefix: str):
    """``tell(msg, *args)`` with ``prefix`` before each message (a pass's name before the
    progress :func:`compute_told` tells), or None without a ``tell``."""
    return None if tell is None else (lambda msg, *args: tell(prefix + msg, *args))


def compute_told(tasks, tell=None, what: str = "tasks") -> tuple:
    """``dask.compute(*tasks)`` (delayed objects) with, from 10 tasks up, ``tell(msg, *args)``
    called as a tenth of them is finished ("3 of 30 tasks") if :data:`TELL_S` seconds have gone
    since the last call (or the start): on a distributed client as its futures finish, on dask's
    local schedulers as its tasks do. A task's error is raised as soon as it is known, as
    ``dask.compute`` raises it."""
    import time

    import dask

    tasks = list(tasks)
    n = len(tasks)
    if tell is None or n < 10:
        return dask.compute(*tasks)
    last = [time.monotonic()]

    def told(done: int) -> None:
        now = time.monotonic()
        if done * 10 // n > (done - 1) * 10 // n and now - last[0] >= TELL_S:
            tell("%d of %d %s", done, n, what)
            last[0] = now

    client = computing_client()
    if client is None:
        from dask.callbacks import Callback

        keys, done = {t.key for t in tasks}, [0]

        def finished(key, result, dsk, state, worker_id) -> None:
            if key in keys:
                done[0] += 1
                told(done[0])

        with Callback(posttask=finished):
            return dask.compute(*tasks)
    from distributed import as_completed

    futures = client.compute(tasks)
    for done, future in enumerate(as_completed(futures, loop=client.loop), 1):
        if future.status == "error":
            future.result()  # raises the task's error
        told(done)
    return tuple(client.gather(futures))


def connect(address: str, *, timeout: float | None = None, set_as_default: bool = False):
    """A client of the scheduler at ``address``, or one :class:`SchedulerError` after
    ``timeout`` seconds (default ``AUV_PIPELINE_CONNECT_TIMEOUT_S``, else 30)."""
    from distributed import Client
    from distributed.comm.addressing import parse_address, parse_host_port

    if timeout is None:
        from .env import setting

        timeout = setting("AUV_PIPELINE_CONNECT_TIMEOUT_S")
    try:  # before a Client is made: one refused for its address waited 60 s at exit
        scheme, location = parse_address(address)
        if scheme in ("tcp", "tls"):
            parse_host_port(location)
    except (ValueError, TypeError) as exc:
        raise SchedulerError(
            f"{address!r} is not a dask scheduler address ({exc}); give one such as "
            "tcp://10.0.0.5:8786, or no scheduler to use a local cluster"
        ) from None
    if scheme == "tcp":
        _probe(address, location, timeout)
    try:
        return Client(address, timeout=timeout, set_as_default=set_as_default)
    except (OSError, ValueError, TypeError) as exc:
        raise SchedulerError(
            f"cannot reach the dask scheduler at {address}: {exc}; start it "
            "(`dask scheduler`) or give no scheduler to use a local "
            "cluster"
        ) from None


# a dask scheduler greets a new connection at once (its handshake); this long a silence
# means something else answers at the address
GREETING_S = 5.0


def _probe(address: str, location: str, timeout: float) -> None:
    """One :class:`SchedulerError` where nothing answers at ``address`` within ``timeout``, or
    where something answers that is no dask scheduler: it does not greet the connection
    within ``GREETING_S`` (an HTTP server, the dashboard's port; the client would wait on it
    for ever)."""
    from distributed.comm.addressing import parse_host_port

    host, port = parse_host_port(location)
    try:
        with socket.create_connection((host, port), timeout=timeout) as sk:
            sk.settimeout(min(timeout, GREETING_S))
            try:
                greeted = bool(sk.recv(8))
            except TimeoutError:
                greeted = False
    except OSError as exc:
        raise SchedulerError(
            f"cannot reach the dask scheduler at {address}: {exc.strerror or exc}; start it "
            "(`dask scheduler`) or give no scheduler to use a local cluster"
        ) from None
    if not greeted:
        raise SchedulerError(
            f"{address} answers but is not a dask scheduler (it did not greet the connection "
            f"within {min(timeout, GREETING_S):g} s; a web server or the dashboard's port?); "
            "give the scheduler's own address (tcp://host:8786 by default)"
        )


def address_of(scheduler_file) -> str:
    """The scheduler address written in a dask scheduler file (JSON)."""
    path = Path(scheduler_file)
    if path.exists() and not path.is_file():  # a FIFO would block the read for ever
        raise SchedulerError(
            f"cannot read the scheduler address from {scheduler_file}: it is not a regular "
            "file; give the file `dask scheduler --scheduler-file` wrote"
        )
    try:
        address = json.loads(path.read_text())["address"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SchedulerError(
            f"cannot read the scheduler address from {scheduler_file}: "
            f"{exc}; give the file `dask scheduler --scheduler-file` "
            "wrote"
        ) from None
    if not isinstance(address, str):
        raise SchedulerError(
            f"{scheduler_file} holds no scheduler address; give the file "
            "`dask scheduler --scheduler-file` wrote"
        )
    return address


def _free_dashboard_address() -> str:
    """Port 8787 on loopback when free, else any free port (loopback only: a dashboard is
    served to the machine it runs on unless asked otherwise)."""
    with socket.socket() as sk:
        busy = sk.connect_ex(("127.0.0.1", DASHBOARD_PORT)) == 0
    return "127.0.0.1:0" if busy else f"127.0.0.1:{DASHBOARD_PORT}"


# --------------------------------------------------------------------------- per process

_LOCAL: dict = {}
_LOCAL_LOCK = threading.Lock()


def shutdown() -> None:
    """Close the clients and the local cluster that :func:`get_client` started in this
    process (it also runs at exit)."""
    with _LOCAL_LOCK:
        items = list(_LOCAL.items())
        _LOCAL.clear()
    for _, x in sorted(items, key=lambda kv: kv[0] == "cluster"):  # clients first
        try:
            x.close()
        except Exception:  # noqa: BLE001 - closing: nothing left to report to
            pass


# the clients that plan in this process: a mission's sections in turn, or shared by threads
IN_PROCESS = ("synchronous", "threads")


def get_client(client=None, *, own: str = "cluster"):
    """The cluster to plan on: ``"synchronous"`` (in this process, a mission's sections in
    turn), ``"threads"`` (in this process, a mission's sections shared by a thread per core),
    a ``distributed.Client``, a scheduler address, or None: the current default client if
    there is one, else (``own="cluster"``) a LocalCluster of :func:`local_workers`
    single-threaded workers started once per process, or (``own="threads"``) this process's
    threads. A client is returned :func:`prompt`."""
    if isinstance(client, str) and client in IN_PROCESS:
        return client
    if client is None and own == "threads":
        active = _active_client()
        if active is None:
            return "threads"
        client = active
    if client is None and _active_client() is None and "client" not in _LOCAL:
        script = unguarded_script()
        if script is not None:
            notice(
                log,
                "%s calls the planner at its top level, outside `if __name__ == "
                "\"__main__\":`: planning on this process's threads (a cluster's worker "
                "processes would run the script again); put the call under that guard to plan "
                "on a local cluster",
                script,
            )
            return "threads"
    got = _client(client)
    prompt(got)
    return got


def unguarded_script() -> str | None:
    """The path of the script this process runs when it is calling here from its top level
    outside an ``if __name__ == "__main__":`` block (worker processes started now would import
    the script and run that call again, and fail to start), else None (a guarded call, a call
    from a function the guard calls, ``python -c``, a notebook)."""
    import ast
    import sys

    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    if main is None or not path or not os.path.isfile(path):
        return None
    frame = sys._getframe(1)
    while frame is not None and not (
        frame.f_globals is vars(main) and frame.f_code.co_name == "<module>"
    ):
        frame = frame.f_back
    if frame is None:
        return None
    line = frame.f_lineno
    try:
        tree = ast.parse(Path(path).read_text(encoding="utf-8"))
    except (OSError, SyntaxError, ValueError):
        return None
    for node in tree.body:
        if node.lineno <= line <= (node.end_lineno or node.lineno):
            return None if _main_guard(node) else str(path)
    return None


def _main_guard(node) -> bool:
    """Whether ``node`` is ``if __name__ == "__main__":`` (either way round)."""
    import ast

    if not isinstance(node, ast.If) or not isinstance(node.test, ast.Compare):
        return False
    t = node.test
    sides = [t.left, *t.comparators]
    names = {s.id for s in sides if isinstance(s, ast.Name)}
    texts = {s.value for s in sides if isinstance(s, ast.Constant)}
    return (
        len(t.ops) == 1
        and isinstance(t.ops[0], ast.Eq)
        and names == {"__name__"}
        and texts == {"__main__"}
    )


def _active_client():
    """The distributed client this process made current (``Client()``, ``with client:``), or
    None; never starts one."""
    try:
        from distributed import default_client

        return default_client()
    except (ImportError, ValueError):
        return None


def local_workers(workers: int | None = None) -> int:
    """How many worker processes a LocalCluster of this tool's has: ``workers`` when given,
    else dask's configuration ``auv_pipeline.workers`` (``DASK_AUV_PIPELINE__WORKERS``), else
    :data:`LOCAL_WORKERS`."""
    import dask

    value = workers if workers is not None else dask.config.get("auv_pipeline.workers", None)
    if value is None:
        return LOCAL_WORKERS
    try:
        n = int(value)
    except (TypeError, ValueError):
        n = 0
    if n < 1 or n != float(value):
        raise InvalidParameterError(
            f"the number of workers must be a whole number of at least 1, got {value!r}"
        )
    most, why = most_local_workers()
    if n > most:
        raise InvalidParameterError(
            f"{n} local workers: this machine holds at most {most} ({why}); give at most "
            f"{most}, or a cluster's address with --scheduler"
        )
    return n


# what a local worker process needs to do its share of a build: it holds about 0.2 GiB once
# the tool is imported, and up to 0.9 at the peak of a 10000^2 maps build (CHANGELOG.md,
# "Measurements"); and how many worker processes a core may carry at most
WORKER_BYTES = 2**30
WORKERS_PER_CORE = 8


def most_local_workers() -> tuple[int, str]:
    """The most worker processes a LocalCluster may start on this machine, and why: one per
    :data:`WORKER_BYTES` of the memory available now, at most :data:`WORKERS_PER_CORE` per
    core (a thousand would start until the memory is gone)."""
    import psutil

    free = psutil.virtual_memory().available
    cores = os.cpu_count() or 1
    by_memory = max(1, int(free // WORKER_BYTES))
    by_cores = WORKERS_PER_CORE * cores
    if by_memory <= by_cores:
        return by_memory, f"{free / 2**30:.1f} GiB of memory available, 1 GiB a worker"
    return by_cores, f"{cores} cores, {WORKERS_PER_CORE} workers a core"


def _client(client):
    from distributed import Client

    if isinstance(client, Client):
        return client
    if isinstance(client, str):
        with _LOCAL_LOCK:
            c = _LOCAL.get(("addr", client))
            if c is None:
                c = connect(client)
                _LOCAL[("addr", client)] = c
            return c
    if client is not None:
        raise InvalidParameterError(
            "`client` must be None, 'synchronous', 'threads', a scheduler address "
            f"or a distributed.Client, got {type(client).__name__}"
        )
    try:
        from distributed import get_client as current

        return current()
    except ValueError:
        pass
    with _LOCAL_LOCK:
        if "client" not in _LOCAL:
            cluster = local_cluster()
            _LOCAL["cluster"] = cluster
            _LOCAL["client"] = Client(cluster, set_as_default=False)
            atexit.register(shutdown)
        return _LOCAL["client"]


# --------------------------------------------------------------------------- per job


def check_dashboard_address(address) -> None:
    """One :class:`InvalidParameterError` unless ``address`` is where a dashboard can listen:
    ``PORT``, ``:PORT`` or ``HOST:PORT`` (a port 0-65535; 0 any free one) with a host this
    machine resolves."""
    text = str(address)
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = "", text
    ok = port.isdigit() and int(port) <= 65535
    if ok and host.strip("[]"):
        try:
            socket.getaddrinfo(host.strip("[]"), None)
        except (OSError, UnicodeError):
            ok = False
    if not ok:
        raise InvalidParameterError(
            f"dashboard address {text!r} must be PORT, :PORT or HOST:PORT with a host this "
            "machine knows (e.g. 8787, :8787 or 127.0.0.1:8787)"
        )


@contextmanager
def session(scheduler=None, scheduler_file=None, dashboard_address=None, workers=None):
    """A client for a job or a command: ``scheduler`` (an address or a ``Client``, used as it
    is and left open), the scheduler named in ``scheduler_file``, or a new LocalCluster of
    :func:`local_workers` (``workers``, by default 2) single-threaded workers (its dashboard at
    ``dashboard_address``, by default on loopback,
    port 8787 when free). The client is the
    default client inside the block, in every thread."""
    from distributed import Client

    if scheduler is not None and scheduler_file is not None:
        raise InvalidParameterError("give a scheduler address or a scheduler file, not both")
    if dashboard_address is not None:
        check_dashboard_address(dashboard_address)
    n_workers = local_workers(workers)  # (checked before anything starts)
    if scheduler_file is not None:
        scheduler = address_of(scheduler_file)
    import dask

    if isinstance(scheduler, Client):
        # the default for dask collections in every thread (missions plan in threads)
        with scheduler.as_current(), dask.config.set(scheduler=scheduler):
            yield scheduler
        return
    cluster = None
    if scheduler:
        client = connect(scheduler, set_as_default=False)
    else:
        cluster = local_cluster(dashboard_address or _free_dashboard_address(), n_workers)
        client = Client(cluster, set_as_default=False)
        if QUIET_TASK_ERRORS:
            from .quiet import QuietTaskErrors

            client.register_plugin(QuietTaskErrors())
    try:
        # the default only inside the block (a context that is always undone), never the
        # process-wide default: a client closed later cannot stay anyone's scheduler
        with client.as_current(), dask.config.set(scheduler=client):
            yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
