"""Archive reprocessing on Dask: extraction -> calibration -> detection for many entries.

An entry is a target observation (one or more cube files) with its calibrator
star(s) (none for an angular-differential reduction). Entries come from a
manifest (CSV or ECSV; columns ``name``, ``target``, ``calibrator`` and
optionally ``instrument``, ``wavelengths``, ``pixscale``, ``pa``; several files
in one cell are separated by ``;``, several calibrator stars by ``|``) or from
a glob with one calibrator rule.

Each entry is reduced by `kpifs.workflow.process_observation` with the same
`~kpifs.workflow.ExtractOptions` and `~kpifs.workflow.DetectOptions` as the
command line (JWST filter pairs and the angular-differential mode included),
and writes ``OUTDIR/<name>/calibrated_kp.fits`` and
``OUTDIR/<name>/detection.fits``; ``OUTDIR/summary.ecsv`` lists every entry
with its status, candidates and limits. An entry whose ``detection.fits``
carries the digest of the same options and inputs is skipped (a rerun
resumes), unless ``overwrite=True``. A failure is recorded for its entry and
does not stop the others.

Workers may live elsewhere (``scheduler=ADDRESS``): every path is made
absolute on the client before an entry is sent (a manifest's relative paths
against the manifest's folder, other relative paths against the client's
current folder), and the workers must see the inputs and the output folder
at those paths (a shared filesystem, as on HPC clusters). A worker that does
not fails the entry with a message naming the worker and the path. An
entry's products are written in a private folder and moved into place once
complete, so an entry whose worker dies leaves nothing half-written.

Dask is an optional dependency (``pip install kpifs[batch]``), imported only
when a batch runs.
"""
import dataclasses
import glob
import json
import logging
import os
import shutil
import socket
import tempfile
import time
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.table import Table

from . import _cluster
from ._lock import LOCK_NAME, FolderLock
from ._utils import check_output_dir, write_table
from .data import DetectionResult
from .exceptions import KpifsError
from .workflow import (DetectOptions, ExtractOptions, observation_digest, options_record,
                       process_observation)

__all__ = ["BatchEntry", "read_manifest", "entries_from_glob", "check_entry_name",
           "absolute_file", "absolute_options", "absolute_entry", "RunContext", "process_entry",
           "run_batch", "BatchInterrupted"]

log = logging.getLogger(__name__)


@dataclass
class BatchEntry:
    """One observation: target files and calibrator stars (each a list of files).

    Examples
    --------
    >>> from kpifs.batch import BatchEntry
    >>> e = BatchEntry("hd1234", ["t1.fits", "t2.fits"], [["c1.fits"]])
    >>> e.instrument, len(e.calibrators)
    ('auto', 1)
    """

    name: str
    target: list
    calibrators: list
    instrument: str = "auto"
    wavelengths: str = None
    pixscale: str = None
    pa: str = None


#: Options that may name a file (a wavelength table, angles, a pupil image or kernel model,
#: a spectrum, templates): made absolute on the client, against the folder they were
#: given from.
FILE_OPTIONS = ("wavelengths", "pa", "pupil", "spectrum", "basis")

_FILE_SUFFIXES = (".fits", ".fit", ".fts", ".fz", ".gz", ".txt", ".dat", ".csv", ".ecsv")


def absolute_file(value, base):
    """*value* as an absolute path when it names a file relative to *base* (it exists
    there, or it has a file's suffix or a folder separator); other values unchanged
    (``"1.52um,1.6um"``, ``"subaru"``, None).

    Examples
    --------
    >>> from kpifs.batch import absolute_file
    >>> absolute_file("wl.txt", "/data/night1"), absolute_file("1.52,1.60", "/data")
    ('/data/night1/wl.txt', '1.52,1.60')
    """
    if not isinstance(value, (str, Path)) or not str(value).strip():
        return value
    text = str(value).strip()
    path = Path(text).expanduser()
    if path.is_absolute():
        return os.path.normpath(path)
    candidate = Path(base) / path
    try:
        exists = candidate.exists()
    except OSError:                      # a long list of values is no file name
        exists = False
    if exists or text.lower().endswith(_FILE_SUFFIXES) or "/" in text or "\\" in text:
        return os.path.normpath(os.path.abspath(candidate))
    return value


