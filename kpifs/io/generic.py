"""Plain FITS cubes: any instrument's images with the wavelengths and pixel scale given.

The reader is `~kpifs.io.cube.read_generic` (one file at a time; several files are
more frames). The simulator's ``plain`` layout writes one 4-D cube per star
(`write_plain_cube`), with the wavelengths in ``KPWL1 ... KPWLn`` (um), ``PIXSCALE``
(mas) and the detector angles in a ``DETPA`` extension: what ``kpifs extract`` reads
without further options. The pupil, when none is given: Subaru's (the seed paper's).
"""
import numpy as np
from astropy import units as u
from astropy.io import fits

from .._utils import write_hdulist
from .cube import read_generic
from .instrument import Instrument, read_each, simulated_header

__all__ = ["write_plain_cube", "INSTRUMENT"]


def write_plain_cube(path, cube, wavelengths, pixscale, *, cards=None, overwrite=False,
                     exptime=None, obj="SIMULATED", detpa=None):
    """Write a 4-D cube ``(nframe, nwave, ny, nx)`` with its wavelengths in the header, and
    the detector position angle of each frame (deg, *detpa*) in a ``DETPA`` extension.

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from kpifs.io.generic import write_plain_cube
    >>> tmp = tempfile.TemporaryDirectory()
    >>> paths = write_plain_cube(tmp.name + "/c.fits", np.zeros((1, 2, 8, 8)),
    ...                          [1.5, 1.6] * u.um, 10 * u.mas)
    >>> paths[0].name
    'c.fits'
    >>> tmp.cleanup()
    """
    wl = u.Quantity(wavelengths, u.um)
    hdr = simulated_header(cards or {}, instrument="generic", pixscale=pixscale,
                           exptime=exptime, obj=obj)
    for i, w in enumerate(wl.value, 1):
        hdr[f"KPWL{i}"] = (float(w), f"[um] wavelength of channel {i}")
    hdus = [fits.PrimaryHDU(np.asarray(cube, np.float32), header=hdr)]
    if detpa is not None:            # what `kpifs.io.angles.header_detpa` reads (issue 37)
        pa = np.broadcast_to(np.asarray(detpa, float), (len(hdus[0].data),))
        hdus.append(fits.ImageHDU(pa, name="DETPA"))
        hdus[1].header["BUNIT"] = ("deg", "detector position angle of each frame")
    return [write_hdulist(fits.HDUList(hdus), path, overwrite=overwrite)]


def _read(paths, *, wavelengths=None, pixscale=None, **_):
    return read_each(lambda p, **kw: read_generic(p, wavelengths=wavelengths,
                                                  pixscale=pixscale))(paths)


def _write(obs, role, outdir, common):
    """`Instrument.write`: one 4-D cube per star, ``target.fits`` or ``calibrator.fits``."""
    p = obs.params
    cube = obs.target if role == "target" else obs.calibrator
    return write_plain_cube(outdir / f"{role}.fits", cube, p.wavelengths, p.pixscale,
                            detpa=p.detpa, **common)


INSTRUMENT = Instrument(
    name="generic", title="plain FITS cube", identify=lambda hdul: True, read=_read,
    pupil="subaru", pixscale="PIXSCALE card (mas) or --pixscale",
    angles="DETPA extension or card (deg), else 0 (North up)", layout="plain", write=_write)
