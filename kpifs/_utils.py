"""Small private helpers shared by every stage: units, random generators, the one
atomic writer and the one progress helper."""
import os
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from astropy import units as u

from ._meta import VERSION
from .exceptions import KpifsError

__all__ = []

_QTY_RE = re.compile(r"^\s*([-+]?[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([A-Za-zµ]+)?\s*$")


def to_quantity(value, unit, *, name="value"):
    """Return *value* as a `~astropy.units.Quantity` in *unit*.

    Accepts a Quantity, a plain number (taken to be in *unit*) or a string such
    as ``"10.42mas"`` / ``"1.6um"`` / ``"0.38 m"`` (comma-separated for several).
    """
    if isinstance(value, str):
        parts = [p for p in value.split(",") if p.strip()]
        if len(parts) > 1:
            return u.Quantity([to_quantity(p, unit, name=name).value for p in parts], unit)
        m = _QTY_RE.match(value.replace("µ", "u"))
        if not m:
            raise KpifsError(f"cannot read {name} {value!r}: expected a number with a unit, "
                             f"e.g. '1.6um' or '10.42mas'")
        number, unit_str = m.groups()
        try:
            value = float(number) * (u.Unit(unit_str) if unit_str else u.Unit(unit))
        except ValueError:
            raise KpifsError(f"cannot read {name} {value!r}: unknown unit {unit_str!r}") \
                from None
    try:
        q = u.Quantity(value, unit)
    except u.UnitConversionError as exc:
        raise KpifsError(f"{name} has the wrong unit: {exc}") from None
    except (TypeError, ValueError) as exc:
        raise KpifsError(f"cannot read {name} {value!r}: {exc}") from None
    return q


def as_rng(seed):
    """Return a `numpy.random.Generator` from an int, a Generator or None."""
    return np.random.default_rng(seed)


def threads():
    """Threads the array work of a search may use: ``KPIFS_THREADS`` if set (1 turns
    threading off), else ``OMP_NUM_THREADS`` if set (what a batch worker is given:
    Dask's are given 1, so that workers side by side do not oversubscribe the
    cores), else the processor cores this process may run on."""
    env = os.environ.get("KPIFS_THREADS")
    if env:
        n = int(env) if env.strip().isdigit() else 0
        if n < 1:
            raise KpifsError(f"KPIFS_THREADS must be a whole number of threads (1 or more), "
                             f"got {env!r}")
        return n
    omp = os.environ.get("OMP_NUM_THREADS", "").split(",")[0].strip()
    if omp.isdigit() and int(omp) >= 1:          # OpenMP's own syntax: a list, the outer first
        return int(omp)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:                                  # not on Linux
        return max(1, os.cpu_count() or 1)


def one_blas_thread():
    """A context in which BLAS keeps to one thread.

    For loops of small matrix products (a simulated frame's propagation, an
    injection's reduction): BLAS's threads do not pay off on them, and on a
    busy machine they wait for each other (kpifs demo's simulation: 60 s of
    wall time for 20 frames with two BLAS threads at a load of 11, 2.4 s with
    one). kpifs's own threads (`thread_map`) still share the cores.
    """
    from threadpoolctl import threadpool_limits
    return threadpool_limits(limits=1, user_api="blas")


def thread_map(fn, items, *, wrap=None, serial=False):
    """``[fn(x) for x in items]`` on `threads` threads, in order.

    numpy releases the interpreter lock in its array operations, so independent
    chunks of one computation (batches of null draws, blocks of positions) run
    side by side on the cores; each chunk's numbers do not depend on the others
    or on the number of threads. *wrap* wraps the iterator of results as they
    come (a progress bar). *fn* must not touch the warnings filters
    (``warnings.catch_warnings`` is process-wide: two threads in it leave the
    filters of one behind, and silence the others' warnings meanwhile); with
    *serial* the items run in turn (the extraction with photutils' centroids).
    """
    from threadpoolctl import threadpool_limits
    items = list(items)
    wrap = wrap or (lambda it: it)
    n = 1 if serial else min(threads(), len(items))
    # one BLAS thread per chunk, however many chunks run at once: BLAS's own threads on
    # top would oversubscribe the cores (the null's draws: 0.40 s on one thread, 0.52 s
    # on two without this, 0.26 s with), and a chunk's rounding is then the same for
    # any number of threads
    with threadpool_limits(limits=1, user_api="blas"):
        if n <= 1:
            return list(wrap(fn(x) for x in items))
        from concurrent.futures import ThreadPoolExecutor
        with ThreadPoolExecutor(n) as pool:
            return list(wrap(pool.map(fn, items)))


def _check_writable(folder, what):
    """Refuse a folder that cannot take a new file (tried, not guessed from permissions)."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".kpifs-probe-", dir=folder)
    except OSError as exc:
        raise KpifsError(f"{what}: cannot write in {folder} ({exc.strerror})") from None
    os.close(fd)
    os.remove(probe)


#: The option that replaces an output, as the user wrote the call: the command line sets
#: it to ``--overwrite`` while a command runs (`kpifs._cli.main`).
OVERWRITE_HINT = ["overwrite=True"]


def check_output_path(path, *, overwrite=False):
    """Refuse an existing output (unless *overwrite*), a directory, a missing or unwritable
    folder: before any work is done."""
    if str(path).endswith(("/", os.sep)) and not Path(path).is_dir():
        raise KpifsError(f"{path}: ends with '{os.sep}', a folder name; expected an output file "
                         f"name (e.g. {Path(path) / 'out.fits'})")
    path = Path(path)
    if path.is_dir():
        raise KpifsError(f"{path}: is a directory, expected an output file name")
    if path.exists() and not overwrite:
        raise KpifsError(f"{path}: output exists; pass {OVERWRITE_HINT[0]} to replace it")
    if not path.parent.exists():
        raise KpifsError(f"{path}: the folder {path.parent} does not exist")
    _check_writable(path.parent, path)
    return path


def check_output_dir(path):
    """Refuse an output folder that exists as a file, or cannot be created or written."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise KpifsError(f"{path}: exists and is not a directory")
    parent = path if path.exists() else next((p for p in path.parents if p.exists()), Path("."))
    if not parent.is_dir():
        raise KpifsError(f"{path}: cannot be created ({parent} is not a directory)")
    _check_writable(parent, path)
    return path


