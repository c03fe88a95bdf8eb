"""``kpifs detect`` with ``--spectral-differential`` against without (issue 39): the ratio
of their times on the same 20-frame, 22-channel CHARIS file (acceptance: at most 1.3).

Simulates the sequence (``kpifs simulate --preset charis --typical-static``, no
companion), extracts it twice with ``kpifs extract`` (with the option, its default
basis unless ``--basis`` says otherwise; without), then times ``kpifs detect`` on each
file in turn (``--allow-uncalibrated`` without the option), *repeat* times, and prints
the ratio of the medians; with
``--cpu``, also that of the median CPU times (user + system of this process and its
children over each call: the steadier figure on a loaded machine). Run from the
project root: ``python benchmarks/bench_sdk.py``.
"""
import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

from kpifs.cli import main as kpifs


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--draws", default="1000")
    ap.add_argument("--basis", default="static", choices=("static", "poly", "both"),
                    help="the option's basis (default: its default, static)")
    ap.add_argument("--cpu", action="store_true",
                    help="also report the CPU times (user + system) and their ratio")
    args = ap.parse_args(argv)
    root = Path(tempfile.mkdtemp(prefix="kpifs-bench-sdk-"))
    assert kpifs(["simulate", "--preset", "charis", "--typical-static", "--shape", "80",
                  "--frames", "20", "--contrasts", ",".join(["0"] * 22),
                  "-o", str(root / "sim"), "-q"]) == 0
    cube = str(root / "sim" / "target.fits")
    assert kpifs(["extract", cube, "-o", str(root / "raw.fits"), "-q"]) == 0
    assert kpifs(["extract", cube, "--spectral-differential", args.basis, "-o",
                  str(root / "sdk.fits"), "-q"]) == 0
    times = {"with": [], "without": []}
    cpu = {"with": [], "without": []}
    for i in range(args.repeat):
        for name, path, extra in (("without", "raw.fits", ["--allow-uncalibrated"]),
                                  ("with", "sdk.fits", [])):
            t0, c0 = time.perf_counter(), _cpu()
            assert kpifs(["detect", str(root / path), "-o", str(root / f"det{i}{name}.fits"),
                          "--draws", args.draws, "--pfa", "0.01", "-q"] + extra) == 0
            times[name].append(time.perf_counter() - t0)
            cpu[name].append(_cpu() - c0)
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"basis {args.basis}; kpifs detect, median of {args.repeat}: without "
          f"{med['without']:.1f} s, with --spectral-differential {med['with']:.1f} s: "
          f"ratio {med['with'] / med['without']:.2f}")
    if args.cpu:
        med = {k: statistics.median(v) for k, v in cpu.items()}
        print(f"CPU (user + sys), median of {args.repeat}: without {med['without']:.1f} s, "
              f"with {med['with']:.1f} s: ratio {med['with'] / med['without']:.2f}")


def _cpu():
    """User + system time of this process and its children so far (s)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


if __name__ == "__main__":
    main()
