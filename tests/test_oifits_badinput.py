"""OIFITS bad inputs (issue 37): through the command line, a clear message naming the file
and the problem, exit status 2, inputs byte-identical and no partial output; the cases
that run to the end are checked against the truth."""
import hashlib

import numpy as np
import pytest
from astropy import units as u
from astropy.io import fits

from kpifs import KernelPhaseData, KpifsError
from kpifs.cli import main
from kpifs.data import DetectionResult

from test_oifits import _mask_kpd, standin

pytestmark = pytest.mark.filterwarnings("ignore::kpifs.KpifsWarning")


def _edit(src, dst, edit):
    """A copy of *src* at *dst* with ``edit(hdul)`` applied."""
    with fits.open(src) as h:
        h = fits.HDUList([x.copy() for x in h])
        edit(h)
        h.writeto(dst)
    return dst


def _set(table, column, value, row=0):
    def edit(h):
        h[table].data[column][row] = value
    return edit


def _header_bytes(path, table, key, value):
    """Rewrite card *key* of extension *table* in place, bytes only (no astropy check)."""
    raw = bytearray(path.read_bytes())
    head = raw.rfind(b"XTENSION", 0, raw.index(f"EXTNAME = '{table}".encode()))
    card = raw.index(key.ljust(8).encode() + b"=", head)
    raw[card:card + 80] = f"{key.ljust(8)}= {value:>20}".ljust(80).encode()
    path.write_bytes(bytes(raw))
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("oifits_bad")
    f = {}
    f["good"] = d / "good.oifits"
    f["truth"] = standin(f["good"], sep=150.0, pa=60.0, f=0.02, sigma_deg=0.1, seed=1,
                         primary=True, baseline_noise=True)
    f["corr"] = d / "corr.oifits"
    standin(f["corr"], corr=True, primary=True)
    f["err0"] = _edit(f["good"], d / "err0.oifits", _set("OI_T3", "T3PHIERR", 0.0, 3))
    f["errneg"] = _edit(f["good"], d / "errneg.oifits", _set("OI_T3", "T3PHIERR", -0.3, 3))
    f["sta99"] = _edit(f["good"], d / "sta99.oifits", _set("OI_T3", "STA_INDEX", [1, 2, 99]))
    f["mjdnan"] = _edit(f["good"], d / "mjdnan.oifits", _set("OI_T3", "MJD", np.nan, 2))

    def wrap360(h):                                   # the same phases in [0, 360)
        h["OI_T3"].data["T3PHI"] = np.mod(h["OI_T3"].data["T3PHI"], 360.0)

    def plus720(h):
        h["OI_T3"].data["T3PHI"] = h["OI_T3"].data["T3PHI"] + 720.0

    def rad_label(h):                                 # degrees in [0, 360) labelled rad
        wrap360(h)
        h["OI_T3"].columns["T3PHI"].unit = "rad"
        h["OI_T3"].columns["T3PHIERR"].unit = "rad"
    f["wrap360"] = _edit(f["good"], d / "wrap360.oifits", wrap360)
    f["plus720"] = _edit(f["good"], d / "plus720.oifits", plus720)
    f["radlabel"] = _edit(f["good"], d / "radlabel.oifits", rad_label)

    def corr_out(h):
        h["OI_CORR"].data["JINDX"][0] = h["OI_CORR"].header["NDATA"] + 5
    f["corrout"] = _edit(f["corr"], d / "corrout.oifits", corr_out)

    def corrindx_out(h):
        h["OI_T3"].data["CORRINDX_T3PHI"][-1] = h["OI_CORR"].header["NDATA"] + 1
    f["corrindx"] = _edit(f["corr"], d / "corrindx.oifits", corrindx_out)
    # sizes a small file implies: 35 triangles x 2000 channels, one OI_CORR entry across
    # two channels -> a joint covariance of 70000 x 70000 (once a MemoryError, exit 3)
    f["wide"] = d / "wide.oifits"
    standin(f["wide"], wl=np.linspace(2.0e-6, 2.4e-6, 2000), primary=True, corr=True)

    def cross(h):
        h["OI_CORR"].data["JINDX"][0] = 2          # triangle 1, channel 2
    f["widecorr"] = _edit(f["wide"], d / "widecorr.oifits", cross)
    # 3 telescopes, noise only: one closure phase per channel (seed 2 once gave a
    # candidate at global P_FA 2e-9 while the energy test said 0.85)
    three = [(0.0, 0.0), (40.0, 10.0), (15.0, 60.0)]
    f["three"] = d / "three.oifits"
    standin(f["three"], stations=three, f=0.0, sigma_deg=0.5, seed=2, diameter=1.8,
            primary=True)
    f["three6"] = d / "three6.oifits"
    standin(f["three6"], stations=three, wl=np.linspace(1.5e-6, 1.8e-6, 6), f=0.0,
            sigma_deg=0.5, seed=2, diameter=1.8, primary=True)
    # an OI_T3 header claiming 1e12 rows: the file cannot hold them
    f["huge"] = d / "huge.oifits"
    standin(f["huge"], wl=np.linspace(2.0e-6, 2.4e-6, 20), primary=True)
    _header_bytes(f["huge"], "OI_T3", "NAXIS2", 10 ** 12)
    f["all"] = [v for v in f.values() if hasattr(v, "is_file")]
    return f


