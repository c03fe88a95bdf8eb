"""Issue 37: physically consistent or refused, on cubes, JWST, GPI, inject, simulate, info and
model-check. Each case records the exit status, the message, that the inputs are unchanged
and that no partial output is left; cases that run to the end check the answer against
the simulation's truth."""
import hashlib
import warnings

import numpy as np
import pytest
from astropy import units as u
from astropy.io import fits

from kpifs import KernelPhaseData
from kpifs.cli import main
from kpifs.exceptions import KpifsError, KpifsWarning
from kpifs.io.layouts import write_observation
from kpifs.simulation.simulate import simulate_scene


def _hashes(files):
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in files if p.is_file()}


def _edit(src, dst, *, phu=None, sci=None, data=None):
    """A copy of a FITS file with header cards (None deletes) and extensions' data changed."""
    with fits.open(src, memmap=False) as h:
        for hdr, cards in ((h[0].header, phu), (h["SCI"].header if "SCI" in h else None, sci)):
            for k, v in (cards or {}).items():
                if v is None:
                    hdr.remove(k, ignore_missing=True)
                else:
                    hdr[k] = v
        for name, edit in (data or {}).items():
            h[name].data = edit(np.array(h[name].data))
        h.writeto(dst)
    return dst


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    d = tmp_path_factory.mktemp("consistency")
    f = {}
    # NIRISS F480M through CLEARP (kernel phase) and NRM (aperture masking)
    for name, tel, seed in (("clearp", "niriss_clearp", 3), ("nrm", "niriss_nrm", 4)):
        obs = simulate_scene("niriss", n_frames=10, npup=64, seed=seed, telescope=tel)
        files = write_observation(obs, d / name, layout="jwst")
        f[name], f[name + "_cal"] = files["target"][0], files["calibrator"][0]
    f["gr700xd"] = _edit(f["clearp"], d / "gr700xd_calints.fits", phu={"PUPIL": "GR700XD"})
    f.update(_err_files(d, f))
    f.update(_nircam_pair(d))
    f.update(_clean_layouts(d))
    f.update(_angle_files(d))
    f.update(_sweep_files(d, f))
    return f


def _sweep_files(d, f):
    """Header cards no instrument writes, found by this issue's own sweep (#12, #17)."""
    jw, ch, gp = f["clean_jwst"][0], f["charis_cal"][0], f["gpi8_cal"][0]
    plain = f["clean_plain"][0]
    out = {
        "kpwl_abc": _raw_card(plain, d / "kpwl_abc.fits", "KPWL2", "'abc'"),
        "exptype_nan": _raw_card(jw, d / "exptype_nan_calints.fits", "EXP_TYPE", "NaN"),
        "vparity0": _edit(jw, d / "vparity0_calints.fits", sci={"VPARITY": 0}),
        "rollref_huge": _edit(jw, d / "rollref_calints.fits", sci={"ROLL_REF": 1e30}),
        "rollref_nan": _raw_card(jw, d / "rollref_nan_calints.fits", "ROLL_REF", "NaN"),
        "lammax_abc": _edit(ch, d / "lammax_CRSA_cube.fits", phu={"LAM_MAX": "abc"}),
        "lammax_nan": _raw_card(ch, d / "lammaxnan_CRSA_cube.fits", "LAM_MAX", "NaN"),
        "parang_huge": _edit(ch, d / "parang_CRSA_cube.fits", phu={"PARANG": 1e30}),
        "avparang_huge": _edit(gp, d / "avparang_spdc.fits", sci={"AVPARANG": 1e30}),
        "cd33_zero": _edit(gp, d / "cd33_spdc.fits", sci={"CD3_3": 0.0}),
        "psfcent_out": _edit(gp, d / "psfcent_spdc.fits", sci={"PSFCENTX": 1.0,
                                                               "PSFCENTY": 1.0}),
    }
    # a header changed by hand after writing (CHECKSUM kept): PIXSCALE 10.42 -> 12.42
    raw = plain.read_bytes()
    i = raw.index(b"PIXSCALE=")
    out["checksum"] = d / "checksum.fits"
    out["checksum"].write_bytes(raw[:i] + raw[i:i + 80].replace(b"10.42", b"12.42") +
                                raw[i + 80:])
    return out


def _raw_card(src, dst, key, text):
    """A copy of *src* whose cards *key* (in every header) read *text* (as written by a tool
    that puts NaN in a header, which astropy refuses to write)."""
    raw = bytearray(src.read_bytes())
    name = f"{key:8s}=".encode()
    for i in range(0, len(raw), 80):
        if raw[i:i + 9] == name:
            raw[i:i + 80] = f"{key:8s}= {text:>20s}".ljust(80).encode()
    dst.write_bytes(bytes(raw))
    return dst


