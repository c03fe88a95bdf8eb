"""A bright companion makes no other (issue 24, item 2): the search subtracts the fitted
model, window gain included, before it looks again."""
import warnings

import numpy as np
import pytest
import astropy.units as u

from kpifs import KernelModel, extract_kernel_phases, make_pupil
from kpifs.calibration.calibrate import calibrate
from kpifs.detect import detect
from kpifs.simulation.simulate import simulate_scene


def _search(offset, contrast, *, n_frames, seed, **kw):
    obs = simulate_scene("paper", n_frames=n_frames, seed=seed, companion_offset=offset * u.mas,
                         contrasts=contrast, **kw)
    km = KernelModel.from_pupil(make_pupil("subaru"))
    args = dict(wavelengths=obs.wavelengths, pixscale=obs.params.pixscale)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = extract_kernel_phases(obs.target, km, **args)
        c = extract_kernel_phases(obs.calibrator, km, **args)
        return detect(calibrate(t, c), pfa=1e-3, n_draws=2000, seed=seed, limits=False)


@pytest.mark.slow
@pytest.mark.parametrize("offset", [(60.0, 40.0), (-90.0, 70.0), (30.0, -120.0)])
def test_bright_companion_alone(offset):
    """Contrast 5e-3 (statistic hundreds of times the threshold) at three positions:
    exactly one candidate, fitted within 2 mas, no flag."""
    res = _search(np.array(offset), 5e-3, n_frames=60, seed=3, npup=64)
    cands = res.candidates
    assert len(cands) == 1
    assert np.hypot(cands["fit_x"][0].value - offset[0], cands["fit_y"][0].value - offset[1]) < 2
    assert cands["statistic"][0] > 20 * res.threshold
    assert cands["flags"][0] == ""


@pytest.mark.slow
def test_readme_detect_example_reports_its_one_companion(tmp_path, capsys):
    """The README's example through the command line (``simulate --preset paper --frames
    400``, one companion at (80, 60) mas, mean contrast 6.3e-4): one candidate, where an
    approximate subtracted model left a second at the grid's edge (global P_FA 1e-5)."""
    from astropy.io import fits
    from kpifs.cli import main
    sim = tmp_path / "sim"
    assert main(["simulate", "--preset", "paper", "--frames", "400", "-o", str(sim), "-q"]) == 0
    for star in ("target", "calibrator"):
        assert main(["extract", str(sim / f"{star}.fits"), "-o", str(tmp_path / f"{star}.fits"),
                     "-q"]) == 0
    out = tmp_path / "detection.fits"
    assert main(["detect", str(tmp_path / "target.fits"), "--calibrator",
                 str(tmp_path / "calibrator.fits"), "--pfa", "1e-3", "-o", str(out), "-q"]) == 0
    cands = fits.getdata(out, "CANDIDATES")
    assert len(cands) == 1
    assert np.hypot(cands["fit_x"][0] - 80, cands["fit_y"][0] - 60) < 3
