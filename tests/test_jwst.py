"""JWST stage-2 products (issue 27): reading, pupils, sky orientation, refusals."""
import warnings

import numpy as np
import pytest
from astropy import units as u
from astropy.io import fits

from kpifs import KernelModel, KernelPhaseData, make_pupil
from kpifs.cli import main
from kpifs.data import DetectionResult
from kpifs.exceptions import KpifsError, KpifsWarning
from kpifs.io import read_cube, write_observation
from kpifs.io.jwst import jwst_detpa, jwst_mode, read_jwst
from kpifs.io.layouts import write_plain_cube
from kpifs.simulation.simulate import simulate_scene


def _one_error(capsys):
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ": error: " in ln]
    assert "Traceback" not in err and len(lines) == 1, err
    return lines[0]


@pytest.fixture(scope="module")
def niriss(tmp_path_factory):
    d = tmp_path_factory.mktemp("niriss")
    obs = simulate_scene("niriss", n_frames=30, npup=64, seed=3)
    files = write_observation(obs, d, layout="jwst")
    return {"target": files["target"][0], "cal": files["calibrator"][0], "obs": obs, "dir": d}


def _modified(src, dst, *, phu=None, sci=None):
    with fits.open(src, memmap=False) as h:
        h[0].header.update(phu or {})
        h["SCI"].header.update(sci or {})
        h.writeto(dst)
    return dst


def test_layout_is_the_pipelines(niriss):
    with fits.open(niriss["target"], memmap=False) as h:
        assert [x.name for x in h] == ["PRIMARY", "SCI", "DQ", "ERR", "VAR_POISSON",
                                       "VAR_RNOISE", "VAR_FLAT", "INT_TIMES", "ASDF"]
        assert h["DQ"].header["BITPIX"] == 32 and h["DQ"].header["BZERO"] == 2147483648
        assert h["DQ"].data.dtype == np.uint32
        assert h[0].header["ROLL_REF"] == 0.0                     # guide-star value, unused
        assert h["SCI"].header["ROLL_REF"] == pytest.approx(250.0)
    # astropy cannot memory-map the scaled DQ: the failure the issue reports
    with fits.open(niriss["target"], memmap=True) as h, \
            pytest.raises(ValueError, match="memory-mapped"):
        h["DQ"].data


def test_reads_dq_nan_and_header(niriss):
    with fits.open(niriss["target"], memmap=False) as h:
        sci, dq = h["SCI"].data.astype(float), h["DQ"].data
    expected = np.isnan(sci) | (((dq & 1) != 0) & (sci != 0))
    with read_jwst(niriss["target"]) as cube:
        data = np.asarray(cube.data[:])[:, 0]
        assert cube.instrument == "jwst" and cube.shape == (30, 1, 80, 80)
        assert cube.wavelengths.to_value(u.um) == pytest.approx([4.8196])
        assert cube.pixscale.to_value(u.mas) == pytest.approx(65.55)
        assert cube.detpa.to_value(u.deg) == pytest.approx(np.full(30, 249.44))
        assert cube.header["KPFILTER"] == "F480M"
    assert np.array_equal(np.isnan(data), expected)
    assert ((dq & 1) != 0).sum() > 0 and ((dq == 2)).sum() > 0          # flags present
    # SATURATED-only pixels are good by default, bad when their bit is asked for
    with read_jwst(niriss["target"], dq_bits=1 | 2) as cube:
        more = np.isnan(np.asarray(cube.data[:])[:, 0])
    assert more.sum() == expected.sum() + ((dq == 2) & ~np.isnan(sci)).sum()


def test_detpa_formula_and_filters():
    assert jwst_detpa(fits.Header({"ROLL_REF": 10.0, "V3I_YANG": -0.56, "VPARITY": -1})) \
        == pytest.approx(9.44)
    assert jwst_detpa(fits.Header({"ROLL_REF": 10.0, "V3I_YANG": 1.25, "VPARITY": 1})) \
        == pytest.approx(8.75)
    assert jwst_detpa(fits.Header({"ROLL_REF": 10.0})) is None
    hdr = {"INSTRUME": "NIRCAM", "EXP_TYPE": "NRC_IMAGE", "FILTER": "F444W", "PUPIL": "F405N"}
    assert jwst_mode(fits.Header(hdr)) == ("NIRCAM", "F405N", "CLEAR")