def _angle_files(d):
    """GPI exposures with one unknown AVPARANG (#13) and a DQ of the wrong shape (#17);
    CHARIS exposures with PARANG 'unavailable' (#17)."""
    out = {}
    obs = simulate_scene("gpi", n_frames=8, npup=64, shape=(240, 240), seed=3)
    files = write_observation(obs, d / "gpi8", layout="gpi")
    out["gpi8_cal"] = files["calibrator"]
    nan = [_raw_card(p, d / "gpi8" / f"nan_{p.name}", "AVPARANG", "NaN") if i == 7 else p
           for i, p in enumerate(files["target"])]
    out["gpi8_nan"], out["gpi8_nan_file"] = nan, nan[7]
    out["gpi8_none"] = [_edit(p, d / "gpi8" / f"none_{p.name}", sci={"AVPARANG": None})
                        if i == 4 else p for i, p in enumerate(files["target"])]
    out["gpi_dq"] = _edit(files["target"][0], d / "gpi_dq.fits",
                          data={"DQ": lambda a: a[:, :-1]})
    obs = simulate_scene("charis", n_frames=4, npup=48, shape=(64, 64), seed=5,
                         detpa=[10.0, 30.0, 50.0, 70.0])
    files = write_observation(obs, d / "charis3", layout="charis")
    out["charis_cal"] = files["calibrator"]
    out["charis_unavail"] = [_edit(p, d / f"unavail_{p.name}", phu={"PARANG": "unavailable"})
                             for p in files["target"]]
    out["charis_one_unavail"] = [out["charis_unavail"][0]] + files["target"][1:]
    return out


def _clean_layouts(d):
    """Companion-free stars in each instrument's layout, for `kpifs inject`."""
    out = {}
    for name, preset, layout, over in (
            ("jwst", "niriss", "jwst", dict(n_frames=10, npup=64)),
            ("charis", "charis", "charis", dict(n_frames=3, npup=48, shape=(64, 64),
                                                detpa=[10.0, 30.0, 50.0])),
            ("gpi", "gpi", "gpi", dict(n_frames=2, npup=48, shape=(128, 128))),
            ("sphere", "sphere", "sphere", dict(n_frames=2, npup=48)),
            ("plain", "paper", "plain", dict(n_frames=2, npup=48))):
        obs = simulate_scene(preset, seed=7, contrasts=0.0, **over)
        files = write_observation(obs, d / f"clean_{name}", layout=layout)
        out[f"clean_{name}"], out[f"clean_{name}_cal"] = files["target"], files["calibrator"]
    return out


def _err_files(d, f):
    """ERR that contradicts the data (#5) and infinite pixels (#6), target and calibrator."""
    out = {}
    edits = {"x100": lambda e: 100 * e, "nan": lambda e: e * np.nan, "zero": lambda e: 0 * e,
             "neg": lambda e: -e}
    for name, edit in edits.items():
        for role, src in (("t", f["clearp"]), ("c", f["clearp_cal"])):
            out[f"err_{name}_{role}"] = _edit(src, d / f"err_{name}_{role}_calints.fits",
                                              data={"ERR": edit})
    # ERR NaN at 4 pixels of the core, where SCI is good: given the image's largest ERR
    core = np.pad(np.ones((2, 2), bool), ((39, 39), (39, 39)))
    out["err_part_t"] = _edit(f["clearp"], d / "err_part_calints.fits",
                              data={"ERR": lambda e: np.where(core, np.nan, e)})
    # SCI normalised to a total of 1 per integration, ERR left in DN/s
    for role, src in (("t", f["clearp"]), ("c", f["clearp_cal"])):
        with fits.open(src) as h:
            total = np.nansum(h["SCI"].data, axis=(1, 2))[:, None, None]
        out[f"norm_{role}"] = _edit(src, d / f"norm_{role}_calints.fits",
                                    data={"SCI": lambda a: a / total})
    out["inf_t"] = _edit(f["clearp"], d / "inf_calints.fits",
                         data={"SCI": lambda a: np.where(np.pad(np.ones((2, 2), bool),
                                                                ((38, 40), (30, 48))), np.inf, a)})
    return out


def _nircam_pair(d):
    """NIRCam F150W (31 mas) and F480M (63 mas), target (W0336-like binary: 84 mas, PA 295
    deg, contrasts 0.076 and 0.19) and calibrator."""
    t, c = [], []
    for (wl, ps, seed), con in zip(((1.5106, 31.0, 1), (4.8213, 63.0, 2)), (0.076, 0.19)):
        obs = simulate_scene("nircam", wavelengths=[wl] * u.um, pixscale=ps * u.mas,
                             contrasts=[con], n_frames=10, seed=seed, detpa=[250.0], npup=64)
        files = write_observation(obs, d / f"nircam{ps:.0f}", layout="jwst")
        t += files["target"]
        c += files["calibrator"]
    return {"nc_t": t, "nc_c": c, "nc_t150": t[0], "nc_c150": c[0], "nc_t480": t[1],
            "nc_c480": c[1]}


