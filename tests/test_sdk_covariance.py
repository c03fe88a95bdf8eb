"""Issue 39: the spectral-differential search sees the channels' correlations (a static
or drifting aberration is shared by every channel): with no calibrator, the target's
frame deviations and time blocks go with the product as covariance and block rows."""
import numpy as np
import pytest
from astropy import units as u

from kpifs import KernelModel, KernelPhaseData, make_pupil
from kpifs.calibration.calibrate import block_rows, covariance_rows
from kpifs.calibration.spectral_diff import frames_autocorrelation, spectral_differential
from kpifs.covariance import rows_covariance
from kpifs.detect.sdk import SpectralStack

WL = np.linspace(1.16, 2.37, 8) * u.um


@pytest.fixture(scope="module")
def km():
    return KernelModel.from_pupil(make_pupil("subaru", step=1.2 * u.m))


def test_covariance_rows_of_frames(km):
    rng = np.random.default_rng(2)
    kp = rng.normal(0, 0.1, (30, len(WL), km.n_kp))
    rows = covariance_rows(KernelPhaseData(kp, WL, 16.2 * u.mas, km))
    joint = rows_covariance(rows, joint=True)
    want = np.cov(kp.reshape(30, -1), rowvar=False) / 30
    assert np.allclose(joint, want)
    assert covariance_rows(KernelPhaseData(kp[:1], WL, 16.2 * u.mas, km)) is None


def test_autocorrelation_time_of_drifting_frames(km):
    """A drift (AR(1), correlation 0.9 from frame to frame) makes the frames' mean vary
    about (1 + 0.9) / (1 - 0.9) = 19 times more than independent frames say; batch
    means in 16 blocks of 25 frames see most of it, independent frames give 1."""
    rng = np.random.default_rng(7)
    n, p = 400, km.n_kp
    x = np.empty((n, 1, p))
    x[0] = rng.normal(0, 1, (1, p))
    for i in range(1, n):
        x[i] = 0.9 * x[i - 1] + np.sqrt(1 - 0.81) * rng.normal(0, 1, (1, p))
    drift = KernelPhaseData(x, [1.6] * u.um, 16.2 * u.mas, km)
    white = KernelPhaseData(rng.normal(0, 1, (n, 1, p)), [1.6] * u.um, 16.2 * u.mas, km)
    tau = [frames_autocorrelation(covariance_rows(k), block_rows(k, [])) for k in (drift, white)]
    # batch means of 25 frames keep (1 - 2 * 0.9 / (25 * 0.1 * 1.9)) ~ 0.62 of 19
    assert 8 < tau[0] < 19 and 1.0 <= tau[1] < 1.5


def test_combination_rows_carry_the_shared_noise(km):
    """The stack's rows give each combination the covariance ``M C M^T`` of the joint
    covariance, cross-channel terms included (in the stack's whitened units), while
    its whitening sums the channels' covariances; a shared noise that is not smooth in
    wavelength survives the projection and shows only in the rows."""
    rng = np.random.default_rng(3)
    q, p, n = len(WL), km.n_kp, 400
    shared = rng.normal(0, 1, (n, 1, p)) * rng.normal(0, 2, (1, q, 1))
    frames = shared + rng.normal(0, 0.5, (n, q, p))
    t = KernelPhaseData(frames, WL, 16.2 * u.mas, km)
    sdk = spectral_differential(t, order=2)
    assert sdk.covariance_rows.shape == (n, q, p) and sdk.block_rows is not None
    assert sdk.meta["calibrated"] is False
    st = SpectralStack(sdk, sdk.kp[0], sdk.covariance, static="none", normalise="none")
    tau = sdk.meta["error_model"]["tau"]            # independent frames: batch means ~1
    assert 1.0 <= tau < 1.5
    joint = tau * np.cov(frames.reshape(n, -1), rowvar=False) / n
    gram = np.einsum("nkp,nkr->kpr", st.rows, st.rows)
    for k, mix in enumerate(st.data_mixing):
        big = np.kron(mix[None], np.eye(p))                     # (p, q p)
        want = st._w[k] @ (big @ joint @ big.T) @ st._w[k].T
        assert np.allclose(gram[k], want, atol=1e-9 * np.max(np.abs(want)))
    # the shared noise adds in some combinations and cancels in others (measured: the
    # rows' mean variance 0.07 to 2.0 of the whitening's): without the rows, the null
    # and the limits would take every combination at 1
    ratio = np.trace(gram, axis1=1, axis2=2) / p
    assert ratio.max() / ratio.min() > 5
