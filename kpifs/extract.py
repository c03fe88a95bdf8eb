"""Batched per-wavelength kernel-phase extraction.

For each wavelength one DFT matrix ``M[b, pix] = exp(-2 pi i (u_b x + v_b y)/lam)``
is built for the window's pixels (cached on the `~kpifs.kernel.KernelModel`)
and applied to all frames at once as one real matrix product. The window
is cut at the integer pixel nearest the star centre; the sub-pixel remainder
``delta`` is applied afterwards as the exact phase ramp ``+2 pi b.delta/lam``,
so the star centre is the DFT origin without interpolating the image.
"""
import logging
import warnings

import numpy as np
from astropy import units as u
from astropy.io import fits
from astropy.table import QTable

from ._utils import to_quantity
from .exceptions import KpifsError, KpifsWarning
from .kernel import MAS, KernelModel, load_kernel_model
from .prepare import cut_out, fill_bad_pixels, find_centres, window_weights

__all__ = ["KernelPhaseData", "extract_kernel_phases", "DEFAULT_WINDOW_RADIUS",
           "DEFAULT_MAX_WINDOW"]

log = logging.getLogger(__name__)

#: Default super-Gaussian window radius, as a fraction of the half-width of
#: the cut-out: wide enough that a companion at half the field radius keeps
#: ~90 % of its flux (w = exp(-(0.5/0.8)**4) = 0.86), narrow enough that the
#: window is ~0.1 at the cut-out's edge.
DEFAULT_WINDOW_RADIUS = 0.8

#: Largest default cut-out (pixels): the image's smaller side up to this. A
#: 64-pixel cut-out is ~1 arcsec for CHARIS and keeps each DFT matrix ~40 MB.
DEFAULT_MAX_WINDOW = 64


class KernelPhaseData:
    """Kernel phases of a cube, with everything needed to interpret them.

    Parameters
    ----------
    kp : ndarray, shape (nframe, nwave, nkp)
        Kernel phases (rad).
    wavelengths : `~astropy.units.Quantity`, shape (nwave,)
    pixscale : `~astropy.units.Quantity`
        Pixel scale of the images the phases come from.
    kernel_model : `~kpifs.kernel.KernelModel`
        The model whose kernel produced *kp*.
    phases, amplitudes : ndarray, shape (nframe, nwave, nuv), optional
        Raw Fourier phases (rad) and normalised amplitudes, for diagnostics.
    centres : `~astropy.table.QTable`, optional
        Star centres used, one row per (frame, wavelength).
    covariance : ndarray, shape (nwave, nkp, nkp), optional
        Covariance of one frame's kernel phases, per channel (the same for
        every frame).
    joint_covariance : ndarray, shape (nwave*nkp, nwave*nkp), optional
        The same across channels (spectral cross-talk included).
    covariance_rows : ndarray, shape (nrow, nwave, nkp), optional
        Rows ``R`` with ``R^T R`` the covariance across all channels (see
        `~kpifs.calibrate.calibrate`): a compact, always-available form of the
        cross-channel covariance used to draw realistic noise.
    header : `~astropy.io.fits.Header`, optional
        Header of the input cube (kept in products).
    meta : dict, optional
        Provenance.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> km = KernelModel.from_pupil(make_pupil("subaru"))
    >>> kpd = KernelPhaseData(np.zeros((2, 3, km.n_kp)), [1.52, 1.6, 1.68] * u.um,
    ...                       10.42 * u.mas, km)
    >>> kpd.shape == (2, 3, km.n_kp)
    True
    """

    def __init__(self, kp, wavelengths, pixscale, kernel_model, *, phases=None,
                 amplitudes=None, centres=None, covariance=None, joint_covariance=None,
                 covariance_rows=None, header=None, detpa=None, bandwidth=None, meta=None):
        kp = np.asarray(kp, float)
        if kp.ndim == 2:
            kp = kp[None]
        self.kp = kp
        self.wavelengths = np.atleast_1d(to_quantity(wavelengths, u.um, name="wavelengths"))
        self.pixscale = to_quantity(pixscale, u.mas, name="pixel scale")
        self.kernel_model = kernel_model
        if kp.ndim != 3 or kp.shape[1] != len(self.wavelengths) or kp.shape[2] != \
                kernel_model.n_kp:
            raise KpifsError(f"kernel phases have shape {kp.shape}, expected (nframe, "
                             f"{len(self.wavelengths)}, {kernel_model.n_kp})")
        self.phases = phases
        self.amplitudes = amplitudes
        self.centres = centres
        n = len(self.wavelengths) * kernel_model.n_kp
        if covariance is not None:
            covariance = np.asarray(covariance, float)
            if covariance.ndim == 4:   # KPFITS (nframe, nwave, nkp, nkp): shared by frames
                covariance = covariance.mean(axis=0)
            if covariance.shape != (len(self.wavelengths), kernel_model.n_kp, kernel_model.n_kp):
                raise KpifsError(f"covariance has shape {covariance.shape}, expected "
                                 f"({len(self.wavelengths)}, {kernel_model.n_kp}, "
                                 f"{kernel_model.n_kp})")
        if joint_covariance is not None:
            joint_covariance = np.asarray(joint_covariance, float)
            if joint_covariance.shape != (n, n):
                raise KpifsError(f"joint covariance has shape {joint_covariance.shape}, "
                                 f"expected ({n}, {n})")
        if covariance_rows is not None:
            covariance_rows = np.asarray(covariance_rows, float)
            if covariance_rows.ndim != 3 or covariance_rows.shape[1:] != kp.shape[1:]:
                raise KpifsError(f"covariance rows have shape {covariance_rows.shape}, "
                                 f"expected (nrow, {kp.shape[1]}, {kp.shape[2]})")
        self.covariance = covariance
        self.joint_covariance = joint_covariance
        self.covariance_rows = covariance_rows
        self.header = fits.Header() if header is None else header.copy()
        self.detpa = None if detpa is None else np.asarray(detpa, float)
        self.bandwidth = bandwidth
        self.meta = dict(meta or {})

    @property
    def shape(self):
        return self.kp.shape

    @property
    def n_frame(self):
        return self.kp.shape[0]

    @property
    def n_wave(self):
        return self.kp.shape[1]

    @property
    def n_kp(self):
        return self.kp.shape[2]

    def __repr__(self):
        return (f"<KernelPhaseData: {self.n_frame} frame(s) x {self.n_wave} channel(s) x "
                f"{self.n_kp} kernel phases, {self.wavelengths.min():.3f}-"
                f"{self.wavelengths.max():.3f}, {self.pixscale:.2f}>")

    def to_hdulist(self, **kwargs):
        """Return the data in the KPFITS1 layout (see `kpifs.io.kpfits`)."""
        from .io.kpfits import kpd_to_hdulist
        return kpd_to_hdulist(self, **kwargs)

    def write(self, path, *, overwrite=False, inputs=()):
        """Write the data to *path* in the KPFITS1 layout."""
        from .io.kpfits import write_kpfits
        return write_kpfits(self, path, overwrite=overwrite, inputs=inputs)

    @classmethod
    def read(cls, path):
        """Read kernel-phase data from a KPFITS file."""
        from .io.kpfits import read_kpfits
        return read_kpfits(path)


