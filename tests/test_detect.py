import numpy as np
import pytest
import astropy.units as u
from astropy.io import fits
from scipy import stats

from kpifs import KernelModel, KernelPhaseData, KpifsError, make_pupil
from kpifs.calibration.calibrate import calibrate
from kpifs.data import DetectionGrid
from kpifs.detect import DetectionModel, NullCalibration, detect
from kpifs.detect.limits import (chi2_ratio_sigma, energy_lambda, limit_binary, limit_energy,
                                 limit_np, pfa_to_sigma, sigma_to_pfa)
from kpifs.detect.known_position import monte_carlo_roc
from kpifs.detect.stats import (auc, binary_pfa, binary_threshold, energy_pd, energy_threshold,
                                np_pd, np_threshold)

WL3 = [1.52, 1.60, 1.68] * u.um


# --- reference numbers (REFERENCE_NUMBERS.md) ---------------------------------------
def test_neyman_pearson_reference():
    assert np_threshold(0.01, 3) == pytest.approx(6.9790, abs=1e-4)
    assert np_pd(0.01, 3) == pytest.approx(0.7497, abs=1e-4)
    assert np_threshold(1e-3, 3) == pytest.approx(9.2707, abs=1e-4)
    assert np_pd(1e-3, 3) == pytest.approx(0.4641, abs=1e-4)
    for norm, a in zip([0.5, 1, 2, 3, 4], [0.63816, 0.76025, 0.92135, 0.98305, 0.99766]):
        assert stats.norm.cdf(norm / np.sqrt(2)) == pytest.approx(a, abs=1e-5)


@pytest.mark.parametrize("p, values", [(303, (363.191, 384.803, 442.460)),
                                       (909, (1011.122, 1046.480, 1138.414))])
def test_energy_thresholds_reference(p, values):
    for pfa, v in zip((0.01, 1e-3, sigma_to_pfa(5)), values):   # "5 sigma": 2.8665e-7
        assert energy_threshold(pfa, p) == pytest.approx(v, abs=2e-3)


def test_energy_pd_reference():
    assert energy_pd(0.01, 303, 3) == pytest.approx(0.0258, abs=1e-4)


def test_binary_laws_reference():
    # one channel: max(z, 0) has the NP threshold
    assert binary_threshold(0.01, 1, "B-paper") == pytest.approx(2.3263, abs=1e-4)
    assert np.sqrt(binary_threshold(0.01, 1, "B")) == pytest.approx(2.3263, abs=1e-4)
    # three channels
    assert binary_threshold(0.01, 3, "B") == pytest.approx(8.7464, abs=1e-3)
    assert binary_threshold(0.01, 3, "B-paper") == pytest.approx(4.1544, abs=2e-3)
    assert binary_threshold(1e-3, 3, "B-paper") == pytest.approx(5.3936, abs=2e-3)
    assert binary_pfa(8.7464, 3, "B") == pytest.approx(0.01, rel=1e-3)


@pytest.mark.parametrize("pfa, pd, np_, ed303, ed909", [
    (0.01, 0.5, 2.3263, 7.807, 10.141), (0.01, 0.9, 3.6079, 10.016, 12.862),
    (1e-3, 0.5, 3.0902, 9.088, 11.757), (1e-3, 0.9, 4.3718, 11.125, 14.236),
    (2.8665e-7, 0.5, 5.0000, 11.844, 15.172)])
def test_limit_constants_reference(pfa, pd, np_, ed303, ed909):
    one = np.ones((1, 1, 1))
    assert limit_np(one, pfa, pd)[0, 0] == pytest.approx(np_, abs=2e-4)
    assert np.sqrt(energy_lambda(pfa, pd, 303)) == pytest.approx(ed303, abs=2e-3)
    assert np.sqrt(energy_lambda(pfa, pd, 909)) == pytest.approx(ed909, abs=2e-3)
    assert limit_energy(one, pfa, pd, 303)[0, 0] == pytest.approx(ed303, abs=2e-3)


def test_three_channels_versus_one():
    one, three = np.ones((1, 1, 1)), np.ones((3, 1, 1))
    assert (limit_np(three, 0.01, 0.5) / limit_np(one, 0.01, 0.5))[0, 0] == \
        pytest.approx(0.5774, abs=1e-4)
    ratio = (limit_energy(three, 0.01, 0.5, 909) / limit_energy(one, 0.01, 0.5, 303))[0, 0]
    assert 0.74 <= ratio <= 0.75


