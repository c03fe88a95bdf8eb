"""Reader for SCExAO/CHARIS cubes from the CHARIS data-reduction pipeline.

One file per exposure, ``<raw>_cube.fits``: HDU 0 the header only, HDU 1 the
cube ``(nlam, 201, 201)``, HDU 2 its inverse variance. Spaxels with
``ivar == 0`` are bad (read as NaN); lenslets outside the field are exactly 0
and stay 0 (they add nothing to the Fourier sums). Wavelengths (nm) are
``LAM_MIN * exp(i * DLOGLAM)``, checked against ``NLAM``, the cube length and
``LAM_MAX``.

Sky orientation: each file's ``PARANG`` (deg, or the string 'unavailable')
gives that frame's detector position angle ``DETPA = PARANG +
CHARIS_DETPA_OFFSET``. The CHARIS pipeline's WCS (charis-dep
``addWCS``: ``TOT_ROT = -(PARANG + 113)``, x scale negative) puts the position
angle of the detector +y axis there; pyKLIP uses 113.5 deg. An unavailable
``PARANG`` gives NaN (unknown).
"""
import logging
import warnings
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.io import fits

from .._utils import check_output_path, to_quantity, write_hdulist
from ..exceptions import KpifsError, KpifsWarning
from .angles import known_angle_files
from .cube import FrameStack, IFSCube, open_fits
from .instrument import Instrument, frame_angles, header_card, simulated_header
from .wavelengths import check_wavelengths, parse_wavelengths

__all__ = ["read_charis", "is_charis", "charis_wavelengths", "charis_setup", "CHARIS_PIXSCALE",
           "CHARIS_DETPA_OFFSET", "write_charis_exposures", "charis_field", "INSTRUMENT"]

log = logging.getLogger(__name__)

#: Default CHARIS lenslet scale (published values 16.15-16.4 mas).
CHARIS_PIXSCALE = 16.2 * u.mas

#: Detector position angle minus ``PARANG`` (deg): the rotation of the CHARIS
#: pipeline's WCS (charis-dep; pyKLIP uses 113.5 deg).
CHARIS_DETPA_OFFSET = 113.0


def is_charis(hdul):
    """True for a CHARIS pipeline cube (wavelength keys and a cube in HDU 1).

    Examples
    --------
    >>> import numpy as np
    >>> from astropy.io import fits
    >>> from kpifs.io.charis import is_charis
    >>> hdul = fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.zeros((22, 8, 8)))])
    >>> hdul[0].header.update(LAM_MIN=1159.56, DLOGLAM=0.0344, NLAM=22)
    >>> is_charis(hdul)
    True
    """
    hdr = hdul[0].header
    has_keys = all(k in hdr for k in ("LAM_MIN", "DLOGLAM", "NLAM"))
    return has_keys and len(hdul) > 1 and hdul[1].data is not None and hdul[1].data.ndim == 3


def charis_setup(header):
    """What a CHARIS target's and calibrator's cubes must share: the mode (``CAL_BAND``).

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.charis import charis_setup
    >>> charis_setup(fits.Header({"CAL_BAND": "H"}))
    {'mode': 'H'}
    """
    band = str(header.get("CAL_BAND", "") or "").strip()
    return {"mode": {"LOWRES": "BROADBAND"}.get(band.upper(), band.upper())} if band else {}


def charis_wavelengths(header, nlam_cube, *, source="CHARIS cube"):
    """Channel wavelengths from a CHARIS header, checked for consistency.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.charis import charis_wavelengths
    >>> hdr = fits.Header({"LAM_MIN": 1159.56, "DLOGLAM": 0.0344, "NLAM": 3})
    >>> charis_wavelengths(hdr, 3).round(4)
    <Quantity [1.1596, 1.2001, 1.2421] um>
    """
    missing = [k for k in ("LAM_MIN", "DLOGLAM", "NLAM") if k not in header]
    if missing:
        raise KpifsError(f"{source}: missing wavelength keyword(s) "
                         f"{', '.join(repr(k) for k in missing)}")
    try:
        lmin = float(header["LAM_MIN"])
        dlog = float(header["DLOGLAM"])
        nlam = int(header["NLAM"])
    except (TypeError, ValueError) as exc:
        raise KpifsError(f"{source}: bad wavelength keyword: {exc}") from None
    if nlam != nlam_cube:
        raise KpifsError(f"{source}: NLAM = {nlam} but the cube has {nlam_cube} channels")
    if not (lmin > 0 and 0 < dlog < 1):        # a log step of 1: a factor e per channel
        raise KpifsError(f"{source}: LAM_MIN = {lmin} and DLOGLAM = {dlog} must be > 0 "
                         f"(DLOGLAM < 1)")
    if not 300 < lmin < 30000:
        raise KpifsError(f"{source}: LAM_MIN = {lmin} is not a wavelength in nm")
    with np.errstate(over="ignore", invalid="ignore"):
        wl = lmin * np.exp(np.arange(nlam) * dlog)
    if "LAM_MAX" in header:
        try:
            lmax = float(header["LAM_MAX"])
        except (TypeError, ValueError):
            lmax = np.nan
        if not abs(wl[-1] - lmax) <= 0.005 * lmax:
            raise KpifsError(f"{source}: LAM_MAX = {lmax} nm disagrees with LAM_MIN * "
                             f"exp((NLAM-1) * DLOGLAM) = {wl[-1]:.2f} nm")
    return check_wavelengths((wl * u.nm).to(u.um), source=source)


