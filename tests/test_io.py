import numpy as np
import pytest
import astropy.units as u
from astropy.io import fits

from kpifs import KpifsError, extract_kernel_phases
from kpifs import ExtractionWindow
from kpifs.io import read_charis, read_cube, read_sphere, read_wavelength_file, write_observation
from kpifs.io.cube import FrameStack
from kpifs.simulation.simulate import simulate_scene


@pytest.fixture(scope="module")
def charis_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("charis")
    obs = simulate_scene("charis", n_frames=3, seed=4, npup=48)
    return write_observation(obs, d, layout="charis"), obs


@pytest.fixture(scope="module")
def sphere_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("sphere")
    obs = simulate_scene("sphere", n_frames=3, seed=4, npup=48)
    return write_observation(obs, d, layout="sphere"), obs


def test_charis_reader(charis_files):
    files, obs = charis_files
    with read_cube(files["target"]) as cube:
        assert cube.instrument == "charis"
        assert cube.shape == (3, 22, 201, 201)
        np.testing.assert_allclose(cube.wavelengths.to_value(u.um),
                                   obs.wavelengths.to_value(u.um), rtol=1e-6)
        assert cube.pixscale == 16.2 * u.mas
        assert cube.angles.shape == (3,)
        sl = cube.data[1:3, 4]
        assert sl.shape == (2, 201, 201)
        # dead spaxels (ivar == 0, garbage values) are NaN; outside the field stays 0
        assert np.isnan(sl).sum() == 2 * 12
        assert sl[0, 0, 0] == 0
        good = np.isfinite(sl)
        np.testing.assert_allclose(sl[good], obs.target[1:3, 4][good], rtol=1e-6)
        assert "(+2 more)" in cube.name
    with read_charis(files["target"][0], pixscale=16.4 * u.mas) as one:
        assert one.shape == (1, 22, 201, 201) and one.pixscale == 16.4 * u.mas


def _edit_charis(src, dst, **cards):
    with fits.open(src) as h:
        for k, v in cards.items():
            if v is None:
                del h[0].header[k]
            else:
                h[0].header[k] = v
        h.writeto(dst)


@pytest.mark.parametrize("cards, match", [
    (dict(NLAM=21), "NLAM = 21 but the cube has 22"),
    (dict(LAM_MAX=2500.0), "LAM_MAX = 2500.0 nm disagrees"),
    (dict(DLOGLAM=None), r"missing wavelength keyword\(s\) 'DLOGLAM'"),
    (dict(LAM_MIN=1.15956), "not a wavelength in nm"),
    (dict(LAM_MIN="abc"), "bad wavelength keyword"),
])
def test_charis_bad_wavelength_keys(charis_files, tmp_path, cards, match):
    files, _ = charis_files
    dst = tmp_path / "bad_cube.fits"
    _edit_charis(files["target"][0], dst, **cards)
    with pytest.raises(KpifsError, match=match) as err:
        read_charis(dst)
    assert "bad_cube.fits" in str(err.value)


def test_charis_parang_unavailable(charis_files, tmp_path):
    files, _ = charis_files
    dst = tmp_path / "noparang_cube.fits"
    _edit_charis(files["target"][0], dst, PARANG="unavailable")
    with read_charis(dst) as cube:
        assert np.isnan(cube.angles[0])


def test_sphere_reader_4d_and_3d(sphere_files, tmp_path):
    files, obs = sphere_files
    cube_path, wave_path, angle_path = files["target"]
    with read_cube(cube_path) as cube:            # INSTRUME = SPHERE, wavelength.fits beside
        assert cube.instrument == "sphere"
        assert cube.shape == (3, 39, 64, 64)
        np.testing.assert_allclose(cube.wavelengths.to_value(u.um),
                                   obs.wavelengths.to_value(u.um), rtol=1e-6)
        np.testing.assert_allclose(np.asarray(cube.data[2, 7]), obs.target[2, 7])
        assert cube.pixscale == 7.46 * u.mas
    three = tmp_path / "cube3d.fits"
    fits.writeto(three, obs.target[0].astype(np.float32))
    with read_sphere(three, wavelengths=wave_path) as cube:
        assert cube.shape == (1, 39, 64, 64)


