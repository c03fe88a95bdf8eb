"""``kpifs detect`` with ``--spectral-differential`` against without (issue 39): the ratio
of their times on the same 20-frame, 22-channel CHARIS file (acceptance: at most 1.3).

Simulates the sequence (``kpifs simulate --preset charis --typical-static``, no
companion), extracts it twice with ``kpifs extract`` (with the option, its default
basis unless ``--basis`` says otherwise; without), then, alternately and *repeat* times
each:

- whole processes of ``kpifs detect FILE --draws D --pfa 0.01`` (``--allow-uncalibrated``
  without the option): what a user waits for, one process per file (wall time, and CPU
  time: user + system, the steadier figure on a loaded machine);
- the search alone, ``kpifs.detect.detect`` on the file already read, in this process,
  with the null's cache emptied before each call: the same work without the imports
  and the file's reading and writing that both commands share.

Each search's candidates are printed: without the option the static aberration gives
the search spurious candidates, whose fits are part of its time. Run from the project
root: ``python benchmarks/bench_sdk.py``. ``--threads N`` sets KPIFS_THREADS and
OPENBLAS_NUM_THREADS (1 by default).
"""
import argparse
import logging
import os
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_detect_stages import run_once  # noqa: E402
from bench_process import ROOT  # noqa: E402


def _cpu():
    """User + system time of this process so far (s)."""
    t = os.times()
    return t.user + t.system


def prepare(root, basis):
    run = [sys.executable, "-m", "kpifs"]
    subprocess.run(run + ["simulate", "--preset", "charis", "--typical-static", "--shape", "80",
                          "--frames", "20", "--contrasts", ",".join(["0"] * 22),
                          "-o", str(root / "sim"), "-q"], check=True)
    cube = str(root / "sim" / "target.fits")
    subprocess.run(run + ["extract", cube, "-o", str(root / "raw.fits"), "-q"], check=True)
    subprocess.run(run + ["extract", cube, "--spectral-differential", basis, "-o",
                          str(root / "sdk.fits"), "-q"], check=True)


def searches(root, draws, repeat, threads):
    """Median CPU and wall time of `kpifs.detect.detect` on each file (read once), the
    null's cache emptied before each call, and each search's number of candidates."""
    from threadpoolctl import threadpool_limits

    from kpifs.data import KernelPhaseData
    from kpifs.detect import detect
    from kpifs.detect.null import _CACHE
    logging.getLogger("kpifs").setLevel(logging.ERROR)
    files = {"without": (KernelPhaseData.read(root / "raw.fits"), {"allow_uncalibrated": True}),
             "with": (KernelPhaseData.read(root / "sdk.fits"), {})}
    runs = {k: [] for k in files}
    found = {}
    for _ in range(repeat):
        for name, (kpd, extra) in files.items():
            _CACHE.clear()
            t0, c0 = time.perf_counter(), _cpu()
            with warnings.catch_warnings(), threadpool_limits(threads):
                warnings.simplefilter("ignore")
                res = detect(kpd, n_draws=int(draws), pfa=0.01, **extra)
            runs[name].append((time.perf_counter() - t0, _cpu() - c0))
            found[name] = len(res.candidates)
    return {k: [statistics.median(x) for x in zip(*v)] for k, v in runs.items()}, found


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--draws", default="1000")
    ap.add_argument("--basis", default="static", choices=("static", "poly", "both"),
                    help="the option's basis (default: its default, static)")
    ap.add_argument("--dir", help="a folder holding raw.fits and sdk.fits made before")
    ap.add_argument("--threads", default="1", help="threads of every search (default 1)")
    args = ap.parse_args(argv)
    os.environ.update(KPIFS_THREADS=args.threads, OPENBLAS_NUM_THREADS=args.threads,
                      OMP_NUM_THREADS=args.threads)
    root = Path(args.dir) if args.dir else Path(tempfile.mkdtemp(prefix="kpifs-bench-sdk-"))
    if not args.dir:
        prepare(root, args.basis)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    load0 = os.getloadavg()
    cmd = {name: [sys.executable, "-m", "kpifs", "detect", str(root / f"{f}.fits"), "-o",
                  str(root / f"det_{f}.fits"), "--overwrite", "--draws", args.draws,
                  "--pfa", "0.01", "-q"] + extra
           for name, f, extra in (("without", "raw", ["--allow-uncalibrated"]),
                                  ("with", "sdk", []))}
    runs = {k: [] for k in cmd}
    for _ in range(args.repeat):
        for name, c in cmd.items():
            runs[name].append(run_once(c, env)[:2])
    proc = {k: [statistics.median(x) for x in zip(*v)] for k, v in runs.items()}
    alone, found = searches(root, args.draws, args.repeat, int(args.threads))
    print(f"basis {args.basis}, {args.draws} draws, median of {args.repeat}, "
          f"{args.threads} thread(s)")
    print(f"{'':36s} {'without':>9s} {'with':>9s} {'ratio':>6s}")
    for label, med in (("kpifs detect, whole process", proc),
                       ("detect() alone, null cache empty", alone)):
        for i, unit in enumerate(("wall", "CPU")):
            a, b = med["without"][i], med["with"][i]
            print(f"{label + ', ' + unit:36s} {a:8.2f}s {b:8.2f}s {b / a:6.2f}")
    print(f"candidates: without the option {found['without']}, with it {found['with']} "
          f"(target: ratio <= 1.3)")
    print(f"load average before {load0}, after {os.getloadavg()} on {os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
