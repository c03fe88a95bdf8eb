"""``kpifs demo``: the whole chain on CHARIS-format data that kpifs simulates itself.

simulate (CHARIS pipeline layout: target with a companion, calibrator) -> read
with the CHARIS reader -> extract kernel phases (22 channels) -> calibrate ->
detect (GLR binary test, calibrated grid search) -> detection FITS and figures,
all through `kpifs.workflow.process_observation`, as ``kpifs batch`` and the
``extract``/``detect`` commands would.
"""
import logging

import numpy as np
from astropy import units as u

from ._utils import check_output_dir
from .detect.sky import detector_to_sky, mean_angle
from .exceptions import KpifsError
from .io.layouts import write_observation
from .plotting import save_detection_plots
from .simulate import simulate_scene
from .workflow import DetectOptions, ExtractOptions, process_observation

__all__ = ["run_demo", "DEMO_SCENE", "DEMO_STEP"]

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


def run_demo(outdir, *, frames=200, seed=1, overwrite=False, progress=True, draws=5000):
    """Run the demonstration; returns the `~kpifs.data.DetectionResult`.

    Writes in *outdir*: ``charis/target/*_cube.fits`` and
    ``charis/calibrator/*_cube.fits`` (simulated), ``target_kp.fits`` and
    ``calibrator_kp.fits`` (KPFITS), ``calibrated_kp.fits``, ``detection.fits``
    and ``figures/*.png``.

    Examples
    --------
    >>> import tempfile, warnings
    >>> from kpifs.demo import run_demo
    >>> with warnings.catch_warnings():
    ...     warnings.simplefilter("ignore")    # 20 frames: kpifs warns the null is optimistic
    ...     res = run_demo(tempfile.mkdtemp(), frames=20, draws=1000, progress=False)
    >>> res.test, len(res.wavelengths)
    ('B', 22)
    """
    outdir = check_output_dir(outdir)
    if (outdir / "detection.fits").exists() and not overwrite:
        raise KpifsError(f"{outdir}: holds the products of an earlier demo; pass --overwrite")
    outdir.mkdir(parents=True, exist_ok=True)
    say = print if progress else (lambda *a, **k: None)

    say(f"[1/4] simulating {frames} CHARIS exposures of a target and of a calibrator")
    obs = simulate_scene("charis", n_frames=frames, seed=seed, progress=progress, **DEMO_SCENE)
    files = write_observation(obs, outdir / "charis", layout="charis", overwrite=overwrite)

    say(f"[2/4] reading, extracting, calibrating and searching (GLR test, {draws} "
        f"Monte-Carlo draws)")
    out = process_observation(files["target"], [files["calibrator"]], outdir,
                              extract_options=ExtractOptions(step=DEMO_STEP),
                              detect_options=DetectOptions(test="B", pfa=1e-3, pd=0.5,
                                                           draws=draws, seed=seed),
                              overwrite=overwrite, keep_stars=True, progress=progress)
    res = out["result"]

    say("[3/4] drawing figures")
    truth = tuple(obs.params.companion_offset.to_value(u.mas))
    shown = truth
    if res.meta.get("frame") == "sky":        # maps on the sky: the truth turned likewise
        shown = detector_to_sky(*truth, mean_angle(res.meta["pa_bins"][0]))
    save_detection_plots(res, outdir / "figures", truth=shown,
                         truth_spectrum=obs.params.contrasts)

    say(f"[4/4] truth: companion at ({truth[0]:.0f}, {truth[1]:.0f}) mas, mean contrast "
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