def test_sphere_data_center_conventions(sphere_files, tmp_path):
    files, obs = sphere_files
    hdr = fits.Header()
    hdr["HIERARCH ESO PRO REC1 ID"] = "sph_ifs_science_dr"
    data = np.swapaxes(obs.target, 0, 1).astype(np.float32)
    fits.writeto(tmp_path / "dc_cube.fits", data, hdr)
    fits.writeto(tmp_path / "dc_lambda.fits", obs.wavelengths.to_value(u.um))
    fits.writeto(tmp_path / "dc_angles.fits", np.array([10.0, 11.0, 12.0]))
    with read_cube(tmp_path / "dc_cube.fits", wavelengths=str(tmp_path / "dc_lambda.fits"),
                   angles=str(tmp_path / "dc_angles.fits")) as cube:
        assert cube.instrument == "sphere"
        assert cube.wavelengths[0].to_value(u.um) == pytest.approx(0.957)
        np.testing.assert_allclose(cube.angles.to_value(u.deg), [-10, -11, -12])


@pytest.mark.parametrize("values, unit", [([957.0, 1000.0, 1329.0], "nm"),
                                          ([0.957, 1.0, 1.329], "um"),
                                          ([9.57e-7, 1e-6, 1.329e-6], "m")])
def test_wavelength_units_told_apart(tmp_path, values, unit):
    f = tmp_path / "wl.txt"
    np.savetxt(f, values)
    wl = read_wavelength_file(f)
    assert wl[0].to_value(u.um) == pytest.approx(0.957)
    fits.writeto(tmp_path / "wl.fits", np.array(values))
    assert read_wavelength_file(tmp_path / "wl.fits")[2].to_value(u.um) == pytest.approx(1.329)


def test_wavelength_unit_ambiguous(tmp_path):
    f = tmp_path / "wl.txt"
    np.savetxt(f, [50.0, 60.0])
    with pytest.raises(KpifsError, match="cannot tell the unit"):
        read_wavelength_file(f)


def test_generic_frames_at_one_wavelength(tmp_path):
    fits.writeto(tmp_path / "stack.fits", np.random.default_rng(0).random((7, 16, 16)))
    with read_cube(tmp_path / "stack.fits", wavelengths=[2.145] * u.um,
                   pixscale=25 * u.mas) as cube:
        assert cube.shape == (7, 1, 16, 16)


def test_several_generic_files_concatenate(tmp_path):
    obs = simulate_scene("paper", n_frames=2, seed=1, npup=32)
    a = write_observation(obs, tmp_path / "a")["target"][0]
    b = write_observation(obs, tmp_path / "b")["target"][0]
    with read_cube([a, b]) as cube:
        assert cube.shape == (4, 3, 40, 40)
        np.testing.assert_allclose(cube.data[2:4, 1], obs.target[:, 1])


def test_frame_stack_is_lazy():
    class Counting:
        def __init__(self, arr):
            self.arr, self.shape, self.reads = arr, arr.shape, 0

        def __getitem__(self, key):
            self.reads += 1
            return self.arr[key]
    parts = [Counting(np.full((2, 3, 4, 4), i, float)) for i in range(3)]
    stack = FrameStack(parts)
    assert stack.shape == (6, 3, 4, 4) and sum(p.reads for p in parts) == 0
    chunk = stack[1:3, 2]
    np.testing.assert_array_equal(chunk[:, 0, 0], [0, 1])
    assert parts[2].reads == 0


def test_extraction_from_charis_reader(charis_files):
    files, _ = charis_files
    with read_cube(files["calibrator"]) as cube:
        with pytest.warns(Warning, match="Nyquist"):
            kpd = extract_kernel_phases(cube.data, "subaru", wavelengths=cube.wavelengths,
                                        pixscale=cube.pixscale,
                                        window=ExtractionWindow.default(cube.shape, size=64),
                                        source=cube.name)
    assert kpd.shape[:2] == (3, 22) and np.all(np.isfinite(kpd.kp))
    # the 12 dead spaxels per slice were filled, not propagated
    assert kpd.meta["n_bad_pixels"] == 3 * 22 * 12


def test_read_cube_rejects_mixed_inputs(charis_files, sphere_files):
    with pytest.raises(KpifsError, match="different kinds"):
        read_cube([charis_files[0]["target"][0], sphere_files[0]["target"][0]])
    with pytest.raises(KpifsError, match="unknown instrument"):
        read_cube(charis_files[0]["target"][0], instrument="osiris")
