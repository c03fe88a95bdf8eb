"""Field rotation (issue 29): calibrated time blocks and the block-by-block sky search."""
import numpy as np
import pytest
from astropy import units as u

from kpifs import KernelModel, KernelPhaseData, make_pupil
from kpifs.calibration.adi import angular_differential
from kpifs.calibration.calibrate import calibrate
from kpifs.data import DetectionGrid
from kpifs.detect import detect
from kpifs.detect.blocks import BlockModel
from kpifs.detect.sky import sky_to_detector
from kpifs.rotation import rotation_blocks, time_blocks

from basis_free import kernel_noise


@pytest.fixture(scope="module")
def km():
    return KernelModel.from_pupil(make_pupil("subaru", step=1.0 * u.m, grey=False))


def _sequence(km, wl, detpa, sky, contrast, sigma, seed):
    rng = np.random.default_rng(seed)
    kp = np.stack([km.binary_kernel_phases(list(sky_to_detector(*sky, t)) * u.mas, contrast, wl)
                   for t in detpa])
    return kp + sigma * kernel_noise(km, rng, kp.shape)


def _observation(km, detpa, contrast, seed, sky=(69.0, -98.0), static=0.0):
    """Target (companion fixed on the sky) and calibrator frames at *detpa*, 3 channels,
    0.01 rad of white noise a frame; *static*: rms of a kernel-phase offset fixed on the
    detector that the target has and the calibrator has not."""
    wl = [1.55, 1.65, 1.75] * u.um
    off = static * kernel_noise(km, np.random.default_rng(seed + 100), (len(wl), km.n_kp))
    tgt = _sequence(km, wl, detpa, sky, contrast, 0.01, seed) + off
    cal = _sequence(km, wl, detpa, sky, 0.0, 0.01, seed + 1)
    return [KernelPhaseData(k, wl, 10 * u.mas, km, detpa=detpa) for k in (tgt, cal)]


def test_time_blocks_pair_up_short_blocks():
    lab = time_blocks(np.linspace(100, 140, 20), width=1.5)       # 2.1 deg per frame
    assert lab.tolist() == np.repeat(np.arange(10), 2).tolist()
    assert time_blocks([359.0, 359.5, 0.2, 0.8], width=1.0).tolist() == [0, 0, 1, 1]


def test_blocks_kept_by_calibration_and_written(km, tmp_path):
    """The calibrated product keeps the blocks (their mean is the calibrated mean), and
    KPFITS carries them; a sequence that does not turn has none."""
    detpa = np.linspace(100.0, 140.0, 24)
    tgt, cal = _observation(km, detpa, 0.0, 1)
    with pytest.warns(Warning, match="spans 40.0 deg"):
        res = calibrate(tgt, [cal])
    rb = res.rotation
    assert rb.n_blocks >= 2 and rb.frames.sum() == 24
    np.testing.assert_allclose(rb.mean(), res.kp[0], atol=1e-12)
    assert np.sum(np.sqrt(rb.frames)[:, None, None] * rb.contrasts()) == pytest.approx(0, abs=1e-9)
    back = KernelPhaseData.read(res.write(tmp_path / "c.fits"))
    np.testing.assert_allclose(back.rotation.data, rb.data)
    np.testing.assert_allclose(back.rotation.angles, rb.angles)
    assert back.rotation.n_target_noise == 24
    fixed = [KernelPhaseData(k.kp, k.wavelengths, k.pixscale, km, detpa=np.full(24, 100.0))
             for k in (tgt, cal)]
    assert rotation_blocks(*fixed[:1], fixed[1:]) is None