def _hashes(paths):
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in paths}


CASES = [
    ("T3PHIERR zero", "err0", "T3PHIERR value(s) are zero, negative or NaN"),
    ("T3PHIERR negative", "errneg", "row 4, channel 1, -0.3"),
    ("STA_INDEX not in OI_ARRAY", "sta99", "STA_INDEX [99] not in the OI_ARRAY table"),
    ("MJD NaN", "mjdnan", "MJD is NaN or infinite in 1 row(s) (first: row 3)"),
    ("degrees labelled rad", "radlabel", "impossible for a phase in radians"),
    ("OI_CORR index beyond NDATA", "corrout", "IINDX/JINDX value(s) outside 1..NDATA = 35"),
    ("CORRINDX beyond NDATA", "corrindx", "CORRINDX_T3PHI points outside OI_CORR 'C'"),
    ("joint covariance of 110 GiB", "widecorr", "the covariance of 35 closure phases x 2000 "
     "channel(s) correlated across channels needs about 110 GiB"),
    ("header claims 1e12 rows", "huge", "not a readable FITS file"),
    ("3 telescopes, 1 channel", "three", "1 independent closure phase(s) (1 per channel x 1 "
     "channel(s)) for the 3 parameters of a companion in test B"),
]


@pytest.mark.parametrize("extra, test", [([], "B"), (["--test", "E"], "E"),
                                         (["--test", "NP"], "NP")])
def test_three_telescopes_answer_with_the_energy_test_alone(files, tmp_path, capsys, extra,
                                                            test):
    """Fewer independent closure phases than a companion's parameters: refused for every
    test, the message giving the energy test's answer (noise: P_FA 0.85)."""
    out = tmp_path / "det.fits"
    assert main(["detect", str(files["three"]), "-o", str(out), "--quiet", *extra]) == 2
    err = capsys.readouterr().err
    assert f"companion in test {test}" in err and "energy test alone: chi2 0.0357 for 1 dof, " \
        "P_FA 0.85" in err, err
    assert not out.exists()


@pytest.mark.slow
def test_three_telescopes_six_channels_searched_honestly(files, tmp_path):
    """3 telescopes and 6 channels: 6 closure phases for the S test's 2 + 3 parameters: the
    search runs, and on noise reports nothing (measured: seeds 0-2, none). (Limits are
    left out: drawn position by position, they take minutes on its 25 000 positions.)"""
    from kpifs.detect import detect
    res = detect(KernelPhaseData.read(files["three6"]), pfa=1e-3, n_draws=1000, seed=0,
                 limits=False)
    assert res.test == "S" and len(res.candidates) == 0 and res.energy["pfa"] > 0.01


