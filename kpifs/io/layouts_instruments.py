"""Write simulated cubes as JWST stage-2 products and GPI pipeline cubes.

- ``jwst``: one ``*_calints.fits`` per star, byte-compatible with the JWST
  pipeline's layout (FORMATS.md): ``PRIMARY`` (no data), ``SCI``
  ``(nints, ny, nx)`` float32, ``DQ`` uint32 (stored with ``BZERO``, as the
  pipeline writes it), ``ERR``, ``VAR_POISSON``, ``VAR_RNOISE``, ``VAR_FLAT``,
  ``INT_TIMES`` and ``ASDF`` tables. Dead pixels are flagged ``DO_NOT_USE``
  and half of them are NaN in ``SCI``; a few more pixels are NaN without a
  flag and a few saturated (``SATURATED`` only, good values). ``ROLL_REF``,
  ``V3I_YANG`` and ``VPARITY`` in ``SCI`` give the scene's detector angle;
  the primary header carries other (guide-star) values under the same names.
- ``gpi``: one ``*_spdc.fits`` per exposure as the GPI pipeline writes it:
  ``SCI`` ``(37, ny, nx)`` mirrored in x, NaN outside a lenslet field turned
  by 23.5 deg, ``DQ`` uint8, the wavelength WCS (``CRVAL3``, ``CD3_3``),
  ``AVPARANG`` per exposure (``IFSROTAT`` 23.5 deg), ``PSFCENTX/Y`` and a
  celestial WCS.
"""
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.io import fits

from .._meta import VERSION
from .._utils import check_output_path, write_hdulist
from ..exceptions import KpifsError
from .gpi import GPI_BANDS
from .jwst import JWST_FILTERS

__all__ = ["write_jwst_calints", "write_gpi_exposures", "JWST_GEOMETRY", "GPI_IFSROTAT"]

#: V3I_YANG (deg) and VPARITY written for each instrument (NIRISS: FORMATS.md).
JWST_GEOMETRY = {"NIRISS": (-0.56, -1), "NIRCAM": (-0.03, -1)}
#: IFSROTAT written in simulated GPI files (deg; 23.5 + PACAL with PACAL = 0).
GPI_IFSROTAT = 23.5


def _filter_of(inst, wavelength):
    best = min((abs(lam / wavelength - 1), name) for (i, name), (lam, _) in
               JWST_FILTERS.items() if i == inst)
    if best[0] > 0.01:
        raise KpifsError(f"no {inst} filter at {wavelength:.4f} um (the JWST layout writes "
                         f"one filter of kpifs's table per file)")
    return best[1]


def _truth(hdr, cards, obj):
    hdr["TARGNAME"] = (obj, "target name")
    for key, val in (cards or {}).items():
        hdr[key] = val
    hdr["KPIFSVER"] = (VERSION, "kpifs version")
    hdr.add_history(f"simulated by kpifs {VERSION}")


