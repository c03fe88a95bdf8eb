"""Keck/NIRC2 imaging: the ground's most used kernel-phase camera.

Files as the Keck archive serves them (``n0001.fits`` ...): the primary HDU a
2-D image ``(ny, nx)`` (one frame), or a stack ``(nframe, ny, nx)`` of frames of
one pointing; several files are more frames. One channel: the filter's.

- Recognition: ``INSTRUME`` (or ``CURRINST``) ``NIRC2``.
- Wavelength: the filter in the inner or outer wheel (``FWINAME``/``FWONAME``,
  else ``FILTER`` = ``'Kp + clear'``), central wavelength and width from the
  Keck NIRC2 filter page (`NIRC2_FILTERS`; broad-band values are the
  manufacturer's, narrow-band ones measured cold).
- Pixel scale: narrow camera (``CAMNAME``) 9.952 mas before the servicing of
  2015 April 13 (Yelda et al. 2010, ApJ 725, 331) and 9.971 mas after (Service
  et al. 2016, PASP 128, 095004), by ``DATE-OBS``; the medium and wide cameras
  need ``--pixscale``.
- Sky orientation (the relation pyKLIP and the Keck astrometry papers use):
  ``ROTMODE = 'vertical angle'`` (pupil tracking): ``DETPA = PARANG + ROTPOSN -
  INSTANGL + NORTH``; ``'position angle'`` (field tracking): ``DETPA = ROTPOSN -
  INSTANGL + NORTH``; with the narrow camera's North offset ``NORTH`` = -0.252 deg
  (Yelda et al. 2010) before 2015 April 13 and -0.262 deg after (Service et al.
  2016); 0 for the other cameras (not measured there). At ``DETPA = 0`` North is
  up and East left. A ``'stationary'`` rotator (or a missing card) leaves the
  angle unknown (NaN; give ``--pa``). Assumed: ``PARANG`` is the parallactic
  angle at the frame's start (a frame's exposure smears it). Check it on a known
  binary, or against the archive's ``ROTNORTH`` when it is present.
- Pupil (``PMSNAME``, the pupil-stop wheel): ``largehex``, ``open`` and ``clear``
  are read with the Keck primary (``keck``: 36 hexagonal segments, the built-in
  model). Assumed: the largehex stop passes the primary's hexagonal outline (its
  own edge and spider covers are not modelled; a pupil image given with
  ``--pupil`` replaces the model). Any other stop (the 9-hole and 18-hole masks,
  the circular stops) is no pupil kpifs models: a warning asks for ``--pupil``.
"""
import logging
import re
import warnings
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.io import fits

from .._utils import check_output_path, to_quantity, write_hdulist
from ..exceptions import KpifsError, KpifsWarning, MissingInformation
from .cube import IFSCube, open_fits
from .instrument import Instrument, header_card, read_each, simulated_header
from .wavelengths import parse_wavelengths

__all__ = ["read_nirc2", "is_nirc2", "nirc2_filter", "nirc2_pupil", "nirc2_detpa",
           "nirc2_pixscale", "nirc2_setup", "write_nirc2_frames", "NIRC2_FILTERS",
           "NIRC2_NARROW_PIXSCALE", "NIRC2_NORTH", "NIRC2_SERVICING", "INSTRUMENT"]

log = logging.getLogger(__name__)

#: Date of the NIRC2 servicing that changed the narrow camera's scale and North offset.
NIRC2_SERVICING = "2015-04-13"
#: Narrow-camera pixel scale (mas) before and after `NIRC2_SERVICING` (Yelda et al. 2010;
#: Service et al. 2016).
NIRC2_NARROW_PIXSCALE = (9.952, 9.971)
#: Narrow-camera North offset (deg) added to ``ROTPOSN - INSTANGL`` before and after
#: `NIRC2_SERVICING` (Yelda et al. 2010; Service et al. 2016).
NIRC2_NORTH = (-0.252, -0.262)

#: Central wavelength and width (um) by filter (Keck NIRC2 filter page), keys in
#: lower case without spaces or punctuation.
NIRC2_FILTERS = {
    "j": (1.248, 0.163), "h": (1.633, 0.296), "k": (2.196, 0.336), "ks": (2.146, 0.311),
    "kp": (2.124, 0.351), "lp": (3.776, 0.700), "ms": (4.670, 0.241),
    "jcont": (1.2132, 0.0198), "pabeta": (1.2903, 0.0193), "hcont": (1.5804, 0.0232),
    "ch4s": (1.5923, 0.1257), "feii": (1.6455, 0.0256), "ch4l": (1.6809, 0.1368),
    "heib": (2.0563, 0.0326), "brgamma": (2.1686, 0.0326), "h2v10": (2.1281, 0.0342),
    "h2v21": (2.2622, 0.0388), "kcont": (2.2706, 0.0296), "co": (2.2891, 0.0267),
    "brgamma2": (2.1603, 0.0354), "h2o": (3.0629, 0.1549), "pah": (3.2904, 0.0555),
}

