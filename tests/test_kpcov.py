"""Issue 35, item 7: the KP-COV that kpifs writes is positive definite, and another tool
that inverts it gets the chi-square that ``detect`` reports (the error model of few
frames keeps only its leading modes; the directions it leaves out weigh nothing)."""
import warnings

import numpy as np
import pytest
import astropy.units as u
from astropy.io import fits

from kpifs import KernelModel, KernelPhaseData, make_pupil
from kpifs.calibration.calibrate import calibrate
from kpifs.covariance import rows_covariance
from kpifs.detect import detect


def _frames(rng, km, n, mix):
    """*n* frames of two channels: drifting aberration modes (a random walk) and noise."""
    drift = np.cumsum(rng.standard_normal((n, len(mix))), axis=0) * 0.3
    return (drift @ mix + rng.standard_normal((n, 2 * km.n_kp))).reshape(n, 2, km.n_kp) * 1e-3


@pytest.fixture(scope="module")
def calibrated():
    """Calibrated data whose error model (10 + 10 frames) keeps 9 of 37 modes per channel."""
    km = KernelModel.from_pupil(make_pupil("subaru", step=1.0 * u.m))
    rng = np.random.default_rng(7)
    mix = rng.standard_normal((6, 2 * km.n_kp))
    tgt, cal = (KernelPhaseData(_frames(rng, km, 10, mix), [1.6, 1.7] * u.um, 10 * u.mas, km,
                                meta={"source": name}) for name in ("t.fits", "c.fits"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")              # few frames: said in a warning
        return calibrate(tgt, cal)


def _chi2_by_inversion(path):
    """What another reader does: KP-DATA and KP-COV, ``d^T C^-1 d`` per channel."""
    with fits.open(path) as h:
        d = np.asarray(h["KP-DATA"].data, float)[0]
        cov = np.asarray(h["KP-COV"].data, float)[0]
    for c in cov:
        np.linalg.cholesky(c)                        # raises unless positive definite
        assert np.linalg.eigvalsh(c).min() > 0
    return float(sum(di @ np.linalg.inv(c) @ di for di, c in zip(d, cov)))


def test_written_kp_cov_inverts_to_detects_chi2(calibrated, tmp_path):
    kpd = calibrated
    assert np.linalg.matrix_rank(kpd.covariance[0]) == 9        # the model's modes only
    path = kpd.write(tmp_path / "cal.fits")
    res = detect(kpd, n_draws=1000, limits=False)
    raw = res.energy["raw"]
    assert res.energy["dof"] == 18
    # before: KP-COV as singular as the model, chi2 of order 1e14 x its dimension
    assert _chi2_by_inversion(path) == pytest.approx(raw, rel=1e-6)
    with fits.open(path) as h:
        assert h["KP-COV"].header["COVFILL"] > 1e5 * kpd.covariance.max()
        # the rows stay beside it
        np.testing.assert_allclose(rows_covariance(h["KP-COVROWS"].data), kpd.covariance,
                                   rtol=1e-12, atol=1e-20)
    # read back, the fill is taken out: detect weighs the data as before
    back = KernelPhaseData.read(path)
    np.testing.assert_allclose(back.covariance, kpd.covariance, rtol=0,
                               atol=1e-8 * kpd.covariance.max())
    again = detect(back, n_draws=1000, limits=False)
    assert again.energy["dof"] == 18
    assert again.energy["raw"] == pytest.approx(raw, rel=1e-6)


def test_definite_covariance_written_unchanged(calibrated, tmp_path):
    # a covariance that leaves nothing out is written as it is, without a fill card
    kpd = calibrated
    cov = np.stack([np.eye(kpd.n_kp) * 1e-6 * (i + 1) for i in range(kpd.n_wave)])
    one = KernelPhaseData(kpd.kp, kpd.wavelengths, kpd.pixscale, kpd.kernel_model,
                          covariance=cov, meta={"calibrated": True})
    path = one.write(tmp_path / "eye.fits")
    with fits.open(path) as h:
        assert "COVFILL" not in h["KP-COV"].header
        np.testing.assert_array_equal(h["KP-COV"].data[0], cov)
    np.testing.assert_array_equal(KernelPhaseData.read(path).covariance, cov)


@pytest.mark.realdata
@pytest.mark.slow
def test_alpha_oph_kp_cov_inverts_to_detects_chi2(real_data, tmp_path):
    """alpha Oph calibrated by eps Her (804 kernel phases, 100 + 100 frames): the model
    keeps 99 modes; inverting KP-COV gave chi2/n = 1.4e14 before."""
    from kpifs import extract_kernel_phases
    from kpifs.io import read_cube
    from kpifs.model.window import ExtractionWindow
    km = KernelModel.from_pupil(make_pupil("pharo", step=0.16 * u.m))
    kps = []
    for name in ("pharo_tgt_cube_alphaOph.fits", "pharo_ca2_cube_epsHer.fits"):
        with read_cube(real_data / name, wavelengths=[2.145] * u.um,
                       pixscale=25 * u.mas) as cube:
            frames = np.array(cube.data, float)
        kps.append(extract_kernel_phases(frames, km, wavelengths=[2.145] * u.um,
                                         pixscale=25 * u.mas, keep_phases=False,
                                         window=ExtractionWindow.default(frames.shape[-2:])))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        kpd = calibrate(kps[0], kps[1])
    path = kpd.write(tmp_path / "alphaoph_cal.fits")
    res = detect(kpd, pfa=1e-3, limits=False)
    assert res.energy["dof"] == 99
    assert _chi2_by_inversion(path) == pytest.approx(res.energy["raw"], rel=1e-6)
    assert len(res.candidates) == 1
