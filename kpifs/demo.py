"""``kpifs demo``: the whole chain on CHARIS-format data that kpifs simulates itself.

simulate (CHARIS pipeline layout: target with a companion, calibrator) -> read
with the CHARIS reader -> extract kernel phases (22 channels) -> calibrate ->
detect (GLR binary test, calibrated grid search) -> detection FITS and figures.
"""
import logging
from pathlib import Path

import numpy as np
from astropy import units as u

from .exceptions import KpifsError

__all__ = ["run_demo", "DEMO_SCENE"]

log = logging.getLogger(__name__)

#: The demo's scene: the CHARIS preset on a 64x64 cut of the field, 1 s frames
#: of a magnitude-5 star, a companion of mean contrast 1e-3 at 130 mas.
DEMO_SCENE = dict(shape=(64, 64), exptime=1.0 * u.s, npup=96,
                  contrasts=1e-3 * np.linspace(1.4, 0.6, 22),
                  companion_offset=[-100.0, 83.0] * u.mas)

#: The demo's pupil model: Subaru on a 0.8 m grid (74 kernel phases), so that
#: the 200 frames per star far outnumber the kernel phases and the estimated
#: covariance (hence the false-alarm calibration) is trustworthy.
DEMO_STEP = 0.8 * u.m


def run_demo(outdir, *, frames=200, seed=1, overwrite=False, progress=True, draws=20000):
    """Run the demonstration; returns the `~kpifs.detect.DetectionResult`.

    Writes in *outdir*: ``charis/target/*_cube.fits`` and
    ``charis/calibrator/*_cube.fits`` (simulated), ``target_kp.fits`` and
    ``calibrator_kp.fits`` (KPFITS), ``calibrated_kp.fits``, ``detection.fits``
    and ``figures/*.png``.
    """
    from .calibrate import calibrate
    from .detect import detect
    from .extract import extract_kernel_phases
    from .io import read_cube, write_observation
    from .io.products import write_detection
    from .kernel import KernelModel
    from .plotting import save_detection_plots
    from .pupil import make_pupil
    from .simulate import simulate_scene

    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise KpifsError(f"{outdir}: exists and is not a directory")
    if (outdir / "detection.fits").exists() and not overwrite:
        raise KpifsError(f"{outdir}: holds the products of an earlier demo; pass --overwrite")
    outdir.mkdir(parents=True, exist_ok=True)
    say = print if progress else (lambda *a, **k: None)

    say(f"[1/5] simulating {frames} CHARIS exposures of a target and of a calibrator")
    obs = simulate_scene("charis", n_frames=frames, seed=seed, progress=progress, **DEMO_SCENE)
    files = write_observation(obs, outdir / "charis", layout="charis", overwrite=overwrite)

    say("[2/5] reading the cubes and extracting kernel phases")
    km = KernelModel.from_pupil(make_pupil("subaru", step=DEMO_STEP))
    kpds = {}
    for role in ("target", "calibrator"):
        with read_cube(files[role]) as cube:
            kpds[role] = extract_kernel_phases(cube.data, km, wavelengths=cube.wavelengths,
                                               pixscale=cube.pixscale, header=cube.header,
                                               source=cube.name, progress=progress)
        kpds[role].write(outdir / f"{role}_kp.fits", overwrite=overwrite,
                         inputs=[str(f) for f in files[role]])

    say("[3/5] calibrating the target with the calibrator")
    cal = calibrate(kpds["target"], kpds["calibrator"])
    cal.write(outdir / "calibrated_kp.fits", overwrite=overwrite,
              inputs=[str(f) for f in files["target"]])

    say(f"[4/5] searching for companions (GLR test, {draws} Monte-Carlo draws)")
    res = detect(cal, test="B", pfa=1e-3, pd=0.5, n_draws=draws, seed=seed, progress=progress)
    write_detection(res, outdir / "detection.fits", header=cal.header,
                    inputs=[str(outdir / "calibrated_kp.fits")], overwrite=overwrite)

    say("[5/5] drawing figures")
    truth = tuple(obs.params.companion_offset.to_value(u.mas))
    save_detection_plots(res, outdir / "figures", truth=truth,
                         truth_spectrum=obs.params.contrasts)
    say(f"truth: companion at ({truth[0]:.0f}, {truth[1]:.0f}) mas, mean contrast "
        f"{obs.params.contrasts.mean():.1e}")
    for row in res.candidates:
        x, dx = row["fit_x"].to_value(u.mas), row["fit_x_err"].to_value(u.mas)
        y, dy = row["fit_y"].to_value(u.mas), row["fit_y_err"].to_value(u.mas)
        say(f"found: ({x:.1f} +- {dx:.1f}, {y:.1f} +- {dy:.1f}) mas, "
            f"mean contrast {np.mean(row['fit_contrast']):.2e}, global P_FA "
            f"{row['pfa_global']:.1e}")
    if not len(res.candidates):
        say("found: no candidate above the threshold")
    say(f"products in {outdir}/: detection.fits, calibrated_kp.fits, figures/")
    return res
