"""`read_cube`: pick the right reader for a file and say which."""
import logging
import warnings
from pathlib import Path

from .._utils import canonical_name
from ..exceptions import KpifsError, KpifsWarning
from .cube import open_fits, refuse_kpfits
from .instruments import INSTRUMENTS as _REGISTRY
from .jwst import parse_dq_bits
from .wavelengths import parse_wavelengths

__all__ = ["read_cube", "detect_instrument", "header_pupil", "check_pupil_header",
           "observing_setup", "setup_differences", "INSTRUMENTS"]

log = logging.getLogger(__name__)

#: ``--instrument`` values: ``'auto'`` and the registered instruments
#: (`kpifs.io.instruments.INSTRUMENTS`).
INSTRUMENTS = ("auto",) + tuple(_REGISTRY)


def detect_instrument(path):
    """The name of the registered instrument (`kpifs.io.instruments.INSTRUMENTS`) whose
    identifier claims a file (``'charis'``, ...), else ``'generic'``.

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
        return _REGISTRY.identify(hdul, path)
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
    instrument : str
        ``'auto'`` or a registered instrument's name
        (`kpifs.io.instruments.INSTRUMENTS`; ``'generic'``: any FITS cube).
        ``'auto'`` asks each instrument's identifier in turn (CHARIS
        pipeline cubes by ``LAM_MIN``/``DLOGLAM``/``NLAM``, SPHERE-IFS by
        ``INSTRUME``, ``ESO SEQ ARM`` or the Data Center's ``ESO PRO REC1 ID``,
        ...); anything else is read as a generic cube. The choice is logged and
        stored in ``cube.instrument``.
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
    if instrument != "auto":
        _REGISTRY.get_instrument(instrument)
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
    return _REGISTRY[instrument].read(paths, wavelengths=wavelengths, pixscale=pixscale,
                                      angles=angles, dq_bits=dq_bits, pa_given=pa_given)


def header_pupil(header):
    """The built-in pupil an instrument's header names (a JWST pupil element, a GPI mask,
    a NIRC2 pupil stop: the instrument's ``header_pupil``), or None.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.readers import header_pupil
    >>> header_pupil(fits.Header({"INSTRUME": "NIRISS", "PUPIL": "NRM"}))
    'niriss_nrm'
    >>> header_pupil(fits.Header({"INSTRUME": "CHARIS"})) is None
    True
    """
    inst = _REGISTRY.of_header(header)
    if inst is None or inst.header_pupil is None or not inst.names(header):
        return None
    return inst.header_pupil(header)


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
    family = set(_REGISTRY.of_header(header).pupils) | {expected}
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
    found = _REGISTRY.of_header(header)
    if found is not None and found.setup is not None:
        out.update(found.setup(header))
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
