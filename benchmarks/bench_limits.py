"""Detection limits with channel correlations (issue 13, item 5).

The binary-test limit solves ``P_D(c) = 0.5`` at every grid position from 1024
correlated draws. Baseline, same run, same draws: a plain bisection on the
Monte-Carlo ``P_D`` (each step evaluates the statistic of every draw). kpifs:
each draw solved for its crossing contrast (Newton on the convex statistic),
the limit their median (`kpifs.detect.limits._limit_binary_draws`), on
all threads and on one (``KPIFS_THREADS=1``). Reports wall times, the ratio and
the largest relative difference of the limits (the bisection stops at 1e-3).
"""
import os
import time

import numpy as np

from kpifs.detect import limits as L


def bisection_limits(m, corr, thr, pd, n_draws, seed, rtol=1e-3):
    """The baseline: the same draws, P_D by counting, a plain bisection on c."""
    npos, q = m.shape
    eps = L._lhs_normal(n_draws, q, seed).T.astype(np.float32)
    out = np.empty(npos)
    for a in range(0, npos, 64):
        sl = slice(a, a + 64)
        z = np.matmul(np.linalg.cholesky(corr[sl] + 1e-9 * np.eye(q)).astype(np.float32), eps)
        mm = m[sl].astype(np.float32)
        lo = np.zeros(len(mm))
        hi = (np.sqrt(thr) * np.sqrt(q) + 6 * q) / m[sl].sum(axis=1)
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            t = z + (mid.astype(np.float32)[:, None] * mm)[:, :, None]
            np.maximum(t, 0, out=t)
            up = np.mean(np.sum(t * t, axis=1) > thr, axis=1) >= pd
            hi, lo = np.where(up, mid, hi), np.where(up, lo, mid)
            if np.all(hi - lo <= rtol * hi):
                break
        out[sl] = 0.5 * (lo + hi)
    return out


def main():
    rng = np.random.default_rng(0)
    npos, q = 1200, 22
    m = rng.uniform(50, 400, (npos, q))                     # signal per unit contrast
    a = rng.standard_normal((npos, q, q)) * 0.15
    corr = np.eye(q)[None] + a @ np.swapaxes(a, 1, 2)
    thr = 60.0
    t0 = time.perf_counter()
    base = bisection_limits(m, corr, thr, 0.5, 1024, 0)
    t_base = time.perf_counter() - t0
    times = {}
    for label, n in (("kpifs, all threads", None), ("kpifs, one thread", "1")):
        if n is None:
            os.environ.pop("KPIFS_THREADS", None)
        else:
            os.environ["KPIFS_THREADS"] = n
        t0 = time.perf_counter()
        lim = L._limit_binary_draws(m, corr, [thr], 0.5, [2], 1024, 0)[0]
        times[label] = time.perf_counter() - t0
    os.environ.pop("KPIFS_THREADS", None)
    print(f"{npos} positions, {q} channels, 1024 draws")
    print(f"plain bisection on P_D (baseline): {t_base:6.2f} s")
    for label, dt in times.items():
        print(f"{label:33s}: {dt:6.2f} s  ({t_base / dt:.1f}x faster)")
    print(f"largest relative difference: {np.nanmax(np.abs(lim / base - 1)):.1e} "
          f"(the bisection's tolerance is 1e-3)")


if __name__ == "__main__":
    main()
