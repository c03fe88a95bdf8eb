"""
From CHARIS pipeline cubes to a detection map
=============================================

One star observed with SCExAO/CHARIS, from the cubes the CHARIS data-reduction
pipeline writes to a detection map, a contrast curve, the companion's spectrum
and an injection check, with the commands you would type.

The files are made by kpifs's simulator in the CHARIS pipeline's own layout:
one ``*_cube.fits`` per exposure, HDU 0 the pipeline's header (``LAM_MIN``,
``DLOGLAM``, ``NLAM``, ``CAL_BAND``, ``PARANG``...), HDU 1 the cube
``(22, ny, nx)`` and HDU 2 its inverse variance. Your own cubes go through the
same commands. To keep this page quick the frames are few (30 per star), the
images are cut to 48 x 48 lenslets and the pupil model is coarse (a 0.8 m grid:
74 kernel phases per channel); on your data keep the defaults and take several
times more frames than kernel phases.

Every ``kpifs`` line below is run by the page itself, through
`kpifs.cli.main` (what the ``kpifs`` executable calls); what it prints,
warnings included, is shown under it.
"""
import contextlib
import glob
import io
import os
import tempfile
from pathlib import Path
import warnings

import matplotlib.pyplot as plt
import numpy as np
import astropy.units as u

from kpifs.cli import main
from kpifs.data import DetectionResult
from kpifs.detect.sky import detector_to_sky
from kpifs.io import read_cube, write_observation
from kpifs.modelcheck import check_pupil_model
from kpifs.plotting import (plot_candidate_spectrum, plot_contrast_curves, plot_detection_map,
                            plot_injection_limits)
from kpifs.simulation.simulate import simulate_scene


def kpifs(command):
    """Run one ``kpifs`` command line as the shell would (file patterns expanded) and
    show what it prints (the progress lines of long commands left out)."""
    print(f"$ kpifs {command}")
    err = io.StringIO()
    with in_folder(here), contextlib.redirect_stderr(err):
        args = []
        for word in command.split():
            args += sorted(glob.glob(word)) if "*" in word else [word]
        code = main(args)
    for line in err.getvalue().splitlines():
        if "elapsed" not in line:
            print(line)
    if code:
        raise RuntimeError(f"kpifs {command} exited with status {code}")


@contextlib.contextmanager
def in_folder(path):
    """Commands run in *path*, as in a shell after ``cd path``."""
    old = os.getcwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(old)


# the tutorial works in a temporary folder, ``here``: in your own reduction, the folder
# that holds your files
workdir = tempfile.TemporaryDirectory(prefix="kpifs-charis-")
here = Path(workdir.name)

###############################################################################
# The files
# ---------
#
# A target with a companion of mean contrast 5e-3 (brighter in the blue) 120
# mas from it, and a calibrator star observed the same way, each star's
# exposures in its own folder as the pipeline leaves them. The simulator puts
# the truth in the target's headers (``KPSIMX``, ``KPSIMY``: the companion's
# offset on the detector, mas).

truth = 5e-3 * np.linspace(1.4, 0.6, 22)
obs = simulate_scene("charis", n_frames=30, seed=3, shape=(48, 48), exptime=1 * u.s,
                     contrasts=truth, companion_offset=[-70.0, 97.5] * u.mas)
write_observation(obs, here, layout="charis")
print(len(list(here.glob("target/*_cube.fits"))), "target files,",
      len(list(here.glob("calibrator/*_cube.fits"))), "calibrator files")

###############################################################################
# ``kpifs info`` says what kpifs reads in a file: the instrument it recognised
# (from the header), the wavelengths (``LAM_MIN * exp(i * DLOGLAM)``), the
# lenslet scale, each exposure's detector position angle (``PARANG + 113``,
# the CHARIS pipeline's sky rotation) and which channels cannot sample every
# baseline of the default pupil model.

kpifs("info target/CRSA00000000_cube.fits")

###############################################################################
# The two bluest channels lose their longest baselines to the Nyquist limit of
# 16.2 mas lenslets; ``kpifs extract`` drops those uv points for every channel
# (so that every channel has the same kernel phases) and says so.
#
# Checking the pupil model
# ------------------------
#
# Before trusting kernel phases, check that the pupil model matches the data:
# ``kpifs model-check calibrator/*_cube.fits`` fits the model's turn and the
# pixel-scale factor to the Fourier amplitudes of a star without a known
# companion (here the calibrator, its two halves compared) and recommends a
# model. Here the same function on a few channels and a short scan, for time:

with read_cube(sorted(here.glob("calibrator/*_cube.fits"))) as cube:
    frames, wl, pixscale = np.array(cube.data, float), cube.wavelengths, cube.pixscale
few = slice(6, None, 8)                                  # 3 of the 22 channels
with warnings.catch_warnings():
    warnings.simplefilter("ignore")                      # the Nyquist note, seen above
    check = check_pupil_model(frames[:12, few], wavelengths=wl[few], pixscale=pixscale,
                              rotations=[-1, 0, 1] * u.deg, scales=[0.99, 1.0, 1.01],
                              cuts=(0.2,), binary=False)
print(check.summary())

###############################################################################
# It prints the fitted turn and pixel-scale factor, the model it recommends and
# why: its last line says how well the Fourier amplitudes pin them down. On 12
# frames in 3 channels they hardly do, so here the default model is used, as
# the simulated pupil is the textbook one. On a real sequence run ``kpifs
# model-check`` with its defaults and give the model it recommends to ``kpifs
# extract`` (``--rotation``, ``--pixscale``).
#
# Calibrated kernel phases
# ------------------------
#
# All the target's exposures are one sequence: pass them all.
# ``--calibrator`` subtracts the calibrator's kernel phases and builds the
# error model from both stars' frames. ``calibrated_kp.fits`` (KPFITS) holds
# the calibrated kernel phases, their covariance, the error model's rows and
# the frames' angles.

