import warnings

import numpy as np
import pytest
import astropy.units as u
from astropy.io import fits

from kpifs import KernelModel, KpifsError, KpifsWarning, make_pupil
from kpifs.model.kernel import load_kernel_model, nyquist_usable
from kpifs.model.pupil import pupil_image
from kpifs.simulation.simulate import simulate_psf


def test_kernel_annihilates_phase_transfer(subaru_model):
    km = subaru_model
    assert np.abs(km.kernel @ km.tfm).max() < 1e-10
    assert km.n_kp == km.n_uv - km.rank
    np.testing.assert_allclose(km.kernel @ km.kernel.T, np.eye(km.n_kp), atol=1e-10)
    assert km.rank == np.linalg.matrix_rank(km.tfm)


def test_uv_points_half_plane_and_redundancy():
    km = KernelModel.from_pupil(make_pupil("subaru", grey=False))
    u_, v_ = km.uv.value.T
    assert np.all((v_ > 1e-9) | ((np.abs(v_) < 1e-9) & (u_ > 0)))
    # every pair counted once: total redundancy = n(n-1)/2 for a binary model
    n = km.pupil.n_sub
    assert km.redundancy.sum() == n * (n - 1) // 2
    # rows of A sum to zero (a piston gives no phase)
    np.testing.assert_allclose(km.blm.sum(axis=1), 0, atol=1e-12)
    # uv points are unique
    assert len(np.unique(np.round(km.uv.value, 6), axis=0)) == km.n_uv


def test_grey_model_kernel():
    km = KernelModel.from_pupil(make_pupil("vlt", grey=True, min_transmission=0.3,
                                           step=0.6 * u.m))
    assert not km.pupil.is_binary
    assert np.abs(km.kernel @ km.tfm).max() < 1e-10
    assert not np.allclose(km.redundancy, np.round(km.redundancy))


@pytest.mark.parametrize("pupil", ["subaru", "vlt", "pharo", "annular", "image"])
def test_default_grey_models_have_exact_kernels(pupil, tmp_path):
    """K R^-1 A = 0 with redundancies weighted by transmission products, for every
    built-in pupil's default (grey) model and a pupil image."""
    kw = dict(diameter=6 * u.m, obstruction=1.5 * u.m) if pupil == "annular" else {}
    if pupil == "image":
        img, dx = pupil_image("vlt", npix=160)
        pupil = str(tmp_path / "pupil.fits")
        fits.PrimaryHDU(img, header=fits.Header({"PUPSCALE": dx})).writeto(pupil)
    pup = make_pupil(pupil, **kw)
    km = KernelModel.from_pupil(pup)
    assert not pup.is_binary
    assert np.abs(km.kernel @ km.tfm).max() < 1e-10
    assert km.kernel_residual() < 1e-12
    np.testing.assert_allclose(km.kernel @ km.kernel.T, np.eye(km.n_kp), atol=1e-10)
    # redundancy = sum of t_j t_k over the pairs of each uv point: over all uv points,
    # every pair once
    t = pup.transmission
    j, k = np.triu_indices(pup.n_sub, 1)
    every = KernelModel.from_pupil(pup, min_redundancy=0)
    assert every.redundancy.sum() == pytest.approx(np.sum(t[j] * t[k]), rel=1e-12)
    assert np.abs(every.kernel @ every.tfm).max() < 1e-10
    # uv points made only of barely covered cells are left out, and counted
    assert km.redundancy.min() >= 0.5 > every.redundancy.min()
    assert every.n_uv - km.n_uv == km.meta["n_uv_low_redundancy"] > 0
    assert km.n_kp == km.n_uv - km.rank


def test_transformed_model_turns_and_scales_uv():
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
    km2 = km.transformed(rotation=30 * u.deg, scale=1.02)
    a = np.deg2rad(30)
    rot = 1.02 * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    np.testing.assert_allclose(km2.uv.value, km.uv.value @ rot.T, atol=1e-12)
    np.testing.assert_allclose(km2.pupil.xy.value, km.pupil.xy.value @ rot.T, atol=1e-12)
    np.testing.assert_array_equal(km2.kernel, km.kernel)
    assert km2.pupil.meta["rotation_deg"] == pytest.approx(30)
    assert km.transformed() is km
    with pytest.raises(KpifsError, match="scale"):
        km.transformed(scale=0)


