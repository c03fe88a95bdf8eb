"""`read_cube`: pick the right reader for a file and say which."""
import logging
import warnings
from pathlib import Path

import numpy as np
from astropy import units as u

from .._utils import canonical_name
from ..exceptions import KpifsError, KpifsWarning
from .charis import charis_setup, is_charis, read_charis
from .cube import FrameStack, IFSCube, open_fits, read_generic, refuse_kpfits
from .gpi import gpi_pupil, gpi_setup, is_gpi, read_gpi
from .jwst import is_jwst, jwst_pupil, jwst_setup, parse_dq_bits, read_jwst
from .sphere import is_sphere, read_sphere, sphere_setup
from .wavelengths import parse_wavelengths

__all__ = ["read_cube", "detect_instrument", "header_pupil", "check_pupil_header",
           "observing_setup", "setup_differences", "INSTRUMENTS"]

log = logging.getLogger(__name__)

INSTRUMENTS = ("auto", "charis", "sphere", "jwst", "gpi", "generic")


def detect_instrument(path):
    """``'charis'``, ``'sphere'``, ``'jwst'``, ``'gpi'`` or ``'generic'`` from a file's headers.

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.io import detect_instrument, write_observation
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> obs = simulate_scene("charis", n_frames=1, npup=32, shape=(32, 32))
    >>> tmp = tempfile.TemporaryDirectory()
    >>> files = write_observation(obs, tmp.name, layout="charis")
    >>> detect_instrument(files["target"][0])
    'charis'
    >>> tmp.cleanup()
    """
    hdul = open_fits(path)
    try:
        refuse_kpfits(hdul, path)
        if is_charis(hdul):
            return "charis"
        if is_sphere(hdul):
            return "sphere"
        if is_jwst(hdul):
            return "jwst"
        if is_gpi(hdul):
            return "gpi"
        if str(hdul[0].header.get("INSTRUME", "")).strip().upper() == "CHARIS":
            warnings.warn(f"{path}: the header says CHARIS but has no wavelength solution "
                          f"(LAM_MIN, DLOGLAM, NLAM): read as a plain cube; give the "
                          f"wavelengths (--wavelengths)", KpifsWarning, stacklevel=2)
        return "generic"
    finally:
        hdul.close()


