"""Reader for Gemini Planet Imager spectral cubes from the GPI data-reduction pipeline.

``*_spdc.fits`` and ``*_spdc_distorcorr.fits``, one exposure per file: the
header in HDU 0, the cube ``(37, 281, 281)`` in the extension named ``SCI``,
an optional ``DQ`` (uint8, bit 0 do not use; refused unless of SCI's shape).
About half of each slice is NaN, outside the tilted lenslet field.

- Wavelengths (um): ``CRVAL3 + (i + 1 - CRPIX3) * CD3_3`` (``CDELT3`` in older
  files), else the centres of 37 equal bins between the band edges of
  ``IFSFILT`` (`GPI_BANDS`).
- Orientation: the cubes are mirrored on the sky; x is reversed on reading
  (``x' = nx - 1 - x``), then ``DETPA = AVPARANG + IFSROTAT - 90`` deg
  (``AVPARANG`` from ``SCI``, ``IFSROTAT`` from HDU 0), which reproduces
  the pipeline's WCS. The pupil is fixed on the detector and the sky turns.
  An exposure whose angle is unknown (``AVPARANG`` NaN or missing) among
  others that have it is left out with a warning: one unknown angle would
  turn the whole search to the detector frame.
- Field: each cube is cut to the largest square around the star (``PSFCENTX``/
  ``PSFCENTY`` when present, else the field's centre) whose border stays
  inside the lenslet field, so that centring and the window never reach the
  NaN outside; a warning says when that square is small.
- Channels shorter than ``2 * pixscale * D`` (1.067 um at 14.161 mas for
  D = 7.7701 m) are under-sampled: a warning names them.
- Polarimetry cubes (``*_podc``: ``CTYPE3 = 'STOKES'`` or the Wollaston)
  are refused; coronagraphic cubes (``OBSMODE`` ``*_coron``) are read with a
  warning (the star's core is occulted).
"""
import logging
import warnings
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.io import fits

from .._utils import canonical_name, check_output_path, to_quantity, write_hdulist
from ..exceptions import KpifsError, KpifsWarning
from .angles import known_angle_files
from .cube import FrameStack, IFSCube, open_fits
from .instrument import Instrument, add_truth
from .wavelengths import check_wavelengths

__all__ = ["read_gpi", "is_gpi", "gpi_wavelengths", "gpi_pupil", "gpi_setup", "GPI_PIXSCALE",
           "GPI_BANDS",
           "GPI_DIAMETER", "MIN_FIELD", "write_gpi_exposures", "GPI_IFSROTAT", "INSTRUMENT"]

log = logging.getLogger(__name__)

#: Lenslet scale (De Rosa et al. 2020; the DRP's constants).
GPI_PIXSCALE = 14.161 * u.mas
#: Diameter of the pupil as GPI sees it (m): the projected M2 baffle.
GPI_DIAMETER = 7.7701
#: Band edges (um) of the DRP's 37-channel grids.
GPI_BANDS = {"Y": (0.9444, 1.1448), "J": (1.1108, 1.3530), "H": (1.4904, 1.8016),
             "K1": (1.8818, 2.1994), "K2": (2.1034, 2.4004)}
#: Side (pixels) of the NaN-free square below which a warning is issued.
MIN_FIELD = 64
_NCHAN = 37


def _card(hdr, key):
    return str(hdr.get(key, "") or "").strip()


def is_gpi(hdul):
    """True for a GPI pipeline product (``INSTRUME = 'GPI'``).

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.gpi import is_gpi
    >>> is_gpi(fits.HDUList([fits.PrimaryHDU(header=fits.Header({"INSTRUME": "GPI"}))]))
    True
    """
    return _card(hdul[0].header, "INSTRUME").upper() == "GPI"


def gpi_pupil(header):
    """``'gpi_nrm'`` for the non-redundant mask (``OBSMODE`` ``NRM_*``), else ``'gpi'``.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.gpi import gpi_pupil
    >>> gpi_pupil(fits.Header({"OBSMODE": "NRM_J"})), gpi_pupil(fits.Header())
    ('gpi_nrm', 'gpi')
    """
    return "gpi_nrm" if _card(header, "OBSMODE").upper().startswith("NRM") else "gpi"


