"""OIFITS: closure phases in (v1, v2, OI_CORR, CPCOV, deviations), OIFITS2 out, masks."""
import itertools
import warnings

import numpy as np
import pytest
from astropy import units as u
from astropy.io import fits

from kpifs import KernelModel, KernelPhaseData, KpifsError, KpifsWarning, make_pupil
from kpifs.cli import main
from kpifs.data import DetectionResult
from kpifs.detect import detect

MAS = np.pi / 180 / 3600 / 1000
NIRISS = [(0.0, -2.64), (-2.28631, 0.0), (2.28631, -1.32), (-2.28631, 1.32),
          (-1.14315, 1.98), (2.28631, 1.32), (1.14315, 1.98)]


# --- an independent minimal OIFITS writer (not kpifs's): the way other tools write -----
def binary_cp(u1, v1, u2, v2, wl, dra, ddec, f):
    """Closure phases (rad) of a binary in the OIFITS convention (FORMATS.md):
    V = (1 + f exp(-2 pi i (u dRA + v dDec) / lam)) / (1 + f)."""
    def vis(uu, vv):
        return 1 + f * np.exp(-2j * np.pi * (uu[:, None] * dra + vv[:, None] * ddec) * MAS
                              / wl[None, :])
    return np.angle(vis(u1, v1) * vis(u2, v2) * np.conj(vis(u1 + u2, v2 + v1)))


