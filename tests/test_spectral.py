"""The spectral-model (subspace) test, the channels' correlation and the noise scale."""
import warnings

import numpy as np
import pytest
import astropy.units as u

from kpifs import KernelModel, KernelPhaseData, make_pupil
from kpifs.data import DetectionGrid
from kpifs.detect import DetectionModel, NullCalibration, detect
from kpifs.detect._laws import chi2_isf
from kpifs.detect.channels import (channel_shrinkage, combined_scale, map_noise, noise_scale,
                                   whiten_weights)
from kpifs.detect.spectral import (blackbody_contrasts, limit_subspace, smooth_basis,
                                   spectral_basis, subspace_spectrum, subspace_weights,
                                   template_basis)
from kpifs.detect.stats import auc, monte_carlo_roc
from kpifs.exceptions import KpifsError

WL = np.linspace(1.16, 2.37, 10) * u.um


@pytest.fixture(scope="module")
def coarse():
    return KernelModel.from_pupil(make_pupil("subaru", step=1.0 * u.m))


def test_smooth_basis_spans_polynomials():
    a = smooth_basis(WL, 3)
    assert np.allclose(a.T @ a, np.eye(3))
    lam = WL.value
    quad = 1 + 0.3 * lam - 0.2 * lam ** 2
    assert np.allclose(a @ (a.T @ quad), quad)          # a quadratic is in the span
    assert not np.allclose(a @ (a.T @ lam ** 3), lam ** 3)
    with pytest.raises(KpifsError, match="rank"):
        smooth_basis(WL, 0)


def test_blackbody_family_is_low_rank_and_red():
    bank = blackbody_contrasts(WL, np.linspace(600, 3000, 25) * u.K)
    assert np.all(np.diff(bank[:, 0]) > 0)              # a cool companion: redder
    basis = template_basis(bank)
    assert basis.shape[1] <= 4
    resid = bank - basis @ (basis.T @ bank)
    assert np.max(np.linalg.norm(resid, axis=0) / np.linalg.norm(bank, axis=0)) < 0.04
    assert spectral_basis("blackbody", WL).shape == (10, basis.shape[1])


def test_subspace_weights_orthonormal_under_correlation():
    rng = np.random.default_rng(3)
    n2 = rng.uniform(0.5, 2.0, (10, 4, 4))
    w = subspace_weights(n2, smooth_basis(WL, 3))
    ww = w.reshape(3, 10, -1)
    assert np.allclose(np.einsum("jik,lik->kjl", ww, ww), np.eye(3)[None], atol=1e-10)
    g = rng.standard_normal((16, 30, 10))
    corr = np.einsum("kri,krj->kij", g, g) / 30
    d = np.sqrt(np.diagonal(corr, axis1=1, axis2=2))
    corr = (corr / d[:, :, None] / d[:, None, :]).reshape(4, 4, 10, 10)
    wc = whiten_weights(w, corr, 0.0).reshape(3, 10, -1)
    cov = np.einsum("jik,kil,mlk->kjm", wc, corr.reshape(-1, 10, 10), wc)
    assert np.allclose(cov, np.eye(3)[None], atol=1e-8)


def test_subspace_false_alarms_match_chi2(coarse):
    """At a known position with independent channels, T_S is chi2_r on the half of the
    draws whose spectrum has a positive mean: its false-alarm rate at the threshold of
    ``chi2_r.sf = 2 P_FA`` matches P_FA within the Monte-Carlo error."""
    grid = DetectionGrid.from_separation(80 * u.mas, 40 * u.mas, min_sep=20 * u.mas)
    dm = DetectionModel(coarse, WL, np.eye(coarse.n_kp)[None].repeat(10, 0), grid, basis=3)
    y = np.random.default_rng(5).standard_normal((4000, 10, coarse.n_kp))
    t = dm.local_statistic(y, "S")[:, 1, 3]                 # one position
    pfa = 0.05
    rate = np.mean(t > chi2_isf(2 * pfa, 3))
    assert abs(rate - pfa) < 4 * np.sqrt(pfa * (1 - pfa) / len(t))


def test_subspace_limit_matches_noncentral_chi2():
    from kpifs.detect._laws import ncx2_sf
    n2 = np.full((6, 1, 1), 1e6)
    w = subspace_weights(n2, smooth_basis(WL[:6], 3))
    thr = chi2_isf(1e-3, 3)
    lim = float(limit_subspace(w, n2, thr, 0.5, n_draws=8192)[0, 0])
    lam = (lim * 1e3) ** 2 * 6                          # ||m||^2 of a flat spectrum
    assert ncx2_sf(thr, 3, lam) == pytest.approx(0.5, abs=0.01)


