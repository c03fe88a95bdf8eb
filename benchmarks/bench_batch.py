"""Archive reprocessing throughput on a local Dask cluster: 1 versus 2 workers (issue 5).

Simulates a small archive (paper-scene target/calibrator pairs), then runs
``kpifs.batch.run_batch`` on it with one and with two worker processes into
fresh output folders, and reports entries per minute.
"""
import argparse
import tempfile
import time
from pathlib import Path

import astropy.units as u

from kpifs.batch import BatchEntry, run_batch
from kpifs.io.layouts import write_observation
from kpifs.simulation.simulate import simulate_scene
from kpifs.workflow import DetectOptions, ExtractOptions


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--entries", type=int, default=6)
    ap.add_argument("--frames", type=int, default=150)
    args = ap.parse_args(argv)
    root = Path(tempfile.mkdtemp(prefix="kpifs-bench-batch-"))
    entries = []
    for i in range(args.entries):
        obs = simulate_scene("paper", n_frames=args.frames, seed=i, npup=64, exptime=1 * u.s)
        files = write_observation(obs, root / f"obs{i}")
        entries.append(BatchEntry(name=f"obs{i}", target=[str(files["target"][0])],
                                  calibrators=[[str(files["calibrator"][0])]]))
    opts = dict(extract_options=ExtractOptions(step=0.6 * u.m),
                detect_options=DetectOptions(draws=10000))
    rates = {}
    for workers in (1, 2):
        t0 = time.perf_counter()
        table = run_batch(entries, root / f"out{workers}", **opts, n_workers=workers,
                          progress=False)
        dt = time.perf_counter() - t0
        assert all(table["status"] == "ok"), table
        rates[workers] = args.entries / dt * 60
        print(f"{workers} worker(s): {args.entries} entries in {dt:.1f} s "
              f"= {rates[workers]:.1f} entries/minute (cluster start-up included)")
    print(f"speed-up with 2 workers: {rates[2] / rates[1]:.2f}x (2 cores)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