def test_binary_limit_one_channel_equals_np():
    lim = limit_binary(np.full((1, 2, 2), 4.0), binary_threshold(0.01, 1, "B"), 0.5)
    np.testing.assert_allclose(lim, 2.3263 / 2, rtol=3e-3)


def test_sigma_converters():
    assert sigma_to_pfa(5) == pytest.approx(2.8665e-7, rel=1e-4)
    assert pfa_to_sigma(2.8665e-7) == pytest.approx(5, abs=1e-4)
    # interferometry's chi2-ratio "3 sigma" with 303 kernels needs ||x|| ~ 8.54
    assert chi2_ratio_sigma(1 + 8.54 ** 2 / 303, 1.0, 303) == pytest.approx(3, abs=0.02)


# --- Monte-Carlo against theory ----------------------------------------------------
def test_monte_carlo_false_alarms_match_theory():
    rng = np.random.default_rng(11)
    x = rng.standard_normal((3, 101))
    x *= 2.5 / np.linalg.norm(x)
    n = 30000
    res = monte_carlo_roc(x, n_draws=n, seed=5)
    sigma_mc = np.sqrt(0.01 * 0.99 / n)
    t0, t1 = res["NP"]
    assert np.mean(t0 > np_threshold(0.01, 2.5)) == pytest.approx(0.01, abs=3 * sigma_mc)
    pd = np_pd(0.01, 2.5)
    assert np.mean(t1 > np_threshold(0.01, 2.5)) == pytest.approx(
        pd, abs=3 * np.sqrt(pd * (1 - pd) / n))
    t0, t1 = res["E"]
    thr = energy_threshold(0.01, 303)
    assert np.mean(t0 > thr) == pytest.approx(0.01, abs=3 * sigma_mc)
    pd = energy_pd(0.01, 303, 2.5)
    assert np.mean(t1 > thr) == pytest.approx(pd, abs=3 * np.sqrt(pd * (1 - pd) / n))
    for form in ("B", "B-paper"):
        t0, _ = res[form]
        assert np.mean(t0 > binary_threshold(0.01, 3, form)) == pytest.approx(
            0.01, abs=3 * sigma_mc)
    assert auc(*res["NP"]) == pytest.approx(stats.norm.cdf(2.5 / np.sqrt(2)), abs=0.003)


@pytest.fixture(scope="module")
def small_model():
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
    grid = DetectionGrid.from_separation(150 * u.mas, 10 * u.mas, min_sep=25 * u.mas)
    w = np.stack([np.eye(km.n_kp) * 1e3] * 3)
    return DetectionModel(km, WL3, w, grid)


@pytest.mark.parametrize("form", ["B", "B-paper", "NP"])
def test_grid_search_threshold_controls_global_false_alarms(small_model, form):
    """The MC-calibrated sup threshold gives the nominal global P_FA on fresh data, computed
    through the separable map (an independent code path from the calibration)."""
    thr = NullCalibration(small_model, form=form, n_draws=20000, seed=1).threshold(0.01)
    n = 6000
    y = np.random.default_rng(77).standard_normal((n, 3, small_model.kernel_model.n_kp))
    t = small_model.local_statistic(y, form)
    maxima = np.nanmax(t.reshape(n, -1), axis=1)
    rate = np.mean(maxima > thr)
    assert rate == pytest.approx(0.01, abs=3 * np.sqrt(0.01 * 0.99 / n))


def test_grid_search_with_correlated_channels(small_model):
    """With covariance rows (channels correlated), the threshold follows the correlation."""
    rng = np.random.default_rng(3)
    p = small_model.kernel_model.n_kp
    common = rng.standard_normal((400, 1, p))
    rows = (0.9 * common + np.sqrt(1 - 0.81) * rng.standard_normal((400, 3, p))) / 20
    thr_corr = NullCalibration(small_model, n_draws=20000, seed=2, noise_rows=rows).threshold(0.01)
    thr_ind = NullCalibration(small_model, n_draws=20000, seed=2).threshold(0.01)
    assert thr_corr > 1.3 * thr_ind
    # fresh correlated data: nominal rate
    n = 4000
    y = np.einsum("mn,nwp->mwp", rng.standard_normal((n, 400)), rows)
    maxima = np.nanmax(small_model.local_statistic(y).reshape(n, -1), axis=1)
    assert np.mean(maxima > thr_corr) == pytest.approx(0.01, abs=3 * np.sqrt(0.01 * 0.99 / n))