#: Pupil stops (``PMSNAME``) read with the Keck primary.
_KECK_STOPS = ("largehex", "open", "clear")
_EMPTY = ("", "clear", "open", "home", "block")        # a wheel position with no filter
#: ROTPOSN and INSTANGL written in simulated files (deg): away from 0, so that each
#: term's sign shows in the position found on the sky.
_SIM_ROTPOSN, _SIM_INSTANGL = 4.0, 0.7


def _key(name):
    return re.sub(r"[^a-z0-9]", "", str(name).lower())


def is_nirc2(hdul):
    """True for a Keck/NIRC2 file (``INSTRUME`` or ``CURRINST`` ``NIRC2``).

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.nirc2 import is_nirc2
    >>> is_nirc2(fits.HDUList([fits.PrimaryHDU(header=fits.Header({"INSTRUME": "NIRC2"}))]))
    True
    """
    hdr = hdul[0].header
    return "NIRC2" in (header_card(hdr, "INSTRUME"), header_card(hdr, "CURRINST"))


def _after_servicing(header):
    date = str(header.get("DATE-OBS", "") or "").strip()
    if not re.match(r"\d{4}-\d{2}-\d{2}", date):
        log.info("NIRC2: no DATE-OBS: the values after %s are used", NIRC2_SERVICING)
        return True
    return date[:10] >= NIRC2_SERVICING


def nirc2_filter(header):
    """``(name, (wavelength, width) or None)``: the filter a NIRC2 header names.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.nirc2 import nirc2_filter
    >>> nirc2_filter(fits.Header({"FWINAME": "Kp", "FWONAME": "clear"}))
    ('Kp', (2.124, 0.351))
    >>> nirc2_filter(fits.Header({"FILTER": "clear + Lp"}))
    ('Lp', (3.776, 0.7))
    """
    names = [str(header.get(k, "") or "").strip() for k in ("FWINAME", "FWONAME")]
    if not any(names):
        names = [s.strip() for s in str(header.get("FILTER", "") or "").split("+")]
    names = [n for n in names if _key(n) not in _EMPTY]
    if not names:
        return "", None
    return names[0], NIRC2_FILTERS.get(_key(names[0]))


def nirc2_pupil(header):
    """The built-in pupil of a NIRC2 header's pupil stop (``PMSNAME``), or None.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.nirc2 import nirc2_pupil
    >>> nirc2_pupil(fits.Header({"PMSNAME": "largehex"})), nirc2_pupil(fits.Header())
    ('keck', 'keck')
    >>> nirc2_pupil(fits.Header({"PMSNAME": "9holeMsk"})) is None
    True
    """
    stop = _key(header.get("PMSNAME", "") or "")
    return "keck" if stop in _KECK_STOPS + ("",) else None


def nirc2_pixscale(header, *, source="NIRC2 file"):
    """The pixel scale (mas) of a NIRC2 header's camera and date.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.nirc2 import nirc2_pixscale
    >>> nirc2_pixscale(fits.Header({"CAMNAME": "narrow", "DATE-OBS": "2012-05-01"}))
    9.952
    """
    camera = _key(header.get("CAMNAME", "") or "")
    if camera != "narrow":
        raise MissingInformation(f"{source}: CAMNAME {camera or '(missing)'!r}: kpifs knows "
                                 f"the narrow camera's pixel scale only: give --pixscale")
    return NIRC2_NARROW_PIXSCALE[_after_servicing(header)]


def nirc2_detpa(header, *, source="NIRC2 file"):
    """``(DETPA in deg, how)`` from ``ROTMODE``, ``PARANG``, ``ROTPOSN`` and ``INSTANGL``
    (NaN when the rotator mode or a card leaves it unknown).

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.nirc2 import nirc2_detpa
    >>> hdr = fits.Header({"ROTMODE": "vertical angle", "PARANG": 30.0, "ROTPOSN": 4.0,
    ...                    "INSTANGL": 0.7, "CAMNAME": "narrow", "DATE-OBS": "2019-06-01"})
    >>> round(nirc2_detpa(hdr)[0], 3)
    33.038
    """
    mode = str(header.get("ROTMODE", "") or "").strip().lower()
    keys = {"vertical angle": ("PARANG", "ROTPOSN", "INSTANGL"),
            "position angle": ("ROTPOSN", "INSTANGL")}.get(mode)
    if keys is None:
        return np.nan, f"none (ROTMODE {mode or 'missing'!r})"
    try:
        values = [float(header[k]) for k in keys]
    except (KeyError, TypeError, ValueError):
        return np.nan, f"none ({', '.join(keys)} not all numbers)"
    if not np.all(np.isfinite(values)):
        return np.nan, f"none ({', '.join(keys)} not finite)"
    if any(abs(v) > 360 for v in values):
        raise KpifsError(f"{source}: {', '.join(keys)} = {values}: not angles (deg)")
    north = (NIRC2_NORTH[_after_servicing(header)]
             if _key(header.get("CAMNAME", "")) == "narrow" else 0.0)
    detpa = sum(values[:-1]) - values[-1] + north
    return float(detpa), (f"{' + '.join(keys[:-1])} - INSTANGL {'-' if north < 0 else '+'} "
                          f"{abs(north):g} deg")