def standin(path, *, stations=NIRISS, wl=(4.8e-6,), sep=150.0, pa=60.0, f=0.05,
            sigma_deg=0.3, seed=0, n_epochs=1, rotate=0.0, unit="DEGREES", version=2,
            diameter=0.0, cpcov=False, corr=False, flag=None, nan=False, tables=1,
            wavelength=True, nwave_t3=None, primary=False, baseline_noise=False):
    """Write an OIFITS file of a binary (AMICAL/fouriever style when asked) and return
    the truth. Epochs turn the array by *rotate* degrees each (Earth rotation)."""
    rng = np.random.default_rng(seed)
    wl = np.asarray(wl, float)
    nw = len(wl)
    dra, ddec = sep * np.sin(np.deg2rad(pa)), sep * np.cos(np.deg2rad(pa))
    xy = np.asarray(stations, float)
    tri = list(itertools.combinations(range(len(xy)), 3))
    rows = {k: [] for k in ("u1", "v1", "u2", "v2", "sta", "phi", "err", "mjd")}
    for e in range(n_epochs):
        t = np.deg2rad(rotate * e)
        rot = xy @ np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]).T
        for a, b, c in tri:
            (u1, v1), (u2, v2) = rot[b] - rot[a], rot[c] - rot[b]
            rows["u1"].append(u1)
            rows["v1"].append(v1)
            rows["u2"].append(u2)
            rows["v2"].append(v2)
            rows["sta"].append((a + 1, b + 1, c + 1))
            rows["mjd"].append(60000.0 + e / 24)
    arr = {k: np.array(v) for k, v in rows.items()}
    truth = binary_cp(arr["u1"], arr["v1"], arr["u2"], arr["v2"], wl, dra, ddec, f)
    ntri = len(tri)
    sig = np.deg2rad(sigma_deg)
    nbl = len(xy) * (len(xy) - 1) // 2
    pairs = {p: i for i, p in enumerate(itertools.combinations(range(len(xy)), 2))}
    cm = np.zeros((ntri, nbl))
    for i, (a, b, c) in enumerate(tri):
        cm[i, pairs[(a, b)]] += 1
        cm[i, pairs[(b, c)]] += 1
        cm[i, pairs[(a, c)]] -= 1
    cor = cm @ cm.T / 3          # closure phases of independent baseline noise
    if baseline_noise:   # noise on the baselines: correlated closure phases (as on sky)
        noise = np.concatenate([cm @ rng.normal(0, sig / np.sqrt(3), (nbl, nw))
                                for _ in range(n_epochs)])
    else:
        noise = rng.normal(0, sig, truth.shape)
    phi = np.rad2deg(truth + noise)
    err = np.full(phi.shape, sigma_deg)
    flags = np.zeros(phi.shape, bool) if flag is None else flag
    if nan:
        phi[0, 0] = np.nan
    hdus = [fits.PrimaryHDU()]
    if primary:
        for k, v in (("ORIGIN", "test"), ("DATE", "2024-01-01"), ("DATE-OBS", "2024-01-01"),
                     ("CONTENT", "OIFITS2"), ("TELESCOP", "JWST"), ("INSTRUME", "NIRISS"),
                     ("OBSERVER", "me"), ("OBJECT", "HD 1"), ("INSMODE", "NRM")):
            hdus[0].header[k] = v
    rev = 2 if version == 2 else 1
    hdus.append(fits.BinTableHDU.from_columns([
        fits.Column("TEL_NAME", "8A", array=[f"A{i}" for i in range(len(xy))]),
        fits.Column("STA_NAME", "8A", array=[f"A{i}" for i in range(len(xy))]),
        fits.Column("STA_INDEX", "I", array=np.arange(1, len(xy) + 1)),
        fits.Column("DIAMETER", "E", unit="m", array=np.full(len(xy), diameter)),
        fits.Column("STAXYZ", "3D", unit="m", array=np.column_stack([xy, 0 * xy[:, 0]]))],
        name="OI_ARRAY"))
    hdus[-1].header.update({"OI_REVN": rev, "ARRNAME": "MASK", "FRAME": "SKY"})
    if wavelength:
        hdus.append(fits.BinTableHDU.from_columns([
            fits.Column("EFF_WAVE", "E", unit="m", array=wl),
            fits.Column("EFF_BAND", "E", unit="m", array=0.05 * wl)], name="OI_WAVELENGTH"))
        hdus[-1].header.update({"OI_REVN": rev, "INSNAME": "INS"})
    ntot = len(phi)
    chunks = np.array_split(np.arange(ntot), tables)
    nwt = nw if nwave_t3 is None else nwave_t3
    for k, idx in enumerate(chunks):
        cols = [fits.Column("TARGET_ID", "I", array=np.ones(len(idx), int)),
                fits.Column("TIME", "D", unit="s", array=np.zeros(len(idx))),
                fits.Column("MJD", "D", unit="day", array=arr["mjd"][idx]),
                fits.Column("INT_TIME", "D", unit="s", array=np.ones(len(idx))),
                fits.Column("T3AMP", f"{nw}D", array=np.ones((len(idx), nw))),
                fits.Column("T3AMPERR", f"{nw}D", array=np.full((len(idx), nw), 1e3)),
                fits.Column("T3PHI", f"{nwt}D", unit=unit,
                            array=np.resize(phi[idx], (len(idx), nwt))),
                fits.Column("T3PHIERR", f"{nw}D", unit=unit, array=err[idx]),
                fits.Column("U1COORD", "D", unit="m", array=arr["u1"][idx]),
                fits.Column("V1COORD", "D", unit="m", array=arr["v1"][idx]),
                fits.Column("U2COORD", "D", unit="m", array=arr["u2"][idx]),
                fits.Column("V2COORD", "D", unit="m", array=arr["v2"][idx]),
                fits.Column("STA_INDEX", "3I", array=arr["sta"][idx]),
                fits.Column("FLAG", f"{nw}L", array=flags[idx])]
        if corr and k == 0:
            cols.append(fits.Column("CORRINDX_T3PHI", "J", array=np.arange(len(idx)) * nw + 1))
        h = fits.BinTableHDU.from_columns(cols, name="OI_T3")
        h.header.update({"OI_REVN": rev, "INSNAME": "INS", "ARRNAME": "MASK",
                         "DATE-OBS": "2024-01-01"})
        if corr and k == 0:
            h.header["CORRNAME"] = "C"
        hdus.append(h)
    if corr:   # +-1/3 between the first epoch's triangles sharing a baseline, channel 1
        ii, jj, cc = [], [], []
        for i, j in itertools.combinations(range(min(len(chunks[0]), ntri)), 2):
            if cor[i, j]:
                ii.append(i * nw + 1)
                jj.append(j * nw + 1)
                cc.append(cor[i, j])
        h = fits.BinTableHDU.from_columns([fits.Column("IINDX", "J", array=ii),
                                           fits.Column("JINDX", "J", array=jj),
                                           fits.Column("CORR", "D", array=cc)], name="OI_CORR")
        h.header.update({"OI_REVN": 1, "CORRNAME": "C", "NDATA": len(chunks[0]) * nw})
        hdus.append(h)
    if cpcov:   # fouriever: per observation, triangle-major, rad^2, correlations +-1/3
        big = np.kron(cor, np.eye(nw)) * sig ** 2
        h = fits.ImageHDU(np.stack([big] * n_epochs), name="CPCOV")
        h.header["INSNAME"] = "INS"
        hdus.append(h)
    fits.HDUList(hdus).writeto(path, overwrite=True)
    return {"dra": dra, "ddec": ddec, "sep": sep, "pa": pa, "f": f, "truth": truth}