def test_block_model_maps_are_the_stacked_inner_products(km):
    """The fast maps (two products per channel over all blocks) equal the explicit inner
    products of the stacked signatures with the data, and norm2 their squared norms."""
    rng = np.random.default_rng(3)
    q, rm, rf, p = 2, 4, 6, km.n_kp
    cm, cf = rng.normal(size=(q, rm, p)), rng.normal(size=(q, rf, p))
    grid = DetectionGrid.from_separation(60 * u.mas, 10 * u.mas, min_sep=10 * u.mas,
                                         frame="sky")
    ang, n = np.array([10.0, 25.0, 47.0]), np.array([2, 3, 2])
    bm = BlockModel(km, [1.6, 1.7] * u.um, grid, cm, cf, ang, n)
    assert bm.dim == rm + 3 * rf
    y = rng.normal(size=(q, bm.dim))
    dots = bm.dot_maps(y)
    iy, ix = 3, 9
    flat = np.array([iy * grid.shape[1] + ix])
    unit = bm._unit_signatures(flat)[:, 0].astype(float)              # (q, dim), unit norm
    # the explicit stack: the mean's signature, then sqrt(n_b)(S_b - their mean)
    dra, ddec = grid.X[iy, ix], grid.Y[iy, ix]
    v = np.sqrt(n / n.sum())
    for i, lam in enumerate([1.6e-6, 1.7e-6]):
        sins = []
        for a in ang:
            x, yy = sky_to_detector(dra, ddec, a)
            th = 2 * np.pi * (x * km.uv.value[:, 0] + yy * km.uv.value[:, 1]) * np.pi / 180 \
                / 3600e3 / lam
            sins.append(km.kernel @ np.sin(-th))
        sins = np.array(sins)
        mean = (n / n.sum()) @ sins
        per = sins @ cf[i].T
        dev = [np.sqrt(nb) * (pb - (n / n.sum()) @ per) for nb, pb in zip(n, per)]
        s = np.concatenate([cm[i] @ mean] + dev)
        assert bm.norm2[i, iy, ix] == pytest.approx(s @ s, rel=1e-5)
        np.testing.assert_allclose(unit[i], s / np.linalg.norm(s), atol=1e-5)
        # the data's block part is projected on the blocks' constraint, as the signature is
        yd = y[i, rm:].reshape(3, rf)
        yd = yd - np.outer(v, v @ yd)
        yp = np.concatenate([y[i, :rm], yd.ravel()])
        assert dots[i, iy, ix] == pytest.approx(s @ yp, rel=1e-4)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:.*stopped at max_candidates")
def test_rotation_no_longer_smears(km):
    """40 deg of rotation: the blocks' search finds the companion where the model averaged
    over the angles (the mean only, before issue 29) is shallower, and fits it on the sky
    (within 2 mas and 1 deg); its limits at 100-150 mas are within 15 % of those of the
    same data without rotation, where the averaged model's are worse."""
    sky = (69.0, -98.0)                      # 120 mas, PA 144.9 deg
    grid = DetectionGrid.from_separation(150 * u.mas, 8 * u.mas, min_sep=30 * u.mas,
                                         frame="sky")
    kw = dict(grid=grid, n_draws=2000, seed=0, max_candidates=1)
    with pytest.warns(Warning, match="spans 40.0 deg"):
        turning = calibrate(*_split(_observation(km, np.linspace(100.0, 140.0, 60), 0.012, 5,
                                                 sky)))
    fixed = calibrate(*_split(_observation(km, np.full(60, 120.0), 0.012, 5, sky)))
    res = detect(turning, **kw)
    smeared = detect(turning, blocks="mean", **kw)
    still = detect(fixed, **kw)
    assert res.meta["frame"] == "sky" and len(res.candidates) == 1
    row = res.candidates[0]
    assert np.hypot(row["fit_dra"].value - sky[0], row["fit_ddec"].value - sky[1]) < 2.0
    assert row["pfa_global"] < 1e-6
    assert np.median(row["fit_contrast"]) == pytest.approx(0.012, rel=0.1)
    sep = np.hypot(grid.X, grid.Y)
    ring = (sep > 90) & (sep < 150) & grid.valid
    ratio = np.median(res.limits["B"][ring]) / np.median(still.limits["B"][ring])
    worse = np.median(smeared.limits["B"][ring]) / np.median(still.limits["B"][ring])
    assert ratio < 1.15 and worse > ratio + 0.1


