"""The empirical (sign-flip) null of the grid maximum (issue 14, item 2): block rows
that carry the calibrated mean's frame noise, the exact law by enumeration, agreement
with the Gaussian Monte-Carlo null where that one is right, and what detection records."""
import numpy as np
import pytest
import astropy.units as u

from kpifs import KernelModel, KernelPhaseData, make_pupil
from kpifs.calibration.calibrate import block_rows, calibrate
from kpifs.covariance import whiten, whitening_matrix
from kpifs.data import DetectionGrid, DetectionResult
from kpifs.detect import DetectionModel, NullCalibration, detect
from kpifs.detect.channels import scale_block_rows
from kpifs.exceptions import KpifsError

WL = [1.6] * u.um
PIX = 10 * u.mas


@pytest.fixture(scope="module")
def km():
    return KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))


@pytest.fixture(scope="module")
def grid():
    return DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)


def _kpd(km, x):
    return KernelPhaseData(x, WL, PIX, km)


def _ar1(rng, n, p, rho):
    """Frames whose every kernel phase is an AR(1) series of unit variance."""
    x = np.empty((n, p))
    x[0] = rng.standard_normal(p)
    for i in range(1, n):
        x[i] = rho * x[i - 1] + np.sqrt(1 - rho ** 2) * rng.standard_normal(p)
    return x[:, None]


def test_sign_patterns_are_enumerated_exactly(km, grid):
    dm = DetectionModel(km, WL, np.eye(km.n_kp)[None], grid, pixscale=PIX)
    rows = np.random.default_rng(0).standard_normal((8, 1, km.n_kp))
    null = NullCalibration(dm, n_draws=5000, noise_rows=rows, coefficients="sign")
    # a symmetric grid: the global sign gives the same maximum, 2**7 distinct draws
    assert null.enumerated and null.n_draws == 128
    coef = null._coefficients(None, 0, 128)
    assert np.all(coef[:, 0] == 1) and len(np.unique(coef, axis=0)) == 128
    assert set(np.unique(coef)) == {-1.0, 1.0}
    # more patterns than draws: random signs, as many as asked
    many = NullCalibration(dm, n_draws=2000, noise_rows=np.tile(rows, (3, 1, 1)),
                           coefficients="sign")
    assert not many.enumerated and many.n_draws == 2000
    with pytest.raises(KpifsError, match="at least 6 block rows"):
        NullCalibration(dm, noise_rows=rows[:3], coefficients="sign")
    with pytest.raises(KpifsError, match="unknown null coefficients"):
        NullCalibration(dm, noise_rows=rows, coefficients="uniform")


def test_block_rows_carry_the_noise_of_the_calibrated_mean(km):
    """Sum of r r^T: the covariance of mean(T) - mean(C), independent frames (exact on
    average) and temporally correlated ones (where the frames' scatter / N is not)."""
    p, n = km.n_kp, 60
    rng = np.random.default_rng(3)
    ratio = []
    for _ in range(40):
        rows = block_rows(_kpd(km, rng.standard_normal((n, 1, p))),
                          _kpd(km, rng.standard_normal((n, 1, p))))
        assert rows.shape == (16, 1, p)          # 8 blocks of each star
        ratio.append(np.sum(rows ** 2) / (p * 2 / n))
    assert abs(np.mean(ratio) - 1) < 0.05, np.mean(ratio)
    # AR(1), rho 0.8: the variance of a 60-frame mean is 8.3 x sigma^2 / N
    rho, drift, naive = 0.8, [], []
    for _ in range(40):
        t, c = _ar1(rng, n, p, rho), _ar1(rng, n, p, rho)
        drift.append(np.sum(block_rows(_kpd(km, t), _kpd(km, c)) ** 2))
        naive.append((t.var(axis=0, ddof=1).sum() + c.var(axis=0, ddof=1).sum()) / n)
    gain = np.mean(drift) / np.mean(naive)
    assert 2.5 < gain < 8.3, gain          # blocks of 7-8 frames see most of it
    # several calibrators weigh 1/M each; a single frame gives none
    one = block_rows(_kpd(km, rng.standard_normal((36, 1, p))),
                     [_kpd(km, rng.standard_normal((36, 1, p)))] * 2)
    assert one.shape == (18, 1, p)
    assert block_rows(_kpd(km, rng.standard_normal((1, 1, p))),
                      _kpd(km, rng.standard_normal((9, 1, p)))) is None