@pytest.mark.slow
def test_info_and_detection_on_the_sky(niriss, tmp_path, capsys):
    assert main(["info", str(niriss["target"])]) == 0
    out = capsys.readouterr().out
    for text in ("jwst cube", "4.8196", "65.55 mas", "249.44", "pupil model niriss_clearp"):
        assert text in out, out
    kp, det = tmp_path / "kp.fits", tmp_path / "det.fits"
    assert main(["extract", str(niriss["target"]), "--calibrator", str(niriss["cal"]),
                 "-o", str(kp), "-q"]) == 0
    kpd = KernelPhaseData.read(kp)
    assert np.asarray(kpd.detpa, float) == pytest.approx([249.44])
    assert kpd.kernel_model.pupil.name == "niriss_clearp"
    assert main(["detect", str(kp), "-o", str(det), "--draws", "1000", "-q"]) == 0
    cand = DetectionResult.read(det).candidates
    assert len(cand) == 1
    dra, ddec = niriss["obs"].params.sky_offset.to_value(u.mas)
    fit_dra, fit_ddec = cand["fit_dra"][0].to_value(u.mas), cand["fit_ddec"][0].to_value(u.mas)
    assert np.hypot(fit_dra - dra, fit_ddec - ddec) < 5
    pa, fit_pa = np.degrees(np.arctan2(dra, ddec)) % 360, cand["fit_pa_sky"][0].to_value(u.deg)
    assert abs((fit_pa - pa + 180) % 360 - 180) < 2


@pytest.mark.parametrize("exp_type", ["NRC_CORON", "NIS_SOSS", "MIR_IMAGE"])
def test_unsupported_mode_refused(niriss, tmp_path, capsys, exp_type):
    bad = _modified(niriss["target"], tmp_path / f"{exp_type}_calints.fits",
                    phu={"EXP_TYPE": exp_type})
    out = tmp_path / "kp.fits"
    assert main(["extract", str(bad), "-o", str(out)]) == 2
    line = _one_error(capsys)
    assert str(bad) in line and f"EXP_TYPE {exp_type} is not supported" in line
    assert not out.exists()


def test_filters_of_one_target_refused(niriss, tmp_path, capsys):
    other = _modified(niriss["target"], tmp_path / "f380m_calints.fits",
                      phu={"FILTER": "F380M"})
    assert main(["extract", str(niriss["target"]), str(other), "-o",
                 str(tmp_path / "kp.fits")]) == 2
    line = _one_error(capsys)
    assert f"{niriss['target']} (F480M)" in line and f"{other} (F380M)" in line


def test_files_of_different_targets_refused(niriss, tmp_path, capsys):
    other = _modified(niriss["target"], tmp_path / "f380m_calints.fits",
                      phu={"FILTER": "F380M", "TARGNAME": "HD 1234"})
    assert main(["extract", str(niriss["target"]), str(other), "-o",
                 str(tmp_path / "kp.fits")]) == 2
    line = _one_error(capsys)
    assert "files of different targets" in line and f"{other} (HD 1234)" in line


def test_pixar_disagreement_warns(niriss, tmp_path):
    odd = _modified(niriss["target"], tmp_path / "odd_calints.fits",
                    sci={"PIXAR_A2": 0.0045 ** 2})
    with pytest.warns(KpifsWarning, match="PIXAR_A2"):
        read_jwst(odd).close()


def test_copied_sci_cube_gets_the_jwst_pupil(niriss, tmp_path):
    """A SCI cube copied to a plain file: the pupil follows INSTRUME, and a mismatch warns."""
    from kpifs.workflow import ExtractOptions, extract_observation
    with fits.open(niriss["target"], memmap=False) as h:
        hdr = h[0].header.copy()
        data = h["SCI"].data[:4].copy()
    path = tmp_path / "copy.fits"
    fits.writeto(path, data, hdr)
    opts = ExtractOptions(wavelengths="4.8196um", pixscale="65.55mas", step="0.6m")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KpifsWarning)     # NaN pixels filled
        kpd = extract_observation(path, opts)
    assert kpd.kernel_model.pupil.name == "niriss_clearp"
    opts.pupil = "subaru"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        extract_observation(path, opts)
    assert any("INSTRUME 'NIRISS' but the pupil model is 'subaru' (expected 'niriss_clearp')"
               in str(w.message) for w in caught)


