"""The one rule for wavelength arguments, used by every reader and command.

A wavelength argument may be a `~astropy.units.Quantity`, a sequence of
numbers (unit given, or told from the values: 0.3-30 is um, 300-30000 nm,
3e-7-3e-5 m), a string list such as ``"1.52um,1.6um"`` or ``"1.52,1.6"``,
or the path of a text or FITS file of wavelengths. Whatever the form, the
result is checked once: finite, positive and within 0.3-30 um (a typo such as
``1.52m`` for ``1.52um`` is refused).
"""
import logging
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.io import fits

from .._utils import to_quantity
from ..exceptions import KpifsError

__all__ = ["parse_wavelengths", "read_wavelength_file", "check_wavelengths",
           "WAVELENGTH_RANGE"]

log = logging.getLogger(__name__)

#: Plausible wavelengths for kpifs's instruments (um): anything outside is a
#: unit mistake.
WAVELENGTH_RANGE = (0.3, 30.0)

_FILE_SUFFIXES = (".fits", ".fit", ".fts", ".txt", ".dat", ".csv", ".gz")


def check_wavelengths(wavelengths, *, source="wavelengths"):
    """Return *wavelengths* (a Quantity) in um, 1-D, after the one validation.

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs.io import check_wavelengths
    >>> check_wavelengths(1600 * u.nm)
    <Quantity [1.6] um>
    """
    try:
        wl = np.atleast_1d(u.Quantity(wavelengths, u.um))
    except (u.UnitsError, TypeError, ValueError) as exc:
        raise KpifsError(f"{source}: wavelengths have the wrong unit: {exc}") from None
    if wl.size == 0:
        raise KpifsError(f"{source}: no wavelengths given")
    if wl.ndim != 1:
        raise KpifsError(f"{source}: expected a list of wavelengths, got shape {wl.shape}")
    if not np.all(np.isfinite(wl.value)) or np.any(wl.value <= 0):
        raise KpifsError(f"{source}: wavelengths must be finite and > 0, got {wl}")
    lo, hi = WAVELENGTH_RANGE
    bad = (wl.value < lo) | (wl.value > hi)
    if bad.any():
        raise KpifsError(f"{source}: wavelength {wl[bad][0]:.4g} is outside {lo:g}-{hi:g} um "
                         f"(a unit mistake? e.g. '1.52m' for '1.52um')")
    return wl


def _infer_unit(values, source):
    med = float(np.median(values))
    for unit, (lo, hi) in ((u.um, (0.3, 30)), (u.nm, (300, 30000)), (u.m, (3e-7, 3e-5))):
        if lo <= med <= hi:
            return unit
    raise KpifsError(f"{source}: cannot tell the unit of wavelengths around {med:g} "
                     f"(expected um, nm or m)")


def _from_values(values, unit, source):
    values = np.atleast_1d(np.asarray(values, float))
    if values.size == 0 or not np.all(np.isfinite(values)) or np.any(values <= 0):
        raise KpifsError(f"{source}: wavelengths must be finite and > 0")
    if unit:
        try:
            unit = u.Unit(str(unit).replace("microns", "um").replace("micron", "um"))
        except ValueError as exc:
            raise KpifsError(f"{source}: wavelength unit {unit!r} not understood: {exc}") \
                from None
    else:
        unit = _infer_unit(values, source)
        log.info("%s: wavelengths taken to be in %s", source, unit)
    try:
        return check_wavelengths(values * unit, source=source)
    except u.UnitConversionError as exc:
        raise KpifsError(f"{source}: wavelength unit {unit} is not a length: {exc}") from None


def read_wavelength_file(path, *, unit=None):
    """Wavelengths from a text file (one per line) or a FITS file (first data array).

    The unit comes from *unit*, from ``BUNIT``/``CUNIT1`` in a FITS header, or
    is inferred from the values (0.3-30 means um, 300-30000 means nm) and logged.

    Examples
    --------
    >>> import tempfile, numpy as np
    >>> from kpifs.io import read_wavelength_file
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = tmp.name + "/wl.txt"
    >>> np.savetxt(path, [1159.56, 1199.70])          # nm, recognised from the values
    >>> read_wavelength_file(path)
    <Quantity [1.15956, 1.1997 ] um>
    >>> tmp.cleanup()
    """
    path = Path(path)
    if path.is_dir():
        raise KpifsError(f"{path}: is a directory, expected a wavelength file")
    if not path.exists():
        raise KpifsError(f"{path}: wavelength file not found")
    hdr_unit = None
    try:
        if path.suffix.lower() in (".fits", ".fit", ".fts") or \
                path.name.lower().endswith(".fits.gz"):
            with fits.open(path) as hdul:
                hdu = next((h for h in hdul if h.data is not None), None)
                if hdu is None:
                    raise KpifsError(f"{path}: no data in the wavelength file")
                values = np.array(hdu.data, float).ravel()
                hdr_unit = hdu.header.get("BUNIT") or hdu.header.get("CUNIT1")
        else:
            values = np.loadtxt(path, ndmin=2, comments="#")[:, 0]
    except (OSError, ValueError, TypeError) as exc:
        raise KpifsError(f"{path}: cannot read wavelengths: {exc}") from None
    return _from_values(values, unit or hdr_unit, str(path))


def _looks_like_file(text):
    try:
        if Path(text).exists():
            return True
    except OSError:          # e.g. a long list of values is no file name
        return False
    return text.lower().endswith(_FILE_SUFFIXES) or "/" in text or "\\" in text


def parse_wavelengths(value, *, unit=None, source="wavelengths"):
    """Wavelengths from any accepted form, as a checked Quantity in um (None stays None).

    Parameters
    ----------
    value : Quantity, sequence, str or path
        ``[1.52, 1.6] * u.um``; ``[1.52, 1.6]`` (unit from *unit* or the
        values); ``"1.52um,1.6um"`` or ``"1.52,1.6"``; a text or FITS file.
    unit : str or `~astropy.units.Unit`, optional
        Unit of unitless values (and of a file without a unit in its header).
    source : str
        Name used in messages (the file or option the value came from).

    Examples
    --------
    >>> from kpifs.io import parse_wavelengths
    >>> parse_wavelengths("1.52um,1.6um")
    <Quantity [1.52, 1.6 ] um>
    >>> parse_wavelengths([1520.0, 1600.0])               # nm, told from the values
    <Quantity [1.52, 1.6 ] um>
    """
    if value is None:
        return None
    if isinstance(value, u.Quantity):
        return check_wavelengths(value, source=source)
    if isinstance(value, Path):
        return read_wavelength_file(value, unit=unit)
    if isinstance(value, str):
        text = value.strip()
        if not text:
            raise KpifsError(f"{source}: empty wavelength list")
        if _looks_like_file(text):
            return read_wavelength_file(text, unit=unit)
        parts = [p.strip() for p in text.split(",") if p.strip()]
        try:
            numbers = [float(p) for p in parts]
        except ValueError:      # values with units: "1.52um,1.6um"
            return check_wavelengths(to_quantity(text, u.um, name=source), source=source)
        return _from_values(numbers, unit, source)
    try:
        items = list(value)
    except TypeError:
        items = [value]
    if items and all(isinstance(v, u.Quantity) for v in items):
        return check_wavelengths(u.Quantity(items), source=source)
    try:
        values = np.asarray(items, float)
    except (TypeError, ValueError):
        raise KpifsError(f"{source}: cannot read wavelengths from {value!r}") from None
    return _from_values(values, unit, source)
