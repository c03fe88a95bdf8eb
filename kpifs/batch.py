"""Archive reprocessing on Dask: extraction -> calibration -> detection for many entries.

An entry is a target observation (one or more cube files) with its calibrator
star(s). Entries come from a manifest (CSV or ECSV; columns ``name``,
``target``, ``calibrator`` and optionally ``instrument``, ``wavelengths``,
``pixscale``; several files in one cell are separated by ``;``, several
calibrator stars by ``|``) or from a glob with one calibrator rule.

Each entry is reduced by `kpifs.workflow.process_observation` with the same
`~kpifs.workflow.ExtractOptions` and `~kpifs.workflow.DetectOptions` as the
command line, and writes ``OUTDIR/<name>/calibrated_kp.fits`` and
``OUTDIR/<name>/detection.fits``; ``OUTDIR/summary.ecsv`` lists every entry
with its status, candidates and limits. An entry whose ``detection.fits``
exists is skipped (a rerun resumes), unless ``overwrite=True``. A failure is
recorded for its entry and does not stop the others.

Dask is an optional dependency (``pip install kpifs[batch]``), imported only
when a batch runs.
"""
import contextlib
import dataclasses
import glob
import logging
import signal
import threading
import time
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.table import Table

from ._utils import progress as progress_bar
from ._utils import check_output_dir, write_table
from .data import DetectionResult
from ._lock import FolderLock
from .exceptions import KpifsError
from .workflow import (DetectOptions, ExtractOptions, observation_digest, options_record,
                       process_observation)

__all__ = ["BatchEntry", "read_manifest", "entries_from_glob", "check_entry_name",
           "process_entry", "run_batch"]

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

    Relative paths are relative to the manifest's folder; cells may hold globs.

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
    base = path.parent
    entries = []
    for row in tab:
        target = [f for p in _split(row["target"]) for f in _expand(p, base)]
        cals = [[f for p in _split(star) for f in _expand(p, base)]
                for star in _split(row["calibrator"], "|")]
        opt = {k: (None if np.ma.is_masked(row[k]) else str(row[k]))
               for k in ("instrument", "wavelengths", "pixscale") if k in tab.colnames}
        entries.append(BatchEntry(name=str(row["name"]), target=target, calibrators=cals,
                                  instrument=opt.get("instrument") or "auto",
                                  wavelengths=opt.get("wavelengths"),
                                  pixscale=opt.get("pixscale")))
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


def entries_from_glob(pattern, calibrator):
    """One entry per file matching *pattern*, all calibrated by the files of *calibrator*.

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
    cals = sorted(glob.glob(calibrator))
    if not cals:
        raise KpifsError(f"no calibrator file matches {calibrator!r}")
    return [BatchEntry(name=Path(f).name.split(".fits")[0], target=[f], calibrators=[cals])
            for f in files]


def _entry_options(entry, extract_options):
    """The entry's own reading options (manifest columns) over the shared ones."""
    changes = {k: getattr(entry, k) for k in ("wavelengths", "pixscale")
               if getattr(entry, k) is not None}
    if entry.instrument not in (None, "auto"):
        changes["instrument"] = entry.instrument
    return dataclasses.replace(extract_options, **changes)


def process_entry(entry, extract_options, detect_options, outdir, *, overwrite=False):
    """Extraction, calibration and detection of one entry; never raises.

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
    >>> row["status"], "missing.fits" in row["message"]
    ('failed', True)
    >>> tmp.cleanup()
    """
    t0 = time.perf_counter()
    out = Path(outdir) / entry.name
    xo = _entry_options(entry, extract_options)
    row = _row(entry, "failed", xo, detect_options)
    note = ""
    if not overwrite:
        earlier, note = _earlier(row, out / "detection.fits")
        if earlier is not None:
            return earlier
    try:
        if not entry.calibrators:
            raise KpifsError(f"{entry.name}: no calibrator")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = process_observation(entry.target, entry.calibrators, out, extract_options=xo,
                                      detect_options=detect_options, overwrite=True)["result"]
        row["message"] = note + "; ".join(sorted({str(w.message)[:160] for w in caught}))
        row["status"] = "ok"
        _summarise(res, row)
    except Exception as exc:  # one entry's failure must not stop the batch
        row["message"] = f"{type(exc).__name__}: {exc}"
        if not isinstance(exc, (KpifsError, OSError)):
            row["message"] += " | " + traceback.format_exc(limit=3).replace("\n", " ")
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


