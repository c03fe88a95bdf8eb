"""Driving Dask for `kpifs.batch`: a local cluster or a running scheduler, tasks collected
as they finish with their progress, and the faults a cluster has (a worker lost, the
scheduler lost, Ctrl-C).

Dask is imported only when a batch runs (``pip install kpifs[batch]``).
"""
import contextlib
import logging
import signal
import sys
import threading
import time

from ._utils import _duration
from .exceptions import KpifsError

__all__ = []

log = logging.getLogger("kpifs.batch")

#: Seconds a client waits for a scheduler that does not answer.
CONNECT_TIMEOUT = 20

#: Seconds between two plain progress lines on a stream that is not a terminal.
PROGRESS_EVERY = 10.0


class SchedulerLost(Exception):
    """The client lost its Dask scheduler while entries were left."""


def _dask():
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise KpifsError("kpifs batch needs Dask: pip install 'kpifs[batch]'") from None
    return Client, LocalCluster, as_completed


@contextlib.contextmanager
def dask_client(scheduler=None, *, n_workers=2, processes=True):
    """A `distributed.Client`: of a running *scheduler* (its address), or of a local
    cluster of *n_workers* single-threaded workers that is closed on exit."""
    Client, LocalCluster, _ = _dask()
    cluster = client = None
    quiet = _Quiet(local=scheduler is None)
    quiet.loop()
    try:
        if scheduler is None:
            # a free port for the dashboard: never the default 8787 another cluster may hold
            with _sigint_ignored():
                cluster = LocalCluster(n_workers=n_workers if processes else 1,
                                       threads_per_worker=1, processes=processes,
                                       dashboard_address=":0")
            client = Client(cluster)
        else:
            try:
                client = Client(scheduler, timeout=CONNECT_TIMEOUT)
            except (OSError, TimeoutError, ValueError, TypeError) as exc:
                raise KpifsError(f"cannot reach the Dask scheduler at {scheduler} "
                                 f"({type(exc).__name__}: {exc}); start one with 'dask "
                                 f"scheduler' and give the address it prints") from None
            quiet.client()
        client.kpifs_quiet = quiet
        yield client
    finally:
        try:
            if client is not None:
                quiet.client()
                client.close()
            if cluster is not None:
                cluster.close()
        finally:
            quiet.restore()


class _Quiet:
    """distributed's own log records, quieted where kpifs says what happened itself: the
    client's complaint (a traceback) when the scheduler goes away, and, for a local
    cluster being stopped by Ctrl-C, the workers' and nannies'."""

    def __init__(self, local):
        self.local, self.saved = local, {}

    def loop(self):
        """The client's event loop: a Ctrl-C that lands in one of distributed's blocking
        calls can make its cancel callback fail on the loop ('cannot access free variable
        future', seen with distributed 2026.8), which tornado logs as a traceback; kpifs says
        itself what was interrupted."""
        lg = logging.getLogger("tornado.application")
        self.saved.setdefault("tornado.application", lg.level)
        lg.setLevel(logging.CRITICAL)

    def client(self):
        for name in ("distributed.client", "distributed.core", "distributed.comm",
                     "distributed.batched"):
            lg = logging.getLogger(name)
            self.saved.setdefault(name, lg.level)
            lg.setLevel(logging.CRITICAL)

    def cluster(self, client):
        """Quiet the workers too (a local cluster only: a shared cluster is left alone)."""
        self.client()
        if not self.local:
            return
        lg = logging.getLogger("distributed")
        self.saved.setdefault("distributed", lg.level)
        lg.setLevel(logging.CRITICAL)
        for nanny in (False, True):
            try:
                client.run(_silence_distributed, nanny=nanny)
            except Exception:    # no nannies (a threaded cluster), or workers already gone
                pass

    def restore(self):
        for name, level in self.saved.items():
            logging.getLogger(name).setLevel(level)
        self.saved = {}


