"""
Choosing a pupil model: alpha Oph with PHARO
============================================

The real Palomar/PHARO frames of alpha Oph (a binary whose companion has
:math:`\\Delta K = 3.5 \\pm 0.2` mag in the literature, a contrast of
0.033-0.048) calibrated by epsilon Her, reduced with three pupil models: the
binary model (cells at least 90 % inside the mask), kpifs's default grey
model, and a grey model that keeps every uv point. For each: the companion's
fitted contrast and separation, the reduced chi2 of the binary fit, and the
number of candidates (one expected).

The frames are third-party data kept outside the package
(``../shared/data/real`` next to the project, see its README, or the folder
named by ``KPIFS_REAL_DATA``). With them, this page shows the comparison and
the detection map of alpha Oph B with the default model; without them (a
fresh clone), it says what it would show and draws nothing.
"""
import os
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import astropy.units as u

from kpifs import ExtractionWindow, KernelModel, extract_kernel_phases, make_pupil
from kpifs.calibration.calibrate import calibrate
from kpifs.detect import detect
from kpifs.io import read_cube
from kpifs.plotting import plot_detection_map


def find_real_data():
    """``KPIFS_REAL_DATA``, or ``shared/data/real`` beside the project (looked for from
    this file and from the working directory upwards)."""
    starts = [Path.cwd().resolve()]
    if "__file__" in globals():
        starts.append(Path(__file__).resolve().parent)
    bases = [Path(os.environ.get("KPIFS_REAL_DATA", "/nonexistent"))]
    for start in starts:
        bases += [p.parent / "shared" / "data" / "real" for p in (start, *start.parents)]
    for base in bases:
        if (base / "pharo_tgt_cube_alphaOph.fits").is_file():
            return base
    return None


real = find_real_data()
if real is None:
    print("The PHARO frames of alpha Oph and eps Her (pharo_tgt_cube_alphaOph.fits,\n"
          "pharo_ca2_cube_epsHer.fits) are not beside this project (../shared/data/real)\n"
          "nor in KPIFS_REAL_DATA, so nothing is computed here. With them this page\n"
          "prints, for three pupil models, alpha Oph B's fitted contrast, separation and\n"
          "reduced chi2 and the number of candidates, draws the contrasts against the\n"
          "literature's range, and draws the detection map of the default model\n"
          "(the measured values are in the user guide: 'Choosing a pupil model').")
else:
    wl, pix = [2.145] * u.um, 25 * u.mas
    frames = {}
    for star, name in (("alpha Oph", "pharo_tgt_cube_alphaOph.fits"),
                       ("eps Her", "pharo_ca2_cube_epsHer.fits")):
        with read_cube(real / name, wavelengths=wl, pixscale=pix) as cube:
            frames[star] = np.array(cube.data, float)
    window = ExtractionWindow.default(frames["eps Her"].shape)
    models = {"binary (cut 0.9)": dict(grey=False),
              "grey (default)": dict(),
              "grey, every uv point": dict(min_transmission=0.1, min_redundancy=0)}
    rows, results = [], {}
    for label, options in models.items():
        km = KernelModel.from_pupil(make_pupil("pharo", **options))
        kp = {star: extract_kernel_phases(f, km, wavelengths=wl, pixscale=pix,
                                          window=window, keep_phases=False)
              for star, f in frames.items()}
        found = detect(calibrate(kp["alpha Oph"], kp["eps Her"]), pfa=1e-3, seed=0)
        results[label] = found
        best = found.candidates[0]
        rows.append((label, km.n_kp, float(best["fit_contrast"][0]),
                     float(best["fit_contrast_err"][0]),
                     float(np.hypot(best["fit_x"].value, best["fit_y"].value)),
                     float(best["chi2_red"]), len(found.candidates)))
    print(f"{'model':24s} {'kernels':>7s} {'contrast':>16s} {'sep (mas)':>9s} "
          f"{'chi2_red':>8s} {'candidates':>10s}")
    for label, nkp, c, err, sep, chi2, n in rows:
        print(f"{label:24s} {nkp:7d} {c:8.4f} +- {err:.4f} {sep:9.1f} {chi2:8.1f} {n:10d}")

    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    y = np.arange(len(rows))
    ax.axvspan(0.033, 0.048, color="0.85", label=r"literature $\Delta K = 3.5 \pm 0.2$")
    ax.errorbar([r[2] for r in rows], y, xerr=[r[3] for r in rows], fmt="o", color="k")
    for yi, r in zip(y, rows):
        ax.annotate(f"  chi2_red {r[5]:.0f}", (r[2] + r[3], yi), va="center", fontsize=8)
    ax.set_yticks(y, [r[0] for r in rows])
    ax.set_xlabel("fitted contrast of alpha Oph B (K band)")
    ax.set_xlim(0.025, 0.06)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()

    # the detection itself, default model: the map the search stopped on (alpha Oph B
    # found, fitted and subtracted), on the detector (no angles come with these frames)
    plot_detection_map(results["grey (default)"])
    plt.show()