# --- reading ------------------------------------------------------------------------
def test_read_amical_style_convention_and_projection(tmp_path):
    """DEGREES units, DIAMETER 0, no primary keywords: 35 triangles -> 15 independent
    closure phases whose model, evaluated on the sky, is the OIFITS binary exactly."""
    p = tmp_path / "ami.oifits"
    t = standin(p, wl=(3.8e-6, 4.8e-6), sigma_deg=1e-9)
    kpd = KernelPhaseData.read(p)
    assert kpd.shape == (1, 2, 15) and kpd.meta["calibrated"]
    km = kpd.kernel_model
    assert km.n_uv == 21 and km.kernel_residual() < 1e-12
    # the sky frame: detector angle 0, model at (x, y) = (-dRA, dDec)
    model = km.binary_kernel_phases([-t["dra"], t["ddec"]] * u.mas, t["f"], kpd.wavelengths)
    assert np.abs(model - kpd.kp[0]).max() < 1e-8
    assert np.abs(kpd.kp).max() > 0.02        # a real signal, not zeros
    # the independent closure phases carry all 35: whitened energies agree when the 35
    # are taken as independent (P = projection) ...
    sig = np.deg2rad(1e-9)
    e_t3 = np.sum(t["truth"][:, 0] ** 2) / sig ** 2
    ind = KernelPhaseData.read(p, correlations="independent")
    e_ind = ind.kp[0, 0] @ np.linalg.solve(ind.covariance[0], ind.kp[0, 0])
    assert e_ind == pytest.approx(e_t3, rel=1e-6)
    # ... and by default they share their baselines' noise (C C^T / 3): with 7 stations
    # the 15 independent ones then carry 3/7 of that energy
    e_kp = kpd.kp[0, 0] @ np.linalg.solve(kpd.covariance[0], kpd.kp[0, 0])
    assert e_kp == pytest.approx(3 / 7 * e_t3, rel=1e-6)


def test_sign_convention_against_analytic_cp(tmp_path):
    """A companion East (dRA > 0) moves the closure phases as the OIFITS formula says;
    its mirror image (West) gives the opposite closure phases."""
    p = tmp_path / "east.oifits"
    standin(p, sep=120.0, pa=90.0, sigma_deg=1e-9)
    kpd = KernelPhaseData.read(p)
    km = kpd.kernel_model
    east = km.binary_kernel_phases([-120.0, 0.0] * u.mas, 0.05, kpd.wavelengths)[0]
    west = km.binary_kernel_phases([120.0, 0.0] * u.mas, 0.05, kpd.wavelengths)[0]
    assert np.abs(kpd.kp[0, 0] - east).max() < 1e-8
    assert np.abs(kpd.kp[0, 0] - west).max() > 0.05


def test_v1_several_tables_epochs_corr_and_flags(tmp_path):
    p = tmp_path / "v1.fits"
    flag = np.zeros((70, 3), bool)
    flag[3, 1] = True               # one point: its triangle leaves every channel
    flag[:, 2] = True               # a channel flagged everywhere: dropped
    standin(p, version=1, n_epochs=2, rotate=20.0, tables=2, wl=(1.6e-6, 1.7e-6, 1.8e-6),
            flag=flag, corr=True, unit="deg", diameter=1.8)
    with pytest.warns(KpifsWarning, match="71 flagged closure phase"):
        kpd = KernelPhaseData.read(p)
    assert kpd.n_wave == 2 and kpd.meta["closure_phases"]["n_epochs"] == 2
    assert kpd.meta["closure_phases"]["n_triangles"] == 69
    assert kpd.n_kp == 30                             # 15 per epoch: one triangle less
    assert "OI_CORR" in kpd.meta["covariance_source"]
    assert kpd.kernel_model.pupil.step.to_value(u.m) == pytest.approx(0.9)   # D / 2