def test_no_kernel_phase_left_refused(tmp_path, capsys):
    """The issue's case: two channels at 65.55 mas, 1.51 um loses most uv points."""
    cube = simulate_scene("paper", n_frames=2, npup=32, seed=1, telescope="jwst",
                          wavelengths=[1.51, 4.82] * u.um, pixscale=65.55 * u.mas,
                          shape=(32, 32), contrasts=[1e-3, 1e-3]).target
    path = write_plain_cube(tmp_path / "two.fits", cube, [1.51, 4.82] * u.um,
                            65.55 * u.mas)[0]
    out = tmp_path / "kp.fits"
    assert main(["extract", str(path), "--pupil", "jwst", "-o", str(out)]) == 2
    line = _one_error(capsys)
    assert str(path) in line and "no kernel phase left: at channel 1 (1.510 um)" in line
    assert "560 of 656 uv points" in line
    assert not out.exists()


@pytest.mark.parametrize("name, n_sub, n_uv, n_kp", [
    ("niriss_nrm", 7, 21, 15), ("gpi_nrm", 10, 45, 36),
    ("jwst", 322, 656, 335), ("niriss_clearp", 296, 656, 361), ("gpi", 81, 140, 60)])
def test_builtin_pupil_counts(name, n_sub, n_uv, n_kp):
    km = KernelModel.from_pupil(make_pupil(name))
    assert (km.pupil.n_sub, km.n_uv, km.n_kp) == (n_sub, n_uv, n_kp)


def test_jwst_pupil_geometry():
    """18 hexagons of 1.32 m flat to flat (1.509 m^2 each) less the struts: ~26.3 m^2."""
    step = 0.05
    g = (np.arange(-70, 71) * step)
    x, y = np.meshgrid(g, g)
    from kpifs.model.pupil import MASKS, TELESCOPES
    area = TELESCOPES["jwst"].transmission(x, y).sum() * step ** 2
    hexes = 18 * np.sqrt(3) / 2 * 1.32 ** 2
    struts = 0.11 * 3.3 + 2 * 0.12 * 3.0                    # along the segments they cross
    assert area == pytest.approx(hexes - struts, rel=0.03)
    # NRM holes: centres over segments, 21 distinct baselines up to ~5.3 m
    holes = np.array(MASKS["niriss_nrm"].holes)
    b = np.hypot(*(holes[:, None] - holes[None]).reshape(-1, 2).T)
    assert b.max() == pytest.approx(np.hypot(2.28631 * 2, 2.64), rel=1e-6)


def test_kernel_from_jwst_pupil_rejects_pupil_phases():
    """A random pupil-plane phase leaves no kernel phase (the model's own check)."""
    km = KernelModel.from_pupil(make_pupil("niriss_nrm"))
    rng = np.random.default_rng(4)
    phi = km.tfm @ rng.normal(0, 0.3, km.pupil.n_sub)
    assert np.abs(km.kernel @ phi).max() < 1e-12


def test_read_cube_auto_and_errors(niriss, tmp_path):
    with read_cube(niriss["target"]) as cube:
        assert cube.instrument == "jwst"
    nofilter = _modified(niriss["target"], tmp_path / "f999_calints.fits",
                         phu={"FILTER": "F999X"})
    with pytest.raises(KpifsError, match="filter F999X"):
        read_cube(nofilter)


@pytest.mark.parametrize("preset, over, inst, filt, channel, scale", [
    ("niriss", dict(wavelengths=[3.8299] * u.um), "NIRISS", "F380M", None, 65.55),
    ("niriss", dict(wavelengths=[4.2870] * u.um), "NIRISS", "F430M", None, 65.55),
    ("niriss", dict(wavelengths=[1.494] * u.um), "NIRISS", "F150W", None, 65.55),
    ("nircam", dict(), "NIRCAM", "F480M", "LONG", 63.0),
    ("nircam", dict(wavelengths=[1.5106] * u.um, pixscale=31 * u.mas), "NIRCAM", "F150W",
     "SHORT", 31.0)])