def read_charis(paths, *, wavelengths=None, pixscale=None, keep_unknown_angles=False):
    """Read one or many CHARIS pipeline cubes as one `~kpifs.io.IFSCube`.

    Parameters
    ----------
    paths : str or list of str
        ``*_cube.fits`` files, one exposure each; they become the frames.
    wavelengths : optional
        Channel wavelengths, in any form `~kpifs.io.parse_wavelengths`
        accepts, replacing the headers' ``LAM_MIN``/``DLOGLAM`` grid (for
        files whose headers lack it or are wrong).
    pixscale : `~astropy.units.Quantity`, optional
        Lenslet scale; default `CHARIS_PIXSCALE` (16.2 mas).

    keep_unknown_angles : bool
        Keep the exposures whose ``PARANG`` is unknown ('unavailable', NaN or
        missing) among others that have it (when the angles are given, ``--pa``);
        otherwise they are left out with a warning
        (`~kpifs.io.angles.known_angle_files`).

    The cube's ``angles`` are the files' ``PARANG`` and its ``detpa``
    ``PARANG + CHARIS_DETPA_OFFSET`` (NaN where ``PARANG`` is unknown).

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> from kpifs.io.layouts import write_observation
    >>> from kpifs.io.charis import read_charis
    >>> tmp = tempfile.TemporaryDirectory()
    >>> d = tmp.name
    >>> files = write_observation(simulate_scene("charis", n_frames=2, npup=32, shape=(64, 64)),
    ...                           d, layout="charis")
    >>> cube = read_charis(files["target"])
    >>> cube.shape, cube.instrument
    ((2, 22, 64, 64), 'charis')
    >>> cube.detpa                                  # PARANG 0 in the simulated files
    <Quantity [113., 113.] deg>
    >>> cube.close()
    >>> tmp.cleanup()
    """
    if isinstance(paths, (str, bytes)) or not hasattr(paths, "__iter__"):
        paths = [paths]
    paths = [str(p) for p in paths]
    if not paths:
        raise KpifsError("no CHARIS files given")
    ps = to_quantity(pixscale if pixscale is not None else CHARIS_PIXSCALE, u.mas,
                     name="pixel scale")
    given = parse_wavelengths(wavelengths, source="CHARIS wavelengths")
    files, data, bad, angles = [], [], [], []
    wl = header = None
    try:
        for path in paths:
            hdul = open_fits(path)
            files.append(hdul)
            if len(hdul) < 2 or hdul[1].data is None or hdul[1].data.ndim != 3:
                raise KpifsError(f"{path}: not a CHARIS pipeline cube (no 3-D cube in HDU 1)")
            cube = hdul[1].data
            if given is not None:
                if len(given) != cube.shape[0]:
                    raise KpifsError(f"{path}: {len(given)} wavelength(s) given but the cube "
                                     f"has {cube.shape[0]} channel(s)")
                _warn_nlam(hdul[0].header, cube.shape[0], path)
                this_wl = given
            else:
                this_wl = charis_wavelengths(hdul[0].header, cube.shape[0], source=path)
            if wl is None:
                wl, header = this_wl, hdul[0].header.copy()
            elif len(this_wl) != len(wl) or not np.allclose(this_wl, wl, rtol=1e-5):
                raise KpifsError(f"{path}: its wavelengths differ from those of {paths[0]}")
            if len(hdul) > 2 and hdul[2].data is not None:
                ivar = hdul[2].data
                if ivar.shape != cube.shape:
                    raise KpifsError(f"{path}: inverse variance {ivar.shape} does not match "
                                     f"the cube {cube.shape}")
                bad.append(_IvarBad(ivar))
            else:
                bad.append(_IvarBad(None, cube.shape))
            data.append(_OneFrame(cube))
            par = hdul[0].header.get("PARANG", "unavailable")
            try:
                angles.append(float(par))
            except (TypeError, ValueError):
                angles.append(np.nan)
            if not np.isfinite(angles[-1]):        # NaN, inf: unknown
                angles[-1] = np.nan
            elif abs(angles[-1]) > 360:
                raise KpifsError(f"{path}: PARANG = {par} is not an angle (deg)")
        keep = (list(range(len(paths))) if keep_unknown_angles
                else known_angle_files(paths, angles, keyword="PARANG"))
        for i in set(range(len(paths))) - set(keep):
            files[i].close()
        paths, files, data, bad = ([x[i] for i in keep] for x in (paths, files, data, bad))
        angles = np.array(angles)[keep]
        cube = IFSCube(data=FrameStack(data, bad), wavelengths=wl, pixscale=ps, header=header,
                       angles=angles * u.deg, detpa=(angles + CHARIS_DETPA_OFFSET) * u.deg,
                       detpa_source=f"PARANG + {CHARIS_DETPA_OFFSET:g} deg",
                       instrument="charis", source=paths, _files=files)
    except BaseException:
        for f in files:
            f.close()
        raise
    if np.any(np.isnan(angles)):
        log.info("PARANG unavailable in %d of %d CHARIS file(s): detector position angle "
                 "unknown (NaN) for those frames", int(np.isnan(angles).sum()), len(angles))
    log.info("read %d CHARIS exposure(s): %d channels %.4f-%.4f um", len(paths), len(wl),
             wl[0].value, wl[-1].value)
    return cube


