"""Cost of the error model of issue 14 against the detection it serves.

For two shapes (PHARO-like: 1 channel x 835 kernel phases, 50 + 50 frames;
CHARIS-like: 22 channels x 357 kernel phases, 20 + 20 frames) of drifting
simulated kernel phases, times in the same run:

- ``calibrate(..., error_model='modes')`` (the model: modes, cross-validation,
  batch means, residual) and ``error_model='frames'`` (sample covariance / N);
- ``detect`` on the result with default options.

Prints the extra cost of the model (modes - frames) as a fraction of detect's
time, and that of the empirical (sign-flip) null: ``detect(null='both')``
against ``detect(null='gaussian')``, the Monte-Carlo caches emptied before each
run. The issue asks for < 25 % in all. Run: ``python benchmarks/bench_errormodel.py``.
"""
import time
import warnings

import numpy as np
import astropy.units as u

from kpifs import ExtractionWindow, KernelModel, KernelPhaseData, make_pupil
from kpifs.calibration.calibrate import calibrate
from kpifs.detect import detect
from kpifs.detect import null as null_module


def frames(rng, n, q, p, rho=0.6, m=8):
    mix = rng.standard_normal((m, q * p))
    a = np.empty((n, m))
    a[0] = rng.standard_normal(m)
    for i in range(1, n):
        a[i] = rho * a[i - 1] + np.sqrt(1 - rho ** 2) * rng.standard_normal(m)
    return ((a @ mix + rng.standard_normal((n, q * p))) * 1e-3).reshape(n, q, p)


def best(fn, repeat=3):
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return min(out)


def main():
    warnings.simplefilter("ignore")
    rng = np.random.default_rng(0)
    cases = {
        "PHARO-like 1 x 835, 50+50 frames": (make_pupil("pharo", step=0.16 * u.m),
                                             [2.145] * u.um, 25 * u.mas, 50, (64, 25.6)),
        "CHARIS-like 22 x 357, 20+20 frames": (make_pupil("subaru"),
                                               np.geomspace(1.16, 2.37, 22) * u.um,
                                               16.2 * u.mas, 20, (64, 25.6)),
    }
    for name, (pupil, wl, pix, n, win) in cases.items():
        km = KernelModel.from_pupil(pupil).for_wavelengths(wl, pix)
        q, p = len(wl), km.n_kp

        def kpd(x):
            return KernelPhaseData(x, wl, pix, km, window=ExtractionWindow(*win))
        t, c = kpd(frames(rng, n, q, p)), kpd(frames(rng, n, q, p))
        t_modes = best(lambda: calibrate(t, c, error_model="modes"))
        t_frames = best(lambda: calibrate(t, c, error_model="frames"))
        cal = calibrate(t, c)

        def run(method):
            null_module._CACHE.clear()
            return detect(cal, null=method)
        t_detect = best(lambda: run("both"), repeat=2)
        t_gauss = best(lambda: run("gaussian"), repeat=2)
        print(f"{name}: calibrate modes {t_modes:.3f} s, frames {t_frames:.3f} s, "
              f"detect {t_detect:.2f} s; extra cost of the model = "
              f"{(t_modes - t_frames) / t_detect:.1%} of detect; of the empirical null "
              f"(detect {t_gauss:.2f} s without) = {(t_detect - t_gauss) / t_detect:.1%}")


if __name__ == "__main__":
    main()
