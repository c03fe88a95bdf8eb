"""Small private helpers shared by several stages (units, safe FITS writing)."""
import os
import re
import tempfile
from pathlib import Path

import numpy as np
from astropy import units as u

from .exceptions import KpifsError

__all__ = []

_QTY_RE = re.compile(r"^\s*([-+]?[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([A-Za-zµ]+)?\s*$")


def to_quantity(value, unit, *, name="value"):
    """Return *value* as a `~astropy.units.Quantity` in *unit*.

    Accepts a Quantity, a plain number (taken to be in *unit*) or a string such
    as ``"10.42mas"`` / ``"1.6um"`` / ``"0.38 m"``.
    """
    if isinstance(value, str):
        parts = [p for p in value.split(",") if p.strip()]
        if len(parts) > 1:
            return u.Quantity([to_quantity(p, unit, name=name).value for p in parts], unit)
        m = _QTY_RE.match(value.replace("µ", "u"))
        if not m:
            raise KpifsError(f"cannot read {name} {value!r}: expected a number with a unit, "
                             f"e.g. '1.6um' or '10.42mas'")
        number, unit_str = m.groups()
        value = float(number) * (u.Unit(unit_str) if unit_str else u.Unit(unit))
    try:
        q = u.Quantity(value, unit)
    except u.UnitConversionError as exc:
        raise KpifsError(f"{name} has the wrong unit: {exc}") from None
    except (TypeError, ValueError) as exc:
        raise KpifsError(f"cannot read {name} {value!r}: {exc}") from None
    return q


def as_rng(seed):
    """Return a `numpy.random.Generator` from an int, a Generator or None."""
    return np.random.default_rng(seed)


def check_output_path(path, *, overwrite=False):
    """Refuse an existing output (unless *overwrite*) and a directory."""
    path = Path(path)
    if path.is_dir():
        raise KpifsError(f"{path}: is a directory, expected an output file name")
    if path.exists() and not overwrite:
        raise KpifsError(f"{path}: output exists; pass overwrite=True (--overwrite) to replace it")
    if not path.parent.exists():
        raise KpifsError(f"{path}: the folder {path.parent} does not exist")
    return path


def write_hdulist(hdul, path, *, overwrite=False, inputs=()):
    """Write *hdul* to *path* atomically (temporary name, then rename).

    An existing *path* is replaced only with ``overwrite=True``; an input file is
    never overwritten, even then.
    """
    path = check_output_path(path, overwrite=overwrite)
    for inp in inputs:
        try:
            if Path(inp).exists() and path.exists() and os.path.samefile(inp, path):
                raise KpifsError(f"{path}: refusing to overwrite an input file")
        except OSError:
            pass
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        hdul.writeto(tmp, overwrite=True, checksum=True)
        # mkstemp makes the file private; give it the permissions of any new file
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    return path
