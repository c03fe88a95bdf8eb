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
from kpifs.detect.limits import limit_binary, limit_np
from kpifs.detect.spectral import spectrum_shape
from kpifs.detect.spectral import (blackbody_contrasts, limit_subspace, smooth_basis,
                                   spectral_basis, subspace_spectrum, subspace_weights,
                                   template_basis)
from kpifs.detect.known_position import monte_carlo_roc
from kpifs.detect.stats import auc
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


def test_detect_subspace_finds_a_smooth_companion(coarse):
    """A smooth-spectrum companion in 10 channels of white noise: the subspace test finds
    it at P_FA 1e-3 where it is, and its spectrum within the model is closer to the truth
    than the free one.

    Machine-proof: the noise is drawn on the uv points and projected by the kernel, so it
    is white in the kernel space and the same realisation whatever orthonormal basis the
    SVD returns (the statistics are functions of ``K^T K``). At 3 times S's median limit
    the statistic's root is about 3 sqrt(threshold) ~ 15 against a unit noise: a miss
    needs a 10-sigma excursion. The fitted position's error is 0.8-1.4 mas per axis (25
    seeds); within 4.5 of its own sigmas (a chi2_2 tail of 4e-5) and within 8 mas (over
    5.7 sigmas). The model spectrum is the err-weighted projection of the free one on a
    basis that holds the truth: closer in that norm by construction."""
    rng = np.random.default_rng(11)
    grid = DetectionGrid.from_separation(110 * u.mas, 10 * u.mas, min_sep=30 * u.mas)
    spec = np.linspace(1.3, 0.7, 10)
    sigma = 1e-3
    dm = DetectionModel(coarse, WL, np.eye(coarse.n_kp)[None].repeat(10, 0) / sigma, grid)
    c0 = 3 * float(np.nanmedian(limit_subspace(dm.subspace, dm.norm2, 30.0, 0.5,
                                               spectrum=spec)))
    kp = coarse.binary_kernel_phases([70, -50] * u.mas, c0 * spec, WL)
    kp = kp + (coarse.kernel @ rng.normal(0, sigma, (coarse.n_uv, 10))).T
    cov = np.stack([np.eye(coarse.n_kp) * sigma ** 2] * 10)
    kpd = KernelPhaseData(kp[None], WL, 10 * u.mas, coarse, covariance=cov,
                          meta={"calibrated": True})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rs = detect(kpd, test="S", grid=grid, n_draws=2000, spectrum=spec, limits=False)
    assert len(rs.candidates) == 1
    row = rs.candidates[0]
    dx, dy = row["fit_x"].value - 70, row["fit_y"].value + 50
    assert np.hypot(dx / row["fit_x_err"].value, dy / row["fit_y_err"].value) < 4.5
    assert np.hypot(dx, dy) < 8
    free = np.asarray(row["fit_contrast"])
    model = np.asarray(row["fit_contrast_model"])
    err = np.asarray(row["fit_contrast_err"])
    truth = c0 * spec
    assert np.linalg.norm((model - truth) / err) <= np.linalg.norm((free - truth) / err)
    assert row["flags"] == ""


def test_subspace_limits_between_np_and_binary(coarse):
    """With independent channels (white noise) S's limits lie between NP's and B's, about
    at B's: B's positivity per channel makes up for its freedom (correlated channels are
    where S gains, `test_correlated_gain`). The limits detect() computes from the grid
    null's thresholds, here from 20 000 draws each: S/B is 0.96-0.98 over seeds (standard
    deviation 0.008), the bounds 0.9 and 1.1 over 7 of those away."""
    grid = DetectionGrid.from_separation(110 * u.mas, 10 * u.mas, min_sep=30 * u.mas)
    spec = spectrum_shape(np.linspace(1.3, 0.7, 10), 10)
    dm = DetectionModel(coarse, WL, np.eye(coarse.n_kp)[None].repeat(10, 0) * 1e3, grid)
    thr = {f: NullCalibration(dm, form=f, n_draws=20000, seed=1).threshold(1e-3)
           for f in ("B", "S")}
    med = {"NP": np.nanmedian(limit_np(dm.norm2, 1e-3, 0.5, spec)),
           "B": np.nanmedian(limit_binary(dm.norm2, thr["B"], 0.5, spectrum=spec)),
           "S": np.nanmedian(limit_subspace(dm.subspace, dm.norm2, thr["S"], 0.5,
                                            spectrum=spec))}
    assert med["NP"] < med["S"]
    assert 0.9 * med["B"] < med["S"] < 1.1 * med["B"]


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
    """The map's mean square is a quadratic form ``y^T A y``, ``A`` the mean over the grid
    of the unit signatures' outer products, of trace 1: its sum over any orthonormal basis
    of the data is 1 exactly (its mean under H0), whatever basis the kernel has. A
    residual along a companion's signature weighs 2.6 times its energy's share."""
    grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    dm = DetectionModel(coarse, [1.6] * u.um, np.eye(coarse.n_kp)[None], grid)
    n = coarse.n_kp
    turned = np.linalg.qr(np.random.default_rng(1).standard_normal((n, n)))[0]
    for basis in (np.eye(n), turned.T):
        assert sum(map_noise(dm, e[None]) for e in basis) == pytest.approx(1, abs=1e-9)
    sig = coarse.binary_kernel_phases([50, 30] * u.mas, [1.0], [1.6] * u.um)[0]
    assert n * map_noise(dm, (sig / np.linalg.norm(sig))[None]) > 2


