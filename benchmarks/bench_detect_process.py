"""Whole-process time of ``kpifs detect`` on the 20-frame CHARIS simulation (issue 13).

Simulates ``kpifs simulate --preset charis --layout charis --frames 20`` (22
channels, 264 kernel phases once calibrated), extracts and calibrates it
(``kpifs extract TARGET --calibrator CAL``), then times, alternately and
--repeat times each, whole processes of ``kpifs detect CALIBRATED`` with the
default options (the issue's target: < 3 s):

- this checkout, on all cores and with ``KPIFS_THREADS=1``;
- optionally ``--baseline-path DIR``: another checkout (e.g. the commit before
  this work), with PYTHONPATH=DIR.

Then, in this process, the Gaussian null's 5000 draws against their bare
matrix products (the same ``(draws, rows) @ (rows, positions)`` products per
channel, nothing else): how far the statistic's elementwise work is from the
BLAS floor. Prints medians of wall time and peak resident memory and the
ratios.
"""
import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_process import ROOT, print_medians, time_commands  # noqa: E402


def prepare(tmp):
    run = [sys.executable, "-m", "kpifs"]
    subprocess.run(run + ["simulate", "--preset", "charis", "--layout", "charis", "--frames",
                          "20", "-o", str(tmp / "sim"), "-q"], check=True)
    cal = tmp / "calibrated.fits"
    subprocess.run(run + ["extract", *sorted(map(str, (tmp / "sim" / "target").glob("*.fits"))),
                          "--calibrator",
                          *sorted(map(str, (tmp / "sim" / "calibrator").glob("*.fits"))),
                          "-o", str(cal), "-q"], check=True)
    return cal


def search_model(cal):
    """The calibrated file *cal* as `kpifs.detect.detect` prepares it: the data, their
    whitening and rank, and the search's `DetectionModel` on the default grid."""
    from kpifs.covariance import whitening_matrix
    from kpifs.data import KernelPhaseData
    from kpifs.detect import DetectionModel, pipeline
    kpd = KernelPhaseData.read(cal)
    kp, cov, kpd = pipeline._prepare(kpd, "auto", False)
    w, rank = whitening_matrix(cov, return_rank=True)
    frame, poses, _ = pipeline._frame_and_poses(kpd, "auto", None)
    model = DetectionModel(kpd.kernel_model, kpd.wavelengths, w,
                           pipeline.default_grid(kpd, frame=frame), pixscale=kpd.pixscale,
                           window=kpd.window, dof=np.atleast_1d(rank), detpa=poses)
    return kpd, w, rank, model


def null_versus_products(cal, repeat=3):
    from kpifs.covariance import whiten
    from kpifs.detect import NullCalibration
    from kpifs.detect.null import _CACHE
    kpd, w, rank, model = search_model(cal)
    rows = whiten(kpd.covariance_rows, w)
    valid, z = model.row_projections(rows)
    positions = model.half_positions()[0]
    proj = np.ascontiguousarray(z[np.searchsorted(valid, positions)].transpose(2, 1, 0),
                                np.float32)                          # (q, nrow, npos)
    coef = np.random.default_rng(0).standard_normal((5000, len(rows)), dtype=np.float32)
    t_null, t_bare = [], []
    for _ in range(repeat):
        _CACHE.clear()
        t0 = time.perf_counter()
        NullCalibration(model, n_draws=5000, seed=1, noise_rows=rows).draws
        t_null.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        out = np.empty((256, proj.shape[2]), np.float32)
        for a in range(0, len(coef), 256):
            for i in range(len(proj)):
                np.matmul(coef[a:a + 256], proj[i], out=out[:len(coef[a:a + 256])])
        t_bare.append(time.perf_counter() - t0)
    return np.median(t_null), np.median(t_bare), proj.shape


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--baseline-path", help="another kpifs checkout to time as well")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp())
    cal = prepare(tmp)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = [sys.executable, "-m", "kpifs", "detect", str(cal), "-o", str(tmp / "det.fits"),
           "--overwrite", "-q"]
    commands = {"kpifs detect": (cmd, None),
                "kpifs detect, KPIFS_THREADS=1": (cmd, {"KPIFS_THREADS": "1"})}
    if args.baseline_path:
        commands["kpifs detect (baseline checkout)"] = (cmd, {"PYTHONPATH": args.baseline_path})
    print_medians(time_commands(commands, args.repeat, env), args.repeat)
    print("target: < 3 s")
    t_null, t_bare, shape = null_versus_products(cal)
    print(f"Gaussian null, 5000 draws, {shape[0]} channels x {shape[1]} rows x {shape[2]} "
          f"positions: {t_null:.2f} s; its bare matrix products {t_bare:.2f} s "
          f"(ratio {t_null / t_bare:.1f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