def _warn_nlam(header, nlam_cube, path):
    """Wavelengths given for a CHARIS cube whose NLAM contradicts it: the header is wrong
    somewhere (a cube from another reduction?); the given wavelengths are used."""
    try:
        nlam = int(header["NLAM"])
    except (KeyError, TypeError, ValueError):
        return
    if nlam != nlam_cube:
        warnings.warn(f"{path}: NLAM = {nlam} in the header but the cube has {nlam_cube} "
                      f"channels: the given wavelengths are used (check they are this "
                      f"cube's)", KpifsWarning, stacklevel=4)


class _OneFrame:
    """A 3-D cube seen as a single frame ``(1, nlam, ny, nx)``."""

    def __init__(self, cube):
        self.cube = cube
        self.shape = (1,) + cube.shape

    def __getitem__(self, key):
        return np.asarray(self.cube[key[1:]])[None] if len(key) > 1 else \
            np.asarray(self.cube)[None]


class _IvarBad(_OneFrame):
    """``ivar == 0`` as a bad-pixel mask, read lazily."""

    def __init__(self, ivar, shape=None):
        self.ivar = ivar
        self.shape = (1,) + (ivar.shape if ivar is not None else shape)

    def __getitem__(self, key):
        if self.ivar is None:
            return np.zeros((1,) + np.empty(self.shape[1:])[key[1:]].shape, bool)
        iv = np.asarray(self.ivar[key[1:]])
        return (~np.isfinite(iv) | (iv <= 0))[None]


def write_charis_exposures(outdir, cube, ivar, wavelengths, pixscale, *, prefix="CRSA",
                           cards=None, overwrite=False, exptime=None, obj="SIMULATED",
                           parang=None):
    """One CHARIS-pipeline ``*_cube.fits`` file per frame; wavelengths must be log-uniform.

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from kpifs.io.charis import write_charis_exposures
    >>> wl = 1.15956 * np.exp(np.arange(3) * 0.03) * u.um
    >>> tmp = tempfile.TemporaryDirectory()
    >>> paths = write_charis_exposures(tmp.name, np.ones((2, 3, 8, 8)),
    ...                                np.ones((2, 3, 8, 8)), wl, 16.2 * u.mas)
    >>> [p.name for p in paths]
    ['CRSA00000000_cube.fits', 'CRSA00000001_cube.fits']
    >>> tmp.cleanup()
    """
    wl_nm = u.Quantity(wavelengths, u.um).to_value(u.nm)
    n = len(wl_nm)
    dlog = np.log(wl_nm[-1] / wl_nm[0]) / (n - 1) if n > 1 else 0.0
    grid = wl_nm[0] * np.exp(np.arange(n) * dlog)
    if not np.allclose(grid, wl_nm, rtol=1e-5):
        raise KpifsError("the CHARIS layout needs log-uniform wavelengths "
                         "(LAM_MIN * exp(i * DLOGLAM)); these are not")
    cube = np.asarray(cube)
    band = "Broadband" if n == 22 else {15: "J", 20: "H", 17: "K"}.get(n, "Broadband")
    paths = []
    outdir = Path(outdir)
    targets = [outdir / f"{prefix}{i:08d}_cube.fits" for i in range(len(cube))]
    for p in targets:  # refuse before writing anything
        check_output_path(p, overwrite=overwrite)
    for i, path in enumerate(targets):
        hdr = simulated_header(cards or {}, instrument="CHARIS", pixscale=pixscale,
                               exptime=exptime, obj=obj)
        hdr["TELESCOP"] = ("Subaru", "telescope")
        hdr["LAM_MIN"] = (float(wl_nm[0]), "[nm] minimum wavelength")
        hdr["LAM_MAX"] = (float(wl_nm[-1]), "[nm] maximum wavelength")
        hdr["DLOGLAM"] = (float(dlog), "log wavelength spacing")
        hdr["NLAM"] = (n, "number of wavelengths")
        hdr["CAL_BAND"] = (band, "band/mode")
        hdr["FILTNAME"] = (band, "filter")
        hdr["MJD"] = (60000.0 + i * 1e-3, "simulated")
        hdr["PARANG"] = (float(parang[i]) if parang is not None else 0.0, "[deg]")
        sci = fits.ImageHDU(np.asarray(cube[i], np.float32), header=hdr.copy())
        sci.header["CTYPE3"] = "AWAV-LOG"
        sci.header["CUNIT3"] = "nm"
        sci.header["CRPIX3"] = 1.0
        sci.header["CRVAL3"] = float(wl_nm[0])
        sci.header["CDELT3"] = float(wl_nm[0] * dlog)
        iv = fits.ImageHDU(np.asarray(ivar[i], np.float32))
        paths.append(write_hdulist(fits.HDUList([fits.PrimaryHDU(header=hdr), sci, iv]), path,
                                   overwrite=overwrite))
    return paths