def nirc2_setup(header):
    """What a NIRC2 target's and calibrator's frames must share: filter, camera and pupil
    stop, as the header says.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.nirc2 import nirc2_setup
    >>> nirc2_setup(fits.Header({"FILTER": "Kp + clear", "CAMNAME": "narrow",
    ...                          "PMSNAME": "largehex"}))
    {'filter': 'Kp', 'camera': 'NARROW', 'pupil stop': 'LARGEHEX'}
    """
    out = {}
    name, _ = nirc2_filter(header)
    if name:
        out["filter"] = name
    for key, what in (("CAMNAME", "camera"), ("PMSNAME", "pupil stop")):
        if header_card(header, key):
            out[what] = header_card(header, key)
    return out


def _wavelengths(header, wavelengths, path):
    if wavelengths is not None:
        return parse_wavelengths(wavelengths, source=f"{path}: wavelengths"), None
    name, found = nirc2_filter(header)
    if found is None:
        raise MissingInformation(f"{path}: NIRC2 filter {name or '(none named)'!r} is not in "
                                 f"kpifs's table: give --wavelengths")
    return [found[0]] * u.um, (name, found[1])


def _read_one(path, *, wavelengths=None, pixscale=None, **_):
    hdul = open_fits(path)
    try:
        hdr = hdul[0].header
        data = hdul[0].data
        if data is None or data.ndim not in (2, 3):
            raise KpifsError(f"{path}: a NIRC2 file holds an image (ny, nx) or a stack "
                             f"(nframe, ny, nx) in its primary HDU, got "
                             f"{None if data is None else data.shape}")
        view = data[None, None] if data.ndim == 2 else data[:, None]
        wl, band = _wavelengths(hdr, wavelengths, path)
        if len(wl) != 1:
            raise KpifsError(f"{path}: NIRC2 images have one channel: {len(wl)} wavelengths "
                             f"given")
        ps = (to_quantity(pixscale, u.mas, name="pixel scale") if pixscale is not None
              else nirc2_pixscale(hdr, source=path) * u.mas)
        if nirc2_pupil(hdr) is None:
            warnings.warn(f"{path}: PMSNAME {hdr.get('PMSNAME')!r} is no pupil kpifs models "
                          f"(largehex, open): give the pupil (--pupil, e.g. a pupil image "
                          f"FITS); the Keck primary is used otherwise", KpifsWarning,
                          stacklevel=4)
        detpa, how = nirc2_detpa(hdr, source=path)
        header = hdr.copy()
        if band is not None:
            header["KPFILTER"] = (band[0], "filter kpifs read (FWINAME/FWONAME)")
            header["KPBWIDTH"] = (band[1], "[um] filter width (Keck NIRC2 page)")
        cube = IFSCube(data=view, wavelengths=wl, pixscale=ps, header=header,
                       detpa=np.full(view.shape[0], detpa) * u.deg, detpa_source=how,
                       instrument="nirc2", source=[str(path)], _files=[hdul])
    except BaseException:
        hdul.close()
        raise
    log.info("%s: NIRC2 %s, %d frame(s) %s, %.3f mas, DETPA %s", path, header.get("KPFILTER"),
             view.shape[0], view.shape[2:], ps.value, how)
    return cube


def read_nirc2(paths, *, wavelengths=None, pixscale=None, **_):
    """Read Keck/NIRC2 image(s) or stack(s) of one star as one `~kpifs.io.IFSCube`.

    Parameters
    ----------
    paths : str or list of str
        Files whose frames become the cube's frames, in order.
    wavelengths : `~astropy.units.Quantity`, optional
        Replaces the filter's central wavelength (`NIRC2_FILTERS`).
    pixscale : `~astropy.units.Quantity`, optional
        Replaces the narrow camera's (`nirc2_pixscale`); needed for the others.

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.io import write_observation
    >>> from kpifs.io.nirc2 import read_nirc2
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> obs = simulate_scene("nirc2", n_frames=2, npup=32, shape=(32, 32))
    >>> tmp = tempfile.TemporaryDirectory()
    >>> files = write_observation(obs, tmp.name, layout="nirc2")
    >>> with read_nirc2(files["target"]) as cube:
    ...     print(cube.shape, cube.wavelengths, cube.pixscale, cube.detpa)
    (2, 1, 32, 32) [2.124] um 9.971 mas [10. 40.] deg
    >>> tmp.cleanup()
    """
    if isinstance(paths, (str, bytes, Path)) or not hasattr(paths, "__iter__"):
        paths = [paths]
    paths = [str(p) for p in paths]
    if not paths:
        raise KpifsError("no NIRC2 files given")
    return read_each(_read_one)(paths, wavelengths=wavelengths, pixscale=pixscale)