def test_presets_write_and_read_each_filter(tmp_path, preset, over, inst, filt, channel,
                                            scale):
    obs = simulate_scene(preset, n_frames=2, npup=32, shape=(32, 32), **over)
    path = write_observation(obs, tmp_path, layout="jwst")["target"][0]
    hdr = fits.getheader(path)
    assert hdr["INSTRUME"] == inst and hdr.get("CHANNEL") == channel
    # NIRISS's short filters sit in the pupil wheel
    assert (hdr["FILTER"], hdr["PUPIL"]) == (("CLEAR", filt) if filt == "F150W" and
                                             inst == "NIRISS" else (filt, hdr["PUPIL"]))
    with read_jwst(path) as cube:
        assert cube.header["KPFILTER"] == filt
        assert cube.pixscale.to_value(u.mas) == scale
        assert cube.wavelengths[0].to_value(u.um) == pytest.approx(
            obs.params.wavelengths[0].to_value(u.um), rel=1e-3)
    from kpifs.workflow import default_pupil
    assert default_pupil("jwst", hdr) == ("niriss_clearp" if inst == "NIRISS" and
                                          filt != "F150W" else "jwst")


def _datamodels_copy(src, dst, datamodels):
    """Re-write one of kpifs's simulated calints with the JWST datamodels library."""
    with fits.open(src, memmap=False) as h:
        sci, dq, phu, shdr = (h["SCI"].data, h["DQ"].data, h[0].header, h["SCI"].header)
        m = datamodels.CubeModel(sci.shape)
        m.data[:] = sci
        m.dq[:] = dq
        m.err[:] = h["ERR"].data
    m.meta.telescope = "JWST"
    m.meta.instrument.name = phu["INSTRUME"]
    m.meta.instrument.detector = phu["DETECTOR"]
    m.meta.instrument.filter = phu["FILTER"]
    m.meta.instrument.pupil = phu["PUPIL"]
    m.meta.exposure.type = phu["EXP_TYPE"]
    m.meta.wcsinfo.roll_ref = shdr["ROLL_REF"]
    m.meta.wcsinfo.v3yangle = shdr["V3I_YANG"]
    m.meta.wcsinfo.vparity = shdr["VPARITY"]
    m.meta.photometry.pixelarea_arcsecsq = shdr["PIXAR_A2"]
    m.save(str(dst))
    m.close()
    return dst


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::ResourceWarning")
def test_files_written_by_the_jwst_datamodels(niriss, tmp_path, capsys):
    """Optional (stdatamodels is no dependency): the same pair written by the JWST
    datamodels library, read with no option beyond the output."""
    datamodels = pytest.importorskip("stdatamodels.jwst.datamodels")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tgt = _datamodels_copy(niriss["target"], tmp_path / "t_calints.fits", datamodels)
        cal = _datamodels_copy(niriss["cal"], tmp_path / "c_calints.fits", datamodels)
    with fits.open(tgt, memmap=False) as h:
        assert h["DQ"].header["BZERO"] == 2147483648 and "ASDF" in h
    kp, det = tmp_path / "kp.fits", tmp_path / "det.fits"
    assert main(["extract", str(tgt), "--calibrator", str(cal), "-o", str(kp), "-q"]) == 0
    assert np.asarray(KernelPhaseData.read(kp).detpa, float) == pytest.approx([249.44])
    assert main(["detect", str(kp), "-o", str(det), "--draws", "1000", "-q"]) == 0
    cand = DetectionResult.read(det).candidates
    dra, ddec = niriss["obs"].params.sky_offset.to_value(u.mas)
    assert len(cand) == 1
    assert np.hypot(cand["fit_dra"][0].to_value(u.mas) - dra,
                    cand["fit_ddec"][0].to_value(u.mas) - ddec) < 5


def test_files_of_one_filter_add_frames(niriss, tmp_path):
    second = _modified(niriss["target"], tmp_path / "second_calints.fits")
    with read_jwst([niriss["target"], second]) as cube:
        assert cube.shape == (60, 1, 80, 80) and len(cube.detpa) == 60
        assert np.array_equal(np.isnan(np.asarray(cube.data[28:32])),
                              np.isnan(np.asarray(cube.data[[28, 29, 0, 1]])))


