"""Reader for JWST stage-2 images: NIRISS kernel phase and AMI, NIRCam imaging.

``*_calints.fits`` (``SCI`` of shape ``(nints, ny, nx)``) and ``*_cal.fits``
(one 2-D image) written by the JWST pipeline. Extensions are found by
``EXTNAME``; a scaled HDU (``DQ``: uint32 stored with ``BZERO``) is read
into memory, never memory-mapped, while ``SCI`` stays memory-mapped. Each
integration is a frame of one channel.

- Mode: ``EXP_TYPE`` ``NIS_AMI``/``NIS_IMAGE`` (NIRISS ``PUPIL`` ``CLEARP``
  kernel phase, ``NRM`` aperture masking, or a pupil-wheel filter) and
  ``NRC_IMAGE``; anything else (coronagraphy, SOSS, grism, MIRI, ...) is
  refused naming ``EXP_TYPE``.
- Filter: ``FILTER``, or ``PUPIL`` when the filter sits in the pupil wheel
  (NIRISS F090W-F200W with ``FILTER = CLEAR``; NIRCam's F162M, F164N, F323N,
  F405N, F466N, F470N). Wavelength and bandwidth from `JWST_FILTERS`.
- Pixel scale from `JWST_PIXSCALES` (``INSTRUME`` and NIRCam ``CHANNEL``),
  checked against ``sqrt(PIXAR_A2)`` of ``SCI`` (a warning when they differ
  by more than 2 %). A pixel scale given is a refinement of the file's own
  (within 2 % of either); one that contradicts it (another detector's) is
  refused, naming the file.
- Pupil element: NIRISS ``CLEARP``, ``NRM`` or a pupil-wheel filter, NIRCam
  ``CLEAR`` or a pupil-wheel filter (`PUPIL_ELEMENTS`); any other ``PUPIL``
  (grisms, weak lenses, Lyot stops) is refused. Files of one star must share
  it (`jwst_setup`: instrument, filter and pupil element, also what a
  calibrator must share with its target, `kpifs._checks.check_same_setup`).
- Sky orientation: ``DETPA = ROLL_REF - V3I_YANG * VPARITY`` (deg) from the
  ``SCI`` header (the PRIMARY header of newer files holds guide-star values
  under the same names), the relation jwst-kpi writes; the same for every
  integration.
- Bad pixels: NaN, and ``DQ`` with any of *dq_bits* set (default
  ``DO_NOT_USE``, bit 0, as jwst-kpi and the jwst ``ami`` step; ``--dq-bits``
  adds others, `parse_dq_bits`).
- Per-pixel noise: ``ERR`` squared, or ``VAR_POISSON + VAR_RNOISE + VAR_FLAT``
  without it, as ``cube.variance`` (read lazily): the extraction propagates it
  to the kernel phases' errors (`kpifs.calibration.pixelnoise`).
- Pupil: `jwst_pupil` (NIRISS ``NRM`` -> ``niriss_nrm``, ``CLEARP`` ->
  ``niriss_clearp``, a pupil-wheel filter or NIRCam -> ``jwst``).
"""
import logging
import warnings

import numpy as np
from astropy import units as u
from astropy.io import fits

from .._memory import check_memory
from .._utils import canonical_name, check_output_path, to_quantity, write_hdulist
from ..exceptions import KpifsError, KpifsWarning
from .cube import FrameStack, IFSCube, open_fits
from .instrument import Instrument, add_truth

__all__ = ["read_jwst", "is_jwst", "is_jwst_header", "jwst_mode", "jwst_pupil", "jwst_setup",
           "jwst_detpa",
           "JWST_FILTERS", "JWST_PIXSCALES", "PUPIL_ELEMENTS", "PIXSCALE_TOLERANCE",
           "own_pixscale", "pixscale_fits", "SUPPORTED_EXP_TYPES", "DO_NOT_USE", "DQ_FLAGS",
           "parse_dq_bits", "write_jwst_calints", "JWST_GEOMETRY", "INSTRUMENT"]

log = logging.getLogger(__name__)

#: DQ bit value of DO_NOT_USE (jwst ``dqflags``).
DO_NOT_USE = 1