@pytest.mark.parametrize("name, key, text", CASES, ids=[c[0] for c in CASES])
def test_refused(files, tmp_path, capsys, name, key, text):
    before = _hashes(files["all"])
    out = tmp_path / "det.fits"
    assert main(["detect", str(files[key]), "-o", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and text in err, err
    assert str(files[key]) in err
    assert len([ln for ln in err.splitlines() if ": error: " in ln]) == 1, err
    assert not out.exists() and not list(tmp_path.glob(".det*"))
    assert _hashes(files["all"]) == before


@pytest.mark.slow
@pytest.mark.parametrize("key", ["good", "wrap360", "plus720"])
def test_wrapped_phases_give_the_same_answer(files, tmp_path, key):
    """Closure phases in (-180, 180], [0, 360) or + 720 deg: one answer, the truth
    (wrapped to (-pi, pi] before anything else)."""
    before = _hashes(files["all"])
    out = tmp_path / "det.fits"
    assert main(["detect", str(files[key]), "-o", str(out), "--quiet", "--draws", "1000"]) == 0
    kpd = KernelPhaseData.read(files[key])
    good = KernelPhaseData.read(files["good"])
    assert kpd.kp == pytest.approx(good.kp, abs=1e-9)
    c = DetectionResult.read(out).candidates
    t = files["truth"]
    assert len(c) == 1
    assert abs(c[0]["fit_separation"].to_value(u.mas) - t["sep"]) < 3
    assert abs(c[0]["fit_pa_sky"].to_value(u.deg) - t["pa"]) < 2
    assert abs(float(np.ravel(c[0]["fit_contrast"])[0]) / t["f"] - 1) < 0.15
    assert _hashes(files["all"]) == before


def test_memory_estimated_before_allocation(files, monkeypatch):
    """Every size a file implies is estimated first: with 1 MiB available, a 7-station
    file of 3 channels (its covariance ~300 kB per table) is refused by name, not by a
    MemoryError."""
    import kpifs._memory
    monkeypatch.setattr(kpifs._memory, "available_memory", lambda: 2 ** 14)
    with pytest.raises(KpifsError, match=r"good\.oifits: .* needs about .* of memory"):
        KernelPhaseData.read(files["good"])


def test_api_write_refuses_its_own_input(tmp_path):
    """read('k.fits').write('k.fits', format='oifits', overwrite=True) replaced the KPFITS
    it was read from: refused as the command line refuses it (either format)."""
    k = _mask_kpd(wl=(4.8,)).write(tmp_path / "k.fits")
    before = k.read_bytes()
    kpd = KernelPhaseData.read(k)
    for fmt in ("oifits", "kpfits"):
        with pytest.raises(KpifsError, match="refusing to overwrite an input"):
            kpd.write(k, format=fmt, overwrite=True)
    assert k.read_bytes() == before
    o = kpd.write(tmp_path / "k.oifits")
    with pytest.raises(KpifsError, match="refusing to overwrite an input"):
        KernelPhaseData.read(o).write(o, overwrite=True)
    kpd.write(tmp_path / "other.fits", format="oifits")          # elsewhere: fine


def test_oifits_keeps_the_calibration_state(tmp_path, capsys):
    """An uncalibrated KPFITS written as OIFITS stays uncalibrated: detect refuses both
    alike (CALFLAG), and accepts both with --allow-uncalibrated."""
    kpd = _mask_kpd(wl=(4.8,))
    kpd.meta["calibrated"] = False
    k = kpd.write(tmp_path / "raw.fits")
    o = KernelPhaseData.read(k).write(tmp_path / "raw.oifits")
    assert not KernelPhaseData.read(o).meta["calibrated"]
    for p in (k, o):
        assert main(["detect", str(p), "-o", str(tmp_path / "d.fits"), "--quiet"]) == 2
        assert "not calibrated" in capsys.readouterr().err
    cal = _mask_kpd(wl=(4.8,)).write(tmp_path / "cal.oifits")
    assert KernelPhaseData.read(cal).meta["calibrated"]


def test_tiny_diameter_bounds_the_grid(tmp_path):
    """OI_ARRAY DIAMETER 1e-3 m once drove the default grid (lambda / D = 1000 arcsec) to
    exhaust the machine's memory: the field is bounded before any grid is made, with a
    note, and the search finds the truth (the companion at 150 mas, modulo the alias)."""
    from kpifs.detect import default_grid, detect
    p = tmp_path / "tiny.oifits"
    t = standin(p, sep=150.0, pa=60.0, f=0.02, sigma_deg=0.1, seed=1, primary=True,
                baseline_noise=True, diameter=1e-3)
    kpd = KernelPhaseData.read(p)
    assert any("default search field" in n and "bounded" in n for n in kpd.meta["notes"])
    g = default_grid(kpd, frame="sky")
    assert g.shape[0] * g.shape[1] * kpd.n_wave <= 1.5e5 * 1.05
    c = detect(kpd, pfa=1e-3, n_draws=1000, seed=0, limits=False).candidates
    assert len(c) == 1
    # the truth modulo the 7-hole mask's alias (lambda / 1.14315 m, lambda / 0.66 m): the
    # wide field bounded by the budget reaches several (measured: (+2, +5) aliases away)
    alias = 4.8e-6 / np.array([1.14315, 0.66]) / (np.pi / 180 / 3600 / 1000)
    k = (np.array([c[0]["fit_dra"].to_value(u.mas), c[0]["fit_ddec"].to_value(u.mas)])
         - [t["dra"], t["ddec"]]) / alias
    assert np.all(np.abs(k - np.round(k)) * alias < 3), k
