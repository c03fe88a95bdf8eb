"""OIFITS written by AMICAL's own writer (``amical.save``), as from its simulated
binaries: the OI_ARRAY FOV AMICAL writes (pixel scale in radians taken for arcsec:
~1e-8 "ARCSEC", below the resolution) is ignored with a note, and the companion is found
at its offset (modulo the mask's alias) with its contrast within 1 %, bright or faint."""
import warnings

import numpy as np
import pytest
from astropy import units as u
from astropy.io import fits

from kpifs import KernelPhaseData
from kpifs.detect import detect

from test_oifits import NIRISS, binary_cp

amical = pytest.importorskip("amical")
pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore::kpifs.KpifsWarning")]

MAS2RAD = np.pi / 180 / 3600 / 1000


def _munch(d):
    from amical.tools import dict2class
    return dict2class(d) if isinstance(d, dict) else d


def amical_standin(path, *, sep, pa, f, sigma_deg, seed, wl=4.817e-6):
    """A calibrated NIRISS 7-hole binary written by ``amical.save``: closure phases of the
    binary plus baseline noise (closure phases of one exposure share it), in AMICAL's
    conventions (degrees, its triangle order, u written as -u of its own frame)."""
    from amical.mf_pipeline.ami_function import compute_index_mask
    rng = np.random.default_rng(seed)
    xy = np.asarray(NIRISS, float)
    idx = compute_index_mask(len(xy))
    bl = idx.bl2h_ix
    # AMICAL's frame: u of baseline (i, j) = x_j - x_i, written East as -u ("oriented")
    u_am = xy[bl[1], 0] - xy[bl[0], 0]
    v_am = xy[bl[1], 1] - xy[bl[0], 1]
    u_e, v_n = -u_am, v_am
    b1, b2 = idx.bs2bl_ix[0], idx.bs2bl_ix[1]
    dra, ddec = sep * np.sin(np.deg2rad(pa)), sep * np.cos(np.deg2rad(pa))
    truth = binary_cp(u_e[b1], v_n[b1], u_e[b2], v_n[b2], np.array([wl]), dra, ddec, f)[:, 0]
    nbl = len(u_e)
    cmat = np.zeros((len(b1), nbl))
    for t, (i, j, k) in enumerate(zip(*idx.bs2bl_ix)):
        cmat[t, i] += 1
        cmat[t, j] += 1
        cmat[t, k] -= 1
    sig = np.deg2rad(sigma_deg)
    cp = truth + cmat @ rng.normal(0, sig / np.sqrt(3), nbl)
    infos = _munch({"instrument": "NIRISS", "maskname": "g7", "pixscale": 65.6 * MAS2RAD,
                    "target": "binary", "filtname": "F480M", "isz": 69, "seeing": 0,
                    "orig": "SimulatedData",
                    "hdr": {"MJD-OBS": 60000.0, "date-obs": "2023-02-25",
                            "OBJECT": "binary"}})
    mask = _munch({"n_baselines": nbl, "bl2h_ix": bl, "bs2bl_ix": idx.bs2bl_ix,
                   "xycoord": xy})
    raw = _munch({"mask": mask, "infos": infos, "u": u_am, "v": v_am, "wl": wl,
                  "e_wl": 0.3e-6, "bl_cp": np.hypot(u_am[b1], v_am[b1])})
    cal = _munch({"raw_t": raw, "raw_c": raw, "cp": np.rad2deg(cp),
                  "e_cp": np.full(len(cp), sigma_deg), "vis2": np.ones(nbl),
                  "e_vis2": np.full(nbl, 0.01)})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        amical.save(cal, oifits_file=path.name, datadir=str(path.parent), fake_obj=True,
                    query_simbad=False)
    return {"dra": dra, "ddec": ddec, "f": f, "sep": sep, "pa": pa}


def _without_fov(src, dst):
    with fits.open(src) as h:
        h = fits.HDUList([x.copy() for x in h])
        arr = h["OI_ARRAY"]
        keep = [c for c in arr.columns if c.name not in ("FOV", "FOVTYPE")]
        new = fits.BinTableHDU.from_columns(keep, header=arr.header, name="OI_ARRAY")
        h[h.index_of("OI_ARRAY")] = new
        h.writeto(dst)
    return dst


@pytest.mark.parametrize("f, sigma", [(0.05, 0.02), (0.005, 0.002)], ids=["bright", "faint"])
def test_amical_written_binary_found(tmp_path, f, sigma):
    p = tmp_path / "amical.oifits"
    t = amical_standin(p, sep=180.0, pa=40.0, f=f, sigma_deg=sigma, seed=3)
    with fits.open(p) as h:
        fov = float(h["OI_ARRAY"].data["FOV"][0])
    assert 0 < fov < 1e-6                                  # AMICAL's FOV card, as real files
    for path in (p, _without_fov(p, tmp_path / "nofov.oifits")):
        kpd = KernelPhaseData.read(path)
        if path == p:
            assert any("OI_ARRAY FOV" in n and "ignored" in n for n in kpd.meta["notes"])
        res = detect(kpd, pfa=1e-3, n_draws=1000, seed=0, limits=False)
        c = res.candidates
        assert len(c) >= 1
        dra, ddec = c[0]["fit_dra"].to_value(u.mas), c[0]["fit_ddec"].to_value(u.mas)
        # modulo the mask's alias: every NIRISS baseline is a multiple of (1.14315, 0.66) m,
        # so offsets of (lambda / 1.14315 m, lambda / 0.66 m) = (869, 1505) mas change no
        # closure phase (measured: the companion at 180 mas is fitted one alias West)
        alias = kpd.wavelengths[0].to_value(u.m) / np.array([1.14315, 0.66]) / MAS2RAD
        k = (np.array([dra, ddec]) - [t["dra"], t["ddec"]]) / alias
        assert np.all(np.abs(k - np.round(k)) * alias < 2), (dra, ddec)
        assert abs(float(np.mean(c[0]["fit_contrast"])) / f - 1) < 0.01
