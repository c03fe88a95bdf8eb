"""Write cubes in the instruments' on-disk layouts (used for simulated data).

- ``plain``: one FITS file, primary HDU a float32 cube ``(nframe, nwave, ny, nx)``
  with the wavelengths in cards ``KPWL1 ... KPWLn`` (um) and ``PIXSCALE`` (mas),
  and, for a scene with detector angles, a ``DETPA`` extension (deg, one per
  frame); what ``kpifs extract`` reads without further options.
- ``charis``: one file per exposure, as the CHARIS data-reduction pipeline
  writes them: HDU 0 header only, HDU 1 the cube ``(nlam, ny, nx)``, HDU 2 its
  inverse variance; ``LAM_MIN``, ``LAM_MAX`` (nm), ``DLOGLAM``, ``NLAM``,
  ``CAL_BAND``, ``PARANG`` and a log-wavelength third WCS axis.
- ``sphere``: as the community SPHERE-IFS pipeline: ``science_cube.fits`` of
  shape ``(nwave, nframe, ny, nx)``, ``wavelength.fits`` (nm) and
  ``parallactic_angles.fits`` (deg).
- ``jwst``, ``gpi``: JWST ``*_calints.fits`` (one file per detector angle: a
  rotating sequence is several exposures) and GPI ``*_spdc.fits``
  (`kpifs.io.layouts_instruments`).
"""
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.io import fits

from .._meta import VERSION
from .._utils import check_output_path, write_hdulist
from .._utils import canonical_name
from ..exceptions import KpifsError
from .charis import CHARIS_DETPA_OFFSET
from .layouts_instruments import write_gpi_exposures, write_jwst_calints
from .sphere import SPHERE_DETPA_OFFSET

__all__ = ["write_plain_cube", "write_charis_exposures", "write_sphere_cube",
           "write_observation", "LAYOUTS"]

LAYOUTS = ("plain", "charis", "sphere", "jwst", "gpi")


def _base_header(cards, *, instrument, pixscale, exptime=None, obj="SIMULATED"):
    hdr = fits.Header()
    hdr["OBJECT"] = (obj, "target name")
    hdr["INSTRUME"] = (instrument.upper(), "instrument")
    hdr["PIXSCALE"] = (float(pixscale.to_value(u.mas)), "[mas] pixel scale")
    if exptime is not None:
        hdr["EXPTIME"] = (float(exptime.to_value(u.s)), "[s] exposure time")
    for key, val in cards.items():
        hdr[key] = val
    hdr["KPIFSVER"] = (VERSION, "kpifs version")
    hdr.add_history(f"simulated by kpifs {VERSION}")
    return hdr


def write_plain_cube(path, cube, wavelengths, pixscale, *, cards=None, overwrite=False,
                     exptime=None, obj="SIMULATED", detpa=None):
    """Write a 4-D cube ``(nframe, nwave, ny, nx)`` with its wavelengths in the header, and
    the detector position angle of each frame (deg, *detpa*) in a ``DETPA`` extension.

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from kpifs.io.layouts import write_plain_cube
    >>> tmp = tempfile.TemporaryDirectory()
    >>> paths = write_plain_cube(tmp.name + "/c.fits", np.zeros((1, 2, 8, 8)),
    ...                          [1.5, 1.6] * u.um, 10 * u.mas)
    >>> paths[0].name
    'c.fits'
    >>> tmp.cleanup()
    """
    wl = u.Quantity(wavelengths, u.um)
    hdr = _base_header(cards or {}, instrument="generic", pixscale=pixscale, exptime=exptime,
                       obj=obj)
    for i, w in enumerate(wl.value, 1):
        hdr[f"KPWL{i}"] = (float(w), f"[um] wavelength of channel {i}")
    hdus = [fits.PrimaryHDU(np.asarray(cube, np.float32), header=hdr)]
    if detpa is not None:            # what `kpifs.io.angles.header_detpa` reads (issue 37)
        pa = np.broadcast_to(np.asarray(detpa, float), (len(hdus[0].data),))
        hdus.append(fits.ImageHDU(pa, name="DETPA"))
        hdus[1].header["BUNIT"] = ("deg", "detector position angle of each frame")
    return [write_hdulist(fits.HDUList(hdus), path, overwrite=overwrite)]


