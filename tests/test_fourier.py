"""The Fourier paths of extraction (kpifs.model.fourier): the dense reference's phases."""
import numpy as np
import pytest
import astropy.units as u

from kpifs import ExtractionWindow, KernelModel, KpifsError, PupilModel, extract_kernel_phases, \
    make_pupil
from kpifs.model import fourier, window
from kpifs.model.fourier import fourier_operator, uv_lattice
from kpifs.model.kernel import MAS
from kpifs.simulation.simulate import simulate_psf

PIX = 10.42 * u.mas
WL = 1.6e-6


def _rotated(pupil, deg):
    t = np.deg2rad(deg)
    rot = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    return PupilModel(pupil.xy.value @ rot.T, pupil.transmission, step=pupil.step,
                      name=f"{pupil.name} turned {deg} deg")


@pytest.fixture(scope="module")
def psf_frames():
    """Realistic frames: PSF + companion + photon-like noise, star off-centre by sub-pixels."""
    rng = np.random.default_rng(4)
    img = simulate_psf("subaru", [1.6] * u.um, pixscale=PIX, shape=(40, 40), npup=64,
                       companions=[([80, 60] * u.mas, 1e-2)])[0]
    frames = 1e5 * img[None] * (1 + 0.01 * rng.standard_normal((6, 1, 1)))
    return frames + rng.normal(0, 3, frames.shape)


def _phases(op, images):
    re, im = op.apply(images)
    return np.arctan2(im, re)


def _wrap(x):
    return (x + np.pi) % (2 * np.pi) - np.pi


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.17, 0.11), (-0.05, 0.31)])
def test_square_grids_are_separable_whatever_the_offset(offset):
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.5 * u.m, offset=offset * u.m))
    lat = uv_lattice(km.uv.value)
    assert lat is not None
    sx, sy, m, n = lat
    assert sx == pytest.approx(0.5, rel=1e-12) and sy == pytest.approx(0.5, rel=1e-12)
    np.testing.assert_allclose(np.column_stack([m * sx, n * sy]), km.uv.value, atol=1e-12)
    assert fourier_operator(km.uv.value, WL, PIX.value * MAS, (32, 32)).method == "separable"


def test_hexagonal_grids_lie_on_a_rectangular_lattice():
    """Hexagonal baselines are multiples of (s/2, s sqrt(3)/2): separable too."""
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m, hexagonal=True))
    sx, sy, m, n = uv_lattice(km.uv.value)
    assert sx == pytest.approx(0.3, rel=1e-12)
    assert sy == pytest.approx(0.6 * np.sqrt(3) / 2, rel=1e-12)
    assert np.all((m + n) % 2 == 0)           # the hexagonal sub-lattice


@pytest.mark.parametrize("deg", [-2.0, 0.7, 30.0])
def test_rotated_models_fall_back(deg):
    km = KernelModel.from_pupil(_rotated(make_pupil("subaru", step=0.5 * u.m), deg))
    assert uv_lattice(km.uv.value) is None
    op = fourier_operator(km.uv.value, WL, PIX.value * MAS, (32, 32))
    assert op.method in ("nufft", "dense")
    with pytest.raises(KpifsError, match="not on a rectangular lattice"):
        fourier_operator(km.uv.value, WL, PIX.value * MAS, (32, 32), method="separable")


def test_irregular_points_fall_back():
    rng = np.random.default_rng(1)
    assert uv_lattice(rng.uniform(-4, 4, (50, 2))) is None


@pytest.mark.parametrize("model", ["square", "hexagonal"])
def test_separable_agrees_with_dense(model, psf_frames):
    pup = make_pupil("subaru", hexagonal=(model == "hexagonal"),
                     step=(0.6 if model == "hexagonal" else 0.38) * u.m)
    uv = KernelModel.from_pupil(pup).uv.value
    dense = fourier_operator(uv, WL, PIX.value * MAS, (40, 40), method="dense")
    sep = fourier_operator(uv, WL, PIX.value * MAS, (40, 40), method="separable")
    assert sep.flops < dense.flops / 4
    assert np.abs(_wrap(_phases(sep, psf_frames) - _phases(dense, psf_frames))).max() < 1e-9
    np.testing.assert_allclose(np.hypot(*sep.apply(psf_frames)),
                               np.hypot(*dense.apply(psf_frames)), rtol=1e-9)


def test_nufft_agrees_with_dense_on_a_rotated_model(psf_frames):
    pytest.importorskip("finufft")
    uv = KernelModel.from_pupil(_rotated(make_pupil("subaru"), -2.0)).uv.value
    dense = fourier_operator(uv, WL, PIX.value * MAS, (40, 40), method="dense")
    nu = fourier_operator(uv, WL, PIX.value * MAS, (40, 40), method="nufft")
    assert np.abs(_wrap(_phases(nu, psf_frames) - _phases(dense, psf_frames))).max() < 1e-6