def _run(corpus, tmp_path, capsys, argv, code):
    """Run the command line; the message, checked: one error line for exit 2, no traceback,
    inputs untouched, no output or temporary left by a refusal."""
    inputs = [p for v in corpus.values() for p in (v if isinstance(v, list) else [v])
              if hasattr(p, "is_file")]
    before = _hashes(inputs)
    out = tmp_path / "out.fits"
    args = [str(a) for a in argv]
    if args[0] in ("extract", "detect", "inject") and "-o" not in args:
        args += ["-o", str(out)]
    assert main(args) == code
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    if code == 2:
        lines = [ln for ln in captured.err.splitlines() if ": error: " in ln]
        assert len(lines) == 1, captured.err
        assert not out.exists()
    assert not list(tmp_path.glob(".out*"))
    assert _hashes(before) == before
    return captured.err + captured.out


CASES = [
    # (name, argv builder, exit status, texts in the message)
    ("3: CLEARP target, NRM calibrator",
     lambda f: ["extract", f["clearp"], "--calibrator", f["nrm_cal"]], 2,
     ["calibrator {nrm_cal}: pupil element NRM, but the target {clearp}: CLEARP"]),
    ("3: NRM target, CLEARP calibrator",
     lambda f: ["extract", f["nrm"], "--calibrator", f["clearp_cal"]], 2,
     ["calibrator {clearp_cal}: pupil element CLEARP, but the target {nrm}: NRM"]),
    ("3: target files through two pupil elements",
     lambda f: ["extract", f["clearp"], f["nrm"], "--calibrator", f["clearp_cal"]], 2,
     ["files through different pupil elements", "{nrm} (PUPIL NRM)"]),
    ("4: --pixscale of another detector, one filter",
     lambda f: ["extract", f["nc_t480"], "--calibrator", f["nc_c480"], "--pixscale", "31mas"], 2,
     ["{nc_t480}: the pixel scale given (31 mas) contradicts this NIRCAM LONG file's own "
      "(63.0 mas in kpifs's table, sqrt(PIXAR_A2) = 63.00 mas)"]),
    ("4: --pixscale that fits no filter",
     lambda f: ["extract", *f["nc_t"], "--calibrator", *f["nc_c"], "--pixscale", "45mas"], 2,
     ["the pixel scale given (45 mas) fits none of the filters' own (F150W 31 mas ({nc_t150}), "
      "F480M 63 mas ({nc_t480}))"]),
    ("5: ERR all NaN: said, not used",
     lambda f: ["extract", f["err_nan_t"], "--calibrator", f["err_nan_c"]], 0,
     ["{err_nan_t}: ERR is NaN, infinite, zero or negative at every pixel used: no noise can "
      "be read from it; not used"]),
    ("5: ERR all zero: said, not used",
     lambda f: ["extract", f["err_zero_t"], "--calibrator", f["err_zero_c"]], 0,
     ["{err_zero_t}: ERR is zero at every pixel used", "{err_zero_c}: ERR is zero"]),
    ("5: ERR negative: said, not used",
     lambda f: ["extract", f["err_neg_t"], "--calibrator", f["err_neg_c"]], 0,
     ["{err_neg_t}: ERR is negative at every pixel used"]),
    ("5: ERR NaN at a few good pixels: said, the image's largest ERR there",
     lambda f: ["extract", f["err_part_t"], "--calibrator", f["clearp_cal"]], 0,
     ["{err_part_t}: ERR is NaN, infinite, zero or negative at 40 of the ",
      "good pixels used: given the largest ERR of their image"]),
    ("5: ERR 100 x too large: scaled to the frames' scatter, said",
     lambda f: ["extract", f["err_x100_t"], "--calibrator", f["clearp_cal"]], 0,
     ["{err_x100_t}: ERR predicts kernel-phase errors 93.6 times the frames' own scatter (10 "
      "frames)", "its variance is scaled by 0.000114 to the frames' scatter"]),
    ("13: one NaN AVPARANG of 8 GPI exposures: left out, said",
     lambda f: ["extract", *f["gpi8_nan"], "--calibrator", *f["gpi8_cal"]], 0,
     ["1 of 8 exposure(s) left out: AVPARANG or IFSROTAT unknown (NaN, missing or not a "
      "number) in {gpi8_nan_file}: the others are searched on the sky"]),
    ("13: a missing AVPARANG: left out, said",
     lambda f: ["extract", *f["gpi8_none"], "--calibrator", *f["gpi8_cal"]], 0,
     ["1 of 8 exposure(s) left out: AVPARANG or IFSROTAT unknown"]),
    ("17: GPI DQ of the wrong shape",
     lambda f: ["extract", f["gpi_dq"], "--calibrator", *f["gpi8_cal"]], 2,
     ["gpi_dq.fits: DQ of shape (37, 239, 240) does not match SCI (37, 240, 240)"]),
    ("17: PARANG unavailable everywhere, angular-differential",
     lambda f: ["extract", *f["charis_unavail"], "--angular-differential"], 2,
     ["--angular-differential needs the detector position angle of every frame: unknown for "
      "4 of 4 (PARANG + 113 deg: missing, NaN or 'unavailable'); give them with --pa"]),
    ("17: PARANG unavailable in one of 3 CHARIS files: left out, said",
     lambda f: ["extract", *f["charis_one_unavail"], "--calibrator", *f["charis_cal"]], 0,
     ["1 of 4 exposure(s) left out: PARANG unknown"]),
    ("17: PARANG unavailable, angles given: every exposure kept",
     lambda f: ["extract", *f["charis_one_unavail"], "--pa", "10,30,50,70", "--calibrator",
                *f["charis_cal"]], 0, ["calibrated kernel phases"]),
    ("12: a KPWL card that is no number (was exit 3)",
     lambda f: ["extract", f["kpwl_abc"]], 2,
     ["kpwl_abc.fits: KPWL2 = \"'abc'\" is not a wavelength (um)"]),
    ("12: a JWST card astropy cannot parse (was exit 3)",
     lambda f: ["extract", f["exptype_nan"]], 2,
     ["exptype_nan_calints.fits: EXP_TYPE NAN is not supported"]),
    ("12: CHARIS LAM_MAX no number (was exit 3)",
     lambda f: ["extract", f["lammax_abc"]], 2,
     ["lammax_CRSA_cube.fits: LAM_MAX = nan nm disagrees with LAM_MIN"]),
    ("17: CHARIS LAM_MAX NaN (was accepted)",
     lambda f: ["extract", f["lammax_nan"]], 2,
     ["lammaxnan_CRSA_cube.fits: LAM_MAX = nan nm disagrees"]),
    ("17: VPARITY 0 (was accepted)",
     lambda f: ["extract", f["vparity0"]], 2,
     ["vparity0_calints.fits: ROLL_REF/V3I_YANG/VPARITY = 250/-0.56/0 are not the angles"]),
    ("17: ROLL_REF 1e30 (was accepted)",
     lambda f: ["extract", f["rollref_huge"]], 2,
     ["rollref_calints.fits: ROLL_REF/V3I_YANG/VPARITY = 1e+30/-0.56/-1 are not the angles"]),
    ("17: ROLL_REF NaN: orientation unknown, said",
     lambda f: ["extract", f["rollref_nan"], "--calibrator", f["clean_jwst_cal"][0]], 0,
     ["rollref_nan_calints.fits: ROLL_REF/V3I_YANG/VPARITY = nan/-0.56/-1.0: the sky "
      "orientation is unknown (give --pa)"]),
    ("17: PARANG 1e30 (was accepted)",
     lambda f: ["extract", f["parang_huge"]], 2,
     ["parang_CRSA_cube.fits: PARANG = 1e+30 is not an angle (deg)"]),
    ("17: AVPARANG 1e30 (was accepted)",
     lambda f: ["extract", f["avparang_huge"]], 2,
     ["avparang_spdc.fits: AVPARANG = 1e+30, IFSROTAT = 23.5: not angles (deg)"]),
    ("17: GPI CD3_3 = 0 (was accepted by info)",
     lambda f: ["info", f["cd33_zero"]], 2,
     ["cd33_spdc.fits: CD3_3 (or CDELT3) = 0: every channel would have one wavelength"]),
    ("17: GPI PSFCENTX/Y outside the lenslet field: said",
     lambda f: ["info", f["psfcent_out"]], 0,
     ["psfcent_spdc.fits: PSFCENTX/Y = (1, 1) is not in the lenslet field: the field's "
      "centre is used"]),
    ("17: info on a header changed after its CHECKSUM (was silent)",
     lambda f: ["info", f["checksum"]], 0,
     ["checksum.fits: header checksum mismatch in HDU 0 (PRIMARY): its header was changed "
      "after it was written", "pixel scale: 12.42 mas"]),
    ("sweep: simulate --exptime -1 (was exit 3)",
     lambda f: ["simulate", "--exptime", "-1", "-o", f["clearp"].parent / "sim1"], 2,
     ["the exposure time must be > 0, got -1.0 s"]),
    ("sweep: simulate --rotation 1e30deg (was accepted)",
     lambda f: ["simulate", "--rotation", "1e30deg", "-o", f["clearp"].parent / "sim2"], 2,
     ["--rotation 1e30deg: a sequence turns by at most 360 deg"]),
    ("sweep: simulate --declination 95 (was accepted)",
     lambda f: ["simulate", "--hour-angle", "-1,1", "--declination", "95", "-o",
                f["clearp"].parent / "sim3"], 2,
     ["--declination 95: a declination is within +-90 deg"]),
    ("sweep: inject --position 1e30,0 (was exit 3)",
     lambda f: ["inject", f["clean_plain"][0], "--position", "1e30,0", "--contrast", "0.1"], 2,
     ["inject: a companion at (1e+30, 0) mas (detector) falls off the image: 100% of its flux"]),
    ("sweep: inject --pa nan (was 'give --pa')",
     lambda f: ["inject", f["clean_plain"][0], "--position", "10,0", "--sky", "--contrast",
                "0.1", "--pa", "nan"], 2, ["cannot read --pa 'nan'"]),
    ("17: unknown NIRISS PUPIL refused",
     lambda f: ["extract", f["gr700xd"], "--calibrator", f["clearp_cal"]], 2,
     ["gr700xd_calints.fits: NIRISS PUPIL 'GR700XD' is no pupil element kpifs models"]),
]


