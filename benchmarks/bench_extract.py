"""Kernel-phase extraction speed: 22 channels x 100 frames, 64x64 window, ~300 sub-pupils.

Compares, in the same run:
(a) a bare matrix product of the same shape ((100, 4096) @ (4096, 2 nuv) per channel),
(b) rebuilding the DFT matrix for every slice (what a per-image library does),
and reports kpifs's frame-channels per second and peak memory (tracemalloc).
"""
import argparse
import time
import tracemalloc

import numpy as np
import astropy.units as u

from kpifs import KernelModel, extract_kernel_phases, make_pupil
from kpifs.kernel import MAS


def best_of(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--channels", type=int, default=22)
    ap.add_argument("--window", type=int, default=64)
    ap.add_argument("--naive-slices", type=int, default=40,
                    help="slices timed for the rebuild-per-slice baseline (extrapolated)")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)

    km = KernelModel.from_pupil(make_pupil("subaru", step=0.34 * u.m))
    wl = np.geomspace(1.16, 2.37, args.channels) * u.um
    pix = 7.0 * u.mas          # Nyquist at every channel: no uv point dropped
    nf, nw, ws = args.frames, args.channels, args.window
    rng = np.random.default_rng(0)
    r2 = np.hypot(*np.mgrid[:ws, :ws] - ws // 2) ** 2
    cube = rng.random((nf, nw, ws, ws)) + 10 * np.exp(-r2 / 20)[None, None]
    centres = (ws // 2, ws // 2)
    slices = nf * nw
    print(f"model: {km.pupil.n_sub} sub-apertures, {km.n_uv} uv points, {km.n_kp} kernels")
    print(f"data: {nf} frames x {nw} channels x {ws}x{ws} pixels")

    def run_kpifs():
        return extract_kernel_phases(cube, km, wavelengths=wl, pixscale=pix, centres=centres,
                                     keep_phases=False)

    t_first = best_of(lambda: (km._dft_cache.clear(), run_kpifs()), 1)
    run_kpifs()
    t_kpifs = best_of(run_kpifs, args.repeat)

    mats = [km.dft_matrix(w, pix, (ws, ws)) for w in wl]
    flat = cube.reshape(nf, nw, ws * ws)

    def run_bare():
        for i in range(nw):
            np.ascontiguousarray(flat[:, i]) @ mats[i].T

    t_bare = best_of(run_bare, args.repeat)

    uvx, uvy = km.uv.value.T
    y, x = np.mgrid[:ws, :ws] - ws // 2
    xr, yr = x.ravel() * pix.value * MAS, y.ravel() * pix.value * MAS

    def naive_slice(img, lam):
        m = np.exp(-2j * np.pi * (np.outer(uvx, xr) + np.outer(uvy, yr)) / lam)
        return km.kernel @ np.angle(m @ img.ravel())

    ns = min(args.naive_slices, slices)
    t0 = time.perf_counter()
    for s in range(ns):
        naive_slice(cube[s % nf, s % nw], wl[s % nw].to_value(u.m))
    t_naive = (time.perf_counter() - t0) / ns * slices

    tracemalloc.start()
    run_kpifs()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()

    rate = slices / t_kpifs
    print(f"{'method':44s} {'time (s)':>9s} {'frame-ch/s':>11s}")
    print(f"{'kpifs (DFT matrices cached)':44s} {t_kpifs:9.3f} {rate:11.0f}")
    print(f"{'kpifs, first call (matrices built)':44s} {t_first:9.3f} {slices / t_first:11.0f}")
    print(f"{'(a) bare matrix products, same shapes':44s} {t_bare:9.3f} {slices / t_bare:11.0f}")
    print(f"{'(b) DFT rebuilt per slice (extrapolated)':44s} {t_naive:9.3f} "
          f"{slices / t_naive:11.0f}")
    print(f"kpifs / bare product time: {t_kpifs / t_bare:.2f}x   (target <= 2x)")
    print(f"rebuild-per-slice / kpifs time: {t_naive / t_kpifs:.0f}x   (target >= 20x)")
    print(f"peak memory of one extraction call (tracemalloc): {peak / 2**20:.0f} MiB "
          f"(input cube {cube.nbytes / 2**20:.0f} MiB, cached DFT matrices "
          f"{sum(m.nbytes for m in km._dft_cache.values()) / 2**20:.0f} MiB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