def test_map_finds_injected_signal(small_model):
    km = small_model.kernel_model
    c = np.array([3e-3, 2.5e-3, 2e-3])
    kp = km.binary_kernel_phases([60, -40] * u.mas, c, WL3)
    y = np.einsum("wij,wj->wi", small_model.whitening, kp)
    t = small_model.local_statistic(y)
    iy, ix = np.unravel_index(np.nanargmax(t), t.shape)
    assert (small_model.grid.X[iy, ix], small_model.grid.Y[iy, ix]) == (60, -40)
    cm, err = small_model.contrast_maps(y)
    np.testing.assert_allclose(cm[:, iy, ix], c, rtol=0.02)


def test_maps_equal_per_position_reference(small_model):
    """The two-product map equals s_i^T y_i computed position by position."""
    from kpifs.model.kernel import MAS
    km = small_model.kernel_model
    y = np.random.default_rng(1).standard_normal((3, km.n_kp))
    fast = small_model.dot_maps(y)
    g = small_model.grid
    for (iy, ix) in [(3, 4), (10, 20), (25, 7)]:
        for i, lam in enumerate(WL3.to_value(u.m)):
            theta = 2 * np.pi * (g.X[iy, ix] * km.uv.value[:, 0]
                                 + g.Y[iy, ix] * km.uv.value[:, 1]) * MAS / lam
            s = small_model.whitening[i] @ km.kernel @ np.sin(-theta)
            assert fast[i, iy, ix] == pytest.approx(s @ y[i], rel=1e-9)
            assert small_model.norm2[i, iy, ix] == pytest.approx(s @ s, rel=1e-9)


# --- the whole chain -----------------------------------------------------------------
def _files_to_kp(tmp_path, seed, contrasts, n_frames):
    from kpifs.extraction.extract import extract_kernel_phases
    from kpifs.io import read_cube, write_observation
    from kpifs.simulation.simulate import simulate_scene
    obs = simulate_scene("paper", n_frames=n_frames, seed=seed, npup=96, exptime=1 * u.s,
                         contrasts=contrasts)
    files = write_observation(obs, tmp_path / f"sim{seed}")
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
    out = {}
    for role in ("target", "calibrator"):
        with read_cube(files[role]) as cube:
            out[role] = extract_kernel_phases(cube.data, km, wavelengths=cube.wavelengths,
                                              pixscale=cube.pixscale, header=cube.header,
                                              source=cube.name)
    return obs, out


@pytest.mark.slow
def test_injected_companion_recovered(tmp_path):
    contrasts = np.array([1.3, 1.0, 0.7]) * 6.31e-4
    obs, kp = _files_to_kp(tmp_path, 21, contrasts, 400)
    res = detect(calibrate(kp["target"], kp["calibrator"]), pfa=1e-3, n_draws=10000, seed=4)
    assert len(res.candidates) >= 1
    best = res.candidates[0]
    step = abs(res.grid.step[0])
    assert abs(best["x"].to_value(u.mas) - 80) <= step
    assert abs(best["y"].to_value(u.mas) - 60) <= step
    fitted, err = np.asarray(best["fit_contrast"]), np.asarray(best["fit_contrast_err"])
    assert np.all(np.abs(fitted - contrasts) < 3 * err), (fitted, err, contrasts)
    assert abs(best["fit_x"].to_value(u.mas) - 80) < 5
    assert abs(best["fit_y"].to_value(u.mas) - 60) < 5