def absolute_options(options, base="."):
    """*options* (`~kpifs.workflow.ExtractOptions` or `~kpifs.workflow.DetectOptions`)
    with every file they name made absolute against *base* (``FILE_OPTIONS``).

    Examples
    --------
    >>> from kpifs.batch import absolute_options
    >>> from kpifs.workflow import ExtractOptions
    >>> absolute_options(ExtractOptions(wavelengths="wl.txt", pupil="subaru"), "/d").wavelengths
    '/d/wl.txt'
    """
    names = {f.name for f in dataclasses.fields(options)}
    return dataclasses.replace(options, **{k: absolute_file(getattr(options, k), base)
                                           for k in FILE_OPTIONS if k in names})


def absolute_entry(entry, base="."):
    """*entry* with its files (and file-valued columns) made absolute against *base*.

    Examples
    --------
    >>> from kpifs.batch import BatchEntry, absolute_entry
    >>> absolute_entry(BatchEntry("x", ["t.fits"], [["c.fits"]]), "/data").target
    ['/data/t.fits']
    """
    def files(paths):
        return [os.path.normpath(os.path.join(os.path.abspath(base), os.path.expanduser(str(p))))
                for p in paths]

    return dataclasses.replace(entry, target=files(entry.target),
                               calibrators=[files(star) for star in entry.calibrators],
                               wavelengths=absolute_file(entry.wavelengths, base),
                               pa=absolute_file(entry.pa, base))


def _split(cell, sep=";"):
    cell = "" if cell is None or (isinstance(cell, np.ma.core.MaskedConstant)) else str(cell)
    return [p.strip() for p in cell.split(sep) if p.strip()]


def _expand(pattern, base):
    path = Path(pattern)
    if not path.is_absolute():
        path = base / path
    hits = sorted(glob.glob(str(path)))
    return hits or [str(path)]          # a missing file fails its entry, with its name


def read_manifest(path):
    """Read a manifest (CSV or ECSV) into a list of `BatchEntry`.

    Relative paths are relative to the manifest's folder (the cube files, and the
    ``wavelengths`` and ``pa`` files), and come back absolute; cells may hold globs.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kpifs.batch import read_manifest
    >>> tmp = tempfile.TemporaryDirectory()
    >>> d = pathlib.Path(tmp.name)
    >>> _ = (d / "m.csv").write_text("name,target,calibrator\\nstar1,a.fits,b.fits|c.fits\\n")
    >>> e = read_manifest(d / "m.csv")[0]
    >>> e.name, len(e.calibrators)
    ('star1', 2)
    >>> tmp.cleanup()
    """
    path = Path(path)
    if not path.is_file():
        raise KpifsError(f"{path}: manifest not found")
    fmt = "ascii.ecsv" if path.suffix == ".ecsv" else "ascii.csv"
    try:
        # utf-8-sig: spreadsheets save "CSV UTF-8" with a byte-order mark before `name`
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise KpifsError(f"{path}: cannot read the manifest: {exc}") from None
    if len([ln for ln in lines if ln.strip() and not ln.lstrip().startswith("#")]) < 2:
        raise KpifsError(f"{path}: the manifest has no entries (a header line and at least "
                         f"one row: name,target,calibrator)")
    try:
        tab = Table.read(lines, format=fmt)
    except Exception as exc:  # astropy raises many types on malformed tables
        raise KpifsError(f"{path}: cannot read the manifest: {exc}") from None
    missing = {"name", "target", "calibrator"} - set(tab.colnames)
    if missing:
        raise KpifsError(f"{path}: manifest lacks column(s) {sorted(missing)}; needs name, "
                         f"target, calibrator")
    names = [str(n) for n in tab["name"]]
    for n in names:
        check_entry_name(n, source=path)
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise KpifsError(f"{path}: entry names must be unique; repeated: {sorted(dup)}")
    base = path.parent.absolute()
    entries = []
    for row in tab:
        target = [f for p in _split(row["target"]) for f in _expand(p, base)]
        cals = [[f for p in _split(star) for f in _expand(p, base)]
                for star in _split(row["calibrator"], "|")]
        opt = {k: (None if np.ma.is_masked(row[k]) or not str(row[k]).strip()
                   else str(row[k]).strip())
               for k in ("instrument", "wavelengths", "pixscale", "pa") if k in tab.colnames}
        # a file named in a cell is the one next to the manifest, wherever the batch runs
        entries.append(absolute_entry(BatchEntry(
            name=str(row["name"]), target=target, calibrators=cals,
            instrument=opt.get("instrument") or "auto", wavelengths=opt.get("wavelengths"),
            pixscale=opt.get("pixscale"), pa=opt.get("pa")), base))
    return entries


