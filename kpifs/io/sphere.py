"""Reader for VLT/SPHERE-IFS cubes.

Community-pipeline products: ``(nwave, nframe, ny, nx)`` (or ``(nwave, ny, nx)``)
with the wavelengths in a separate file (nm) and frame angles in another.
SPHERE Data Center products (``HIERARCH ESO PRO REC1 ID = 'sph_ifs_science_dr'``)
have the same layout but wavelengths in um and angles of the opposite sign.
The cube is kept memory-mapped and viewed as ``(nframe, nwave, ny, nx)``.

Sky orientation: the detector position angle of a frame is ``DETPA = angle +
SPHERE_DETPA_OFFSET`` (33.76 deg) with the frame's parallactic angle from the angle
file: the pupil offset in pupil-tracking mode, the IFS offset and the true-North
correction of Maire et al. (2016, SPIE 9908, 990834), combined as vlt-sphere's
``toolbox.compute_angles`` combines them into its derotation angle (``DEROT ANGLE =
PARANG + 135.99 - 100.48 - 1.75`` for ``INS4 DROT2 MODE = ELEV``), which is the
DETPA. Assumed: the angle file holds parallactic angles (check them against the raw
frames' ``HIERARCH ESO TEL PARANG START``/``END``). A file of derotation angles
(vlt-sphere's ``DEROT ANGLE``) goes to ``--pa``, to which no offset is added; Data
Center products carry the opposite sign, inverted here (docs: "Reading cubes").
"""
import logging
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.io import fits

from .._utils import check_output_path, to_quantity, write_hdulist
from ..exceptions import KpifsError, MissingInformation
from .cube import IFSCube, open_fits
from .instrument import Instrument, frame_angles, read_each, simulated_header
from .wavelengths import parse_wavelengths, read_wavelength_file

__all__ = ["read_sphere", "is_sphere", "sphere_setup", "SPHERE_PIXSCALE", "SPHERE_DETPA_OFFSET",
           "SPHERE_PUPIL_OFFSET", "SPHERE_IFS_OFFSET", "SPHERE_TRUE_NORTH", "write_sphere_cube",
           "INSTRUMENT"]

log = logging.getLogger(__name__)

#: SPHERE-IFS spaxel scale.
SPHERE_PIXSCALE = 7.46 * u.mas

#: Pupil offset in pupil-tracking ('ELEV') mode (deg, +135.99 +- 0.11; Maire et al. 2016).
SPHERE_PUPIL_OFFSET = 135.99
#: IFS instrument offset (deg, -100.48 +- 0.10).
SPHERE_IFS_OFFSET = -100.48
#: True-north correction (deg, -1.75 +- 0.08).
SPHERE_TRUE_NORTH = -1.75
#: Detector position angle minus the angle file's parallactic angle (deg): see the
#: module docstring.
SPHERE_DETPA_OFFSET = SPHERE_PUPIL_OFFSET + SPHERE_IFS_OFFSET + SPHERE_TRUE_NORTH

_WAVE_NAMES = ("wavelength.fits", "wavelengths.fits", "lambda.fits")


def _is_dc(header):
    return str(header.get("HIERARCH ESO PRO REC1 ID", "")).strip() == "sph_ifs_science_dr"


def sphere_setup(header):
    """What a SPHERE-IFS target's and calibrator's cubes must share: the mode (``ESO INS2
    COMB IFS``: ``OBS_YJ`` or ``OBS_H``), when the header has it.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.sphere import sphere_setup
    >>> sphere_setup(fits.Header({"HIERARCH ESO INS2 COMB IFS": "OBS_YJ"}))
    {'mode': 'OBS_YJ'}
    """
    mode = str(header.get("HIERARCH ESO INS2 COMB IFS", "") or "").strip().upper()
    return {"mode": mode} if mode else {}


def is_sphere(hdul):
    """True when the header says SPHERE-IFS (or the SPHERE Data Center).

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.sphere import is_sphere
    >>> hdul = fits.HDUList([fits.PrimaryHDU()])
    >>> hdul[0].header["HIERARCH ESO SEQ ARM"] = "IFS"
    >>> is_sphere(hdul)
    True
    """
    hdr = hdul[0].header
    return (_is_dc(hdr) or str(hdr.get("INSTRUME", "")).strip().upper() == "SPHERE"
            or str(hdr.get("HIERARCH ESO SEQ ARM", "")).strip().upper() == "IFS")


def _find_wavelengths(path, hdr, nwave, wavelengths):
    if wavelengths is not None:
        return parse_wavelengths(wavelengths, unit="um" if _is_dc(hdr) else None,
                                 source=f"{path}: wavelengths")
    for name in _WAVE_NAMES:
        cand = Path(path).with_name(name)
        if cand.exists():
            log.info("%s: wavelengths from %s", path, cand)
            return read_wavelength_file(cand, unit="um" if _is_dc(hdr) else None)
    lmin = hdr.get("HIERARCH ESO DRS IFS MIN LAMBDA")
    lmax = hdr.get("HIERARCH ESO DRS IFS MAX LAMBDA")
    if lmin is not None and lmax is not None:
        log.info("%s: wavelengths spread linearly between the DRS limits", path)
        return np.linspace(float(lmin), float(lmax), nwave) * u.um
    raise MissingInformation(f"{path}: no wavelengths: give a wavelength file (--wavelengths "
                             f"wavelength.fits) or put one named wavelength.fits beside the "
                             f"cube")


