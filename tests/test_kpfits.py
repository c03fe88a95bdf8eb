"""KPFITS interoperability: files as xara, jwst-kpi and PyKernel/pynrm write them are read
right; kpifs's own files round-trip and open the way fouriever's reader opens them."""
import re

import numpy as np
import pytest
import astropy.units as u
from astropy.io import fits

from kpifs import KernelPhaseData, KpifsError
from kpifs.calibration.calibrate import calibrate
from kpifs.covariance import filled_covariance
from kpifs.detect import detect
from kpifs.io import kpfits, write_observation
from kpifs.simulation.simulate import simulate_scene
from kpifs.workflow import ExtractOptions, extract_observation

from kpfits_layouts import (fouriever_like_kernel_model, fouriever_like_open, parts_of,
                            sky_to_detector, write_jwstkpi, write_pykernel, write_xara)

NF = 8


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """Kernel phases of kpifs's simulator: 8 frames x 3 channels x 74 kernel phases (a
    binary model, as the other tools make)."""
    d = tmp_path_factory.mktemp("kpsim")
    files = write_observation(simulate_scene("paper", n_frames=NF, seed=7, npup=48), d)
    tgt = extract_observation(files["target"], ExtractOptions(step="0.8m", grey=False))
    cal = extract_observation(files["calibrator"], ExtractOptions(step="0.8m", grey=False),
                              model=tgt.kernel_model)
    # every uv point kept: some of its redundancies round to 0 (see below)
    grey = extract_observation(files["target"], ExtractOptions(
        step="0.8m", grey=True, min_transmission=0.3, min_redundancy=0))
    nkp = tgt.n_kp
    rng = np.random.default_rng(3)
    m = rng.normal(size=(nkp, nkp))
    cov1 = 1e-4 * (m @ m.T / nkp + np.eye(nkp))         # one frame's covariance
    return {"target": tgt, "calibrator": cal, "grey": grey, "cov1": cov1,
            "detpa": np.linspace(-30.0, 40.0, NF)}


def _cov3(sim):
    return np.stack([sim["cov1"] * s for s in (1.0, 1.5, 2.0)])