#: DQ flag values by name (jwst ``dqflags``; FORMATS.md). Bits 7, 8 and 28 were renamed
#: between versions: give them by value.
DQ_FLAGS = {name: 1 << bit for bit, name in (
    (0, "DO_NOT_USE"), (1, "SATURATED"), (2, "JUMP_DET"), (3, "DROPOUT"), (4, "OUTLIER"),
    (5, "PERSISTENCE"), (6, "AD_FLOOR"), (9, "NON_SCIENCE"), (10, "DEAD"), (11, "HOT"),
    (12, "WARM"), (13, "LOW_QE"), (14, "RC"), (15, "TELEGRAPH"), (16, "NONLINEAR"),
    (17, "BAD_REF_PIXEL"), (18, "NO_FLAT_FIELD"), (19, "NO_GAIN_VALUE"), (20, "NO_LIN_CORR"),
    (21, "NO_SAT_CHECK"), (22, "UNRELIABLE_BIAS"), (23, "UNRELIABLE_DARK"),
    (24, "UNRELIABLE_SLOPE"), (25, "UNRELIABLE_FLAT"), (26, "OPEN"), (27, "ADJ_OPEN"),
    (29, "MSA_FAILED_OPEN"), (30, "OTHER_BAD_PIXEL"), (31, "REFERENCE_PIXEL"))}


def parse_dq_bits(value, *, source="--dq-bits"):
    """The DQ mask of bad pixels from an integer or a list of flag names and values.

    *value*: None (``DO_NOT_USE`` alone), an int, or a string of names of
    `DQ_FLAGS` and integer values (decimal or ``0x`` hex) separated by ``,``,
    ``|`` or ``+``. ``DO_NOT_USE`` is always included: the pipeline marks with
    it the pixels it could not calibrate.

    Examples
    --------
    >>> from kpifs.io.jwst import parse_dq_bits
    >>> parse_dq_bits(None), parse_dq_bits("saturated,JUMP_DET"), parse_dq_bits("0x800|4096")
    (1, 7, 6145)
    """
    if value is None:
        return DO_NOT_USE
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        tokens = [int(value)]
    else:
        tokens = [t.strip() for t in str(value).replace("|", ",").replace("+", ",").split(",")
                  if t.strip()]
    mask = DO_NOT_USE
    for t in tokens:
        if isinstance(t, int):
            v = t
        elif t.upper() in DQ_FLAGS:
            v = DQ_FLAGS[t.upper()]
        else:
            try:
                v = int(t, 0)
            except ValueError:
                raise KpifsError(f"{source}: {t!r} is neither a DQ flag name (e.g. SATURATED, "
                                 f"JUMP_DET) nor an integer") from None
        if not 0 <= v < 2 ** 32:
            raise KpifsError(f"{source}: {v} is not a 32-bit DQ value")
        mask |= v
    return mask


#: EXP_TYPEs read (imaging with a full or masked pupil).
SUPPORTED_EXP_TYPES = ("NIS_AMI", "NIS_IMAGE", "NRC_IMAGE")

#: Pupil elements read, by instrument (``CLEAR``: a filter in the pupil wheel, or NIRCam's
#: open pupil); NIRISS ``GR700XD``, NIRCam's weak lenses, grisms and coronagraphic Lyot
#: stops are refused.
PUPIL_ELEMENTS = {"NIRISS": ("CLEARP", "NRM", "CLEAR"), "NIRCAM": ("CLEAR",)}

#: Pixel scales (mas) by instrument and NIRCam channel (jwst-kpi ``constants.py``).
JWST_PIXSCALES = {("NIRISS", None): 65.55, ("NIRCAM", "SHORT"): 31.0,
                  ("NIRCAM", "LONG"): 63.0}

