"""Whole-process ``kpifs detect`` on a rotating sequence against a fixed one (issue 29).

Simulates the 20-frame 22-channel CHARIS scene twice with the same seed, once
with the sky turning by 40 deg over the sequence (``kpifs simulate --preset
charis --layout charis --rotation 40deg``) and once without, extracts and
calibrates both (``kpifs extract TARGET --calibrator CAL``), then times,
alternately and --repeat times each, whole processes of ``kpifs detect`` with
the default options:

- the fixed sequence (the reference: one mean, the fast path);
- the rotating one, searched block by block (`kpifs.detect.blocks`, the default);
- the rotating one with ``--blocks mean`` (the model averaged over the angles,
  the search before issue 29).

The issue's target: the rotating file at most 1.5 x the fixed one.
"""
import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_process import ROOT, print_medians, time_commands  # noqa: E402


def prepare(tmp, rotation):
    run = [sys.executable, "-m", "kpifs"]
    sim = tmp / f"sim{rotation}"
    extra = ["--rotation", f"{rotation}deg"] if rotation else []
    subprocess.run(run + ["simulate", "--preset", "charis", "--layout", "charis", "--frames",
                          "20", "-o", str(sim), "-q", *extra], check=True)
    cal = tmp / f"calibrated{rotation}.fits"
    subprocess.run(run + ["extract", *sorted(map(str, (sim / "target").glob("*.fits"))),
                          "--calibrator", *sorted(map(str, (sim / "calibrator").glob("*.fits"))),
                          "-o", str(cal), "-q"], check=True)
    return cal


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp())
    fixed, turning = prepare(tmp, 0), prepare(tmp, 40)
    env = dict(os.environ, PYTHONPATH=str(ROOT))

    def cmd(path, *extra):
        return [sys.executable, "-m", "kpifs", "detect", str(path), "-o",
                str(tmp / "det.fits"), "--overwrite", "-q", *extra]
    commands = {"kpifs detect, fixed (reference)": (cmd(fixed), None),
                "kpifs detect, 40 deg of rotation, blocks": (cmd(turning), None),
                "kpifs detect, 40 deg, --blocks mean": (cmd(turning, "--blocks", "mean"), None)}
    print_medians(time_commands(commands, args.repeat, env), args.repeat)
    print("target: the rotating file's at most 1.5 x the fixed one's")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
