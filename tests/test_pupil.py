import numpy as np
import pytest
import astropy.units as u
from astropy.io import fits

from kpifs import KernelModel, KpifsError, make_pupil
from kpifs.model.pupil import MODEL_DEFAULTS, TELESCOPES, model_defaults, pupil_image


def test_subaru_default_model_size():
    pup = make_pupil("subaru", grey=False)
    # binary: 0.38 m grid, cells >= 90 % inside the pupil (see module docs)
    assert pup.n_sub == 242
    assert pup.is_binary
    assert not pup.is_centrosymmetric()
    # every kept cell is inside the outer rim and outside the obstruction
    r = np.hypot(*pup.xy.value.T)
    assert r.max() < 7.92 / 2 and r.min() > 2.3 / 2


def test_paper_sized_model_with_partial_cells():
    # keeping half-covered cells at a 0.365 m step gives the paper's ~320 sub-pupils
    pup = make_pupil("subaru", step=0.365 * u.m, min_transmission=0.5)
    assert 310 <= pup.n_sub <= 330


def test_area_matches_geometry():
    # a grey model with all partial cells integrates the pupil area
    pup = make_pupil("annular", diameter=8 * u.m, obstruction=2 * u.m, step=0.2 * u.m,
                     grey=True, min_transmission=1e-3)
    area = np.sum(pup.transmission) * 0.2 ** 2
    assert area == pytest.approx(np.pi / 4 * (64 - 4), rel=2e-3)


def test_vlt_and_hexagonal():
    pup = make_pupil("vlt", hexagonal=True, step=0.5 * u.m)
    # hexagonal cell area is sqrt(3)/2 step^2
    geo = TELESCOPES["vlt"]
    area = np.pi / 4 * (geo.diameter ** 2 - geo.obstruction ** 2)
    assert pup.n_sub == pytest.approx(area / (np.sqrt(3) / 2 * 0.25), rel=0.15)
    d = np.hypot(*(pup.xy.value[:, None] - pup.xy.value[None]).transpose(2, 0, 1))
    assert np.min(d[d > 0]) == pytest.approx(0.5)


def test_centrosymmetric_model_has_half_rank():
    pup = make_pupil("subaru", offset=(0, 0) * u.m)
    assert pup.is_centrosymmetric()
    km = KernelModel.from_pupil(pup)
    # even pupil phases give no Fourier phase: rank = n_sub / 2, not n_sub - 1
    assert km.rank == pup.n_sub // 2
    km2 = KernelModel.from_pupil(make_pupil("subaru"))
    assert km2.rank == km2.pupil.n_sub - 1


def test_pupil_from_fits_image(tmp_path):
    img, dx = pupil_image("vlt", npix=200)
    path = tmp_path / "pupil.fits"
    hdu = fits.PrimaryHDU(img)
    hdu.header["PUPSCALE"] = dx
    hdu.writeto(path)
    from_img = make_pupil(str(path), step=0.5 * u.m, offset=(0.1, 0.05) * u.m)
    analytic = make_pupil("vlt", step=0.5 * u.m, offset=(0.1, 0.05) * u.m)
    assert abs(from_img.n_sub - analytic.n_sub) <= 4
    # without PUPSCALE the pixel size must be given
    fits.PrimaryHDU(img).writeto(tmp_path / "noscale.fits")
    with pytest.raises(KpifsError, match="PUPSCALE"):
        make_pupil(str(tmp_path / "noscale.fits"))
    assert make_pupil(str(tmp_path / "noscale.fits"), pupil_scale=dx * u.m,
                      step=0.5 * u.m, offset=(0.1, 0.05) * u.m).n_sub == from_img.n_sub


def test_rotation_turns_the_model():
    a = make_pupil("subaru", offset=(0, 0) * u.m, min_transmission=0.5)
    b = make_pupil("subaru", offset=(0, 0) * u.m, min_transmission=0.5, rotation=90 * u.deg)
    # the whole model (grid and aperture) turns: same cells, positions turned by 90 deg
    np.testing.assert_allclose(b.xy.value, a.xy.value @ np.array([[0, 1], [-1, 0]]),
                               atol=1e-12)
    np.testing.assert_array_equal(a.transmission, b.transmission)
    # ... and sits on the turned pupil: every cell of b is (mostly) inside it
    img_fn = TELESCOPES["subaru"].transmission
    c, s = np.cos(np.pi / 2), np.sin(np.pi / 2)
    x, y = b.xy.value.T
    assert img_fn(c * x + s * y, -s * x + c * y).mean() > 0.9


def test_per_pupil_defaults():
    """Grey models by default, with each pupil's step (MODEL_DEFAULTS, with sources)."""
    for name in ("subaru", "vlt", "pharo", "charis", "sphere", "scexao"):
        d = MODEL_DEFAULTS[name]
        assert d.grey and d.source
        pup = make_pupil(name)
        assert not pup.is_binary
        assert pup.step.to_value(u.m) == d.step
        assert pup.transmission.min() >= d.min_transmission
        assert pup.meta["min_redundancy"] == d.min_redundancy
    assert make_pupil("pharo").step == 0.16 * u.m
    assert model_defaults("annular") is MODEL_DEFAULTS["generic"]
    annulus = make_pupil("annular", diameter=4 * u.m, obstruction=1 * u.m)
    assert not annulus.is_binary
    # binary on request, with its own cut
    binary = make_pupil("subaru", grey=False)
    assert binary.is_binary and binary.meta["min_transmission"] == 0.9
    assert binary.meta["min_redundancy"] == 0