def test_single_precision_error_is_small(psf_frames):
    """float32 products: phase errors ~1e-5 rad at the faintest uv points of a PSF."""
    uv = KernelModel.from_pupil(make_pupil("subaru")).uv.value
    ref = _phases(fourier_operator(uv, WL, PIX.value * MAS, (40, 40), method="dense"),
                  psf_frames)
    for method in ("separable", "dense"):
        op = fourier_operator(uv, WL, PIX.value * MAS, (40, 40), method=method,
                              dtype=np.float32)
        assert np.abs(_wrap(_phases(op, psf_frames) - ref)).max() < 1e-3


@pytest.mark.parametrize("method", ["separable", "dense", "auto"])
def test_extraction_paths_agree(method, paper_wavelengths, rng):
    km = KernelModel.from_pupil(make_pupil("subaru"))
    cube = simulate_psf("subaru", paper_wavelengths, pixscale=PIX, shape=(40, 40),
                        companions=[([80, 60] * u.mas, 1e-2)])
    frames = 1e5 * cube[None] * (1 + 0.01 * rng.standard_normal((4, 3, 1, 1)))
    centres = 20 + rng.uniform(-0.4, 0.4, (4, 3, 2))
    args = dict(wavelengths=paper_wavelengths, pixscale=PIX, centres=centres)
    ref = extract_kernel_phases(frames, km, fourier="dense", **args)
    kpd = extract_kernel_phases(frames, km, fourier=method, **args)
    assert np.abs(kpd.kp - ref.kp).max() < 1e-9
    assert np.abs(_wrap(kpd.phases - ref.phases)).max() < 1e-9


def test_unknown_fourier_method(paper_wavelengths):
    with pytest.raises(KpifsError, match="unknown Fourier method"):
        extract_kernel_phases(np.ones((3, 16, 16)), "subaru", wavelengths=paper_wavelengths,
                              pixscale=PIX, fourier="fft")


def test_operators_shared_across_models_and_cache_bounded(monkeypatch):
    fourier.clear_cache()
    pup = make_pupil("subaru", step=0.8 * u.m)
    a, b = KernelModel.from_pupil(pup), KernelModel.from_pupil(pup)   # a model per file
    assert a.dft_matrix(1.6 * u.um, PIX, (24, 24)) is b.dft_matrix(1.6 * u.um, PIX, (24, 24))
    op = fourier_operator(a.uv.value, WL, PIX.value * MAS, (24, 24))
    assert fourier_operator(b.uv.value, WL, PIX.value * MAS, (24, 24)) is op
    one = fourier.cache_info()[1] // 2 + 1
    monkeypatch.setattr(fourier, "CACHE_BYTES", 3 * one)
    for i in range(10):
        a.dft_matrix((1.6 + 0.01 * i) * u.um, PIX, (24, 24))
        n, nbytes = fourier.cache_info()
        assert nbytes <= 3 * one or n == 1
    monkeypatch.setattr(fourier, "CACHE_ENTRIES", 4)
    for i in range(10):
        fourier_operator(a.uv.value, WL * (1 + 0.01 * i), PIX.value * MAS, (24, 24))
    assert fourier.cache_info()[0] <= 4
    fourier.clear_cache()
    assert fourier.cache_info() == (0, 0)


def test_quantised_windows_cached_and_close(monkeypatch):
    win = ExtractionWindow(32, 12.8)
    rng = np.random.default_rng(2)
    delta = rng.uniform(-0.5, 0.5, (50, 2))
    exact = win.apply(np.ones((50, 32, 32)), delta, quantum=None)
    quant = win.apply(np.ones((50, 32, 32)), delta)
    # rounding alone would err by up to |grad w| q / sqrt(2) (slope <= 1.51 / radius);
    # the first-order correction leaves the curvature term, ~(q/2)^2 / radius^2
    assert np.abs(quant - exact).max() < 1e-2 * 1.51 / 12.8 * window.WINDOW_QUANTUM
    assert np.abs(quant - exact).max() > 0
    for order in (2.0, 1.0, np.inf):
        w = ExtractionWindow(32, 12.8, order)
        np.testing.assert_allclose(w.apply(np.ones((50, 32, 32)), delta),
                                   w.weights(delta), rtol=0, atol=1e-5)
    monkeypatch.setattr(window, "WINDOW_CACHE_BYTES", 10 * 32 * 32 * 8)
    win.apply(np.ones((50, 32, 32)), rng.uniform(-0.5, 0.5, (50, 2)))
    assert len(window._window_cache) <= 10 / 3


