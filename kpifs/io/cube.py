"""The `IFSCube` container and the generic FITS cube reader."""
import logging
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.io import fits

from .._utils import to_quantity
from ..exceptions import KpifsError, MissingInformation
from .angles import header_detpa
from .wavelengths import check_wavelengths, parse_wavelengths

__all__ = ["IFSCube", "read_generic", "FrameStack", "open_fits", "check_header_checksums"]

log = logging.getLogger(__name__)


@dataclass
class IFSCube:
    """An IFS data set viewed as ``(nframe, nwave, ny, nx)``.

    Attributes
    ----------
    data : ndarray
        Images, possibly memory-mapped (read lazily, one batch at a time).
    wavelengths : `~astropy.units.Quantity` (nwave,)
    pixscale : `~astropy.units.Quantity`
    header : `~astropy.io.fits.Header`
        Header of the (first) input file, a copy.
    mask : ndarray of bool or None
        True for bad pixels, broadcastable to *data*.
    angles : `~astropy.units.Quantity` or None
        Per-frame angles as the instrument records them (CHARIS ``PARANG``,
        the SPHERE angle file).
    detpa : `~astropy.units.Quantity` or None
        Per-frame detector position angles: the position angle, East of North,
        of the detector +y axis (NaN where unknown); see `kpifs.io.angles`.
    detpa_source : str or None
        Where *detpa* came from (for messages and the products).
    instrument : str
    source : list of str
        Input file names.
    variance : array-like or None
        Per-pixel noise variance of each frame, shape of *data* (read lazily;
        JWST ``ERR**2``), propagated to the kernel phases' errors
        (`kpifs.calibration.pixelnoise`).
    variance_source : str or None
        Where *variance* came from.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs.io import IFSCube
    >>> cube = IFSCube(np.zeros((2, 3, 16, 16)), [1.5, 1.6, 1.7] * u.um, 10 * u.mas)
    >>> cube.shape, cube.name
    ((2, 3, 16, 16), '<array>')
    """

    data: np.ndarray
    wavelengths: u.Quantity
    pixscale: u.Quantity
    header: fits.Header = field(default_factory=fits.Header)
    mask: np.ndarray = None
    angles: u.Quantity = None
    detpa: u.Quantity = None
    detpa_source: str = None
    instrument: str = "generic"
    source: list = field(default_factory=list)
    variance: object = None
    variance_source: str = None
    _files: list = field(default_factory=list, repr=False)

    def __post_init__(self):
        # one set of plausibility checks for every reader (and `kpifs info`)
        self.wavelengths = check_wavelengths(self.wavelengths, source=self.name)
        ps = to_quantity(self.pixscale, u.mas, name="pixel scale")
        if not np.isfinite(ps.value) or ps.value <= 0:
            raise KpifsError(f"{self.name}: pixel scale must be > 0, got {ps}")
        self.pixscale = ps
        if self.detpa is not None:
            pa = np.atleast_1d(to_quantity(self.detpa, u.deg, name="detector position angle"))
            if pa.shape != (self.data.shape[0],):
                raise KpifsError(f"{self.name}: {pa.size} detector position angle(s) for "
                                 f"{self.data.shape[0]} frame(s)")
            self.detpa = pa

    def close(self):
        """Close the memory-mapped files behind `data`."""
        for f in self._files:
            f.close()
        self._files = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def shape(self):
        return self.data.shape

    @property
    def name(self):
        """The input's name for messages: the first file, and how many more."""
        if not self.source:
            return "<array>"
        more = f" (+{len(self.source) - 1} more)" if len(self.source) > 1 else ""
        return f"{self.source[0]}{more}"

    def __repr__(self):
        return (f"<IFSCube {self.instrument}: {self.shape}, {len(self.wavelengths)} channels "
                f"{self.wavelengths.min():.3f}-{self.wavelengths.max():.3f}, "
                f"{self.pixscale:.2f}, from {self.name}>")