def charis_field(shape=(201, 201), *, side=133.0, angle=27.0):
    """The CHARIS lenslet array's illuminated field: a square tilted by *angle* deg.

    Approximates the real pipeline's Broadband lenslet flat (a ~133-spaxel
    square turned by ~27 degrees in the 201x201 cube); the simulator blanks its
    ``charis`` scene outside it.

    Examples
    --------
    >>> from kpifs.io.charis import charis_field
    >>> field = charis_field()
    >>> field.shape, bool(field[100, 100]), bool(field[0, 0])
    ((201, 201), True, False)
    """
    ny, nx = shape
    y, x = np.mgrid[:ny, :nx]
    x = x - (nx - 1) / 2
    y = y - (ny - 1) / 2
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    xr, yr = c * x + s * y, -s * x + c * y
    return (np.abs(xr) <= side / 2) & (np.abs(yr) <= side / 2)


#: The simulator's CHARIS scene: 22 broadband channels (1159.56-2369.34 nm,
#: log-uniform), 16.2 mas, the 201x201 cube with its tilted field and 12 dead spaxels.
SCENE = dict(wavelengths=1.15956 * np.exp(np.arange(22) * np.log(2.36934 / 1.15956) / 21) * u.um,
             pixscale=16.2 * u.mas, shape=(201, 201), n_frames=20, instrument="charis",
             field="charis", n_dead=12, contrasts=10 ** (-8 / 2.5) * np.linspace(1.4, 0.6, 22),
             companion_offset=[120.0, 90.0] * u.mas)


def _write(obs, role, outdir, common):
    """`Instrument.write`: one ``*_cube.fits`` per frame in ``outdir/role``."""
    p = obs.params
    cube, var = ((obs.target, obs.variance_target) if role == "target"
                 else (obs.calibrator, obs.variance_calibrator))
    (outdir / role).mkdir(exist_ok=True)
    return write_charis_exposures(outdir / role, cube, 1 / var, p.wavelengths, p.pixscale,
                                  parang=frame_angles(p, len(cube), CHARIS_DETPA_OFFSET),
                                  **common)


def _hint(hdul, path):
    """A header that says CHARIS without the pipeline's wavelength solution."""
    if header_card(hdul[0].header, "INSTRUME") == "CHARIS":
        warnings.warn(f"{path}: the header says CHARIS but has no wavelength solution "
                      f"(LAM_MIN, DLOGLAM, NLAM): read as a plain cube; give the "
                      f"wavelengths (--wavelengths)", KpifsWarning, stacklevel=3)


def _read(paths, *, wavelengths=None, pixscale=None, pa_given=False, **_):
    return read_charis(paths, wavelengths=wavelengths, pixscale=pixscale,
                       keep_unknown_angles=pa_given)


INSTRUMENT = Instrument(
    name="charis", title="SCExAO/CHARIS", identify=is_charis, read=_read, pupil="subaru",
    instrume=("CHARIS",), keywords=("CAL_BAND",), pupils=("subaru", "scexao", "charis"),
    setup=charis_setup, pixscale=f"{CHARIS_PIXSCALE.value:g} mas (--pixscale)",
    angles=f"PARANG + {CHARIS_DETPA_OFFSET:g} deg", layout="charis", write=_write,
    scenes={"charis": SCENE}, hint=_hint, telescop="Subaru", field_mask=charis_field,
    sequence=(CHARIS_DETPA_OFFSET, "maunakea"), data_hdu=1)