def check_entry_name(name, *, source="entry", outdir=None):
    """Refuse an entry name that is not one folder name inside the output folder
    (``../x``, ``/abs/path``, ``a/b``, ``.``, empty), or that leads out of *outdir*
    through a symbolic link.

    Examples
    --------
    >>> from kpifs.batch import check_entry_name
    >>> from kpifs.exceptions import KpifsError
    >>> check_entry_name("hd1234")
    >>> try:
    ...     check_entry_name("../x", source="m.csv")
    ... except KpifsError as err:
    ...     print(err)                                     # doctest: +ELLIPSIS
    m.csv: entry name '../x' is not a plain folder name (it would be written outside ...)
    """
    text = str(name)
    if (not text.strip() or text in (".", "..") or "/" in text or "\\" in text
            or "\0" in text or Path(text).is_absolute()):
        raise KpifsError(f"{source}: entry name {text!r} is not a plain folder name (it "
                         f"would be written outside the output folder)")
    if outdir is not None:
        root = Path(outdir).resolve()
        if (root / text).resolve().parent != root:
            raise KpifsError(f"{source}: entry name {text!r} leads outside the output folder "
                             f"{outdir} (a symbolic link?)")


def entries_from_glob(pattern, calibrator=None):
    """One entry per file matching *pattern*, all calibrated by the files of *calibrator*
    (none without: for an angular-differential reduction).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kpifs.batch import entries_from_glob
    >>> tmp = tempfile.TemporaryDirectory()
    >>> d = pathlib.Path(tmp.name)
    >>> for name in ("a.fits", "b.fits", "cal.fits"):
    ...     _ = (d / name).write_bytes(b"")
    >>> [e.name for e in entries_from_glob(str(d / "[ab].fits"), str(d / "cal.fits"))]
    ['a', 'b']
    >>> tmp.cleanup()
    """
    files = sorted(glob.glob(pattern))
    if not files:
        raise KpifsError(f"no file matches {pattern!r}")
    cals = sorted(glob.glob(calibrator)) if calibrator else []
    if calibrator and not cals:
        raise KpifsError(f"no calibrator file matches {calibrator!r}")
    return [absolute_entry(BatchEntry(name=Path(f).name.split(".fits")[0], target=[f],
                                      calibrators=[cals] if cals else []))
            for f in files]


def _entry_options(entry, extract_options):
    """The entry's own reading options (manifest columns) over the shared ones."""
    changes = {k: getattr(entry, k) for k in ("wavelengths", "pixscale", "pa")
               if getattr(entry, k) is not None}
    if entry.instrument not in (None, "auto"):
        changes["instrument"] = entry.instrument
    return dataclasses.replace(extract_options, **changes)


#: The folder, inside the output folder, where entries write before their products are
#: moved into place (removed by the client at the end of a run).
PARTIAL = ".kpifs-partial"


