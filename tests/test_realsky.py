"""Honest statistics on the real PHARO frames (issue 14): no false alarm when eps Her
calibrates itself, alpha Oph's companion alone, and injection-recovery into real frames
with pulls of unit scatter and limits that match detection."""
import numpy as np
import pytest
import astropy.units as u

from kpifs import KernelModel, extract_kernel_phases, make_pupil
from kpifs.calibration.calibrate import calibrate
from kpifs.detect import detect
from kpifs.inject import inject_companion
from kpifs.io import read_cube
from kpifs.model.window import ExtractionWindow

pytestmark = [pytest.mark.realdata, pytest.mark.slow]

PIX = 25 * u.mas
WL = [2.145] * u.um


@pytest.fixture(scope="module")
def pharo(real_data):
    km = KernelModel.from_pupil(make_pupil("pharo", step=0.16 * u.m))
    out = {"model": km}
    for role, name in (("alpha_oph", "pharo_tgt_cube_alphaOph.fits"),
                       ("eps_her", "pharo_ca2_cube_epsHer.fits")):
        with read_cube(real_data / name, wavelengths=WL, pixscale=PIX) as cube:
            out[role] = np.array(cube.data, float)
    out["window"] = ExtractionWindow.default(out["eps_her"].shape[-2:])
    return out


def _kp(pharo, frames):
    return extract_kernel_phases(frames, pharo["model"], wavelengths=WL, pixscale=PIX,
                                 window=pharo["window"], keep_phases=False)


def _search(pharo, target, calibrator, seed=0):
    return detect(calibrate(_kp(pharo, target), _kp(pharo, calibrator)), pfa=1e-3, seed=seed)


@pytest.mark.parametrize("split", ["halves", "halves swapped", "odd/even", "even/odd",
                                   "quarters 1/3", "quarters 2/4"])
def test_eps_her_calibrating_itself_gives_no_candidate(pharo, split):
    f = pharo["eps_her"]
    t, c = {"halves": (f[:50], f[50:]), "halves swapped": (f[50:], f[:50]),
            "odd/even": (f[1::2], f[::2]), "even/odd": (f[::2], f[1::2]),
            "quarters 1/3": (f[:25], f[50:75]), "quarters 2/4": (f[25:50], f[75:])}[split]
    res = _search(pharo, t, c)
    # before the error model: 5 candidates (the cap) in every split
    assert len(res.candidates) == 0, res.candidates
    assert res.meta["error_model"]["model"] == "modes"
    # the empirical null (sign flips of 12-14 time blocks) against the Gaussian one:
    # measured 0.91-1.17 with the split-halves residual, 0.71-0.75 with the residual
    # measured at detection (the block rows keep the model's scale); the search uses
    # the larger
    nul = res.meta["null"]
    assert nul["method"] == "gaussian+empirical"
    assert 0.65 < nul["threshold_empirical"] / nul["threshold_gaussian"] < 1.35
    assert res.threshold == max(nul["threshold_gaussian"], nul["threshold_empirical"])


def test_alpha_oph_companion_alone(pharo):
    res = _search(pharo, pharo["alpha_oph"], pharo["eps_her"])
    tab = res.candidates
    assert len(tab) == 1, tab
    sep = float(np.hypot(tab["fit_x"][0].value, tab["fit_y"][0].value))
    assert abs(sep - 124) < 10
    c, err = float(tab["fit_contrast"][0][0]), float(tab["fit_contrast_err"][0][0])
    # the calibration residual between two stars inflates the fit (chi2_red ~ 50): the
    # error says so (was 1.9e-4 on 0.028)
    # the literature Delta K = 3.5 +- 0.2 mag (default grey model: 0.046 +- 0.003)
    assert 0.033 < c < 0.048 and 1e-3 < err < 6e-3
    assert tab["chi2_red"][0] > 5