class FrameStack:
    """Frames from several files seen as one ``(nframe, nwave, ny, nx)`` array.

    Nothing is read until a slice is asked for (``stack[f0:f1, iw]``), so
    memory stays near one batch of frames. Each part is an array-like of shape
    ``(nf_i, nwave, ny, nx)`` (memory-mapped, usually); *bad* parts (same
    shapes, True = bad) turn their non-zero pixels into NaN on reading.
    """

    def __init__(self, parts, bad=None):
        self.parts = list(parts)
        self.bad = None if bad is None else list(bad)
        shapes = {p.shape[1:] for p in self.parts}
        if len(shapes) != 1:
            raise KpifsError(f"the files do not share one cube shape: {sorted(shapes)}")
        self._starts = np.cumsum([0] + [p.shape[0] for p in self.parts])
        self.shape = (int(self._starts[-1]),) + shapes.pop()
        self.ndim = 4
        self.dtype = np.dtype(float)

    def __len__(self):
        return self.shape[0]

    def __array__(self, dtype=None, copy=None):
        return self[:].astype(dtype or float, copy=False)

    def __getitem__(self, key):
        if not isinstance(key, tuple):
            key = (key,)
        fkey, rest = key[0], key[1:]
        if isinstance(fkey, (int, np.integer)):
            return self[(slice(fkey, fkey + 1),) + rest][0]
        idx = np.arange(self.shape[0])[fkey]
        out = []
        for i, part in enumerate(self.parts):
            sel = idx[(idx >= self._starts[i]) & (idx < self._starts[i + 1])] - self._starts[i]
            if sel.size == 0:
                continue
            sl = slice(sel[0], sel[-1] + 1) if np.all(np.diff(sel) == 1) else sel
            chunk = np.array(part[(sl,) + rest], dtype=float)
            if self.bad is not None:
                # exact zeros (CHARIS: lenslets outside the field) stay zero: they
                # add nothing to the Fourier sums and need no filling
                chunk[np.asarray(self.bad[i][(sl,) + rest]) & (chunk != 0)] = np.nan
            out.append(chunk)
        if not out:
            return np.empty((0,) + self.shape[1:])[(slice(None),) + rest]
        return np.concatenate(out)


def open_fits(path, *, verify=False):
    """Open a FITS file, refusing directories, missing, truncated and unreadable files.

    Cubes are memory-mapped (read later, one batch at a time). With *verify*
    the whole file is read and its CHECKSUM/DATASUM cards, when present, are
    checked (kpifs writes them on every product): a mismatch is reported as
    "checksum mismatch (corrupted?)".

    Examples
    --------
    >>> import tempfile, numpy as np
    >>> from astropy.io import fits
    >>> from kpifs.io.cube import open_fits
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = tmp.name + "/a.fits"
    >>> fits.writeto(path, np.zeros((4, 4)), checksum=True)
    >>> with open_fits(path, verify=True) as hdul:
    ...     print(hdul[0].data.shape)
    (4, 4)
    >>> tmp.cleanup()
    """
    path = Path(path)
    if path.is_dir():
        raise KpifsError(f"{path}: is a directory, expected a FITS file")
    if not path.exists():
        raise KpifsError(f"{path}: file not found")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            hdul = fits.open(path, memmap=not verify, checksum=verify)
            if not verify and _scaled(hdul):
                # integers with BZERO/BSCALE (int16 scaled, uint16 as BZERO 32768): astropy
                # scales them on reading, which a memory map cannot do
                hdul.close()
                hdul = fits.open(path, memmap=False)
        except (OSError, ValueError, TypeError, IndexError) as exc:
            raise KpifsError(f"{path}: not a readable FITS file ({exc})") from None
        try:
            hdul.verify("silentfix")
            for h in hdul:  # touching every HDU's data finds truncated files now
                if not verify and any(k in h.header for k in ("BZERO", "BSCALE", "BLANK")):
                    continue    # scaled (JWST DQ): cannot be memory-mapped; read on demand
                if h.data is not None:
                    h.data.shape
        except (OSError, ValueError, TypeError, IndexError) as exc:
            hdul.close()
            if path.stat().st_size % 2880 or "truncat" in str(exc) or "reshape" in str(exc):
                raise KpifsError(f"{path}: truncated FITS file ({path.stat().st_size} bytes; "
                                 f"an interrupted copy?)") from None
            raise KpifsError(f"{path}: not a readable FITS file ({exc})") from None
    messages = [str(w.message) for w in caught]
    if any("truncated" in m or "Error validating header" in m or "is corrupted" in m
           for m in messages):
        hdul.close()
        raise KpifsError(f"{path}: truncated FITS file ({path.stat().st_size} bytes; an "
                         f"interrupted copy?)")
    if any("Checksum verification failed" in m or "Datasum verification failed" in m
           for m in messages):
        hdul.close()
        raise KpifsError(f"{path}: checksum mismatch (corrupted?)")
    for m in messages:           # anything else astropy had to say is worth passing on
        log.info("%s: %s", path, m.strip())
    return hdul