@pytest.mark.slow
def test_cpcov_file_extract_refuses_detect_reads(tmp_path, capsys):
    p = tmp_path / "pionier_like.fits"
    xy = [(0.0, 0.0), (40.0, 10.0), (15.0, 60.0), (-30.0, 45.0)]
    standin(p, stations=xy, wl=(1.55e-6, 1.65e-6, 1.75e-6), n_epochs=50, rotate=2.0,
            sep=8.0, pa=200.0, f=0.02, sigma_deg=0.5, cpcov=True, diameter=1.8)
    with fits.open(p) as h:
        assert h["CPCOV"].data.shape == (50, 12, 12)
    rc = main(["extract", str(p), "--instrument", "generic", "--wavelengths", "1.6um",
               "--pixscale", "10mas", "-o", str(tmp_path / "kp.fits")])
    err = capsys.readouterr().err
    assert rc == 2 and "OIFITS" in err and "kpifs detect" in err
    kpd = KernelPhaseData.read(p)
    assert kpd.shape == (1, 3, 150) and "CPCOV" in kpd.meta["covariance_source"]
    out = tmp_path / "det.fits"
    rc = main(["detect", str(p), "-o", str(out), "--max-sep", "30mas", "--draws", "1000",
               "--quiet"])
    assert rc == 0
    res = DetectionResult.read(out)
    assert res.grid.frame == "sky" and len(res.candidates) >= 1
    c = res.candidates[0]
    assert np.hypot(c["fit_dra"].to_value(u.mas) - 8 * np.sin(np.deg2rad(200)),
                    c["fit_ddec"].to_value(u.mas) - 8 * np.cos(np.deg2rad(200))) < 1.0


@pytest.mark.parametrize("case, match", [
    ("nan", "NaN but not flagged"), ("nowave", "no OI_WAVELENGTH"),
    ("nwave", "mismatched NWAVE"), ("truncated", "truncated")])
def test_bad_oifits(tmp_path, capsys, case, match):
    p = tmp_path / "bad.oifits"
    standin(p, wl=(1.6e-6, 1.7e-6), nan=case == "nan", wavelength=case != "nowave",
            nwave_t3=3 if case == "nwave" else None)
    if case == "truncated":
        data = p.read_bytes()
        p.write_bytes(data[:len(data) - 4000])
    with pytest.raises(KpifsError, match=match) as exc:
        KernelPhaseData.read(p)
    assert str(p) in str(exc.value)
    if case in ("nan", "nwave"):
        assert "OI_T3 #1" in str(exc.value)
    rc = main(["detect", str(p), "-o", str(tmp_path / "d.fits"), "--quiet"])
    assert rc == 2 and str(p) in capsys.readouterr().err


def test_info_describes_oifits(tmp_path, capsys):
    p = tmp_path / "x.oifits"
    standin(p)
    assert main(["info", str(p)]) == 0
    out = capsys.readouterr().out
    assert "35 triangles" in out and "15 independent closure phases" in out


# --- detection ----------------------------------------------------------------------
def test_ami_standin_companion_found(tmp_path, capsys):
    """An AMI-like file written by another writer: `kpifs detect` finds the companion
    within 3 mas, 1 deg and 10 % in contrast."""
    p = tmp_path / "ami.oifits"
    t = standin(p, sep=150.0, pa=60.0, f=0.05, sigma_deg=0.15, seed=1)
    out = tmp_path / "det.fits"
    assert main(["detect", str(p), "-o", str(out), "--draws", "1000", "--quiet"]) == 0
    assert "per dof" in capsys.readouterr().out
    c = DetectionResult.read(out).candidates
    assert len(c) == 1
    c = c[0]
    assert abs(c["fit_separation"].to_value(u.mas) - t["sep"]) < 3
    assert abs(c["fit_pa_sky"].to_value(u.deg) - t["pa"]) < 1
    assert abs(float(np.ravel(c["fit_contrast"])[0]) / t["f"] - 1) < 0.1


def test_companion_free_honest(tmp_path):
    """Ten companion-free files: at most one candidate at global P_FA 1e-3."""
    n = 0
    for seed in range(10):
        p = tmp_path / f"null{seed}.oifits"
        standin(p, f=0.0, seed=100 + seed, wl=(3.8e-6, 4.3e-6), baseline_noise=True,
                corr=False, cpcov=True)
        kpd = KernelPhaseData.read(p)
        n += len(detect(kpd, pfa=1e-3, n_draws=1000, seed=seed, limits=False).candidates)
    assert n <= 1