def test_injections_into_eps_her(pharo):
    """20 companions (100-600 mas, contrasts 2e-3 to 3e-2) injected into frames 0-49 as
    shifted, scaled copies of the frames themselves; frames 50-99 calibrate."""
    f = pharo["eps_her"]
    cal = _kp(pharo, f[50:])
    rng = np.random.default_rng(7)
    pulls, found, strong_err, false = [], [], [], 0
    for i in range(20):
        r, th = rng.uniform(100, 600), rng.uniform(0, 2 * np.pi)
        x, y = r * np.cos(th), r * np.sin(th)
        c = float(np.exp(rng.uniform(np.log(2e-3), np.log(3e-2))))
        tgt = _kp(pharo, inject_companion(f[:50], position=[x, y] * u.mas, contrast=c,
                                          pixscale=PIX))
        res = detect(calibrate(tgt, cal), pfa=1e-3, seed=i)
        tab = res.candidates
        g, lim = res.grid, res.limits["B"]
        k = np.nanargmin(np.where(np.isnan(lim), np.inf, np.hypot(g.X - x, g.Y - y)))
        ratio = c / float(lim.ravel()[k])
        d = np.hypot(tab["fit_x"].value - x, tab["fit_y"].value - y) if len(tab) else []
        hit = [j for j in range(len(tab)) if d[j] < 40]
        false += len(tab) - len(hit)
        found.append((ratio, bool(hit)))
        if hit:
            row = tab[hit[0]]
            pulls += [(float(row["fit_contrast"][0]) - c) / float(row["fit_contrast_err"][0]),
                      (row["fit_x"].value - x) / row["fit_x_err"].value,
                      (row["fit_y"].value - y) / row["fit_y_err"].value]
            fc, ec = float(row["fit_contrast"][0]), float(row["fit_contrast_err"][0])
            if fc / ec > 20:                         # a strong detection: 5 % errors
                strong_err.append(fc / c - 1)
    rms = float(np.sqrt(np.mean(np.square(pulls))))
    assert false == 0
    # before: pulls of ~6 sigma; 1.60 with the search's error model alone (0.5 nu
    # modes); measured 1.20 (contrast 1.05, positions 1.2 and 1.33) with candidates
    # characterised by the 0.8 nu model (calibrate's fit_modes)
    assert 0.7 < rms < 1.5, rms
    # within 10 % for most; the binary pupil model (partly covered cells left out) biases
    # some low by up to ~17 % (the pupil-model issue): the median is what the errors show
    assert len(strong_err) >= 3 and np.all(np.abs(strong_err) < 0.2), strong_err
    assert abs(np.median(strong_err)) < 0.05
    above = [hit for ratio, hit in found if ratio > 2]
    below = [hit for ratio, hit in found if ratio < 0.5]
    assert len(above) >= 5 and all(above)          # twice the P_D = 0.5 limit: found
    assert not any(below)                          # half of it: not found


def _draw_pharo_pupil(path, npix=256):
    """PHARO's pupil as a user draws it from the published geometry (Hayward et al. 2001;
    ../shared/data/real/README.md): the "med" cross Lyot mask's 4.646 m clear aperture,
    2.293 m central obstruction and two 0.25 m spider arms along the detector axes,
    turned by -2 deg, on a 4.978 m grid."""
    from astropy.io import fits
    scale = 4.978 / npix
    y, x = (np.mgrid[:npix, :npix] - (npix - 1) / 2) * scale
    t = np.deg2rad(-2.0)
    xr, yr = np.cos(t) * x + np.sin(t) * y, -np.sin(t) * x + np.cos(t) * y
    r = np.hypot(x, y)
    img = (r <= 4.646 / 2) & (r >= 2.293 / 2) & (np.abs(xr) > 0.125) & (np.abs(yr) > 0.125)
    fits.writeto(path, img.astype(float), fits.Header({"PUPSCALE": scale}))
    return path


def test_alpha_oph_alone_with_a_user_drawn_pupil(pharo, tmp_path):
    """alpha Oph calibrated by eps Her with a kernel model made from a pupil image drawn
    from the published geometry (0.16 m step): one candidate within 10 mas of
    (-124, +8) mas, contrast 0.033-0.048 (the literature Delta K = 3.5 +- 0.2); before the
    noise scale on the map, a second candidate appeared at (290, 145) mas."""
    km = KernelModel.from_pupil(make_pupil(str(_draw_pharo_pupil(tmp_path / "pupil.fits")),
                                           step=0.16 * u.m))
    user = dict(pharo, model=km)
    res = _search(user, pharo["alpha_oph"], pharo["eps_her"])
    tab = res.candidates
    assert len(tab) == 1, tab
    assert np.hypot(abs(tab["fit_x"][0].value) - 124, abs(tab["fit_y"][0].value) - 8) < 10
    assert 0.033 < float(tab["fit_contrast"][0][0]) < 0.048