def read_cube(paths, instrument="auto", *, wavelengths=None, pixscale=None, angles=None,
              dq_bits=None, pa_given=False):
    """Read one or several cube files as an `~kpifs.io.IFSCube`.

    Parameters
    ----------
    paths : str or list of str
        Several files are read as more frames of one observation (CHARIS:
        one exposure per file).
    instrument : {'auto', 'charis', 'sphere', 'generic'}
        ``'auto'`` recognises CHARIS pipeline cubes (``LAM_MIN``/``DLOGLAM``/
        ``NLAM``) and SPHERE-IFS products (``INSTRUME``, ``ESO SEQ ARM`` or the
        Data Center's ``ESO PRO REC1 ID``); anything else is read as a generic
        cube. The choice is logged and stored in ``cube.instrument``.
    wavelengths
        Any form `~kpifs.io.parse_wavelengths` accepts (a Quantity, values,
        ``"1.52um,1.6um"`` or a text/FITS file); overrides the header, or
        supplies what it lacks.
    pixscale, angles
        Passed to the reader (override the header, or supply what it lacks).
    dq_bits : int or str, optional
        JWST: the DQ flags read as bad pixels (`~kpifs.io.jwst.parse_dq_bits`;
        default ``DO_NOT_USE``). Ignored by the other readers.
    pa_given : bool
        The detector angles will be given (``--pa``): CHARIS and GPI exposures
        whose header angle is unknown are kept, not left out.

    Examples
    --------
    >>> import tempfile, astropy.units as u
    >>> from kpifs.io import read_cube, write_observation
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> tmp = tempfile.TemporaryDirectory()
    >>> d = tmp.name
    >>> files = write_observation(simulate_scene("paper", n_frames=2, npup=32), d)
    >>> with read_cube(files["target"]) as cube:
    ...     print(cube.instrument, cube.shape)
    generic (2, 3, 40, 40)
    >>> tmp.cleanup()
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    paths = [str(p) for p in paths]
    if not paths:
        raise KpifsError("no input files")
    if instrument not in INSTRUMENTS:
        raise KpifsError(f"unknown instrument {instrument!r}: use one of {INSTRUMENTS}")
    wavelengths = parse_wavelengths(wavelengths)     # once, whatever the number of files
    dq_bits = parse_dq_bits(dq_bits)
    if instrument == "auto":
        kinds = {p: detect_instrument(p) for p in paths}
        if len(set(kinds.values())) > 1:
            raise KpifsError("the inputs are of different kinds: " + ", ".join(
                f"{p} ({k})" for p, k in kinds.items()))
        instrument = kinds[paths[0]]
        log.info("%s: read as %s", paths[0] if len(paths) == 1 else f"{len(paths)} files",
                 instrument)
    if instrument == "charis":
        return read_charis(paths, wavelengths=wavelengths, pixscale=pixscale,
                           keep_unknown_angles=pa_given)
    if instrument == "jwst":
        return read_jwst(paths, wavelengths=wavelengths, pixscale=pixscale,
                         dq_bits=dq_bits)
    if instrument == "gpi":
        return read_gpi(paths, wavelengths=wavelengths, pixscale=pixscale,
                        keep_unknown_angles=pa_given)
    readers = {"sphere": lambda p: read_sphere(p, wavelengths=wavelengths, pixscale=pixscale,
                                               angles=angles),
               "generic": lambda p: read_generic(p, wavelengths=wavelengths,
                                                 pixscale=pixscale)}
    cubes = []
    try:
        for p in paths:
            cubes.append(readers[instrument](p))
        if len(cubes) == 1:
            return cubes[0]
        return _concatenate(cubes)
    except BaseException:
        for c in cubes:
            c.close()
        raise


def _concatenate(cubes):
    first = cubes[0]
    for c in cubes[1:]:
        if len(c.wavelengths) != len(first.wavelengths) or not np.allclose(
                c.wavelengths, first.wavelengths, rtol=1e-5):
            raise KpifsError(f"{c.name}: its wavelengths differ from those of {first.name}")
        if abs(c.pixscale / first.pixscale - 1) > 1e-3:
            raise KpifsError(f"{c.name}: pixel scale {c.pixscale} differs from {first.pixscale}")
    stack = FrameStack([c.data for c in cubes])
    files = [f for c in cubes for f in c._files]
    angles = detpa = None
    if all(c.angles is not None for c in cubes):
        angles = np.concatenate([c.angles.to_value(u.deg) for c in cubes]) * u.deg
    if all(c.detpa is not None for c in cubes):
        detpa = np.concatenate([c.detpa.to_value(u.deg) for c in cubes]) * u.deg
    sources = list(dict.fromkeys(c.detpa_source for c in cubes))
    return IFSCube(data=stack, wavelengths=first.wavelengths, pixscale=first.pixscale,
                   header=first.header, angles=angles, detpa=detpa,
                   detpa_source="; ".join(str(s) for s in sources), instrument=first.instrument,
                   source=[s for c in cubes for s in c.source], _files=files)


def header_pupil(header):
    """The built-in pupil an instrument's header names (JWST, GPI), or None.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.readers import header_pupil
    >>> header_pupil(fits.Header({"INSTRUME": "NIRISS", "PUPIL": "NRM"}))
    'niriss_nrm'
    >>> header_pupil(fits.Header({"INSTRUME": "CHARIS"})) is None
    True
    """
    if str(header.get("INSTRUME", "")).strip().upper() == "GPI":
        return gpi_pupil(header)
    return jwst_pupil(header)


#: Pupils that fit each telescope's headers (a warning for any other built-in one).
_PUPIL_FAMILIES = ({"jwst", "niriss_clearp", "niriss_nrm", "nircam_clear"},
                   {"gpi", "gemini_south", "gpi_nrm"})


def check_pupil_header(pupil, header, *, source="cube"):
    """Warn when a built-in *pupil* is not the telescope the header's INSTRUME names.

    Examples
    --------
    >>> import warnings
    >>> from astropy.io import fits
    >>> from kpifs.io.readers import check_pupil_header
    >>> with warnings.catch_warnings(record=True) as w:
    ...     warnings.simplefilter("always")
    ...     check_pupil_header("subaru", fits.Header({"INSTRUME": "NIRISS"}))
    >>> "NIRISS" in str(w[0].message)
    True
    """
    expected = header_pupil(header) if header is not None else None
    key = canonical_name(pupil) if isinstance(pupil, str) else str(pupil).lower()
    if expected is None or key.endswith((".fits", ".fit", ".fits.gz")):
        return
    family = next((f for f in _PUPIL_FAMILIES if expected in f), {expected})
    if key not in family:
        warnings.warn(f"{source}: INSTRUME {header.get('INSTRUME')!r} but the pupil model is "
                      f"{pupil!r} (expected {expected!r})", KpifsWarning, stacklevel=2)


def observing_setup(header):
    """What a target's and its calibrator's files must share, as the header says: the
    instrument (``INSTRUME``, unless generic) and that instrument's own facts (JWST
    filter and pupil element, GPI band, mode, apodizer and Lyot stop, CHARIS and
    SPHERE-IFS mode: each instrument module's ``*_setup``). Only what the header says
    is in it.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.readers import observing_setup
    >>> observing_setup(fits.Header({"INSTRUME": "NIRISS", "FILTER": "F480M",
    ...                              "PUPIL": "CLEARP"}))
    {'instrument': 'NIRISS', 'filter': 'F480M', 'pupil element': 'CLEARP'}
    >>> observing_setup(None)
    {}
    """
    if header is None:
        return {}
    inst = str(header.get("INSTRUME", "") or "").strip().upper()
    out = {"instrument": inst} if inst and inst != "GENERIC" else {}
    if inst in ("NIRISS", "NIRCAM"):
        out.update(jwst_setup(header))
    elif inst == "GPI":
        out.update(gpi_setup(header))
    elif inst == "CHARIS" or "CAL_BAND" in header:
        out.update(charis_setup(header))
    elif inst == "SPHERE" or "HIERARCH ESO INS2 COMB IFS" in header:
        out.update(sphere_setup(header))
    return out


def setup_differences(first, other):
    """``[(fact, value in first, value in other)]`` for the facts of two
    `observing_setup` results that both state and that differ.

    Examples
    --------
    >>> from kpifs.io.readers import setup_differences
    >>> setup_differences({"filter": "F480M", "pupil element": "CLEARP"},
    ...                   {"filter": "F480M", "pupil element": "NRM"})
    [('pupil element', 'CLEARP', 'NRM')]
    """
    return [(k, v, other[k]) for k, v in first.items() if k in other and other[k] != v]