def read_sphere(path, *, wavelengths=None, pixscale=None, angles=None):
    """Read a SPHERE-IFS cube as an `~kpifs.io.IFSCube`.

    Parameters
    ----------
    path : str
        ``(nwave, nframe, ny, nx)`` or ``(nwave, ny, nx)`` FITS cube.
    wavelengths : str, array or `~astropy.units.Quantity`, optional
        Any form `~kpifs.io.parse_wavelengths` accepts: a wavelength file
        (FITS or text), a list such as ``"1.5um,1.6um"`` or values; nm and um
        are told apart from the values (or the header). Default: ``wavelength.fits`` beside
        the cube, else the DRS limits in the header.
    pixscale : `~astropy.units.Quantity`, optional
        Default `SPHERE_PIXSCALE` (7.46 mas).
    angles : str or array, optional
        Frame angles (deg), or a FITS file of them; default
        ``parallactic_angles.fits`` beside the cube when present. Data Center
        angles are sign-inverted to the community convention. The detector
        position angles are ``angles + SPHERE_DETPA_OFFSET`` (NaN without an
        angle file).

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.io import read_sphere, write_observation
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> obs = simulate_scene("sphere", n_frames=2, npup=32, shape=(32, 32))
    >>> tmp = tempfile.TemporaryDirectory()
    >>> files = write_observation(obs, tmp.name, layout="sphere")
    >>> with read_sphere(files["target"][0]) as cube:   # wavelength.fits is found beside it
    ...     print(cube.shape, f"{cube.wavelengths[0]:.3f}")
    (2, 39, 32, 32) 0.957 um
    >>> tmp.cleanup()
    """
    hdul = open_fits(path)
    try:
        hdu = next((h for h in hdul if h.data is not None and h.is_image), None)
        if hdu is None:
            raise KpifsError(f"{path}: no image data")
        data = hdu.data
        hdr = hdul[0].header.copy()
        if data.ndim == 3:
            view = data[None]                      # (1, nwave, ny, nx)
        elif data.ndim == 4:
            view = np.swapaxes(data, 0, 1)         # (nframe, nwave, ny, nx), still a memmap
        else:
            raise KpifsError(f"{path}: SPHERE-IFS cubes are 3-D (nwave, y, x) or 4-D (nwave, "
                             f"nframe, y, x); this one has {data.ndim} dimension(s)")
        nwave = view.shape[1]
        wl = _find_wavelengths(path, hdr, nwave, wavelengths)
        if len(wl) != nwave:
            raise KpifsError(f"{path}: {len(wl)} wavelengths for {nwave} channels")
        ps = to_quantity(pixscale if pixscale is not None else SPHERE_PIXSCALE, u.mas,
                         name="pixel scale")
        ang = _angles(path, angles, view.shape[0], _is_dc(hdr))
        if ang is None:
            log.info("%s: no angle file: detector position angles unknown", path)
            detpa, where = np.full(view.shape[0], np.nan) * u.deg, "none (unknown)"
        else:
            detpa = ang + SPHERE_DETPA_OFFSET * u.deg
            where = f"angle file + {SPHERE_DETPA_OFFSET:.2f} deg"
        cube = IFSCube(data=view, wavelengths=wl, pixscale=ps, header=hdr, angles=ang,
                       detpa=detpa, detpa_source=where, instrument="sphere",
                       source=[str(path)], _files=[hdul])
    except BaseException:
        hdul.close()
        raise
    log.info("read SPHERE-IFS cube %s: %d frame(s), %d channels %.4f-%.4f um%s", path,
             view.shape[0], nwave, wl[0].value, wl[-1].value,
             " (Data Center product)" if _is_dc(hdr) else "")
    return cube


def _angles(path, angles, nframe, dc):
    if angles is None:
        cand = Path(path).with_name("parallactic_angles.fits")
        if not cand.exists():
            return None
        angles = cand
    if isinstance(angles, (str, Path)):
        try:
            angles = np.ravel(fits.getdata(angles)).astype(float)
        except (OSError, TypeError) as exc:
            raise KpifsError(f"{angles}: cannot read frame angles: {exc}") from None
    ang = np.atleast_1d(np.asarray(u.Quantity(angles, u.deg).value, float))
    if ang.size != nframe:
        raise KpifsError(f"{path}: {ang.size} frame angles for {nframe} frame(s)")
    return (-ang if dc else ang) * u.deg