def _silence_distributed():
    logging.getLogger("distributed").setLevel(logging.CRITICAL)


@contextlib.contextmanager
def _sigint_ignored():
    """SIGINT ignored while the cluster starts its processes, which inherit that (it
    survives exec, and Python leaves an ignored SIGINT ignored): a Ctrl-C that a terminal
    sends to the whole process group then reaches this process only, which stops the
    cluster in order, instead of killing workers mid-task with their tracebacks. A Ctrl-C
    during the few seconds of the start itself is not seen: press it again."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def collect(client, futures, on_done, *, progress=True):
    """Call ``on_done(index, row)`` for each future as it finishes; a task that Dask
    gave up on (its workers died, ``KilledWorker``) gives ``row=None`` and the reason.

    Raises `SchedulerLost` when the scheduler goes away (the futures are cancelled
    under us), and lets KeyboardInterrupt through after cancelling what is left.
    """
    _, _, as_completed = _dask()
    index = {f.key: i for i, f in enumerate(futures)}
    shown = Progress(len(futures), capacity=lambda: _capacity(client), enabled=progress)
    try:
        for fut in as_completed(futures):
            if fut.status == "cancelled":
                raise SchedulerLost(_reason(fut))
            if fut.status == "finished":
                row, why = fut.result(), None
            else:
                exc = fut.exception()
                row, why = None, f"{type(exc).__name__}: {exc}"
                if type(exc).__name__ == "KilledWorker":
                    why = (f"the workers running it died ({why}); killed, or out of "
                           f"memory? a rerun tries again")
            on_done(index[fut.key], row, why)
            shown.update(row["status"] if row else "failed")
    except KeyboardInterrupt:
        client.kpifs_quiet.cluster(client)
        client.cancel(futures)
        raise
    finally:
        shown.close()


def _reason(fut):
    try:
        fut.result(timeout=0)
    except Exception as exc:  # FutureCancelledError: "cancelled for reason: ..."
        return str(exc).split("\n")[0]
    return "cancelled"


def _capacity(client):
    """Tasks the cluster runs at once (its workers' threads)."""
    try:
        return sum(client.nthreads().values())
    except Exception:         # the scheduler is going: the next result says so
        return 0


class Progress:
    """Entries done, running, failed and left, with the time left: a line on a terminal,
    one every `PROGRESS_EVERY` seconds on a stream that is not one, and a log record
    (``kpifs.batch``, level INFO) for every entry."""

    def __init__(self, total, *, capacity, enabled=True):
        self.total, self.capacity, self.enabled = total, capacity, enabled
        self.counts = {"done": 0, "failed": 0}
        self.start = self.last = time.monotonic()
        self.tty = enabled and getattr(sys.stderr, "isatty", lambda: False)()
        self.workers, self.asked = 0, 0.0

    def text(self):
        n = self.counts["done"] + self.counts["failed"]
        left = self.total - n
        now = time.monotonic()
        if now - self.asked > 5:             # ask the scheduler at most every 5 s
            self.workers, self.asked = self.capacity(), now
        running = min(left, self.workers)
        eta = (f", about {_duration((now - self.start) * left / n)} left"
               if 0 < n and left else "")
        return (f"batch: {self.counts['done']} done, {running} running, "
                f"{self.counts['failed']} failed, {left - running} left of {self.total}"
                f"{eta}")

    def update(self, status):
        self.counts["failed" if status == "failed" else "done"] += 1
        line = self.text()
        log.info("%s", line)
        if not self.enabled:
            return
        now = time.monotonic()
        if self.tty:
            print(f"\r\033[Kkpifs {line}", end="", file=sys.stderr, flush=True)
        elif now - self.last >= PROGRESS_EVERY:
            self.last = now
            print(f"kpifs {line}", file=sys.stderr, flush=True)

    def close(self):
        if self.tty and self.counts["done"] + self.counts["failed"]:
            print(file=sys.stderr, flush=True)
