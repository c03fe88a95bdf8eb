"""Issue 39: a static term of several groups, one free amplitude each
(`kpifs.simulation.aberrations.fit_static_amplitudes`), fitted jointly by maximum
likelihood, in the spectral-differential search's error model and its products."""
import numpy as np
import pytest
from astropy import units as u

from kpifs import KernelModel, KernelPhaseData, make_pupil
from kpifs.calibration.spectral_diff import spectral_differential
from kpifs.detect.sdk import SpectralStack, static_term_groups
from kpifs.simulation.aberrations import (_amplitudes_nll, fit_static_amplitude,
                                          fit_static_amplitudes)

WL = np.linspace(1.16, 2.37, 8) * u.um


def _nll(y, groups, a):
    """``-2 log L`` (constants dropped) of *y* (D,) under ``I + sum_g a_g R_g^T R_g``, in
    full (D x D), for the check."""
    cov = np.eye(len(y)) + sum(v * r.T @ r for v, r in zip(a, groups))
    return float(np.linalg.slogdet(cov)[1] + y @ np.linalg.solve(cov, y))


def test_orthogonal_groups_recovered_exactly():
    """Groups on orthogonal directions and data whose square in each direction is the
    model's variance there (``1 + a s^2``): the maximum likelihood is the truth, 2 and 0.5
    exactly; a group whose directions hold less than the noise (0.25 < 1) gets 0."""
    d = 60
    eye = np.eye(d)
    groups = [3.0 * eye[0:5], 2.0 * eye[5:13], 1.5 * eye[13:20]]
    y = np.zeros(d)
    y[0:5] = np.sqrt(1 + 9 * 2.0) * np.array([1, -1, 1, 1, -1])
    y[5:13] = np.sqrt(1 + 4 * 0.5) * np.array([1, 1, -1, 1, -1, -1, 1, 1])
    y[13:20] = 0.5
    y[20:] = 7.0                                        # off every group: no say
    a = fit_static_amplitudes(y[None], eye[None], [g[:, None] for g in groups])
    assert np.allclose(a, [2.0, 0.5, 0.0], rtol=1e-9, atol=1e-12)
    assert a[2] == 0.0


def test_one_group_is_the_single_fit():
    """With one group the joint fit is `fit_static_amplitude`'s."""
    rng = np.random.default_rng(3)
    rows = rng.standard_normal((25, 2, 80)) / 5
    y = rng.standard_normal((2, 80)) + 1.5 * rng.standard_normal(25) @ rows.reshape(25, -1) \
        .reshape(25, 2, 80).transpose(1, 0, 2)
    w = np.stack([np.eye(80)] * 2)
    assert np.allclose(fit_static_amplitudes(y, w, [rows]), fit_static_amplitude(y, w, rows),
                       rtol=1e-8)


def test_fit_is_the_likelihood_maximum():
    """Two groups sharing directions (not orthogonal), data drawn with amplitudes 3 and
    0.7: the likelihood at the fit is not below that at the truth nor at any nearby
    amplitudes (on ``a >= 0``), its slope is 0 at a positive amplitude, and the Woodbury
    likelihood, its slope and curvature are the full-covariance ones."""
    rng = np.random.default_rng(21)
    d = 120
    base = rng.standard_normal((12, d))
    g1 = rng.standard_normal((15, 12)) @ base / 12 + 0.1 * rng.standard_normal((15, d))
    g2 = rng.standard_normal((10, 12)) @ base / 12 + 0.3 * rng.standard_normal((10, d))
    truth = np.array([3.0, 0.7])
    for trial in range(5):
        y = rng.standard_normal(d) + np.sqrt(truth[0]) * rng.standard_normal(15) @ g1 \
            + np.sqrt(truth[1]) * rng.standard_normal(10) @ g2
        a = fit_static_amplitudes(y[None], np.eye(d)[None], [g1[:, None], g2[:, None]])
        best = _nll(y, [g1, g2], a)
        assert best <= _nll(y, [g1, g2], truth) + 1e-9
        for step in ([1e-3, 0], [-1e-3, 0], [0, 1e-3], [0, -1e-3], [1e-3, -1e-3]):
            near = np.clip(a * (1 + np.array(step)) + np.array(step) * 1e-3, 0, None)
            assert best <= _nll(y, [g1, g2], near) + 1e-9
        big = np.concatenate([g1, g2])
        group = np.r_[np.zeros(15, int), np.ones(10, int)]
        f, grad, hess = _amplitudes_nll(a, big @ big.T, big @ y, group)
        assert np.isclose(f + y @ y, best, rtol=1e-9)
        scale = np.abs(np.diag(hess)) * np.maximum(a, 1)
        assert np.all(np.where(a > 0, np.abs(grad) < 1e-6 * scale, grad > -1e-6 * scale))
    # slope and curvature against finite differences of the full likelihood
    at, h = np.array([2.0, 0.5]), 1e-4
    f0, grad, hess = _amplitudes_nll(at, big @ big.T, big @ y, group)
    for i in range(2):
        e = h * np.eye(2)[i]
        num = (_nll(y, [g1, g2], at + e) - _nll(y, [g1, g2], at - e)) / (2 * h)
        assert np.isclose(grad[i], num, rtol=1e-5)
        gp = _amplitudes_nll(at + e, big @ big.T, big @ y, group)[1]
        gm = _amplitudes_nll(at - e, big @ big.T, big @ y, group)[1]
        assert np.allclose(hess[i], (gp - gm) / (2 * h), rtol=1e-5, atol=1e-9)