#: (mean wavelength, effective width) in um by (instrument, filter). The six of
#: FORMATS.md's sampling table are SVO means (jwst-kpi); the others are the
#: pivot wavelengths and bandwidths of the JWST user documentation's filter
#: tables, rounded.
JWST_FILTERS = {
    ("NIRISS", "F090W"): (0.902, 0.194), ("NIRISS", "F115W"): (1.150, 0.228),
    ("NIRISS", "F140M"): (1.404, 0.144), ("NIRISS", "F150W"): (1.494, 0.318),
    ("NIRISS", "F158M"): (1.582, 0.198), ("NIRISS", "F200W"): (1.993, 0.464),
    ("NIRISS", "F277W"): (2.8000, 0.6448), ("NIRISS", "F380M"): (3.8299, 0.2020),
    ("NIRISS", "F430M"): (4.2870, 0.2039), ("NIRISS", "F480M"): (4.8196, 0.2974),
    ("NIRCAM", "F070W"): (0.704, 0.128), ("NIRCAM", "F090W"): (0.901, 0.194),
    ("NIRCAM", "F115W"): (1.154, 0.225), ("NIRCAM", "F140M"): (1.404, 0.142),
    ("NIRCAM", "F150W"): (1.5106, 0.2892), ("NIRCAM", "F162M"): (1.626, 0.168),
    ("NIRCAM", "F164N"): (1.644, 0.020), ("NIRCAM", "F182M"): (1.845, 0.238),
    ("NIRCAM", "F187N"): (1.874, 0.024), ("NIRCAM", "F200W"): (1.990, 0.461),
    ("NIRCAM", "F210M"): (2.093, 0.205), ("NIRCAM", "F212N"): (2.120, 0.027),
    ("NIRCAM", "F250M"): (2.503, 0.181), ("NIRCAM", "F277W"): (2.786, 0.672),
    ("NIRCAM", "F300M"): (2.996, 0.318), ("NIRCAM", "F323N"): (3.237, 0.038),
    ("NIRCAM", "F335M"): (3.365, 0.347), ("NIRCAM", "F356W"): (3.563, 0.787),
    ("NIRCAM", "F360M"): (3.621, 0.372), ("NIRCAM", "F405N"): (4.055, 0.046),
    ("NIRCAM", "F410M"): (4.092, 0.436), ("NIRCAM", "F430M"): (4.280, 0.228),
    ("NIRCAM", "F444W"): (4.421, 1.024), ("NIRCAM", "F460M"): (4.624, 0.228),
    ("NIRCAM", "F466N"): (4.654, 0.054), ("NIRCAM", "F470N"): (4.707, 0.051),
    ("NIRCAM", "F480M"): (4.8213, 0.3141),
}

_SCALED = ("BZERO", "BSCALE", "BLANK")


def _card(hdr, key):
    try:
        value = hdr.get(key, "")
    except (fits.VerifyError, ValueError):       # a card astropy cannot parse (NaN, ...)
        value = hdr.cards[key].image[10:].split("/")[0].strip(" '")
    return str(value or "").strip().upper()


def is_jwst(hdul):
    """True for a JWST pipeline product (``TELESCOP = 'JWST'`` and a ``SCI`` extension).

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.jwst import is_jwst
    >>> hdr = fits.Header({"TELESCOP": "JWST"})
    >>> is_jwst(fits.HDUList([fits.PrimaryHDU(header=hdr), fits.ImageHDU(name="SCI")]))
    True
    """
    return is_jwst_header(hdul[0].header) and "SCI" in hdul


def is_jwst_header(header):
    """True for a primary header of JWST's (``TELESCOP = 'JWST'``).

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.jwst import is_jwst_header
    >>> is_jwst_header(fits.Header({"TELESCOP": " jwst"})), is_jwst_header(fits.Header())
    (True, False)
    """
    return _card(header, "TELESCOP") == "JWST"


def jwst_mode(header, *, source="JWST file"):
    """``(instrument, filter, pupil element)`` of a supported JWST exposure.

    Refuses (`~kpifs.exceptions.KpifsError`) an ``EXP_TYPE`` other than
    `SUPPORTED_EXP_TYPES` and a filter missing from `JWST_FILTERS`.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.jwst import jwst_mode
    >>> jwst_mode(fits.Header({"INSTRUME": "NIRISS", "EXP_TYPE": "NIS_AMI",
    ...                        "FILTER": "CLEAR", "PUPIL": "F200W"}))
    ('NIRISS', 'F200W', 'CLEAR')
    """
    exp = _card(header, "EXP_TYPE")
    if exp not in SUPPORTED_EXP_TYPES:
        raise KpifsError(f"{source}: EXP_TYPE {exp or '(missing)'} is not supported: kpifs "
                         f"reads {', '.join(SUPPORTED_EXP_TYPES)} (kernel phase, AMI and "
                         f"imaging), not coronagraphy, SOSS, grism or MIRI")
    inst, filt, pupil = _elements(header)
    if (inst, filt) not in JWST_FILTERS:
        raise KpifsError(f"{source}: {inst} filter {filt or '(missing)'} (FILTER "
                         f"{_card(header, 'FILTER')!r}, PUPIL {_card(header, 'PUPIL')!r}) is "
                         f"not in kpifs's table: give --wavelengths and --pixscale with "
                         f"--instrument generic")
    if pupil not in PUPIL_ELEMENTS.get(inst, ()):
        raise KpifsError(f"{source}: {inst} PUPIL {_card(header, 'PUPIL') or '(missing)'!r} is "
                         f"no pupil element kpifs models (its {inst} pupils: "
                         f"{', '.join(PUPIL_ELEMENTS.get(inst, ()))} or a pupil-wheel filter):"
                         f" its images are not those of a known pupil")
    return inst, filt, pupil


