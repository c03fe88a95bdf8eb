"""Third-party suite: the real SPHERE-IFS PSF of V471 Tau (../shared/data/real; issue 35).

Sequences are built from the real PSF (39 YJ channels, 7.46 mas): each frame is the
PSF with a random sub-pixel shift, photon and read noise; a companion is a shifted,
scaled copy of the same real PSF. The file is read as its README says (the SPHERE
reader with its wavelength file) and nothing else is assumed about it."""
import numpy as np
import pytest
import astropy.units as u

from kpifs import KernelModel, extract_kernel_phases, make_pupil
from kpifs.calibration.calibrate import calibrate
from kpifs.detect import detect
from kpifs.io import read_cube
from kpifs.model.window import ExtractionWindow

pytestmark = [pytest.mark.realdata, pytest.mark.slow,
              pytest.mark.filterwarnings("ignore:.*Ledoit-Wolf shrinkage")]

PAD = 48


def _shift(img, dx, dy):
    """Fourier shift of (..., n, n) images by (dx, dy) pixels (x along columns)."""
    n = img.shape[-1]
    f = np.fft.fftfreq(n)
    ph = np.exp(-2j * np.pi * (f[None, :] * dx + f[:, None] * dy))
    return np.fft.ifft2(np.fft.fft2(img) * ph).real


@pytest.fixture(scope="module")
def psf(real_data):
    return load_psf(real_data)


def load_psf(real_data):
    """The real PSF, each channel normalised to 1 and padded to PAD x PAD, and its
    wavelengths and pixel scale."""
    with read_cube(real_data / "sphere_ifs_v471tau_psf.fits", instrument="sphere",
                   wavelengths=str(real_data / "sphere_ifs_v471tau_wl.fits")) as cube:
        img = np.array(cube.data[0], float)                       # (39, 25, 25)
        wl, ps = cube.wavelengths, cube.pixscale
    out = np.zeros((img.shape[0], PAD, PAD))
    o = (PAD - img.shape[-1]) // 2
    out[:, o:o + img.shape[-1], o:o + img.shape[-1]] = img / img.sum(axis=(1, 2),
                                                                     keepdims=True)
    return out, wl, ps


def _frames(psf, n, rng, *, companion=None, flux=3e6, read_noise=5.0):
    img, wl, ps = psf
    out = np.empty((n,) + img.shape)
    for i in range(n):
        scene = img.copy()
        if companion is not None:
            (x, y), c = companion
            scene = scene + c * _shift(img, x / ps.to_value(u.mas), y / ps.to_value(u.mas))
        scene = _shift(scene, *rng.normal(0, 0.15, 2))
        out[i] = rng.poisson(np.clip(scene, 0, None) * flux) + rng.normal(0, read_noise,
                                                                          scene.shape)
    return out


def _search(psf, target, calibrator, seed=0):
    _, wl, ps = psf
    km = KernelModel.from_pupil(make_pupil("vlt", step=0.8 * u.m))
    win = ExtractionWindow.default((PAD, PAD))
    kt, kc = (extract_kernel_phases(f, km, wavelengths=wl, pixscale=ps, window=win)
              for f in (target, calibrator))
    return detect(calibrate(kt, kc), pfa=1e-3, seed=seed, n_draws=2000)


def test_real_psf_companion_found_with_its_contrast(psf):
    """A 2e-2 companion at (45, -30) mas in 30 frames of the real PSF, calibrated by 30
    companion-free frames of the same PSF: one candidate within 1.5 mas, its mean
    contrast within 10 % (measured: 0.22 mas off, contrast +1.1 %; median limit 1.1e-3
    at 30-60 mas)."""
    rng = np.random.default_rng(3)
    truth = (45.0, -30.0)
    t = _frames(psf, 30, rng, companion=(truth, 2e-2))
    c = _frames(psf, 30, rng)
    res = _search(psf, t, c)
    tab = res.candidates
    assert len(tab) == 1, tab
    assert np.hypot(tab["fit_x"][0].value - truth[0], tab["fit_y"][0].value - truth[1]) < 1.5
    assert np.mean(np.asarray(tab["fit_contrast"][0])) == pytest.approx(2e-2, rel=0.1)


def test_real_psf_without_companion_gives_none(psf):
    """The same sequences without the companion: no candidate at P_FA 1e-3."""
    rng = np.random.default_rng(4)
    res = _search(psf, _frames(psf, 30, rng), _frames(psf, 30, rng), seed=1)
    assert len(res.candidates) == 0, res.candidates