#: Cases that run an extraction of several seconds (GPI: 8 exposures of 37 channels).
SLOW_CASES = ("13: one NaN AVPARANG of 8 GPI exposures: left out, said",
              "13: a missing AVPARANG: left out, said")


@pytest.mark.parametrize("name, argv, code, texts", [
    pytest.param(*c, marks=[pytest.mark.slow] if c[0] in SLOW_CASES else [], id=c[0])
    for c in CASES])
@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::ResourceWarning")
def test_refused_or_said(corpus, tmp_path, capsys, name, argv, code, texts):
    message = _run(corpus, tmp_path, capsys, argv(corpus), code)
    for text in texts:
        assert text.format(**{k: v for k, v in corpus.items()}) in message, message


@pytest.mark.slow
def test_same_setup_through_the_python_api(corpus):
    """The refusal is made where target and calibrator meet: `calibrate` too."""
    from kpifs.calibration.calibrate import calibrate
    from kpifs.workflow import ExtractOptions, extract_observation
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KpifsWarning)
        t = extract_observation(corpus["clearp"], ExtractOptions())
        c = extract_observation(corpus["nrm_cal"], ExtractOptions(), model=t.kernel_model)
    with pytest.raises(KpifsError, match="pupil element NRM, but the target"):
        calibrate(t, [c])
    # kernel-phase files read back keep the headers: `detect --calibrator` refuses too
    kt = t.write(corpus["clearp"].parent / "t_kp.fits")
    kc = c.write(corpus["clearp"].parent / "c_kp.fits")
    with pytest.raises(KpifsError, match="pupil element NRM"):
        calibrate(KernelPhaseData.read(kt), [KernelPhaseData.read(kc)])