def _elements(header):
    """``(INSTRUME, filter, pupil element)`` as the header says (a filter in the pupil wheel
    moved to the filter, the pupil element then ``CLEAR``), not checked."""
    inst = _card(header, "INSTRUME")
    filt, pupil = _card(header, "FILTER"), _card(header, "PUPIL")
    if pupil.startswith("F") and pupil[1:4].isdigit():     # a filter in the pupil wheel
        filt, pupil = pupil, "CLEAR"
    return inst, filt, pupil


def jwst_setup(header):
    """What a JWST target's and calibrator's files must share: instrument, filter and pupil
    element (NIRISS ``CLEARP`` kernel phase or ``NRM`` aperture masking), as the header
    says. Empty for a header without ``INSTRUME``.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.jwst import jwst_setup
    >>> jwst_setup(fits.Header({"INSTRUME": "NIRISS", "FILTER": "F480M", "PUPIL": "NRM"}))
    {'instrument': 'NIRISS', 'filter': 'F480M', 'pupil element': 'NRM'}
    """
    inst, filt, pupil = _elements(header)
    if not inst:
        return {}
    out = {"instrument": inst}
    if filt:
        out["filter"] = filt
    if pupil:
        out["pupil element"] = pupil
    return out


def jwst_pupil(header):
    """The built-in pupil (a `~kpifs.model.pupil.TELESCOPES` or `~kpifs.model.pupil.MASKS`
    key) for a
    JWST header, or None (not JWST, or a ``PUPIL`` none of them models: never the full
    pupil in its place).

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.jwst import jwst_pupil
    >>> jwst_pupil(fits.Header({"INSTRUME": "NIRISS", "PUPIL": "CLEARP"}))
    'niriss_clearp'
    >>> jwst_pupil(fits.Header({"INSTRUME": "NIRCAM", "PUPIL": "CLEAR"}))
    'jwst'
    """
    inst, _, pupil = _elements(header)
    if inst == "NIRISS":
        return {"NRM": "niriss_nrm", "CLEARP": "niriss_clearp", "CLEAR": "jwst",
                "": "jwst"}.get(pupil)
    if inst == "NIRCAM":
        return "jwst" if pupil in PUPIL_ELEMENTS["NIRCAM"] + ("",) else None
    return None


def jwst_detpa(sci_header, *, source="JWST file"):
    """Detector position angle (deg) from ``ROLL_REF``, ``V3I_YANG`` and ``VPARITY``.

    ``DETPA = ROLL_REF - V3I_YANG * VPARITY`` (jwst-kpi); None when a card is
    missing, NaN (with a warning) when one is not finite; refused when they are not
    angles and a parity.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.jwst import jwst_detpa
    >>> jwst_detpa(fits.Header({"ROLL_REF": 250.0, "V3I_YANG": -0.56, "VPARITY": -1}))
    249.44
    """
    try:
        roll, yang, par = (float(sci_header[k]) for k in ("ROLL_REF", "V3I_YANG", "VPARITY"))
    except KeyError:
        return None
    except (TypeError, ValueError, fits.VerifyError) as exc:
        raise KpifsError(f"{source}: ROLL_REF/V3I_YANG/VPARITY not numbers: {exc}") from None
    if not np.all(np.isfinite([roll, yang, par])):
        warnings.warn(f"{source}: ROLL_REF/V3I_YANG/VPARITY = {roll}/{yang}/{par}: the sky "
                      f"orientation is unknown (give --pa)", KpifsWarning, stacklevel=3)
        return np.nan
    if par not in (-1.0, 1.0) or abs(roll) > 360 or abs(yang) > 360:
        raise KpifsError(f"{source}: ROLL_REF/V3I_YANG/VPARITY = {roll:g}/{yang:g}/{par:g} are "
                         f"not the angles (deg) and parity (+1 or -1) they should be")
    return round((roll - yang * par) % 360.0, 10)


def _hdu(hdul, name, path, *, required=True):
    if name in hdul:
        return hdul[name]
    if required:
        raise KpifsError(f"{path}: no {name} extension (EXTNAME) in this JWST file")
    return None