def test_scaled_block_rows_take_the_whitened_dimension():
    b = np.random.default_rng(1).standard_normal((10, 3, 20))
    s, ratio = scale_block_rows(b, np.array([20, 15, 0]))
    assert np.allclose(np.sum(s ** 2, axis=(0, 2)), [20, 15, 0])
    assert ratio == pytest.approx(np.mean(np.sum(b[:, :2] ** 2, axis=(0, 2)) / [20, 15]))


@pytest.mark.filterwarnings("ignore")
def test_empirical_null_agrees_with_gaussian_on_independent_frames(km, grid):
    """Where the Gaussian null is right (independent Gaussian frames), the sign flips of
    28 time blocks give the same threshold of the grid maximum within their scatter."""
    ratio = []
    for seed in range(4):
        rng = np.random.default_rng(seed)
        cal = calibrate(_kpd(km, rng.standard_normal((200, 1, km.n_kp))),
                        _kpd(km, rng.standard_normal((200, 1, km.n_kp))))
        res = detect(cal, grid=grid, pfa=0.01, n_draws=4000, seed=seed, limits=False)
        nul = res.meta["null"]
        assert nul["method"] == "gaussian+empirical" and nul["n_blocks"] == 28
        ratio.append(nul["threshold_empirical"] / nul["threshold_gaussian"])
        # in-sample, the blocks' whitened energy is low (they helped make the covariance)
        assert 0.5 < nul["block_energy"] < 1.0
    # measured 0.92-1.05
    assert 0.85 < np.median(ratio) < 1.15 and np.all(np.abs(np.log(ratio)) < 0.3), ratio


def test_detection_records_both_nulls(km, grid, tmp_path):
    rng = np.random.default_rng(5)
    cal = calibrate(_kpd(km, rng.standard_normal((40, 1, km.n_kp)) * 1e-2),
                    _kpd(km, rng.standard_normal((40, 1, km.n_kp)) * 1e-2))
    assert cal.block_rows.shape == (12, 1, km.n_kp)
    path = tmp_path / "cal.fits"
    cal.write(path)
    back = KernelPhaseData.read(path)
    assert np.allclose(back.block_rows, cal.block_rows)
    res = detect(back, grid=grid, n_draws=2000, seed=1)
    nul = res.meta["null"]
    assert res.threshold == max(nul["threshold_gaussian"], nul["threshold_empirical"])
    assert nul["empirical_draws"] == 2048                  # 2**11 patterns, all of them
    # every P_FA is the larger of the two nulls'
    g = detect(back, grid=grid, n_draws=2000, seed=1, null="gaussian")
    e = detect(back, grid=grid, n_draws=2000, seed=1, null="empirical")
    assert set(g.meta["null"]) >= {"threshold_gaussian"} and \
        "threshold_empirical" not in g.meta["null"]
    assert e.threshold == pytest.approx(nul["threshold_empirical"])
    valid = grid.valid
    assert np.allclose(res.pfa_global[valid],
                       np.maximum(g.pfa_global[valid], e.pfa_global[valid]))
    res.write(tmp_path / "det.fits")
    read = DetectionResult.read(tmp_path / "det.fits")
    assert read.meta["null"]["method"] == "gaussian+empirical"
    assert read.meta["null"]["threshold_empirical"] == pytest.approx(
        nul["threshold_empirical"], rel=1e-5)
    assert read.meta["null"]["n_blocks"] == 12
    # data without time blocks (one frame with a covariance) cannot have it
    single = KernelPhaseData(cal.kp, WL, PIX, km, covariance=cal.covariance,
                             meta={"calibrated": True})
    with pytest.raises(KpifsError, match="KP-BLKROWS"):
        detect(single, grid=grid, n_draws=2000, null="empirical")
    assert detect(single, grid=grid, n_draws=2000, limits=False).meta["null"]["method"] == \
        "gaussian"
    with pytest.raises(KpifsError, match="unknown null"):
        detect(back, grid=grid, n_draws=2000, null="bootstrap")