# --- writing ------------------------------------------------------------------------
def _mask_kpd(mask="niriss_nrm", wl=(3.8, 4.3, 4.8), detpa=25.0, corr=True):
    km = KernelModel.from_pupil(make_pupil(mask))
    wl = np.asarray(wl) * u.um
    rng = np.random.default_rng(3)
    kp = km.binary_kernel_phases([90, -60] * u.mas, 0.03, wl)[None]
    a = rng.normal(size=(len(wl) * km.n_kp, len(wl) * km.n_kp)) * 1e-3
    joint = a @ a.T + np.eye(len(a)) * 1e-5
    if not corr:
        joint = np.diag(np.diag(joint))
    nk = km.n_kp
    per = np.stack([joint[w * nk:(w + 1) * nk, w * nk:(w + 1) * nk] for w in range(len(wl))])
    return KernelPhaseData(kp, wl, 65.6 * u.mas, km, covariance=per, joint_covariance=joint,
                           detpa=[detpa], meta={"calibrated": True, "detpa_source": "given"},
                           header=fits.Header({"OBJECT": "HD 1", "DATE-OBS": "2024-05-06"}))


def test_write_strict_oifits2_rules(tmp_path):
    """Mandatory keywords, tables, columns and units (oifitslib's oifits-check rules)."""
    p = _mask_kpd().write(tmp_path / "x.oifits")
    with fits.open(p) as h:
        hdr = h[0].header
        for k in ("ORIGIN", "DATE", "DATE-OBS", "CONTENT", "TELESCOP", "INSTRUME",
                  "OBSERVER", "OBJECT", "INSMODE"):
            assert str(hdr[k]).strip(), k
        assert hdr["CONTENT"] == "OIFITS2"
        names = [x.name for x in h]
        for t in ("OI_TARGET", "OI_ARRAY", "OI_WAVELENGTH", "OI_T3", "OI_CORR"):
            assert t in names
        need = {"OI_TARGET": {"TARGET_ID": "", "TARGET": "", "RAEP0": "deg", "DECEP0": "deg",
                              "EQUINOX": "yr", "PARALLAX": "deg", "SPECTYP": ""},
                "OI_ARRAY": {"TEL_NAME": "", "STA_NAME": "", "STA_INDEX": "",
                             "DIAMETER": "m", "STAXYZ": "m", "FOV": "arcsec", "FOVTYPE": ""},
                "OI_WAVELENGTH": {"EFF_WAVE": "m", "EFF_BAND": "m"},
                "OI_T3": {"TARGET_ID": "", "TIME": "s", "MJD": "day", "INT_TIME": "s",
                          "T3AMP": "", "T3AMPERR": "", "T3PHI": "deg", "T3PHIERR": "deg",
                          "U1COORD": "m", "V1COORD": "m", "U2COORD": "m", "V2COORD": "m",
                          "STA_INDEX": "", "FLAG": "", "CORRINDX_T3PHI": ""},
                "OI_CORR": {"IINDX": "", "JINDX": "", "CORR": ""}}
        for t, cols in need.items():
            hdu = h[t]
            for c, unit in cols.items():
                assert c in hdu.columns.names, (t, c)
                assert (hdu.columns[c].unit or "") == unit, (t, c)
        assert h["OI_T3"].header["OI_REVN"] == 2 and h["OI_CORR"].header["OI_REVN"] == 1
        for t in ("OI_T3",):
            for k in ("DATE-OBS", "ARRNAME", "INSNAME", "CORRNAME"):
                assert str(h[t].header[k]).strip()
        assert h["OI_ARRAY"].header["FRAME"] in ("GEOCENTRIC", "SKY")
        assert set(h["OI_ARRAY"].data["FOVTYPE"]) <= {"FWHM", "RADIUS"}
        assert np.all(h["OI_ARRAY"].data["DIAMETER"] == pytest.approx(0.82))
        assert np.all(h["OI_T3"].data["TIME"] == 0)
        assert np.all(np.diff(h["OI_WAVELENGTH"].data["EFF_WAVE"]) > 0)
        assert np.all(h["OI_T3"].data["T3PHIERR"] > 0)
        arr = h["OI_ARRAY"].header["ARRNAME"]
        assert set(np.ravel(h["OI_T3"].data["STA_INDEX"])) <= set(h["OI_ARRAY"].data["STA_INDEX"])
        assert h["OI_T3"].header["ARRNAME"] == arr
        assert h["OI_CORR"].header["NDATA"] == 35 * 3
        c = h["OI_CORR"].data
        assert np.all(c["IINDX"] < c["JINDX"]) and np.all(np.abs(c["CORR"]) <= 1 + 1e-9)