def _row(entry, status, extract_options, detect_options, message=""):
    """A summary row with nothing measured yet."""
    return {"name": entry.name, "status": status, "message": message, "n_candidates": -1,
            "best_x": np.nan, "best_y": np.nan, "best_separation": np.nan,
            "best_pfa_global": np.nan, "best_contrast": np.nan, "limit_median": np.nan,
            "seconds": 0.0,
            "options_hash": observation_digest(entry.target, entry.calibrators,
                                               extract_options, detect_options),
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
              scheduler=None, n_workers=2, processes=True, progress=True):
    """Process *entries* on Dask; write and return the summary table.

    Parameters
    ----------
    entries : list of `BatchEntry`
    outdir : str or Path
    extract_options : `~kpifs.workflow.ExtractOptions`
        How every entry's cubes are reduced (as ``kpifs extract`` would).
    detect_options : `~kpifs.workflow.DetectOptions`
        How every entry is searched (as ``kpifs detect`` would).
    overwrite : bool
        Redo entries already done (default: skip them, resuming a run).
    scheduler : str, optional
        Address of a running Dask scheduler; default a local cluster of
        *n_workers* single-threaded workers.
    processes : bool
        Local cluster with worker processes (default) or, for small jobs and
        tests, one thread (entries then run one at a time: recording each
        entry's warnings is process-wide in Python).
    progress : bool
        A progress bar over finished entries (on a terminal).

    Returns
    -------
    `~astropy.table.Table`
        One row per entry (also written to ``OUTDIR/summary.ecsv``).

    The output folder is locked while the batch runs (``OUTDIR/.kpifs-batch.lock``):
    a second run on it is refused, naming the holder (pid, host, start time); the
    lock of a run that was killed is taken over with a warning. Entry names are
    plain folder names inside *outdir*.

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
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise KpifsError("kpifs batch needs Dask: pip install 'kpifs[batch]'") from None
    xo = extract_options or ExtractOptions()
    do = (detect_options or DetectOptions()).validate()
    outdir = check_output_dir(outdir)
    names = [e.name for e in entries]
    if len(set(names)) != len(names):
        raise KpifsError("entry names must be unique")
    if not entries:
        raise KpifsError("no entries to process")
    outdir.mkdir(parents=True, exist_ok=True)
    for e in entries:
        check_entry_name(e.name, outdir=outdir)
    with FolderLock(outdir):
        return _run_locked(entries, outdir, xo, do, overwrite=overwrite, scheduler=scheduler,
                           n_workers=n_workers, processes=processes, progress=progress,
                           dask=(Client, LocalCluster, as_completed))


def _run_locked(entries, outdir, xo, do, *, overwrite, scheduler, n_workers, processes,
                progress, dask):
    """`run_batch` once the output folder's lock is held."""
    Client, LocalCluster, as_completed = dask
    names = [e.name for e in entries]
    cluster = client = None
    rows, futures = [], []
    interrupted = False
    try:
        if scheduler is None:
            # a free port for the dashboard: never the default 8787 another cluster may hold
            with _sigint_ignored():
                cluster = LocalCluster(n_workers=n_workers if processes else 1,
                                       threads_per_worker=1, processes=processes,
                                       dashboard_address=":0")
            client = Client(cluster)
        else:
            client = Client(scheduler)
        futures = [client.submit(process_entry, e, xo, do, str(outdir), overwrite=overwrite,
                                 key=f"kpifs-{e.name}", pure=False) for e in entries]
        for fut in progress_bar(as_completed(futures), total=len(futures), desc="batch",
                                unit="entry", enabled=progress):
            rows.append(fut.result())
    except KeyboardInterrupt:
        # also while the cluster starts: every entry is then recorded as interrupted
        interrupted = True
        _silence_distributed()
        if client is not None:
            client.cancel(futures)
            _quiet_shutdown(client)
    finally:
        try:
            if client is not None:
                client.close()
            if cluster is not None:
                cluster.close()
        except KeyboardInterrupt:     # a second Ctrl-C while the cluster closes
            interrupted = True
    done = {r["name"] for r in rows}
    for e in entries:
        if e.name in done:
            continue
        row = _row(e, "interrupted", _entry_options(e, xo), do,
                   "interrupted before it finished; a rerun does it")
        finished, _ = _earlier(row, outdir / e.name / "detection.fits")
        if finished is not None and not overwrite:   # finished before the interrupt
            finished.update(status="ok", message="finished before the interrupt")
        rows.append(finished if finished is not None and not overwrite else row)
    order = {n: i for i, n in enumerate(names)}
    rows.sort(key=lambda r: order[r["name"]])
    table = Table(rows=[[r[k] for k in rows[0]] for r in rows], names=list(rows[0]))
    table.meta.update({"extract_options": options_record(xo),
                       "detect_options": options_record(do), "n_entries": len(rows)})
    for col in ("best_x", "best_y", "best_separation"):
        table[col].unit = u.mas
    _write_summary(table, outdir / "summary.ecsv")
    if interrupted:
        n = int(np.sum(table["status"] == "interrupted"))
        raise BatchInterrupted(f"{len(table) - n} entries finished, {n} interrupted; "
                               f"{outdir / 'summary.ecsv'} records them; rerun to resume")
    return table


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


def _silence_distributed():
    logging.getLogger("distributed").setLevel(logging.CRITICAL)


def _quiet_shutdown(client):
    """Before an interrupted batch closes its cluster: the workers' and nannies' complaints
    that the scheduler went away mid-heartbeat (tracebacks, on a race of the shutdown)
    are noise then, and the user asked for a short message."""
    _silence_distributed()
    for nanny in (False, True):
        try:
            client.run(_silence_distributed, nanny=nanny)
        except Exception:    # no nannies (a threaded cluster), or workers already gone
            pass


class BatchInterrupted(KeyboardInterrupt):
    """A batch stopped by Ctrl-C, after its summary was written (the message says where)."""


def _write_summary(table, path):
    write_table(table, path, overwrite=True)
