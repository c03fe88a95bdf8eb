"""Third-party suite: GPI DRP spectral cubes written here in the pipeline's layout, with a
PSF simulated independently of kpifs's simulator and writer (`thirdparty_gpi`; issue 35,
item 4)."""
import warnings

import numpy as np
import pytest
from astropy import units as u
from astropy.io import fits
from astropy.wcs import WCS

from kpifs.cli import main
from kpifs.data import DetectionResult
from kpifs.exceptions import KpifsWarning
from kpifs.io import read_cube

import thirdparty_gpi as tg


def test_drp_cubes_read_as_the_pipeline_wrote_them(tmp_path):
    """Wavelengths CRVAL3 + i CD3_3, DETPA = AVPARANG + IFSROTAT - 90 (the DRP's WCS), the
    mirrored x undone, the square read centred on PSFCENTX/Y and free of the NaN outside
    the turned lenslet field."""
    rng = np.random.default_rng(0)
    par = np.array([-20.0, -5.0])
    cubes, star = tg.exposures(rng, 2, parang=par, box=32, nscreen=1, oversample=1)
    paths = tg.write_spdc(tmp_path, cubes, star, par)
    with read_cube(paths) as c:
        data = np.asarray(c.data[:])
        assert c.instrument == "gpi"
        assert c.wavelengths.to_value(u.um) == pytest.approx(tg.h_wavelengths(), abs=1e-6)
        assert c.detpa.to_value(u.deg) == pytest.approx(par + tg.IFSROTAT - 90)
        side = c.header["KPCROP"]
    # the largest NaN-free square of a 190-lenslet field turned by 24.5 deg: 145 pixels
    assert 140 <= side <= 150 and np.isnan(data).mean() < 0.002
    peak = np.unravel_index(np.nanargmax(data[0, 18]), data.shape[-2:])
    assert peak == (side // 2, side // 2)
    # North from the DRP's celestial WCS is at DETPA from the reader's +y axis
    w = WCS(fits.getheader(paths[0], "SCI"), naxis=[1, 2])
    (ra0, de0), (ra1, de1) = w.pixel_to_world_values([[140, 140], [140, 150]])
    pa = np.degrees(np.arctan2((ra1 - ra0) * np.cos(np.radians(de0)), de1 - de0))
    assert (pa - (par[0] + tg.IFSROTAT - 90) + 180) % 360 - 180 == pytest.approx(0, abs=0.01)


@pytest.mark.slow
def test_drp_sequence_search_states_its_field(tmp_path, capsys):
    """8 target and 8 calibrator exposures (H band) with a 5e-3 companion at 300 mas
    (7 lambda/D): the default 0.8 m model (60 kernel phases per channel) aliases beyond
    183 mas. The search says so, what the window (363 mas) and the images (1027 mas)
    would allow, and which step reaches the window (0.40 m); the product's FLD* cards
    record it. (Before: nothing said the field stopped at 183 mas. With --step 0.4m,
    278 kernel phases, the search reaches 362 mas and finds no candidate: its B limit
    at 280-320 mas is 7e-2 with these 8 exposures.)"""
    t, c, off = tg.sequence(tmp_path, seed=0, nscreen=1, oversample=1, box=72)
    kp, det = tmp_path / "kp.fits", tmp_path / "det.fits"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KpifsWarning)
        assert main(["extract", *t, "--calibrator", *c, "-o", str(kp), "-q"]) == 0
        assert main(["detect", str(kp), "-o", str(det), "--draws", "1000"]) == 0
    out = capsys.readouterr().out
    assert ("field searched 20-183 mas: beyond, the 0.80 m grid of the pupil model (60 "
            "kernel phases per channel, 8 frames) aliases; the window reaches 363 mas and "
            "the images 1027 mas; --step 0.40m reaches 363 mas") in out
    hdr = fits.getheader(det)
    assert hdr["FLDLIM"] == "model" and hdr["FLDOUT"] == pytest.approx(183, abs=1)
    assert hdr["FLDSTEPR"] == pytest.approx(0.40, abs=0.005)
    assert hdr["FLDIMG"] == pytest.approx(1027, abs=15)
    res = DetectionResult.read(det)
    assert res.meta["field"]["limit"] == "model"
    assert np.hypot(*off) > np.nanmax(res.grid.sep[res.grid.valid])     # never searched
    assert main(["info", str(det)]) == 0
    assert "(60 kernel phases per channel, 8 frames) aliases" in capsys.readouterr().out