kpifs("extract target/*_cube.fits --calibrator calibrator/*_cube.fits --step 0.8m "
      "--min-transmission 0.9 -o calibrated_kp.fits")

###############################################################################
# **A warning to act on.** 30 frames per star (58 degrees of freedom) for 74
# kernel phases per channel are too few for a full covariance: kpifs models it
# on its best-measured modes and measures its scale on the calibrated data when
# detecting. The search stays honest, but a longer sequence (or a coarser
# model, ``--step``) goes deeper. The other warnings you may meet, and what to
# do, are at the end of this page.

kpifs("info calibrated_kp.fits")

###############################################################################
# The search
# ----------
#
# ``kpifs detect`` searches a grid of positions for a companion at a global
# false-alarm probability (here the default, 1e-3, over the whole grid),
# fits what it finds, and writes the maps, candidates and limits. Its first
# line says which test ran: with 22 channels the default (``--test auto``) is
# ``S``, the spectral-model test. The frames' angles are known, so the map is
# on the sky (dRA, dDec, East left).

kpifs("detect calibrated_kp.fits --draws 2000 -o detection.fits --plots figures")

###############################################################################
# One line per fact: the test, its threshold, each candidate (its fitted
# position with errors on the detector and on the sky, its contrast, its global
# false-alarm probability: here far beyond what 2000 Monte-Carlo draws reach,
# so extrapolated from the null's tail), and how well the error model
# describes the data once the candidate is subtracted. ``kpifs info
# detection.fits`` gives the details.
#
# Reading the map
# ---------------
#
# The map is what the search decided on. Candidates are found one at a time:
# the strongest peak above the threshold is fitted and subtracted, and the map
# of what remains is searched again, until nothing crosses the threshold. The
# map drawn is that last residual, in units of the threshold (the contour at
# 1); each subtracted candidate is circled at its fitted position, with its own
# statistic in units of the threshold. The ``DETECTION`` extension of the
# products keeps the data's own map (companion included), ``SEARCH`` this one.

res = DetectionResult.read(here / "detection.fits")
shown = detector_to_sky(-70.0, 97.5, 113.0)     # PARANG 0 here: every DETPA is 113 deg
plot_detection_map(res, truth=shown)
plt.show()

###############################################################################
# Detection limits
# ----------------
#
# The contrast a companion needs to be found half the time (``P_D`` 0.5) at
# the same global false-alarm probability, against separation: the median over
# position angles (line) and their range (band), for every test, the one the
# search used drawn thick. ``NP`` is the local matched filter, a reference no
# search reaches; the limits include the noise scale printed above.

plot_contrast_curves(res)
plt.show()

###############################################################################
# The companion's spectrum
# ------------------------
#
# The fitted contrast in each channel with its 1-sigma error, beside the
# simulated truth. The two bluest channels alias some of their uv points: their
# contrasts are biased (the products flag them; ``--aliased exclude`` leaves
# them out of the search).

plot_candidate_spectrum(res, truth=truth)
plt.show()

###############################################################################
# An injection check
# ------------------
#
# A limit is a claim that can be checked: ``kpifs inject --curve`` makes
# companions out of each frame's own image, shifted and scaled, injects them
# at several position angles into the target's frames, and reruns the whole
# reduction for each. Here at 70 mas (50 mas or more from the real companion,
# which is not counted), four angles at two contrasts, for time; by default the
# steps start from the analytic limit and extend until they bracket the 50 %
# level. The limit is stated as far as the steps allow: between the highest
# step found significantly less than half the time and the lowest found
# significantly more (with four angles, 0 and 4 of 4 are; 1 to 3 are not), a
# value interpolated only between adjacent such steps.

kpifs("inject target/*_cube.fits --calibrator calibrator/*_cube.fits --curve "
      "--separations 70mas --contrasts 1.5e-3,1.2e-2 --angles 4 --step 0.8m "
      "--min-transmission 0.9 --draws 2000 -o curve.fits")

###############################################################################

from astropy.table import QTable                         # noqa: E402
injections = QTable.read(here / "curve.fits", hdu="INJECTIONS")
injections.meta.update(pd=0.5, pfa=1e-3)
plot_injection_limits(injections, analytic=res)
plt.show()

###############################################################################
# When a warning appears
# ----------------------
#
# - *too few frames for the covariance*: the error model keeps the modes the
#   frames measure and the search measures the noise scale on the data; take a
#   longer sequence or a coarser model (``--step``) to go deeper.
# - *uv points beyond the Nyquist limit*: the bluest channels cannot sample
#   the longest baselines; they are dropped for every channel (``--nyquist
#   raise`` refuses instead). *aliased* channels are flagged in the products;
#   ``kpifs detect --aliased exclude`` leaves them out.
# - *the null is optimistic* / *few Monte-Carlo draws*: raise ``--draws``.
# - a candidate ``[flagged: ...]``: ``chi2`` (the fit leaves more than the
#   noise), ``moved`` (the fit left the peak), ``inner-edge``/``outer-edge``
#   (at the grid's edge), ``contrast-bound``: read it as doubtful.
# - *the frames' angles are unknown*: the search stays on the detector; give
#   them with ``kpifs extract --pa``.
# - *spans N deg* (the target's frames turn during the sequence): the
#   calibrated mean smears a companion; keep the blocks (the default with
#   rotating sequences) or calibrate angular-differentially.

workdir.cleanup()