def test_dq_bits_option(niriss, tmp_path, capsys):
    """``--dq-bits`` by name or value; DO_NOT_USE always in; a bad name is one line, rc 2."""
    from kpifs.io.jwst import parse_dq_bits
    assert parse_dq_bits(None) == 1 and parse_dq_bits("SATURATED") == 3
    assert parse_dq_bits("saturated|jump_det") == parse_dq_bits(6) == parse_dq_bits("0x6") == 7
    with fits.open(niriss["target"], memmap=False) as h:
        sci, dq = h["SCI"].data.astype(float), h["DQ"].data
    sat = ((dq == 2) & ~np.isnan(sci)).sum()
    with read_cube(niriss["target"]) as a, read_cube(niriss["target"], dq_bits="SATURATED") as b:
        assert np.isnan(b.data[:]).sum() == np.isnan(a.data[:]).sum() + sat > 0
        assert b.header["KPDQBITS"] == 3
    out = tmp_path / "kp.fits"
    assert main(["extract", str(niriss["target"]), "--dq-bits", "SATURATED,JUMP_DET",
                 "-o", str(out)]) == 0
    assert '"dq_bits": "SATURATED,JUMP_DET"' in fits.getval(out, "KPXOPTS")
    capsys.readouterr()
    assert main(["extract", str(niriss["target"]), "--dq-bits", "SATURATD",
                 "-o", str(tmp_path / "x.fits")]) == 2
    assert "--dq-bits: 'SATURATD' is neither a DQ flag name" in _one_error(capsys)


def test_err_propagated_to_kernel_phase_errors(tmp_path):
    """ERR through the linear extraction predicts the frames' scatter: photon and read
    noise only (no wavefront, no jitter), 40 integrations: median ratio 1.01 (10-90 %:
    0.87-1.18, the scatter of 40-frame estimates); written as KP-SIGM."""
    obs = simulate_scene("niriss", n_frames=40, npup=64, seed=5, wavefront_rms=0 * u.nm,
                         jitter=0.0, contrasts=[0.0])
    files = write_observation(obs, tmp_path, layout="jwst")
    from kpifs.workflow import extract_observation
    kpd = extract_observation(files["target"])
    assert kpd.meta["pixel_noise"] == "ERR" and kpd.kp_err.shape == kpd.shape
    ratio = kpd.kp.std(0, ddof=1)[0] / kpd.kp_err.mean(0)[0]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.05)
    cov = kpd.meta["pixel_covariance"][0]
    assert np.sqrt(np.diag(cov)) == pytest.approx(kpd.kp_err.mean(0)[0], rel=0.02)
    # VAR_* when ERR is missing: the same numbers (ERR**2 = VAR_POISSON here)
    nerr = tmp_path / "noerr_calints.fits"
    with fits.open(files["target"][0], memmap=False) as h:
        del h["ERR"]
        h.writeto(nerr)
    other = extract_observation([nerr])
    assert other.meta["pixel_noise"] == "VAR_*"
    assert other.kp_err == pytest.approx(kpd.kp_err, rel=1e-5)
    out = kpd.write(tmp_path / "kp.fits")
    back = KernelPhaseData.read(out)
    assert back.kp_err == pytest.approx(kpd.kp_err, rel=1e-6)
    assert back.header["KPPIXNOI"] == "ERR"


# --- filters as channels (issue 27, item 3) ---------------------------------------------
def _nircam_pair(d, contrasts, *, nf=20, detpa=(250.0, 250.0)):
    """F150W (31 mas) and F480M (63 mas) of one target and its calibrator, W0336-like:
    84 mas at PA 295 deg."""
    t, c = [], []
    for (wl, ps, seed), con, pa in zip(((1.5106, 31.0, 1), (4.8213, 63.0, 2)), contrasts,
                                       detpa):
        obs = simulate_scene("nircam", wavelengths=[wl] * u.um, pixscale=ps * u.mas,
                             contrasts=[con], n_frames=nf, seed=seed, detpa=[pa])
        f = write_observation(obs, d / f"{ps:.0f}", layout="jwst")
        t += [str(x) for x in f["target"]]
        c += [str(x) for x in f["calibrator"]]
    return t, c