# --- kpifs's own files ---------------------------------------------------------------
def test_own_files_round_trip(sim, tmp_path):
    t = sim["target"]
    kpd = KernelPhaseData(t.kp, t.wavelengths, t.pixscale, t.kernel_model, window=t.window,
                          phases=t.phases, amplitudes=t.amplitudes, covariance=_cov3(sim),
                          header=t.header, detpa=sim["detpa"],
                          meta=dict(t.meta, detpa_source="--pa"))
    path = kpd.write(tmp_path / "kp.fits")
    back = KernelPhaseData.read(path)
    for name in ("kp", "covariance", "detpa"):
        np.testing.assert_array_equal(getattr(back, name), getattr(kpd, name))
    assert back.kp_err is None
    km, bkm = kpd.kernel_model, back.kernel_model
    for a, b in ((km.kernel, bkm.kernel), (km.blm, bkm.blm), (km.redundancy, bkm.redundancy),
                 (km.uv, bkm.uv), (km.pupil.xy, bkm.pupil.xy)):
        np.testing.assert_array_equal(a, b)
    assert u.allclose(back.wavelengths, kpd.wavelengths, rtol=1e-15)
    assert back.window == kpd.window and back.pixscale == kpd.pixscale
    # CVIS-DATA holds (real, imag) in float32: phases and amplitudes to single precision
    np.testing.assert_allclose(back.amplitudes, kpd.amplitudes, rtol=3e-7, atol=1e-8)
    dphi = (back.phases - kpd.phases + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(dphi).max() < 1e-5
    assert back.meta["detpa_source"] == "--pa" and back.meta["layout"] == "kpifs"
    with fits.open(path) as h:
        hdr = h[0].header
        assert hdr["PROCSOFT"].startswith("kpifs") and hdr["CONTENT"] == "KPFITS1"
        assert (hdr["INSTRUME"], hdr["TELESCOP"]) == ("GENERIC", "UNKNOWN")
        assert hdr["DIAM"] == pytest.approx(7.92) and hdr["PSCALE"] == pytest.approx(10.42)
        assert hdr["WRAD"] == kpd.window.radius and hdr["CALFLAG"] is False
        assert (hdr["NFRAME"], hdr["NWAVE"], hdr["EXPTIME"]) == (NF, 3, 0.1)
        assert h["KP-COV"].data.shape == (NF, 3, kpd.n_kp, kpd.n_kp)
        assert h["KP-COV"].header["COVFRAME"] == "EVERY"
        assert h["KP-SIGM"].data.shape == kpd.kp.shape
        assert h["CVIS-DATA"].header["CVISFORM"] == "REIM"
        cw = h["CWAVEL"].data
        np.testing.assert_array_equal(cw["DWAVEL"], cw["BWIDTH"])
        assert "detector +y axis" in str(h["DETPA"].header["COMMENT"])
    # per-frame errors round-trip too
    kpd.kp_err = np.full(kpd.kp.shape, 0.02)
    back = KernelPhaseData.read(kpd.write(tmp_path / "kp_err.fits"))
    np.testing.assert_array_equal(back.kp_err, kpd.kp_err)


def test_older_kpifs_files_phase_amplitude(sim, tmp_path):
    """Files written before CVISFORM hold (phase, amplitude) and are still read right."""
    t = sim["target"]
    path = t.write(tmp_path / "new.fits")
    with fits.open(path) as h:
        hl = fits.HDUList([x.copy() for x in h])
    hl["CVIS-DATA"] = fits.ImageHDU(np.stack([t.phases, t.amplitudes]), name="CVIS-DATA")
    hl.writeto(tmp_path / "old.fits", checksum=True)
    back = KernelPhaseData.read(tmp_path / "old.fits")
    np.testing.assert_array_equal(back.phases, t.phases)
    np.testing.assert_array_equal(back.amplitudes, t.amplitudes)


def test_fouriever_reads_kpifs_files(sim, tmp_path):
    """fouriever's reading sequence finds every part, a covariance for every frame, and
    its binary model (PA rotated by -DETPA) matches data made with kpifs's convention."""
    t = sim["target"]
    km, wl = t.kernel_model, t.wavelengths
    dra, ddec, c = 60.0, -45.0, 0.02
    kp = np.stack([km.binary_kernel_phases(sky_to_detector(dra, ddec, pa) * u.mas, c, wl)
                   for pa in sim["detpa"]])
    kpd = KernelPhaseData(kp, wl, t.pixscale, km, window=t.window, covariance=_cov3(sim),
                          detpa=sim["detpa"], header=t.header)
    path = kpd.write(tmp_path / "kp.fits")
    for strict in (False, True):
        frames = fouriever_like_open(path, strict_dwavel=strict)
        assert len(frames) == NF
    for i, f in enumerate(frames):
        np.testing.assert_array_equal(f["kp"], kp[i].T)
        np.testing.assert_allclose(f["dkp"], np.sqrt(np.diagonal(_cov3(sim), axis1=1,
                                                                 axis2=2)).T)
        np.testing.assert_array_equal(f["kpcov"], sim["cov1"])      # channel 0's, each frame
        assert f["pa"] == sim["detpa"][i] and f["diam"] == pytest.approx(7.92)
        np.testing.assert_allclose(f["wave"], wl.to_value(u.m))
        np.testing.assert_array_equal(f["kpu"], -km.uv.value[:, 0])
        model = fouriever_like_kernel_model(f, dra, ddec, c)
        np.testing.assert_allclose(model, f["kp"], atol=1e-10)
        # the opposite rotation (xara's cvis_binary with +DETPA) would not fit
        if abs(np.sin(np.deg2rad(sim["detpa"][i]))) > 0.1:
            wrong = fouriever_like_kernel_model(dict(f, pa=-f["pa"]), dra, ddec, c)
            assert np.abs(wrong - f["kp"]).max() > 1e-3


@pytest.mark.filterwarnings("ignore:.*Ledoit-Wolf shrinkage")
def test_fouriever_reads_calibrated_files(sim, tmp_path):
    cal = calibrate(sim["target"], sim["calibrator"])
    path = cal.write(tmp_path / "cal.fits")
    (frame,) = fouriever_like_open(path)
    # positive definite, so that fouriever can invert it (issue 35): the model's modes,
    # and no weight to the directions they leave out
    full, _ = filled_covariance(cal.covariance, data=cal.kp)
    np.testing.assert_array_equal(frame["kpcov"], full[0])
    np.linalg.cholesky(frame["kpcov"])
    assert frame["kp"].shape == (cal.n_kp, 3)
    back = KernelPhaseData.read(path)
    np.testing.assert_allclose(back.covariance, cal.covariance, rtol=0,
                               atol=1e-8 * np.abs(cal.covariance).max())
    assert back.meta["calibrated"] and back.n_frame == 1


def test_large_covariances_written_once(sim, tmp_path, monkeypatch):
    monkeypatch.setattr(kpfits, "KPCOV_COPY_LIMIT", 0)
    t = sim["target"]
    kpd = KernelPhaseData(t.kp, t.wavelengths, t.pixscale, t.kernel_model,
                          covariance=_cov3(sim), detpa=sim["detpa"])
    path = kpd.write(tmp_path / "kp.fits")
    with fits.open(path) as h:
        assert h["KP-COV"].data.shape == (1, 3, t.n_kp, t.n_kp)
        assert h["KP-COV"].header["COVFRAME"] == "FIRST"
    np.testing.assert_array_equal(KernelPhaseData.read(path).covariance, kpd.covariance)
    frames = fouriever_like_open(path)
    assert "kpcov" in frames[0] and "kpcov" not in frames[1]


# --- other tools' files ----------------------------------------------------------------
def test_xara_layout(sim, tmp_path):
    g = sim["grey"]
    p = parts_of(g)
    assert np.any(g.kernel_model.pupil.transmission < 1)             # a grey model
    path = write_xara(tmp_path / "xara.fits", p, detpa=12.0, phases=g.phases,
                      amplitudes=g.amplitudes)
    back = KernelPhaseData.read(path)
    assert back.meta["layout"] == "xara" and not back.meta["calibrated"]
    np.testing.assert_array_equal(back.kp, g.kp[:, :1])
    assert back.wavelengths.to_value(u.um) == pytest.approx([1.52])
    np.testing.assert_array_equal(back.detpa, np.full(NF, 12.0))
    assert back.covariance is None and back.kp_err is None          # NaN placeholders
    km, bkm = g.kernel_model, back.kernel_model
    np.testing.assert_array_equal(bkm.pupil.transmission, km.pupil.transmission)
    np.testing.assert_array_equal(bkm.redundancy, km.redundancy)    # floats, not truncated
    np.testing.assert_array_equal(bkm.blm, km.blm)
    np.testing.assert_allclose(back.amplitudes, g.amplitudes[:, :1], rtol=1e-13)
    assert bkm.kernel_residual() < 1e-12


def test_older_xara_unnormalised_kernel_without_blm(sim, tmp_path):
    """Rows of any norm are kept as stored (with the data in the same units); without
    BLM-MAT the matrix is rebuilt for the file's own uv points, in any half plane."""
    t = sim["target"]
    p = parts_of(t)
    scale = np.random.default_rng(1).uniform(2, 30, t.n_kp)
    sigma = np.full(t.kp.shape, 0.01)
    for sign in (1.0, -1.0):
        path = write_xara(tmp_path / f"xara{sign:+.0f}.fits", p, kernel_scale=scale,
                          sigma=sigma, blm=None, uv_sign=sign, bandwidth=0.05e-6)
        back = KernelPhaseData.read(path)
        km = back.kernel_model
        np.testing.assert_allclose(km.kernel, t.kernel_model.kernel * scale[:, None])
        np.testing.assert_allclose(back.kp, t.kp[:, :1] * scale)
        np.testing.assert_allclose(back.kp_err, sigma[:, :1] * scale)
        np.testing.assert_allclose(np.diag(back.covariance[0]), (0.01 * scale) ** 2)
        np.testing.assert_allclose(km.blm, sign * t.kernel_model.blm, atol=1e-12)
        assert km.meta["blm_rebuilt"] == "from the aperture"
        assert km.kernel_residual() < 1e-12
        assert back.bandwidth.to_value(u.um) == pytest.approx([0.05])
        assert any("not unit-normalised" in n for n in back.meta["notes"])


def test_jwstkpi_layout(sim, tmp_path):
    t = sim["target"]
    p = parts_of(t)
    covs = sim["cov1"] * np.linspace(1, 2, NF)[:, None, None, None]      # per frame
    one = dict(p, kp=t.kp[:, :1], wavelengths=p["wavelengths"][:1])
    path = write_jwstkpi(tmp_path / "jwst1.fits", one, detpa=sim["detpa"], cov=covs,
                         phases=t.phases[:, :1], amplitudes=t.amplitudes[:, :1])
    with fits.open(path) as h:
        assert h["KP-DATA"].data.ndim == 2 and h["BLM-MAT"].data.shape[1] == \
            t.kernel_model.pupil.n_sub - 1 and h["UV-PLANE"].data["RED"].dtype.kind == "i"
    back = KernelPhaseData.read(path)
    assert back.meta["layout"] == "jwst-kpi"
    assert back.meta["calibrated"] is False                       # the string 'False'
    assert (back.meta["instrument"], back.meta["diameter"]) == ("NIRISS", 6.559348)
    np.testing.assert_array_equal(back.kp, t.kp[:, :1])
    np.testing.assert_array_equal(back.detpa, sim["detpa"])
    np.testing.assert_allclose(back.covariance, covs.mean(axis=0))    # one frame's: the mean
    np.testing.assert_allclose(back.kp_err, np.sqrt(np.diagonal(covs, axis1=2, axis2=3)))
    km = back.kernel_model
    np.testing.assert_allclose(km.blm, t.kernel_model.blm, atol=1e-12)   # reference rebuilt
    assert km.kernel_residual() < 1e-12 and km.meta["blm_rebuilt"] == "reference column"
    assert np.all(km.redundancy == t.kernel_model.redundancy)
    dphi = (back.phases - t.phases[:, :1] + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(dphi).max() < 1e-12
    # three wavelengths, 3-D KP-DATA, DWAVEL instead of BWIDTH
    path = write_jwstkpi(tmp_path / "jwst3.fits", p, detpa=sim["detpa"], cov=_cov3(sim),
                         bandwidth_column="DWAVEL")
    back = KernelPhaseData.read(path)
    np.testing.assert_array_equal(back.kp, t.kp)
    np.testing.assert_allclose(back.covariance, _cov3(sim))
    assert u.allclose(back.bandwidth, 0.1 * t.wavelengths)


@pytest.mark.filterwarnings("ignore:.*Ledoit-Wolf shrinkage")
def test_calibrated_jwstkpi_file_is_searched(sim, tmp_path):
    """A calibrated file of another tool (CALFLAG 'True', one frame, KP-COV) is detectable,
    and a kernel with rows of other norms (data and covariance alike) gives the same maps."""
    # full-rank frame covariance: the statistics are invariant under any invertible
    # rescaling of kernel rows only when the whitening is (not a projection onto modes)
    cal = calibrate(sim["target"], sim["calibrator"], error_model="frames")
    p = parts_of(cal)
    scale = np.random.default_rng(2).uniform(0.5, 20, cal.n_kp)
    out = []
    for name, ks in (("unit", None), ("scaled", scale)):
        path = write_jwstkpi(tmp_path / f"{name}.fits", p, detpa=15.0,
                             cov=cal.covariance[None], calflag="True", kernel_scale=ks)
        kpd = KernelPhaseData.read(path)
        assert kpd.meta["calibrated"] is True and kpd.n_frame == 1
        out.append(detect(kpd, n_draws=1000, fit=False, seed=1))
    # the maps: the same but for the noise scale's downward bound, read from the null's
    # own (Monte-Carlo) draws of the map's mean square, where no annulus's noise is higher
    np.testing.assert_allclose(out[1].statistic, out[0].statistic, rtol=2e-2, atol=1e-8)
    np.testing.assert_allclose(out[1].contrast, out[0].contrast, rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("v410tau", [False, True], ids=["nirc2", "v410tau"])
def test_pykernel_layout(sim, tmp_path, v410tau):
    """PyKernel/pynrm (the NIRC2 file of the issue): a 2-D KP-DATA with the wavelength in
    header cards is 8 frames of one wavelength, not 8 channels of one frame."""
    t = sim["target"]
    covs = sim["cov1"] * np.linspace(1, 3, NF)[:, None, None]
    path = write_pykernel(tmp_path / "nirc2.fits", parts_of(t), detpa=sim["detpa"],
                          cov=covs, v410tau=v410tau)
    back = KernelPhaseData.read(path)
    assert back.shape == (NF, 1, t.n_kp)
    np.testing.assert_array_equal(back.kp, t.kp[:, :1])
    assert back.wavelengths.to_value(u.um) == pytest.approx([1.52])
    np.testing.assert_array_equal(back.detpa, sim["detpa"].astype(np.float32))
    np.testing.assert_allclose(back.covariance[0], covs.mean(axis=0))
    np.testing.assert_allclose(back.kp_err[:, 0], np.sqrt(np.diagonal(covs, axis1=1, axis2=2)))
    np.testing.assert_allclose(back.kernel_model.blm, t.kernel_model.blm, atol=1e-12)
    assert back.kernel_model.kernel_residual() < 1e-12
    assert back.meta["instrument"] == "NIRC2" and back.meta["diameter"] == 10.95
    if v410tau:
        assert back.meta["wavelength_source"] == "CWAVEL image"
        assert back.meta["detpa_source"] == "DETPA extension"
    else:
        assert back.meta["layout"] == "pykernel"
        assert back.meta["wavelength_source"] == "primary CWAVE card"
        assert back.meta["detpa_source"] == "TEL table"


def test_detpa_given_replaces_the_files(sim, tmp_path):
    path = write_pykernel(tmp_path / "tel3.fits", parts_of(sim["target"]), detpa=5.0,
                          cov=sim["cov1"], tel_rows=3)
    with pytest.raises(KpifsError, match=r"3 detector position angles \(TEL table\) for 8 "
                                         r"frames of KP-DATA; give them explicitly"):
        KernelPhaseData.read(path)
    back = KernelPhaseData.read(path, detpa=sim["detpa"])
    np.testing.assert_array_equal(back.detpa, sim["detpa"])


# --- files kpifs cannot interpret -------------------------------------------------------
def _drop(name):
    return lambda h: h.pop(h.index_of(name))


def _replace(name, data):
    def edit(h):
        h[name] = fits.ImageHDU(data(h[name].data), name=name)
    return edit


def _del_cards(*keys):
    def edit(h):
        for k in keys:
            del h[0].header[k]
    return edit


def _legacy(h):
    h["KP-DATA"].name = "KP-DATA1"
    h.append(fits.ImageHDU(h["KP-DATA1"].data, name="KP-DATA2"))


def _wide_kp(h):
    h.append(fits.BinTableHDU.from_columns(
        [fits.Column(name="CWAVEL", format="D", array=[1.5e-6, 1.6e-6, 1.7e-6])],
        name="CWAVEL"))


def _nan_kp(h):
    h["KP-DATA"].data[2, 5] = np.nan


def _tel_rows(h):
    h["TEL"] = fits.BinTableHDU.from_columns(
        [fits.Column(name="pa", format="E", array=np.zeros(3))], name="TEL")


BAD = [
    ("no UV-PLANE", _drop("UV-PLANE"), "not a kernel model: no UV-PLANE extension"),
    ("no APERTURE", _drop("APERTURE"), "no APERTURE extension"),
    ("BLM-MAT width", _replace("BLM-MAT", lambda a: a[:, 2:]),
     r"BLM-MAT has (\d+) columns but APERTURE has (\d+) sub-apertures: expected"),
    ("BLM-MAT rows", _replace("BLM-MAT", lambda a: a[1:]), "BLM-MAT has shape"),
    ("KER-MAT columns", _replace("KER-MAT", lambda a: a[:, 1:]),
     r"KER-MAT has shape \(74, \d+\) but UV-PLANE has \d+ rows"),
    ("KP-DATA last axis", _replace("KP-DATA", lambda a: a[:, :-1]),
     "KP-DATA has shape (8, 73) but KER-MAT has 74 rows"),
    ("KP-DATA 4-D", _replace("KP-DATA", lambda a: a[:, None, None]),
     "KP-DATA has 4 dimensions"),
    ("2-D KP-DATA, 3 wavelengths", _wide_kp, "KP-DATA is 2-D (8, 74) but there are 3 "
                                             "wavelengths"),
    ("KP-SIGM shape", _replace("KP-SIGM", lambda a: a[:, :5]), "KP-SIGM has shape"),
    ("NaN kernel phase", _nan_kp, "KP-DATA holds 1 NaN or infinite kernel phases"),
    ("TEL rows", _tel_rows, "3 detector position angles (TEL table) for 8 frames"),
    ("no wavelength", _del_cards("CWAVE", "CENWAVE"), "no wavelength: neither a CWAVEL "
                                                      "extension nor"),
    ("no pixel scale", _del_cards("PSCALE"), "no pixel scale (PSCALE)"),
    ("legacy data sets", _legacy, "2 data sets (KP-DATA1, KP-DATA2; xara's legacy layout)"),
]


@pytest.mark.parametrize("name, edit, message", BAD, ids=[b[0] for b in BAD])
def test_files_kpifs_cannot_interpret(sim, tmp_path, name, edit, message):
    good = write_pykernel(tmp_path / "good.fits", parts_of(sim["target"]),
                          detpa=sim["detpa"], cov=sim["cov1"])
    with fits.open(good) as h:
        hl = fits.HDUList([x.copy() for x in h])
    edit(hl)
    bad = tmp_path / "bad.fits"
    hl.writeto(bad)
    with pytest.raises(KpifsError) as err:
        KernelPhaseData.read(bad)
    text = str(err.value)
    assert text.startswith(f"{bad}: ") and "\n" not in text
    if message.startswith(("BLM-MAT has (", "KER-MAT has shape \\(")):
        assert re.search(message, text), text
    else:
        assert message in text, text


def test_grey_model_with_integer_redundancies_is_flagged(sim, tmp_path):
    """jwst-kpi and PyKernel write RED as int16: a grey model's weights are truncated and
    the stored kernel no longer annuls BLM / RED. The file is read, with a warning."""
    g = sim["grey"]
    p = parts_of(g)
    with pytest.raises(KpifsError, match="RED has .* not > 0 .integer redundancies of a grey"):
        KernelPhaseData.read(write_jwstkpi(tmp_path / "grey0.fits", p, detpa=0.0))
    p["redundancy"] = np.maximum(np.rint(p["redundancy"]), 1.0)     # none rounded to 0
    path = write_jwstkpi(tmp_path / "grey_int.fits", p, detpa=0.0, red_int=True)
    with pytest.warns(Warning, match="KER-MAT is not orthogonal to BLM-MAT / RED"):
        back = KernelPhaseData.read(path)
    np.testing.assert_array_equal(back.kp, g.kp)


def test_info_describes_other_tools_files(sim, tmp_path, capsys):
    from kpifs.cli import main
    path = write_pykernel(tmp_path / "nirc2.fits", parts_of(sim["target"]),
                          detpa=sim["detpa"], cov=sim["cov1"])
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "written by PyKernel/pynrm" in out and "NIRC2 on Keck II" in out
    assert "8 frame(s) x 1 channel(s) x 74 kernel phases" in out
    assert "detector position angle: -30.00 to 40.00 deg (TEL table)" in out
    assert "note: BLM-MAT has" in out


def test_table_extensions_same_bytes_as_astropy_tables():
    """The writers' binary tables (made without astropy.table) are byte for byte those of
    ``fits.BinTableHDU(Table)``."""
    import io
    from astropy.table import Table
    from kpifs.io._kpfits_common import _table_hdu
    rng = np.random.default_rng(3)
    a, b, c = rng.random((3, 7))
    t = Table([a, b, c], names=("UUC", "VVC", "RED"))
    t["UUC"].unit = t["VVC"].unit = "m"
    ours = _table_hdu({"UUC": a, "VVC": b, "RED": c}, "UV-PLANE", {"UUC": "m", "VVC": "m"})
    bufs = [io.BytesIO(), io.BytesIO()]
    for buf, hdu in zip(bufs, (fits.BinTableHDU(t, name="UV-PLANE"), ours)):
        fits.HDUList([fits.PrimaryHDU(), hdu]).writeto(buf)
    assert bufs[0].getvalue() == bufs[1].getvalue()
