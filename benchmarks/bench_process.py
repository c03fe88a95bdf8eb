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

Prints the median wall time of each and the ratios. Peak memory of one
process: run it under ``/usr/bin/time -v`` ("Maximum resident set size").
"""
import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def write_cube(path, nframe=300, nwave=22, size=64, seed=0):
    import astropy.units as u
    from kpifs.io.layouts import write_plain_cube
    from kpifs.simulate import simulate_psf
    rng = np.random.default_rng(seed)
    wl = np.geomspace(1.15956, 2.36934, nwave) * u.um
    pix = 16.2 * u.mas
    jit = rng.uniform(-0.4, 0.4, (8, 2))
    psfs = np.stack([simulate_psf("subaru", wl, pixscale=pix, shape=(size, size), npup=64,
                                  centre=tuple(j)) for j in jit]).astype(np.float32)
    cube = np.empty((nframe, nwave, size, size), np.float32)
    for f in range(nframe):
        cube[f] = rng.poisson(2e5 * psfs[rng.integers(0, 8)]) + rng.normal(0, 10, cube.shape[1:])
    write_plain_cube(path, cube, wl, pix, overwrite=True)
    return path


def reference(cube_path, out_path):
    """Dense complex128 DFT per channel (the reference library's approach at its best)."""
    import astropy.units as u
    from astropy.io import fits
    from kpifs import KernelModel, make_pupil
    from kpifs.kernel import MAS
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


def time_commands(commands, repeat, env=None):
    times = {name: [] for name in commands}
    for _ in range(repeat):
        for name, (cmd, extra_env) in commands.items():
            e = dict(os.environ, **(extra_env or {}))
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, env=e, stdout=subprocess.DEVNULL)
            times[name].append(time.perf_counter() - t0)
    return {k: float(np.median(v)) for k, v in times.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cube", help="existing cube (default: write one in a temporary folder)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--baseline-path", help="another kpifs checkout to time as well")
    ap.add_argument("--no-reference", action="store_true",
                    help="skip the (slow) reference-library re-implementation")
    ap.add_argument("--reference", metavar="CUBE", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.reference:
        reference(args.reference, tempfile.mktemp(suffix=".npy"))
        return 0
    tmp = tempfile.mkdtemp()
    cube = args.cube or write_cube(str(Path(tmp) / "cube300.fits"))
    out = str(Path(tmp) / "kp.fits")
    kpifs = [sys.executable, "-m", "kpifs", "extract", cube, "-o", out, "--overwrite", "-q"]
    commands = {"kpifs extract": (kpifs, None)}
    if args.baseline_path:
        commands["kpifs extract (baseline checkout)"] = (kpifs, {"PYTHONPATH":
                                                                 args.baseline_path})
    if not args.no_reference:
        commands["reference: dense complex128 per channel"] = (
            [sys.executable, __file__, "--reference", cube], None)
    med = time_commands(commands, args.repeat)
    base = med["kpifs extract"]
    print(f"{'whole process (median of %d)' % args.repeat:48s} {'wall (s)':>9s} {'ratio':>7s}")
    for name, t in med.items():
        print(f"{name:48s} {t:9.2f} {t / base:7.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
