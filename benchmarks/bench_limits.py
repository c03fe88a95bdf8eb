"""Detection-limit root finding (issue 13, item 5).

The binary-test limit with channel correlations solves ``P_D(c) = 0.5`` at every
grid position from 1024 correlated quasi-random draws. Baseline, same run: a
plain bisection on the same draws (the method used before); candidate: the
safeguarded regula falsi of ``kpifs.detect.limits._bisect``. Reports the
P_D evaluations (in position-evaluations), the wall time and the largest
relative difference of the limits.
"""
import time

import numpy as np

from kpifs.detect import limits as L


def plain_bisection(pdet, pd, hi, n_iter=40, rtol=1e-3):
    ok = np.isfinite(hi) & (hi > 0)
    idx = np.flatnonzero(ok)
    lo = np.zeros(len(hi))
    hi = np.where(ok, hi, np.nan)
    for _ in range(n_iter):
        mid = 0.5 * (lo[idx] + hi[idx])
        above = pdet(mid, idx) >= pd
        hi[idx] = np.where(above, mid, hi[idx])
        lo[idx] = np.where(above, lo[idx], mid)
        if np.all(hi[idx] - lo[idx] <= rtol * hi[idx]):
            break
    out = np.full(len(hi), np.nan)
    out[idx] = 0.5 * (lo[idx] + hi[idx])
    return out


def main():
    rng = np.random.default_rng(0)
    npos, q = 1200, 22
    m = rng.uniform(50, 400, (npos, q))                     # signal per unit contrast
    a = rng.standard_normal((npos, q, q)) * 0.15
    corr = np.eye(q)[None] + a @ np.swapaxes(a, 1, 2)
    thr = 60.0
    out = {}
    for name, finder in (("plain bisection", plain_bisection), ("kpifs _bisect", L._bisect)):
        calls = [0]
        orig = L._bisect

        def counting(pdet, pd, hi, **kw):
            def wrapped(c, idx):
                calls[0] += len(idx)
                return pdet(c, idx)
            return finder(wrapped, pd, hi, **kw)
        L._bisect = counting
        t0 = time.perf_counter()
        lim = L._limit_binary_correlated(m, corr, [thr], 0.5, [2], 1024, 0)[0]
        dt = time.perf_counter() - t0
        L._bisect = orig
        out[name] = (lim, calls[0], dt)
        print(f"{name:16s}: {calls[0] / npos:5.1f} evaluations per position, {dt:6.2f} s")
    base, new = out["plain bisection"], out["kpifs _bisect"]
    print(f"ratio: {base[2] / new[2]:.2f}x faster, {base[1] / new[1]:.2f}x fewer evaluations; "
          f"largest relative difference {np.nanmax(np.abs(new[0] / base[0] - 1)):.1e}")


if __name__ == "__main__":
    main()