@pytest.mark.slow
def test_no_candidate_without_companion(tmp_path):
    _, kp = _files_to_kp(tmp_path, 22, 0.0, 400)
    res = detect(calibrate(kp["target"], kp["calibrator"]), pfa=1e-3, n_draws=10000, seed=4)
    assert len(res.candidates) == 0
    assert np.nanmin(res.pfa_global) > 1e-3


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:.*Ledoit-Wolf shrinkage")
def test_roc_experiment_small():
    from kpifs.detect.roc import paper_experiment
    tab, curves = paper_experiment(n_frames=150, n_draws=20000, seed=3, npup=64)
    n = 20000
    rows = {(r["channels"], r["test"]): r for r in tab}
    for (chans, test), r in rows.items():
        if test in ("NP", "E", "S"):
            pd = r["pd_theory"]
            assert abs(r["pd"] - pd) < 4 * np.sqrt(max(pd * (1 - pd), 0.01 * 0.99) / n) + 0.01
            assert r["auc"] == pytest.approx(r["auc_theory"], abs=0.01)
    singles = [k for k in {c for c, _ in rows} if k != "all"]
    assert all(rows[("all", "NP")]["auc"] > rows[(s, "NP")]["auc"] for s in singles)
    for chans in ["all"] + singles:
        assert rows[(chans, "NP")]["auc"] >= rows[(chans, "B")]["auc"] - 0.002
        assert rows[(chans, "B")]["auc"] >= rows[(chans, "E")]["auc"]
        assert rows[(chans, "B-paper")]["auc"] >= rows[(chans, "E")]["auc"]
    # the spectral-model test lies between the two extremes on all channels
    assert rows[("all", "NP")]["auc"] >= rows[("all", "S")]["auc"] >= rows[("all", "B")]["auc"]


# --- products, CLI and bad input -------------------------------------------------------
@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    rng = np.random.default_rng(8)
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
    sig = 1e-3
    c = np.array([4e-3, 3e-3, 2e-3])
    truth = km.binary_kernel_phases([70, 40] * u.mas, c, WL3)
    frames = lambda n: rng.normal(0, sig, (n, 3, km.n_kp))  # noqa: E731
    tgt = KernelPhaseData(frames(600) + truth, WL3, 10.42 * u.mas, km, meta={"source": "t"})
    cal = KernelPhaseData(frames(600), WL3, 10.42 * u.mas, km, meta={"source": "c"})
    d = tmp_path_factory.mktemp("kp")
    tgt.write(d / "t.fits")
    cal.write(d / "c.fits")
    return d


def test_detect_cli_products(calibrated, tmp_path, capsys):
    from kpifs.cli import main
    out = tmp_path / "det.fits"
    assert main(["detect", str(calibrated / "t.fits"), "--calibrator", str(calibrated / "c.fits"),
                 "--pfa", "1e-3", "--draws", "5000", "--max-sep", "150mas", "--step", "10mas",
                 "--plots", str(tmp_path / "figs"), "-o", str(out), "-q"]) == 0
    assert "1 candidate(s)" in capsys.readouterr().out
    with fits.open(out) as h:
        names = [x.name for x in h]
        for ext in ("DETECTION", "PFA", "CONTRAST", "CONTRAST_ERR", "LIMIT", "CURVES",
                    "CANDIDATES"):
            assert ext in names
        hdr = h[0].header
        # three channels: S's quadratic model has as many dimensions, so 'auto' picks B
        assert hdr["TEST"] == "B" and hdr["PFA"] == 1e-3 and hdr["PD"] == 0.5
        assert hdr["KPIFSVER"] and hdr["KPCAL1"].endswith("c.fits")
        assert h["CONTRAST"].data.shape[0] == 3
        from astropy.wcs import WCS
        w = WCS(h["DETECTION"].header)
        ny, nx = h["DETECTION"].data.shape
        x0, y0 = w.pixel_to_world_values((nx - 1) / 2, (ny - 1) / 2)
        assert abs(x0) < 1e-9 and abs(y0) < 1e-9          # map centre = the star
        cand = h["CANDIDATES"].data
        assert abs(cand["x"][0] - 70) <= 10 and abs(cand["y"][0] - 40) <= 10
        np.testing.assert_allclose(cand["fit_contrast"][0], [4e-3, 3e-3, 2e-3], rtol=0.1)
        curves = h["CURVES"].data
        assert {"separation", "NP_median", "B_median", "E_median"} <= set(curves.names)
        assert np.all(curves["NP_median"] <= curves["E_median"])
    assert (tmp_path / "figs" / "detection_map.png").exists()
    assert main(["info", str(out)]) == 0
    assert "1 candidate(s)" in capsys.readouterr().out