def write_sphere_cube(outdir, cube, wavelengths, pixscale, *, prefix="", cards=None,
                      overwrite=False, exptime=None, obj="SIMULATED", angles=None):
    """SPHERE-IFS community-pipeline layout: wave-first 4-D cube plus wavelength file (nm).

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from kpifs.io.sphere import write_sphere_cube
    >>> tmp = tempfile.TemporaryDirectory()
    >>> paths = write_sphere_cube(tmp.name, np.ones((2, 3, 8, 8)),
    ...                           [1.0, 1.1, 1.2] * u.um, 7.46 * u.mas)
    >>> [p.name for p in paths]
    ['science_cube.fits', 'wavelength.fits', 'parallactic_angles.fits']
    >>> tmp.cleanup()
    """
    outdir = Path(outdir)
    cube = np.asarray(cube)
    names = [outdir / f"{prefix}science_cube.fits", outdir / f"{prefix}wavelength.fits",
             outdir / f"{prefix}parallactic_angles.fits"]
    for p in names:
        check_output_path(p, overwrite=overwrite)
    hdr = simulated_header(cards or {}, instrument="SPHERE", pixscale=pixscale,
                           exptime=exptime, obj=obj)
    hdr["BUNIT"] = "ADU"
    data = np.ascontiguousarray(np.swapaxes(cube, 0, 1), np.float32)
    wl = u.Quantity(wavelengths, u.um).to_value(u.nm)
    ang = np.zeros(len(cube)) if angles is None else np.asarray(angles, float)
    return [write_hdulist(fits.HDUList([fits.PrimaryHDU(data, header=hdr)]), names[0],
                          overwrite=overwrite),
            write_hdulist(fits.HDUList([fits.PrimaryHDU(wl)]), names[1], overwrite=overwrite),
            write_hdulist(fits.HDUList([fits.PrimaryHDU(ang)]), names[2], overwrite=overwrite)]


def _write(obs, role, outdir, common):
    """`Instrument.write`: the community pipeline's three files in ``outdir/role``."""
    p = obs.params
    cube = obs.target if role == "target" else obs.calibrator
    (outdir / role).mkdir(exist_ok=True)
    return write_sphere_cube(outdir / role, cube, p.wavelengths, p.pixscale,
                             angles=frame_angles(p, len(cube), SPHERE_DETPA_OFFSET), **common)


def _read(paths, *, wavelengths=None, pixscale=None, angles=None, **_):
    return read_each(lambda p, **kw: read_sphere(p, wavelengths=wavelengths, pixscale=pixscale,
                                                 angles=angles))(paths)


#: The simulator's SPHERE scenes: ``sphere``, 39 IFS YJ channels (0.957-1.329 um),
#: 7.46 mas, VLT pupil; ``sphere-yjh`` (issue 39), the same in YJH (39 channels over
#: 0.957-1.636 um, a factor of 1.7 in lambda); ``sphere-sam`` (issue 28), the 7-hole SAM
#: mask behind the IFS (YJ, 50 nm of residual wavefront), a companion of 2 % brighter in
#: the blue at (60, -40) mas, in plain cubes.
SCENES = {"sphere": dict(telescope="vlt", wavelengths=np.linspace(0.957, 1.329, 39) * u.um,
                         pixscale=7.46 * u.mas, shape=(64, 64), n_frames=20, instrument="sphere",
                         contrasts=10 ** (-8 / 2.5) * np.linspace(1.3, 0.7, 39),
                         companion_offset=[80.0, 60.0] * u.mas)}
SCENES["sphere-yjh"] = dict(SCENES["sphere"], wavelengths=np.linspace(0.957, 1.636, 39) * u.um)
SCENES["sphere-sam"] = dict(telescope="sphere_sam7",
                            wavelengths=np.linspace(0.957, 1.329, 39) * u.um,
                            pixscale=7.46 * u.mas, shape=(64, 64), n_frames=20,
                            wavefront_rms=50 * u.nm,
                            contrasts=2e-2 * np.linspace(1.3, 0.7, 39),
                            companion_offset=[60.0, -40.0] * u.mas)


def _to_file(source, block, shape):
    """A block of the cube in a SPHERE cube's wave-first order, ``(nwave, nframe, ny,
    nx)`` or ``(nwave, ny, nx)``."""
    return np.swapaxes(block, 0, 1).reshape(shape)


INSTRUMENT = Instrument(
    name="sphere", title="VLT/SPHERE-IFS", identify=is_sphere, read=_read, pupil="vlt",
    instrume=("SPHERE",), keywords=("HIERARCH ESO INS2 COMB IFS",),
    pupils=("vlt", "sphere", "sphere_sam7"), setup=sphere_setup,
    pixscale=f"{SPHERE_PIXSCALE.value:g} mas (--pixscale)",
    angles=f"angle file + {SPHERE_DETPA_OFFSET:.2f} deg", layout="sphere", write=_write,
    scenes=SCENES, telescop="ESO-VLT-U3", data_ndim=3, to_file=_to_file,
    sequence=(33.76, "paranal"),      # SPHERE_DETPA_OFFSET to 0.01 deg
    copy_note="a SPHERE-IFS cube: its wavelengths and frame angles are in the files beside")