def _as_frames(data, nwave, source):
    data = np.asarray(data) if not isinstance(data, np.ndarray) else data
    if data.ndim == 2 and nwave == 1:
        data = data[None, None]
    elif data.ndim == 3:
        if data.shape[0] != nwave:
            raise KpifsError(f"{source}: cube has {data.shape[0]} slices but {nwave} "
                             f"wavelength(s) were given")
        data = data[None]
    elif data.ndim != 4:
        raise KpifsError(f"{source}: expected a cube (nwave, ny, nx) or (nframe, nwave, ny, nx), "
                         f"got {data.ndim} dimension(s)")
    if data.shape[1] != nwave:
        raise KpifsError(f"{source}: cube has {data.shape[1]} channels but {nwave} "
                         f"wavelength(s) were given")
    return data


def _centres_array(centres, nframe, nwave):
    c = np.asarray(centres, float)
    try:
        return np.broadcast_to(c, (nframe, nwave, 2)).copy()
    except ValueError:
        raise KpifsError(f"centres of shape {c.shape} do not match ({nframe}, {nwave}, 2)") \
            from None


def extract_kernel_phases(data, pupil, *, wavelengths, pixscale, centres=None, mask=None,
                          window_size=None, window_radius=None, window_order=4,
                          centroid="com", bad_pixels="fill", on_nyquist="drop",
                          batch_size=256, header=None,
                          source="<array>", keep_phases=True, progress=False):
    """Kernel phases of every frame and channel of an IFS cube.

    Parameters
    ----------
    data : array-like, shape (nwave, ny, nx) or (nframe, nwave, ny, nx)
        Images (memory-mapped arrays are read one batch of frames at a time).
    pupil : `~kpifs.kernel.KernelModel`, `~kpifs.pupil.PupilModel` or str
        Kernel model, pupil model, telescope name or FITS file (see
        `~kpifs.kernel.load_kernel_model`).
    wavelengths : `~astropy.units.Quantity`, shape (nwave,)
    pixscale : `~astropy.units.Quantity`
        Angular pixel size.
    centres : array-like, optional
        Star centres ``(x, y)`` in pixels, broadcastable to (nframe, nwave, 2);
        found with `~kpifs.prepare.find_centres` (method *centroid*) if omitted.
    mask : array-like of bool, optional
        True for bad pixels, broadcastable to the data; NaN pixels are bad too.
    bad_pixels : {'fill', 'exclude'}
        ``'fill'``: interpolate bad pixels from their neighbours
        (`~kpifs.prepare.fill_bad_pixels`); ``'exclude'``: leave them out of the
        Fourier sums (set to zero).
    window_size : int, optional
        Side of the square cut-out around the star (pixels); default the
        image's smaller side (even), at most `DEFAULT_MAX_WINDOW`. Pixels of the
        cut-out outside the image count as excluded.
    window_radius : float, optional
        Super-Gaussian radius in pixels; default ``0.8 * window_size / 2``.
    window_order : float
        Super-Gaussian exponent (4 by default; ``np.inf`` would be a hard disk).
    centroid : str
        Centroid method when *centres* is omitted.
    on_nyquist : {'drop', 'raise'}
        What to do with uv points beyond the Nyquist limit of some channel
        (see `~kpifs.kernel.KernelModel.for_wavelengths`).
    batch_size : int
        Frames processed together (bounds the memory in use).
    header : `~astropy.io.fits.Header`, optional
        Header of the input, kept in the result.
    source : str
        Name of the input, used in messages and provenance.
    keep_phases : bool
        Keep raw Fourier phases and amplitudes in the result.
    progress : bool
        Show a progress bar over the channels (tqdm).

    Returns
    -------
    `KernelPhaseData`

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import extract_kernel_phases
    >>> from kpifs.simulate import simulate_psf
    >>> wl = [1.6] * u.um
    >>> cube = simulate_psf("subaru", wl, pixscale=10.42 * u.mas, shape=(40, 40))
    >>> kpd = extract_kernel_phases(cube, "subaru", wavelengths=wl, pixscale=10.42 * u.mas)
    >>> kpd.shape[:2], bool(np.abs(kpd.kp).max() < 1e-3)
    ((1, 1), True)
    """
    wl = np.atleast_1d(to_quantity(wavelengths, u.um, name="wavelengths"))
    if wl.size == 0:
        raise KpifsError(f"{source}: no wavelengths given")
    if not np.all(np.isfinite(wl.value)) or np.any(wl.value <= 0):
        raise KpifsError(f"{source}: wavelengths must be finite and > 0, got {wl}")
    ps = to_quantity(pixscale, u.mas, name="pixel scale")
    if not np.isfinite(ps.value) or ps.value <= 0:
        raise KpifsError(f"{source}: pixel scale must be > 0, got {ps}")
    km = load_kernel_model(pupil) if not isinstance(pupil, KernelModel) else pupil
    km = km.for_wavelengths(wl, ps, on_nyquist=on_nyquist, source=source)

    cube = _as_frames(data, len(wl), source)
    nframe, nwave, ny, nx = cube.shape
    if window_size is None:
        window_size = min(ny, nx, DEFAULT_MAX_WINDOW) - min(ny, nx, DEFAULT_MAX_WINDOW) % 2
    window_size = int(window_size)
    if window_size > min(ny, nx):
        raise KpifsError(f"{source}: window of {window_size} pixels is larger than the "
                         f"{ny}x{nx} image")
    if window_size < 4:
        raise KpifsError(f"{source}: window of {window_size} pixels is too small")
    if window_radius is None:
        window_radius = DEFAULT_WINDOW_RADIUS * window_size / 2
    if not window_radius > 0:
        raise KpifsError(f"{source}: window radius must be > 0, got {window_radius}")
    if bad_pixels not in ("fill", "exclude"):
        raise KpifsError(f"bad_pixels must be 'fill' or 'exclude', got {bad_pixels!r}")
    if mask is not None:
        mask = np.asarray(mask, bool)
        try:
            np.broadcast_shapes(mask.shape, cube.shape)
        except ValueError:
            raise KpifsError(f"{source}: mask of shape {mask.shape} does not match the cube "
                             f"{cube.shape}") from None

    if centres is not None:
        centres = _centres_array(centres, nframe, nwave)

    ws = window_size
    uvx, uvy = km.uv.value.T
    kp = np.empty((nframe, nwave, km.n_kp))
    phases = np.empty((nframe, nwave, km.n_uv)) if keep_phases else None
    amps = np.empty((nframe, nwave, km.n_uv)) if keep_phases else None
    used_centres = np.empty((nframe, nwave, 2))
    n_bad_total = 0
    n_clipped = 0
    bmask = None if mask is None else np.broadcast_to(mask, cube.shape)
    # wavelength outermost: each DFT matrix is built (or fetched) once per call
    channels = range(nwave)
    if progress:
        from tqdm.auto import tqdm
        channels = tqdm(channels, desc=f"extracting {source}"[:40], unit="channel")
    for iw in channels:
        mat = km.dft_matrix(wl[iw], ps, (ws, ws))
        lam = wl[iw].to_value(u.m)
        for f0 in range(0, nframe, batch_size):
            f1 = min(nframe, f0 + batch_size)
            sl = np.array(cube[f0:f1, iw], dtype=float)
            if bmask is not None:
                sl[bmask[f0:f1, iw]] = np.nan
            finite = np.isfinite(sl)
            all_finite = finite.all()
            if not all_finite:
                n_bad_total += int(sl.size - finite.sum())
                sl[~finite] = np.nan
            empty = ~np.any(np.nan_to_num(sl) != 0, axis=(1, 2))
            if empty.any():
                fr = int(np.argmax(empty))
                raise KpifsError(f"{source}: frame {f0 + fr}, channel {iw} "
                                 f"({wl[iw]:.3f}) is empty (all zero or non-finite): "
                                 f"{empty.sum()} such frame(s) at this channel")
            if centres is None:
                bc = find_centres(sl, method=centroid)
            else:
                bc = centres[f0:f1, iw]
            if not all_finite:
                if bad_pixels == "fill":
                    fill_bad_pixels(sl)
                else:
                    sl[~finite] = 0.0
            if (np.any((bc[:, 0] < -0.5) | (bc[:, 0] > nx - 0.5) | (bc[:, 1] < -0.5)
                       | (bc[:, 1] > ny - 0.5)) or not np.all(np.isfinite(bc))):
                raise KpifsError(f"{source}: a star centre lies outside the {ny}x{nx} image "
                                 f"(channel {iw})")
            used_centres[f0:f1, iw] = bc
            # the edge matters where the window still weighs more than 1/e
            edge = np.minimum.reduce([bc[:, 0] + 0.5, nx - 0.5 - bc[:, 0],
                                      bc[:, 1] + 0.5, ny - 0.5 - bc[:, 1]])
            n_clipped += int(np.sum(edge < window_radius))
            cut, delta = cut_out(sl, bc, ws)
            win = window_weights(delta, ws, window_radius, window_order)
            cut *= win
            cut = cut.reshape(len(cut), ws * ws)
            ri = cut @ mat.T
            re, im = ri[:, :km.n_uv], ri[:, km.n_uv:]
            ph = np.arctan2(im, re)
            # the sub-pixel remainder of the centre, as an exact phase ramp
            ramp = np.outer(delta[:, 0], uvx) + np.outer(delta[:, 1], uvy)
            ph += (2 * np.pi * ps.value * MAS / lam) * ramp
            ph = (ph + np.pi) % (2 * np.pi) - np.pi
            kp[f0:f1, iw] = ph @ km.kernel.T
            if keep_phases:
                phases[f0:f1, iw] = ph
                amps[f0:f1, iw] = np.hypot(re, im) / cut.sum(axis=1)[:, None]
    if n_clipped:
        warnings.warn(f"{source}: the star is closer to the image edge than the window radius "
                      f"({window_radius:.1f} pixels) in {n_clipped} of {nframe * nwave} "
                      f"slice(s); the edge cuts the window (use a smaller --window-radius)",
                      KpifsWarning, stacklevel=2)
    if n_bad_total:
        log.info("%s: %d bad or NaN pixels excluded from the Fourier sums", source, n_bad_total)
    frame_idx, wave_idx = np.meshgrid(np.arange(nframe), np.arange(nwave), indexing="ij")
    ctab = QTable([frame_idx.ravel(), np.broadcast_to(wl, (nframe, nwave)).ravel(),
                   used_centres[..., 0].ravel(), used_centres[..., 1].ravel()],
                  names=("frame", "wavelength", "x", "y"))
    ctab["x"].unit = ctab["y"].unit = u.pix
    meta = {"source": str(source), "window_size": ws, "window_radius": float(window_radius),
            "window_order": float(window_order), "centroid": centroid if centres is None
            else "given", "n_bad_pixels": n_bad_total, "bad_pixels": bad_pixels}
    return KernelPhaseData(kp, wl, ps, km, phases=phases, amplitudes=amps, centres=ctab,
                           header=header, meta=meta)
