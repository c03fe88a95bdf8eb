"""A lock on an output folder, so that two batch runs never write in it at once.

The lock is a small file (``.kpifs-batch.lock``) created atomically
(``O_CREAT | O_EXCL``) holding the holder's process id, host and start time. A
second run finds it and is refused with the holder named. A lock whose holder is
on this host and no longer runs (a run killed by SIGKILL or a power cut: it
could not remove its lock) is stale: taken over with a warning.
"""
import errno
import json
import os
import socket
import time
import uuid
import warnings
from pathlib import Path

from .exceptions import KpifsError, KpifsWarning

__all__ = []

LOCK_NAME = ".kpifs-batch.lock"


def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:          # someone else's process: alive
        return True
    except OSError:
        return True
    return True


def _holder_text(info):
    when = info.get("time")
    stamp = (time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(when))
             if isinstance(when, (int, float)) else "an unknown time")
    return f"pid {info.get('pid', '?')} on {info.get('host', '?')}, since {stamp}"


class FolderLock:
    """Hold *folder*'s batch lock for the life of a ``with`` block.

    Examples
    --------
    >>> import tempfile
    >>> from kpifs._lock import FolderLock
    >>> tmp = tempfile.TemporaryDirectory()
    >>> d = tmp.name
    >>> with FolderLock(d) as lock:
    ...     lock.path.name
    '.kpifs-batch.lock'
    >>> tmp.cleanup()
    """

    def __init__(self, folder):
        self.path = Path(folder) / LOCK_NAME
        self.info = None

    def _create(self):
        # the token tells a batch's workers that they see this very folder (`kpifs.batch`)
        info = {"pid": os.getpid(), "host": socket.gethostname(), "time": time.time(),
                "token": uuid.uuid4().hex}
        fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        with os.fdopen(fd, "w") as f:
            json.dump(info, f)
        self.info = info

    def acquire(self):
        for _ in range(3):
            try:
                self._create()
                return self
            except FileExistsError:
                pass
            except OSError as exc:
                if exc.errno in (errno.EROFS, errno.EACCES):
                    raise KpifsError(f"{self.path.parent}: cannot write in it "
                                     f"({exc.strerror})") from None
                raise
            try:
                info = json.loads(self.path.read_text())
            except FileNotFoundError:            # released meanwhile: try again
                continue
            except (OSError, ValueError):
                info = {}
            here = info.get("host") == socket.gethostname()
            pid = info.get("pid")
            if here and isinstance(pid, int) and not _alive(pid):
                warnings.warn(f"{self.path.parent}: a stale batch lock ({_holder_text(info)}, "
                              f"no longer running: killed?) taken over; entries it left "
                              f"unfinished are redone", KpifsWarning, stacklevel=3)
                try:
                    self.path.unlink()
                except FileNotFoundError:
                    pass
                continue
            raise KpifsError(f"{self.path.parent}: another kpifs batch writes in this folder "
                             f"({_holder_text(info)}); wait for it, or remove {self.path} if "
                             f"that run is dead")
        raise KpifsError(f"{self.path.parent}: cannot take the batch lock {self.path}")

    def retire_token(self):
        """Give the lock a new token: tasks of this run still running elsewhere no longer
        publish (`kpifs.batch`), while the folder stays locked."""
        if self.info is None:
            return
        self.info = dict(self.info, token=uuid.uuid4().hex)
        tmp = self.path.with_name(self.path.name + ".new")
        tmp.write_text(json.dumps(self.info))
        os.replace(tmp, self.path)

    def release(self):
        if self.info is None:
            return
        try:
            info = json.loads(self.path.read_text())
            if info.get("pid") == self.info["pid"] and info.get("host") == self.info["host"]:
                self.path.unlink()
        except (OSError, ValueError):
            pass
        self.info = None

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()