def gpi_setup(header):
    """What a GPI target's and calibrator's exposures must share: the band (``IFSFILT``),
    the mode (``OBSMODE``), the apodizer or mask (``APODIZER``) and the Lyot stop
    (``LYOTMASK``), as far as the header says.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.gpi import gpi_setup
    >>> gpi_setup(fits.Header({"IFSFILT": "IFSFILT_H_G1213", "OBSMODE": "NRM_H"}))
    {'band': 'H', 'mode': 'NRM_H'}
    """
    band = _card(header, "IFSFILT").split("_")
    out = {"band": band[1].upper()} if len(band) > 1 and band[1] else {}
    for key, name in (("OBSMODE", "mode"), ("APODIZER", "apodizer"), ("LYOTMASK", "Lyot stop")):
        if _card(header, key):
            out[name] = _card(header, key)
    return out


def gpi_wavelengths(phu, sci, nchan, *, source="GPI cube"):
    """Channel wavelengths (um) from the ``SCI`` WCS, else from ``IFSFILT``'s band.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.gpi import gpi_wavelengths
    >>> wl = gpi_wavelengths(fits.Header({"IFSFILT": "IFSFILT_H_G1213"}), fits.Header(), 37)
    >>> round(float(wl[0].value), 5), round(float(wl[-1].value), 5)
    (1.49461, 1.79739)
    """
    step = sci.get("CD3_3", sci.get("CDELT3"))
    if "CRVAL3" in sci and step is not None:
        try:
            crval, step = float(sci["CRVAL3"]), float(step)
            crpix = float(sci.get("CRPIX3", 1.0))
        except (TypeError, ValueError) as exc:
            raise KpifsError(f"{source}: bad wavelength WCS: {exc}") from None
        if step == 0:
            raise KpifsError(f"{source}: CD3_3 (or CDELT3) = 0: every channel would have one "
                             f"wavelength")
        unit = _card(sci, "CUNIT3").lower() or "um"
        unit = u.um if unit.startswith("micron") or unit == "um" else u.Unit(unit)
        with np.errstate(invalid="ignore", over="ignore"):
            wl = (crval + (np.arange(nchan) + 1 - crpix) * step) * unit
        return check_wavelengths(wl.to(u.um), source=f"{source}: CRVAL3/CD3_3")
    band = _card(phu, "IFSFILT").split("_")
    band = band[1].upper() if len(band) > 1 else ""
    if band not in GPI_BANDS:
        raise KpifsError(f"{source}: no wavelength WCS (CRVAL3, CD3_3) and IFSFILT "
                         f"{_card(phu, 'IFSFILT')!r} names no band of {sorted(GPI_BANDS)}")
    lo, hi = GPI_BANDS[band]
    log.info("%s: wavelengths from the %s band edges (IFSFILT)", source, band)
    return check_wavelengths((lo + (np.arange(nchan) + 0.5) * (hi - lo) / nchan) * u.um,
                             source=source)


def _check_mode(path, phu, sci, data):
    if (_card(sci, "CTYPE3").upper() == "STOKES" or "WOLLASTON" in _card(phu, "DISPERSR").upper()
            or (data.ndim == 3 and data.shape[0] in (2, 4) and "CRVAL3" not in sci)):
        raise KpifsError(f"{path}: a GPI polarimetry cube (DISPERSR "
                         f"{_card(phu, 'DISPERSR') or '?'}, CTYPE3 {_card(sci, 'CTYPE3') or '?'}):"
                         f" kpifs reads spectral cubes (*_spdc.fits)")
    if data.ndim != 3:
        raise KpifsError(f"{path}: SCI must be a (37, ny, nx) spectral cube, got {data.shape}")
    if _card(phu, "OBSMODE").lower().endswith("_coron"):
        warnings.warn(f"{path}: coronagraphic cube (OBSMODE {_card(phu, 'OBSMODE')}): the "
                      f"star's core is occulted and its kernel phases are not those of a "
                      f"point source", KpifsWarning, stacklevel=4)


