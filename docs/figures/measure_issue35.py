"""Issue 35 figures (items 1 and 5), on kpifs's simulator.

``python docs/figures/measure_issue35.py static CONTRAST FIRST:LAST [auto|none]``:
the V410 Tau-like stand-ins of ``tests/test_static_bright.py`` (6 single-channel
NIRC2-like frames in PyKernel's layout, 105 kernel phases, no calibrator), searched at
P_FA 1e-2; prints each seed's candidates and how many seeds have one.

``python docs/figures/measure_issue35.py joint CONTRAST FIRST:LAST``: 22 CHARIS-like
channels (64x64 pixels), 20 frames, one calibrator with 15 nm of static difference,
a flat-spectrum companion at (120, -90) mas (150 mas) searched at P_FA 1e-3; prints
the candidates and how many seeds have a second one. The stated limit at 150 mas
(test S) of seed 0 without a companion was 3.76e-4: 2x is 7.52e-4.
"""
import sys
import tempfile
import warnings
from pathlib import Path

import astropy.units as u

from kpifs import KernelModel, extract_kernel_phases, make_pupil
from kpifs.calibration.calibrate import calibrate
from kpifs.detect import detect
from kpifs.simulation.simulate import simulate_scene

warnings.simplefilter("ignore")


def static(contrast, seeds, mode="auto"):
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
    from test_static_bright import v410tau_like
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.7 * u.m, grey=False))
    d = Path(tempfile.mkdtemp())
    found = 0
    for s in seeds:
        res = detect(v410tau_like(d / f"s{s}.fits", km, s, contrast), pfa=1e-2, n_draws=1000,
                     seed=s, allow_uncalibrated=True, static=mode, limits=False)
        c = res.candidates
        found += len(c) > 0
        print(s, len(c), res.meta["static"],
              [(round(float(r["fit_x"].value)), round(float(r["fit_y"].value)),
                round(float(r["fit_contrast"][0]), 4), float(r["statistic"])) for r in c],
              flush=True)
    print("seeds with a candidate:", found, "of", len(seeds))


def joint(contrast, seeds):
    km = KernelModel.from_pupil(make_pupil("subaru"))
    kw = dict(n_frames=20, npup=64, shape=(64, 64), field=None, n_dead=0,
              wavefront_rms=30 * u.nm, drift_rms=20 * u.nm, drift_time=8.0,
              static_diff_rms=15 * u.nm, exptime=1 * u.s, contrasts=contrast,
              companion_offset=[120.0, -90.0] * u.mas)
    second = 0
    for s in seeds:
        obs = simulate_scene("charis", seed=s, **kw)
        args = dict(wavelengths=obs.wavelengths, pixscale=obs.params.pixscale)
        res = detect(calibrate(extract_kernel_phases(obs.target, km, **args),
                               extract_kernel_phases(obs.calibrator, km, **args)),
                     pfa=1e-3, seed=s, limits=False)
        second += len(res.candidates) > 1
        print(f"seed {s}: {len(res.candidates)} candidate(s)", flush=True)
        for r in res.candidates:
            print("   grid", float(r["x"].value), float(r["y"].value), "fit",
                  round(float(r["fit_x"].value), 1), round(float(r["fit_y"].value), 1),
                  "statistic %.1f" % r["statistic"], repr(str(r["flags"])), flush=True)
    print("seeds with a second candidate:", second, "of", len(seeds))


if __name__ == "__main__":
    what, c, span = sys.argv[1], float(sys.argv[2]), sys.argv[3]
    seeds = range(*[int(x) for x in span.split(":")])
    if what == "static":
        static(c, seeds, *sys.argv[4:5])
    else:
        joint(c, seeds)