def _dq_bad(path, shape, dq_bits):
    """The DQ mask (True = bad) read into memory: DQ is scaled, so never memory-mapped."""
    with fits.open(path, memmap=False) as hdul:
        if "DQ" not in hdul or not hdul["DQ"].header.get("NAXIS"):
            return None
        hdr = hdul["DQ"].header
        n = np.prod([hdr.get(f"NAXIS{i}", 0) for i in range(1, hdr["NAXIS"] + 1)], dtype=float)
        # the scaled integers, their mask and the flags (issue 37: bounded before reading)
        check_memory(13.0 * n, f"{path}: DQ of {n:.3g} pixels", "read fewer integrations")
        dq = np.asarray(hdul["DQ"].data)
    dq = dq[:, None] if dq.ndim == 3 else dq           # (nints, 1, ny, nx) as the frames
    try:
        bad = np.bitwise_and(dq, np.asarray(dq_bits, dtype=dq.dtype)) != 0
        return np.broadcast_to(bad, shape)
    except ValueError:
        raise KpifsError(f"{path}: DQ of shape {dq.shape} does not match SCI") from None


class _Variance:
    """Per-pixel variance of the frames, read lazily: ``ERR**2`` or the sum of ``VAR_*``."""

    def __init__(self, arrays, square):
        self.arrays, self.square = arrays, square
        self.shape = arrays[0].shape

    def __getitem__(self, key):
        if self.square:          # a negative ERR stays negative: not a noise (refused later)
            err = np.asarray(self.arrays[0][key], float)
            return np.copysign(np.square(err), err)
        return sum(np.asarray(a[key], float) for a in self.arrays)


def _variance(hdul, path, shape):
    """``cube.variance`` part of one file (nints, 1, ny, nx), or None without ERR/VAR_*."""
    def view(name):
        hdu = hdul[name] if name in hdul else None
        if hdu is None or hdu.data is None:
            return None
        d = hdu.data
        d = d[None, None] if d.ndim == 2 else (d[:, None] if d.ndim == 3 else d)
        if d.shape != shape:
            raise KpifsError(f"{path}: {name} of shape {hdu.data.shape} does not match SCI")
        return d
    err = view("ERR")
    if err is not None:
        return _Variance([err], square=True), "ERR"
    parts = [v for v in map(view, ("VAR_POISSON", "VAR_RNOISE", "VAR_FLAT")) if v is not None]
    if parts:
        return _Variance(parts, square=False), "VAR_*"
    return None, None


#: Largest relative difference between a pixel scale given and a file's own (kpifs's table
#: or ``sqrt(PIXAR_A2)``) for the given one to be taken as a refinement of it; beyond it, the
#: given scale is another detector's (NIRCam SW 31 mas against LW 63 mas).
PIXSCALE_TOLERANCE = 0.02


def own_pixscale(header, sci_header=None, *, source="JWST file"):
    """A JWST file's own pixel scale (mas): kpifs's table value (`JWST_PIXSCALES`, by
    ``INSTRUME`` and NIRCam ``CHANNEL``) and ``sqrt(PIXAR_A2)`` of ``SCI`` (NaN without it).

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.jwst import own_pixscale
    >>> own_pixscale(fits.Header({"INSTRUME": "NIRCAM", "CHANNEL": "LONG"}),
    ...              fits.Header({"PIXAR_A2": 0.063 ** 2}))
    (63.0, 63.0)
    """
    inst = _card(header, "INSTRUME")
    channel = _card(header, "CHANNEL") if inst == "NIRCAM" else None
    if (inst, channel) not in JWST_PIXSCALES:
        raise KpifsError(f"{source}: no pixel scale for {inst} channel {channel!r}: give "
                         f"--pixscale")
    try:
        from_area = 1000 * np.sqrt(float((sci_header or {})["PIXAR_A2"]))
    except (KeyError, TypeError, ValueError):
        from_area = np.nan
    return JWST_PIXSCALES[(inst, channel)], round(float(from_area), 6)


def pixscale_fits(given, own):
    """Whether a pixel scale *given* (mas) agrees with a file's *own* (`own_pixscale`)
    within `PIXSCALE_TOLERANCE`.

    Examples
    --------
    >>> from kpifs.io.jwst import pixscale_fits
    >>> pixscale_fits(65.6, (65.55, 65.6)), pixscale_fits(31.0, (63.0, 63.0))
    (True, False)
    """
    return any(abs(given / v - 1) <= PIXSCALE_TOLERANCE for v in own if np.isfinite(v))