def _centre(sci, field, path):
    """The star's pixel (x, y) in the x-reversed frame."""
    ny, nx = field.shape
    try:
        cx, cy = float(sci["PSFCENTX"]), float(sci["PSFCENTY"])
        if np.isfinite(cx) and np.isfinite(cy) and 0 <= cx < nx and 0 <= cy < ny:
            if field[int(round(cy)), nx - 1 - int(round(cx))]:
                return nx - 1 - cx, cy, "PSFCENTX/Y"
        warnings.warn(f"{path}: PSFCENTX/Y = ({cx:g}, {cy:g}) is not in the lenslet field: "
                      f"the field's centre is used", KpifsWarning, stacklevel=4)
    except (KeyError, TypeError, ValueError):
        pass
    yy, xx = np.nonzero(field)
    if xx.size == 0:
        raise KpifsError(f"{path}: every pixel of the cube is NaN")
    return float(xx.mean()), float(yy.mean()), "the field's centre"


def _half_side(field, cx, cy, *, max_nan=0.02):
    """Largest h such that every square ring up to h around (cx, cy) is mostly inside."""
    ny, nx = field.shape
    ix, iy = int(round(cx)), int(round(cy))
    hmax = min(ix, iy, nx - 1 - ix, ny - 1 - iy)
    for h in range(1, hmax + 1):
        ring = np.concatenate([field[iy - h, ix - h:ix + h + 1], field[iy + h, ix - h:ix + h + 1],
                               field[iy - h:iy + h + 1, ix - h], field[iy - h:iy + h + 1, ix + h]])
        if np.mean(~ring) > max_nan:
            return h - 1
    return hmax


def _detpa(path, phu, sci):
    """``AVPARANG + IFSROTAT - 90`` (deg); NaN when either is unknown (NaN, missing or not a
    number), refused when either is a number no angle can be."""
    try:
        avpa, rot = float(sci.get("AVPARANG", np.nan)), float(phu.get("IFSROTAT", np.nan))
    except (TypeError, ValueError):
        return np.nan
    if not (np.isfinite(avpa) and np.isfinite(rot)):
        return np.nan
    if abs(avpa) > 360 or abs(rot) > 360:
        raise KpifsError(f"{path}: AVPARANG = {avpa:g}, IFSROTAT = {rot:g}: not angles (deg)")
    return avpa + rot - 90


class _Crop:
    """One exposure ``(37, ny, nx)``, x reversed and cut, seen as ``(1, 37, h, w)``."""

    def __init__(self, cube, ys, xs, bad=False):
        self.cube, self.ys, self.xs, self.bad = cube, ys, xs, bad
        self.shape = (1, cube.shape[0], ys.stop - ys.start, xs.stop - xs.start)

    def __getitem__(self, key):
        key = key[1:] if isinstance(key, tuple) else ()
        view = self.cube[:, self.ys, ::-1][:, :, self.xs]
        out = np.asarray(view[key] if key else view)
        if self.bad:
            out = (out.astype(np.uint8) & 1) != 0
        return out[None]