@pytest.mark.parametrize("extra, match", [
    (["--pfa", "1.5"], "P_FA must be in (0, 1)"),
    (["--pd", "0"], "P_D must be in (0, 1)"),
    (["--max-sep", "2000mas"], "beyond the"),
    (["--spectrum", "1,2"], "2 values for 3 channels"),
])
def test_detect_bad_input(calibrated, tmp_path, capsys, extra, match):
    from kpifs.cli import main
    out = tmp_path / "det.fits"
    code = main(["detect", str(calibrated / "t.fits"), "--calibrator",
                 str(calibrated / "c.fits"), "--draws", "2000", "-o", str(out), "-q", *extra])
    assert code == 2
    assert match in capsys.readouterr().err
    assert not out.exists()


def test_detect_rejects_bad_covariance_and_channels(subaru_model):
    kpd = KernelPhaseData(np.zeros((1, 3, subaru_model.n_kp)), WL3, 10.42 * u.mas,
                          subaru_model, covariance=-np.stack([np.eye(subaru_model.n_kp)] * 3),
                          meta={"calibrated": True})
    with pytest.raises(KpifsError, match="not positive"):
        detect(kpd, n_draws=1000)
    kpd.meta["calibrated"] = False
    with pytest.raises(KpifsError, match="not calibrated.*--allow-uncalibrated"):
        detect(kpd, n_draws=1000)
    with pytest.raises(KpifsError, match="at least 1000"):
        detect(kpd, n_draws=10, allow_uncalibrated=True)
    t = KernelPhaseData(np.zeros((5, 3, subaru_model.n_kp)), WL3, 10.42 * u.mas, subaru_model)
    c = KernelPhaseData(np.zeros((5, 2, subaru_model.n_kp)), WL3[:2], 10.42 * u.mas,
                        subaru_model)
    with pytest.raises(KpifsError, match="has channels"):
        calibrate(t, c)
    with pytest.raises(KpifsError, match="unknown test"):
        detect(t, test="Z")


def test_fit_errors_account_for_correlated_channels():
    """Two identical channels with fully correlated noise carry one channel's information:
    the sandwich errors are sqrt(2) times the independent-channel errors."""
    from kpifs.detect.fit import fit_binary
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
    wl = [1.6, 1.6] * u.um
    kp = km.binary_kernel_phases([60, -30] * u.mas, [5e-3, 5e-3], wl)
    w = np.stack([np.eye(km.n_kp) * 1e3] * 2)
    ind = fit_binary(kp, w, km, wl, (58.0, -28.0), [4e-3, 4e-3])
    rows = np.repeat(np.eye(km.n_kp)[:, None, :], 2, axis=1)     # R^T R: channels identical
    cor = fit_binary(kp, w, km, wl, (58.0, -28.0), [4e-3, 4e-3], noise_rows=rows)
    assert cor["x"] == pytest.approx(60, abs=1e-3)
    assert cor["x_err"] / ind["x_err"] == pytest.approx(np.sqrt(2), rel=1e-3)
    assert cor["y_err"] / ind["y_err"] == pytest.approx(np.sqrt(2), rel=1e-3)


def test_correlated_binary_limit_closed_form():
    """Two channels with fully correlated noise: T_B = 2 max(z + mu, 0)^2, so at P_D = 0.5
    the limit is sqrt(xi / 2) / ||s||."""
    xi = 9.0
    corr = np.ones((1, 1, 2, 2))
    lim = limit_binary(np.full((2, 1, 1), 4.0), xi, 0.5, correlation=corr)
    assert lim[0, 0] == pytest.approx(np.sqrt(xi / 2) / 2, rel=5e-3)
    # with independent channels the same threshold needs less signal
    assert limit_binary(np.full((2, 1, 1), 4.0), xi, 0.5)[0, 0] < lim[0, 0]


