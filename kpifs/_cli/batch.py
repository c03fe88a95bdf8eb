"""``kpifs batch``: many observations, reduced as ``extract`` + ``detect`` would, on Dask."""
import os
import sys

import numpy as np

from ..batch import entries_from_glob, read_manifest, run_batch
from ..exceptions import KpifsError
from ._options import detect_options, extract_options


def _blas_threads():
    env = os.environ.get("KPIFS_BLAS_THREADS", "").strip()
    return int(env) if env.isdigit() and int(env) > 0 else 1


def run(args):
    entries = []
    for m in args.manifest or []:
        entries += read_manifest(m)
    if args.glob:
        if not args.calibrator and not args.angular_differential \
                and not args.spectral_differential:
            raise KpifsError("--glob needs --calibrator PATTERN (the calibrator rule), or "
                             "--angular-differential or --spectral-differential")
        entries += entries_from_glob(args.glob, args.calibrator)
    if not entries:
        raise KpifsError("nothing to do: give a MANIFEST or --glob PATTERN --calibrator PATTERN")
    table = run_batch(entries, args.output, extract_options=extract_options(args),
                      detect_options=detect_options(args), overwrite=args.overwrite,
                      scheduler=args.scheduler, n_workers=args.workers,
                      progress=not args.quiet, blas_threads=_blas_threads())
    counts = {s: int(np.sum(table["status"] == s)) for s in ("ok", "skipped", "failed")}
    print(f"{len(table)} entries: {counts['ok']} processed, {counts['skipped']} done earlier, "
          f"{counts['failed']} failed -> {args.output}/summary.ecsv")
    for row in table[table["status"] == "failed"]:
        print(f"  {row['name']}: {row['message'][:200]}", file=sys.stderr)
    return 0 if counts["failed"] == 0 else 1
