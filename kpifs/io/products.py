"""Detection products on disk: one FITS file per search.

Extensions: DETECTION (the local statistic of the map test), PFA (global false-
alarm probability of each position; PFA_LOCAL the local one), CONTRAST and
CONTRAST_ERR ``(nwave, ny, nx)``, LIMIT (detection limit of the chosen test)
and LIMIT_<TEST> for every test, CURVES (radial limits, a table), CANDIDATES
(a table, sorted by significance, possibly empty). Images carry a WCS from map
pixels to offsets in mas along image x and y; the primary header says which
test, P_FA, P_D, calibrators, inputs and kpifs version.
"""
import numpy as np
from astropy.io import fits
from astropy.table import QTable

from .._utils import write_hdulist
from .kpfits import _card

__all__ = ["detection_hdulist", "write_detection", "read_detection"]


def _image(data, name, wcs_header, bunit=None, comment=None):
    hdu = fits.ImageHDU(np.asarray(data, np.float64), header=wcs_header.copy(), name=name)
    if bunit:
        hdu.header["BUNIT"] = bunit
    if comment:
        hdu.header["COMMENT"] = comment
    return hdu


def detection_hdulist(result, *, header=None, inputs=()):
    """Build the products of a `~kpifs.detect.DetectionResult` as an HDUList.

    Examples
    --------
    >>> from kpifs.detect.pipeline import _example_result
    >>> from kpifs.io.products import detection_hdulist
    >>> hdul = detection_hdulist(_example_result())
    >>> hdul[0].header["CONTENT"], "CANDIDATES" in hdul
    ('KPIFS-DETECTION', True)
    """
    from .. import __version__
    hdr = fits.Header() if header is None else _strip(header)
    hdr["KPIFSVER"] = (__version__, "kpifs version")
    hdr["CONTENT"] = ("KPIFS-DETECTION", "kpifs detection products")
    hdr["TEST"] = (result.test, "detection test (B, B-paper, NP, E)")
    hdr["MAPTEST"] = ("B" if result.test == "E" else result.test, "test of the DETECTION map")
    hdr["PFA"] = (result.pfa, "global false-alarm probability of the search")
    hdr["PD"] = (result.pd, "detection probability of the limits")
    hdr["THRESH"] = (result.threshold, "threshold of the map statistic at PFA")
    hdr["NDRAWS"] = (result.meta.get("n_draws", 0), "Monte-Carlo draws calibrating the search")
    hdr["MCSEED"] = (result.meta.get("seed", 0), "seed of those draws")
    hdr["NCAND"] = (len(result.candidates), "candidates above the threshold")
    hdr["ESTAT"] = (result.energy.get("statistic", np.nan), "energy-detector statistic")
    hdr["EDOF"] = (result.energy.get("dof", 0), "energy-detector degrees of freedom")
    hdr["EPFA"] = (result.energy.get("pfa", np.nan), "energy-detector P_FA of the data")
    for i, w in enumerate(result.wavelengths.to_value("um"), 1):
        hdr[f"WAVE{i}"] = (float(w), f"[um] wavelength of channel {i}")
    for i, a in enumerate(result.meta.get("spectrum", []), 1):
        hdr[f"SPEC{i}"] = (float(a), "companion spectrum shape used for limits")
    hdr["NULLCHAN"] = (result.meta.get("null_channels", "independent"),
                       "channel model: null, B/E limits")
    cals = result.meta.get("calibrators", [])
    hdr["CALIB"] = (len(cals) > 0, "calibrated with a calibrator star")
    for i, c in enumerate(cals, 1):
        hdr[f"KPCAL{i}"] = _card(c, "calibrator")
    for i, name in enumerate(inputs, 1):
        hdr[f"KPIN{i}"] = _card(name, "input file")
    hdr.add_history(f"kpifs {__version__}: {result.test} search, P_FA {result.pfa:g}, "
                    f"P_D {result.pd:g}, {len(result.candidates)} candidate(s)")
    wcs_hdr = result.grid.wcs().to_header()
    q = len(result.wavelengths)
    wcs3 = wcs_hdr.copy()
    wcs3["CTYPE3"], wcs3["CUNIT3"] = "CHANNEL", ""
    wcs3["CRPIX3"], wcs3["CRVAL3"], wcs3["CDELT3"] = 1.0, 1.0, 1.0
    hdus = [fits.PrimaryHDU(header=hdr),
            _image(result.statistic, "DETECTION", wcs_hdr, comment="local map statistic"),
            _image(result.pfa_global, "PFA", wcs_hdr, comment="global false-alarm probability"),
            _image(result.pfa_local, "PFA_LOCAL", wcs_hdr,
                   comment="false-alarm probability at a known position"),
            _image(result.contrast, "CONTRAST", wcs3, comment=f"{q} channels"),
            _image(result.contrast_err, "CONTRAST_ERR", wcs3, comment="1-sigma"),
            _image(result.limit, "LIMIT", wcs_hdr,
                   comment=f"{result.test} limit at P_FA {result.pfa:g}, P_D {result.pd:g}")]
    for name, lim in result.limits.items():
        hdus.append(_image(lim, f"LIMIT_{name.upper().replace('-', '_')}", wcs_hdr))
    curves = fits.table_to_hdu(result.curves)
    curves.name = "CURVES"
    hdus.append(curves)
    cand = result.candidates.copy()
    cand.meta = {"TEST": result.test, "THRESH": float(result.threshold)}
    ch = fits.table_to_hdu(cand)
    ch.name = "CANDIDATES"
    hdus.append(ch)
    return fits.HDUList(hdus)


def _strip(header):
    out = fits.Header()
    skip = {"SIMPLE", "BITPIX", "EXTEND", "CHECKSUM", "DATASUM", "CONTENT", "PCOUNT",
            "GCOUNT", "XTENSION", "END"}
    for card in header.cards:
        if card.keyword in skip or card.keyword.startswith("NAXIS"):
            continue
        try:
            out.append(card)
        except (ValueError, fits.VerifyError):
            pass
    return out


def write_detection(result, path, *, header=None, inputs=(), overwrite=False):
    """Write detection products atomically (never over an input).

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.detect.pipeline import _example_result
    >>> from kpifs.io.products import write_detection
    >>> write_detection(_example_result(), tempfile.mkdtemp() + "/det.fits").name
    'det.fits'
    """
    return write_hdulist(detection_hdulist(result, header=header, inputs=inputs), path,
                         overwrite=overwrite, inputs=inputs)


def read_detection(path):
    """Read back products: a dict of arrays and tables keyed by extension name.

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.detect.pipeline import _example_result
    >>> from kpifs.io.products import read_detection, write_detection
    >>> path = write_detection(_example_result(), tempfile.mkdtemp() + "/det.fits")
    >>> products = read_detection(path)
    >>> products["header"]["TEST"], products["DETECTION"].ndim
    ('B', 2)
    """
    out = {}
    with fits.open(path) as hdul:
        out["header"] = hdul[0].header.copy()
        for h in hdul[1:]:
            out[h.name] = QTable.read(h) if isinstance(h, fits.BinTableHDU) else np.array(h.data)
    return out