def _found(det, sep, pa, *, dsep=15.0, dpa=3.0):
    """The detection file's single candidate at (sep mas, PA deg East of North), within
    *dsep* (NIRISS at 4.8 um: a tenth of lambda/D) and *dpa*."""
    from kpifs.data import DetectionResult
    cands = DetectionResult.read(det).candidates
    assert len(cands) == 1, cands
    assert abs(cands[0]["fit_separation"].to_value(u.mas) - sep) < dsep, cands
    assert abs((cands[0]["fit_pa_sky"].to_value(u.deg) - pa + 180) % 360 - 180) < dpa
    return cands[0]


#: The NIRISS preset's companion: (dRA, dDec) = (-150, 200) mas, contrast 1e-2.
NIRISS_TRUTH = (250.0, 323.13)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::ResourceWarning")
@pytest.mark.parametrize("target, cal, said", [
    ("err_x100_t", "err_x100_c", "times the frames' own scatter"),           # 5
    ("norm_t", "norm_c", "times the frames' own scatter"),                   # 5: DN/s
    ("inf_t", "clearp_cal", "40 infinite pixel value(s), treated as bad"),   # 6
    ("clearp", "clearp_cal", None)])                                         # the reference
def test_err_and_inf_keep_the_companion(corpus, tmp_path, capsys, target, cal, said):
    """ERR 100 x too large, SCI normalised with ERR left in DN/s, and +inf pixels: the
    companion of the NIRISS preset is found where it is (250 mas, PA 323.1 deg), as from
    the clean files (before: lost; ERR x100: noise scale clamped at 0.1)."""
    kp, det = tmp_path / "kp.fits", tmp_path / "det.fits"
    message = _run(corpus, tmp_path, capsys, ["extract", corpus[target], "--calibrator",
                                              corpus[cal], "-o", kp], 0)
    assert said is None or said in message, message
    message = _run(corpus, tmp_path, capsys, ["detect", kp, "-o", det, "--draws", "1000"], 0)
    assert "clamped" not in message
    _found(det, *NIRISS_TRUTH)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::ResourceWarning")
