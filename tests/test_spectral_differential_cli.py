"""``--spectral-differential`` through the one driver, the command line and the products
(issue 39)."""
import numpy as np
import pytest
from astropy import units as u
from astropy.io import fits

from kpifs import DetectionResult, KernelPhaseData
from kpifs.cli import main
from kpifs.detect.sdk import STATIC_SPECTRA
from kpifs.exceptions import KpifsError, KpifsWarning
from kpifs.io.layouts import write_observation
from kpifs.simulation.simulate import simulate_scene
from kpifs.workflow import ExtractOptions, reduce_observation

WL = np.linspace(1.2, 2.3, 8) * u.um


@pytest.fixture(scope="module")
def sim8(tmp_path_factory):
    """Eight channels, no companion, 30 nm of static aberration."""
    d = tmp_path_factory.mktemp("sdk")
    obs = simulate_scene("paper", wavelengths=WL, contrasts=0.0, pixscale=7.0 * u.mas,
                         n_frames=30, seed=4, npup=32, static_rms=30 * u.nm)
    return write_observation(obs, d)


@pytest.fixture(scope="module")
def sim1(tmp_path_factory):
    d = tmp_path_factory.mktemp("sdk1")
    obs = simulate_scene("paper", wavelengths=[1.6] * u.um, contrasts=0.0, n_frames=4,
                         seed=4, npup=32)
    return write_observation(obs, d)


def test_single_channel_refused(sim1, tmp_path, capsys):
    out = tmp_path / "kp.fits"
    code = main(["extract", str(sim1["target"][0]), "--step", "1.2m",
                 "--spectral-differential", "poly", "-o", str(out), "-q"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert "--spectral-differential needs several channels" in err and "one channel" in err
    assert not out.exists()
    with pytest.raises(KpifsError, match="several channels"):
        reduce_observation(sim1["target"], [], ExtractOptions(step="1.2m",
                                                              spectral_differential="poly"))


def test_asdi_needs_a_turning_sequence(sim8):
    # ASDI (tests/test_asdi.py) needs the rotation's time blocks: these frames do not turn
    with pytest.raises(KpifsError, match="--angular-differential needs"):
        reduce_observation(sim8["target"], [], ExtractOptions(
            step="1.2m", spectral_differential="poly", angular_differential=True))


def test_extract_and_detect(sim8, tmp_path, capsys):
    """extract writes the profiles (KP-SDK) with no calibrator; detect prints what was
    projected and where the search starts, and writes it in the product's cards."""
    kp = tmp_path / "sdk.fits"
    assert main(["extract", str(sim8["target"][0]), "--step", "1.2m",
                 "--spectral-differential", "poly", "-o", str(kp), "-q"]) == 0
    assert "spectral-differential kernel phases" in capsys.readouterr().out
    back = KernelPhaseData.read(kp)
    assert back.n_frame == 1 and back.spectral["profiles"].shape == (8, 3)
    # the search's static term, imaged once with the product, by groups (one amplitude
    # each: `kpifs.detect.sdk.STATIC_SPECTRA`)
    n_groups = len(STATIC_SPECTRA)
    assert len(back.spectral["static_groups"]) == n_groups
    assert sum(back.spectral["static_groups"]) == len(back.spectral["static_rows"])
    det = tmp_path / "det.fits"
    assert main(["detect", str(kp), "-o", str(det), "--draws", "1000", "--pfa", "0.01",
                 "-q"]) == 0
    out = capsys.readouterr().out
    assert "spectral-differential: 3 profile(s) along the channels (poly)" in out
    assert "5 channel combinations searched" in out
    hdr = fits.getheader(det)
    assert hdr["SDKNPROF"] == 3 and hdr["SDKNCOMB"] == 5 and hdr["SDKBASIS"] == "poly"
    amps = [hdr[f"SDKSTA{i}"] for i in range(1, n_groups + 1)]
    assert f"SDKSTA{n_groups + 1}" not in hdr and min(amps) >= 0
    assert DetectionResult.read(det).meta["blocks"]["static_amplitudes"] == amps


@pytest.mark.slow
def test_process_observation_without_calibrator(sim8, tmp_path):
    """The one driver (batch's) reduces a target alone with the option, and refuses it
    without (no calibrator)."""
    from kpifs.workflow import DetectOptions, process_observation
    with pytest.raises(KpifsError, match="no calibrator"):
        process_observation(sim8["target"], [], tmp_path / "a",
                            extract_options=ExtractOptions(step="1.2m"))
    with pytest.warns(KpifsWarning, match="30 frames for 25 kernel phases"):
        out = process_observation(sim8["target"], [], tmp_path / "b",
                                  extract_options=ExtractOptions(
                                      step="1.2m", spectral_differential="poly"),
                                  detect_options=DetectOptions(draws=1000, pfa=0.01))
    assert out["calibrated"].spectral["profiles"].shape == (8, 3)
    assert out["result"].meta["blocks"]["combinations"] == 5
    assert fits.getheader(out["paths"]["detection"])["SDKNCOMB"] == 5
