import warnings

import numpy as np
import pytest
import astropy.units as u

from kpifs import KernelPhaseData, KpifsError, KpifsWarning, extract_kernel_phases
from kpifs.calibration.calibrate import calibrate
from kpifs.calibration.pixelnoise import propagated_covariance
from kpifs.covariance import (empirical_covariance, hartlap_factor, ledoit_wolf,
                              whiten, whitening_matrix)
from kpifs.simulation.simulate import simulate_psf

PIX = 10.42 * u.mas
WL = [1.52, 1.60, 1.68] * u.um
PHOTONS = 3e6
READ = 10.0


@pytest.fixture(scope="module")
def psf():
    return simulate_psf("subaru", WL, pixscale=PIX, shape=(40, 40), npup=96)


def noise_frames(psf, n, seed):
    """Companion-free frames with photon and read noise only (electrons)."""
    rng = np.random.default_rng(seed)
    frames = rng.poisson(psf[None] * PHOTONS, size=(n,) + psf.shape).astype(float)
    frames += rng.normal(0, READ, frames.shape)
    return frames


@pytest.fixture(scope="module")
def coarse_model():
    """0.8 m grid: uv points no denser than the 40x40 field resolves (lambda/FOV ~ 0.75 m),
    so the kernel phases are linearly independent and their covariance well conditioned."""
    from kpifs import KernelModel, make_pupil
    return KernelModel.from_pupil(make_pupil("subaru", step=0.8 * u.m))


@pytest.fixture(scope="module")
def noise_kp(psf, coarse_model):
    a = extract_kernel_phases(noise_frames(psf, 3000, 1), coarse_model, wavelengths=WL,
                              pixscale=PIX, centres=(20, 20), keep_phases=False)
    b = extract_kernel_phases(noise_frames(psf, 1000, 2), coarse_model, wavelengths=WL,
                              pixscale=PIX, centres=(20, 20), keep_phases=False)
    return a, b


def test_small_field_limits_independent_kernels(psf, subaru_model):
    """The paper's 40x40 field cannot resolve a 0.38 m uv grid: low-rank covariance."""
    a = extract_kernel_phases(noise_frames(psf, 1500, 7)[:, :1], subaru_model, wavelengths=WL[:1],
                              pixscale=PIX, centres=(20, 20), keep_phases=False)
    w, rank = whitening_matrix(empirical_covariance(a.kp), return_rank=True)
    assert 120 < rank[0] < 0.8 * subaru_model.n_kp
    y = whiten(a.kp - a.kp.mean(0), w)
    # the kept modes are white, the dropped ones are zero
    assert np.mean(np.sum(y ** 2, axis=2)) == pytest.approx(rank[0], rel=0.02)


def test_ledoit_wolf_matches_brute_force():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((15, 6)) @ np.diag([1, 2, 3, 1, 1, 0.5])
    cov, s = ledoit_wolf(x)
    xc = x - x.mean(0)
    n, p = x.shape
    samp = xc.T @ xc / n
    mu = np.trace(samp) / p
    b2 = sum(np.sum((np.outer(v, v) - samp) ** 2) for v in xc) / n ** 2
    d2 = np.sum((samp - mu * np.eye(p)) ** 2)
    assert s == pytest.approx(min(b2, d2) / d2)
    np.testing.assert_allclose(cov, (1 - s) * samp + s * mu * np.eye(p))


def test_shrinkage_helps_when_frames_are_few():
    rng = np.random.default_rng(3)
    p, n = 80, 40
    true = np.diag(np.linspace(0.5, 2, p))
    x = rng.multivariate_normal(np.zeros(p), true, size=n)
    with pytest.warns(KpifsWarning, match="40 frames for 80 kernel phases"):
        shrunk = empirical_covariance(x[:, None, :])[0]
    sample = np.cov(x, rowvar=False)
    assert np.linalg.norm(shrunk - true) < 0.5 * np.linalg.norm(sample - true)
    assert np.all(np.linalg.eigvalsh(shrunk) > 0)
    assert whitening_matrix(shrunk, return_rank=True)[1] == p     # invertible
    # the sample covariance of 40 frames has rank 39: whitening keeps 39 modes
    assert whitening_matrix(sample, return_rank=True)[1] == n - 1
    with pytest.raises(KpifsError, match="not positive"):
        whitening_matrix(np.array([[1.0, 2.0], [2.0, 1.0]]))
    # with many frames no shrinkage and no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        big = empirical_covariance(rng.standard_normal((400, 1, 20)))
    assert big.shape == (1, 20, 20)