def test_pixscale_applied_where_it_fits(corpus, tmp_path, capsys):
    """#4: --pixscale 31mas with F150W (31 mas) and F480M (63 mas): applied to F150W, F480M
    keeps its own, with a note; the binary's contrasts come out as simulated (0.076, 0.19;
    before: F480M 0.0089)."""
    kp, det = tmp_path / "kp.fits", tmp_path / "det.fits"
    message = _run(corpus, tmp_path, capsys, ["extract", *corpus["nc_t"], "--calibrator",
                                              *corpus["nc_c"], "--pixscale", "31mas", "-o", kp], 0)
    assert (f"the pixel scale given (31 mas) is applied to F150W only: it contradicts the own "
            f"scale of F480M 63 mas ({corpus['nc_t480']}), which is kept") in message
    _run(corpus, tmp_path, capsys, ["detect", kp, "-o", det, "--draws", "1000"], 0)
    row = _found(det, 84.0, 295.0, dsep=4.0, dpa=2.0)
    assert np.asarray(row["fit_contrast"]) == pytest.approx([0.076, 0.19], rel=0.1)


def test_noise_scale_clamp_is_said():
    """#5: errors 100 x too large for the data: the noise scale is clamped at 0.1 with a
    warning, never silently."""
    from kpifs import KernelModel, make_pupil
    from kpifs.detect import detect
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.8 * u.m))
    rng = np.random.default_rng(0)
    kpd = KernelPhaseData(rng.normal(0, 0.01, (1, 2, km.n_kp)), [1.6, 1.7] * u.um, 10 * u.mas,
                          km, covariance=np.broadcast_to(np.eye(km.n_kp), (2, km.n_kp, km.n_kp)),
                          meta={"calibrated": True})
    with pytest.warns(KpifsWarning, match="noise scale clamped at 0.1"):
        res = detect(kpd, n_draws=1000, seed=0)
    assert res.meta["noise_scale"] == 0.1


@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::ResourceWarning")
@pytest.mark.parametrize("layout", ["jwst", "charis", "gpi", "sphere", "plain"])
def test_inject_keeps_the_layout(corpus, tmp_path, capsys, layout):
    """#8: an injected file is a copy of its input in the instrument's layout, with the
    companion added where the input was read as good: read back, it is the input plus
    exactly the companion `inject_companion` makes (to float32 precision), and keeps what
    the instrument's reader needs (JWST: ERR, DQ, PUPIL, ROLL_REF; GPI: the mirror, crop and
    AVPARANG; CHARIS: PARANG and the inverse variance). Several files go to a folder."""
    from kpifs.inject import inject_companion
    from kpifs.io import read_cube
    src = [p for p in corpus[f"clean_{layout}"] if "wavelength" not in p.name
           and "angles" not in p.name]
    out = tmp_path / ("inj" if len(src) > 1 else "inj.fits")
    args = ["inject", *src, "--sky", "--position", "-60,40", "--contrast", "0.05", "-o", out]
    if layout == "plain":
        args += ["--pa", "30"]
    message = _run(corpus, tmp_path, capsys, args, 0)
    assert ("a SPHERE-IFS cube: its wavelengths and frame angles are in the files beside"
            in message) == (layout == "sphere")
    outs = [out / p.name for p in src] if len(src) > 1 else [out]
    opts = dict(wavelengths=[1.5, 1.6, 1.7] * u.um) if layout == "plain" else {}
    with read_cube(src) as cube:
        before = np.array(cube.data, float)
        detpa = np.full(len(before), 30.0) if layout == "plain" else cube.detpa.value
        expected = inject_companion(before, position=[-60, 40] * u.mas, contrast=0.05,
                                    pixscale=cube.pixscale, frame="sky", detpa=detpa)
        wl = cube.wavelengths
    with read_cube(outs, wavelengths=wl if layout == "sphere" else opts.get("wavelengths")) \
            as back:
        after = np.array(back.data, float)
        assert back.instrument == ("generic" if layout == "plain" else layout)
        good = np.isfinite(before)
        assert np.array_equal(good, np.isfinite(after))
        scale = np.nanmax(np.abs(before))
        assert np.abs(after - expected)[good].max() < 1e-6 * scale
        assert np.abs(after - before)[good].max() > 1e-3 * scale     # a companion is there
        if layout != "sphere":
            assert np.allclose(back.detpa.value, cube.detpa.value if layout != "plain" else 0)
    with fits.open(outs[0]) as h, fits.open(src[0]) as s0:
        assert h[0].header["INJC1"] == 0.05 and "companion injected" in str(h[0].header)
        assert [x.name for x in h] == [x.name for x in s0]
        if layout == "jwst":
            for name in ("ERR", "DQ"):
                assert np.array_equal(h[name].data, s0[name].data, equal_nan=True)
            assert h[0].header["PUPIL"] == "CLEARP"
            assert h["SCI"].header["ROLL_REF"] == s0["SCI"].header["ROLL_REF"]


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::ResourceWarning")
def test_injected_jwst_file_found_against_its_calibrator(corpus, tmp_path, capsys):
    """#8: a companion injected into a JWST file (NIRISS preset position, contrast 1e-2)
    is found there when the injected file is calibrated by a JWST calibrator (before: a
    generic cube read with the Subaru pupil, both companions lost)."""
    inj, kp, det = tmp_path / "inj.fits", tmp_path / "kp.fits", tmp_path / "det.fits"
    _run(corpus, tmp_path, capsys, ["inject", corpus["clean_jwst"][0], "--sky", "--position",
                                    "-150,200", "--contrast", "0.01", "-o", inj], 0)
    _run(corpus, tmp_path, capsys, ["extract", inj, "--calibrator", corpus["clean_jwst_cal"][0],
                                    "-o", kp], 0)
    assert KernelPhaseData.read(kp).kernel_model.pupil.name == "niriss_clearp"
    _run(corpus, tmp_path, capsys, ["detect", kp, "-o", det, "--draws", "1000"], 0)
    _found(det, *NIRISS_TRUTH)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::ResourceWarning")