@dataclass
class RunContext:
    """What the client sends with every entry besides its options: the token of the
    output folder's lock (so that a worker can tell it sees the client's folder) and
    the BLAS threads of a worker's task.

    Examples
    --------
    >>> from kpifs.batch import RunContext
    >>> RunContext().blas_threads
    1
    """

    token: str = None
    blas_threads: int = 1


def _worker_name():
    """This worker's Dask address and host (the process, outside a worker)."""
    host = socket.gethostname()
    try:
        from distributed import get_worker
        return f"worker {get_worker().address} on {host}"
    except (ImportError, ValueError):
        return f"process {os.getpid()} on {host}"


def _lock_token(outdir):
    try:
        return json.loads((Path(outdir) / LOCK_NAME).read_text()).get("token")
    except (OSError, ValueError, AttributeError):
        return None


def _check_visible(entry, xo, do, outdir, run):
    """Refuse, naming this worker and the path, an input it cannot see or an output folder
    that is not the client's (no lock of this run in it) or that it cannot write."""
    who = _worker_name()
    shared = ("kpifs batch needs the inputs and the output folder on a filesystem that the "
              "client and every worker share, at the same paths")
    files = list(entry.target) + [f for star in entry.calibrators for f in star]
    files += [getattr(o, k) for o in (xo, do) for k in FILE_OPTIONS
              if isinstance(getattr(o, k, None), str) and os.path.isabs(getattr(o, k))]
    for f in files:
        if not os.path.exists(f):
            raise KpifsError(f"{f}: not found by {who} ({shared})")
    if run is not None and run.token is not None and _lock_token(outdir) != run.token:
        raise KpifsError(f"{outdir}: {who} does not see the client's output folder there (no "
                         f"lock of this batch run in it; {shared})")


def _private_folder(outdir, name):
    """A new folder for one attempt at an entry, inside the output folder."""
    root = Path(outdir) / PARTIAL
    try:
        root.mkdir(exist_ok=True)
        return Path(tempfile.mkdtemp(prefix=f"{name}.", dir=root))
    except OSError as exc:
        raise KpifsError(f"{outdir}: {_worker_name()} cannot write in it "
                         f"({exc.strerror or exc})") from None


def _publish(tmp, out, run):
    """Move an attempt's complete products into the entry's folder, ``detection.fits``
    (what a rerun checks) last, after removing the old one; nothing if the run that
    sent the entry has ended meanwhile (an interrupted run's task still running)."""
    if run is not None and run.token is not None and _lock_token(out.parent) != run.token:
        raise KpifsError(f"{out.name}: the batch run ended before this entry finished; its "
                         f"products are discarded (a rerun makes them)")
    out.mkdir(exist_ok=True)
    (out / "detection.fits").unlink(missing_ok=True)
    for f in sorted(tmp.iterdir(), key=lambda p: p.name == "detection.fits"):
        os.replace(f, out / f.name)


