import numpy as np
import pytest
import astropy.units as u
from astropy.io import fits

from kpifs import KpifsError
from kpifs.io.layouts import write_observation
from kpifs.simulation.simulate import SceneParameters, simulate_psf, simulate_scene


def test_paper_preset_truth_and_photometry():
    obs = simulate_scene("paper", n_frames=3, seed=7)
    flat = simulate_scene("paper", n_frames=3, seed=7, wavefront_rms=0 * u.nm)
    assert obs.target.shape == (3, 3, 40, 40)
    t = obs.truth
    assert t["KPSIMX"][0] == pytest.approx(80) and t["KPSIMY"][0] == pytest.approx(60)
    c = [t[f"KPSIMC{i}"][0] for i in (1, 2, 3)]
    assert np.mean(c) == pytest.approx(10 ** (-8 / 2.5), rel=1e-6)   # Delta H = 8
    assert c[0] > c[1] > c[2]                                        # brighter in the blue
    assert t["KPSIMSEE"][0] == 7
    # photon budget: m_H = 5, 10 % throughput, Subaru area, 0.08 um channels, 0.1 s
    expected = SceneParameters().star_photons()
    assert np.all(expected > 1e5)
    frac_in_field = simulate_psf("subaru", obs.wavelengths, pixscale=10.42 * u.mas,
                                 shape=(40, 40)).sum(axis=(1, 2))
    assert np.all((frac_in_field > 0.8) & (frac_in_field < 1))
    measured = flat.calibrator.sum(axis=(2, 3)).mean(0)
    np.testing.assert_allclose(measured, expected * frac_in_field, rtol=0.01)
    # aberrations scatter light out of the small field, more in the blue
    lost = 1 - obs.calibrator.sum(axis=(2, 3)).mean(0) / measured
    assert np.all(lost > 0) and lost[0] > lost[2]


def test_seeded_reproducible():
    a = simulate_scene("paper", n_frames=2, seed=3)
    b = simulate_scene("paper", n_frames=2, seed=3)
    c = simulate_scene("paper", n_frames=2, seed=4)
    np.testing.assert_array_equal(a.target, b.target)
    assert not np.array_equal(a.target, c.target)


def test_aberrations_new_every_frame():
    obs = simulate_scene("paper", n_frames=2, seed=1, read_noise=0.0, star_mag=-5)
    d = np.abs(obs.calibrator[0] - obs.calibrator[1]).sum() / obs.calibrator[0].sum()
    assert d > 0.02


@pytest.mark.parametrize("layout", ["plain", "charis", "sphere"])
def test_layouts(tmp_path, layout):
    preset = {"plain": "paper", "charis": "charis", "sphere": "sphere"}[layout]
    obs = simulate_scene(preset, n_frames=2, seed=2, shape=(48, 48), npup=64)
    paths = write_observation(obs, tmp_path, layout=layout)
    tgt = paths["target"]
    if layout == "plain":
        with fits.open(tgt[0]) as h:
            assert h[0].data.shape == (2, 3, 48, 48)
            assert h[0].header["KPWL2"] == pytest.approx(1.60)
            assert h[0].header["KPSIMX"] == pytest.approx(80)
    elif layout == "charis":
        assert len(tgt) == 2
        with fits.open(tgt[0]) as h:
            hdr = h[0].header
            assert h[0].data is None and h[1].data.shape == (22, 48, 48)
            wl = hdr["LAM_MIN"] * np.exp(np.arange(hdr["NLAM"]) * hdr["DLOGLAM"])
            assert wl[-1] == pytest.approx(hdr["LAM_MAX"]) == pytest.approx(2369.34, rel=1e-5)
            assert hdr["LAM_MIN"] == pytest.approx(1159.56)
            assert h[2].data.shape == (22, 48, 48)
            # a 48x48 cut lies inside the tilted field: only the 12 dead spaxels are bad
            assert np.all((h[2].data == 0).sum(axis=(1, 2)) == 12)
            assert h[1].header["CTYPE3"] == "AWAV-LOG"
    else:
        with fits.open(tgt[0]) as h:
            assert h[0].data.shape == (39, 2, 48, 48)
        with fits.open(tgt[1]) as h:
            assert h[0].data[0] == pytest.approx(957.0)
    with pytest.raises(KpifsError, match="exists"):
        write_observation(obs, tmp_path, layout=layout)


