"""Whole-process time of ``kpifs extract`` on a 300 x 22 x 64^2 cube (issue 13).

Writes the cube once (PSFs of kpifs's simulator at 8 sub-pixel positions per
channel, photon and read noise; float32, plain layout with KPWLn/PIXSCALE
cards), then times, alternately and --repeat times each, whole processes:

- ``python -m kpifs extract CUBE -o OUT`` (this checkout);
- the reference: this script with ``--reference CUBE``, one complex128 DFT
  matrix per channel applied to all the channel's frames in one product, with
  the same kernel model: the reference kernel-phase library's approach at its
  best (its own package is not installable here);
- optionally ``--baseline-path DIR``: ``kpifs extract`` of another checkout
  (e.g. the commit before issue 13), run with PYTHONPATH=DIR.

Prints the median wall time and peak resident memory of each, the reference's
time over kpifs's (target >= 10), and the command line's start: the import
time (``python -X importtime``, median) of ``kpifs --help`` and of the modules
``kpifs extract`` loads before it reads anything (target < 0.25 s).

``--memory FRAMES SIZE`` instead writes a FRAMES x 22 x SIZE^2 cube frame by
frame (e.g. ``--memory 2000 128``: 2.9 GB) and reports the peak resident
memory of ``kpifs extract`` on it (target: below ~1 GB plus the output).

Modules are byte-compiled first (``compileall``), as in an installed package,
so that neither side pays for compiling kpifs at every start when
PYTHONDONTWRITEBYTECODE is set (``--no-compile`` to skip). ``--threads N``
sets OPENBLAS_NUM_THREADS/OMP_NUM_THREADS for every process (on a machine
shared with other work, N=1 gives steadier figures).
"""
import argparse
import compileall
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def _psfs(nwave, size, seed):
    import astropy.units as u
    from kpifs.simulation.simulate import simulate_psf
    rng = np.random.default_rng(seed)
    wl = np.geomspace(1.15956, 2.36934, nwave) * u.um
    pix = 16.2 * u.mas
    jit = rng.uniform(-0.4, 0.4, (8, 2))
    psfs = np.stack([simulate_psf("subaru", wl, pixscale=pix, shape=(size, size), npup=64,
                                  centre=tuple(j)) for j in jit]).astype(np.float32)
    return rng, wl, pix, psfs


def write_cube(path, nframe=300, nwave=22, size=64, seed=0):
    from kpifs.io.layouts import write_plain_cube
    rng, wl, pix, psfs = _psfs(nwave, size, seed)
    cube = np.empty((nframe, nwave, size, size), np.float32)
    for f in range(nframe):
        cube[f] = rng.poisson(2e5 * psfs[rng.integers(0, 8)]) + rng.normal(0, 10, cube.shape[1:])
    write_plain_cube(path, cube, wl, pix, overwrite=True)
    return path


def write_large_cube(path, nframe, nwave=22, size=128, seed=0):
    """The same kind of cube, streamed to disk frame by frame (16 noisy frames repeated)."""
    from astropy.io import fits
    from kpifs.io.layouts import write_plain_cube
    rng, wl, pix, psfs = _psfs(nwave, size, seed)
    frames = np.stack([rng.poisson(2e5 * psfs[i % 8]) + rng.normal(0, 10, psfs.shape[1:])
                       for i in range(16)]).astype(">f4")
    write_plain_cube(path, frames[:1], wl, pix, overwrite=True)   # header of one frame
    hdr = fits.getheader(path)
    hdr["NAXIS4"] = nframe
    os.remove(path)
    shdu = fits.StreamingHDU(path, hdr)
    for f in range(nframe):
        shdu.write(frames[f % 16])
    shdu.close()
    return path