def test_extract_command_imports_no_scipy():
    """`kpifs extract` needs neither scipy.stats nor scipy.optimize (loaded on first use)."""
    import subprocess
    import sys
    code = ("import sys, kpifs._cli.extract; "
            "print(sorted(m for m in ('scipy.stats', 'scipy.optimize') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_extract_command_imports_no_analysis_module(tmp_path):
    """A whole `kpifs extract` run (read, extract, write) never loads scipy's statistics
    and optimisers nor matplotlib. (The one driver imports the detection modules, in
    plain sight: they and astropy.table cost about 0.2 s of start-up.)"""
    import subprocess
    import sys
    from kpifs.io.layouts import write_plain_cube
    wl = [1.6, 1.7] * u.um
    cube = simulate_psf("subaru", wl, pixscale=PIX, shape=(32, 32))
    frames = np.stack([1e5 * cube, 1.01e5 * cube, 0.99e5 * cube]).astype(np.float32)
    path = str(tmp_path / "c.fits")
    write_plain_cube(path, frames, wl, PIX)
    code = ("import sys\nfrom kpifs.cli import main\n"
            f"assert main(['extract', {path!r}, '-o', {str(tmp_path / 'kp.fits')!r}, '-q']) == 0\n"
            "print(sorted(m for m in ('scipy.stats', 'scipy.optimize', 'matplotlib') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "[]"


def test_separable_uses_half_the_x_frequencies_and_stays_exact(psf_frames):
    """Products for |m| only (cos even, sin odd in m): the same V as dense, to rounding."""
    uv = KernelModel.from_pupil(make_pupil("subaru")).uv.value
    sep = fourier_operator(uv, WL, PIX.value * MAS, (40, 40), method="separable")
    dense = fourier_operator(uv, WL, PIX.value * MAS, (40, 40), method="dense")
    m = uv_lattice(uv)[2]
    assert (m < 0).any() and sep._ex.shape[1] == 2 * len(np.unique(np.abs(m)))
    for a, b in zip(sep.apply(psf_frames), dense.apply(psf_frames)):
        assert np.abs(a - b).max() < 1e-12 * np.abs(b).max()


def test_windows_into_out_and_phase_wrap():
    """`ExtractionWindow.apply(out=)` equals the in-place product; the cheap phase wrap of
    extraction equals ``(x + pi) % 2 pi - pi``."""
    from kpifs.extraction.extract import _wrap_phases
    rng = np.random.default_rng(7)
    win = ExtractionWindow(32, 12.8)
    imgs = rng.random((20, 40, 40))
    delta = rng.uniform(-0.5, 0.5, (20, 2))
    view = imgs[:, 4:36, 4:36]
    out = win.apply(view, delta, out=np.empty((20, 32, 32)))
    np.testing.assert_array_equal(out, win.apply(view.copy(), delta))
    assert np.array_equal(imgs[:, 4:36, 4:36], view)           # the input is left alone
    for spread in (np.pi + 2.3, 40.0):                          # one turn, and many
        ph = rng.uniform(-spread, spread, (50, 300))
        ref = _wrap(ph)
        assert np.abs(_wrap_phases(ph.copy()) - ref).max() < 1e-12


def test_single_precision_extraction_error_against_photon_noise():
    """precision='single': kernel phases within a few 1e-6 rad of the dense float64
    reference, a few 1e-4 of the frame-to-frame (photon-noise) scatter of the frames."""
    rng = np.random.default_rng(11)
    wl = [1.2, 1.6, 2.2] * u.um
    pix = PIX
    jit = rng.uniform(-0.4, 0.4, (4, 2))
    psfs = np.stack([simulate_psf("subaru", wl, pixscale=pix, shape=(48, 48), npup=64,
                                  centre=tuple(j)) for j in jit])
    frames = rng.poisson(2e5 * psfs[rng.integers(0, 4, 24)]) + rng.normal(0, 10, (24, 3, 48, 48))
    frames = frames.astype(np.float32)
    km = KernelModel.from_pupil(make_pupil("subaru"))
    args = dict(wavelengths=wl, pixscale=pix)
    ref = extract_kernel_phases(frames, km, fourier="dense", **args)
    dbl = extract_kernel_phases(frames, km, **args)
    sgl = extract_kernel_phases(frames, km, precision="single", **args)
    assert np.abs(dbl.kp - ref.kp).max() < 1e-9
    err = np.abs(sgl.kp - ref.kp)
    noise = ref.kp.std(axis=0)
    assert 0 < err.max() < 2e-5
    assert (err / noise).max() < 2e-3
    with pytest.raises(KpifsError, match="precision"):
        extract_kernel_phases(frames, km, precision="half", **args)