def _ones_complement_sum(raw, start=0):
    """The 32-bit ones'-complement sum of big-endian words (the FITS checksum's)."""
    total = int(np.frombuffer(raw, dtype=">u4").sum(dtype=np.uint64)) + int(start)
    while total >> 32:
        total = (total & 0xFFFFFFFF) + (total >> 32)
    return total


def check_header_checksums(path):
    """Refuse a file whose header was changed after its CHECKSUM was written.

    Each HDU with ``CHECKSUM`` and ``DATASUM`` cards: the ones'-complement sum of its
    header as stored plus its ``DATASUM`` must be all ones (the FITS checksum
    convention). Only the headers are read: a header edited by hand (a scale, a
    wavelength, an angle) is caught without reading a large cube's data (whose
    ``DATASUM`` the readers check where they read it).

    Examples
    --------
    >>> import pathlib, tempfile, numpy as np
    >>> from astropy.io import fits
    >>> from kpifs.io.cube import check_header_checksums
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "a.fits"
    >>> fits.writeto(path, np.zeros((4, 4)), fits.Header({"PIXSCALE": 10.0}), checksum=True)
    >>> check_header_checksums(path)
    >>> _ = path.write_bytes(path.read_bytes().replace(b"PIXSCALE=                 10.0",
    ...                                                b"PIXSCALE=                 12.0"))
    >>> try:
    ...     check_header_checksums(path)
    ... except Exception as err:
    ...     print(str(err).split(": ", 1)[1])
    header checksum mismatch in HDU 0 (PRIMARY): its header was changed after it was written
    """
    with fits.open(path, memmap=True, lazy_load_hdus=False) as hdul, open(path, "rb") as f:
        for i, h in enumerate(hdul):
            hdr = h.header
            if "CHECKSUM" not in hdr or "DATASUM" not in hdr:
                continue
            try:
                datasum = int(str(hdr["DATASUM"]).strip())
            except (TypeError, ValueError):
                raise KpifsError(f"{path}: DATASUM {hdr['DATASUM']!r} in HDU {i} is not a "
                                 f"checksum (corrupted?)") from None
            info = hdul.fileinfo(i)
            f.seek(info["hdrLoc"])
            raw = f.read(info["datLoc"] - info["hdrLoc"])
            if _ones_complement_sum(raw, datasum) != 0xFFFFFFFF:
                raise KpifsError(f"{path}: header checksum mismatch in HDU {i} "
                                 f"({h.name or 'no name'}): its header was changed after it "
                                 f"was written")


def _scaled(hdul):
    """True when an image HDU stores scaled integers (BZERO, BSCALE or BLANK cards)."""
    for h in hdul:
        hdr = h.header
        if hdr.get("NAXIS", 0) and (hdr.get("BSCALE", 1) != 1 or hdr.get("BZERO", 0) != 0
                                    or "BLANK" in hdr):
            return True
    return False


def _header_wavelengths(hdr, path):
    keys = sorted((k for k in hdr if k.startswith("KPWL") and k[4:].isdigit()),
                  key=lambda k: int(k[4:]))
    if not keys:
        return None
    values = []
    for k in keys:
        try:
            values.append(float(hdr[k]))
        except (TypeError, ValueError, fits.VerifyError):
            raise KpifsError(f"{path}: {k} = {hdr.cards[k].image[10:30].strip()!r} is not a "
                             f"wavelength (um): give the wavelengths (--wavelengths)") from None
    return check_wavelengths(values * u.um, source=f"{path}: KPWLn cards")


def read_generic(path, *, wavelengths=None, pixscale=None):
    """Read a plain FITS cube: 2-D ``(ny, nx)``, 3-D ``(nwave, ny, nx)`` or 4-D
    ``(nframe, nwave, ny, nx)``.

    Wavelengths come from *wavelengths* or the header cards ``KPWL1 ... KPWLn``
    (um, as kpifs's simulator writes them); the pixel scale from *pixscale* or
    ``PIXSCALE`` (mas). The detector position angles come from a ``DETPA``
    image extension (one value per frame) or a ``DETPA`` card (deg); without
    either they are taken to be 0 (North up, East left) and
    ``cube.detpa_source`` says so. The data stay memory-mapped.

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from astropy.io import fits
    >>> from kpifs.io import read_generic
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = tmp.name + "/cube.fits"
    >>> fits.writeto(path, np.ones((3, 16, 16), np.float32))
    >>> with read_generic(path, wavelengths=[1.5, 1.6, 1.7] * u.um, pixscale=10 * u.mas) as c:
    ...     print(c.shape)
    (1, 3, 16, 16)
    >>> tmp.cleanup()
    """
    hdul = open_fits(path)
    try:
        cube = _generic_from_hdul(hdul, path, wavelengths, pixscale)
    except BaseException:
        hdul.close()
        raise
    cube._files.append(hdul)
    return cube