def _pixscale(path, inst, hdr, sci_hdr, pixscale):
    table, from_area = own_pixscale(hdr, sci_hdr, source=path)
    what = f"{inst}{' ' + _card(hdr, 'CHANNEL') if inst == 'NIRCAM' else ''}"
    if pixscale is not None:
        given = to_quantity(pixscale, u.mas, name="pixel scale")
        if not pixscale_fits(given.value, (table, from_area)):
            raise KpifsError(f"{path}: the pixel scale given ({given.value:g} mas) contradicts "
                             f"this {what} file's own ({table} mas in kpifs's table, "
                             f"sqrt(PIXAR_A2) = {from_area:.2f} mas): give that, or no "
                             f"pixel scale")
        return given
    if "PIXAR_A2" in sci_hdr and not abs(from_area / table - 1) <= PIXSCALE_TOLERANCE:
        warnings.warn(f"{path}: pixel scale {table} mas ({what}) differs from sqrt(PIXAR_A2) "
                      f"= {from_area:.2f} mas; using {table} mas (give --pixscale to change "
                      f"it)", KpifsWarning, stacklevel=3)
    return table * u.mas


def _read_one(path, wavelengths, pixscale, dq_bits):
    hdul = open_fits(path)
    try:
        hdr = hdul[0].header
        inst, filt, pupil = jwst_mode(hdr, source=path)
        sci = _hdu(hdul, "SCI", path)
        if any(k in sci.header for k in _SCALED):
            raise KpifsError(f"{path}: SCI is a scaled (integer) image: not a stage-2 "
                             f"calibrated product")
        data = sci.data
        if data is None or data.ndim not in (2, 3):
            raise KpifsError(f"{path}: SCI must be (ny, nx) or (nints, ny, nx), got "
                             f"{None if data is None else data.shape}")
        view = data[None, None] if data.ndim == 2 else data[:, None]
        bad = _dq_bad(path, view.shape, dq_bits)
        var, var_from = _variance(hdul, path, view.shape)
        wl = (wavelengths if wavelengths is not None
              else [JWST_FILTERS[(inst, filt)][0]] * u.um)
        ps = _pixscale(path, inst, hdr, sci.header, pixscale)
        detpa = jwst_detpa(sci.header, source=path)
        header = hdr.copy()
        header.update({k: v for k, v in sci.header.items() if k not in header and k not in
                       ("XTENSION", "PCOUNT", "GCOUNT", "EXTNAME", "BITPIX") and
                       not k.startswith("NAXIS")})
        header["KPFILTER"] = (filt, "filter kpifs read (FILTER or pupil wheel)")
        header["KPBWIDTH"] = (JWST_FILTERS[(inst, filt)][1], "[um] filter effective width")
        nint = view.shape[0]
        where = "ROLL_REF - V3I_YANG * VPARITY (SCI header)"
        if detpa is None:
            log.warning("%s: no ROLL_REF/V3I_YANG/VPARITY in SCI: sky orientation unknown",
                        path)
            pa, where = np.full(nint, np.nan), "none (unknown)"
        else:
            pa = np.full(nint, detpa)
        header["KPDQBITS"] = (int(dq_bits), "DQ bits read as bad pixels")
        stack = FrameStack([view], None if bad is None else [bad])
        cube = IFSCube(data=stack, wavelengths=wl, pixscale=ps, header=header,
                       detpa=pa * u.deg, detpa_source=where, instrument="jwst",
                       source=[str(path)], _files=[hdul],
                       variance=None if var is None else FrameStack([var]),
                       variance_source=var_from)
    except BaseException:
        hdul.close()
        raise
    log.info("%s: %s %s %s, %d integration(s) %s, %.2f mas, DETPA %s", path, inst,
             _card(hdr, "EXP_TYPE"), filt, view.shape[0], view.shape[2:], ps.value,
             "unknown" if detpa is None else f"{detpa:.2f} deg")
    return cube, filt


