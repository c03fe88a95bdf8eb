"""Figure of docs/user/spectral_differential.rst: a static residual against a companion
across the channels, and what the projection keeps of a companion by separation.

For the CHARIS model (Subaru pupil, 0.38 m grid, 264 kernel phases, 22 channels at
1.16-2.37 um, 16.2 mas pixels):

- left: one kernel phase (the one a 150 mas companion moves most) across the
  channels, for the static residual of one random 50 nm wavefront imaged through
  the pupil (`kpifs.simulation.aberrations.static_residual_rows`, its leading
  screen) and for companions at 150 and 300 mas (scaled to the same range);
- right: the median over position angles of the fraction of a companion's squared
  signal kept (`kpifs.calibration.spectral_diff.retained_fraction`) with each basis
  (3 static channel profiles, polynomials of degree 2 in 1/lambda, both), for CHARIS
  (22 channels) and SPHERE-IFS YJ (39 channels, 0.957-1.329 um).

Run: ``python docs/figures/make_sdk.py`` (about two minutes of CPU: the static
residual is imaged through the pupil).
"""
from pathlib import Path

import matplotlib
import numpy as np
from astropy import units as u

matplotlib.use("agg")
import matplotlib.pyplot as plt  # noqa: E402

from kpifs import KernelPhaseData  # noqa: E402
from kpifs.calibration.spectral_diff import (kept_combinations, nuisance_profiles,  # noqa: E402
                                             retained_fraction)
from kpifs.model.window import ExtractionWindow  # noqa: E402
from kpifs.simulation.aberrations import static_residual_rows  # noqa: E402
from kpifs.simulation.simulate import PRESETS  # noqa: E402
from kpifs.workflow import ExtractOptions, kernel_model_for  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "user" / "spectral_differential.png"
SEPS = np.arange(40.0, 301.0, 20.0)


def _kpd(preset, instrument):
    km = kernel_model_for(ExtractOptions(), instrument)
    wl = PRESETS[preset]["wavelengths"]
    kpd = KernelPhaseData(np.zeros((1, len(wl), km.n_kp)), wl, PRESETS[preset]["pixscale"],
                          km, window=ExtractionWindow.default((80, 80)))
    rows = static_residual_rows(km, wl, kpd.pixscale, window=kpd.window, n_screens=60)
    return kpd, rows


def _curves(kpd, rows):
    out = {}
    ang = np.arange(16) * np.pi / 16
    for basis in ("static", "poly", "both"):
        v = kept_combinations(nuisance_profiles(kpd, basis=basis, static_rows=rows),
                              np.ones(kpd.n_wave))
        out[basis] = [np.median(retained_fraction(
            kpd.kernel_model, kpd.wavelengths,
            np.stack([s * np.cos(ang), s * np.sin(ang)], 1), v)) for s in SEPS]
    return out


def main():
    charis, rows = _kpd("charis", "charis")
    km, wl = charis.kernel_model, charis.wavelengths
    lam = wl.to_value(u.m)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    sig = {}
    for sep in (150.0, 300.0):
        theta = 2 * np.pi * (np.array([sep, 0.0]) * np.pi / 180 / 3600e3) @ km.uv.value.T
        sig[sep] = np.sin(theta[None] / lam[:, None]) @ km.kernel.T          # (q, p)
    j = int(np.argmax(np.ptp(sig[150.0], axis=0)))
    stat = rows[0, :, j]
    for y, lab in ((stat, "static residual"), (sig[150.0][:, j], "companion, 150 mas"),
                   (sig[300.0][:, j], "companion, 300 mas")):
        ax1.plot(wl.to_value(u.um), y / np.max(np.abs(y)), "o-", ms=3, label=lab)
    ax1.set_xlabel("wavelength (um)")
    ax1.set_ylabel(f"kernel phase {j} (scaled)")
    ax1.legend(fontsize=8)
    sphere, srows = _kpd("sphere", "sphere")
    for (name, kpd, r), ls in (((("CHARIS", charis, rows)), "-"),
                               ((("SPHERE YJ", sphere, srows)), "--")):
        for basis, frac in _curves(kpd, r).items():
            ax2.plot(SEPS, frac, ls, label=f"{name}, {basis}")
    ax2.axhline(0.5, color="0.6", lw=0.8)
    ax2.set_xlabel("separation (mas)")
    ax2.set_ylabel("companion's squared signal kept")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(OUT, dpi=110)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