def test_channel_shrinkage_follows_the_rows():
    rng = np.random.default_rng(4)
    indep = rng.standard_normal((20, 100, 5)) / 10
    assert channel_shrinkage(indep) >= 0.5
    common = rng.standard_normal((20, 100, 1))
    shared = (0.95 * common + 0.3 * rng.standard_normal((20, 100, 5))) / 10
    assert channel_shrinkage(shared) <= 0.1


def test_subspace_spectrum_projection():
    """The projection's errors are its scatter: over 4000 noise draws each channel is within
    its 1-sigma error in 68.27 % of them (binomial standard deviation 0.74 %: the bound,
    3.5 %, is 4.7 of them, a false failure of 3e-6 per channel) and is unbiased; the errors
    are below the free ones (the model has two dimensions for ten channels)."""
    a = smooth_basis(WL, 2)
    truth = np.linspace(2e-3, 1e-3, 10)
    noisy = truth + np.random.default_rng(2).normal(0, 2e-4, (4000, 10))
    fits = [subspace_spectrum(n, np.full(10, 2e-4), a) for n in noisy]
    c, e = np.array([f[0] for f in fits]), fits[0][1]
    assert np.all(np.abs(np.mean(np.abs(c - truth) < e, axis=0) - 0.6827) < 0.035)
    assert np.all(np.abs(np.mean(c - truth, axis=0)) < 4.7 * e / np.sqrt(len(c)))
    assert np.all(e < 2e-4)


def test_subspace_limit_does_not_depend_on_eigenvector_signs(monkeypatch):
    """The correlated noise of the subspace limit is drawn through the symmetric square
    root of its covariance: eigenvectors returned with other signs (as another CPU's
    LAPACK may) give the same limits, not another set of draws."""
    rng = np.random.default_rng(11)
    q, r, npos = 6, 3, 40
    n2 = rng.uniform(1e5, 1e6, (q, 5, 8))
    w = rng.normal(0, 1, (r, q, 5, 8))
    x = rng.normal(0, 1, (npos, q, q))
    corr = (np.matmul(x, x.transpose(0, 2, 1)) / q + np.eye(q)).reshape(5, 8, q, q)
    before = limit_subspace(w, n2, 12.0, 0.5, correlation=corr)
    eigh = np.linalg.eigh

    def flipped(a):
        val, vec = eigh(a)
        return val, vec * np.where(np.arange(vec.shape[-1]) % 2, -1.0, 1.0)
    monkeypatch.setattr(np.linalg, "eigh", flipped)
    after = limit_subspace(w, n2, 12.0, 0.5, correlation=corr)
    assert np.all(np.isfinite(before))
    assert np.allclose(after, before, rtol=1e-10)


def test_np_correlated_power_is_that_of_the_pseudo_inverse():
    # full-rank correlations by one solve, rank-deficient ones by pinv: m^T C^+ m either way
    from kpifs.detect.channels import _pinv_power
    rng = np.random.default_rng(1)
    x = rng.standard_normal((40, 5, 8))
    c = x.transpose(0, 2, 1) @ x                          # rank 5 of 8
    c[:15] = np.eye(8) + 0.1                               # full rank
    m = rng.random((40, 8))
    ref = np.einsum("ni,nij,nj->n", m, np.linalg.pinv(c, rcond=1e-9, hermitian=True), m)
    np.testing.assert_allclose(_pinv_power(c, m), ref, rtol=1e-12)
    inv = np.linalg.inv(np.eye(8) + 0.1)
    np.testing.assert_allclose(_pinv_power(c[:15], m[:15]),
                               np.einsum("ni,ij,nj->n", m[:15], inv, m[:15]), rtol=1e-12)


def test_annulus_expectation_follows_the_channels_correlation(coarse):
    # `annulus_noise`'s expectation is kept on the model, and taken again when the
    # channels' correlation changes: the same maps as a model made afresh
    from kpifs.detect.channels import annulus_noise
    grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    w = np.stack([np.eye(coarse.n_kp)] * 3)
    dm = DetectionModel(coarse, [1.5, 1.6, 1.7] * u.um, w, grid)
    y = np.random.default_rng(2).standard_normal((3, coarse.n_kp))
    rows = np.random.default_rng(3).standard_normal((40, 3, coarse.n_kp)) / 40 ** 0.5
    first = [annulus_noise(dm, y, subspace=s) for s in (False, True)]
    dm.correlate(rows * 2)
    fresh = DetectionModel(coarse, [1.5, 1.6, 1.7] * u.um, w, grid)
    fresh.correlate(rows * 2)
    v = grid.valid
    for s, before in zip((False, True), first):
        after = annulus_noise(dm, y, subspace=s)
        assert np.array_equal(after, annulus_noise(fresh, y, subspace=s), equal_nan=True)
        assert np.all(after[v] < 0.5 * before[v])            # four times the variance


def test_dot_maps_of_one_data_set_kept_and_copied(coarse):
    # kept for the next calls (a search projects one residual several times): the same
    # numbers as made afresh, and a caller's change to its copy does not reach the next
    grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    dm = DetectionModel(coarse, [1.5, 1.6] * u.um, np.stack([np.eye(coarse.n_kp)] * 2), grid)
    y = np.random.default_rng(5).standard_normal((2, coarse.n_kp))
    first = dm.dot_maps(y)
    first[:] = 0.0
    again = dm.dot_maps(y)
    assert np.array_equal(again, dm._dot_maps(y)) and np.abs(again).max() > 0
    both = dm.dot_maps(np.stack([y, 2 * y]))              # several data sets: not kept
    np.testing.assert_allclose(both, np.stack([again, 2 * again]), rtol=1e-12, atol=1e-12)
