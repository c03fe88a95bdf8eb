"""Detector position angles: the one rule for angle arguments, and the generic sources.

The detector position angle (DETPA) of a frame is the position angle, East of
North, of the detector's +y axis (image rows increasing); the detector is not
mirrored. At DETPA = 0 North is up and East is left. A sky offset
(dRA East-positive, dDec) lands at image offsets

    x = -dRA cos(DETPA) + dDec sin(DETPA),   y = dRA sin(DETPA) + dDec cos(DETPA)

(the convention of fouriever and of the producers of KPFITS files; see
``docs/user/reading.rst``). Each instrument reader says where its angles come
from (CHARIS: ``PARANG`` + 113 deg; SPHERE-IFS: the angle file plus an offset);
`parse_angles` reads the ``--pa`` override and `header_detpa` the angles of a
generic cube.
"""
import warnings
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.io import fits

from .._utils import to_quantity
from ..exceptions import KpifsError, KpifsWarning

__all__ = ["parse_angles", "header_detpa", "frame_detpa", "known_angle_files", "mean_angle",
           "data_angles"]


def parse_angles(value, *, source="--pa"):
    """Angles (deg, a 1-D float array) from a value, a list or a file (None stays None).

    Parameters
    ----------
    value : float, str, sequence, Quantity or path
        ``30``, ``"30deg"``, ``"10,11.5,13"`` (deg unless a unit is given), a
        sequence or Quantity, or a text file (one value per line) or FITS file
        (its first data array) of angles in degrees.
    source : str
        Name used in messages.

    Examples
    --------
    >>> from kpifs.io import parse_angles
    >>> parse_angles("10,11.5,13")
    array([10. , 11.5, 13. ])
    >>> parse_angles("0.5rad").round(3)
    array([28.648])
    """
    if value is None:
        return None
    path = None
    if isinstance(value, Path):
        path = value
    elif isinstance(value, str):
        text = value.strip()
        if not text:
            raise KpifsError(f"{source}: empty list of angles")
        try:
            is_file = Path(text).is_file()
        except OSError:
            is_file = False
        if is_file:
            path = Path(text)
        elif text.lower().endswith((".fits", ".fit", ".txt", ".dat", ".csv")) or "/" in text:
            raise KpifsError(f"{source}: angle file {text} not found")
    if path is not None:
        try:
            if path.suffix.lower() in (".fits", ".fit", ".fts") or \
                    path.name.lower().endswith(".fits.gz"):
                with fits.open(path) as hdul:
                    hdu = next((h for h in hdul if h.data is not None), None)
                    if hdu is None:
                        raise KpifsError(f"{path}: no data in the angle file")
                    values = np.array(hdu.data, float).ravel()
            else:
                values = np.loadtxt(path, ndmin=2, comments="#")[:, 0]
        except (OSError, ValueError, TypeError, IndexError) as exc:
            raise KpifsError(f"{path}: cannot read angles: {exc}") from None
        source = str(path)
    else:
        values = np.atleast_1d(to_quantity(value, u.deg, name=source).to_value(u.deg))
    values = np.asarray(values, float).ravel()
    if values.size == 0:
        raise KpifsError(f"{source}: no angles")
    if not np.all(np.isfinite(values)):
        raise KpifsError(f"{source}: angles must be finite numbers (deg)")
    return values


def header_detpa(hdul, nframe, *, source="<file>"):
    """Detector position angles of a generic cube: a ``DETPA`` extension or card, or None.

    A ``DETPA`` image extension holds one value per frame (or one for all);
    a ``DETPA`` card in the primary header applies to every frame. Returns
    ``(angles, where)`` with *angles* of shape (nframe,), or ``(None, None)``.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.angles import header_detpa
    >>> hdul = fits.HDUList([fits.PrimaryHDU()])
    >>> hdul[0].header["DETPA"] = 12.5
    >>> header_detpa(hdul, 2)
    (array([12.5, 12.5]), 'DETPA card')
    """
    values, where = None, None
    if "DETPA" in hdul and hdul["DETPA"].is_image and hdul["DETPA"].data is not None:
        values, where = np.ravel(np.asarray(hdul["DETPA"].data, float)), "DETPA extension"
    elif "DETPA" in hdul[0].header:
        try:
            values = np.atleast_1d(float(hdul[0].header["DETPA"]))
        except (TypeError, ValueError):
            raise KpifsError(f"{source}: DETPA card {hdul[0].header['DETPA']!r} is not a "
                             f"number (deg)") from None
        where = "DETPA card"
    if values is None:
        return None, None
    return frame_detpa(values, nframe, source=f"{source}: {where}"), where