def test_write_read_round_trip(tmp_path):
    """kpifs -> OIFITS2 -> kpifs: the same closure phases, covariance and model (1e-6)."""
    kpd = _mask_kpd()
    p = kpd.write(tmp_path / "x.oifits")
    back = KernelPhaseData.read(p)
    # the same binary on the sky predicts what was read
    from kpifs.detect.sky import detector_to_sky
    dra, ddec = detector_to_sky(90.0, -60.0, 25.0)
    model = back.kernel_model.binary_kernel_phases([-dra, ddec] * u.mas, 0.03, back.wavelengths)
    assert np.abs(model - back.kp[0]).max() < 1e-6
    # whitened quantities are basis-free: the joint chi-square agrees
    y0 = kpd.kp[0].ravel()
    y1 = back.kp[0].ravel()
    chi0 = y0 @ np.linalg.solve(kpd.joint_covariance, y0)
    chi1 = y1 @ np.linalg.solve(back.joint_covariance, y1)
    assert chi1 == pytest.approx(chi0, rel=1e-6)
    # a second round trip is exact in the read basis
    p2 = back.write(tmp_path / "y.oifits")
    again = KernelPhaseData.read(p2)
    assert np.abs(again.kp - back.kp).max() < 1e-6 * np.abs(back.kp).max()
    assert np.abs(again.joint_covariance - back.joint_covariance).max() < \
        1e-6 * np.abs(back.joint_covariance).max()


def test_write_refuses_full_pupil(tmp_path):
    km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    kpd = KernelPhaseData(np.zeros((1, 1, km.n_kp)), [1.6] * u.um, 10 * u.mas, km,
                          covariance=np.eye(km.n_kp)[None])
    with pytest.raises(KpifsError, match="KPFITS"):
        kpd.write(tmp_path / "x.oifits", format="oifits")
    assert not (tmp_path / "x.oifits").exists()


def test_oifits_package_reads_corr(tmp_path):
    oifits = pytest.importorskip("oifits")
    p = _mask_kpd().write(tmp_path / "x.oifits")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = oifits.open(str(p))
    assert len(data.t3) == 35
    c = data.corr["KPIFS"]
    with fits.open(p) as h:
        ref = h["OI_CORR"].data
        assert len(ref) == 5460 and np.array_equal(np.asarray(c.iindx), ref["IINDX"])
        assert np.array_equal(np.asarray(c.jindx), ref["JINDX"])
        assert np.allclose(np.asarray(c.corr), ref["CORR"], rtol=0, atol=1e-15)
    assert data.t3[0].corrindx_t3phi == 1 and data.t3[1].corrindx_t3phi == 4


# --- SPHERE SAM behind the IFS: simulator -> extract -> OIFITS2 -> detect -------------
@pytest.mark.slow
def test_sphere_sam_ifs_sequence(tmp_path, capsys):
    """A simulated 39-channel SAM sequence with a companion goes through `kpifs extract`
    to closure phases and OIFITS2; `kpifs detect` finds the companion and its spectrum,
    and the 39-channel search goes deeper than the best single channels."""
    from kpifs.data import DetectionGrid
    from kpifs.io import write_observation
    from kpifs.simulation.simulate import simulate_scene
    obs = simulate_scene("sphere-sam", n_frames=12, npup=48, seed=1)
    files = write_observation(obs, tmp_path / "sim")
    out = tmp_path / "cal.oifits"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KpifsWarning)     # detector angle unknown: 0
        rc = main(["extract", str(files["target"][0]), "--pupil", "sphere_sam7",
                   "--calibrator", str(files["calibrator"][0]), "-o", str(out), "--quiet"])
    assert rc == 0
    kpd = KernelPhaseData.read(out)
    assert kpd.shape == (1, 39, 15)
    grid = DetectionGrid.from_separation(100 * u.mas, 6 * u.mas, min_sep=20 * u.mas,
                                         frame="sky")
    res = detect(kpd, grid=grid, n_draws=1000, seed=0)
    assert len(res.candidates) == 1
    c = res.candidates[0]
    truth = (-60.0, -40.0)          # detector (60, -40) at angle 0: dRA = -x
    assert np.hypot(c["fit_dra"].to_value(u.mas) - truth[0],
                    c["fit_ddec"].to_value(u.mas) - truth[1]) < 3
    spec = np.ravel(c["fit_contrast"])
    true = obs.params.contrasts
    assert abs(spec.mean() / true.mean() - 1) < 0.2
    slope = np.polyfit(obs.params.wavelengths.value, spec, 1)[0]
    true_slope = np.polyfit(obs.params.wavelengths.value, true, 1)[0]
    assert slope < 0 and abs(slope / true_slope - 1) < 0.6
    # deeper: the B limit of all channels against the best single channels', at the truth
    iy, ix = np.unravel_index(np.argmin((grid.X - truth[0]) ** 2 + (grid.Y - truth[1]) ** 2),
                              grid.shape)
    multi = res.limits["B"][iy, ix]
    kp, cov = kpd.kp, kpd.covariance
    single = []
    for i in np.argsort(np.diagonal(cov, axis1=1, axis2=2).mean(axis=1))[:3]:
        one = KernelPhaseData(kp[:, [i]], kpd.wavelengths[[i]], kpd.pixscale, kpd.kernel_model,
                              covariance=cov[[i]], detpa=[0.0],
                              meta={"calibrated": True, "detpa_source": "given"})
        single.append(detect(one, grid=grid, n_draws=1000, seed=0).limits["B"][iy, ix])
    assert multi < 0.7 * min(single)


