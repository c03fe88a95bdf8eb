"""Third-party suite: JWST NIRCam files written by the JWST datamodels library
(stdatamodels' CubeModel, ``*_calints.fits``), with a PSF simulated independently of
kpifs's simulator (`thirdparty_jwst`; issue 35, item 9)."""
import warnings

import numpy as np
import pytest
from astropy import units as u
from astropy.io import fits

from kpifs.cli import main
from kpifs.data import DetectionResult, KernelPhaseData
from kpifs.exceptions import KpifsWarning
from kpifs.io import read_cube

pytest.importorskip("stdatamodels")

import thirdparty_jwst as tj  # noqa: E402


def test_datamodels_file_read_as_written(tmp_path):
    """What stdatamodels writes (DN/s, ERR, VAR_*, DQ as uint32 with BZERO, the WCS
    cards in SCI): read with the filter's wavelength and scale, DETPA from the SCI
    cards, DO_NOT_USE pixels bad, ERR as the pixel noise."""
    rng = np.random.default_rng(0)
    img = tj.psf_cube(rng, "F480M", 2, npup=48, nlam=2, oversample=1)
    path = tj.write_calints(tmp_path / "a_calints.fits", "F480M", img, rng=rng,
                            roll_ref=250.0)
    with fits.open(path) as h:
        assert h["DQ"].header["BZERO"] == 2147483648 and h["SCI"].header["BUNIT"] == "DN/s"
        assert h[0].header["DATAMODL"] == "CubeModel"
        nan = np.isnan(h["SCI"].data)
        flagged = (h["DQ"].data & 1) != 0
    with read_cube([path]) as c:
        assert c.instrument == "jwst"
        assert c.wavelengths.to_value(u.um) == pytest.approx([4.8213])
        assert c.pixscale.to_value(u.mas) == 63.0
        assert c.detpa.to_value(u.deg) == pytest.approx([250.0, 250.0])
        assert c.variance_source == "ERR"
        read = np.isnan(np.asarray(c.data[:])[:, 0])
        warm = (fits.getdata(path, "DQ") & 4096) != 0
    # DO_NOT_USE pixels (NaN in SCI) are bad; WARM alone is not (jwst-kpi's choice)
    assert flagged.any() and warm.any() and np.array_equal(nan, flagged)
    assert np.array_equal(read, flagged)


@pytest.mark.slow
def test_nircam_pair_written_by_datamodels(tmp_path):
    """F150W + F480M, the W0336-like binary (84 mas, PA 295 deg, contrasts 0.076 and
    0.19), 20 integrations per star and filter: band, pixel integration, jitter, a star
    off the subarray centre, a calibrator 0.38 px from the target's place, DQ. One
    candidate, fitted within 1.5 mas and 1 deg, contrasts within 10 %."""
    t, c, off = tj.nircam_pair(tmp_path, seed=0)
    out, det = tmp_path / "kp.fits", tmp_path / "det.fits"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KpifsWarning)
        assert main(["extract", *t, "--calibrator", *c, "-o", str(out), "-q"]) == 0
        assert main(["detect", str(out), "-o", str(det), "--draws", "1000", "-q"]) == 0
    kpd = KernelPhaseData.read(out)
    assert kpd.channel_n_kp.tolist() == [117, 335]
    cands = DetectionResult.read(det).candidates
    assert len(cands) >= 1
    row = cands[0]
    dra, ddec = row["fit_dra"].to_value(u.mas), row["fit_ddec"].to_value(u.mas)
    assert np.hypot(dra - off[0], ddec - off[1]) < 1.5
    assert abs(row["fit_pa_sky"].to_value(u.deg) - 295.0) < 1.0
    assert np.asarray(row["fit_contrast"]) == pytest.approx([0.076, 0.19], rel=0.1)


def test_err_in_dn_per_second_is_the_kernel_phase_noise(tmp_path):
    """ERR written by stdatamodels in DN/s (photon and read noise of electrons / gain /
    EFFINTTM): the kernel-phase errors kpifs propagates from it match the scatter of 30
    integrations of a fixed wavefront (median ratio within 10 %; measured 0.92, against
    0.97 for point-sampled monochromatic images: the pixels' and the band's transfer
    function lowers the signal at the longest baselines, where first-order propagation
    overstates a phase's scatter)."""
    from kpifs.workflow import extract_observation
    rng = np.random.default_rng(5)
    pup, dx = tj.jwst_pupil(64)
    static = tj._screen(rng, 64, dx, 60e-9, pup > 0)
    img = tj.psf_cube(rng, "F480M", 30, npup=64, nlam=3, oversample=2, static=static,
                      drift_nm=0.0, effects=tj.Effects(jitter=False))
    path = tj.write_calints(tmp_path / "a_calints.fits", "F480M", img, rng=rng)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KpifsWarning)
        kpd = extract_observation([path])
    assert kpd.meta["pixel_noise"] == "ERR"
    ratio = kpd.kp.std(0, ddof=1)[0] / kpd.kp_err.mean(0)[0]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.1)


def test_mjy_per_sr_same_kernel_phases_and_errors(tmp_path):
    """Imaging products calibrated to MJy/sr (SCI, ERR and VAR_* scaled by PHOTMJSR): the
    same kernel phases and errors as in DN/s."""
    from kpifs.workflow import extract_observation
    out = []
    for conv in (None, 0.37):
        rng = np.random.default_rng(6)
        img = tj.psf_cube(rng, "F480M", 4, npup=48, nlam=2, oversample=1)
        path = tj.write_calints(tmp_path / f"{conv}_calints.fits", "F480M", img, rng=rng,
                                photmjsr=conv)
        assert fits.getval(path, "BUNIT", "SCI") == ("DN/s" if conv is None else "MJy/sr")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", KpifsWarning)
            out.append(extract_observation([path]))
    np.testing.assert_allclose(out[1].kp, out[0].kp, atol=1e-5)
    np.testing.assert_allclose(out[1].kp_err, out[0].kp_err, rtol=1e-4)
