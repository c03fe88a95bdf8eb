"""Issue 39: the pixels the extraction fills in every frame (dead spaxels) near the star,
as one more group of the spectral-differential search's static term (their kernel-phase
responses, `kpifs.extraction.filled.filled_pixel_rows`), carried by the product."""
import numpy as np
import pytest
from astropy import units as u
from astropy.io import fits

from kpifs import KernelPhaseData
from kpifs.detect.sdk import STATIC_SPECTRA, SpectralStack, static_term_groups
from kpifs.extraction.extract import extract_kernel_phases
from kpifs.extraction.filled import FILLED_STEP, FILLED_STEP_FLOOR, filled_pixel_rows
from kpifs.extraction.prepare import fill_bad_pixels
from kpifs.io.layouts import write_observation
from kpifs.simulation.simulate import simulate_scene
from kpifs.workflow import ExtractOptions, reduce_observation

WL = np.linspace(1.2, 2.3, 8) * u.um
OPTS = ExtractOptions(step="1.2m", spectral_differential="poly")
DEAD = (22, 21)                        # (y, x): 2 pixels from the star (20, 20)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Eight channels, 80 frames, no companion: the cube as simulated, and with the
    pixel DEAD non-finite in every frame and channel, and with a pixel far outside the
    window's radius dead instead."""
    d = tmp_path_factory.mktemp("filled")
    obs = simulate_scene("paper", wavelengths=WL, contrasts=0.0, pixscale=7.0 * u.mas,
                         n_frames=80, seed=4, npup=32, static_rms=30 * u.nm)
    clean = write_observation(obs, d)["target"]
    out = {"clean": clean}
    for name, pix in (("dead", DEAD), ("far", (0, 39))):
        with fits.open(clean[0]) as hdul:
            data = hdul[0].data.astype(float)
            data[:, :, pix[0], pix[1]] = np.nan
            path = d / f"{name}.fits"
            fits.PrimaryHDU(data, hdul[0].header).writeto(path)
        out[name] = [path]
    return out


@pytest.fixture(scope="module")
def products(files):
    return {k: reduce_observation(v, [], OPTS) for k, v in files.items()}


def _finite_difference(path, tkp):
    """The response, written out: the frames' mean (NaN at DEAD), filled, DEAD raised by
    the step in each channel alone, extracted."""
    data = fits.getdata(path).astype(float)
    base = fill_bad_pixels(data.mean(axis=0))
    kw = dict(wavelengths=tkp.wavelengths, pixscale=tkp.pixscale, window=tkp.window,
              keep_phases=False)
    k0 = extract_kernel_phases(base[None], tkp.kernel_model, **kw).kp[0]
    out = np.zeros((len(WL),) + k0.shape)
    for c in range(len(WL)):
        pert = base.copy()
        y, x = DEAD
        pert[c, y, x] += max(FILLED_STEP * abs(base[c, y, x]),
                             FILLED_STEP_FLOOR * base[c].max())
        out[c, c] = extract_kernel_phases(pert[None], tkp.kernel_model, **kw).kp[0, c] - k0[c]
    return out


def test_dead_pixel_is_a_group(files, products):
    """A pixel dead in every frame near the star: one more group of the static term, a
    row per channel with that channel's finite-difference response only."""
    kpd, (tkp,) = products["dead"]
    sdk = kpd.spectral
    n_kp = kpd.kp.shape[-1]
    assert len(sdk["static_groups"]) == len(STATIC_SPECTRA) + 1
    assert sdk["static_groups"][-1] == len(WL) and sdk["static_filled"] == 1
    assert sum(sdk["static_groups"]) == len(sdk["static_rows"])
    rows = static_term_groups(kpd)[-1]
    assert rows.shape == (len(WL), len(WL), n_kp)
    expect = _finite_difference(files["dead"][0], tkp)
    assert np.abs(expect).max() > 1e-4                  # a response, not rounding
    assert np.allclose(rows, expect, rtol=1e-9, atol=1e-12)
    off = ~np.eye(len(WL), dtype=bool)
    assert np.all(rows[off] == 0)
    # the search fits it an amplitude of its own
    st = SpectralStack(kpd, kpd.kp[0], kpd.covariance)
    assert len(st.static_amplitudes) == len(STATIC_SPECTRA) + 1
    assert min(st.static_amplitudes) >= 0


def test_no_dead_pixel_no_group(files, products):
    """No pixel bad in every frame, or one beyond the window's radius: the static term
    of the product as before (its groups alone, the same rows)."""
    for name in ("clean", "far"):
        kpd, (tkp,) = products[name]
        assert "static_filled" not in kpd.spectral
        assert len(kpd.spectral["static_groups"]) == len(STATIC_SPECTRA)
        assert np.array_equal(kpd.spectral["static_rows"],
                              np.concatenate(static_term_groups(tkp)))
    rows, pixels = filled_pixel_rows(fits.getdata(files["far"][0]), tkp.kernel_model,
                                     wavelengths=tkp.wavelengths, pixscale=tkp.pixscale,
                                     window=tkp.window)
    assert rows is None and pixels.shape == (0, 2)
    rows, pixels = filled_pixel_rows(fits.getdata(files["far"][0]), tkp.kernel_model,
                                     wavelengths=tkp.wavelengths, pixscale=tkp.pixscale,
                                     window=tkp.window, radius=40.0)
    assert rows.shape == (len(WL), len(WL), tkp.kp.shape[-1]) and pixels.tolist() == [[0, 39]]


def test_round_trip(products, tmp_path):
    """The group through the file: its rows (to float32), sizes and pixel count."""
    kpd, _ = products["dead"]
    path = tmp_path / "sdk.fits"
    kpd.write(path)
    back = KernelPhaseData.read(path).spectral
    assert back["static_groups"] == list(kpd.spectral["static_groups"])
    assert back["static_filled"] == 1
    assert fits.getheader(path, "KP-SDKSTAT")["SDKFILL"] == 1
    assert np.allclose(back["static_rows"], kpd.spectral["static_rows"], rtol=1e-6,
                       atol=1e-6 * np.abs(kpd.spectral["static_rows"]).max())