def test_grey_default_for_pupil_images(tmp_path):
    img, dx = pupil_image("vlt", npix=200)
    path = tmp_path / "pupil.fits"
    fits.PrimaryHDU(img, header=fits.Header({"PUPSCALE": dx})).writeto(path)
    pup = make_pupil(str(path), step=0.5 * u.m)
    assert not pup.is_binary and pup.transmission.min() >= 0.2


def test_supersampled_pupil_turns_smoothly():
    # the anti-aliased pupil's area changes by far less than a pixel's between close angles
    a, _ = pupil_image("subaru", npix=64, rotation=1.0 * u.deg, supersample=4)
    b, _ = pupil_image("subaru", npix=64, rotation=1.05 * u.deg, supersample=4)
    assert abs(a.sum() - b.sum()) < 0.5 and 0 < a.min() + 1 and 0 < a[a > 0].min() < 1


@pytest.mark.parametrize("kwargs, match", [
    (dict(pupil="hubble"), "unknown pupil"),
    (dict(pupil="circular"), "diameter"),
    (dict(pupil="subaru", step=-1 * u.m), "step"),
    (dict(pupil="subaru", step=5 * u.m, grey=False), "fewer than two"),
    (dict(pupil="subaru", min_redundancy=-1), "min_redundancy"),
    (dict(pupil="subaru", min_transmission=1.5), "min_transmission"),
    (dict(pupil="subaru", step=0.4 * u.s), "wrong unit"),
])
def test_bad_pupil_input(kwargs, match):
    with pytest.raises(KpifsError, match=match):
        make_pupil(**kwargs)


@pytest.mark.parametrize("canonical, other, n_holes, n_kp", [
    ("niriss_nrm", "NIRISS-NRM", 7, 15), ("sphere_sam7", "sphere-sam7", 7, 15),
    ("gpi_nrm", "gpi-nrm", 10, 36)])
def test_one_model_per_mask_in_either_spelling(canonical, other, n_holes, n_kp):
    """Issues 27 and 28 named the masks twice: one `MaskGeometry` each, both spellings."""
    from kpifs.model.pupil import MASKS, MaskGeometry
    assert MASKS[other] is MASKS[canonical] and isinstance(MASKS[canonical], MaskGeometry)
    a, b = make_pupil(canonical), make_pupil(other, step=0 * u.m, offset=(1, 1) * u.m)
    assert a.name == b.name == canonical
    np.testing.assert_array_equal(a.xy.value, b.xy.value)      # grid options ignored
    grid = make_pupil(other, step=0.1 * u.m)                   # a step discretises the holes
    assert grid.name == canonical and grid.n_sub > 20 * n_holes
    km = KernelModel.from_pupil(a)
    assert (a.n_sub, km.n_uv, km.n_kp) == (n_holes, n_holes * (n_holes - 1) // 2,
                                           (n_holes - 1) * (n_holes - 2) // 2)
    assert km.n_kp == n_kp
    # the step is half a hole: the search reaches lambda / D_hole
    assert a.step.to_value(u.m) == pytest.approx(MASKS[canonical].hole_diameter / 2)
    assert model_defaults(other) is MODEL_DEFAULTS[canonical]
    img, _ = pupil_image(other, npix=64)
    assert img.sum() > 0


def test_mask_geometry_published_numbers():
    """NIRISS: the as-built g7s6 holes (V2 reversed), hexagons of 0.82 m; GPI: the g10s40
    centres times 647.62 (FORMATS.md), 45 baselines from 0.95 to 6.68 m."""
    from kpifs.model.pupil import MASKS
    nrm = MASKS["niriss_nrm"]
    assert nrm.shape == "hex" and nrm.hole_diameter == 0.82
    assert (2.28631, 0.0) in nrm.holes and (-2.28631, 0.0) not in nrm.holes   # C2 open
    assert nrm.area == pytest.approx(7 * np.sqrt(3) / 2 * 0.82 ** 2)
    # the hexagon's corners are inside its circumscribed circle: 0.82 m * 2 / sqrt(3)
    assert nrm.diameter == pytest.approx(2 * 2.64 + 0.82 * 2 / np.sqrt(3))
    gpi = np.asarray(MASKS["gpi_nrm"].holes)
    b = np.hypot(*(gpi[:, None] - gpi[None]).reshape(-1, 2).T)
    b = np.unique(np.round(b[b > 0], 6))
    assert len(b) == 45 and b.min() == pytest.approx(0.95, abs=0.01)
    assert b.max() == pytest.approx(6.68, abs=0.01)
    assert MASKS["gpi_nrm"].hole_diameter == pytest.approx(0.596, abs=1e-3)


def test_unknown_pupil_lists_the_masks():
    with pytest.raises(KpifsError, match="gpi_nrm, niriss_nrm, sphere_sam7"):
        make_pupil("niriss_nmr")