def frame_detpa(values, nframe, *, source="--pa"):
    """One detector position angle per frame: *values* of length 1 (broadcast) or nframe.

    Examples
    --------
    >>> from kpifs.io.angles import frame_detpa
    >>> frame_detpa([30.0], 3)
    array([30., 30., 30.])
    """
    values = np.ravel(np.asarray(values, float))
    if values.size == 1:
        return np.full(nframe, values[0])
    if values.size != nframe:
        raise KpifsError(f"{source}: {values.size} detector position angles for {nframe} "
                         f"frame(s) (give one value, or one per frame)")
    return values.copy()


def known_angle_files(paths, angles, *, keyword="the angle"):
    """Indices of the exposures (one per file) to keep: those whose angle is known, when
    some are and some are not, with a warning naming the files left out; every one
    otherwise. One unknown angle would turn the whole search to the detector frame
    (issue 37: one NaN AVPARANG of 6 GPI exposures lost the companion).

    Examples
    --------
    >>> import warnings
    >>> from kpifs.io.angles import known_angle_files
    >>> with warnings.catch_warnings(record=True) as w:
    ...     warnings.simplefilter("always")
    ...     keep = known_angle_files(["a.fits", "b.fits", "c.fits"], [10.0, float("nan"), 12.0])
    >>> keep, "b.fits" in str(w[0].message)
    ([0, 2], True)
    """
    a = np.asarray(angles, float)
    known = np.isfinite(a)
    if known.all() or not known.any():
        return list(range(len(a)))
    gone = [str(p) for p, k in zip(paths, known) if not k]
    warnings.warn(f"{len(gone)} of {len(a)} exposure(s) left out: {keyword} unknown (NaN, "
                  f"missing or not a number) in {', '.join(gone)}: the others are searched on "
                  f"the sky (give --pa to keep them all)", KpifsWarning, stacklevel=3)
    return [int(i) for i in np.flatnonzero(known)]


def mean_angle(detpa):
    """Circular mean (deg) of angles, NaN ignored; NaN when none is known.

    Examples
    --------
    >>> from kpifs.io.angles import mean_angle
    >>> round(float(mean_angle([359.0, 1.0, 3.0])) % 360, 6)
    1.0
    """
    a = np.deg2rad(np.asarray(detpa, float).ravel())
    a = a[np.isfinite(a)]
    if a.size == 0:
        return np.nan
    return float(np.rad2deg(np.arctan2(np.sin(a).mean(), np.cos(a).mean())) % 360.0)


def data_angles(kpd):
    """The detector position angles of the frames behind *kpd* (deg), or None if unknown.

    Calibrated data carry their target frames' angles (``meta['detpa_frames']``);
    otherwise the data's own. Angles that were only assumed (no header keyword,
    ``meta['detpa_source']`` 'none...' or 'unknown') count as unknown.

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> from kpifs.io.angles import data_angles
    >>> data_angles(SimpleNamespace(meta={"detpa_source": "header PARANG"},
    ...                             detpa=[10.0, 12.0])).tolist()
    [10.0, 12.0]
    >>> data_angles(SimpleNamespace(meta={"detpa_source": "none (assumed 0)"}, detpa=[0.0])) is None
    True
    """
    source = str(kpd.meta.get("detpa_source", ""))
    if source.startswith(("none", "unknown")) or "(none" in source or "(unknown" in source:
        return None
    frames = kpd.meta.get("detpa_frames")
    ang = frames if frames is not None else kpd.detpa
    if ang is None:
        return None
    ang = np.atleast_1d(np.asarray(ang, float))
    return ang if ang.size and np.all(np.isfinite(ang)) else None
