"""
Detection map, contrast curves and companion spectrum
=====================================================

A simulated target with a companion and a calibrator star are extracted,
calibrated and searched; the figures show the detection map with the
candidate, the limits of every test and the recovered spectrum.
"""
import astropy.units as u
import matplotlib.pyplot as plt
import numpy as np

from kpifs import KernelModel, extract_kernel_phases, make_pupil
from kpifs.calibration.calibrate import calibrate
from kpifs.detect import detect
from kpifs.plotting import plot_candidate_spectrum, plot_contrast_curves, plot_detection_map
from kpifs.simulation.simulate import simulate_scene

contrasts = np.array([1.3, 1.0, 0.7]) * 6.3e-4
obs = simulate_scene("paper", n_frames=300, seed=2, npup=64, exptime=1 * u.s,
                     contrasts=contrasts)
km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
kp = {role: extract_kernel_phases(getattr(obs, role), km, wavelengths=obs.wavelengths,
                                  pixscale=obs.params.pixscale)
      for role in ("target", "calibrator")}
result = detect(calibrate(kp["target"], kp["calibrator"]), pfa=1e-3, n_draws=10000)

fig, axes = plt.subplots(1, 3, figsize=(15, 4.3))
plot_detection_map(result, ax=axes[0], truth=(80, 60))
plot_contrast_curves(result, ax=axes[1])
plot_candidate_spectrum(result, ax=axes[2], truth=contrasts)
fig.tight_layout()
print(result.candidates["x", "y", "pfa_global"])