def read_gpi(paths, *, wavelengths=None, pixscale=None, keep_unknown_angles=False):
    """Read GPI ``*_spdc.fits`` cube(s), one exposure each, as one `IFSCube`.

    Parameters
    ----------
    paths : str or list of str
        The exposures of one star: they become the frames.
    wavelengths : `~astropy.units.Quantity`, optional
        Replaces the header's wavelengths.
    pixscale : `~astropy.units.Quantity`, optional
        Default `GPI_PIXSCALE` (14.161 mas).
    keep_unknown_angles : bool
        Keep the exposures whose ``AVPARANG`` (or ``IFSROTAT``) is unknown among
        others that have it (when the angles are given, ``--pa``); otherwise
        they are left out with a warning (`~kpifs.io.angles.known_angle_files`).

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.io import write_observation
    >>> from kpifs.io.gpi import read_gpi
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> obs = simulate_scene("gpi", n_frames=2, npup=32, shape=(128, 128))
    >>> tmp = tempfile.TemporaryDirectory()
    >>> files = write_observation(obs, tmp.name, layout="gpi")
    >>> with read_gpi(files["target"]) as cube:
    ...     print(cube.shape, f"{cube.wavelengths[0]:.4f}", cube.detpa_source)
    (2, 37, 67, 67) 1.4946 um AVPARANG + IFSROTAT - 90
    >>> tmp.cleanup()
    """
    if isinstance(paths, (str, bytes)) or not hasattr(paths, "__iter__"):
        paths = [paths]
    paths = [str(p) for p in paths]
    if not paths:
        raise KpifsError("no GPI files given")
    ps = to_quantity(pixscale if pixscale is not None else GPI_PIXSCALE, u.mas,
                     name="pixel scale")
    files, found = [], []
    try:
        for path in paths:
            hdul = open_fits(path)
            files.append(hdul)
            if "SCI" not in hdul or hdul["SCI"].data is None:
                raise KpifsError(f"{path}: no SCI extension holding a cube")
            phu, sci = hdul[0].header, hdul["SCI"].header
            data = hdul["SCI"].data
            _check_mode(path, phu, sci, data)
            field = np.isfinite(np.asarray(data[data.shape[0] // 2]))[:, ::-1]
            cx, cy, how = _centre(sci, field, path)
            wl = (wavelengths if wavelengths is not None
                  else gpi_wavelengths(phu, sci, data.shape[0], source=path))
            if len(wl) != data.shape[0]:
                raise KpifsError(f"{path}: {len(wl)} wavelengths for {data.shape[0]} channels")
            pa = _detpa(path, phu, sci)
            dq = hdul["DQ"].data if "DQ" in hdul and hdul["DQ"].data is not None else None
            if dq is not None and dq.shape != data.shape:
                raise KpifsError(f"{path}: DQ of shape {dq.shape} does not match SCI "
                                 f"{data.shape}: its bad pixels cannot be placed")
            found.append((data, dq, cx, cy, _half_side(field, cx, cy), wl, pa, how))
        keep = (list(range(len(paths))) if keep_unknown_angles else
                known_angle_files(paths, [f[6] for f in found], keyword="AVPARANG or IFSROTAT"))
        for i in set(range(len(found))) - set(keep):
            files[i].close()
        paths, found = [paths[i] for i in keep], [found[i] for i in keep]
        files = [files[i] for i in keep]
        wl0 = found[0][5]
        for path, f in zip(paths, found):
            if len(f[5]) != len(wl0) or not np.allclose(f[5], wl0, rtol=1e-5):
                raise KpifsError(f"{path}: its wavelengths differ from those of {paths[0]}")
        h = min(f[4] for f in found)
        if 2 * h + 1 < MIN_FIELD:
            warnings.warn(f"{paths[0]}: the lenslet field around the star is only {2 * h + 1} "
                          f"pixels wide: the extraction window reaches the NaN outside it "
                          f"(filled as bad pixels)", KpifsWarning, stacklevel=2)
        h = max(h, MIN_FIELD // 2)
        parts, bad = [], []
        for path, (data, dq, cx, cy, _, _, _, _) in zip(paths, found):
            ny, nx = data.shape[1:]
            ix = min(max(int(round(cx)), h), nx - 1 - h)
            iy = min(max(int(round(cy)), h), ny - 1 - h)
            ys, xs = slice(iy - h, iy + h + 1), slice(ix - h, ix + h + 1)
            parts.append(_Crop(data, ys, xs))
            bad.append(_Crop(dq, ys, xs, bad=True) if dq is not None
                       else _NoBad(parts[-1].shape))
        pa = np.array([f[6] for f in found])
        header = files[0][0].header.copy()
        header["KPCENTRE"] = (found[0][7], "where kpifs took the star's position")
        header["KPCROP"] = (2 * h + 1, "[pix] side of the square read around the star")
        cube = IFSCube(data=FrameStack(parts, bad), wavelengths=wl0, pixscale=ps,
                       header=header, angles=[f[6] + 90 for f in found] * u.deg,
                       detpa=pa * u.deg, detpa_source="AVPARANG + IFSROTAT - 90",
                       instrument="gpi", source=paths, _files=files)
    except BaseException:
        for f in files:
            f.close()
        raise
    _flag_sampling(cube, paths[0])
    log.info("read %d GPI exposure(s): %d channels %.4f-%.4f um, %dx%d around the star "
             "(%s)", len(paths), len(wl0), wl0[0].value, wl0[-1].value, 2 * h + 1, 2 * h + 1,
             found[0][7])
    return cube


class _NoBad:
    """The bad-pixel part of a file without DQ: nothing flagged."""

    def __init__(self, shape):
        self.shape = shape

    def __getitem__(self, key):
        return np.zeros(np.empty(self.shape, bool)[key].shape, bool)


def _flag_sampling(cube, name):
    limit = 2 * cube.pixscale.to_value(u.rad) * GPI_DIAMETER * 1e6     # um
    under = cube.wavelengths.to_value(u.um) < limit
    if under.any():
        warnings.warn(f"{name}: {int(under.sum())} of {len(under)} channels "
                      f"({cube.wavelengths[under][0]:.4f}-{cube.wavelengths[under][-1]:.4f}) "
                      f"are shorter than the sampling limit {limit:.3f} um of the "
                      f"{GPI_DIAMETER} m pupil at {cube.pixscale:.3f}: their longest "
                      f"baselines are lost", KpifsWarning, stacklevel=3)


#: IFSROTAT written in simulated GPI files (deg; 23.5 + PACAL with PACAL = 0).
GPI_IFSROTAT = 23.5


def _lenslet_field(shape, angle=23.5, fraction=0.68):
    ny, nx = shape
    y, x = np.mgrid[:ny, :nx]
    x = x - (nx - 1) / 2
    y = y - (ny - 1) / 2
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    half = fraction * min(shape) / 2
    return (np.abs(c * x + s * y) <= half) & (np.abs(-s * x + c * y) <= half)


def write_gpi_exposures(outdir, cube, variance, wavelengths, pixscale, *, detpa=None,
                        prefix="S20260101S", cards=None, overwrite=False, obj="SIMULATED",
                        exptime=None, obsmode="H_direct"):
    """One GPI ``*_spdc.fits`` per frame of ``(nframe, 37, ny, nx)`` (the kpifs frame).

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from astropy.io import fits
    >>> from kpifs.io.gpi import write_gpi_exposures
    >>> wl = (1.4904 + (np.arange(37) + 0.5) * 0.3112 / 37) * u.um
    >>> tmp = tempfile.TemporaryDirectory()
    >>> paths = write_gpi_exposures(tmp.name, np.ones((1, 37, 32, 32)),
    ...                             np.ones((1, 37, 32, 32)), wl, 14.161 * u.mas)
    >>> paths[0].name, fits.getval(paths[0], "IFSFILT")
    ('S20260101S0001_spdc.fits', 'IFSFILT_H_G1213')
    >>> tmp.cleanup()
    """
    wl = u.Quantity(wavelengths, u.um).value
    band = next((b for b, (lo, hi) in GPI_BANDS.items() if lo < wl[0] < wl[-1] < hi), "H")
    cube = np.asarray(cube)
    nf, nw, ny, nx = cube.shape
    pa = np.zeros(nf) if detpa is None else np.broadcast_to(np.asarray(detpa, float), (nf,))
    outdir = Path(outdir)
    paths = [outdir / f"{prefix}{i + 1:04d}_spdc.fits" for i in range(nf)]
    for p in paths:
        check_output_path(p, overwrite=overwrite)
    field = _lenslet_field((ny, nx))
    s = float(u.Quantity(pixscale, u.mas).value) / 3.6e6
    out = []
    for i, path in enumerate(paths):
        phu = fits.Header()
        phu.update(INSTRUME="GPI", TELESCOP="Gemini South", OBJECT=obj,
                   IFSFILT=f"IFSFILT_{band}_G1213", DISPERSR="DISP_PRISM_G6262",
                   OBSMODE=obsmode, APODIZER="APOD_CLEAR_G6201", OCCULTER="SCIENCE",
                   LYOTMASK="Open", IFSROTAT=GPI_IFSROTAT, PAR_ANG=float(pa[i]) + 66.5,
                   RA=83.8, DEC=-5.4)
        phu["DATE-OBS"], phu["MJD-OBS"] = "2026-01-01", 61041.0 + i * 1e-3
        add_truth(phu, cards, obj)
        data = np.where(field, cube[i], np.nan)[..., ::-1].astype(np.float32)
        bad = ~np.isfinite(variance[i]) & field
        sci = fits.ImageHDU(data, name="SCI")
        h = sci.header
        h["BUNIT"] = "ADU per coadd"
        h["AVPARANG"] = (float(pa[i]) - GPI_IFSROTAT + 90, "[deg] mean parallactic angle")
        h.update(CTYPE3="WAVE", CUNIT3="microns", CRPIX3=1, CRVAL3=float(wl[0]),
                 CD3_3=float(np.mean(np.diff(wl))) if nw > 1 else 0.01)
        h["PSFCENTX"] = (float(nx - 1 - nx // 2), "star x (0-based, file frame)")
        h["PSFCENTY"] = (float(ny // 2), "star y (0-based)")
        t = np.radians(pa[i])
        h.update(CTYPE1="RA---TAN", CTYPE2="DEC--TAN", CRPIX1=(nx + 1) / 2, CRPIX2=(ny + 1) / 2,
                 CRVAL1=83.8, CRVAL2=-5.4, CD1_1=s * np.cos(t), CD1_2=s * np.sin(t),
                 CD2_1=-s * np.sin(t), CD2_2=s * np.cos(t))
        exp = float(u.Quantity(exptime if exptime is not None else 1.0, u.s).value)
        h.update(ITIME=exp, COADDS=1, EXPTIME=exp)
        dq = (bad[..., ::-1]).astype(np.uint8)
        hdul = fits.HDUList([fits.PrimaryHDU(header=phu), sci, fits.ImageHDU(dq, name="DQ")])
        out.append(write_hdulist(hdul, path, overwrite=overwrite))
    return out


def _write(obs, role, outdir, common):
    """`Instrument.write`: one ``*_spdc.fits`` per frame in ``outdir/role``."""
    p = obs.params
    cube, var = ((obs.target, obs.variance_target) if role == "target"
                 else (obs.calibrator, obs.variance_calibrator))
    (outdir / role).mkdir(exist_ok=True)
    mode = "NRM_H" if canonical_name(p.telescope) == "gpi_nrm" else "H_direct"
    return write_gpi_exposures(outdir / role, cube, var, p.wavelengths, p.pixscale,
                               detpa=p.detpa, obsmode=mode, **common)


def _read(paths, *, wavelengths=None, pixscale=None, pa_given=False, **_):
    return read_gpi(paths, wavelengths=wavelengths, pixscale=pixscale,
                    keep_unknown_angles=pa_given)


#: The simulator's GPI scene: H band, 37 channels (DRP grid), 8 exposures over 40 deg of
#: parallactic angle, the companion fixed on the sky.
SCENE = dict(telescope="gpi", wavelengths=(1.4904 + (np.arange(37) + 0.5) * 0.3112 / 37) * u.um,
             pixscale=14.161 * u.mas, shape=(281, 281), n_frames=8, instrument="gpi",
             contrasts=1e-2 * np.linspace(1.2, 0.8, 37), wavefront_rms=20 * u.nm,
             exptime=60 * u.s,   # 60 s exposures: AO averaged
             detpa=np.linspace(-86.5, -46.5, 8), sky_offset=[120.0, 160.0] * u.mas)


def _to_file(source, block, shape):
    """A block of the cube in a GPI file: put back in its crop (*source*'s ``ys``,
    ``xs``) of the image, then mirrored in x."""
    full = np.zeros(shape)
    full[:, source.ys, source.xs] = block[0]
    return full[:, :, ::-1]


INSTRUMENT = Instrument(
    name="gpi", title="Gemini/GPI", identify=is_gpi, read=_read, pupil="gpi",
    instrume=("GPI",), header_pupil=gpi_pupil, pupils=("gpi", "gemini_south", "gpi_nrm"),
    setup=gpi_setup, pixscale=f"{GPI_PIXSCALE.value:g} mas (--pixscale)",
    angles="AVPARANG + IFSROTAT - 90 deg (x mirrored)", layout="gpi", write=_write,
    scenes={"gpi": SCENE}, sequence=(-66.5, "pachon"), data_hdu="SCI", to_file=_to_file)
