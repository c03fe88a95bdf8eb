"""Real interferometric files of ../shared/data/real (skipped when the folder is absent),
read with no option beyond what its README gives."""
import numpy as np
import pytest
from astropy import units as u

from kpifs import KernelPhaseData, KpifsWarning
from kpifs.cli import main
from kpifs.data import DetectionResult
from kpifs.detect import detect
from kpifs.detect.resolved import fit_resolved_binary

pytestmark = pytest.mark.realdata

AMI = "jwst_niriss_ami_nuhor_f480m.oifits"
GRAVITY = "vlti_gravity_oleo_2022-02-28.fits"
#: the README's published fit of the GRAVITY epoch (x towards East: dRA)
OLEO = {"dra": -0.919, "ddec": 3.553, "f": 0.2536, "diameters": [1.26, 0.67] * u.mas}


def test_ami_real_null_and_its_cards(real_data, tmp_path, capsys):
    """JWST/NIRISS AMI, nu Hor (no companion published): the FOV card of 2.2e-8 arcsec
    (below the resolution, 188 mas) and the MJD (58886 against DATE-OBS 2023-10-31) are
    ignored with notes; `kpifs detect` reports no candidate, the energy test is
    consistent with noise once the errors are scaled to the data's own scatter (T3PHIERR
    is 12.7x smaller than it), and its limit is a contrast of 3.6e-3 (B, P_FA 1e-3,
    P_D 0.5) from 100 to 700 mas."""
    path = real_data / AMI
    kpd = KernelPhaseData.read(path)
    notes = " | ".join(kpd.meta["notes"])
    assert "OI_ARRAY FOV" in notes and "ignored: smaller than the resolution" in notes
    assert "MJD 58886.04 is -1362 days from DATE-OBS 2023-10-31" in notes
    assert kpd.shape == (1, 1, 15)
    out = tmp_path / "det.fits"
    assert main(["detect", str(path), "-o", str(out), "--quiet"]) == 0
    res = DetectionResult.read(out)
    assert len(res.candidates) == 0
    assert res.energy["pfa"] > 0.01
    assert res.energy["noise_scale"] == pytest.approx(161.9, rel=0.01)
    sep = np.hypot(res.grid.X, res.grid.Y)
    ring = (sep >= 100) & (sep < 700) & np.isfinite(res.limits["B"])
    assert np.median(res.limits["B"][ring]) == pytest.approx(3.6e-3, rel=0.1)


def _read_gravity(real_data, **kw):
    with pytest.warns(KpifsWarning) as rec:
        kpd = KernelPhaseData.read(real_data / GRAVITY, **kw)
    text = " | ".join(str(r.message) for r in rec)
    assert "'GRAVITY_SC' holds the science" in text and "'GRAVITY_FT'" in text
    return kpd


def test_gravity_science_channels_kept(real_data):
    """GRAVITY: the fringe tracker's 6 channels on another grid no longer turn the 1628
    science channels into one achromatic channel: GRAVITY_SC is read with its channels
    (3 flagged ones left out), binned by default to 20 (documented: a companion at the
    default field's edge, 34 mas, turns by at most 0.1 fringe across a bin), or all
    1625 with binning='none'."""
    kpd = _read_gravity(real_data)
    assert kpd.shape == (1, 20, 3)
    notes = " | ".join(kpd.meta["notes"])
    assert "1625 channels binned to 20" in notes and "default search field 34 mas" in notes
    assert sum(kpd.meta["binned_channels"]) == 1625
    full = _read_gravity(real_data, binning="none")
    assert full.shape == (1, 1625, 3)


@pytest.mark.parametrize("binning", ["auto", "none"])
def test_gravity_resolved_binary_published_answer(real_data, binning):
    """From the closure phases alone, with the diameters the README gives, the companion
    is at the published position within 0.5 mas and its flux ratio within 15 %
    (measured: within 0.02 mas and 3 %), in the documented bins or all 1625 channels."""
    kpd = _read_gravity(real_data, binning=binning)
    r = fit_resolved_binary(kpd, [-1.0, 4.0] * u.mas, OLEO["diameters"], contrast=0.2)
    assert np.hypot(r["dra"].to_value(u.mas) - OLEO["dra"],
                    r["ddec"].to_value(u.mas) - OLEO["ddec"]) < 0.5
    assert abs(r["contrast"] / OLEO["f"] - 1) < 0.15


@pytest.mark.slow
def test_gravity_detect_finds_the_companion(real_data):
    """`detect` (point sources) finds the companion first, 0.6 mas from the published
    position with a flux ratio of 0.17: the resolved stars' bias of a point model
    (docs/user/oifits.rst); refitted with the README's diameters from that candidate,
    the published answer (test above)."""
    kpd = _read_gravity(real_data)
    res = detect(kpd, pfa=1e-3, n_draws=1000, seed=0, limits=False)
    c = res.candidates[0]
    dra, ddec = c["fit_dra"].to_value(u.mas), c["fit_ddec"].to_value(u.mas)
    assert np.hypot(dra - OLEO["dra"], ddec - OLEO["ddec"]) < 0.8
    assert 0.12 < float(np.mean(c["fit_contrast"])) < 0.22
    r = fit_resolved_binary(kpd, [dra, ddec] * u.mas, OLEO["diameters"], contrast=0.2)
    assert np.hypot(r["dra"].to_value(u.mas) - OLEO["dra"],
                    r["ddec"].to_value(u.mas) - OLEO["ddec"]) < 0.5
    assert abs(r["contrast"] / OLEO["f"] - 1) < 0.15