def read_jwst(paths, *, wavelengths=None, pixscale=None, dq_bits=DO_NOT_USE):
    """Read JWST ``_calints.fits``/``_cal.fits`` file(s) of one filter as an `IFSCube`.

    Parameters
    ----------
    paths : str or list of str
        Files of one target in one filter: their integrations become the frames.
    wavelengths : `~astropy.units.Quantity`, optional
        Replaces the filter table's mean wavelength.
    pixscale : `~astropy.units.Quantity`, optional
        Replaces the table's pixel scale: a refinement of it (within
        `PIXSCALE_TOLERANCE` of the table or of ``sqrt(PIXAR_A2)``); a value
        that contradicts a file's own is refused.
    dq_bits : int or str
        DQ bits that make a pixel bad (`parse_dq_bits`: default ``DO_NOT_USE``
        = 1; e.g. ``1 | 2 | 4`` or ``'SATURATED,JUMP_DET'`` add SATURATED and
        JUMP_DET). NaN pixels are always bad.

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.io import write_observation
    >>> from kpifs.io.jwst import read_jwst
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> obs = simulate_scene("niriss", n_frames=2, npup=32, shape=(32, 32))
    >>> tmp = tempfile.TemporaryDirectory()
    >>> files = write_observation(obs, tmp.name, layout="jwst")
    >>> with read_jwst(files["target"]) as cube:
    ...     print(cube.shape, cube.wavelengths, cube.pixscale, cube.detpa[0])
    (2, 1, 32, 32) [4.8196] um 65.55 mas 249.44 deg
    >>> tmp.cleanup()
    """
    if isinstance(paths, (str, bytes)) or not hasattr(paths, "__iter__"):
        paths = [paths]
    paths = [str(p) for p in paths]
    if not paths:
        raise KpifsError("no JWST files given")
    dq_bits = parse_dq_bits(dq_bits, source="dq_bits")
    cubes, filters = [], []
    try:
        for p in paths:
            cube, filt = _read_one(p, wavelengths, pixscale, dq_bits)
            cubes.append(cube)
            filters.append(filt)
        targets = [_card(c.header, "TARGNAME") for c in cubes]
        if len(set(targets)) > 1:
            raise KpifsError("files of different targets: " + ", ".join(
                f"{p} ({t or '?'})" for p, t in zip(paths, targets))
                + ": give the calibrator with --calibrator")
        elements = {p: jwst_setup(c.header).get("pupil element") for p, c in zip(paths, cubes)}
        if len(set(elements.values())) > 1:
            raise KpifsError("files through different pupil elements: " + ", ".join(
                f"{p} (PUPIL {e})" for p, e in elements.items()) + ": one cube is one pupil "
                "(kernel phase and aperture masking are different observations)")
        if len(set(filters)) > 1:
            raise KpifsError(
                "files in different filters: " + ", ".join(f"{p} ({f})" for p, f in
                                                           zip(paths, filters))
                + ": one cube is one filter; kpifs extract makes filters the channels of "
                "one calibrated product (give the calibrator's files with --calibrator)")
        if len(cubes) == 1:
            return cubes[0]
        return _join(cubes)
    except BaseException:
        for c in cubes:
            c.close()
        raise


def _join(cubes):
    """Files of one target and filter as more frames of one cube."""
    first = cubes[0]
    for c in cubes[1:]:
        if abs(c.pixscale / first.pixscale - 1) > 1e-3:
            raise KpifsError(f"{c.name}: pixel scale {c.pixscale} differs from {first.pixscale}")
    detpa = np.concatenate([c.detpa.to_value(u.deg) for c in cubes]) * u.deg
    return IFSCube(data=FrameStack([c.data for c in cubes]), wavelengths=first.wavelengths,
                   pixscale=first.pixscale, header=first.header, detpa=detpa,
                   detpa_source=first.detpa_source, instrument="jwst",
                   source=[s for c in cubes for s in c.source],
                   _files=[f for c in cubes for f in c._files],
                   variance=(FrameStack([c.variance for c in cubes])
                             if all(c.variance is not None for c in cubes) else None),
                   variance_source=first.variance_source)


#: V3I_YANG (deg) and VPARITY written for each instrument (NIRISS: FORMATS.md).
JWST_GEOMETRY = {"NIRISS": (-0.56, -1), "NIRCAM": (-0.03, -1)}


def _filter_of(inst, wavelength):
    best = min((abs(lam / wavelength - 1), name) for (i, name), (lam, _) in
               JWST_FILTERS.items() if i == inst)
    if best[0] > 0.01:
        raise KpifsError(f"no {inst} filter at {wavelength:.4f} um (the JWST layout writes "
                         f"one filter of kpifs's table per file)")
    return best[1]