@pytest.mark.slow
def test_nircam_two_filters_one_product(tmp_path, capsys):
    """F150W + F480M become one product of 2 channels, each with its own kernel: F150W the
    117 kernel phases of the 438 uv points it samples (<= 5.03 m), F480M all 335 (the
    nested kernel's first rows are F150W's); the binary (0.076, 0.19) is fitted at
    83.9 mas, 294.9 deg, contrasts -0.7 % and +1.0 % (within 3 mas, 2 deg, 10 %)."""
    t, c = _nircam_pair(tmp_path, (0.076, 0.19))
    out = tmp_path / "kp.fits"
    assert main(["extract", *t, "--calibrator", *c, "-o", str(out)]) == 0
    assert "uv points" not in capsys.readouterr().err      # no filter loses any of its own
    kpd = KernelPhaseData.read(out)
    assert kpd.n_wave == 2 and kpd.n_kp == 335 and kpd.header["KPFILTER"] == "F150W+F480M"
    assert kpd.channel_n_kp.tolist() == [117, 335] and kpd.header["NKPCH1"] == 117
    assert main(["info", str(out)]) == 0
    assert "own kernel (its first kernel phases): 1.5106 um 117, 4.8213 um 335" in \
        capsys.readouterr().out
    # F150W's rows beyond its own are not data: zero, with zero covariance
    assert not kpd.kp[0, 0, 117:].any() and not kpd.covariance[0, 117:].any()
    assert np.abs(kpd.kernel_model.kernel[:117, kpd.kernel_model.baseline_length.value
                                          > 5.04]).max() < 1e-12
    assert kpd.wavelengths.to_value(u.um) == pytest.approx([1.5106, 4.8213])
    assert kpd.pixscale.to_value(u.mas) == 31.0 and kpd.window.radius == pytest.approx(25.6)
    det = tmp_path / "det.fits"
    assert main(["detect", str(out), "-o", str(det), "--draws", "1000", "--quiet"]) == 0
    cands = DetectionResult.read(det).candidates
    assert len(cands) == 1
    row = cands[0]
    assert abs(row["fit_separation"].to_value(u.mas) - 84.0) < 3
    assert abs(row["fit_pa_sky"].to_value(u.deg) - 295.0) < 2
    assert np.asarray(row["fit_contrast"]) == pytest.approx([0.076, 0.19], rel=0.1)


@pytest.mark.slow
def test_two_filters_go_deeper(tmp_path):
    """A flat 8e-4 companion at 84 mas: the two-filter product (each filter its own kernel,
    pixel noise beyond the modes) finds it (P_FA 5.7e-4 at 82 mas), neither filter alone
    does (the same product, one channel); median B limits at 60-90 / 90-120 mas: 5.9e-4 /
    3.5e-4 for the pair against 1.2e-3 / 9.1e-4 (F150W) and 2.2e-3 / 1.1e-3 (F480M)."""
    from kpifs.detect import detect
    from kpifs.workflow import extract_filters
    from kpifs.workflow import ExtractOptions
    t, c = _nircam_pair(tmp_path, (8e-4, 8e-4))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KpifsWarning)
        both = extract_filters(t, [c], ExtractOptions())
    assert both.channel_n_kp.tolist() == [117, 335]
    assert both.meta["error_model"]["pixel_modes"] > 0
    res = [detect(k, pfa=1e-3, n_draws=1000, seed=0)
           for k in (both.select_channels([0]), both.select_channels([1]), both)]
    assert [len(r.candidates) for r in res] == [0, 0, 1]
    assert abs(res[2].candidates[0]["fit_separation"].to_value(u.mas) - 84.0) < 5
    for lo, hi in ((60, 90), (90, 120)):
        lim = [np.nanmedian(r.limit[(r.grid.sep >= lo) & (r.grid.sep < hi)]) for r in res]
        assert lim[2] < 0.7 * min(lim[:2])


def test_filters_refusals(tmp_path, capsys):
    """A calibrator without one of the target's filters, and filters at different
    detector angles (field rotation between filters needs blocks): rc 2, one line."""
    t, c = _nircam_pair(tmp_path, (0.0, 0.0), nf=4, detpa=(250.0, 262.0))
    assert main(["extract", *t, "--calibrator", c[0], "-o", str(tmp_path / "a.fits")]) == 2
    assert f"calibrator {c[0]}: no files in filter(s) F480M" in _one_error(capsys)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KpifsWarning)
        assert main(["extract", *t, "--calibrator", *c, "-o", str(tmp_path / "b.fits")]) == 2
    line = _one_error(capsys)
    assert "filters at different detector angles" in line and f"F480M 262.0 deg in {t[1]}" in line
    assert not (tmp_path / "b.fits").exists()