def test_charis_layout_needs_log_grid(tmp_path):
    obs = simulate_scene("paper", n_frames=1, seed=2, npup=64)
    with pytest.raises(KpifsError, match="log-uniform"):
        write_observation(obs, tmp_path, layout="charis")


def test_bad_preset():
    with pytest.raises(KpifsError, match="unknown preset"):
        simulate_scene("keck")
    with pytest.raises(KpifsError, match="bad simulation parameter"):
        simulate_scene("paper", colour="blue")


def test_charis_field_matches_real_lenslet_flat(real_data):
    from astropy.io import fits
    from kpifs.io.charis import charis_field
    flat = fits.getdata(real_data / "charis_lensletflat_Broadband.fits") > 0
    model = charis_field(flat.shape)
    overlap = (flat & model).sum() / (flat | model).sum()
    assert overlap > 0.95


def test_charis_preset_blanks_outside_field():
    obs = simulate_scene("charis", n_frames=1, seed=1, npup=64)
    assert obs.target.shape == (1, 22, 201, 201)
    assert obs.target[0, 0, 0, 0] == 0 and np.isinf(obs.variance_target[0, 0, 0, 0])
    assert 17000 < np.isfinite(obs.variance_target[0, 0]).sum() < 18000
    assert np.isinf(obs.variance_target[0, 0, 100, 100]) is np.False_


def _leading_block_ratio(kp, block=10, modes=4):
    """Variance of block means of the leading modes over what independent frames give."""
    dev = kp - kp.mean(0)
    vt = np.linalg.svd(dev, full_matrices=False)[2][:modes]
    a = dev @ vt.T
    b = a[: len(a) // block * block].reshape(-1, block, modes).mean(1)
    return float(np.mean(block * b.var(0, ddof=1) / a.var(0, ddof=1)))


def test_drifting_aberrations_correlate_frames():
    """Quasi-static aberrations drifting over ~10 frames: 10-frame block means of the
    kernel phases vary ~4x more than independent frames would (the PHARO frames: 3x)."""
    from kpifs import KernelModel, extract_kernel_phases, make_pupil
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.8 * u.m))
    ratio = {}
    for drift in (0, 60):
        obs = simulate_scene("paper", n_frames=60, seed=3, npup=48, wavelengths=[1.6] * u.um,
                             contrasts=0.0, wavefront_rms=30 * u.nm, drift_rms=drift * u.nm,
                             drift_time=10.0, exptime=1 * u.s)
        kp = extract_kernel_phases(obs.calibrator, km, wavelengths=obs.wavelengths,
                                   pixscale=obs.params.pixscale).kp[:, 0]
        ratio[drift] = _leading_block_ratio(kp)
    assert ratio[0] < 1.5 and ratio[60] > 3, ratio
    assert obs.truth["KPSIMDRF"][0] == 60.0 and obs.truth["KPSIMDRT"][0] == 10.0


def test_static_difference_is_a_calibration_residual():
    """A static aberration seen by the calibrator only offsets its mean kernel phases
    from the target's far beyond the frame noise of the mean; none without it."""
    from kpifs import KernelModel, extract_kernel_phases, make_pupil
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.8 * u.m))
    chi = {}
    for diff in (0, 20):
        obs = simulate_scene("paper", n_frames=30, seed=5, npup=48, wavelengths=[1.6] * u.um,
                             contrasts=0.0, wavefront_rms=30 * u.nm, static_rms=20 * u.nm,
                             static_diff_rms=diff * u.nm, exptime=1 * u.s)
        args = dict(wavelengths=obs.wavelengths, pixscale=obs.params.pixscale)
        t = extract_kernel_phases(obs.target, km, **args).kp[:, 0]
        c = extract_kernel_phases(obs.calibrator, km, **args).kp[:, 0]
        d = t.mean(0) - c.mean(0)
        var = t.var(0, ddof=1) / len(t) + c.var(0, ddof=1) / len(c)
        chi[diff] = float(np.mean(d ** 2 / var))
    assert chi[0] < 2 and chi[20] > 10, chi
