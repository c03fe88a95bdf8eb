"""Archive reprocessing on Dask, as on a cluster (issue 40): entries per minute and the
per-entry overhead of the distributed path, and a paper estimate for a large archive.

A synthetic archive of small entries (paper scene, target + calibrator each) is run
with ``kpifs batch`` in three set-ups, each into a fresh output folder:

- a local cluster of 1 worker process;
- a local cluster of 2 worker processes;
- a ``dask scheduler`` and 2 ``dask worker`` processes started separately, in a folder
  of their own, and ``kpifs batch --scheduler`` (what a cluster does, on localhost).

For each: the wall time of the whole command (start-up included), entries per minute,
and the per-entry overhead: the wall time each worker spends per entry beyond the time
the entry's own work takes inside `kpifs.batch.process_entry` (the summary's
``seconds``), i.e. ``(wall - start-up) * workers / entries - mean(seconds)``, where
start-up is the time of the same command on an archive of one entry less that entry's
work. One CHARIS-like entry (22 channels, 64x64 pixels) is then timed in this process, and
the estimate for 10^4 CHARIS sequences on 100 nodes is printed from those measures.
The machine's load is printed with the figures: they are only comparable within a run.
"""
import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import astropy.units as u
import numpy as np
from astropy.table import Table

from kpifs.batch import BatchEntry, process_entry
from kpifs.io.layouts import write_observation
from kpifs.simulation.simulate import simulate_scene
from kpifs.workflow import DetectOptions, ExtractOptions

OPTIONS = ["--step", "1.2m", "--draws", "1000", "--pfa", "0.01", "-q"]


def _archive(root, n, frames):
    lines = ["name,target,calibrator"]
    for i in range(n):
        obs = simulate_scene("paper", n_frames=frames, seed=i, npup=32, exptime=1 * u.s)
        write_observation(obs, root / f"e{i}")
        lines.append(f"e{i},e{i}/target.fits,e{i}/calibrator.fits")
    (root / "all.csv").write_text("\n".join(lines) + "\n")
    (root / "one.csv").write_text("\n".join(lines[:2]) + "\n")


def _batch(manifest, out, extra):
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "kpifs", "batch", str(manifest), *OPTIONS,
                          *extra, "-o", str(out)], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        raise SystemExit(f"kpifs batch failed: {res.stderr}")
    return wall, np.asarray(Table.read(out / "summary.ecsv")["seconds"], float)


def _remote_cluster(home, n_workers):
    home.mkdir()
    sfile = home / "scheduler.json"
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler",
                               "--port", "0", "--no-dashboard", "--scheduler-file", str(sfile)],
                              cwd=home, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              start_new_session=True)]
    while not sfile.exists():
        time.sleep(0.1)
    address = json.loads(sfile.read_text())["address"]
    for _ in range(n_workers):
        procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker",
                                       address, "--nthreads", "1", "--no-dashboard",
                                       "--local-directory", str(home)], cwd=home,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                      start_new_session=True))
    from dask.distributed import Client
    with Client(address) as c:
        c.wait_for_workers(n_workers, timeout=120)
    return address, procs


def _stop(procs):
    for p in procs:
        try:
            os.killpg(p.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
    for p in procs:
        p.wait(timeout=30)


def _charis_entry(root):
    """Seconds of one CHARIS-like entry (22 channels, 64x64, 40 frames per star)."""
    obs = simulate_scene("charis", n_frames=40, seed=1, npup=64, shape=(64, 64),
                         exptime=1 * u.s)
    files = write_observation(obs, root / "charis")
    (root / "charis_out").mkdir()
    entry = BatchEntry("charis", [str(f) for f in files["target"]],
                       [[str(f) for f in files["calibrator"]]])
    row = process_entry(entry, ExtractOptions(step="0.8m", min_transmission=0.9),
                        DetectOptions(), str(root / "charis_out"))
    if row["status"] != "ok":
        raise SystemExit(f"CHARIS entry failed: {row['message']}")
    return row["seconds"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--entries", type=int, default=40)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--overhead", type=float,
                    help="skip the archive runs: time the CHARIS entry and estimate with this "
                         "per-entry overhead (s)")
    args = ap.parse_args(argv)
    root = Path(tempfile.mkdtemp(prefix="kpifs-bench-cluster-"))
    if args.overhead is not None:
        return _estimate(root, args.overhead)
    _archive(root, args.entries, args.frames)
    print(f"archive: {args.entries} entries (paper scene, {args.frames} frames per star, "
          f"32-pixel pupil); load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    setups = [("local, 1 worker", 1, ["--workers", "1"], None),
              ("local, 2 workers", 2, ["--workers", "2"], None),
              ("scheduler + 2 workers, separate processes", 2, None, 2)]
    rows = []
    for k, (label, n, extra, remote) in enumerate(setups):
        procs = []
        if remote:
            address, procs = _remote_cluster(root / f"cluster{k}", remote)
            extra = ["--scheduler", address]
        try:
            w1, s1 = _batch(root / "one.csv", root / f"one{k}", extra)
            wall, secs = _batch(root / "all.csv", root / f"out{k}", extra)
        finally:
            _stop(procs)
        start = max(0.0, w1 - s1.sum())
        overhead = (wall - start) * n / args.entries - secs.mean()
        rows.append((label, wall, 60 * args.entries / wall, start, secs.mean(), overhead))
        print(f"{label}: {args.entries} entries in {wall:.1f} s = "
              f"{rows[-1][2]:.1f} entries/minute; start-up {start:.1f} s; an entry's work "
              f"{secs.mean():.2f} s, overhead per entry {overhead:.2f} s "
              f"(load {os.getloadavg()[0]:.1f})", flush=True)
    return _estimate(root, max(0.0, max(r[5] for r in rows)))


def _estimate(root, over):
    t_charis = _charis_entry(root)
    print(f"one CHARIS-like entry (22 channels, 40+40 frames of 64x64, 5000 draws): "
          f"{t_charis:.1f} s of work on one core (load {os.getloadavg()[0]:.1f})")
    for cores in (16, 32):
        workers = 100 * cores
        hours = 1e4 * (t_charis + over) / workers / 3600
        print(f"paper estimate: 1e4 CHARIS sequences on 100 nodes x {cores} single-thread "
              f"workers = {1e4 / workers:.1f} entries per worker x ({t_charis:.1f} s + "
              f"{over:.2f} s overhead) = {hours:.2f} h, if the filesystem serves "
              f"{workers} readers (one sequence ~{22 * 80 * 64 * 64 * 4 / 1e6:.0f} MB as "
              f"float32 cut-outs)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
