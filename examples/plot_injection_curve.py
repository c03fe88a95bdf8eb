"""
Limits checked by injections
============================

A detection limit is a claim: a companion this bright would be found half the
time. Here it is checked on an unkind simulation (aberrations drifting from
frame to frame, the calibrator seen through a static aberration of its own):
companions are injected into the target's frames as shifted, scaled copies of
the frames themselves, extracted, calibrated and searched exactly as real
data, at several position angles per separation and contrast. The contrast
steps start from the analytic limit at each separation (0.5, 1 and 2 times it)
and extend by factors of 2 until they bracket the 50 % level. The points give
the fraction found at each step; the black bar, where the steps put the 50 %
limit: from the highest step found significantly less than half the time to
the lowest found significantly more (with 4 angles, 0 and 4 of 4 are; 1, 2
or 3 of 4 are not, and a value is interpolated only between adjacent steps
that are); the dashed line, the analytic limit of the same data without
injections.
"""
import warnings

import matplotlib.pyplot as plt
import numpy as np
import astropy.units as u

from kpifs import KernelModel, extract_kernel_phases, make_pupil
from kpifs.calibration.calibrate import calibrate
from kpifs.detect import detect
from kpifs.inject import injection_brackets, injection_limits
from kpifs.plotting import analytic_column, plot_injection_limits
from kpifs.simulation.simulate import simulate_scene

obs = simulate_scene("paper", n_frames=30, seed=5, npup=64, contrasts=0.0,
                     wavefront_rms=30 * u.nm, drift_rms=30 * u.nm, drift_time=8.0,
                     static_diff_rms=10 * u.nm, exptime=1 * u.s)
km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
args = dict(wavelengths=obs.wavelengths, pixscale=obs.params.pixscale)
with warnings.catch_warnings():
    warnings.simplefilter("ignore")          # few frames: kpifs says the null is optimistic
    cal = extract_kernel_phases(obs.calibrator, km, **args)
    tgt = extract_kernel_phases(obs.target, km, **args)
    analytic = detect(calibrate(tgt, [cal]), pfa=1e-3, n_draws=5000, seed=0)
    seps = [60, 120] * u.mas
    start = np.interp(seps.value, analytic.curves["separation"].to_value(u.mas),
                      analytic.curves[analytic_column(analytic)])
    table = injection_limits(obs.target, [cal], km, window=cal.window, **args,
                             separations=seps, start=start, n_angles=4, seed=1)

print(table)
print("analytic limits:", [f"{v:.2e}" for v in start])
# where the steps put the 50 % limit (NaN: no conclusive step on that side; the
# interpolated value only where the two ends are adjacent steps)
print(injection_brackets(table))
fig = plot_injection_limits(table, analytic=analytic)
plt.show()