def test_phase_transfer_sign_matches_optics():
    """A small pupil phase phi gives Fourier phases R^-1 A phi in the simulator's images."""
    # binary: each cell's phase is the phase at its centre (a grey edge cell sees the
    # phase of its covered part only)
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.66 * u.m, grey=False))
    npup = 132
    img, dx = pupil_image("subaru", npix=npup)
    lam = 1.6e-6
    # a smooth, odd-and-even aberration: x^2 y + 0.5 x (coma-like + tilt-free part)
    c = (np.arange(npup) - (npup - 1) / 2) * dx
    gx, gy = np.meshgrid(c, c)
    phi = 0.02 * (gx ** 2 * gy / 8 + 0.3 * gy ** 2)
    opd = phi * lam / (2 * np.pi)
    cube = simulate_psf("subaru", [1.6] * u.um, pixscale=5 * u.mas, shape=(256, 256),
                        npup=npup, opd=opd)
    from kpifs import ExtractionWindow, extract_kernel_phases
    kpd = extract_kernel_phases(cube, km, wavelengths=[1.6] * u.um, pixscale=5 * u.mas,
                                centres=(128, 128), window=ExtractionWindow.default(
                                    cube.shape, radius=110))
    xy = km.pupil.xy.value
    ix = np.clip(np.rint(xy[:, 0] / dx + (npup - 1) / 2).astype(int), 0, npup - 1)
    iy = np.clip(np.rint(xy[:, 1] / dx + (npup - 1) / 2).astype(int), 0, npup - 1)
    predicted = km.tfm @ phi[iy, ix]
    measured = kpd.phases[0, 0]
    corr = np.corrcoef(predicted, measured)[0, 1]
    slope = np.dot(predicted, measured) / np.dot(predicted, predicted)
    # with the opposite sign convention both would be negative
    assert corr > 0.9
    assert 0.8 < slope < 1.2


def test_nyquist_guard_charis():
    km = load_kernel_model("subaru")
    wl = [1.16, 1.6] * u.um
    usable = nyquist_usable(km.uv, wl, 16.2 * u.mas)
    assert not usable[0].all()
    assert usable[1].all()
    with pytest.warns(KpifsWarning, match=r"1 channel.*1\.160"):
        reduced = km.for_wavelengths(wl, 16.2 * u.mas)
    assert reduced.n_uv == usable[0].sum()
    assert np.abs(reduced.kernel @ reduced.tfm).max() < 1e-10
    with pytest.raises(KpifsError, match="Nyquist"):
        km.for_wavelengths(wl, 16.2 * u.mas, on_nyquist="raise")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert km.for_wavelengths([1.6] * u.um, 16.2 * u.mas) is km


def test_fits_round_trip(tmp_path, subaru_model):
    path = tmp_path / "model.fits"
    subaru_model.write(path)
    with fits.open(path) as h:
        assert h[0].header["CONTENT"] == "KPFITS1"
        assert [x.name for x in h[1:]] == ["APERTURE", "UV-PLANE", "KER-MAT", "BLM-MAT"]
        assert h["UV-PLANE"].columns["RED"].format in ("D", "E")
    km = KernelModel.read(path)
    np.testing.assert_array_equal(km.kernel, subaru_model.kernel)
    np.testing.assert_array_equal(km.uv.value, subaru_model.uv.value)
    assert km.rank == subaru_model.rank
    assert load_kernel_model(str(path)).n_kp == subaru_model.n_kp
    with pytest.raises(KpifsError, match="exists"):
        subaru_model.write(path)
    subaru_model.write(path, overwrite=True)


def test_read_foreign_model_without_unit_rows(tmp_path):
    """Files of other tools: integer redundancies, non-normalised kernel rows, no BLM-MAT."""
    from kpifs.io.kpfits import model_hdus
    subaru_model = KernelModel.from_pupil(make_pupil("subaru", grey=False))
    hdus = model_hdus(subaru_model)[:3]
    hdus[1].data["RED"] = np.round(hdus[1].data["RED"])
    hdus[2].data = hdus[2].data * 3.0
    del hdus[2].header["RANK"]
    path = tmp_path / "foreign.fits"
    fits.HDUList([fits.PrimaryHDU(), *hdus]).writeto(path)
    km = KernelModel.read(path)
    np.testing.assert_allclose(np.linalg.norm(km.kernel, axis=1), 3.0)
    assert np.abs(km.kernel @ km.tfm).max() < 1e-9
    assert km.rank == subaru_model.rank


def test_signature_is_first_order_of_exact_model(subaru_model, paper_wavelengths):
    sig = subaru_model.signature([80, 60] * u.mas, paper_wavelengths)
    exact = subaru_model.binary_kernel_phases([80, 60] * u.mas, 1e-4, paper_wavelengths)
    np.testing.assert_allclose(exact, 1e-4 * sig, atol=1e-4 * 1e-3 * np.abs(sig).max() + 1e-12,
                               rtol=2e-3)