def test_correlated_draw_starts_reach_the_same_crossings():
    """The correlated limits' per-draw starts bound each draw's crossing (right of it for
    power 1; for power 2 mostly left of it, from the all-on quadratic), and Newton lands
    from them where it lands from the per-position moment guess."""
    from kpifs.detect.limits import _crossings, _draw_starts, _moment_guess
    rng = np.random.default_rng(3)
    q, n = 6, 256
    a = rng.standard_normal((5, q, q))
    corr = a @ a.transpose(0, 2, 1) / q + 0.1 * np.eye(q)
    z = np.matmul(np.linalg.cholesky(corr).astype(np.float32),
                  rng.standard_normal((q, n)).astype(np.float32))
    m = rng.uniform(0.1, 2.0, (5, q))
    for xi, power in ((30.0, 2), (12.0, 1)):
        guess = _moment_guess(m, np.sqrt(np.einsum("kii->ki", corr)), xi, power, 0.5)
        ref = _crossings(z, m, xi, power, guess)
        start = _draw_starts(z, m, xi, power)
        if power == 1:
            assert np.all(start >= ref * (1 - 1e-5))
        else:
            assert np.mean(start <= ref * (1 + 1e-5)) > 0.9
        assert np.allclose(_crossings(z, m, xi, power, start), ref, rtol=1e-5, atol=0)


def test_correlated_energy_limit_matches_chi2_when_white():
    from kpifs.detect.limits import limit_energy_correlated
    rng = np.random.default_rng(4)
    p, n = 50, 40000
    noise = rng.standard_normal((n, p))
    x = np.zeros((p, 3))
    x[0, 0], x[:, 1], x[3, 2] = 1.0, 1 / np.sqrt(p), 1.0        # unit-norm signals
    energy = np.sum(noise ** 2, axis=1)
    thr = np.quantile(energy, 0.99)
    lim = limit_energy_correlated(noise @ x, np.ones(3), energy, thr, 0.5)
    np.testing.assert_allclose(lim, np.sqrt(energy_lambda(0.01, 0.5, p)), rtol=0.03)


def test_detect_without_limits_finds_the_same_candidates():
    """``limits=False`` (the injection curves' search) skips the limits only."""
    from kpifs.detect.pipeline import _example_result
    full = _example_result()
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
    wl = [1.6, 1.7] * u.um
    rng = np.random.default_rng(1)             # the data of _example_result
    kp = km.binary_kernel_phases([60, -40] * u.mas, [4e-3, 3e-3], wl)
    kp = kp + rng.normal(0, 1e-3, kp.shape)
    kpd = KernelPhaseData(kp[None], wl, 10.42 * u.mas, km,
                          covariance=np.stack([np.eye(km.n_kp) * 1e-6] * 2),
                          meta={"calibrated": True})
    grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    fast = detect(kpd, grid=grid, n_draws=2000, seed=0, limits=False)
    assert fast.limits == {} and len(fast.candidates) == len(full.candidates) == 1
    assert float(fast.candidates["fit_x"][0].value) == float(full.candidates["fit_x"][0].value)
    assert fast.threshold == full.threshold


def test_window_max_is_ndimage_maximum_filter():
    """The search's local maxima use a numpy window maximum: scipy.ndimage's, exactly."""
    ndimage = pytest.importorskip("scipy.ndimage")
    from kpifs.detect.maps import _window_max
    rng = np.random.default_rng(1)
    for size in (3, 5, 9):
        t = rng.standard_normal((23, 31))
        t[rng.random(t.shape) < 0.2] = -np.inf
        np.testing.assert_array_equal(
            _window_max(t, size),
            ndimage.maximum_filter(t, size=size, mode="constant", cval=-np.inf))


def test_null_and_limits_do_not_depend_on_the_thread_count(monkeypatch):
    """Batches of null draws and blocks of limit positions run on several threads: the
    numbers are the same on one."""
    from kpifs.detect.null import NullCalibration, _CACHE
    from kpifs.detect.limits import limit_binary_correlated_forms
    km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    rng = np.random.default_rng(4)
    dm = DetectionModel(km, [1.5, 1.7] * u.um, np.stack([np.eye(km.n_kp)] * 2), grid)
    rows = rng.standard_normal((8, 2, km.n_kp)) / 8 ** 0.5
    corr = np.broadcast_to([[1.0, 0.6], [0.6, 1.0]], grid.shape + (2, 2))
    out = []
    for n in ("1", "2"):
        monkeypatch.setenv("KPIFS_THREADS", n)
        _CACHE.clear()
        draws = NullCalibration(dm, n_draws=1500, seed=2, noise_rows=rows).draws
        lim = limit_binary_correlated_forms(dm.norm2, {"B": 30.0, "B-paper": 9.0}, 0.5,
                                            correlation=corr)
        out.append((draws, lim))
    np.testing.assert_array_equal(out[0][0], out[1][0])
    for f in ("B", "B-paper"):
        np.testing.assert_array_equal(out[0][1][f], out[1][1][f])


