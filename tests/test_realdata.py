"""Real third-party data (../shared/data/real); skipped when the folder is absent."""
import numpy as np
import pytest
import astropy.units as u

from kpifs import KernelModel, KernelPhaseData, extract_kernel_phases, make_pupil
from kpifs.calibration.calibrate import calibrate
from kpifs.covariance import whiten, whitening_matrix
from kpifs.io import read_cube
from kpifs.model.kernel import nyquist_usable

pytestmark = [pytest.mark.realdata,
              pytest.mark.filterwarnings("ignore:.*Ledoit-Wolf shrinkage")]


def test_sphere_v471tau_psf(real_data):
    path = real_data / "sphere_ifs_v471tau_psf.fits"
    with read_cube(path, instrument="sphere",
                   wavelengths=str(real_data / "sphere_ifs_v471tau_wl.fits")) as cube:
        assert cube.shape == (1, 39, 25, 25)
        assert cube.wavelengths[0].to_value(u.um) == pytest.approx(0.957557, rel=1e-5)
        km = KernelModel.from_pupil(make_pupil("vlt"))
        # no channel is Nyquist-limited at 7.46 mas: no warning, no uv point lost
        assert nyquist_usable(km.uv, cube.wavelengths, cube.pixscale).all()
        kpd = extract_kernel_phases(cube.data, km, wavelengths=cube.wavelengths,
                                    pixscale=cube.pixscale, source=str(path))
    assert kpd.shape == (1, 39, km.n_kp)
    assert np.all(np.isfinite(kpd.kp))
    # an unsaturated PSF: kernel phases much smaller than the raw Fourier phases
    ratio = np.std(kpd.phases, axis=2) / np.std(kpd.kp, axis=2)
    assert np.median(ratio) > 2


def test_sphere_wavelength_tables(real_data):
    from kpifs.io import read_wavelength_file
    yj = read_wavelength_file(real_data / "sphere_ifs_wave_YJ.fits")
    yjh = read_wavelength_file(real_data / "sphere_ifs_wave_YJH.fits")
    assert len(yj) == len(yjh) == 39
    assert yj[-1].to_value(u.um) == pytest.approx(1.329, abs=1e-3)
    assert yjh[-1].to_value(u.um) == pytest.approx(1.677, abs=1e-3)


def test_charis_wavelength_tables_match_header_grid(real_data):
    """The pipeline's lowres table is the LAM_MIN * exp(i DLOGLAM) grid of the simulator."""
    from kpifs.simulation.simulate import PRESETS
    table = np.loadtxt(real_data / "charis_wavelengths" / "lowres_wvlh.txt")
    grid = PRESETS["charis"]["wavelengths"].to_value(u.nm)
    np.testing.assert_allclose(grid, table, rtol=2e-3)


@pytest.fixture(scope="module")
def pharo(real_data):
    km = KernelModel.from_pupil(make_pupil("pharo", step=0.16 * u.m))
    out = {}
    for role, name in (("target", "pharo_tgt_cube_alphaOph.fits"),
                       ("calibrator", "pharo_ca2_cube_epsHer.fits")):
        with read_cube(real_data / name, wavelengths=[2.145] * u.um,
                       pixscale=25 * u.mas) as cube:
            out[role] = extract_kernel_phases(cube.data, km, wavelengths=cube.wavelengths,
                                              pixscale=cube.pixscale, source=name)
    return out


def _chi2(kpd):
    w = whitening_matrix(kpd.covariance)
    return float(np.sum(whiten(kpd.kp[0], w) ** 2))


def test_pharo_binary_detected_against_calibrator(pharo):
    """alpha Oph (a known binary) calibrated by eps Her: chi2 far above a null split."""
    tgt, cal = pharo["target"], pharo["calibrator"]
    assert tgt.shape == (100, 1, tgt.kernel_model.n_kp)
    chi2_target = _chi2(calibrate(tgt, cal))
    halves = [KernelPhaseData(cal.kp[i::2], cal.wavelengths, cal.pixscale, cal.kernel_model,
                              meta={"source": f"half {i}"}) for i in (0, 1)]
    chi2_null = _chi2(calibrate(*halves))
    n = tgt.n_kp
    # measured: ~4.3e4 against ~280 for 835 kernel phases
    assert chi2_null < 2 * n
    assert chi2_target > 20 * chi2_null