def process_entry(entry, extract_options, detect_options, outdir, *, overwrite=False,
                  run=None):
    """Extraction, calibration and detection of one entry; never raises.

    Runs where Dask sends it: every path in *entry*, the options and *outdir*
    must be absolute (`run_batch` makes them so). The products are written in
    a private folder, then moved into ``outdir/<name>`` once complete. *run*
    (`RunContext`) carries the output folder's lock token and the BLAS threads.

    Returns a dict: ``name``, ``status`` ('ok', 'skipped' or 'failed'),
    ``message``, ``n_candidates``, the strongest candidate, the median limit,
    and the elapsed time.

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.batch import BatchEntry, process_entry
    >>> from kpifs.workflow import DetectOptions, ExtractOptions
    >>> tmp = tempfile.TemporaryDirectory()
    >>> row = process_entry(BatchEntry("x", ["missing.fits"], [["cal.fits"]]),
    ...                     ExtractOptions(), DetectOptions(), tmp.name)
    >>> row["status"], "missing.fits: not found by process" in row["message"]
    ('failed', True)
    >>> tmp.cleanup()
    """
    from threadpoolctl import threadpool_limits
    t0 = time.perf_counter()
    out = Path(outdir) / entry.name
    xo = _entry_options(entry, extract_options)
    row = _row(entry, "failed", xo, detect_options, digest=False)
    tmp = None
    try:
        _check_visible(entry, xo, detect_options, outdir, run)
        row["options_hash"] = observation_digest(entry.target, entry.calibrators, xo,
                                                 detect_options)
        note = ""
        if not overwrite:
            earlier, note = _earlier(row, out / "detection.fits")
            if earlier is not None:
                return earlier
        if not entry.calibrators and not xo.angular_differential \
                and not xo.spectral_differential:
            raise KpifsError(f"{entry.name}: no calibrator")
        tmp = _private_folder(outdir, entry.name)
        with warnings.catch_warnings(record=True) as caught, \
                threadpool_limits(limits=(run or RunContext()).blas_threads, user_api="blas"):
            warnings.simplefilter("always")
            res = process_observation(entry.target, entry.calibrators, tmp, extract_options=xo,
                                      detect_options=detect_options, overwrite=True)["result"]
        _publish(tmp, out, run)
        row["message"] = note + "; ".join(sorted({str(w.message)[:160] for w in caught}))
        row["status"] = "ok"
        _summarise(res, row)
    except Exception as exc:  # one entry's failure must not stop the batch
        row["message"] = f"{type(exc).__name__}: {exc}"
        if not isinstance(exc, (KpifsError, OSError)):
            row["message"] += " | " + traceback.format_exc(limit=3).replace("\n", " ")
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    row["seconds"] = time.perf_counter() - t0
    return row


def _earlier(row, path):
    """``(row, note)``: *row* filled from earlier products made with the same options and
    inputs (status 'skipped'), or None and a note saying why the entry is redone."""
    if not path.exists():
        return None, ""
    try:
        earlier = DetectionResult.read(path)
    except Exception as exc:  # a damaged earlier product: say so, redo it
        return None, f"earlier {path.name} unreadable ({exc}): redone; "
    if earlier.header.get("KPHASH") != row["options_hash"]:
        return None, "redone: the options or inputs differ from the earlier run's; "
    row = dict(row, status="skipped", message="done earlier with the same options and inputs")
    _summarise(earlier, row)
    return row, ""


def _row(entry, status, extract_options, detect_options, message="", *, digest=True):
    """A summary row with nothing measured yet (*digest*: with the ``KPHASH`` its products
    get, which reads the inputs)."""
    return {"name": entry.name, "status": status, "message": message, "n_candidates": -1,
            "best_x": np.nan, "best_y": np.nan, "best_separation": np.nan,
            "best_pfa_global": np.nan, "best_contrast": np.nan, "limit_median": np.nan,
            "seconds": 0.0,
            "options_hash": observation_digest(entry.target, entry.calibrators,
                                               extract_options, detect_options)
            if digest else "",
            "options": _options_text(extract_options, detect_options)}


def _summarise(result, row):
    """Fill *row* with a detection result's strongest candidate and median limit."""
    cand = result.candidates
    row.update(n_candidates=len(cand), limit_median=float(np.nanmedian(result.limit)))
    if len(cand):
        best = cand[0]
        key = "fit_contrast" if "fit_contrast" in cand.colnames else "contrast"
        row.update(best_x=float(u.Quantity(best["x"], u.mas).value),
                   best_y=float(u.Quantity(best["y"], u.mas).value),
                   best_separation=float(u.Quantity(best["separation"], u.mas).value),
                   best_pfa_global=float(best["pfa_global"]),
                   best_contrast=float(np.mean(best[key])))


def _options_text(extract_options, detect_options):
    """The options that differ from the defaults, as ``name=value; ...``."""
    parts = []
    for opts, default in ((extract_options, ExtractOptions()), (detect_options, DetectOptions())):
        mine, base = options_record(opts), options_record(default)
        parts += [f"{k}={v}" for k, v in mine.items() if v != base[k]]
    return "; ".join(parts) or "defaults"