def test_whitened_noise_is_white(noise_kp):
    """Sigma from 3000 frames whitens 1000 independent frames: mean 0, covariance I.

    With an estimated Sigma, E||y||^2 / p = (N-1)/(N-p-2) (inverse-Wishart mean).
    """
    a, b = noise_kp
    p = a.n_kp
    cov = empirical_covariance(a.kp)
    w, rank = whitening_matrix(cov, return_rank=True)
    assert np.all(rank == p)
    y = whiten(b.kp - a.kp.mean(0), w)          # (1000, 3, p)
    n_a = a.n_frame
    expected = (n_a - 1) / (n_a - p - 2)
    per_channel = np.mean(np.sum(y ** 2, axis=2), axis=0) / p
    np.testing.assert_allclose(per_channel, expected, rtol=0.03)
    # mean ~ 0: each whitened mean, scaled by sqrt(N_b), is ~N(0, expected (1 + N_b/N_a))
    # (the reference mean of set a is itself noisy)
    z = y.mean(0) * np.sqrt(b.n_frame) / np.sqrt(expected * (1 + b.n_frame / n_a))
    assert abs(np.mean(z)) < 4 / np.sqrt(z.size)
    assert np.std(z) == pytest.approx(1, abs=0.1)
    # covariance ~ I: off-diagonal correlations at the sampling level 1/sqrt(N)
    c = np.cov(y[:, 1], rowvar=False) / expected
    off = c[~np.eye(p, dtype=bool)]
    assert np.std(off) < 2 / np.sqrt(b.n_frame)


def test_joint_whitening(noise_kp):
    a, b = noise_kp
    jcov = empirical_covariance(a.kp, joint=True)
    nw, p = a.n_wave, a.n_kp
    assert jcov.shape == (nw * p, nw * p)
    # channels are independent here: off-diagonal blocks are at the sampling level
    block01 = jcov[:p, p:2 * p] / np.sqrt(np.outer(np.diag(jcov)[:p], np.diag(jcov)[p:2 * p]))
    assert np.std(block01) < 2 / np.sqrt(a.n_frame)
    y = whiten(b.kp - a.kp.mean(0), whitening_matrix(jcov))
    expected = (a.n_frame - 1) / (a.n_frame - nw * p - 2)
    assert np.mean(np.sum(y ** 2, axis=(1, 2))) / (nw * p) == pytest.approx(expected, rel=0.03)


def test_propagated_matches_empirical(psf, noise_kp):
    a, _ = noise_kp
    var = psf * PHOTONS + READ ** 2
    cov = propagated_covariance(psf * PHOTONS, var, a.kernel_model, wavelengths=WL,
                                pixscale=PIX, centres=(20, 20),
                                window=a.window)
    emp = empirical_covariance(a.kp)
    ratio = np.diagonal(emp, axis1=1, axis2=2) / np.diagonal(cov, axis1=1, axis2=2)
    # each empirical variance from 3000 frames has a relative error of sqrt(2/3000) = 2.6 %
    assert np.median(ratio) == pytest.approx(1, abs=0.05)
    assert np.percentile(ratio, 95) < 1.15 and np.percentile(ratio, 5) > 0.85
    # the correlations agree too
    i, j = np.triu_indices(a.n_kp, 1)
    c_emp = emp[1][i, j] / np.sqrt(emp[1][i, i] * emp[1][j, j])
    c_pro = cov[1][i, j] / np.sqrt(cov[1][i, i] * cov[1][j, j])
    assert np.corrcoef(c_emp, c_pro)[0, 1] > 0.8


def test_calibration_covariance_and_null_chi2(psf, coarse_model):
    """Calibrated companion-free data: chi2 against zero follows chi2_p."""
    chi2 = []
    for seed in range(6):
        t = extract_kernel_phases(noise_frames(psf, 400, 10 + seed), coarse_model,
                                  wavelengths=WL, pixscale=PIX,
                                  centres=(20, 20), keep_phases=False, source=f"t{seed}")
        c = extract_kernel_phases(noise_frames(psf, 600, 100 + seed), coarse_model,
                                  wavelengths=WL, pixscale=PIX, centres=(20, 20),
                                  keep_phases=False, source=f"c{seed}")
        raw = calibrate(t, c, debias=False, error_model="frames")
        np.testing.assert_allclose(raw.covariance, empirical_covariance(t.kp) / 400
                                   + empirical_covariance(c.kp) / 600)
        res = calibrate(t, c, error_model="frames")   # debiased: whitened variance 1 on average
        h = res.covariance[0, 0, 0] / raw.covariance[0, 0, 0]
        # Welch-Satterthwaite: ~400 + 600 - 2 effective frames
        assert hartlap_factor(1000, t.n_kp) < h < hartlap_factor(800, t.n_kp)
        np.testing.assert_allclose(res.covariance, h * raw.covariance)
        assert res.meta["calibrators"] == [f"c{seed}"]
        # the covariance rows reproduce the per-channel covariance blocks
        r = res.covariance_rows
        np.testing.assert_allclose(np.einsum("nwi,nwj->wij", r, r), res.covariance)
        y = whiten(res.kp[0], whitening_matrix(res.covariance))
        chi2.append(np.sum(y ** 2, axis=1))
    p = coarse_model.n_kp
    chi2 = np.array(chi2).ravel() / p
    # 18 draws of chi2_p / p with a debiased estimated covariance: mean 1,
    # standard error sqrt(2/p/18) = 3.9 %
    assert np.mean(chi2) == pytest.approx(1.0, abs=3 * np.sqrt(2 / p / 18))