def test_injection_curve_reads_the_header_pupil(corpus, tmp_path, capsys):
    """#7: `inject --curve` on NIRISS CLEARP files uses the header's pupil (niriss_clearp: the
    same analytic limit as with --pupil niriss_clearp, 7.2e-4 at 250 mas; before: the full
    JWST pupil's, 4e-3), and reduces each injection as the target (its ERR: 1e-2 found at
    both angles; before: not found, the injections calibrated on 10 frames' scatter alone)."""
    out = tmp_path / "curve.fits"
    message = _run(corpus, tmp_path, capsys, [
        "inject", corpus["clean_jwst"][0], "--curve", "--calibrator",
        corpus["clean_jwst_cal"][0], "--separations", "250mas", "--contrasts", "0.01",
        "--angles", "2", "--draws", "1000", "--injection-draws", "1000", "-o", out], 0)
    # found at both angles (2 of 2 is no bracket: issue 36 prints what the steps allow)
    assert "250 mas: injections" in message and "found 2/2 at 1.0e-02" in message, message
    with fits.open(out) as h:
        analytic = float(h["LIMITS"].data["limit_analytic"][0])
    assert 5e-4 < analytic < 1e-3


def _examples():
    """Every ``kpifs ...`` example line of every command's --help (continuations joined)."""
    import re
    from kpifs._cli import _epilogs
    text = "\n".join(v for k, v in vars(_epilogs).items() if k.startswith("EPILOG_"))
    text = re.sub(r"\\\n\s*", " ", text)
    return [ln.split("#")[0].strip() for ln in text.splitlines()
            if ln.strip().startswith("kpifs ")]


@pytest.mark.parametrize("line", _examples())
def test_every_help_example_parses(line):
    """#17: each example of the commands' --help parses as written (model-check's
    ``--rotations -3,-2,-1,0,1,2,3`` was taken for an option)."""
    import shlex
    from kpifs._cli._parser import build_parser, join_negative_values
    args = build_parser().parse_args(join_negative_values(shlex.split(line)[1:]))
    assert args.command == line.split()[1]


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::ResourceWarning")
def test_gpi_unknown_angle_keeps_the_others_on_the_sky(corpus, tmp_path, capsys):
    """#13: one NaN AVPARANG of 8 exposures: the exposure is left out and the other seven
    are searched on the sky; the companion is found at its simulated sky offset (dRA 120,
    dDec 160 mas: 200 mas, PA 36.9 deg; before: the whole search on the detector, lost).
    (240 x 240 images: at 200 x 200 this scene's companion is not found even without NaN,
    in the plain layout as well. The NaN is in the last exposure: without a middle one,
    or with 5 left of 6, `kpifs.rotation.time_blocks` merges frames into a block
    spanning
    11.4 deg, which smears the companion at 200 mas, and it is lost: reported.)"""
    kp, det = tmp_path / "kp.fits", tmp_path / "det.fits"
    _run(corpus, tmp_path, capsys, ["extract", *corpus["gpi8_nan"], "--calibrator",
                                    *corpus["gpi8_cal"], "-o", kp], 0)
    assert KernelPhaseData.read(kp).meta["n_target_frames"] == 7
    _run(corpus, tmp_path, capsys, ["detect", kp, "-o", det, "--draws", "1000"], 0)
    _found(det, 200.0, 36.87, dsep=20.0, dpa=3.0)