def run_batch(entries, outdir, *, extract_options=None, detect_options=None, overwrite=False,
              scheduler=None, n_workers=2, processes=True, progress=True, blas_threads=1):
    """Process *entries* on Dask; write and return the summary table.

    Parameters
    ----------
    entries : list of `BatchEntry`
        Relative paths are taken from the current folder (`read_manifest` has
        already made a manifest's absolute, against its own folder).
    outdir : str or Path
    extract_options : `~kpifs.workflow.ExtractOptions`
        How every entry's cubes are reduced (as ``kpifs extract`` would).
    detect_options : `~kpifs.workflow.DetectOptions`
        How every entry is searched (as ``kpifs detect`` would).
    overwrite : bool
        Redo entries already done (default: skip them, resuming a run).
    scheduler : str, optional
        Address of a running Dask scheduler, whose workers see the inputs and
        *outdir* at the same paths as this process (a shared filesystem);
        default a local cluster of *n_workers* single-threaded workers.
    processes : bool
        Local cluster with worker processes (default) or, for small jobs and
        tests, one thread (entries then run one at a time: recording each
        entry's warnings is process-wide in Python).
    progress : bool
        Entries done, running, failed and left, with the time left, on stderr
        (they are also logged by ``kpifs.batch`` at level INFO).
    blas_threads : int
        BLAS threads of each entry on its worker.

    Returns
    -------
    `~astropy.table.Table`
        One row per entry, also written to ``OUTDIR/summary.ecsv`` as entries
        finish (not-yet-finished entries are listed as 'pending' meanwhile).

    The output folder is locked while the batch runs (``OUTDIR/.kpifs-batch.lock``):
    a second run on it is refused, naming the holder (pid, host, start time); the
    lock of a run that was killed is taken over with a warning. Entry names are
    plain folder names inside *outdir*. Losing the scheduler stops the run with
    a `~kpifs.KpifsError` after the summary is written; Ctrl-C raises
    `BatchInterrupted` after it is.

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.batch import BatchEntry, run_batch
    >>> entries = [BatchEntry("x", ["missing.fits"], [["cal.fits"]])]
    >>> tmp = tempfile.TemporaryDirectory()
    >>> table = run_batch(entries, tmp.name, n_workers=1, processes=False,
    ...                   progress=False)
    >>> [str(s) for s in table["status"]]
    ['failed']
    >>> tmp.cleanup()
    """
    _cluster._dask()                               # refused now if Dask is missing
    here = os.getcwd()
    xo = absolute_options(extract_options or ExtractOptions(), here)
    do = absolute_options((detect_options or DetectOptions()).validate(), here)
    outdir = Path(os.path.abspath(check_output_dir(outdir)))
    entries = [absolute_entry(e, here) for e in entries]
    names = [e.name for e in entries]
    if len(set(names)) != len(names):
        raise KpifsError("entry names must be unique")
    if not entries:
        raise KpifsError("no entries to process")
    outdir.mkdir(parents=True, exist_ok=True)
    for e in entries:
        check_entry_name(e.name, outdir=outdir)
    with FolderLock(outdir) as lock:
        shutil.rmtree(outdir / PARTIAL, ignore_errors=True)     # an earlier run's leftovers
        try:
            return _run_locked(entries, outdir, xo, do, overwrite=overwrite,
                               scheduler=scheduler, n_workers=n_workers, processes=processes,
                               progress=progress, lock=lock,
                               run=RunContext(lock.info["token"], int(blas_threads)))
        finally:
            shutil.rmtree(outdir / PARTIAL, ignore_errors=True)


