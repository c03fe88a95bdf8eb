"""``kpifs demo``: the whole chain on CHARIS-format data that kpifs simulates itself.

simulate (CHARIS pipeline layout: target with a companion, calibrator) -> read
with the CHARIS reader -> extract kernel phases (22 channels) -> calibrate ->
detect (the default test, ``--test auto``: S on these 22 channels; calibrated grid
search) -> detection FITS and figures, all through
`kpifs.workflow.process_observation`, as ``kpifs batch`` and the
``extract``/``detect`` commands would.
"""
import logging
import tempfile
from pathlib import Path

import numpy as np
from astropy import units as u

from ._utils import check_output_dir, one_blas_thread
from .detect.sky import detector_to_sky, mean_angle
from .exceptions import KpifsError
from .io.layouts import write_observation
from .plotting import save_detection_plots
from .simulation.simulate import simulate_scene
from .workflow import DetectOptions, ExtractOptions, process_observation

__all__ = ["run_demo", "DEMO_SCENE", "DEMO_STEP", "DEMO_MIN_TRANSMISSION"]

log = logging.getLogger(__name__)

#: The demo's scene: the CHARIS preset on a 64x64 cut of the field, 1 s frames
#: of a magnitude-5 star, a companion of mean contrast 1e-3 at 130 mas.
DEMO_SCENE = dict(shape=(64, 64), exptime=1.0 * u.s, npup=96,
                  contrasts=1e-3 * np.linspace(1.4, 0.6, 22),
                  companion_offset=[-100.0, 83.0] * u.mas)

#: The demo's pupil model: Subaru on a 0.8 m grid, so that the 200 frames per star
#: far outnumber the 74 kernel phases and the estimated covariance (hence the
#: false-alarm calibration) is trustworthy ...
DEMO_STEP = 0.8 * u.m
#: ... of cells at least 90 % inside the pupil: its longest baseline (7.2 m) is
#: sampled by CHARIS's 16.2 mas pixels down to the shortest channel, 1.16 um
#: (the default cut, 0.2, reaches 7.6 m, beyond the 7.4 m there).
DEMO_MIN_TRANSMISSION = 0.9


def _position(row, sky):
    """A candidate's fitted position, naming its frame."""
    def text(a, b, names):
        va, ea = row[f"fit_{a}"].to_value(u.mas), row[f"fit_{a}_err"].to_value(u.mas)
        vb, eb = row[f"fit_{b}"].to_value(u.mas), row[f"fit_{b}_err"].to_value(u.mas)
        return f"{names[0]} {va:.1f} +- {ea:.1f}, {names[1]} {vb:.1f} +- {eb:.1f} mas"
    if sky and "fit_dra" in row.colnames:
        return text("dra", "ddec", ("dRA", "dDec")) + " on the sky (East positive)"
    return text("x", "y", ("x", "y")) + " on the detector"


def run_demo(outdir, *, frames=200, seed=1, overwrite=False, progress=True, draws=5000,
             keep_inputs=False):
    """Run the demonstration; returns the `~kpifs.data.DetectionResult`.

    Writes in *outdir*: ``target_kp.fits`` and ``calibrator_kp.fits`` (KPFITS),
    ``calibrated_kp.fits``, ``detection.fits`` and ``figures/*.png`` (24 MB with
    the defaults). The simulated CHARIS cubes are made in a temporary folder and
    removed (about 300 MB), or kept in ``charis/target/*_cube.fits`` and
    ``charis/calibrator/*_cube.fits`` with *keep_inputs*.

    Examples
    --------
    >>> import tempfile, warnings
    >>> from kpifs.demo import run_demo
    >>> tmp = tempfile.TemporaryDirectory()
    >>> with warnings.catch_warnings():
    ...     warnings.simplefilter("ignore")    # 20 frames: kpifs warns the null is optimistic
    ...     res = run_demo(tmp.name, frames=20, draws=1000, progress=False)
    >>> res.test, len(res.wavelengths)      # the default test on 22 channels
    ('S', 22)
    >>> tmp.cleanup()
    """
    outdir = check_output_dir(outdir)
    if (outdir / "detection.fits").exists() and not overwrite:
        raise KpifsError(f"{outdir}: holds the products of an earlier demo; pass --overwrite")
    outdir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="kpifs-demo-") as tmp, one_blas_thread():
        # the chain's products are small matrices: BLAS's own threads would only wait
        inputs = outdir / "charis" if keep_inputs else Path(tmp)
        return _run(outdir, inputs, frames=frames, seed=seed, overwrite=overwrite,
                    progress=progress, draws=draws, keep_inputs=keep_inputs)


def _run(outdir, inputs, *, frames, seed, overwrite, progress, draws, keep_inputs):
    say = print if progress else (lambda *a, **k: None)
    where = f"in {inputs}" if keep_inputs else "in a temporary folder"
    say(f"[1/4] simulating {frames} CHARIS exposures of a target and of a calibrator ({where})")
    obs = simulate_scene("charis", n_frames=frames, seed=seed, progress=progress, **DEMO_SCENE)
    files = write_observation(obs, inputs, layout="charis", overwrite=overwrite)

    say(f"[2/4] reading, extracting, calibrating and searching (the default test, {draws} "
        f"Monte-Carlo draws)")
    xo = ExtractOptions(step=DEMO_STEP, min_transmission=DEMO_MIN_TRANSMISSION)
    out = process_observation(files["target"], [files["calibrator"]], outdir,
                              extract_options=xo,
                              detect_options=DetectOptions(pfa=1e-3, pd=0.5, draws=draws,
                                                           seed=seed),
                              overwrite=overwrite, keep_stars=True, progress=progress)
    res = out["result"]

    say("[3/4] drawing figures")
    truth = tuple(obs.params.companion_offset.to_value(u.mas))
    sky = res.meta.get("frame") == "sky"
    shown = detector_to_sky(*truth, mean_angle(res.meta["pa_bins"][0])) if sky else truth
    save_detection_plots(res, outdir / "figures", truth=shown,
                         truth_spectrum=obs.params.contrasts)

    frame = ("dRA {:.0f}, dDec {:.0f} mas on the sky (East positive)" if sky
             else "x {:.0f}, y {:.0f} mas on the detector")
    say(f"[4/4] test: {res.test} (the default, --test auto: S on data with more channels "
        f"than its spectral model's rank, else B), global P_FA {res.pfa:g}")
    say(f"truth: companion at {frame.format(*shown)}, mean contrast "
        f"{obs.params.contrasts.mean():.1e}")
    for i, row in enumerate(res.candidates, 1):
        say(f"found {i}: {_position(row, sky)}, mean contrast "
            f"{np.mean(row['fit_contrast']):.2e}, global P_FA {row['pfa_global']:.1e}")
    if not len(res.candidates):
        say("found: no candidate above the threshold")
    size = sum(p.stat().st_size for p in outdir.rglob("*") if p.is_file()) / 2 ** 20
    say(f"products in {outdir}/ ({size:.0f} MB): detection.fits, calibrated_kp.fits, "
        f"figures/")
    return res