def write_jwst_calints(path, cube, variance, wavelength, pixscale, *, instrument="NIRISS",
                       pupil=None, detpa=0.0, cards=None, overwrite=False, obj="SIMULATED",
                       exptime=None, seed=0):
    """Write ``(nints, ny, nx)`` images as a JWST stage-2 ``*_calints.fits``.

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from astropy.io import fits
    >>> from kpifs.io.layouts_instruments import write_jwst_calints
    >>> tmp = tempfile.TemporaryDirectory()
    >>> p = write_jwst_calints(tmp.name + "/a_calints.fits", np.ones((2, 8, 8)),
    ...                        np.ones((2, 8, 8)), 4.8196 * u.um, 65.55 * u.mas)
    >>> fits.getheader(p, "DQ")["BZERO"], fits.getval(p, "FILTER")
    (2147483648, 'F480M')
    >>> tmp.cleanup()
    """
    check_output_path(path, overwrite=overwrite)
    inst = instrument.upper()
    lam = float(u.Quantity(wavelength, u.um).value)
    ps = float(u.Quantity(pixscale, u.mas).value)
    filt = _filter_of(inst, lam)
    cube = np.asarray(cube, np.float32).copy()
    var = np.asarray(variance, float)
    nint, ny, nx = cube.shape
    rng = np.random.default_rng(seed)
    dq = np.zeros(cube.shape, np.uint32)
    dead = ~np.isfinite(var)
    dq[dead] |= 1
    nan_dead = dead & (rng.random(cube.shape) < 0.5)
    cube[nan_dead] = np.nan
    for flag, value in ((None, np.nan), (2, None)):      # NaN without a flag; saturated only
        idx = rng.integers(0, [nint, ny, nx], (3, 3))
        for i, y, x in idx:
            if flag is None:
                cube[i, y, x] = value
            else:
                dq[i, y, x] |= flag
    yang, parity = JWST_GEOMETRY.get(inst, (0.0, -1))
    phu = fits.Header()
    phu["TELESCOP"] = "JWST"
    phu["INSTRUME"] = inst
    if inst == "NIRISS":
        phu["DETECTOR"] = "NIS"
        phu["EXP_TYPE"] = "NIS_AMI"
        wheel = filt in ("F090W", "F115W", "F140M", "F150W", "F158M", "F200W")
        phu["FILTER"], phu["PUPIL"] = ("CLEAR", filt) if wheel else (filt, pupil or "CLEARP")
        phu["SUBARRAY"] = f"SUB{nx}"
    else:
        phu["CHANNEL"] = "SHORT" if ps < 45 else "LONG"
        phu["DETECTOR"] = "NRCA1" if ps < 45 else "NRCALONG"
        phu["EXP_TYPE"] = "NRC_IMAGE"
        phu["FILTER"], phu["PUPIL"] = filt, pupil or "CLEAR"
        phu["SUBARRAY"] = "SUB64P" if nx == 64 else "FULL"
    phu.update(SUBSTRT1=1, SUBSTRT2=1, SUBSIZE1=nx, SUBSIZE2=ny, NINTS=nint,
               EFFINTTM=float(u.Quantity(exptime if exptime is not None else 1.0, u.s).value))
    phu["TARG_RA"], phu["TARG_DEC"] = 53.1, -27.8
    phu["DATE-OBS"], phu["TIME-OBS"] = "2026-01-01", "00:00:00.000"
    # newer schemas: guide-star values under the reader's names in PRIMARY (never read)
    phu["ROLL_REF"], phu["V3I_YANG"], phu["VPARITY"] = 0.0, 0.0, 1
    _truth(phu, cards, obj)
    sci = fits.ImageHDU(cube, name="SCI")
    sci.header["BUNIT"] = "DN/s"
    sci.header["PIXAR_A2"] = ((ps / 1000) ** 2, "[arcsec^2] nominal pixel area")
    sci.header["PIXAR_SR"] = (((ps / 1000) * np.pi / 180 / 3600) ** 2, "[sr] pixel area")
    sci.header.update(RA_REF=53.1, DEC_REF=-27.8, V2_REF=-290.1, V3_REF=-697.5)
    sci.header["ROLL_REF"] = (float(detpa) + yang * parity, "[deg] V3 PA at the reference")
    sci.header["V3I_YANG"] = (yang, "[deg] angle from V3 to ideal y")
    sci.header["VPARITY"] = (parity, "relative sense of rotation, V3 to ideal")
    sci.header["PA_V3"] = sci.header["ROLL_REF"]
    sci.header["PA_APER"] = float(detpa)
    err = np.sqrt(np.where(np.isfinite(var), var, np.nan)).astype(np.float32)
    var32 = np.where(np.isfinite(var), var, np.nan).astype(np.float32)
    times = fits.BinTableHDU.from_columns(
        [fits.Column(name="integration_number", format="J", array=np.arange(1, nint + 1)),
         fits.Column(name="int_mid_MJD_UTC", format="D", array=60000 + np.arange(nint) * 1e-4)],
        name="INT_TIMES")
    asdf = fits.BinTableHDU.from_columns(
        [fits.Column(name="ASDF_METADATA", format="20A", array=np.array([b"#ASDF 1.0.0"]))],
        name="ASDF")
    hdul = fits.HDUList([fits.PrimaryHDU(header=phu), sci, fits.ImageHDU(dq, name="DQ"),
                         fits.ImageHDU(err, name="ERR"),
                         fits.ImageHDU(var32, name="VAR_POISSON"),
                         fits.ImageHDU(np.zeros_like(var32), name="VAR_RNOISE"),
                         fits.ImageHDU(np.zeros_like(var32), name="VAR_FLAT"), times, asdf])
    return write_hdulist(hdul, path, overwrite=overwrite)


def _lenslet_field(shape, angle=23.5, fraction=0.68):
    ny, nx = shape
    y, x = np.mgrid[:ny, :nx]
    x = x - (nx - 1) / 2
    y = y - (ny - 1) / 2
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    half = fraction * min(shape) / 2
    return (np.abs(c * x + s * y) <= half) & (np.abs(-s * x + c * y) <= half)


