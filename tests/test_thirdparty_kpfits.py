"""Third-party suite: KPFITS written in the layouts of jwst-kpi and PyKernel (and opened the
way fouriever opens them), holding a bright and a faint companion, and files whose
optional cards are wrong (issue 35).

The arrays are kpifs's own simulation and extraction (74 kernel phases of a binary
0.8 m model, 3 channels, 40 frames per star), so the search of another tool's file can
be compared number for number with the search of kpifs's own product."""
import numpy as np
import pytest
import astropy.units as u
from astropy.io import fits

from kpifs import KernelPhaseData
from kpifs.calibration.calibrate import calibrate
from kpifs.detect import detect
from kpifs.io import write_observation
from kpifs.simulation.simulate import simulate_scene
from kpifs.workflow import ExtractOptions, extract_observation

from kpfits_layouts import fouriever_like_open, parts_of, write_jwstkpi, write_pykernel

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore:.*Ledoit-Wolf shrinkage")]

#: (contrast, what) of the two companions, at the simulator's (80, 60) mas; the B limit
#: at 80-120 mas is 1.9e-3 (P_FA 1e-3, P_D 0.5) for these sequences
CASES = {"bright": 2e-2, "faint": 4e-3}


@pytest.fixture(scope="module", params=sorted(CASES))
def seq(request, tmp_path_factory):
    c = CASES[request.param]
    d = tmp_path_factory.mktemp(request.param)
    files = write_observation(simulate_scene("paper", n_frames=40, seed=11, npup=48,
                                             contrasts=[c] * 3), d)
    opts = ExtractOptions(step="0.8m", grey=False)
    t = extract_observation(files["target"], opts)
    k = extract_observation(files["calibrator"], opts, model=t.kernel_model)
    own = detect(calibrate(t, k), pfa=1e-3, n_draws=1000, seed=0)
    return {"name": request.param, "contrast": c, "target": t, "calibrator": k, "own": own,
            "dir": d}


def _same_candidate(res, own, contrast):
    assert len(res.candidates) == len(own.candidates) == 1
    a, b = res.candidates[0], own.candidates[0]
    assert np.hypot(a["fit_x"].value - b["fit_x"].value, a["fit_y"].value - b["fit_y"].value) \
        < 0.05
    assert np.mean(np.asarray(a["fit_contrast"])) == pytest.approx(
        np.mean(np.asarray(b["fit_contrast"])), rel=1e-3)
    assert np.hypot(a["fit_x"].value - 80, a["fit_y"].value - 60) < 3
    assert np.mean(np.asarray(a["fit_contrast"])) == pytest.approx(contrast, rel=0.25)


def test_jwstkpi_files_of_target_and_calibrator(seq, tmp_path):
    """jwst-kpi's layout (2-D/3-D KP-DATA, integer RED, BLM-MAT without the reference
    column, CALFLAG 'False', the window as WRAD on the SCI frames' size), one file per
    star: the same candidate as kpifs's own product, within 0.05 mas and 0.1 % in
    contrast. Before WRAD was read, the window was not modelled: the bright companion
    came out 2.3 mas from kpifs's own fit and 7 % fainter."""
    t, k = seq["target"], seq["calibrator"]
    assert (t.window.size, t.window.radius, t.window.order) == (40, 16.0, 4.0)
    paths = [write_jwstkpi(tmp_path / f"{n}.fits", parts_of(x), detpa=0.0, wrad=16,
                           image_size=40) for n, x in (("t", t), ("c", k))]
    bt, bk = (KernelPhaseData.read(p) for p in paths)
    assert bt.meta["layout"] == "jwst-kpi" and bt.meta["calibrated"] is False
    assert bt.window == t.window
    np.testing.assert_array_equal(bt.kp, t.kp)
    res = detect(calibrate(bt, bk), pfa=1e-3, n_draws=1000, seed=0)
    _same_candidate(res, seq["own"], seq["contrast"])


@pytest.mark.parametrize("wrad, note", [("NONE", "no extraction window"),
                                        (-3, "is no window radius: ignored")])
def test_jwstkpi_without_window(tmp_path, wrad, note):
    from kpifs import KernelModel, make_pupil
    km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m, grey=False))
    p = {"xy": km.pupil.xy.value, "transmission": km.pupil.transmission, "uv": km.uv.value,
         "redundancy": km.redundancy, "kernel": km.kernel, "blm": km.blm,
         "kp": np.zeros((2, 1, km.n_kp)), "wavelengths": np.array([1.6e-6]),
         "pixscale": 10.0}
    back = KernelPhaseData.read(write_jwstkpi(tmp_path / "a.fits", p, detpa=0.0, wrad=wrad))
    assert back.window is None and any(note in n for n in back.meta["notes"])


def test_pykernel_one_channel(seq, tmp_path):
    """PyKernel/pynrm's NIRC2 layout keeps one channel (wavelength in header cards, angles
    in the TEL table, no window card): kpifs finds what it finds in its own channel 1
    searched without a window."""
    t, k = seq["target"], seq["calibrator"]
    cov = np.cov(t.kp[:, 0].T)
    paths = [write_pykernel(tmp_path / f"{n}.fits", parts_of(x), detpa=0.0, cov=cov)
             for n, x in (("t", t), ("c", k))]
    bt, bk = (KernelPhaseData.read(p) for p in paths)
    assert bt.shape == (t.n_frame, 1, t.n_kp)
    res = detect(calibrate(bt, bk), pfa=1e-3, n_draws=1000, seed=0)
    # PyKernel writes no window card: kpifs's own channel searched without its window
    t0, k0 = t.select_channels([0]), k.select_channels([0])
    t0.window = k0.window = None
    assert bt.window is None
    own = detect(calibrate(t0, k0), pfa=1e-3, n_draws=1000, seed=0)
    assert len(res.candidates) == len(own.candidates)
    if seq["name"] == "bright":
        _same_candidate(res, own, seq["contrast"])


#: Optional cards with wrong or meaningless values, as real writers leave them
ODD = {"EXPTIME": "N/A", "DATEOBS": "2022-13-45T99:00:00", "GAIN": -1.0, "WRAD": -3.0,
       "MJD": 0.0, "TELESCOP": "", "INSTRUME": "UNKNOWN", "FIX_METH": 42,
       "CENT_X": "nan"}


def test_wrong_optional_cards_change_nothing(seq, tmp_path):
    """A calibrated jwst-kpi file (one frame, KP-COV) whose optional cards are wrong:
    read with the same data, searched with the same result, and fouriever's way of
    opening it still works."""
    cal = calibrate(seq["target"], seq["calibrator"], error_model="frames")
    clean = write_jwstkpi(tmp_path / "clean.fits", parts_of(cal), detpa=0.0,
                          cov=cal.covariance[None], calflag="True")
    odd = tmp_path / "odd.fits"
    with fits.open(clean) as h:
        for key, val in ODD.items():
            h[0].header[key] = val
        h.writeto(odd)
    a, b = KernelPhaseData.read(clean), KernelPhaseData.read(odd)
    np.testing.assert_array_equal(a.kp, b.kp)
    np.testing.assert_array_equal(a.covariance, b.covariance)
    assert a.pixscale == b.pixscale and u.allclose(a.wavelengths, b.wavelengths)
    ra, rb = (detect(x, pfa=1e-3, n_draws=1000, fit=False, seed=1) for x in (a, b))
    np.testing.assert_allclose(ra.statistic, rb.statistic)
    assert len(ra.candidates) == len(rb.candidates) >= 1
    assert len(fouriever_like_open(odd)) == 1