def test_null_threshold_read_through_the_fitted_tail():
    """Fewer than 100 draws above a level: the threshold comes from the exponential tail
    fitted to the upper decile, and 5000 draws give the threshold 100 000 read directly."""
    from kpifs.detect.null import _CACHE
    km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    dm = DetectionModel(km, [1.6] * u.um, np.eye(km.n_kp)[None], grid)
    _CACHE.clear()
    ref = NullCalibration(dm, n_draws=100000, seed=9)
    assert 1e-3 * len(ref.draws) >= ref.exceedances         # read directly
    truth = ref.threshold(1e-3)
    small = [NullCalibration(dm, n_draws=5000, seed=s) for s in range(6)]
    u0, beta = small[0]._tail()
    assert small[0].threshold(1e-3) == pytest.approx(u0 + beta * np.log(100), rel=1e-12)
    assert small[0].threshold(0.05) == np.quantile(small[0].draws, 0.95, method="higher")
    thr = np.array([n.threshold(1e-3) for n in small])
    # the true false-alarm rate at each threshold (from the reference draws) is near 1e-3,
    # the tail a little conservative. Measured over 38 kernel bases (the draws are made in
    # the kernel basis, which the SVD turns machine by machine): mean threshold / truth
    # -2.0 to +4.1 % (mean +1.6 %, standard deviation 1.7 %), rates 0.40e-3 to 1.56e-3.
    # The bounds are about 4 standard deviations out (false failure below 1e-4).
    rate = np.array([np.mean(ref.draws > t) for t in thr])
    assert 0.2e-3 < rate.min() and rate.max() < 4e-3
    assert abs(np.mean(thr) / truth - 1) < 0.08


@pytest.mark.parametrize("value", ["abc", "0", "-2", "1.5"])
def test_bad_thread_count_is_refused(monkeypatch, value):
    from kpifs._utils import threads
    monkeypatch.setenv("KPIFS_THREADS", value)
    with pytest.raises(KpifsError, match="KPIFS_THREADS must be a whole number"):
        threads()


def test_thread_count_follows_the_environment(monkeypatch):
    """KPIFS_THREADS first, then OMP_NUM_THREADS (a batch worker's 1), then the cores."""
    from kpifs._utils import threads
    monkeypatch.delenv("KPIFS_THREADS", raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert threads() == 1
    monkeypatch.setenv("OMP_NUM_THREADS", "3,2")            # OpenMP's nested form
    assert threads() == 3
    monkeypatch.setenv("KPIFS_THREADS", "2")
    assert threads() == 2
    monkeypatch.delenv("KPIFS_THREADS")
    monkeypatch.setenv("OMP_NUM_THREADS", "many")            # not ours to refuse: the cores
    assert threads() >= 1


def test_negative_contrast_fit_goes_to_the_mirror():
    # kernel phases are odd: a fit started at the mirror of a companion finds the same
    # model with negative contrasts; the refinement takes the mirror (positive contrast)
    from astropy.table import QTable
    from kpifs.detect.fit import refine_candidates
    from kpifs.detect.quality import flag_candidates
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
    kp = km.binary_kernel_phases([70, -40] * u.mas, [4e-3, 3e-3, 2e-3], WL3)
    kpd = KernelPhaseData(kp[None], WL3, 10.42 * u.mas, km)
    t = QTable({"x": [-68.0] * u.mas, "y": [41.0] * u.mas, "contrast": [[-3e-3] * 3]})
    refine_candidates(t, kp, np.stack([np.eye(km.n_kp) * 1e3] * 3), kpd)
    assert abs(t["fit_x"][0].value - 70) < 0.5 and abs(t["fit_y"][0].value + 40) < 0.5
    assert np.allclose(t["fit_contrast"][0], [4e-3, 3e-3, 2e-3], rtol=0.02)
    grid = DetectionGrid.from_separation(150 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    flag_candidates(t, grid, resolution=40.0)
    assert t["flags"][0] == ""            # at the peak's mirror: not 'moved'