def write_charis_exposures(outdir, cube, ivar, wavelengths, pixscale, *, prefix="CRSA",
                           cards=None, overwrite=False, exptime=None, obj="SIMULATED",
                           parang=None):
    """One CHARIS-pipeline ``*_cube.fits`` file per frame; wavelengths must be log-uniform.

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from kpifs.io.layouts import write_charis_exposures
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
        hdr = _base_header(cards or {}, instrument="CHARIS", pixscale=pixscale,
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


def write_sphere_cube(outdir, cube, wavelengths, pixscale, *, prefix="", cards=None,
                      overwrite=False, exptime=None, obj="SIMULATED", angles=None):
    """SPHERE-IFS community-pipeline layout: wave-first 4-D cube plus wavelength file (nm).

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from kpifs.io.layouts import write_sphere_cube
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
    hdr = _base_header(cards or {}, instrument="SPHERE", pixscale=pixscale, exptime=exptime,
                       obj=obj)
    hdr["BUNIT"] = "ADU"
    data = np.ascontiguousarray(np.swapaxes(cube, 0, 1), np.float32)
    wl = u.Quantity(wavelengths, u.um).to_value(u.nm)
    ang = np.zeros(len(cube)) if angles is None else np.asarray(angles, float)
    return [write_hdulist(fits.HDUList([fits.PrimaryHDU(data, header=hdr)]), names[0],
                          overwrite=overwrite),
            write_hdulist(fits.HDUList([fits.PrimaryHDU(wl)]), names[1], overwrite=overwrite),
            write_hdulist(fits.HDUList([fits.PrimaryHDU(ang)]), names[2], overwrite=overwrite)]


def write_observation(obs, outdir, *, layout="plain", overwrite=False):
    """Write a `~kpifs.simulation.simulate.SimulatedObservation` (target and calibrator)
    to *outdir*.

    Returns a dict ``{"target": [paths], "calibrator": [paths]}``.

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.io import write_observation
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> tmp = tempfile.TemporaryDirectory()
    >>> files = write_observation(simulate_scene("paper", n_frames=1, npup=32), tmp.name)
    >>> [p.name for p in files["target"]]
    ['target.fits']
    >>> tmp.cleanup()
    """
    if layout not in LAYOUTS:
        raise KpifsError(f"unknown layout {layout!r}: use one of {LAYOUTS}")
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise KpifsError(f"{outdir}: exists and is not a directory")
    outdir.mkdir(parents=True, exist_ok=True)
    p = obs.params
    out = {}
    for role, cube, var in (("target", obs.target, obs.variance_target),
                            ("calibrator", obs.calibrator, obs.variance_calibrator)):
        cards = dict(obs.truth) if role == "target" else {"KPSIMSEE": obs.truth["KPSIMSEE"]}
        cards["KPSIMROL"] = (role, "simulated target or calibrator")
        obj = "SIM-TARGET" if role == "target" else "SIM-CALIB"
        common = dict(cards=cards, overwrite=overwrite, exptime=p.exptime, obj=obj)
        if layout == "plain":
            out[role] = write_plain_cube(outdir / f"{role}.fits", cube, p.wavelengths,
                                         p.pixscale, detpa=p.detpa, **common)
        elif layout == "charis":
            (outdir / role).mkdir(exist_ok=True)
            out[role] = write_charis_exposures(outdir / role, cube, 1 / var, p.wavelengths,
                                               p.pixscale, parang=_angles(p, len(cube),
                                                                          CHARIS_DETPA_OFFSET),
                                               **common)
        elif layout in ("jwst", "gpi"):
            out[role] = _write_instrument(layout, obs, role, cube, var, outdir, common)
        else:
            (outdir / role).mkdir(exist_ok=True)
            out[role] = write_sphere_cube(outdir / role, cube, p.wavelengths, p.pixscale,
                                          angles=_angles(p, len(cube), SPHERE_DETPA_OFFSET),
                                          **common)
    return out


def _angles(params, nframe, offset):
    """The instrument's angle of each frame (its DETPA minus *offset*), or None (issue 29)."""
    if params.detpa is None:
        return None
    return np.broadcast_to(np.asarray(params.detpa, float), (nframe,)) - offset


def _write_instrument(layout, obs, role, cube, var, outdir, common):
    """The JWST and GPI layouts (`kpifs.io.layouts_instruments`)."""
    p = obs.params
    telescope = canonical_name(p.telescope)
    if layout == "gpi":
        (outdir / role).mkdir(exist_ok=True)
        mode = "NRM_H" if telescope == "gpi_nrm" else "H_direct"
        return write_gpi_exposures(outdir / role, cube, var, p.wavelengths, p.pixscale,
                                   detpa=p.detpa, obsmode=mode, **common)
    if len(p.wavelengths) != 1:
        raise KpifsError("the JWST layout writes one filter per file: simulate one "
                         "wavelength")
    inst = "NIRCAM" if "nircam" in str(p.instrument).lower() else "NIRISS"
    pupil = "NRM" if telescope == "niriss_nrm" else None
    det = "nis" if inst == "NIRISS" else ("nrca1" if p.pixscale.to_value(u.mas) < 45
                                          else "nrcalong")
    # one file per detector angle: ROLL_REF is one per exposure (issue 37: a rotating
    # sequence was written with its mean angle)
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