def _run_locked(entries, outdir, xo, do, *, overwrite, scheduler, n_workers, processes,
                progress, lock, run):
    """`run_batch` once the output folder's lock is held."""
    summary = _Summary(entries, outdir, xo, do)
    # every entry pending, on disk before any work: a record from the start, and the table
    # writer's imports done before a Ctrl-C can land inside one of them
    summary.write()
    stopped = None
    try:
        with _cluster.dask_client(scheduler, n_workers=n_workers,
                                  processes=processes) as client:
            futures = [client.submit(process_entry, e, xo, do, str(outdir),
                                     overwrite=overwrite, run=run, key=f"kpifs-{e.name}",
                                     pure=False) for e in entries]
            _cluster.collect(client, futures, summary.finished, progress=progress)
    except KeyboardInterrupt:
        # also while the cluster starts: every entry is then recorded as interrupted
        stopped = "interrupted"
    except _cluster.SchedulerLost as exc:
        stopped = f"lost the Dask scheduler at {scheduler} ({exc})"
    # tasks still running on a cluster that outlives this run (a remote one: Ctrl-C, the
    # scheduler lost) must not publish once the summary is written
    lock.retire_token()
    table = summary.close(overwrite=overwrite, lost=stopped not in (None, "interrupted"))
    if stopped is not None:
        n = int(np.sum(table["status"] == "interrupted"))
        what = (f"{len(table) - n} entries finished, {n} not; {outdir / 'summary.ecsv'} "
                f"records them; rerun to resume")
        if stopped == "interrupted":
            raise BatchInterrupted(what)
        raise KpifsError(f"{stopped}: {what}")
    return table


class _Summary:
    """``OUTDIR/summary.ecsv``, rewritten as entries finish (at most 5 % of the client's
    time goes to it), so that a client that dies loses nothing already done."""

    def __init__(self, entries, outdir, xo, do):
        self.entries, self.path, self.xo, self.do = entries, outdir / "summary.ecsv", xo, do
        self.rows = {}
        self.next = 0.0
        self.pending = _row(entries[0], "pending", xo, do, "not finished yet", digest=False)

    def finished(self, i, row, why=None):
        e = self.entries[i]
        if row is None:                     # Dask gave up on it (its workers died)
            row = _row(e, "failed", _entry_options(e, self.xo), self.do, why, digest=False)
        self.rows[e.name] = row
        now = time.monotonic()
        if now >= self.next:
            self.write()
            self.next = now + 20 * (time.monotonic() - now)

    def table(self):
        rows = [self.rows.get(e.name) or dict(self.pending, name=e.name)
                for e in self.entries]
        table = Table(rows=[[r[k] for k in rows[0]] for r in rows], names=list(rows[0]))
        table.meta.update({"extract_options": options_record(self.xo),
                           "detect_options": options_record(self.do),
                           "n_entries": len(rows)})
        for col in ("best_x", "best_y", "best_separation"):
            table[col].unit = u.mas
        return table

    def write(self):
        write_table(self.table(), self.path, overwrite=True)

    def close(self, *, overwrite, lost):
        """The final table: entries not finished are 'interrupted' (or, finished before
        the stop, 'ok' from their products)."""
        why = ("the scheduler was lost before it finished" if lost
               else "interrupted before it finished") + "; a rerun does it"
        for e in self.entries:
            if e.name in self.rows:
                continue
            row = _row(e, "interrupted", _entry_options(e, self.xo), self.do, why,
                       digest=False)
            path = self.path.parent / e.name / "detection.fits"
            if path.exists() and not overwrite:       # finished before the stop?
                row["options_hash"] = observation_digest(
                    e.target, e.calibrators, _entry_options(e, self.xo), self.do)
                finished, _ = _earlier(row, path)
                if finished is not None:
                    row = dict(finished, status="ok", message="finished before the stop")
            self.rows[e.name] = row
        table = self.table()
        write_table(table, self.path, overwrite=True)
        return table


class BatchInterrupted(KeyboardInterrupt):
    """A batch stopped by Ctrl-C, after its summary was written (the message says where).

    A `KeyboardInterrupt`, so that code which catches Ctrl-C catches it too.

    Examples
    --------
    >>> from kpifs.batch import BatchInterrupted
    >>> try:
    ...     raise BatchInterrupted("interrupted: summary of what finished in out/summary.ecsv")
    ... except KeyboardInterrupt as err:
    ...     print(err)
    interrupted: summary of what finished in out/summary.ecsv
    """