def _split(pair):
    return pair[0], [pair[1]]


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:.*stopped at max_candidates")
@pytest.mark.filterwarnings("ignore:.*of rotation keep")
def test_angular_differential_without_calibrator_false_alarms_and_recovery(km):
    """A scaled-down ``docs/figures/measure_rotation.py`` (false-alarms, injection): no
    calibrator, a static kernel-phase offset three times the frames' noise fixed on the
    detector, 24 frames over 60 deg. The angular-differential search gives a candidate at
    P_FA 1e-2 in few companion-free sequences (2 of seeds 0-19, noise drawn on the uv
    points: the same realisation on every machine; at a true rate of 0.1, 5 or more of 6
    happen 5e-5 of the time), the mean of the frames, searched as if calibrated, in more
    (3 of seeds 0-5 at P_FA 1.8e-5 to 7e-4, 5 of 0-11: the noise scale absorbs much of the
    offset); companions injected at the stated limit are found about half the time and at
    twice the limit every time."""
    detpa = np.linspace(100.0, 160.0, 24)
    wl = [1.55, 1.65, 1.75] * u.um
    grid = DetectionGrid.from_separation(150 * u.mas, 8 * u.mas, min_sep=60 * u.mas,
                                         frame="sky")
    # the spectral-model test, as measured (its default quadratic basis); 'auto' takes B on
    # three channels, whose limit here is conservative (8 of 8 found at it)
    kw = dict(grid=grid, pfa=1e-2, n_draws=1000, seed=0, max_candidates=1, test="S")

    def target(seed, sky=(0.0, 120.0), contrast=0.0):
        off = 0.03 * kernel_noise(km, np.random.default_rng(seed + 100), (len(wl), km.n_kp))
        kp = _sequence(km, wl, detpa, sky, contrast, 0.01, seed) + off
        return KernelPhaseData(kp, wl, 10 * u.mas, km, detpa=detpa)

    alarms, plain = 0, 0
    for seed in range(6):
        res = detect(angular_differential(target(seed)), **kw)
        alarms += len(res.candidates) > 0
        if seed == 0:
            free = res
        t = target(seed)
        cov = np.stack([np.cov(k.T) for k in t.kp.transpose(1, 0, 2)]) / 24
        mean = KernelPhaseData(t.kp.mean(axis=0)[None], wl, 10 * u.mas, km, covariance=cov,
                               detpa=[130.0], meta={"calibrated": True})
        plain += len(detect(mean, **kw).candidates) > 0
    assert alarms <= 4 and plain >= 2
    # injections at 120 mas, 8 position angles, each in its own noise (drawn on the uv
    # points: the same on every machine): 3 of 8 found at the limit, 8 of 8 at twice it; the
    # bounds leave room for injections near the threshold to change with the null's draws
    pas = np.deg2rad(20 + 45 * np.arange(8))
    sky = [(120 * np.sin(a), 120 * np.cos(a)) for a in pas]
    g = free.grid
    lim = np.median([free.limit[np.argmin(np.abs(g.y - d)), np.argmin(np.abs(g.x - r))]
                     for r, d in sky])
    found = {}
    for f in (1.0, 2.0):
        hits = 0
        for k, pos in enumerate(sky):        # each injection in its own noise
            res = detect(angular_differential(target(10 + k, pos, f * lim)), **kw)
            c = res.candidates
            hits += bool(len(c)) and np.hypot(c["fit_dra"][0].value - pos[0],
                                              c["fit_ddec"][0].value - pos[1]) < 20
        found[f] = hits
    assert 1 <= found[1.0] <= 7 and found[2.0] == 8


