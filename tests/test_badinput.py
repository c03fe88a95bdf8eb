"""Bad inputs through the command line: a clear one-line message naming the file and
the problem, exit status 2 for errors, inputs byte-identical, no partial output."""
import hashlib
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

from kpifs import KernelPhaseData
from kpifs.cli import main
from kpifs.io.layouts import write_observation
from kpifs.simulation.simulate import simulate_scene

from kpfits_layouts import parts_of, write_jwstkpi, write_pykernel


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    d = tmp_path_factory.mktemp("corpus")
    paper = simulate_scene("paper", n_frames=4, seed=3, npup=48)
    plain = write_observation(paper, d / "plain")
    charis = write_observation(simulate_scene("charis", n_frames=3, seed=3, npup=48,
                                              shape=(64, 64)), d / "charis", layout="charis")
    sphere = write_observation(simulate_scene("sphere", n_frames=2, seed=3, npup=48),
                               d / "sphere", layout="sphere")
    f = {"target": plain["target"][0], "cal": plain["calibrator"][0],
         "charis": charis["target"][0], "charis_tgt": charis["target"],
         "charis_cal": charis["calibrator"],
         "sphere_cube": sphere["target"][0]}
    with fits.open(f["target"]) as h:
        data, hdr = h[0].data.copy(), h[0].header.copy()
    f["truncated"] = d / "truncated.fits"
    f["truncated"].write_bytes(f["target"].read_bytes()[:10000])
    f["notfits"] = d / "notfits.fits"
    f["notfits"].write_text("SIMPLE = this is not FITS\n" * 20)
    f["naxis1"] = d / "spectrum.fits"
    fits.writeto(f["naxis1"], np.arange(100.0))
    f["naxis5"] = d / "fivedim.fits"
    fits.writeto(f["naxis5"], np.ones((2, 2, 3, 8, 8)))
    bad = data.copy()
    bad[2, 1] = np.nan
    f["nanslice"] = d / "nanslice.fits"
    fits.writeto(f["nanslice"], bad, hdr)
    bad = data.copy()
    bad[3] = 0
    f["zeroframe"] = d / "zeroframe.fits"
    fits.writeto(f["zeroframe"], bad, hdr)
    bad = data.copy()
    bad[1] = np.nan
    bad[3, 2] = -np.abs(bad[3, 2])                       # a sign-flipped slice: no flux
    f["twobad"] = d / "twobad.fits"
    fits.writeto(f["twobad"], bad, hdr)
    cy, cx = np.unravel_index(np.argmax(data[0, 0]), data.shape[2:])
    bad = data.copy()
    bad[0, 0, 5, 5] = np.inf
    f["infpix"] = d / "infpix.fits"
    fits.writeto(f["infpix"], bad, hdr)
    bad = data.copy()
    bad[:, :, cy - 1:cy + 2, cx - 1:cx + 2] = np.nan      # saturated core masked
    f["corenan"] = d / "corenan.fits"
    fits.writeto(f["corenan"], bad, hdr)
    bad = data - 0.5 * data.max(axis=(2, 3), keepdims=True) / data.shape[3]
    f["negative"] = d / "negative.fits"                   # background over-subtracted
    fits.writeto(f["negative"], bad, hdr)
    edge = np.roll(data, (-17, -17), axis=(2, 3))          # star 3 pixels from a corner
    f["edge"] = d / "edge.fits"
    fits.writeto(f["edge"], edge, hdr)
    for name, cards in {"nlam": dict(NLAM=20), "lammax": dict(LAM_MAX=3000.0)}.items():
        with fits.open(f["charis"]) as h:
            h[0].header.update(cards)
            f[name] = d / f"{name}_cube.fits"
            h.writeto(f[name])
    hdr2 = hdr.copy()
    del hdr2["KPWL3"]
    f["twochan"] = d / "twochannels.fits"
    fits.writeto(f["twochan"], data[:, :2], hdr2)
    hdr3 = hdr.copy()
    hdr3["PIXSCALE"] = 12.0
    f["otherscale"] = d / "otherscale.fits"
    fits.writeto(f["otherscale"], data, hdr3)
    f["single"] = d / "single.fits"
    fits.writeto(f["single"], data[:1], hdr)
    f["wl_unknown"] = d / "wl_unknown.txt"
    np.savetxt(f["wl_unknown"], [50.0, 60.0, 70.0])
    f["pupil_noscale"] = d / "pupil_noscale.fits"
    fits.writeto(f["pupil_noscale"], np.ones((64, 64)))
    f["adir"] = d / "adir.fits"
    f["adir"].mkdir()
    f["lone_sphere"] = d / "lone" / "science_cube.fits"
    f["lone_sphere"].parent.mkdir()
    f["lone_sphere"].write_bytes(f["sphere_cube"].read_bytes())
    # kernel-phase files (0.8 m model: 74 kernel phases), made with kpifs itself
    kp = d / "kp"
    kp.mkdir()
    common = ["--step", "0.8m", "-q"]
    assert main(["extract", str(f["target"]), "--calibrator", str(f["cal"]), *common,
                 "-o", str(kp / "calibrated.fits")]) == 0
    assert main(["extract", str(f["target"]), *common, "-o", str(kp / "target_kp.fits")]) == 0
    assert main(["extract", str(f["cal"]), *common, "-o", str(kp / "cal_kp.fits")]) == 0
    assert main(["extract", str(f["twochan"]), *common, "-o", str(kp / "twochan_kp.fits")]) == 0
    fits.writeto(d / "two_frames.fits", data[:2], hdr)
    assert main(["extract", str(d / "two_frames.fits"), *common,
                 "-o", str(kp / "twoframes_kp.fits")]) == 0
    names = ("calibrated", "target_kp", "cal_kp", "twochan_kp", "twoframes_kp")
    f.update({k: kp / f"{k}.fits" for k in names})
    f["two_frames"] = d / "two_frames.fits"
    raw = bytearray((kp / "calibrated.fits").read_bytes())
    with fits.open(kp / "calibrated.fits") as h:
        where = h.fileinfo(h.index_of("KP-DATA"))["datLoc"]
    raw[where + 11] ^= 0x40                                   # one flipped bit in the data
    f["kp_corrupt"] = kp / "kp_corrupt.fits"
    f["kp_corrupt"].write_bytes(bytes(raw))
    f["kp_trunc"] = kp / "kp_trunc.fits"
    f["kp_trunc"].write_bytes(bytes(raw[:len(raw) // 2]))
    raw = bytearray((kp / "cal_kp.fits").read_bytes())
    raw[where + 11] ^= 0x40
    f["calkp_corrupt"] = kp / "calkp_corrupt.fits"
    f["calkp_corrupt"].write_bytes(bytes(raw))
    hdr4 = hdr.copy()
    for key in ("KPWL1", "KPWL2", "KPWL3"):
        del hdr4[key]
    hdr4["INSTRUME"] = "CHARIS"
    f["nowl_cube"] = d / "nowl.fits"
    fits.writeto(f["nowl_cube"], data)
    f["charis_nowl"] = d / "charis_nowl.fits"
    fits.writeto(f["charis_nowl"], data, hdr4)
    (d / "nocol.csv").write_text("name,target\nx,plain/target.fits\n")
    f["nocol"] = d / "nocol.csv"
    (d / "one.csv").write_text("name,target,calibrator\n"
                               f"good,{f['target']},{f['cal']}\n"
                               f"badcal,{f['target']},{f['truncated']}\n")
    f["one"] = d / "one.csv"
    f["unwritable"] = _unwritable(d)
    f.update(_other_tools_files(d, f["target_kp"]))
    f.update(_issue25_files(d, f, data, hdr))
    return f


def _rewrite(src, dst, edit):
    """A copy of FITS file *src* at *dst*, changed by ``edit(hdulist)``, checksums renewed."""
    with fits.open(src) as h:
        hl = fits.HDUList([x.copy() for x in h])
    edit(hl)
    hl.writeto(dst, checksum=True)
    return dst


def _issue25_files(d, f, data, hdr):
    """Inputs of the sweep of issue 25: calibrations twice, scaled integers, manifests..."""
    import os
    out = {}
    kp = d / "kp"
    raw = bytearray(f["target_kp"].read_bytes())
    with fits.open(f["target_kp"]) as h:
        where = h.fileinfo(h.index_of("KP-DATA"))["datLoc"]
    raw[where + 11] ^= 0x40
    out["tkp_corrupt"] = kp / "tkp_corrupt.fits"
    out["tkp_corrupt"].write_bytes(bytes(raw))
    out["tkp_copy"] = kp / "target_kp_copy.fits"             # the same star under a new name
    out["tkp_copy"].write_bytes(f["target_kp"].read_bytes())
    out["target_link"] = d / "target_link.fits"
    os.symlink(f["target"], out["target_link"])
    out["nan_rows"] = _rewrite(f["calibrated"], kp / "nan_rows.fits", lambda h: h[
        "KP-COVROWS"].data.__setitem__((0, 1, 2), np.nan))

    def not_a_covariance(h):
        cov = h["KP-COV"].data
        cov[..., 0, 0] = -10 * np.abs(cov).max()
        for name in ("KP-COVROWS", "KP-FITROWS", "KP-BLKROWS"):
            del h[name]
    out["bad_cov"] = _rewrite(f["calibrated"], kp / "bad_cov.fits", not_a_covariance)

    def no_angles(h):
        for name in ("DETPA", "DETPA-FR"):
            if name in h:
                h[name].data = np.full_like(h[name].data, np.nan)
    out["no_pa"] = _rewrite(f["calibrated"], kp / "no_pa.fits", no_angles)
    scaled = fits.PrimaryHDU(data.astype(np.float32), hdr)
    scaled.scale("int16", bscale=float(data.max() / 30000), bzero=0.0)
    out["int16"] = d / "int16.fits"
    scaled.writeto(out["int16"])
    out["uint16"] = d / "uint16.fits"
    fits.PrimaryHDU(np.round(data / data.max() * 60000).astype(np.uint16),
                    hdr).writeto(out["uint16"])
    dead = data.copy()
    dead[:, 1] = np.nan
    out["dead"] = d / "deadchannel.fits"
    fits.writeto(out["dead"], dead, hdr)
    out["accent"] = d / "données" / "cible.fits"
    out["accent"].parent.mkdir()
    out["accent"].write_bytes(f["target"].read_bytes())
    wl22 = d / "charis_wl.txt"
    np.savetxt(wl22, 1.1596 * np.exp(np.arange(22) * 0.0344), header="um")
    out["charis_wl"] = wl22
    out["model"] = d / "model.fits"
    assert main(["kernel", "--step", "0.8m", "-q", "-o", str(out["model"])]) == 0
    target, cal = f["target"], f["cal"]
    manifests = {"escape": f"../x,{target},{cal}\n", "absolute": f"/tmp/abs,{target},{cal}\n",
                 "slash": f"a/b,{target},{cal}\n", "dot": f".,{target},{cal}\n",
                 "twice": f"twice,{target};{out['target_link']},{cal}\n",
                 "selfcal": f"self,{target},{target}\n", "header_only": ""}
    for name, rows in manifests.items():
        out[f"m_{name}"] = d / f"m_{name}.csv"
        out[f"m_{name}"].write_text("name,target,calibrator\n" + rows)
    out["m_bom"] = d / "m_bom.csv"
    out["m_bom"].write_bytes("name,target,calibrator\nbom,missing_t.fits,missing_c.fits\n"
                             .encode("utf-8-sig"))
    locked = d / "locked"
    locked.mkdir()
    (locked / ".kpifs-batch.lock").write_text(
        '{"pid": %d, "host": "%s", "time": 1.0e9}' % (os.getpid(), __import__(
            "socket").gethostname()))
    out["locked"] = locked / ".kpifs-batch.lock"
    sim = d / "earlier_sim"
    sim.mkdir()
    (sim / "target.fits").write_bytes(b"an earlier simulation")
    out["earlier_sim"] = sim / "target.fits"
    out["curve"] = _injection_product(d / "curve.fits")
    return out


def _injection_product(path):
    """A file as ``kpifs inject --curve`` writes it (two separations)."""
    from astropy import units as u
    from astropy.table import QTable
    hdr = fits.Header({"CONTENT": "KPIFS-INJECTION", "PFA": 1e-3, "PD": 0.5, "NANGLES": 4})
    inj = QTable({"separation": [100.0, 100.0, 200.0, 200.0] * u.mas,
                  "contrast": [1e-3, 2e-3, 1e-3, 2e-3], "n_injected": [4] * 4,
                  "n_detected": [1, 3, 2, 4], "pd": [0.25, 0.75, 0.5, 1.0]})
    lim = QTable({"separation": [100.0, 200.0] * u.mas, "limit_injection": [1.41e-3, 1e-3],
                  "limit_analytic": [1.3e-3, 0.9e-3]})
    t1, t2 = fits.table_to_hdu(inj), fits.table_to_hdu(lim)
    t1.name, t2.name = "INJECTIONS", "LIMITS"
    fits.HDUList([fits.PrimaryHDU(header=hdr), t1, t2]).writeto(path, checksum=True)
    return path


def _other_tools_files(d, target_kp):
    """KPFITS files as other tools write them (from kpifs's own 4-frame extraction)."""
    kpd = KernelPhaseData.read(target_kp)
    p = parts_of(kpd)
    one = dict(p, kp=kpd.kp[:, :1], wavelengths=p["wavelengths"][:1])
    cov = 1e-4 * np.eye(kpd.n_kp)
    out = {"jwst_uncal": write_jwstkpi(d / "jwst_uncal.fits", p, detpa=10.0, cov=cov),
           "pyk_tel": write_pykernel(d / "pyk_tel.fits", one, detpa=5.0, cov=cov, tel_rows=3)}
    good = write_pykernel(d / "pyk_good.fits", one, detpa=5.0, cov=cov)
    for name, edit in (("pyk_blm", lambda h: h.__setitem__(
            "BLM-MAT", fits.ImageHDU(h["BLM-MAT"].data[:, 2:], name="BLM-MAT"))),
                       ("pyk_nouv", lambda h: h.pop(h.index_of("UV-PLANE"))),
                       ("pyk_nowl", lambda h: [h[0].header.remove(k) for k in
                                               ("CWAVE", "CENWAVE")])):
        with fits.open(good) as h:
            hl = fits.HDUList([x.copy() for x in h])
        edit(hl)
        out[name] = d / f"{name}.fits"
        hl.writeto(out[name])
    return out


def _unwritable(base):
    """A folder no new file can be written in: read-only for a normal user, or /sys
    (refused even to root); None when there is none."""
    import os
    import tempfile
    ro = base / "readonly"
    ro.mkdir()
    os.chmod(ro, 0o500)
    for cand in (ro, Path("/sys")):
        try:
            fd, probe = tempfile.mkstemp(dir=cand)
        except OSError:
            return cand
        os.close(fd)
        os.remove(probe)
    return None


def _hashes(files):
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in files if p.is_file()}


CASES = [
    # (name, argv builder, expected exit, text in the message)
    ("truncated FITS", lambda f: ["extract", f["truncated"]], 2, "truncated.fits"),
    ("not FITS", lambda f: ["extract", f["notfits"]], 2, "notfits.fits: not a readable FITS"),
    ("NAXIS 1", lambda f: ["extract", f["naxis1"], "--wavelengths", "1.6um", "--pixscale",
                           "10mas"], 2, "spectrum.fits: no image data"),
    ("NAXIS 5", lambda f: ["extract", f["naxis5"], "--wavelengths", "1.5,1.6,1.7",
                           "--pixscale", "10mas"], 2, "5 dimensions"),
    ("NLAM vs cube", lambda f: ["extract", f["nlam"]], 2, "NLAM = 20 but the cube has 22"),
    ("LAM_MAX contradicts", lambda f: ["extract", f["lammax"]], 2, "LAM_MAX = 3000.0"),
    ("wavelength unit", lambda f: ["extract", f["target"], "--wavelengths", "1.5kg,1.6,1.7"],
     2, "wrong unit"),
    ("wavelength file unit", lambda f: ["extract", f["target"], "--wavelengths",
                                        f["wl_unknown"]], 2, "cannot tell the unit"),
    ("all-NaN slice dropped", lambda f: ["extract", f["nanslice"]], 0,
     "nanslice.fits: 1 bad frame(s) of 4 dropped: frame(s) 2: empty (first at 1.600 um)"),
    ("all-NaN slice, --bad-frames fail",
     lambda f: ["extract", f["nanslice"], "--bad-frames", "fail"], 2,
     "nanslice.fits: 1 bad frame(s) of 4: frame(s) 2: empty"),
    ("all-zero frame dropped", lambda f: ["extract", f["zeroframe"]], 0,
     "zeroframe.fits: 1 bad frame(s) of 4 dropped: frame(s) 3: empty"),
    ("two bad frames of four", lambda f: ["extract", f["twobad"]], 2,
     "twobad.fits: only 2 good frame(s) of 4 (frame(s) 1: empty"),
    ("sign-flipped slice named", lambda f: ["extract", f["twobad"], "--bad-frames", "fail"], 2,
     "frame(s) 3: no positive flux"),
    ("infinite pixel", lambda f: ["extract", f["infpix"]], 0,
     "infpix.fits: 1 infinite pixel value(s), treated as bad pixels"),
    ("NaN patch on the core", lambda f: ["extract", f["corenan"]], 0,
     "corenan.fits: bad or NaN pixels on the PSF core (more than 10% of the flux "
     "interpolated) in 12 of 12 slice(s)"),
    ("negative flux", lambda f: ["extract", f["negative"]], 0,
     "negative.fits: negative pixels hold more than 10% of the positive flux"),
    ("calibrator channels", lambda f: ["extract", f["target"], "--calibrator",
                                       f["twochan"]], 2,
     "twochannels.fits has channels 1.5200-1.6000 um (2 channels), the target"),
    ("calibrator pixel scale", lambda f: ["extract", f["target"], "--calibrator",
                                          f["otherscale"]], 2, "otherscale.fits has pixel"),
    ("single target frame", lambda f: ["extract", f["single"], "--calibrator", f["cal"]], 2,
     "single frame without a covariance"),
    ("input is a directory", lambda f: ["extract", f["adir"]], 2, "adir.fits: is a directory"),
    ("missing input", lambda f: ["extract", f["adir"].parent / "nope.fits"], 2,
     "nope.fits: file not found"),
    ("missing calibrator", lambda f: ["extract", f["target"], "--calibrator",
                                      f["adir"].parent / "nocal.fits"], 2, "nocal.fits"),
    ("pupil without scale", lambda f: ["extract", f["target"], "--pupil",
                                       f["pupil_noscale"]], 2, "PUPSCALE"),
    ("unknown pupil", lambda f: ["extract", f["target"], "--pupil", "hubble"], 2,
     "unknown pupil 'hubble'"),
    ("plain cube read as CHARIS", lambda f: ["extract", f["target"], "--instrument",
                                             "charis"], 2, "not a CHARIS pipeline cube"),
    ("SPHERE without wavelengths", lambda f: ["extract", f["lone_sphere"]], 2,
     "science_cube.fits: no wavelengths"),
    ("window larger than image", lambda f: ["extract", f["target"], "--window", "80"], 2,
     "larger than"),
    ("info on a truncated file", lambda f: ["info", f["truncated"]], 2, "truncated.fits"),
    ("extract: pixel scale 0", lambda f: ["extract", f["target"], "--pixscale", "0mas"], 2,
     "pixel scale must be > 0"),
    ("extract: 1.52m for 1.52um",
     lambda f: ["extract", f["target"], "--wavelengths", "1.52m,1.60um,1.68um"], 2,
     "outside 0.3-30 um"),
    ("extract: unwritable folder", lambda f: ["extract", f["target"], "-o",
                                              _in(f, "unwritable", "kp.fits")], 2,
     "cannot write in"),
    ("extract: 2-frame calibrator", lambda f: ["extract", f["target"], "--calibrator",
                                               f["two_frames"]], 2, "2 frames are too few"),
    ("extract: CHARIS override count", lambda f: ["extract", *f["charis_tgt"],
                                                  "--wavelengths", "1.2um,1.3um"], 2,
     "2 wavelength(s) given but the cube has 22"),
    # detection
    ("detect: corrupted KPFITS", lambda f: ["detect", f["kp_corrupt"]], 2,
     "kp_corrupt.fits: checksum mismatch (corrupted?)"),
    ("detect: truncated KPFITS", lambda f: ["detect", f["kp_trunc"]], 2,
     "kp_trunc.fits: truncated FITS file"),
    ("detect: corrupted target, healthy calibrator",
     lambda f: ["detect", f["tkp_corrupt"], "--calibrator", f["cal_kp"]], 2,
     "tkp_corrupt.fits: checksum mismatch"),
    ("detect: healthy target, corrupted calibrator",
     lambda f: ["detect", f["target_kp"], "--calibrator", f["calkp_corrupt"]], 2,
     "calkp_corrupt.fits: checksum mismatch"),
    ("detect: uncalibrated", lambda f: ["detect", f["target_kp"]], 2,
     "target_kp.fits: not calibrated"),
    ("detect: --draws 0", lambda f: ["detect", f["calibrated"], "--draws", "0"], 2,
     "0 Monte-Carlo draws cannot resolve"),
    ("detect: too few draws", lambda f: ["detect", f["calibrated"], "--draws", "300"], 2,
     "use at least 1000"),
    ("detect: P_FA out of range", lambda f: ["detect", f["calibrated"], "--pfa", "2"], 2,
     "P_FA must be in (0, 1)"),
    ("detect: spectrum text", lambda f: ["detect", f["calibrated"], "--spectrum", "blue"], 2,
     "spectrum: expected 'flat'"),
    ("detect: spectrum length", lambda f: ["detect", f["calibrated"], "--spectrum", "1,2"], 2,
     "the spectrum has 2 values for 3 channels"),
    ("detect: a cube given", lambda f: ["detect", f["target"]], 2,
     "target.fits: no KP-DATA extension"),
    ("detect: missing file", lambda f: ["detect", f["adir"].parent / "none_kp.fits"], 2,
     "none_kp.fits: file not found"),
    ("detect: calibrator channels", lambda f: ["detect", f["target_kp"], "--calibrator",
                                               f["twochan_kp"]], 2,
     "twochan_kp.fits has channels"),
    ("detect: 2-frame calibrator", lambda f: ["detect", f["target_kp"], "--calibrator",
                                              f["twoframes_kp"]], 2, "2 frames are too few"),
    ("detect: beyond the window", lambda f: ["detect", f["calibrated"], "--max-sep",
                                             "400mas"], 2, "beyond"),
    ("detect: unwritable plots folder", lambda f: ["detect", f["calibrated"], "--plots",
                                                   _in(f, "unwritable", "figs")], 2,
     "cannot write in"),
    ("detect: unwritable output", lambda f: ["detect", f["calibrated"], "-o",
                                             _in(f, "unwritable", "det.fits")], 2,
     "cannot write in"),
    # kernel-phase files of other tools
    ("detect: jwst-kpi file, CALFLAG 'False'", lambda f: ["detect", f["jwst_uncal"]], 2,
     "jwst_uncal.fits: not calibrated"),
    ("detect: TEL table of other length", lambda f: ["detect", f["pyk_tel"]], 2,
     "pyk_tel.fits: 3 detector position angles (TEL table) for 4 frames of KP-DATA"),
    ("info: TEL table of other length", lambda f: ["info", f["pyk_tel"]], 2,
     "pyk_tel.fits: 3 detector position angles (TEL table)"),
    ("detect: BLM-MAT columns", lambda f: ["detect", f["pyk_blm"]], 2,
     "pyk_blm.fits: BLM-MAT has"),
    ("detect: no UV-PLANE", lambda f: ["detect", f["pyk_nouv"]], 2,
     "pyk_nouv.fits: not a kernel model: no UV-PLANE extension"),
    ("info: no wavelength", lambda f: ["info", f["pyk_nowl"]], 2,
     "pyk_nowl.fits: no wavelength: neither a CWAVEL extension nor"),
    ("extract: --pa count", lambda f: ["extract", f["target"], "--pa", "1,2"], 2,
     "target.fits: --pa: 2 detector position angles for 4 frame(s)"),
    ("extract: --pa file missing", lambda f: ["extract", f["target"], "--pa",
                                              f["adir"].parent / "pa.txt"], 2,
     "pa.txt not found"),
    ("extract: --pa not an angle", lambda f: ["extract", f["target"], "--pa", "north"], 2,
     "cannot read --pa 'north'"),
    # info
    ("info: no wavelengths", lambda f: ["info", f["nowl_cube"]], 0,
     "incomplete: no wavelengths"),
    ("info: CHARIS header, no wavelengths", lambda f: ["info", f["charis_nowl"]], 0,
     "says CHARIS but has no wavelength solution"),
    ("info: pixel scale 0", lambda f: ["info", f["target"], "--pixscale", "0mas"], 2,
     "pixel scale must be > 0"),
    ("info: 1.52m for 1.52um", lambda f: ["info", f["target"], "--wavelengths",
                                          "1.52m,1.6um,1.68um"], 2, "outside 0.3-30 um"),
    ("info: corrupted KPFITS", lambda f: ["info", f["kp_corrupt"]], 2,
     "kp_corrupt.fits: checksum mismatch"),
    ("info: next command keeps the model", lambda f: ["info", f["target"], "--step", "0.8m",
                                                      "--binary", "--rotation", "1deg"], 0,
     "--step 0.8m --binary --rotation 1deg"),
    # the pupil-model check
    ("model-check: missing cube", lambda f: ["model-check", f["adir"].parent / "none.fits"], 2,
     "none.fits: file not found"),
    ("model-check: --rotations not numbers",
     lambda f: ["model-check", f["target"], "--rotations", "a,b"], 2,
     "--rotations must be a comma list of numbers"),
    ("model-check: unknown pupil", lambda f: ["model-check", f["target"], "--pupil", "hubble"],
     2, "unknown pupil 'hubble'"),
    # archives
    ("batch: missing manifest", lambda f: ["batch", f["adir"].parent / "none.csv"], 2,
     "none.csv: manifest not found"),
    ("batch: manifest column", lambda f: ["batch", f["nocol"]], 2, "lacks column"),
    ("batch: --draws 0", lambda f: ["batch", f["one"], "--draws", "0"], 2,
     "0 Monte-Carlo draws"),
    ("batch: glob matches nothing", lambda f: ["batch", "--glob", f["adir"] / "*.fits",
                                               "--calibrator", f["cal"]], 2,
     "no file matches"),
    ("batch: output is a file", lambda f: ["batch", f["one"], "-o", f["nocol"]], 2,
     "nocol.csv: exists and is not a directory"),
    ("batch: one bad calibrator", lambda f: ["batch", f["one"], "--step", "0.8m", "--draws",
                                             "1000", "--workers", "1"], 1,
     "truncated.fits: truncated FITS file"),
    # issue 25: nothing lost, nothing false
    ("inject: -o is the input", lambda f: ["inject", f["target"], "--position", "50,0mas",
                                           "--contrast", "0.01", "-o", f["target"],
                                           "--overwrite"], 2, "refusing to overwrite an input"),
    ("inject: -o is the input through a link",
     lambda f: ["inject", f["target_link"], "--position", "50,0mas", "--contrast", "0.01",
                "-o", f["target"], "--overwrite"], 2, "refusing to overwrite an input"),
    ("batch: name ../x", lambda f: ["batch", f["m_escape"]], 2,
     "m_escape.csv: entry name '../x' is not a plain folder name"),
    ("batch: absolute name", lambda f: ["batch", f["m_absolute"]], 2,
     "entry name '/tmp/abs' is not a plain folder name"),
    ("batch: name a/b", lambda f: ["batch", f["m_slash"]], 2, "entry name 'a/b'"),
    ("batch: name .", lambda f: ["batch", f["m_dot"]], 2, "entry name '.'"),
    ("detect: calibrated data given a calibrator",
     lambda f: ["detect", f["calibrated"], "--calibrator", f["cal_kp"]], 2,
     "calibrated.fits: already calibrated (CALFLAG true)"),
    ("detect: a calibrated file as the calibrator",
     lambda f: ["detect", f["target_kp"], "--calibrator", f["calibrated"]], 2,
     "calibrator " + "{calibrated}: already calibrated (CALFLAG true)"),
    ("extract: a KPFITS as the calibrator",
     lambda f: ["extract", f["target"], "--calibrator", f["calibrated"]], 2,
     "calibrated.fits: kernel-phase data (KPFITS"),
    ("extract: target file twice", lambda f: ["extract", f["target"], f["target"]], 2,
     "given twice as a target file"),
    ("extract: target file and a link to it", lambda f: ["extract", f["target"],
                                                         f["target_link"]], 2,
     "target_link.fits: given twice as a target file (the same file as"),
    ("extract: a star as its own calibrator",
     lambda f: ["extract", f["target"], "--calibrator", f["target_link"]], 2,
     "a star cannot be its own calibrator"),
    ("extract: one calibrator twice",
     lambda f: ["extract", f["target"], "--calibrator", f["cal"], "--calibrator", f["cal"]], 2,
     "given twice as a calibrator file"),
    ("detect: a star as its own calibrator",
     lambda f: ["detect", f["target_kp"], "--calibrator", f["target_kp"]], 2,
     "a star cannot be its own calibrator"),
    ("detect: identical kernel phases as calibrator",
     lambda f: ["detect", f["target_kp"], "--calibrator", f["tkp_copy"]], 2,
     "its kernel phases are the target"),
    ("batch: target twice (a link)",
     lambda f: ["batch", f["m_twice"], "--workers", "1", "--step", "0.8m"], 1,
     "given twice as a target file"),
    ("batch: a star as its own calibrator",
     lambda f: ["batch", f["m_selfcal"], "--workers", "1", "--step", "0.8m"], 1,
     "a star cannot be its own calibrator"),
    ("inject: position off the image", lambda f: ["inject", f["target"], "--position",
                                                  "5000,0mas", "--contrast", "0.01"], 2,
     "falls off the image: 100% of its flux would be lost"),
    ("inject: position near the edge", lambda f: ["inject", f["target"], "--position",
                                                  "180,0mas", "--contrast", "0.01"], 0,
     "of the flux of the companion at (180, 0) mas (detector) falls off the image"),
    ("inject: contrast 2", lambda f: ["inject", f["target"], "--position", "50,0mas",
                                      "--contrast", "2"], 2, "--contrast 2: contrasts are"),
    ("inject: contrast 0", lambda f: ["inject", f["target"], "--position", "50,0mas",
                                      "--contrast", "0"], 2, "each in (0, 1)"),
    ("inject: contrasts per channel", lambda f: ["inject", f["target"], "--position",
                                                 "50,0mas", "--contrast", "0.01,0.02"], 2,
     "--contrast 0.01,0.02: 2 contrasts for 3 channel(s)"),
    ("inject: --seed -1", lambda f: ["inject", f["target"], "--position", "50,0mas",
                                     "--contrast", "0.01", "--seed=-1"], 2,
     "--seed must be a whole number >= 0"),
    ("inject: no position", lambda f: ["inject", f["target"], "--contrast", "0.01"], 2,
     "give --position and --contrast"),
    ("inject --curve: nothing computable",
     lambda f: ["inject", f["target"], "--curve", "--calibrator", f["cal"], "--separations",
                "5000mas", "--step", "0.8m"], 2,
     "--separations: 5000 mas beyond the search's reach"),
    ("inject --curve: contrast ladder", lambda f: ["inject", f["target"], "--curve",
                                                   "--calibrator", f["cal"], "--contrasts",
                                                   "0,0.01"], 2, "--contrasts 0,0.01"),
    ("inject --curve: --draws 0", lambda f: ["inject", f["target"], "--curve", "--calibrator",
                                             f["cal"], "--draws", "0"], 2,
     "0 Monte-Carlo draws"),
    ("simulate: --seed -1", lambda f: ["simulate", "--seed=-1", "-o",
                                       f["adir"].parent / "sim_seed"], 2,
     "--seed must be a whole number >= 0"),
    ("inject --curve: --angles 0", lambda f: ["inject", f["target"], "--curve",
                                              "--calibrator", f["cal"], "--angles", "0"], 2,
     "--angles must be at least 1"),
    ("inject: -o names a folder", lambda f: ["inject", f["target"], "--position", "50,0mas",
                                             "--contrast", "0.01", "-o", _folder(f)], 2,
     "newdir/: ends with '/'"),
    ("extract: non-ASCII path", lambda f: ["extract", f["accent"], "--step", "0.8m"], 0,
     "kernel phases ->"),
    ("inject: non-ASCII path", lambda f: ["inject", f["accent"], "--position", "50,0mas",
                                          "--contrast", "0.01"], 0, "injected a companion"),
    ("detect: NaN in KP-COVROWS", lambda f: ["detect", f["nan_rows"]], 2,
     "nan_rows.fits: KP-COVROWS has 1 NaN or infinite value(s)"),
    ("detect: --grid-step too fine", lambda f: ["detect", f["calibrated"], "--grid-step",
                                                "0.001mas"], 2,
     "--grid-step 0.001 mas: a search grid of"),
    ("detect: --draws too many", lambda f: ["detect", f["calibrated"], "--draws",
                                            "1000000000000"], 2, "--draws 1e+12 needs about"),
    ("detect: --seed -1", lambda f: ["detect", f["calibrated"], "--seed=-1"], 2,
     "--seed must be a whole number >= 0"),
    ("detect: --grid-step 0", lambda f: ["detect", f["calibrated"], "--grid-step", "0mas"], 2,
     "--grid-step must be > 0"),
    ("extract: int16 cube with BSCALE", lambda f: ["extract", f["int16"], "--step", "0.8m"], 0,
     "kernel phases ->"),
    ("extract: uint16 cube with BZERO 32768", lambda f: ["extract", f["uint16"], "--step",
                                                         "0.8m"], 0, "kernel phases ->"),
    ("batch: manifest with a byte-order mark",
     lambda f: ["batch", f["m_bom"], "--workers", "1"], 1,
     "missing_t.fits: not found by worker"),
    ("batch: header-only manifest", lambda f: ["batch", f["m_header_only"]], 2,
     "m_header_only.csv: the manifest has no entries"),
    ("batch: folder locked by a running batch",
     lambda f: ["batch", f["m_bom"], "-o", f["locked"].parent], 2,
     "another kpifs batch writes in this folder (pid"),
    ("detect: --max-sep below --min-sep", lambda f: ["detect", f["calibrated"], "--max-sep",
                                                     "20mas", "--min-sep", "40mas"], 2,
     "--max-sep 20.0 mas must be larger than --min-sep 40.0 mas"),
    ("detect: KP-COV not a covariance", lambda f: ["detect", f["bad_cov"]], 2,
     "bad_cov.fits: KP-COV is not a covariance at channel 1"),
    ("model-check: too few frames", lambda f: ["model-check", f["two_frames"]], 2,
     "two_frames.fits: 2 frame(s): kpifs model-check needs at least 4 frames"),
    ("model-check: a star against itself",
     lambda f: ["model-check", f["target"], "--calibrator", f["target_link"]], 2,
     "a star cannot be its own calibrator"),
    ("extract: a KPFITS given as a cube", lambda f: ["extract", f["target_kp"]], 2,
     "target_kp.fits: kernel-phase data (KPFITS, a KP-DATA extension), not an image cube"),
    ("extract: a kernel model given as a cube", lambda f: ["extract", f["model"]], 2,
     "model.fits: a kernel model, not an image cube"),
    ("extract: -o names a folder", lambda f: ["extract", f["target"], "-o", _folder(f)], 2,
     "newdir/: ends with '/', a folder name"),
    ("detect: -o names a folder", lambda f: ["detect", f["calibrated"], "-o", _folder(f)], 2,
     "newdir/: ends with '/'"),
    ("info: injection curve", lambda f: ["info", f["curve"]], 0,
     "200 mas: injections 1.00e-03, analytic 9.00e-04"),
    ("info: KPFITS from its headers", lambda f: ["info", f["calibrated"]], 0,
     "1 frame(s) x 3 channel(s) x 65 kernel phases; 1.5200-1.6800 um; 10.42 mas"),
    ("detect: output is the input", lambda f: ["detect", f["calibrated"], "-o", f["calibrated"],
                                               "--overwrite"], 2,
     "refusing to overwrite an input"),
    ("simulate: earlier simulation", lambda f: ["simulate", "--frames", "2", "-o",
                                                f["earlier_sim"].parent], 2,
     "an earlier simulation exists there (target.fits); pass --overwrite"),
    ("detect: --frame sky without angles", lambda f: ["detect", f["no_pa"], "--frame", "sky"],
     2, "no_pa.fits: --frame sky needs the detector position angle"),
    ("extract: a dead channel dropped", lambda f: ["extract", f["dead"], "--step", "0.8m"], 0,
     "deadchannel.fits: 1 dead channel(s) of 3 dropped (unusable in every frame): channel(s) 1 "
     "(1.600 um"),
    ("extract: a dead channel, calibrator matched",
     lambda f: ["extract", f["dead"], "--calibrator", f["cal"], "--step", "0.8m"], 0,
     "channel(s) 1.600 um left out: dead in another star"),
    ("extract: CHARIS NLAM contradicted by the cube",
     lambda f: ["extract", f["nlam"], "--wavelengths", f["charis_wl"], "--step", "0.8m"], 0,
     "NLAM = 20 in the header but the cube has 22 channels"),
    # warnings: the job runs, the message says what happened
    ("star at the edge", lambda f: ["extract", f["edge"]], 0, "closer to the image edge"),
    ("fewer frames than kernels", lambda f: ["extract", f["target"], "--calibrator",
                                             f["cal"]], 0,
     "too few frames ([4, 4], 6 degrees of freedom) for the covariance"),
    ("Nyquist-limited channel", lambda f: ["extract", *f["charis_tgt"], "--calibrator",
                                           *f["charis_cal"]], 0, "beyond the Nyquist limit"),
]


def _folder(files):
    """An output named as a folder that does not exist (``-o newdir/``)."""
    return str(files["adir"].parent / "newdir") + "/"


def _in(files, key, name):
    if files[key] is None:
        pytest.skip("no unwritable folder on this machine")
    return files[key] / name


@pytest.mark.parametrize("name, argv, code, text", CASES, ids=[c[0] for c in CASES])
@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::ResourceWarning",
                            "ignore::pytest.PytestUnraisableExceptionWarning")
def test_bad_input(corpus, tmp_path, capsys, name, argv, code, text):
    out = tmp_path / ("out" if name.startswith("batch") else "out.fits")
    inputs = [p for v in corpus.values() if v is not None
              for p in (v if isinstance(v, list) else [v])]
    before = _hashes(inputs)
    args = [str(a) for a in argv(corpus)]
    text = text.format(**{k: v for k, v in corpus.items() if v is not None})
    if args[0] in ("extract", "detect", "batch", "inject") and "-o" not in args:
        args += ["-o", str(out)]
    assert main(args) == code
    captured = capsys.readouterr()
    err = captured.err + (captured.out if code == 0 else "")
    assert "Traceback" not in err
    assert text in err, err
    if code == 2:
        lines = [ln for ln in captured.err.splitlines() if ": error: " in ln]
        assert len(lines) == 1, captured.err
        assert not out.exists()                           # refused before any work
    assert not list(tmp_path.glob(".out*"))               # no temporary left behind
    assert _hashes(before) == before                      # inputs untouched


def test_existing_output_and_directory_output(corpus, tmp_path, capsys):
    out = tmp_path / "kp.fits"
    out.write_bytes(b"keep me")
    assert main(["extract", str(corpus["target"]), "-o", str(out)]) == 2
    assert "exists; pass --overwrite to replace it" in capsys.readouterr().err
    assert out.read_bytes() == b"keep me"
    assert main(["extract", str(corpus["target"]), "-o", str(tmp_path)]) == 2
    assert "is a directory" in capsys.readouterr().err
    assert main(["extract", str(corpus["target"]), "-o", str(tmp_path / "no" / "x.fits")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_never_overwrite_an_input(corpus, tmp_path, capsys):
    src = tmp_path / "cube.fits"
    src.write_bytes(corpus["target"].read_bytes())
    before = src.read_bytes()
    assert main(["extract", str(src), "-o", str(src), "--overwrite"]) == 2
    assert "refusing to overwrite an input" in capsys.readouterr().err
    assert src.read_bytes() == before


def test_disk_full_names_the_output(corpus, tmp_path, capsys, monkeypatch):
    """A write that fails (disk full) names the output, and leaves no temporary behind."""
    import errno

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(fits.HDUList, "writeto", full)
    out = tmp_path / "kp.fits"
    assert main(["extract", str(corpus["target"]), "--step", "0.8m", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{out}: cannot write it (No space left on device)" in err
    assert list(tmp_path.iterdir()) == []


def test_non_ascii_paths_are_escaped_in_headers(corpus, tmp_path, capsys):
    """A path with accents is written into the header cards escaped, and read back."""
    out = tmp_path / "kp.fits"
    assert main(["extract", str(corpus["accent"]), "--step", "0.8m", "-o", str(out)]) == 0
    with fits.open(out) as h:
        card = h[0].header["KPIN1"]
        assert card.endswith("donn\\xe9es/cible.fits") and card.isascii()
        assert any("donn\\xe9es" in str(line) for line in h[0].header["HISTORY"])