def test_whitened_blocks_are_in_sample_biased(km):
    """Why the empirical null takes its scale from the error model: the blocks' whitened
    energy is ~1/Hartlap of the dimension while the calibrated mean's is the dimension."""
    rng = np.random.default_rng(11)
    e_blk, e_mean = [], []
    for _ in range(10):
        cal = calibrate(_kpd(km, rng.standard_normal((60, 1, km.n_kp))),
                        _kpd(km, rng.standard_normal((60, 1, km.n_kp))), error_model="frames")
        w = whitening_matrix(cal.covariance)
        e_blk.append(np.sum(whiten(cal.block_rows, w) ** 2))
        e_mean.append(np.sum(whiten(cal.kp[0], w) ** 2))
    h = cal.meta["error_model"]["hartlap"]
    assert abs(np.mean(e_mean) / km.n_kp - 1) < 0.15
    assert abs(np.mean(e_blk) / km.n_kp * h - 1) < 0.15


def test_cli_null_option_and_report(km, grid, tmp_path, capsys):
    from kpifs.cli import main
    rng = np.random.default_rng(8)
    cal = calibrate(_kpd(km, rng.standard_normal((40, 1, km.n_kp)) * 1e-2),
                    _kpd(km, rng.standard_normal((40, 1, km.n_kp)) * 1e-2))
    cal.write(tmp_path / "cal.fits")
    args = ["detect", str(tmp_path / "cal.fits"), "--max-sep", "100mas", "--draws", "2000"]
    assert main(args + ["-o", str(tmp_path / "det.fits")]) == 0
    out = capsys.readouterr().out
    assert "the larger of the Gaussian null's" in out and ", 12 time blocks)" in out
    assert main(["info", str(tmp_path / "det.fits")]) == 0
    assert "null gaussian+empirical: Gaussian threshold" in capsys.readouterr().out
    # a calibrated file without time blocks (another tool's, or written before them)
    single = KernelPhaseData(cal.kp, WL, PIX, km, covariance=cal.covariance,
                             meta={"calibrated": True})
    single.write(tmp_path / "noblocks.fits")
    args = ["detect", str(tmp_path / "noblocks.fits"), "--max-sep", "100mas", "--draws", "2000",
            "--null", "empirical", "-o", str(tmp_path / "det2.fits")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "noblocks.fits: no time blocks" in err and "--null gaussian" in err
    assert main(args[:-4] + ["--null", "gaussian", "-o", str(tmp_path / "det2.fits")]) == 0


def test_correlated_limits_on_half_the_grid_are_mirrored(km, grid):
    """The correlated limits are computed on half a symmetric grid and mirrored (the
    signature at -pos is minus that at pos): complete and symmetric maps."""
    rng = np.random.default_rng(2)
    common = rng.standard_normal((30, 1, km.n_kp))        # channels correlated
    wl = [1.6, 1.7] * u.um

    def kpd(x):
        return KernelPhaseData(x, wl, PIX, km)
    t = kpd(np.concatenate([common, common], axis=1) + 0.3 * rng.standard_normal((30, 2, km.n_kp)))
    c = kpd(0.3 * rng.standard_normal((30, 2, km.n_kp)))
    res = detect(calibrate(t, c), grid=grid, n_draws=2000, seed=3)
    assert res.meta["null_channels"] == "covariance rows"
    valid = grid.valid
    for f in ("B", "B-paper", "E"):
        lim = res.limits[f]
        assert np.all(np.isfinite(lim[valid])) and np.all(np.isnan(lim[~valid]))
        assert np.array_equal(lim, lim[::-1, ::-1], equal_nan=True)