def write_jwst_calints(path, cube, variance, wavelength, pixscale, *, instrument="NIRISS",
                       pupil=None, detpa=0.0, cards=None, overwrite=False, obj="SIMULATED",
                       exptime=None, seed=0):
    """Write ``(nints, ny, nx)`` images as a JWST stage-2 ``*_calints.fits``.

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from astropy.io import fits
    >>> from kpifs.io.jwst import write_jwst_calints
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
    add_truth(phu, cards, obj)
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


def _write(obs, role, outdir, common):
    """`Instrument.write`: one ``*_calints.fits`` per detector angle (ROLL_REF is one per
    exposure: issue 37, a rotating sequence was written with its mean angle)."""
    p = obs.params
    cube, var = ((obs.target, obs.variance_target) if role == "target"
                 else (obs.calibrator, obs.variance_calibrator))
    if len(p.wavelengths) != 1:
        raise KpifsError("the JWST layout writes one filter per file: simulate one "
                         "wavelength")
    inst = "NIRCAM" if "nircam" in str(p.instrument).lower() else "NIRISS"
    pupil = "NRM" if canonical_name(p.telescope) == "niriss_nrm" else None
    det = "nis" if inst == "NIRISS" else ("nrca1" if p.pixscale.to_value(u.mas) < 45
                                          else "nrcalong")
    groups = _angle_groups(p.detpa, len(cube))
    out = []
    for k, (angle, frames) in enumerate(groups):
        tag = ({"target": "00001", "calibrator": "00002"}[role] if len(groups) == 1 else
               f"{1 if role == 'target' else 2}{k + 1:04d}")
        path = outdir / f"jw01234001001_01101_{tag}_{det}_calints.fits"
        out += [write_jwst_calints(path, cube[frames, 0], var[frames, 0], p.wavelengths[0],
                                   p.pixscale, instrument=inst, pupil=pupil, detpa=angle,
                                   seed=obs.seed + (role == "calibrator") + 2 * k, **common)]
    return out


def _angle_groups(detpa, nframe):
    """``[(angle, frames)]``: runs of consecutive frames at one detector angle (deg)."""
    if detpa is None:
        return [(0.0, slice(0, nframe))]
    pa = np.broadcast_to(np.asarray(detpa, float), (nframe,))
    cuts = [0] + [i for i in range(1, nframe) if pa[i] != pa[i - 1]] + [nframe]
    return [(float(pa[a]), slice(a, b)) for a, b in zip(cuts[:-1], cuts[1:])]


def _read(paths, *, wavelengths=None, pixscale=None, dq_bits=DO_NOT_USE, **_):
    return read_jwst(paths, wavelengths=wavelengths, pixscale=pixscale, dq_bits=dq_bits)


#: The simulator's JWST scenes (issue 27): one filter per scene, one integration per
#: frame, ROLL_REF 250 deg (DETPA 249.44 for NIRISS: FORMATS.md); the companion fixed
#: on the sky.
SCENES = {
    "niriss": dict(telescope="niriss_clearp", wavelengths=[4.8196] * u.um,
                   pixscale=65.55 * u.mas, shape=(80, 80), n_frames=10, instrument="niriss",
                   wavefront_rms=20 * u.nm, jitter=0.05, star_mag=6.0, exptime=1 * u.s,
                   contrasts=[1e-2], detpa=[249.44], sky_offset=[-150.0, 200.0] * u.mas,
                   n_dead=6),
    "nircam": dict(telescope="jwst", wavelengths=[4.8213] * u.um, pixscale=63.0 * u.mas,
                   shape=(64, 64), n_frames=10, instrument="nircam", wavefront_rms=20 * u.nm,
                   jitter=0.05, star_mag=6.0, exptime=1 * u.s, contrasts=[0.19],
                   detpa=[250.0], sky_offset=[-76.1, 35.5] * u.mas, n_dead=6),
}


INSTRUMENT = Instrument(
    name="jwst", title="JWST NIRISS/NIRCam", identify=is_jwst, read=_read, pupil="jwst",
    instrume=("NIRISS", "NIRCAM"), header_pupil=jwst_pupil,
    pupils=("jwst", "niriss_clearp", "niriss_nrm", "nircam_clear"), setup=jwst_setup,
    pixscale="NIRISS 65.55 mas, NIRCam 31/63 mas (checked against PIXAR_A2)",
    angles="ROLL_REF - V3I_YANG * VPARITY (SCI header)", layout="jwst", write=_write,
    scenes=SCENES, data_hdu="SCI")