def _new_file_mode():
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def atomic_write(path, write, *, overwrite=False, inputs=()):
    """Write a file through ``write(temporary_path)``, then rename it to *path*.

    The one way kpifs writes an output: an existing *path* is replaced only
    with ``overwrite=True``, an input file never (even then), nothing is left
    behind when *write* fails, and the file gets the permissions of any new
    file (the umask's).
    """
    path = check_output_path(path, overwrite=overwrite)
    for inp in inputs:
        try:
            if Path(inp).exists() and path.exists() and os.path.samefile(inp, path):
                raise KpifsError(f"{path}: refusing to overwrite an input file")
        except OSError:
            pass
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, _new_file_mode())
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.remove(tmp)
        if isinstance(exc, OSError) and not isinstance(exc, KpifsError):
            # disk full, quota, a vanished folder: say which output could not be written
            raise KpifsError(f"{path}: cannot write it ({exc.strerror or exc})") from None
        raise
    return path


def write_hdulist(hdul, path, *, overwrite=False, inputs=()):
    """Write *hdul* to *path* atomically, with CHECKSUM/DATASUM cards."""
    return atomic_write(path, lambda tmp: hdul.writeto(tmp, overwrite=True, checksum=True),
                        overwrite=overwrite, inputs=inputs)


def write_table(table, path, *, overwrite=False, format="ascii.ecsv"):
    """Write an astropy table atomically (ECSV by default)."""
    return atomic_write(path, lambda tmp: table.write(tmp, format=format, overwrite=True),
                        overwrite=overwrite)


#: Seconds between the plain progress lines written when stderr is not a terminal.
PROGRESS_EVERY = 10.0


def _duration(seconds):
    seconds = int(round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    minutes, seconds = divmod(seconds, 60)
    if minutes < 60:
        return f"{minutes} min {seconds:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"


class _PlainProgress:
    """Progress for logs and pipes: one line on stderr every `PROGRESS_EVERY` seconds
    (none for work shorter than that), with the time left estimated from the mean pace."""

    def __init__(self, iterable, desc, unit, total, every):
        self.iterable, self.desc, self.unit, self.every = iterable, desc or "working", unit, every
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)
        self.total, self.n = total, 0
        self.start = self.last = time.monotonic()

    def __iter__(self):
        for item in self.iterable:
            yield item
            self.update(1)

    def update(self, n=1):
        self.n += n
        now = time.monotonic()
        if now - self.last >= self.every:
            self.last = now
            self.write(now - self.start)

    def write(self, elapsed):
        unit = self.unit if self.n == 1 or self.unit.endswith("s") else (
            self.unit[:-1] + "ies" if self.unit.endswith("y") else self.unit + "s")
        done = f"{self.n}" + (f"/{self.total}" if self.total else "") + f" {unit}"
        left = ""
        if self.total and 0 < self.n < self.total:
            left = f", about {_duration(elapsed * (self.total - self.n) / self.n)} left"
        print(f"kpifs: {self.desc}: {done}, {_duration(elapsed)} elapsed{left}",
              file=sys.stderr, flush=True)

    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class _NoProgress(_PlainProgress):
    def update(self, n=1):
        self.n += n


def progress(iterable=None, *, desc=None, unit="it", total=None, enabled=True):
    """*iterable* with progress shown on stderr, or unchanged.

    On a terminal a tqdm bar; otherwise (logs, pipes) a plain line every
    `PROGRESS_EVERY` seconds with the count and the time left, so that short
    work prints nothing. Without *iterable*, an object to ``update(n)`` by hand
    (its ``total`` may be changed as the work grows) and ``close()``; with
    *enabled* False it counts silently.
    """
    if not enabled:
        return iterable if iterable is not None else _NoProgress(None, desc, unit, total, 0)
    if getattr(sys.stderr, "isatty", lambda: False)():
        from tqdm.auto import tqdm   # deferred: tqdm is only needed when a bar is shown
        return tqdm(iterable, desc=desc, unit=unit, total=total)
    return _PlainProgress(iterable, desc, unit, total, PROGRESS_EVERY)


def version_cards(header, what):
    """Add the kpifs version card and a HISTORY line saying *what* was done."""
    header["KPIFSVER"] = (VERSION, "kpifs version")
    header.add_history(f"kpifs {VERSION}: {what}")
    return header


def canonical_name(name):
    """The canonical spelling of a built-in pupil or mask name: lower case, ``_`` for ``-``.

    Both spellings are accepted everywhere (``'niriss-nrm'`` is ``'niriss_nrm'``).

    Examples
    --------
    >>> from kpifs.model.pupil import canonical_name
    >>> canonical_name("SPHERE-SAM7")
    'sphere_sam7'
    """
    return str(name).strip().lower().replace("-", "_")