def refuse_kpfits(hdul, path):
    """Refuse a kernel-phase (KPFITS) or detection file given where a cube is expected."""
    names = {h.name for h in hdul}
    if "KP-DATA" in names or any(n.startswith("KP-DATA") and n[7:].isdigit() for n in names):
        raise KpifsError(f"{path}: kernel-phase data (KPFITS, a KP-DATA extension), not an "
                         f"image cube: search it with kpifs detect, describe it with kpifs info")
    content = str(hdul[0].header.get("CONTENT", ""))
    if content.startswith("KPIFS-") or "KER-MAT" in names:
        what = "a kernel model" if "KER-MAT" in names else f"a kpifs product ({content})"
        raise KpifsError(f"{path}: {what}, not an image cube (kpifs info describes it)")


def _not_a_cube(hdul, path):
    """Refuse OIFITS, KPFITS and table-only files: their images (CPCOV covariances,
    KP-DATA) are no cube, and taking them for one gives a silent wrong answer."""
    names = [h.name for h in hdul]
    oi = [n for n in dict.fromkeys(names) if n.startswith("OI_")]
    if oi:
        raise KpifsError(f"{path}: an OIFITS file ({', '.join(oi)}): closure phases, not an "
                         f"image cube; `kpifs detect` and `kpifs info` read it")
    refuse_kpfits(hdul, path)
    tables = [h.name or f"HDU {i}" for i, h in enumerate(hdul) if not h.is_image]
    if tables and not any(h.is_image and h.data is not None and h.data.ndim >= 2
                          for h in hdul):
        raise KpifsError(f"{path}: only tables ({', '.join(tables)}), no image cube: `kpifs "
                         f"extract` reads image cubes")


def _generic_from_hdul(hdul, path, wavelengths, pixscale):
    _not_a_cube(hdul, path)
    hdu = next((h for h in hdul if h.data is not None and h.is_image and h.data.ndim >= 2),
               None)
    if hdu is None:
        raise KpifsError(f"{path}: no image data in any HDU")
    data = hdu.data
    hdr = hdul[0].header.copy()
    if hdu is not hdul[0]:
        hdr.update({k: v for k, v in hdu.header.items() if k not in hdr and k not in
                    ("XTENSION", "PCOUNT", "GCOUNT")})
    if wavelengths is not None:
        wl = parse_wavelengths(wavelengths, source=f"{path}: wavelengths")
    else:
        wl = _header_wavelengths(hdr, path)
    if wl is None:
        raise MissingInformation(f"{path}: no wavelengths: give them (--wavelengths "
                                 f"1.52um,1.60um or a file)")
    if data.ndim == 2:
        data = data[None, None]
    elif data.ndim == 3:
        # (nwave, ny, nx), or a stack of frames at a single wavelength
        data = data[:, None] if (len(wl) == 1 and data.shape[0] != 1) else data[None]
    elif data.ndim != 4:
        raise KpifsError(f"{path}: data have {data.ndim} dimensions; expected 2, 3 or 4")
    if len(wl) != data.shape[1]:
        raise KpifsError(f"{path}: {len(wl)} wavelength(s) given but the cube has "
                         f"{data.shape[1]} channel(s)")
    ps = pixscale if pixscale is not None else hdr.get("PIXSCALE")
    if ps is None:
        raise MissingInformation(f"{path}: no pixel scale: give one (--pixscale 10.42mas)")
    ps = to_quantity(ps, u.mas, name="pixel scale")
    detpa, where = header_detpa(hdul, data.shape[0], source=str(path))
    if detpa is None:
        log.info("%s: no detector position angle (DETPA extension or card): 0 deg assumed "
                 "(North up); give --pa", path)
        detpa, where = np.zeros(data.shape[0]), "none (0 assumed)"
    return IFSCube(data=data, wavelengths=wl, pixscale=ps, header=hdr, instrument="generic",
                   source=[str(path)], detpa=detpa * u.deg, detpa_source=where)
