import numpy as np
import pytest
import astropy.units as u
from astropy.io import fits

from kpifs import (ExtractionWindow, KernelModel, KpifsError, KpifsWarning, extract_kernel_phases,
                   make_pupil)
from kpifs.model.window import DEFAULT_WINDOW_RADIUS
from kpifs.model.kernel import MAS
from kpifs.model.pupil import pupil_image
from kpifs.simulation.simulate import phase_screens, simulate_psf

PIX = 10.42 * u.mas
OFFSET = [80, 60] * u.mas   # 100 mas, off both axes


def _binary_residual(km, wl, shape, contrast=1e-2):
    cube = simulate_psf("subaru", wl, pixscale=PIX, shape=shape, companions=[(OFFSET, contrast)])
    kpd = extract_kernel_phases(cube, km, wavelengths=wl, pixscale=PIX)
    radius = DEFAULT_WINDOW_RADIUS * (min(shape) // 2)
    w = np.exp(-((100 / PIX.value) / radius) ** 4)
    model = km.binary_kernel_phases(OFFSET, contrast * w, wl)
    res = kpd.kp[0] - model
    return np.std(res, axis=1) / np.std(model, axis=1)


@pytest.mark.parametrize("shape, tolerance", [((40, 40), 0.20), ((64, 64), 0.10)])
def test_binary_kernel_phases_match_analytic(subaru_model, paper_wavelengths, shape, tolerance):
    """Fixes the Fourier sign convention end to end (simulator -> extraction -> model)."""
    rel = _binary_residual(subaru_model, paper_wavelengths, shape)
    assert np.all(rel < tolerance), rel
    # measured with the default (grey) model: ~0.11 (40x40) and ~0.025 (64x64); the
    # binary model: ~0.075 and ~0.017
    assert np.all(rel < 0.65 * tolerance)


def test_opposite_sign_would_fail(subaru_model, paper_wavelengths):
    cube = simulate_psf("subaru", paper_wavelengths, pixscale=PIX, shape=(40, 40),
                        companions=[(OFFSET, 1e-2)])
    kpd = extract_kernel_phases(cube, subaru_model, wavelengths=paper_wavelengths, pixscale=PIX)
    mirrored = subaru_model.binary_kernel_phases(-OFFSET, 1e-2, paper_wavelengths)
    assert np.all(np.sum(kpd.kp[0] * mirrored, axis=1) < 0)


def test_single_pixel_dft_sign(subaru_model):
    """V(u, v) = sum I exp(-2 pi i (u x + v y)/lam): one bright pixel at (+3, -2) px."""
    img = np.zeros((1, 32, 32))
    img[0, 16, 16] = 1.0
    img[0, 16 - 2, 16 + 3] = 0.5
    with pytest.warns(KpifsWarning, match="closer to the image edge"):
        kpd = extract_kernel_phases(img, subaru_model, wavelengths=[2.0] * u.um, pixscale=PIX,
                                    centres=(16, 16), window=ExtractionWindow(32, 1e6))
    uv = subaru_model.uv.value
    theta = 2 * np.pi * (3 * uv[:, 0] - 2 * uv[:, 1]) * PIX.value * MAS / 2e-6
    expected = np.angle(1 + 0.5 * np.exp(-1j * theta))
    np.testing.assert_allclose(kpd.phases[0, 0], expected, atol=1e-10)


def _smooth_opd(npup, dx, rms_rad, lam, seed):
    img, _ = pupil_image("subaru", npix=npup)
    return phase_screens(npup, dx, 1, rms=rms_rad * lam / (2 * np.pi), mask=img > 0,
                         cutoff=1e-3, seed=seed)[0]


def test_kernel_phases_reject_aberrations(subaru_model):
    """0.1 rad rms of smooth aberrations: kernel phases >= 5x smaller than raw phases."""
    lam = 1.6e-6
    _, dx = pupil_image("subaru", npix=128)
    rng = np.random.default_rng(3)
    ratios = []
    for _ in range(6):
        cube = simulate_psf("subaru", [1.6] * u.um, pixscale=PIX, shape=(40, 40),
                            opd=_smooth_opd(128, dx, 0.1, lam, rng))
        kpd = extract_kernel_phases(cube, subaru_model, wavelengths=[1.6] * u.um, pixscale=PIX)
        ratios.append(np.std(kpd.phases[0, 0]) / np.std(kpd.kp[0, 0]))
    assert np.median(ratios) >= 5, ratios
    assert min(ratios) >= 4, ratios


def test_grey_model_rejects_edge_aberrations_better_than_binary(subaru_model):
    """The default grey model models the light of partly covered cells, so its kernel
    cancels their aberrations too: measured 40-80x rejection against ~10x for the
    binary model (cells >= 90 % inside)."""
    binary = KernelModel.from_pupil(make_pupil("subaru", grey=False))
    lam = 1.6e-6
    _, dx = pupil_image("subaru", npix=128)
    rng = np.random.default_rng(5)
    ratio = {"grey": [], "binary": []}
    for _ in range(4):
        cube = simulate_psf("subaru", [1.6] * u.um, pixscale=PIX, shape=(40, 40),
                            opd=_smooth_opd(128, dx, 0.1, lam, rng))
        for name, km in (("grey", subaru_model), ("binary", binary)):
            kpd = extract_kernel_phases(cube, km, wavelengths=[1.6] * u.um, pixscale=PIX)
            ratio[name].append(np.std(kpd.phases[0, 0]) / np.std(kpd.kp[0, 0]))
    assert not subaru_model.pupil.is_binary
    assert np.median(ratio["grey"]) > 2.5 * np.median(ratio["binary"]), ratio


def test_subpixel_centre_is_dft_origin(paper_wavelengths):
    """A star moved by a sub-pixel amount gives the same phases once centred (binary
    model: a grey model's edge uv points, where the transfer is low, are sensitive to
    the pixel sampling itself)."""
    subaru_model = KernelModel.from_pupil(make_pupil("subaru", grey=False))
    base = simulate_psf("subaru", paper_wavelengths, pixscale=PIX, shape=(40, 40),
                        companions=[(OFFSET, 1e-2)])
    moved = simulate_psf("subaru", paper_wavelengths, pixscale=PIX, shape=(40, 40),
                         companions=[(OFFSET, 1e-2)], centre=(0.37, -0.29))
    k0 = extract_kernel_phases(base, subaru_model, wavelengths=paper_wavelengths, pixscale=PIX,
                               centres=(20, 20))
    k1 = extract_kernel_phases(moved, subaru_model, wavelengths=paper_wavelengths, pixscale=PIX,
                               centres=(20.37, 19.71))
    np.testing.assert_allclose(k1.phases, k0.phases, atol=2e-3)
    assert np.std(k1.kp - k0.kp) < 0.03 * np.std(k0.kp)
    # found centres are close to the truth
    k2 = extract_kernel_phases(moved, subaru_model, wavelengths=paper_wavelengths, pixscale=PIX)
    assert np.allclose(k2.centres["x"].value, 20.37, atol=0.1)
    assert np.allclose(k2.centres["y"].value, 19.71, atol=0.1)


def test_batches_and_nan_pixels(subaru_model, paper_wavelengths, rng):
    cube = simulate_psf("subaru", paper_wavelengths, pixscale=PIX, shape=(40, 40))
    frames = cube[None] * (1 + 0.01 * rng.standard_normal((5, 3, 1, 1)))
    a = extract_kernel_phases(frames, subaru_model, wavelengths=paper_wavelengths,
                              pixscale=PIX, batch_size=2, centres=(20, 20))
    b = extract_kernel_phases(frames, subaru_model, wavelengths=paper_wavelengths,
                              pixscale=PIX, batch_size=100, centres=(20, 20))
    np.testing.assert_allclose(a.kp, b.kp, atol=1e-12)
    bad = frames.copy()
    bad[:, :, 2, 3] = np.nan            # far from the star: negligible effect
    c = extract_kernel_phases(bad, subaru_model, wavelengths=paper_wavelengths, pixscale=PIX,
                              centres=(20, 20))
    assert np.all(np.isfinite(c.kp))
    assert c.meta["n_bad_pixels"] == 15
    np.testing.assert_allclose(c.kp, b.kp, atol=1e-5)
    mask = np.zeros((40, 40), bool)
    mask[2, 3] = True
    d = extract_kernel_phases(frames, subaru_model, wavelengths=paper_wavelengths, pixscale=PIX,
                              centres=(20, 20), mask=mask)
    np.testing.assert_allclose(d.kp, c.kp, atol=1e-12)


def test_dft_matrix_cached(paper_wavelengths):
    km = KernelModel.from_pupil(make_pupil("subaru"))
    m1 = km.dft_matrix(1.6 * u.um, PIX, (40, 40))
    m2 = km.dft_matrix(1600 * u.nm, PIX, (40, 40))
    assert m1 is m2
    assert m1.shape == (2 * km.n_uv, 1600)


@pytest.mark.parametrize("mutate, kwargs, match", [
    (lambda c: c.__setitem__((0, 1), np.nan), {}, "empty"),
    (lambda c: c.__setitem__((0, 0), 0.0), {}, "empty"),
    (None, dict(window=ExtractionWindow(64, 25.6)), "larger than"),
    (None, dict(centres=(50.0, 20.0)), "outside"),
    (None, dict(wavelengths=[-1.5, 1.6, 1.68] * u.um), "> 0"),
    (None, dict(wavelengths=[] * u.um), "no wavelengths"),
    (None, dict(wavelengths=[1.6, 1.7] * u.um), "3 channels"),
    (None, dict(pixscale=0 * u.mas), "pixel scale"),
])
def test_bad_input(subaru_model, paper_wavelengths, mutate, kwargs, match):
    cube = simulate_psf("subaru", paper_wavelengths, pixscale=PIX, shape=(40, 40))[None]
    cube = np.repeat(cube, 2, axis=0)
    if mutate:
        mutate(cube)
    args = dict(wavelengths=paper_wavelengths, pixscale=PIX, source="cube.fits")
    args.update(kwargs)
    with pytest.raises(KpifsError, match=match) as err:
        extract_kernel_phases(cube, subaru_model, **args)
    assert "cube.fits" in str(err.value) or match in ("pixel scale",)


def test_unknown_pupil_name(paper_wavelengths):
    with pytest.raises(KpifsError, match="unknown pupil 'hubble'"):
        extract_kernel_phases(np.ones((3, 8, 8)), "hubble", wavelengths=paper_wavelengths,
                              pixscale=PIX)


def test_bad_frames_dropped_and_recorded(subaru_model, paper_wavelengths, rng, tmp_path):
    cube = simulate_psf("subaru", paper_wavelengths, pixscale=PIX, shape=(40, 40))
    frames = cube[None] * (1 + 0.01 * rng.standard_normal((6, 3, 1, 1)))
    frames += 1e-4 * frames.max() * rng.standard_normal(frames.shape)
    bad = frames.copy()
    bad[1, 2] = np.nan                   # readout glitch at one channel
    bad[4] = 0.0                         # empty frame
    args = dict(wavelengths=paper_wavelengths, pixscale=PIX, source="seq.fits",
                detpa=np.arange(6.0), batch_size=4)
    with pytest.warns(KpifsWarning, match=r"seq.fits: 2 bad frame\(s\) of 6 dropped: "
                                          r"frame\(s\) 1: empty.*frame\(s\) 4: empty"):
        kpd = extract_kernel_phases(bad, subaru_model, **args)
    keep = [0, 2, 3, 5]
    ref = extract_kernel_phases(frames[keep], subaru_model, wavelengths=paper_wavelengths,
                                pixscale=PIX)
    np.testing.assert_allclose(kpd.kp, ref.kp, atol=1e-12)
    np.testing.assert_array_equal(kpd.detpa, keep)
    assert sorted(set(kpd.centres["frame"])) == keep
    assert kpd.meta["dropped_frames"] == [1, 4] and kpd.meta["bad_frames"] == "drop"
    path = kpd.write(tmp_path / "kp.fits")
    hdr = fits.getheader(path)
    assert hdr["BADFRMS"] == "drop" and hdr["NDROPFR"] == 2
    assert any("left out (bad): 1, 4" in str(h) for h in hdr["HISTORY"])
    with pytest.raises(KpifsError, match=r"seq.fits: 2 bad frame\(s\) of 6: frame\(s\) 1"):
        extract_kernel_phases(bad, subaru_model, bad_frames="fail", **args)
    with pytest.raises(KpifsError, match="bad_frames must be"):
        extract_kernel_phases(bad, subaru_model, bad_frames="ignore", **args)


def test_warnings_for_suspicious_pixels(subaru_model, paper_wavelengths):
    cube = np.repeat(simulate_psf("subaru", paper_wavelengths, pixscale=PIX,
                                  shape=(40, 40))[None], 3, axis=0)
    args = dict(wavelengths=paper_wavelengths, pixscale=PIX, source="c.fits")
    core = cube.copy()
    core[0, 1, 19:22, 19:22] = np.nan
    with pytest.warns(KpifsWarning, match=r"PSF core \(more than 10% of the flux "
                                          r"interpolated\) in 1 of 9"):
        extract_kernel_phases(core, subaru_model, **args)
    far = cube.copy()
    far[0, 1, 2, 3] = np.inf
    with pytest.warns(KpifsWarning, match="1 infinite pixel") as rec:
        extract_kernel_phases(far, subaru_model, **args)
    assert not any("PSF core" in str(w.message) for w in rec)
    with pytest.warns(KpifsWarning, match="negative pixels hold more than 10%"):
        extract_kernel_phases(cube - 0.3 * cube.max() / 40, subaru_model, **args)


def test_memory_mapped_pages_released_by_byte_budget(subaru_model, paper_wavelengths, tmp_path,
                                                     monkeypatch):
    """Pages of a memory-mapped cube are given back every RELEASE_BYTES read, not per batch;
    the kernel phases do not depend on it."""
    from kpifs.extraction import extract as ex
    cube = simulate_psf("subaru", paper_wavelengths, pixscale=PIX, shape=(32, 32))
    frames = (1e5 * cube[None] * np.linspace(0.9, 1.1, 6)[:, None, None, None]).astype(">f4")
    path = tmp_path / "c.fits"
    fits.writeto(path, frames)
    calls = []
    monkeypatch.setattr(ex, "release_pages", lambda data: calls.append(1))
    args = dict(wavelengths=paper_wavelengths, pixscale=PIX, batch_size=2, centres=(16, 16))
    with fits.open(path, memmap=True) as hdul:
        ref = extract_kernel_phases(hdul[0].data, subaru_model, **args)
        assert calls == []                               # 3 x 6 x 4 kB read: below the budget
        monkeypatch.setattr(ex, "RELEASE_BYTES", 2 * 32 * 32 * 4)
        kpd = extract_kernel_phases(hdul[0].data, subaru_model, **args)
    assert len(calls) == 3 * 3                            # every batch of two frames
    np.testing.assert_array_equal(kpd.kp, ref.kp)


def test_channels_on_threads_give_the_same_numbers(subaru_model, paper_wavelengths, rng,
                                                   monkeypatch):
    """Channels are extracted side by side: the same kernel phases on one thread, and a
    channel's warning (here from bad pixels filled on the core) is not lost meanwhile."""
    cube = simulate_psf("subaru", paper_wavelengths, pixscale=PIX, shape=(40, 40))
    frames = cube[None] * (1 + 0.01 * rng.standard_normal((6, 3, 1, 1)))
    frames[1, 2, 19:22, 19:22] = np.nan
    out = []
    for n in ("1", "3"):
        monkeypatch.setenv("KPIFS_THREADS", n)
        with pytest.warns(KpifsWarning, match=r"PSF core .* in 1 of 18"):
            out.append(extract_kernel_phases(frames, subaru_model, wavelengths=paper_wavelengths,
                                             pixscale=PIX, batch_size=4))
    np.testing.assert_array_equal(out[0].kp, out[1].kp)
    np.testing.assert_array_equal(out[0].phases, out[1].phases)
