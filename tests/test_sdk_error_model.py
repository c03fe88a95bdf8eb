"""Issue 39: the error model of a spectral-differential search with no calibrator.

Each combination is whitened by its channels' covariances summed, scaled to the
variance its covariance rows (the frames' deviations) hold, so that the data's
reduced chi-square reads the rows' scale; what the static profiles leave of a static
residual is a term of free amplitude, fitted to the combinations by maximum
likelihood, in the whitening and the rows."""
import numpy as np
import pytest
from astropy import units as u

from kpifs import KernelModel, KernelPhaseData, make_pupil
from kpifs.calibration.spectral_diff import spectral_differential
from kpifs.detect.sdk import SpectralStack
from kpifs.exceptions import KpifsError

WL = np.linspace(1.16, 2.37, 8) * u.um


@pytest.fixture(scope="module")
def km():
    return KernelModel.from_pupil(make_pupil("subaru", step=1.2 * u.m))


def _frames(rng, km, n, mix):
    """*n* frames of noise correlated across the channels: a noise shared by every
    channel with weights *mix* (q,), plus each channel's own."""
    q, p = len(WL), km.n_kp
    shared = rng.normal(0, 1, (n, 1, p)) * mix[None, :, None]
    return shared + rng.normal(0, 0.5, (n, q, p))


def _stack(km, frames, **kw):
    sdk = spectral_differential(KernelPhaseData(frames, WL, 16.2 * u.mas, km), order=2,
                                shrinkage="none")
    return SpectralStack(sdk, sdk.kp[0], sdk.covariance, **kw)


def test_rows_hold_the_whitened_variance(km):
    """Scaled, each combination's covariance rows hold one unit of variance per degree
    of freedom of its whitening (their trace is the rank); unscaled, they hold less
    when the noise is correlated across the channels (the summed covariance ignores
    the cancellation in a combination)."""
    rng = np.random.default_rng(11)
    frames = _frames(rng, km, 80, rng.normal(0, 2, len(WL)))
    st = _stack(km, frames, static="none", normalise="combination")
    assert np.allclose(np.sum(st.rows ** 2, axis=(0, 2)), st.rank, rtol=1e-9)
    raw = _stack(km, frames, static="none", normalise="none")
    assert raw.rows_variance is None
    spread = np.sum(raw.rows ** 2, axis=(0, 2)) / raw.rank
    assert spread.max() / spread.min() > 2
    one = _stack(km, frames, static="none")
    total = np.sum(one.rows ** 2, axis=(0, 2))
    assert np.isclose(total.sum(), one.rank.sum(), rtol=1e-9)
    # one scale for all: the combinations keep the unscaled whitening's relative weights
    assert np.allclose(total / one.rank, spread * one.rank.sum() / np.sum(spread * raw.rank))
    with pytest.raises(KpifsError, match="normalise"):
        _stack(km, frames, normalise="yes")


def test_whitened_energy_of_noise_is_its_dof(km):
    """Companion-free sequences whose noise is shared across the channels, whitened by
    a covariance independent of their frames (4000 other frames): the whitened energy
    over the degrees of freedom, times the frames' autocorrelation time that scales
    the rows (`frames_autocorrelation`), has mean 1 (a little more: the rows' variance
    divides, so by Jensen about 1 + 2 / n_eff, measured 1.02). 200 sequences of 80
    frames; each ratio's spread is measured 0.23, so the mean of 200 has a standard
    deviation of 0.016: 0.1 is 4.7 sigma from the mean measured.
    (Whitened by their own frames' covariance, the energy exceeds the rows' variance:
    the search's noise scale, measured on the data, takes that up.)"""
    rng = np.random.default_rng(5)
    mix = rng.normal(0, 2, len(WL))
    ref = _frames(rng, km, 4000, mix)
    cov = np.stack([np.cov(ref[:, c], rowvar=False) for c in range(len(WL))]) / 80
    ratio = []
    for _ in range(200):
        sdk = spectral_differential(KernelPhaseData(_frames(rng, km, 80, mix), WL,
                                                    16.2 * u.mas, km), order=2,
                                    shrinkage="none")
        st = SpectralStack(sdk, sdk.kp[0], cov, static="none")
        ratio.append(np.sum(st.kp ** 2) / st.rank.sum() * sdk.meta["error_model"]["tau"])
    assert abs(np.mean(ratio) - 1) < 0.1


def test_static_amplitude_recovered(km):
    """A static term of known amplitude added to the mean (not to the frames' scatter,
    like a static aberration) is fitted back by maximum likelihood: 4 (an amplitude of
    2) within a factor 1.6 in the median of 15 sequences, 0 in companion-free noise."""
    rng = np.random.default_rng(8)
    q, p = len(WL), km.n_kp
    rows = rng.normal(0, 1, (30, q, p)) * 0.02
    fits, none = [], []
    for _ in range(15):
        frames = _frames(rng, km, 80, np.ones(q))
        st0 = _stack(km, frames, static=rows)
        none.append(st0.static_amplitude)
        frames = frames + 2.0 * np.einsum("n,nqp->qp", rng.normal(0, 1, 30), rows)[None]
        st = _stack(km, frames, static=rows)
        fits.append(st.static_amplitude)
        assert len(st.rows) == 80 + 30
    assert 4 / 1.6 < np.median(fits) < 4 * 1.6
    assert np.median(none) < 0.5


def test_error_model_survives_kpfits(km, tmp_path):
    """A product written and read back (``kpifs extract`` then ``kpifs detect``) gets the
    same error model: no calibrator (CALFLAG) and its covariance rows (KP-COVROWS)."""
    rng = np.random.default_rng(4)
    sdk = spectral_differential(KernelPhaseData(_frames(rng, km, 80, np.ones(len(WL))), WL,
                                                16.2 * u.mas, km), order=2, shrinkage="none")
    sdk.write(tmp_path / "sdk.fits")
    back = KernelPhaseData.read(tmp_path / "sdk.fits")
    one, two = (SpectralStack(k, k.kp[0], k.covariance, static="none") for k in (sdk, back))
    assert one.rows_variance is not None
    assert np.allclose(two.rows_variance, one.rows_variance)
    assert np.allclose(two.kp, one.kp)
