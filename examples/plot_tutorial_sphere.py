"""
From SPHERE-IFS cubes (with their wavelength and angle files) to a detection map
================================================================================

One star observed with VLT/SPHERE-IFS, from the reduced cube and its
wavelength and angle files to a detection map, a contrast curve, the
companion's spectrum and an injection check, with the commands you would type.

The files are made by kpifs's simulator in the layout of the community
SPHERE-IFS pipeline's products (vlt-sphere): ``science_cube.fits``, a 4-D cube
``(39 wavelengths, frames, y, x)`` with almost no header; ``wavelength.fits``,
the 39 wavelengths in nm; ``parallactic_angles.fits``, one angle per frame in
degrees. Your own files go through the same commands. To keep this page quick
the frames are few (24 per star), the images 48 x 48 pixels and the pupil
model coarse (a 0.8 m grid: 59 kernel phases per channel); on your data keep
the defaults and take several times more frames than kernel phases.

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
from astropy.io import fits
from astropy.table import QTable

from kpifs.cli import main
from kpifs.data import DetectionResult
from kpifs.detect.sky import detector_to_sky
from kpifs.io import read_cube, write_observation
from kpifs.io.sphere import SPHERE_DETPA_OFFSET
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
workdir = tempfile.TemporaryDirectory(prefix="kpifs-sphere-")
here = Path(workdir.name)

###############################################################################
# The files
# ---------
#
# A target with a companion of mean contrast 4e-3 (brighter in the blue) 100
# mas from it, and a calibrator star observed the same way, in the YJ mode (39
# channels, 0.96-1.33 um, 7.46 mas pixels). The frames' detector position
# angles run from 60 to 60.8 deg. The simulator puts the truth in the target's
# header (``KPSIMX``, ``KPSIMY``: the companion's offset on the detector, mas).

truth = 4e-3 * np.linspace(1.3, 0.7, 39)
detpa = np.linspace(60.0, 60.8, 24)
obs = simulate_scene("sphere", n_frames=24, seed=5, shape=(48, 48), detpa=detpa,
                     contrasts=truth, companion_offset=[80.0, 60.0] * u.mas)
write_observation(obs, here, layout="sphere")
for name in sorted(here.glob("target/*.fits")):
    print(name.relative_to(here), fits.getdata(name).shape)

###############################################################################
# ``kpifs info`` finds the wavelength and angle files beside the cube (by their
# names; ``kpifs extract --wavelengths FILE`` and ``--pa FILE`` give others),
# tells nm from um, and shows the detector position angle it derives from the
# angle file.

kpifs("info target/science_cube.fits")

###############################################################################
# The angle convention
# --------------------
#
# kpifs needs each frame's *detector position angle* (DETPA): the position
# angle, East of North, of the detector's +y axis. For SPHERE-IFS in
# pupil-tracking mode it takes
#
# ``DETPA = angle + 135.99 - 100.48 - 1.75 = angle + 33.76 deg``
#
# with *angle* the frame's parallactic angle from the angle file: the pupil
# offset (135.99 +- 0.11 deg), the IFS offset (-100.48 +- 0.10 deg) and the
# true-North correction (-1.75 +- 0.08 deg) of Maire et al. (2016, SPIE 9908,
# 990834), as the vlt-sphere pipeline combines them into its derotation angle
# (``toolbox.compute_angles``: ``DEROT ANGLE = PARANG + pupoff + instru_offset
# + true_north`` for ``INS4 DROT2 MODE = ELEV``). The derotation angle that
# turns a frame North-up is the DETPA kpifs uses.
#
# What is assumed, and how to check it on your files:
#
# - the angle file holds **parallactic angles**, in degrees, one per frame.
#   Compare it with the raw frames' headers (``HIERARCH ESO TEL PARANG START``
#   and ``END``): the values should lie between them.
# - if your file holds **derotation angles** instead (vlt-sphere writes both
#   in ``frames_info*.csv``: the ``PARANG`` and ``DEROT ANGLE`` columns), give
#   them to ``kpifs extract --pa FILE``: no offset is added to ``--pa``.
# - SPHERE Data Center products (recognised by ``HIERARCH ESO PRO REC1 ID =
#   'sph_ifs_science_dr'``) carry the angles with the opposite sign; kpifs
#   inverts them. ``kpifs info`` shows the DETPA it derived: check its sign and
#   range against your log.
# - the final check is a known binary, or a companion you detect: its position
#   angle on the sky must not depend on the night's parallactic angles.
#
# The same cube with derotation angles given directly: the DETPA kpifs uses is
# the same (no offset is added to ``--pa``).

angles = fits.getdata(here / "target/parallactic_angles.fits")
np.savetxt(here / "derotation_angles.txt", angles + SPHERE_DETPA_OFFSET)
kpifs("extract target/science_cube.fits --pa derotation_angles.txt --step 0.8m "
      "-o target_kp.fits")
kpifs("info target_kp.fits")

###############################################################################
# Checking the pupil model
# ------------------------
#
# ``kpifs model-check calibrator/science_cube.fits`` fits the VLT pupil
# model's turn and the pixel-scale factor to the Fourier amplitudes of a star
# without a known companion (the calibrator's two halves compared) and
# recommends a model. Here the same function on a few channels and a short
# scan, for time:

with read_cube(here / "calibrator/science_cube.fits") as cube:
    frames, wl, pixscale = np.array(cube.data, float), cube.wavelengths, cube.pixscale
few = slice(6, None, 13)                                 # 3 of the 39 channels
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    check = check_pupil_model(frames[:12, few], wavelengths=wl[few], pixscale=pixscale,
                              pupil="vlt", rotations=[-1, 0, 1] * u.deg,
                              scales=[0.99, 1.0, 1.01], cuts=(0.2,), binary=False)
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

kpifs("extract target/science_cube.fits --calibrator calibrator/science_cube.fits "
      "--step 0.8m -o calibrated_kp.fits")

###############################################################################
# The warning says the covariance is modelled on the modes that 24 + 24 frames
# measure, with its scale measured on the data when detecting: honest, but a
# longer sequence goes deeper. ``kpifs info calibrated_kp.fits`` shows the
# mean DETPA the calibrated data carry.

kpifs("info calibrated_kp.fits")

###############################################################################
# The search
# ----------
#
# The frames' angles are known: the search and its maps are on the sky (dRA
# East-positive, dDec; East left). With 39 channels the default test is
# ``S``, the spectral-model test; the first line says so.

kpifs("detect calibrated_kp.fits --draws 2000 -o detection.fits")

###############################################################################
# Reading the map
# ---------------
#
# The map is the residual the search stopped on, in units of its threshold:
# the companion, found, fitted and subtracted, is circled with its own
# statistic; nothing left crosses the threshold (the contour). The cross is
# the simulated companion, turned to the sky with the frames' mean DETPA.

res = DetectionResult.read(here / "detection.fits")
plot_detection_map(res, truth=detector_to_sky(80.0, 60.0, float(np.mean(detpa))))
plt.show()

###############################################################################
# Detection limits and spectrum
# -----------------------------

plot_contrast_curves(res)
plt.show()

###############################################################################

plot_candidate_spectrum(res, truth=truth)
plt.show()

###############################################################################
# An injection check
# ------------------
#
# Companions made of the frames themselves, injected at four position angles
# and two contrasts at 60 mas (away from the real one), each reduction rerun:
# where do the steps put the limit, against the analytic one?

kpifs("inject target/science_cube.fits --calibrator calibrator/science_cube.fits --curve "
      "--separations 60mas --contrasts 2e-3,1.6e-2 --angles 4 --step 0.8m --draws 2000 "
      "-o curve.fits")

###############################################################################

injections = QTable.read(here / "curve.fits", hdu="INJECTIONS")
injections.meta.update(pd=0.5, pfa=1e-3)
plot_injection_limits(injections, analytic=res)
plt.show()

###############################################################################
# When a warning appears
# ----------------------
#
# - *no angle file: detector position angles unknown*: the search stays on
#   the detector (x, y) and prints no sky offsets; give the angles with
#   ``--pa``.
# - *spans N deg over its frames*: in pupil tracking the field turns; kpifs
#   keeps the calibrated data's time blocks and searches them on the sky
#   block by block.
# - *too few frames for the covariance*, *the null is optimistic*, a candidate
#   ``[flagged: ...]``: see the end of :doc:`plot_tutorial_charis`.
# - wavelengths that look like nm given as um (or the reverse) are refused
#   with the file named: check ``wavelength.fits``'s unit.

workdir.cleanup()