@pytest.fixture(scope="module")
def km():
    return KernelModel.from_pupil(make_pupil("subaru", step=1.2 * u.m))


def _sdk(km, rng, n=80):
    q, p = len(WL), km.n_kp
    frames = rng.normal(0, 1, (n, 1, p)) + rng.normal(0, 0.5, (n, q, p))
    return spectral_differential(KernelPhaseData(frames, WL, 16.2 * u.mas, km), order=2,
                                 shrinkage="none")


def test_stack_records_each_group(km):
    """Rows given as a list are groups: each gets its amplitude, recorded in the stack's
    info (``static_amplitudes``; ``static_amplitude`` the first group's), and each
    group's rows enter the error model at its own amplitude; rows given as one array
    are one group, fitted as before."""
    rng = np.random.default_rng(5)
    q, p = len(WL), km.n_kp
    sdk = _sdk(km, rng)
    r1 = rng.normal(0, 0.02, (20, q, p))
    r2 = rng.normal(0, 0.02, (12, q, p))
    kp = sdk.kp[0] + 2.0 * np.einsum("n,nqp->qp", rng.normal(0, 1, 20), r1)
    st = SpectralStack(sdk, kp, sdk.covariance, static=[r1, r2])
    assert len(st.info["static_amplitudes"]) == 2
    assert st.info["static_amplitude"] == st.static_amplitudes[0] > 0
    kept = sum(len(r) for r, a in zip((r1, r2), st.static_amplitudes) if a > 0)
    assert len(st.static_rows) == kept
    one = SpectralStack(sdk, kp, sdk.covariance, static=r1)
    assert len(one.static_amplitudes) == 1
    assert np.allclose(one.static_rows, np.einsum("kc,ncp->nkp", one.data_mixing, r1)
                       * np.sqrt(one.static_amplitude))


def test_groups_survive_kpfits(km, tmp_path):
    """A product's static term (``spectral['static_rows']``) keeps its groups
    (``static_groups``, cards SDKGRPn of KP-SDKSTAT) when written and read back; a
    product without them is one group."""
    rng = np.random.default_rng(6)
    q, p = len(WL), km.n_kp
    sdk = _sdk(km, rng)
    rows = rng.normal(0, 0.02, (9, q, p)).astype(np.float32).astype(float)
    sdk.spectral["static_rows"], sdk.spectral["static_groups"] = rows, [4, 5]
    sdk.write(tmp_path / "sdk.fits")
    back = KernelPhaseData.read(tmp_path / "sdk.fits")
    assert back.spectral["static_groups"] == [4, 5]
    got = static_term_groups(back)
    assert [len(g) for g in got] == [4, 5]
    assert np.allclose(np.concatenate(got), rows, rtol=1e-6)
    del sdk.spectral["static_groups"]
    sdk.write(tmp_path / "one.fits")
    one = KernelPhaseData.read(tmp_path / "one.fits")
    assert "static_groups" not in one.spectral
    assert [len(g) for g in static_term_groups(one)] == [9]