def write_gpi_exposures(outdir, cube, variance, wavelengths, pixscale, *, detpa=None,
                        prefix="S20260101S", cards=None, overwrite=False, obj="SIMULATED",
                        exptime=None, obsmode="H_direct"):
    """One GPI ``*_spdc.fits`` per frame of ``(nframe, 37, ny, nx)`` (the kpifs frame).

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from astropy.io import fits
    >>> from kpifs.io.layouts_instruments import write_gpi_exposures
    >>> wl = (1.4904 + (np.arange(37) + 0.5) * 0.3112 / 37) * u.um
    >>> tmp = tempfile.TemporaryDirectory()
    >>> paths = write_gpi_exposures(tmp.name, np.ones((1, 37, 32, 32)),
    ...                             np.ones((1, 37, 32, 32)), wl, 14.161 * u.mas)
    >>> paths[0].name, fits.getval(paths[0], "IFSFILT")
    ('S20260101S0001_spdc.fits', 'IFSFILT_H_G1213')
    >>> tmp.cleanup()
    """
    wl = u.Quantity(wavelengths, u.um).value
    band = next((b for b, (lo, hi) in GPI_BANDS.items() if lo < wl[0] < wl[-1] < hi), "H")
    cube = np.asarray(cube)
    nf, nw, ny, nx = cube.shape
    pa = np.zeros(nf) if detpa is None else np.broadcast_to(np.asarray(detpa, float), (nf,))
    outdir = Path(outdir)
    paths = [outdir / f"{prefix}{i + 1:04d}_spdc.fits" for i in range(nf)]
    for p in paths:
        check_output_path(p, overwrite=overwrite)
    field = _lenslet_field((ny, nx))
    s = float(u.Quantity(pixscale, u.mas).value) / 3.6e6
    out = []
    for i, path in enumerate(paths):
        phu = fits.Header()
        phu.update(INSTRUME="GPI", TELESCOP="Gemini South", OBJECT=obj,
                   IFSFILT=f"IFSFILT_{band}_G1213", DISPERSR="DISP_PRISM_G6262",
                   OBSMODE=obsmode, APODIZER="APOD_CLEAR_G6201", OCCULTER="SCIENCE",
                   LYOTMASK="Open", IFSROTAT=GPI_IFSROTAT, PAR_ANG=float(pa[i]) + 66.5,
                   RA=83.8, DEC=-5.4)
        phu["DATE-OBS"], phu["MJD-OBS"] = "2026-01-01", 61041.0 + i * 1e-3
        _truth(phu, cards, obj)
        data = np.where(field, cube[i], np.nan)[..., ::-1].astype(np.float32)
        bad = ~np.isfinite(variance[i]) & field
        sci = fits.ImageHDU(data, name="SCI")
        h = sci.header
        h["BUNIT"] = "ADU per coadd"
        h["AVPARANG"] = (float(pa[i]) - GPI_IFSROTAT + 90, "[deg] mean parallactic angle")
        h.update(CTYPE3="WAVE", CUNIT3="microns", CRPIX3=1, CRVAL3=float(wl[0]),
                 CD3_3=float(np.mean(np.diff(wl))) if nw > 1 else 0.01)
        h["PSFCENTX"] = (float(nx - 1 - nx // 2), "star x (0-based, file frame)")
        h["PSFCENTY"] = (float(ny // 2), "star y (0-based)")
        t = np.radians(pa[i])
        h.update(CTYPE1="RA---TAN", CTYPE2="DEC--TAN", CRPIX1=(nx + 1) / 2, CRPIX2=(ny + 1) / 2,
                 CRVAL1=83.8, CRVAL2=-5.4, CD1_1=s * np.cos(t), CD1_2=s * np.sin(t),
                 CD2_1=-s * np.sin(t), CD2_2=s * np.cos(t))
        exp = float(u.Quantity(exptime if exptime is not None else 1.0, u.s).value)
        h.update(ITIME=exp, COADDS=1, EXPTIME=exp)
        dq = (bad[..., ::-1]).astype(np.uint8)
        hdul = fits.HDUList([fits.PrimaryHDU(header=phu), sci, fits.ImageHDU(dq, name="DQ")])
        out.append(write_hdulist(hdul, path, overwrite=overwrite))
    return out