def reference(cube_path, out_path):
    """Dense complex128 DFT per channel (the reference library's approach at its best)."""
    import astropy.units as u
    from astropy.io import fits
    from kpifs import KernelModel, make_pupil
    from kpifs.model.kernel import MAS
    with fits.open(cube_path, memmap=True) as hdul:
        hdr = hdul[0].header
        wl = np.array([hdr[f"KPWL{i + 1}"] for i in range(hdul[0].data.shape[1])]) * 1e-6
        pix = hdr["PIXSCALE"] * MAS
        km = KernelModel.from_pupil(make_pupil("subaru")).for_wavelengths(wl * u.m,
                                                                          hdr["PIXSCALE"] * u.mas)
        data = hdul[0].data
        nf, nw, ny, nx = data.shape
        uv = km.uv.to_value(u.m)
        y, x = np.mgrid[:ny, :nx]
        kp = np.empty((nf, nw, km.n_kp))
        r2 = (x - nx // 2) ** 2 + (y - ny // 2) ** 2
        win = np.exp(-(r2 / (0.8 * nx / 2) ** 2) ** 2)                   # window
        for i in range(nw):
            m = np.exp(-2j * np.pi * (np.outer(uv[:, 0], (x.ravel() - nx // 2) * pix)
                                      + np.outer(uv[:, 1], (y.ravel() - ny // 2) * pix)) / wl[i])
            imgs = np.array(data[:, i], float)
            for f in range(nf):                                           # recentre
                py, px = np.unravel_index(np.argmax(imgs[f]), imgs[f].shape)
                imgs[f] = np.roll(imgs[f], (ny // 2 - py, nx // 2 - px), axis=(0, 1)) * win
            # all frames of the channel in one complex128 product: its best use
            kp[:, i] = np.angle(imgs.reshape(nf, -1) @ m.T) @ km.kernel.T
    np.save(out_path, kp)


def run_once(cmd, env):
    """Wall time (s) and peak resident memory (MiB) of one process."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, cwd=tempfile.gettempdir())
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd)} exited with {proc.returncode}")
    return wall, usage.ru_maxrss / 1024


def time_commands(commands, repeat, base_env):
    """Median wall time and peak memory of each command, run in turn (A B A B ...)."""
    runs = {name: [] for name in commands}
    for _ in range(repeat):
        for name, (cmd, extra_env) in commands.items():
            runs[name].append(run_once(cmd, dict(base_env, **(extra_env or {}))))
    return {k: tuple(np.median(np.array(v), axis=0)) for k, v in runs.items()}


def print_medians(med, repeat):
    """The table of `time_commands`, each wall time also over the first command's."""
    base = next(iter(med.values()))[0]
    print(f"{'whole process (median of %d)' % repeat:48s} {'wall (s)':>9s} "
          f"{'/ kpifs':>8s} {'peak MiB':>9s}")
    for name, (t, peak) in med.items():
        print(f"{name:48s} {t:9.2f} {t / base:8.2f} {peak:9.0f}")


def import_time(args, base_env, repeat):
    """Median total import time (s) that ``python -X importtime ARGS`` reports."""
    totals = []
    for _ in range(repeat):
        err = subprocess.run([sys.executable, "-X", "importtime", *args], env=base_env,
                             capture_output=True, text=True, cwd=tempfile.gettempdir()).stderr
        self_us = [int(m.group(1)) for m in re.finditer(r"import time:\s+(\d+) \|", err)]
        totals.append(sum(self_us) / 1e6)
    return float(np.median(totals))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cube", help="existing cube (default: write one in a temporary folder)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--baseline-path", help="another kpifs checkout to time as well")
    ap.add_argument("--no-reference", action="store_true",
                    help="skip the (slow) reference-library re-implementation")
    ap.add_argument("--no-compile", action="store_true",
                    help="do not byte-compile the kpifs modules first")
    ap.add_argument("--threads", type=int, help="BLAS threads of every process")
    ap.add_argument("--memory", nargs=2, type=int, metavar=("FRAMES", "SIZE"),
                    help="peak memory of kpifs extract on a FRAMES x 22 x SIZE^2 cube")
    ap.add_argument("--reference", metavar="CUBE", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.reference:
        reference(args.reference, tempfile.mktemp(suffix=".npy"))
        return 0
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    if args.threads:
        env.update(OPENBLAS_NUM_THREADS=str(args.threads), OMP_NUM_THREADS=str(args.threads))
    if not args.no_compile:
        for root in [ROOT] + ([Path(args.baseline_path)] if args.baseline_path else []):
            compileall.compile_dir(str(root / "kpifs"), quiet=1)
    tmp = tempfile.mkdtemp()
    out = str(Path(tmp) / "kp.fits")
    kpifs = [sys.executable, "-m", "kpifs", "extract", "CUBE", "-o", out, "--overwrite", "-q"]
    if args.memory:
        nframe, size = args.memory
        cube = args.cube or write_large_cube(str(Path(tmp) / "large.fits"), nframe, size=size)
        wall, peak = run_once([cube if a == "CUBE" else a for a in kpifs], env)
        print(f"kpifs extract, {nframe} x 22 x {size}^2 cube "
              f"({os.path.getsize(cube) / 2 ** 30:.2f} GiB): {wall:.1f} s, "
              f"peak resident memory {peak:.0f} MiB, output {os.path.getsize(out) / 2 ** 20:.0f} "
              f"MiB")
        return 0
    cube = args.cube or write_cube(str(Path(tmp) / "cube300.fits"))
    kpifs = [cube if a == "CUBE" else a for a in kpifs]
    commands = {"kpifs extract": (kpifs, None)}
    if args.baseline_path:
        commands["kpifs extract (baseline checkout)"] = (kpifs, {"PYTHONPATH":
                                                                 args.baseline_path})
    if not args.no_reference:
        commands["reference: dense complex128 per channel"] = (
            [sys.executable, str(Path(__file__).resolve()), "--reference", cube], None)
    med = time_commands(commands, args.repeat, env)
    print_medians(med, args.repeat)
    base = med["kpifs extract"][0]
    ref = med.get("reference: dense complex128 per channel")
    if ref:
        print(f"speed-up over the reference: {ref[0] / base:.1f}x   (target >= 10x)")
    help_t = import_time(["-m", "kpifs", "--help"], env, args.repeat)
    start_t = import_time(["-c", "import kpifs._cli.extract"], env, args.repeat)
    print(f"CLI start, python -X importtime (median): kpifs --help {help_t:.3f} s, "
          f"kpifs extract's modules {start_t:.3f} s   (target < 0.25 s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
