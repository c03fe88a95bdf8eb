"""The pupil-model check (issue 10): orientation and pixel scale recovered on simulations
where the detector's pupil is turned and the pixel scale is off; the PHARO table."""
import numpy as np
import pytest
import astropy.units as u

from kpifs import KpifsError
from kpifs.modelcheck import check_pupil_model
from kpifs.simulation.simulate import simulate_scene

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("rotation, factor, seed", [(2.0, 1.01, 3), (-1.3, 0.992, 4)])
def test_turned_pupil_and_wrong_pixel_scale_recovered(rotation, factor, seed):
    """Pupil turned by a known angle and a pixel scale off by about 1 %, with drifting
    aberrations: both recovered within a quarter of the error (0.5 deg and 0.25 %)."""
    obs = simulate_scene("paper", n_frames=40, seed=seed, contrasts=0.0,
                         pupil_rotation=rotation * u.deg, drift_rms=30 * u.nm,
                         wavefront_rms=80 * u.nm)
    given = obs.params.pixscale / factor
    chk = check_pupil_model(obs.target, obs.calibrator, wavelengths=obs.wavelengths,
                            pixscale=given, pupil="subaru", cuts=(0.2,), binary=False)
    assert abs(chk.rotation.to_value(u.deg) - rotation) < 0.25 * abs(rotation)
    assert abs(chk.scale - factor) < 0.25 * abs(factor - 1)
    # the textbook pupil describes simulated amplitudes: the fitted geometry is used
    assert chk.meta["shape_ok"]
    rec = chk.recommended
    assert rec["rotation"].to_value(u.deg) == pytest.approx(chk.rotation.to_value(u.deg))
    assert rec["pixscale"].to_value(u.mas) == pytest.approx(given.value * chk.scale)
    t = chk.table
    assert set(t["scan"]) >= {"default", "rotation", "scale", "refine", "fitted", "cut"}
    # the amplitude mismatch at the fit is far below the default geometry's
    assert t["amp_mismatch"][t["scan"] == "fitted"][0] < 0.5 * t["amp_mismatch"][0]


def test_halves_of_one_sequence_and_bad_input():
    obs = simulate_scene("paper", n_frames=16, seed=1, contrasts=0.0, npup=64)
    chk = check_pupil_model(obs.target, wavelengths=obs.wavelengths,
                            pixscale=obs.params.pixscale, rotations=[-1.5, 0, 1.5] * u.deg,
                            scales=[0.99, 1.0, 1.01], cuts=(0.2, 0.5), binary=True)
    assert chk.meta["pair"] == "the two halves of the sequence"
    assert chk.meta["n_target"] == chk.meta["n_calibrator"] == 8
    assert {"grey", "binary"} <= {("grey" if g else "binary") for g in chk.table["grey"]}
    assert "chi2" in chk.reason and "recommended" in chk.summary()
    with pytest.raises(KpifsError, match="at least 4 frames"):
        check_pupil_model(obs.target[:2], wavelengths=obs.wavelengths,
                          pixscale=obs.params.pixscale)
    with pytest.raises(KpifsError, match="must agree"):
        check_pupil_model(obs.target, obs.calibrator[:, :2], wavelengths=obs.wavelengths,
                          pixscale=obs.params.pixscale)


@pytest.mark.realdata
def test_pharo_table_and_recommendation(real_data, tmp_path, capsys):
    """On the real PHARO calibrator (halves) the check prints its table and a
    recommendation; the textbook pupil does not describe PHARO's amplitudes to within
    their noise, and the kernel phases do not confirm the fitted turn: the default
    model is kept."""
    from astropy.table import QTable
    from kpifs.cli import main
    out = tmp_path / "check.ecsv"
    assert main(["model-check", str(real_data / "pharo_ca2_cube_epsHer.fits"),
                 "--wavelengths", "2.145um", "--pixscale", "25mas", "--pupil", "pharo",
                 "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "recommended:" in text and "why:" in text
    t = QTable.read(out)
    assert len(t) > 20 and np.all(np.isfinite(t["chi2_red"]))
    assert set(t["min_transmission"][t["scan"] == "cut"]) >= {0.1, 0.2, 0.5, 0.9}
    assert "default kept" in text


def test_recommendation_needs_a_chi2_difference_beyond_its_noise():
    """The README's model-check on kpifs's own 400-frame simulated calibrator: every model
    had a calibrated reduced chi2 of 2.06-2.35 over 597 modes, and the binary model's 2.06
    against the default's 2.35 was recommended. Each chi2 scatters by chi2_red * sqrt(2 / n)
    (0.136 and 0.119 here), so the difference's standard deviation is 0.181: 0.29 is 1.6 of
    them, within the noise. A real improvement (to 1.2) is still taken."""
    from kpifs.modelcheck import _chi2_difference_sd, _significantly_lower
    default = {"chi2_red": 2.35, "n_modes": 597}
    binary = {"chi2_red": 2.06, "n_modes": 597}
    assert _chi2_difference_sd(binary, default) == pytest.approx(
        np.sqrt(2 * (2.35 ** 2 + 2.06 ** 2) / 597), rel=1e-12)
    assert _chi2_difference_sd(binary, default) == pytest.approx(0.181, abs=1e-3)
    assert not _significantly_lower(binary, default)
    assert _significantly_lower({"chi2_red": 1.2, "n_modes": 597}, default)
    # with few modes the same relative gain is noise
    assert not _significantly_lower({"chi2_red": 1.2, "n_modes": 10},
                                    {"chi2_red": 2.35, "n_modes": 10})


@pytest.mark.slow
def test_default_kept_on_the_simulators_own_calibrator():
    obs = simulate_scene("paper", n_frames=200, seed=0, contrasts=0.0)
    chk = check_pupil_model(obs.calibrator, wavelengths=obs.wavelengths,
                            pixscale=obs.params.pixscale, rotations=[-1.5, 0, 1.5] * u.deg,
                            scales=[1.0])
    cuts = chk.table[chk.table["scan"] == "cut"]
    assert np.ptp(cuts["chi2_red"]) > 0.1          # the models' chi2 differ, by noise
    assert chk.recommended["grey"] and chk.recommended["min_transmission"] == 0.2
    assert "not lower by 2 standard deviations" in chk.reason