@pytest.mark.parametrize("layout", ["plain", "jwst"])
def test_simulated_rotation_writes_every_angle(tmp_path, capsys, layout):
    """#14: `simulate --rotation` writes each frame's detector angle: the plain layout a DETPA
    extension (before: none), the JWST layout one exposure per angle (before: one file at
    the mean angle); read back, the angles are the simulated ones."""
    from kpifs.io import read_cube
    from kpifs.rotation import sequence_angles
    out = tmp_path / "sim"
    assert main(["simulate", "--preset", "niriss" if layout == "jwst" else "paper",
                 "--rotation", "40deg", "--frames", "4", "--shape", "32", "--layout", layout,
                 "-q", "-o", str(out)]) == 0
    expected = sequence_angles(4, span=40 * u.deg, start=0.0)
    target = sorted(p for p in out.iterdir() if "target" in p.name or "_1000" in p.name)
    assert len(target) == (1 if layout == "plain" else 4)
    with read_cube(target) as cube:
        assert cube.detpa.to_value(u.deg) == pytest.approx(np.asarray(expected, float),
                                                           abs=1e-6)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::ResourceWarning")
def test_simulated_rotation_found_on_the_sky(tmp_path, capsys):
    """#14: a plain-layout rotating sequence (40 deg, 20 frames, contrast 0.01) is searched
    on the sky and its companion found where simulated (dRA -80, dDec 60 mas: 100 mas, PA
    306.9 deg; before: no angles written, found at PA 273.5 deg with P_FA 3.8e-7)."""
    sim, kp, det = tmp_path / "sim", tmp_path / "kp.fits", tmp_path / "det.fits"
    assert main(["simulate", "--preset", "paper", "--rotation", "40deg", "--frames", "20",
                 "--contrasts", "0.01", "--shape", "32", "--seed", "2", "-q", "-o",
                 str(sim)]) == 0
    assert main(["extract", str(sim / "target.fits"), "--calibrator",
                 str(sim / "calibrator.fits"), "--step", "0.8m", "-q", "-o", str(kp)]) == 0
    assert main(["detect", str(kp), "--draws", "1000", "-q", "-o", str(det)]) == 0
    _found(det, 100.0, 306.87, dsep=8.0, dpa=3.0)


def test_sizes_bounded_before_allocation(corpus, tmp_path, capsys, monkeypatch):
    """#12: what a file's or the options' numbers imply is bounded before it is allocated:
    a simulation (was exit 3, MemoryError), the frames `inject` and `model-check` read whole,
    a JWST DQ read into memory."""
    import kpifs._memory
    message = _run(corpus, tmp_path, capsys, ["simulate", "--frames", "100000", "--shape",
                                              "2048", "-q", "-o", tmp_path / "sim"], 2)
    assert "a simulation of 100000 frames x 3 channels of 2048 x 2048 pixels needs about " \
           "18.3 TiB of memory" in message
    monkeypatch.setattr(kpifs._memory, "available_memory", lambda: 2 ** 20)
    src = corpus["clean_jwst"][0]
    message = _run(corpus, tmp_path, capsys, ["inject", src, "--position", "100,0",
                                              "--contrast", "0.01"], 2)
    assert f"{src}: DQ of 6.4e+04 pixels" not in message   # 1 MiB: fits
    assert f"{src}: 10 frames of 1 x 80 x 80 needs about 1.46 MiB of memory (1 MiB available)" \
        in message
    monkeypatch.setattr(kpifs._memory, "available_memory", lambda: 900 * 2 ** 10)
    message = _run(corpus, tmp_path, capsys, ["model-check", src, "-q"], 2)
    assert f"{src}: 10 frames of 1 x 80 x 80 needs about 1000 KiB" in message
    monkeypatch.setattr(kpifs._memory, "available_memory", lambda: 2 ** 19)
    message = _run(corpus, tmp_path, capsys, ["info", src], 2)
    assert f"{src}: DQ of 6.4e+04 pixels needs about 812 KiB of memory (512 KiB available)" \
        in message