def write_nirc2_frames(outdir, cube, wavelength, pixscale, *, detpa=None, prefix="n",
                       cards=None, overwrite=False, obj="SIMULATED", exptime=None):
    """One NIRC2 narrow-camera file per frame of ``(nframe, ny, nx)``, pupil tracking
    (``ROTMODE = 'vertical angle'``), with the ``PARANG`` that gives each frame's *detpa*.

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from astropy.io import fits
    >>> from kpifs.io.nirc2 import write_nirc2_frames
    >>> tmp = tempfile.TemporaryDirectory()
    >>> p = write_nirc2_frames(tmp.name, np.ones((2, 8, 8)), 2.124 * u.um, 9.971 * u.mas)
    >>> p[0].name, fits.getval(p[0], "FILTER")
    ('n0001.fits', 'Kp + clear')
    >>> tmp.cleanup()
    """
    lam = float(u.Quantity(wavelength, u.um).value)
    name = min(NIRC2_FILTERS, key=lambda k: abs(NIRC2_FILTERS[k][0] - lam))
    if abs(NIRC2_FILTERS[name][0] / lam - 1) > 0.01:
        raise KpifsError(f"no NIRC2 filter at {lam:.4f} um")
    title = {"kp": "Kp", "ks": "Ks", "lp": "Lp", "ms": "Ms"}.get(name, name.upper())
    cube = np.asarray(cube, np.float32)
    pa = np.zeros(len(cube)) if detpa is None else np.broadcast_to(
        np.asarray(detpa, float), (len(cube),))
    outdir = Path(outdir)
    paths = [outdir / f"{prefix}{i + 1:04d}.fits" for i in range(len(cube))]
    for p in paths:
        check_output_path(p, overwrite=overwrite)
    out = []
    for i, path in enumerate(paths):
        hdr = simulated_header(cards or {}, instrument="NIRC2", pixscale=pixscale,
                               exptime=exptime, obj=obj)
        hdr.update(TELESCOP="Keck II", CAMNAME="narrow", FWINAME=title, FWONAME="clear",
                   FILTER=f"{title} + clear", PMSNAME="largehex", ROTMODE="vertical angle",
                   ROTPOSN=_SIM_ROTPOSN, INSTANGL=_SIM_INSTANGL)
        hdr["DATE-OBS"] = "2026-01-01"
        hdr["PARANG"] = (float(pa[i]) - _SIM_ROTPOSN + _SIM_INSTANGL - NIRC2_NORTH[1],
                         "[deg] parallactic angle")
        out.append(write_hdulist(fits.HDUList([fits.PrimaryHDU(cube[i], header=hdr)]), path,
                                 overwrite=overwrite))
    return out


def _write(obs, role, outdir, common):
    """`Instrument.write`: one star of a single-channel scene, one file per frame."""
    p = obs.params
    if len(p.wavelengths) != 1:
        raise KpifsError("the NIRC2 layout writes one filter: simulate one wavelength")
    cube = obs.target if role == "target" else obs.calibrator
    (outdir / role).mkdir(exist_ok=True)
    return write_nirc2_frames(outdir / role, cube[:, 0], p.wavelengths[0], p.pixscale,
                              detpa=p.detpa, **common)


INSTRUMENT = Instrument(
    name="nirc2", title="Keck/NIRC2", identify=is_nirc2, read=read_nirc2, pupil="keck",
    instrume=("NIRC2",), header_pupil=nirc2_pupil, pupils=("keck",), setup=nirc2_setup,
    pixscale="narrow camera 9.952 mas (before 2015-04-13), 9.971 mas (after)",
    angles="PARANG + ROTPOSN - INSTANGL - 0.252/0.262 deg (vertical angle mode)",
    layout="nirc2", write=_write,
    scenes={"nirc2": dict(
        telescope="keck", wavelengths=[2.124] * u.um, pixscale=9.971 * u.mas, shape=(64, 64),
        n_frames=10, instrument="nirc2", contrasts=[2e-2], wavefront_rms=50 * u.nm,
        exptime=1 * u.s, detpa=np.linspace(10.0, 40.0, 10),
        sky_offset=[120.0, 90.0] * u.mas)})