@pytest.mark.filterwarnings("ignore:.*of rotation keep")
def test_angular_differential_search_starts_where_half_the_signal_is_kept(km):
    # 40 deg of rotation: near the star a companion hardly moves between blocks and the
    # search there would answer to the residual's structure; the default grid starts where
    # the rotation keeps half a companion's squared signal (here ~70 mas, not ~24)
    from kpifs.calibration.adi import inner_separation
    detpa = np.linspace(100.0, 140.0, 16)
    wl = [1.55, 1.65, 1.75] * u.um
    kp = _sequence(km, wl, detpa, (0.0, 120.0), 0.0, 0.01, 3)
    kpd = angular_differential(KernelPhaseData(kp, wl, 10 * u.mas, km, detpa=detpa))
    res = detect(kpd, n_draws=1000, seed=0, limits=False)
    inner = res.meta["blocks"]["inner_separation"]
    full = detect(kpd, n_draws=1000, seed=0, limits=False,
                  grid=DetectionGrid.from_separation(float(res.grid.max_sep) * u.mas,
                                                     abs(float(res.grid.step[0])) * u.mas,
                                                     min_sep=10 * u.mas, frame="sky"))
    assert float(res.grid.min_sep) == pytest.approx(inner)
    assert 50 < inner < 100
    assert "inner_separation" not in full.meta["blocks"]         # a grid given is kept
    assert float(full.grid.min_sep) == 10
    assert inner_separation.__module__ == "kpifs.calibration.adi"


@pytest.mark.filterwarnings("ignore:.*of rotation keep")
def test_block_signatures_follow_the_frames_within_each_block(km):
    # 24 frames over 72 deg in blocks of 4: a companion at 120-150 mas moves by ~half a
    # fringe within a block. The search's signatures (two poses per block, at its angle
    # -/+ its frames' spread) match the fit's exact model (each frame's own angle, averaged
    # within the block) within 2 %; one pose at the block's angle overstates them, by 16-34 %
    # over four noise realisations (the frames' noise modes kept in the whitening depend on
    # them): 10 % at least, never the 1 / 0.69 of 300 mas
    from kpifs.detect.blocks import BlockStack
    detpa = np.linspace(100.0, 172.0, 24)
    wl = [1.55, 1.75] * u.um
    kp = _sequence(km, wl, detpa, (0.0, 120.0), 0.0, 0.01, 4)
    kpd = angular_differential(KernelPhaseData(kp, wl, 10 * u.mas, km, detpa=detpa))
    assert kpd.rotation.frames.tolist() == [4] * 6
    stack = BlockStack(kpd, kpd.kp[0], None, np.zeros(2, int), mode="angular-differential")
    spread = stack.spread()
    np.testing.assert_allclose(spread, np.std(detpa[:4]), rtol=1e-9)      # 3.5 deg
    grid = DetectionGrid.from_separation(150 * u.mas, 10 * u.mas, frame="sky")
    model = stack.detection_model(grid)
    single = BlockModel(km, wl, grid, None, stack.comp_frame, kpd.rotation.angles,
                        kpd.rotation.frames)
    ratio, over = [], []
    for iy, ix in ((3, 15), (15, 27), (27, 15), (10, 5)):          # 120-150 mas
        c = 1e-4
        exact = np.sum(stack.model_kp((grid.x[ix], grid.y[iy]), c) ** 2, axis=1) / c ** 2
        ratio.append(model.norm2[:, iy, ix] / exact)
        over.append(single.norm2[:, iy, ix] / exact)
    np.testing.assert_allclose(ratio, 1.0, atol=0.02)
    assert 1.1 < np.min(over) and np.max(over) < 1 / 0.69


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:.*spans 40.0 deg")
@pytest.mark.filterwarnings("ignore:.*stopped at max_candidates")
def test_angular_differential_with_calibrator_keeps_the_mean_at_its_own_scale(km):
    # with a calibrator the angular-differential search keeps the calibrated mean, whose
    # reduced chi-square (the static target-calibrator difference is in it alone) scales
    # it (38 here, with a difference ten times the mean's noise); the departures keep the
    # frames' noise
    detpa = np.linspace(100.0, 140.0, 24)
    grid = DetectionGrid.from_separation(120 * u.mas, 10 * u.mas, min_sep=40 * u.mas,
                                         frame="sky")
    kw = dict(grid=grid, n_draws=1000, seed=0, limits=False, max_candidates=1)
    scales = []
    for static in (0.0, 0.02):
        tgt, cal = _observation(km, detpa, 0.0, 7, static=static)
        res = detect(angular_differential(tgt, calibrate(tgt, [cal])), **kw)
        info = res.meta["blocks"]
        assert info["mode"] == "angular-differential"
        scales.append(info["mean_scale"])
    assert scales[0] < 1.5 and scales[1] > 10