def test_roc_auc_between_np_and_binary():
    """Known position, 8 channels of a smooth spectrum: NP > S > B in AUC (the paper's
    ROC experiment with the new test)."""
    x = np.zeros((8, 20))
    x[:, 0] = np.linspace(0.6, 0.3, 8)
    res = monte_carlo_roc(x, n_draws=40000, seed=2)
    a = {k: auc(*res[k]) for k in ("NP", "S", "B")}
    assert a["NP"] > a["S"] > a["B"]


def test_detect_subspace_finds_what_b_misses(coarse):
    """A faint smooth-spectrum companion in 10 channels of white noise: the subspace
    test finds it at P_FA 1e-3, and its limits lie between NP's and about B's (with
    independent channels; correlated ones are where it gains, `test_correlated_gain`)."""
    rng = np.random.default_rng(11)
    grid = DetectionGrid.from_separation(110 * u.mas, 10 * u.mas, min_sep=30 * u.mas)
    spec = np.linspace(1.3, 0.7, 10)
    sigma = 1e-3
    # the contrast where S's limit lies, about 1.5x below B's
    dm = DetectionModel(coarse, WL, np.eye(coarse.n_kp)[None].repeat(10, 0) / sigma, grid)
    c0 = 1.1 * float(np.nanmedian(limit_subspace(dm.subspace, dm.norm2, 30.0, 0.5,
                                                 spectrum=spec)))
    kp = coarse.binary_kernel_phases([70, -50] * u.mas, c0 * spec, WL)
    kp = kp + rng.normal(0, sigma, kp.shape)
    cov = np.stack([np.eye(coarse.n_kp) * sigma ** 2] * 10)
    kpd = KernelPhaseData(kp[None], WL, 10 * u.mas, coarse, covariance=cov,
                          meta={"calibrated": True})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rs = detect(kpd, test="S", grid=grid, n_draws=2000, spectrum=spec)
    assert len(rs.candidates) == 1
    assert np.hypot(rs.candidates["fit_x"][0].value - 70, rs.candidates["fit_y"][0].value + 50) < 5
    med = {k: float(np.nanmedian(rs.limits[k])) for k in ("NP", "S", "B")}
    # with independent channels B's positivity per channel makes up for its freedom
    assert med["NP"] < med["S"] < 1.1 * med["B"]
    # the spectrum within the model is closer to the truth than the free one
    free = np.asarray(rs.candidates["fit_contrast"][0])
    model = np.asarray(rs.candidates["fit_contrast_model"][0])
    truth = c0 * spec
    assert np.linalg.norm(model - truth) < np.linalg.norm(free - truth)
    assert rs.candidates["flags"][0] == ""


def test_null_of_subspace_above_single_position(coarse):
    grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    dm = DetectionModel(coarse, WL[:4], np.eye(coarse.n_kp)[None].repeat(4, 0), grid)
    null = NullCalibration(dm, form="S", n_draws=2000, seed=1)
    assert null.threshold(0.01) > chi2_isf(0.01, 3)
    z2 = null.noise_draws()
    assert abs(np.mean(z2) - 1) < 0.02                     # the map's mean square under H0


def test_noise_scale_both_ways():
    assert noise_scale(1.7, 0.1) == 1.7
    assert noise_scale(0.5, 0.1) == pytest.approx(0.625)   # down to the upper bound
    assert noise_scale(0.95, 0.1) == 1.0
    assert combined_scale(0.5, 0.1, 2.0, 0.8) == 2.0       # the map's residual wins


def test_map_noise_sees_a_residual_on_signatures(coarse):
    grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    dm = DetectionModel(coarse, [1.6] * u.um, np.eye(coarse.n_kp)[None], grid)
    rng = np.random.default_rng(1)
    y = rng.standard_normal((1, coarse.n_kp))
    assert 0.7 < map_noise(dm, y) < 1.3
    # a residual along companions' signatures inflates the map far more than the energy
    sig = coarse.binary_kernel_phases([50, 30] * u.mas, [1.0], [1.6] * u.um)[0]
    r = y + 3 * sig / np.linalg.norm(sig)
    assert map_noise(dm, r) > 1.3 * map_noise(dm, y)


def test_channel_shrinkage_follows_the_rows():
    rng = np.random.default_rng(4)
    indep = rng.standard_normal((20, 100, 5)) / 10
    assert channel_shrinkage(indep) >= 0.5
    common = rng.standard_normal((20, 100, 1))
    shared = (0.95 * common + 0.3 * rng.standard_normal((20, 100, 5))) / 10
    assert channel_shrinkage(shared) <= 0.1


def test_subspace_spectrum_projection():
    a = smooth_basis(WL, 2)
    truth = np.linspace(2e-3, 1e-3, 10)
    noisy = truth + np.random.default_rng(2).normal(0, 2e-4, 10)
    c, e = subspace_spectrum(noisy, np.full(10, 2e-4), a)
    assert np.all(np.abs(c - truth) < 3 * e)
    assert np.all(e < 2e-4)