# --- several files, several grids (issue 28's "several files of one target combine") ----
def _two_grids(path, a, b):
    """One file holding *a*'s and *b*'s tables under INSNAMEs 'A' and 'B' (two grids)."""
    with fits.open(a) as ha, fits.open(b) as hb:
        hdus = [fits.PrimaryHDU(header=ha[0].header)]
        for h, ins in ((ha, "A"), (hb, "B")):
            for x in h[1:]:
                if x.name == "OI_ARRAY" and ins == "B":
                    continue
                x = x.copy()
                if x.name in ("OI_WAVELENGTH", "OI_T3"):
                    x.header["INSNAME"] = ins
                hdus.append(x)
        fits.HDUList(hdus).writeto(path)
    return path


def _turned(deg):
    t = np.deg2rad(deg)
    return np.asarray(NIRISS) @ np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]).T


def _epoch_files(tmp_path, f, seed):
    """Two files of one target, the second with the mask turned by 30 deg (a roll)."""
    files = [tmp_path / f"e{e}_{seed}.oifits" for e in range(2)]
    for e, p in enumerate(files):
        # noise on the baselines (as on the sky), 0.15 deg x sqrt(3 / 7) per closure phase:
        # the information of 0.15 deg independent closure phases
        t = standin(p, stations=_turned(30.0 * e), sep=150.0, pa=60.0, f=f, sigma_deg=0.098,
                    seed=seed + 7 * e, primary=True, baseline_noise=True)
    return files, t


def test_several_files_combine(tmp_path, capsys):
    """Two epochs of one target in two files: 30 closure phases, energies adding up; one
    epoch's hexagonal uv lattice leaves an alias at 879 mas (the second file alone picks
    it), the two together find the companion within 3 mas, 1 deg and 10 %."""
    files, t = _epoch_files(tmp_path, 0.01, 4)
    both = KernelPhaseData.read(files)
    one = [KernelPhaseData.read(f) for f in files]
    assert both.n_kp == 30 and both.meta["n_reads"] == 2 and not both.meta["achromatic"]
    assert both.kernel_model.n_uv == 42 and both.kp[0, 0] == pytest.approx(
        np.concatenate([k.kp[0, 0] for k in one]))
    energy = [float(k.kp[0, 0] @ np.linalg.solve(k.covariance[0], k.kp[0, 0])) for k in one]
    assert float(both.kp[0, 0] @ np.linalg.solve(both.covariance[0], both.kp[0, 0])) \
        == pytest.approx(sum(energy), rel=1e-9)
    alone = detect(one[1], pfa=1e-3, n_draws=1000, seed=0, limits=False).candidates
    assert abs(alone[0]["fit_separation"].to_value(u.mas) - t["sep"]) > 100      # the alias
    out = tmp_path / "det.fits"
    assert main(["detect", str(files[0]), str(files[1]), "-o", str(out), "--draws", "1000",
                 "--quiet"]) == 0
    c = DetectionResult.read(out).candidates
    assert len(c) == 1
    assert abs(c[0]["fit_separation"].to_value(u.mas) - t["sep"]) < 3
    assert abs(c[0]["fit_pa_sky"].to_value(u.deg) - t["pa"]) < 1
    assert abs(float(np.ravel(c[0]["fit_contrast"])[0]) / t["f"] - 1) < 0.1


