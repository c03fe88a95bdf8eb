"""Time the README's commands, each as a whole process, the way a user runs them.

Runs, in a temporary folder, ``kpifs demo`` and the commands of the README's
"Command line" section in their order (each one's inputs are the previous
ones' outputs), and prints for each its CPU seconds (user + system, the process
and its children) and wall seconds, with the machine's load average before and
after and its processor, so that the README can quote them as what they are:
measurements on one machine at one load. Also counts the tests (``pytest
--collect-only``) and those marked slow.

Run from the project root::

    python docs/figures/measure_readme_timings.py            # everything
    python docs/figures/measure_readme_timings.py --skip-demo

Measured figures go into the README as ranges with their machine.
"""
import argparse
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

COMMANDS = [
    "kpifs --version",
    "kpifs kernel --pupil subaru --step 0.38m -o subaru_model.fits",
    "kpifs simulate --preset paper --frames 400 -o sim",
    "kpifs info sim/target.fits",
    "kpifs model-check sim/calibrator.fits --pupil subaru",
    "kpifs extract sim/target.fits --wavelengths 1.52um,1.60um,1.68um --pixscale 10.42mas "
    "--pupil subaru -o target_kp.fits",
    "kpifs extract sim/calibrator.fits -o calibrator_kp.fits",
    "kpifs detect target_kp.fits --calibrator calibrator_kp.fits --pfa 1e-3 -o detection.fits "
    "--plots figures",
    "kpifs inject sim/target.fits --calibrator sim/calibrator.fits --curve --separations "
    "60,120mas -o curve.fits --plots figures",
    "kpifs info curve.fits",
    "kpifs roc --preset paper --frames 1000 -o roc",
]


def timed(command, cwd):
    """CPU (user + system, children) and wall seconds of one shell-free command."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    argv = command.split()
    argv[0] = str(Path(sys.executable).with_name("kpifs"))
    done = subprocess.run(argv, cwd=cwd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if done.returncode:
        raise SystemExit(f"{command}: exit {done.returncode}\n{done.stderr}")
    return cpu, wall, done.stdout


def count_tests():
    """(all tests and doctests, those marked slow), as pytest collects them."""
    out = {}
    for key, extra in (("all", []), ("slow", ["-m", "slow"])):
        done = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q",
                               "-p", "no:cacheprovider", *extra], cwd=ROOT,
                              capture_output=True, text=True)
        last = [line for line in done.stdout.splitlines() if "collected" in line
                or "tests collected" in line or line.endswith("selected")]
        out[key] = last[-1] if last else done.stdout.splitlines()[-1]
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--skip-demo", action="store_true")
    p.add_argument("--skip-tests", action="store_true")
    args = p.parse_args(argv)
    cpu_name = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu_name = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    print(f"machine: {cpu_name}, {os.cpu_count()} cores; load before "
          f"{os.getloadavg()[0]:.1f}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="kpifs-readme-") as tmp:
        if not args.skip_demo:
            cpu, wall, out = timed("kpifs demo -o demo_output", tmp)
            size = sum(f.stat().st_size for f in (Path(tmp) / "demo_output").rglob("*")
                       if f.is_file()) / 2 ** 20
            rows.append(("kpifs demo -o demo_output", cpu, wall, f"{size:.0f} MB written"))
            print(out)
            shutil.rmtree(Path(tmp) / "demo_output")
        for command in COMMANDS:
            cpu, wall, out = timed(command, tmp)
            rows.append((command.split(" -o ")[0][:60], cpu, wall, ""))
            print(f"{cpu:7.1f} s CPU {wall:7.1f} s wall  {command}", flush=True)
            if command.startswith(("kpifs detect", "kpifs inject")):
                print(out, flush=True)
    print(f"load after {os.getloadavg()[0]:.1f}")
    print(f"{'command':62s} {'CPU s':>7s} {'wall s':>7s}")
    for name, cpu, wall, note in rows:
        print(f"{name:62s} {cpu:7.1f} {wall:7.1f} {note}")
    if not args.skip_tests:
        for key, text in count_tests().items():
            print(f"tests ({key}): {text}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
