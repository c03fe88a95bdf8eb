"""Aliased channels (issue 22, item 4): which channels the pixels sample too coarsely,
that a companion's contrast there is what the model says elsewhere, and that
detection flags or leaves out the aliased channels."""
import numpy as np
import pytest
from astropy import units as u

from kpifs import KernelModel, KernelPhaseData, make_pupil
from kpifs.detect import detect
from kpifs.extract import extract_kernel_phases
from kpifs.sampling import aliased_channels, aliased_uv, pupil_extent
from kpifs.simulate import PRESETS, simulate_psf

MAS = np.pi / 180 / 3600e3


def test_alias_circle_analytic():
    # 16.2 mas pixels at 1.2 um: the copy at 1/p sits at lam/p = 15.28 m of baseline;
    # with D = 8 m a point is aliased when closer than 8 m to it, i.e. beyond 7.28 m on x
    lam, p, d = 1.2e-6, 16.2, 8.0
    edge = lam / (p * MAS) - d
    uv = [[edge - 0.01, 0.0], [edge + 0.01, 0.0], [0.0, edge + 0.01], [3.0, 3.0]] * u.m
    hit = aliased_uv(uv, [lam] * u.m, p * u.mas, diameter=d * u.m)[0]
    assert hit.tolist() == [False, True, True, False]
    # twice finer pixels: nothing within reach
    assert not aliased_uv(uv, [lam] * u.m, p / 2 * u.mas, diameter=d * u.m).any()


def test_pupil_extent_subaru():
    # the discrete Subaru model: cells up to ~8.1 m apart plus one cell
    ext = pupil_extent(make_pupil("subaru", step=0.5 * u.m)).to_value(u.m)
    assert 8.2 < ext < 8.7


def test_charis_blue_channels_flagged():
    # CHARIS: 16.2 mas pixels from 1.16 um; after the Nyquist cut the two bluest
    # channels keep uv points within reach of the first copies, the rest do not
    wl = PRESETS["charis"]["wavelengths"]
    km = KernelModel.from_pupil(make_pupil("subaru"))
    with pytest.warns(UserWarning, match="Nyquist"):
        km = km.for_wavelengths(wl, 16.2 * u.mas)
    frac = aliased_channels(km, wl, 16.2 * u.mas)
    assert np.flatnonzero(frac > 0).tolist() == [0, 1]
    assert 0.02 < frac[0] < 0.2 and frac[1] < frac[0]
    # SPHERE-IFS (7.46 mas, VLT) is sampled well in every channel
    sw = PRESETS["sphere"]["wavelengths"]
    vkm = KernelModel.from_pupil(make_pupil("vlt"))
    assert not aliased_channels(vkm, sw, 7.46 * u.mas).any()


@pytest.mark.parametrize("supersample", [1, 3])
def test_undersampled_contrasts_unbiased_noise_free(supersample):
    # what the kpifs model leaves out does not bias contrasts below Nyquist: point-
    # sampled and pixel-integrated (3x3 sub-pixels) images at 16.2 mas from 1.16 um,
    # noise-free, give every channel's contrast within 3 % (aliased ones included)
    wl = PRESETS["charis"]["wavelengths"][[0, 1, 3, 12, 21]]
    n, ps, c, pos = 48, 16.2, 1e-2, [120.0, 90.0]

    def cube(comp):
        s = supersample
        im = simulate_psf("subaru", wl, pixscale=ps / s * u.mas, shape=(n * s, n * s),
                          companions=comp, npup=96)
        return im.reshape(len(wl), n, s, n, s).sum(axis=(2, 4))

    with pytest.warns(UserWarning, match="Nyquist"):
        star = extract_kernel_phases(cube([])[None], "subaru", wavelengths=wl,
                                     pixscale=ps * u.mas)
        comp = extract_kernel_phases(cube([(pos, c)])[None], "subaru", wavelengths=wl,
                                     pixscale=ps * u.mas)
    d = comp.kp[0] - star.kp[0]
    m = np.asarray(comp.kernel_model.binary_kernel_phases(pos * u.mas, np.full(len(wl), c), wl))
    m = m * comp.window.at(np.hypot(*pos), comp.pixscale)
    ratio = np.sum(d * m, axis=1) / np.sum(m * m, axis=1)
    assert np.all(np.abs(ratio - 1) < 0.03), ratio


def _data(q=4, seed=0):
    km = KernelModel.from_pupil(make_pupil("subaru", step=1.0 * u.m))
    wl = np.linspace(1.16, 1.4, q) * u.um
    rng = np.random.default_rng(seed)
    kp = km.binary_kernel_phases([60, -40] * u.mas, np.full(q, 2e-2), wl)
    kp = kp + rng.normal(0, 1e-3, kp.shape)
    cov = np.stack([np.eye(km.n_kp) * 1e-6] * q)
    return KernelPhaseData(kp[None], wl, 16.2 * u.mas, km, covariance=cov,
                           meta={"calibrated": True})


def test_select_channels_follows_everything():
    kpd = _data()
    kpd.covariance_rows = np.random.default_rng(1).normal(size=(5, 4, kpd.n_kp))
    sub = kpd.select_channels([1, 3])
    assert np.array_equal(sub.wavelengths, kpd.wavelengths[[1, 3]])
    assert np.array_equal(sub.kp[0], kpd.kp[0, [1, 3]])
    assert np.array_equal(sub.covariance, kpd.covariance[[1, 3]])
    assert np.array_equal(sub.covariance_rows, kpd.covariance_rows[:, [1, 3]])
    assert sub.meta["channels"] == [2, 4]
    assert sub.select_channels([1]).meta["channels"] == [4]      # numbers stay the input's
    with pytest.raises(Exception, match="do not select"):
        kpd.select_channels([7])


def test_detect_aliased_keep_and_exclude(tmp_path):
    kpd = _data()
    frac = aliased_channels(kpd.kernel_model, kpd.wavelengths, kpd.pixscale)
    bad = np.flatnonzero(frac > 0)
    assert 0 < bad.size < kpd.n_wave
    grid_kw = dict(n_draws=1000, seed=0)
    keep = detect(kpd, **grid_kw)
    assert keep.meta["excluded_channels"] == []
    assert np.array_equal(np.asarray(keep.meta["aliased"]) > 0, frac > 0)
    out = detect(kpd, aliased="exclude", **grid_kw)
    assert out.meta["excluded_channels"] == (bad + 1).tolist()
    assert len(out.wavelengths) == kpd.n_wave - bad.size
    # the same as searching the unaliased channels by hand
    hand = detect(kpd.select_channels(frac == 0), **grid_kw)
    assert len(out.candidates) == len(hand.candidates) == 1
    assert out.candidates["fit_x"][0] == hand.candidates["fit_x"][0]
    # products: the flags and the channel numbering survive a round trip
    path = tmp_path / "d.fits"
    keep.write(path)
    from kpifs.data import DetectionResult
    back = DetectionResult.read(path)
    assert np.allclose(back.meta["aliased"], np.round(keep.meta["aliased"], 4))
    out.write(tmp_path / "e.fits")
    back = DetectionResult.read(tmp_path / "e.fits")
    assert back.meta["excluded_channels"] == (bad + 1).tolist()
    assert back.meta["channels"] == out.meta["channels"]
    with pytest.raises(Exception, match="aliased must be"):
        detect(kpd, aliased="drop")