def test_several_files_go_deeper(tmp_path):
    """A faint companion (f = 0.0012, baseline noise, seed 8) that neither file shows at
    P_FA 1e-3 is found in the two together, near its position (at this signal-to-noise
    ratio the fit is within 5 mas and 3 deg: 8 mas across)."""
    files, t = _epoch_files(tmp_path, 0.0012, 8)
    found = [detect(KernelPhaseData.read(f), pfa=1e-3, n_draws=1000, seed=0,
                    limits=False).candidates for f in files]
    assert [len(c) for c in found] == [0, 0]
    c = detect(KernelPhaseData.read(files), pfa=1e-3, n_draws=1000, seed=0,
               limits=False).candidates
    assert len(c) == 1
    assert abs(c[0]["fit_separation"].to_value(u.mas) - t["sep"]) < 20
    assert abs(c[0]["fit_pa_sky"].to_value(u.deg) - t["pa"]) < 5


def test_different_grids_read_as_one_achromatic_channel(tmp_path):
    """Tables on different wavelength grids (once refused): one channel at the shortest
    wavelength, baselines scaled by lambda_0 / lambda; a grey companion found there."""
    a, b = tmp_path / "a.oifits", tmp_path / "b.oifits"
    t = standin(a, wl=(3.8e-6, 4.3e-6), sep=150.0, pa=60.0, f=0.03, sigma_deg=0.2, seed=2,
                primary=True, corr=True)
    standin(b, wl=(4.8e-6,), sep=150.0, pa=60.0, f=0.03, sigma_deg=0.2, seed=3, primary=True)
    mixed = _two_grids(tmp_path / "mixed.oifits", a, b)
    with pytest.warns(KpifsWarning, match="different wavelength grids"):
        kpd = KernelPhaseData.read(mixed)
    assert kpd.meta["achromatic"] and kpd.n_wave == 1 and kpd.n_kp == 45
    assert kpd.wavelengths.to_value(u.um) == pytest.approx([3.8])
    # the model reproduces the files' closure phases: the 4.8 um table's baselines x 3.8/4.8
    km = kpd.kernel_model
    model = km.binary_kernel_phases([-t["dra"], t["ddec"]] * u.mas, t["f"], kpd.wavelengths)
    resid = (kpd.kp[0, 0] - model[0]) / np.sqrt(np.diag(kpd.covariance[0]))
    assert np.sqrt(np.mean(resid ** 2)) < 1.5
    with pytest.warns(KpifsWarning, match="different wavelength grids"):
        also = KernelPhaseData.read([a, b])          # the same as two files
    assert also.kp == pytest.approx(kpd.kp)
    one = KernelPhaseData.read(mixed, insname="A")   # one grid keeps its channels
    assert one.n_wave == 2 and one.n_kp == 15
    res = detect(kpd, pfa=1e-3, n_draws=1000, seed=0, limits=False)
    c = res.candidates[0]
    assert abs(c["fit_separation"].to_value(u.mas) - t["sep"]) < 3
    assert abs(float(np.ravel(c["fit_contrast"])[0]) / t["f"] - 1) < 0.1


def test_several_files_refused(tmp_path, capsys):
    a, b = tmp_path / "a.oifits", tmp_path / "b.oifits"
    standin(a, primary=True)
    standin(b, primary=True, seed=1)
    with fits.open(b, mode="update") as h:
        h[0].header["OBJECT"] = "HD 2"
    assert main(["detect", str(a), str(b), "-o", str(tmp_path / "d.fits")]) == 2
    err = capsys.readouterr().err
    assert "OIFITS files of different targets" in err and "HD 2" in err
    kp = _mask_kpd(wl=(4.8,)).write(tmp_path / "kp.fits")
    assert main(["detect", str(a), str(kp), "-o", str(tmp_path / "d.fits")]) == 2
    assert "only OIFITS files combine" in capsys.readouterr().err
    assert main(["detect", str(a), str(a), "-o", str(tmp_path / "d.fits")]) == 2
    assert "given twice" in capsys.readouterr().err