def test_several_calibrators_average(subaru_model):
    rng = np.random.default_rng(5)

    def kpd(mean, n, name):
        return KernelPhaseData(rng.normal(mean, 0.01, (n, 2, subaru_model.n_kp)),
                               [1.6, 1.7] * u.um, PIX, subaru_model, meta={"source": name})
    tgt = kpd(0.05, 800, "tgt")
    cals = [kpd(0.01, 800, "c1"), kpd(0.03, 800, "c2")]
    res = calibrate(tgt, cals, debias=False, error_model="frames")
    assert np.mean(res.kp) == pytest.approx(0.03, abs=1e-3)
    # variance of the calibrated mean: s^2/N_t + (s^2/N_1 + s^2/N_2) / 4
    expected = 1e-4 / 800 + (1e-4 / 800 + 1e-4 / 800) / 4
    assert np.mean(np.diagonal(res.covariance, axis1=1, axis2=2)) == pytest.approx(expected,
                                                                                   rel=0.05)
    assert res.meta["calibrators"] == ["c1", "c2"]


def test_incompatible_calibrators(subaru_model):
    from kpifs import KernelModel, make_pupil
    base = KernelPhaseData(np.zeros((3, 2, subaru_model.n_kp)), [1.6, 1.7] * u.um, PIX,
                           subaru_model, meta={"source": "target.fits"})
    other_wl = KernelPhaseData(np.zeros((3, 2, subaru_model.n_kp)), [1.6, 1.8] * u.um, PIX,
                               subaru_model, meta={"source": "cal.fits"})
    other_ps = KernelPhaseData(np.zeros((3, 2, subaru_model.n_kp)), [1.6, 1.7] * u.um,
                               12 * u.mas, subaru_model, meta={"source": "cal.fits"})
    km2 = KernelModel.from_pupil(make_pupil("subaru", step=0.5 * u.m))
    other_km = KernelPhaseData(np.zeros((3, 2, km2.n_kp)), [1.6, 1.7] * u.um, PIX, km2,
                               meta={"source": "cal.fits"})
    with pytest.raises(KpifsError, match="cal.fits has channels"):
        calibrate(base, other_wl)
    with pytest.raises(KpifsError, match="cal.fits has pixel scale"):
        calibrate(base, other_ps)
    with pytest.raises(KpifsError, match="another kernel model"):
        calibrate(base, other_km)
    with pytest.raises(KpifsError, match="no calibrator"):
        calibrate(base, [])


def test_kpfits_round_trip_with_covariance(tmp_path, subaru_model):
    rng = np.random.default_rng(2)
    t = KernelPhaseData(rng.normal(0, 0.01, (30, 2, subaru_model.n_kp)), [1.6, 1.7] * u.um,
                        PIX, subaru_model, meta={"source": "t.fits"})
    c = KernelPhaseData(rng.normal(0, 0.01, (30, 2, subaru_model.n_kp)), [1.6, 1.7] * u.um,
                        PIX, subaru_model, meta={"source": "c.fits"})
    with pytest.warns(KpifsWarning, match="shrinkage"):
        res = calibrate(t, c, joint=True, error_model="frames")
    path = tmp_path / "cal.fits"
    res.write(path, inputs=["t.fits"])
    back = KernelPhaseData.read(path)
    np.testing.assert_allclose(back.kp, res.kp)
    np.testing.assert_allclose(back.covariance, res.covariance)
    np.testing.assert_allclose(back.joint_covariance, res.joint_covariance)
    assert back.meta["calibrated"] and back.meta["calibrators"] == ["c.fits"]
    from astropy.io import fits
    with fits.open(path) as h:
        assert h["KP-COV"].data.shape == (1, 2, subaru_model.n_kp, subaru_model.n_kp)
        assert h["KP-SIGM"].data.shape == (1, 2, subaru_model.n_kp)
        assert h[0].header["KPCAL1"] == "c.fits" and h[0].header["CALFLAG"]


def test_whitening_bad_input():
    with pytest.raises(KpifsError, match="not symmetric"):
        whitening_matrix(np.array([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(KpifsError, match="NaN"):
        whitening_matrix(np.array([[1.0, np.nan], [np.nan, 1.0]]))
    with pytest.raises(KpifsError, match="does not fit"):
        whiten(np.zeros((2, 3)), np.eye(4))
