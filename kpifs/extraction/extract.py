"""Batched per-wavelength kernel-phase extraction.

For each wavelength one Fourier operator at the model's uv points
(`kpifs.model.fourier`: separable products when the uv points lie on a lattice, as
for every grid pupil model; a non-uniform FFT or the dense DFT matrix
``M[b, pix] = exp(-2 pi i (u_b x + v_b y)/lam)`` otherwise) is built for the
window's pixels, kept in a bounded module-level cache, and applied to whole
batches of frames. The window is cut at the integer pixel nearest the star
centre; the sub-pixel remainder ``delta`` is applied afterwards as the exact
phase ramp ``+2 pi b.delta/lam``, so the star centre is the DFT origin without
interpolating the image. The apodisation follows the star to
`~kpifs.model.window.WINDOW_QUANTUM` of a pixel, so windows are cached too.

`extract_kernel_phases` checks its inputs once (`_check_inputs`) and then runs
`_extract_batch` on each batch of frames of each channel.
"""
import functools
import logging
import warnings
from dataclasses import dataclass
from threading import Lock

import numpy as np
from astropy import units as u

from .._checks import drop_dead_channels
from .._utils import progress as progress_bar, thread_map, to_quantity
from ..data import KernelPhaseData
from ..exceptions import KpifsError, KpifsWarning
from ..model.fourier import METHODS as FOURIER_METHODS, fourier_operator
from ..io.pages import release_pages
from ..io.wavelengths import check_wavelengths
from ..model.kernel import MAS, KernelModel, load_kernel_model
from .prepare import CENTROID_METHODS, cut_out, fill_bad_pixels, find_centres
from ..model.sampling import measured_rows
from ..model.window import WINDOW_QUANTUM, ExtractionWindow

__all__ = ["extract_kernel_phases"]

log = logging.getLogger(__name__)


def _as_frames(data, nwave, source):
    data = np.asarray(data) if not hasattr(data, "shape") else data
    if data.ndim == 2 and nwave == 1:
        data = np.asarray(data)[None, None]
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


@dataclass
class _Plan:
    """Checked inputs of one extraction."""

    cube: object                  # (nframe, nwave, ny, nx) array-like, read per batch
    wavelengths: u.Quantity
    pixscale: u.Quantity
    model: KernelModel
    window: ExtractionWindow
    centres: np.ndarray           # (nframe, nwave, 2) or None: found per batch
    mask: np.ndarray              # broadcast to the cube, or None
    centroid: str
    bad_pixels: str
    source: str
    fourier: str = "auto"
    precision: str = "double"

    def __post_init__(self):
        # the model's arrays in the layout the products want, made once per extraction
        self.uv_t = np.ascontiguousarray(self.model.uv.to_value(u.m).T)
        self.kernel_t = self.model.kernel.T
        # phase per pixel of shift at each channel and uv point: (nwave, 2, nuv)
        per_m = 2 * np.pi * self.pixscale.to_value(u.mas) * MAS / self.wavelengths.to_value(u.m)
        self.ramp = per_m[:, None, None] * self.uv_t[None]


def _check_inputs(data, pupil, *, wavelengths, pixscale, centres, mask, window, centroid,
                  bad_pixels, on_nyquist, source, fourier="auto", precision="double"):
    """Validate everything once; return the `_Plan` of the extraction."""
    wl = check_wavelengths(to_quantity(wavelengths, u.um, name="wavelengths"), source=source)
    ps = to_quantity(pixscale, u.mas, name="pixel scale")
    if not np.isfinite(ps.value) or ps.value <= 0:
        raise KpifsError(f"{source}: pixel scale must be > 0, got {ps}")
    if bad_pixels not in ("fill", "exclude"):
        raise KpifsError(f"bad_pixels must be 'fill' or 'exclude', got {bad_pixels!r}")
    if fourier not in FOURIER_METHODS:
        raise KpifsError(f"unknown Fourier method {fourier!r}: use one of {FOURIER_METHODS}")
    if precision not in PRECISIONS:
        raise KpifsError(f"precision must be one of {tuple(PRECISIONS)}, got {precision!r}")
    if centroid not in CENTROID_METHODS:
        raise KpifsError(f"unknown centroid method {centroid!r}: use one of {CENTROID_METHODS}")
    km = load_kernel_model(pupil) if not isinstance(pupil, KernelModel) else pupil
    km = km.for_wavelengths(wl, ps, on_nyquist=on_nyquist, source=source)
    cube = _as_frames(data, len(wl), source)
    nframe, nwave, ny, nx = cube.shape
    try:
        if window is None:
            window = ExtractionWindow.default((ny, nx))
        elif not isinstance(window, ExtractionWindow):
            raise KpifsError(f"window must be an ExtractionWindow, got {window!r}")
        elif window.size > min(ny, nx):
            raise KpifsError(f"window of {window.size} pixels is larger than the {ny}x{nx} "
                             f"image")
    except KpifsError as exc:
        raise KpifsError(f"{source}: {exc}") from None
    if mask is not None:
        mask = np.asarray(mask, bool)
        try:
            mask = np.broadcast_to(mask, cube.shape)
        except ValueError:
            raise KpifsError(f"{source}: mask of shape {mask.shape} does not match the cube "
                             f"{cube.shape}") from None
    if centres is not None:
        c = np.asarray(centres, float)
        try:
            centres = np.broadcast_to(c, (nframe, nwave, 2)).copy()
        except ValueError:
            raise KpifsError(f"centres of shape {c.shape} do not match ({nframe}, {nwave}, 2)") \
                from None
    return _Plan(cube, wl, ps, km, window, centres, mask, centroid, bad_pixels, str(source),
                 fourier, precision)


#: Precision of the Fourier products: ``'single'`` (float32) halves their time and
#: memory traffic and adds ~1e-6 rad to the kernel phases (2.8e-6 at most, 2e-7 rms on
#: the 300 x 22 x 64^2 benchmark cube: 2e-4 of the frames' photon-noise scatter).
PRECISIONS = {"double": np.float64, "single": np.float32}

#: Pages of a memory-mapped input are given back (`~kpifs.io.pages.release_pages`) each time
#: this many bytes have been read: the resident input stays below it, at any cube's size.
RELEASE_BYTES = 32 * 2 ** 20

#: A slice with more than this fraction of non-finite pixels is a bad frame.
MAX_BAD_FRACTION = 0.5
#: Negative pixels over this fraction of a slice's positive flux: a warning (background).
NEGATIVE_FLUX_WARN = 0.1
#: The fewest good frames a cube of at least that many frames must keep.
MIN_GOOD_FRAMES = 3


def _slice_quality(sl, finite, all_finite, total=None):
    """Why each image of a batch is unusable (``''`` when it is usable), and its flux.

    Returns ``(why, total, negative)``: *total* the summed flux (given when
    known: every pixel finite) and *negative* the flux of the negative pixels
    of each image.
    """
    n_pix = sl.shape[1] * sl.shape[2]
    clean = (sl if all_finite else np.where(finite, sl, 0.0)).reshape(len(sl), n_pix)
    if total is None or not all_finite:
        total = clean.sum(axis=1)
    # sum |x| = positive - negative flux: one pass for the negative flux and for empty images
    absolute = np.abs(clean).sum(axis=1)
    negative = 0.5 * (total - absolute)
    why = np.full(len(sl), "", dtype=object)
    why[total <= 0] = "no positive flux"
    if not all_finite:
        why[n_pix - finite.sum(axis=(1, 2)) > MAX_BAD_FRACTION * n_pix] = "mostly non-finite"
    why[absolute == 0] = "empty"
    return why, total, negative


#: Interpolated (bad) pixels carrying more than this fraction of a slice's flux (a NaN
#: patch on the core) are worth a warning; a lone dead spaxel off the peak carries a few %.
CORE_FLUX_WARN = 0.1


@dataclass
class _BatchResult:
    """What `_extract_batch` gives back for frames ``f0:f1`` of one channel."""

    kp: np.ndarray
    phases: np.ndarray
    amplitudes: np.ndarray
    centres: np.ndarray
    bad: np.ndarray               # (nbatch,) object: '' or why the image is unusable
    n_bad_pixels: int = 0
    n_inf: int = 0
    n_clipped: int = 0
    core_nan: int = 0
    negative: int = 0


def _extract_batch(plan, iw, f0, f1, op):
    """Kernel phases of frames ``f0:f1`` at channel *iw* with the Fourier operator *op*.

    Unusable images (empty, mostly non-finite, no positive flux, centre off the
    image) are reported in ``bad`` and give NaN rows; the caller decides.
    """
    win = plan.window
    nx, ny = plan.cube.shape[3], plan.cube.shape[2]
    sl = np.array(plan.cube[f0:f1, iw], dtype=float)
    nb = f1 - f0
    if plan.mask is not None:
        sl[plan.mask[f0:f1, iw]] = np.nan
    # a finite sum per image says every pixel is finite (NaN and inf propagate), without
    # a pass over the batch; the pixel-wise test only when some sum is not
    total = sl.reshape(nb, -1).sum(axis=1)
    all_finite = bool(np.isfinite(total).all())
    finite = None if all_finite else np.isfinite(sl)
    why, total, neg = _slice_quality(sl, finite, all_finite, total)
    res = _BatchResult(np.full((nb, plan.model.n_kp), np.nan),
                       np.full((nb, plan.model.n_uv), np.nan),
                       np.full((nb, plan.model.n_uv), np.nan),
                       np.full((nb, 2), np.nan), why)
    if not all_finite:
        res.n_bad_pixels = int(sl.size - finite.sum())
        res.n_inf = int(np.isinf(sl).sum())
        sl[~finite] = np.nan
    # total = positive + negative flux
    res.negative = int(np.sum((why == "") & (-neg > NEGATIVE_FLUX_WARN * (total - neg))))
    good = np.flatnonzero(res.bad == "")
    if not len(good):
        return res
    every = len(good) == nb       # the usual case: no copies of the batch
    if not every:
        sl = sl[good]
        finite = None if all_finite else finite[good]
    bc = find_centres(sl, method=plan.centroid) if plan.centres is None \
        else plan.centres[f0:f1, iw][good]
    off = ((bc[:, 0] < -0.5) | (bc[:, 0] > nx - 0.5) | (bc[:, 1] < -0.5)
           | (bc[:, 1] > ny - 0.5) | ~np.all(np.isfinite(bc), axis=1))
    if off.any():
        res.bad[good[off]] = "star centre outside the image"
        good, sl, bc = good[~off], sl[~off], bc[~off]
        finite = None if all_finite else finite[~off]
        every = False
        if not len(good):
            return res
    if not all_finite:
        filled = fill_bad_pixels(sl if plan.bad_pixels == "fill" else sl.copy())
        # interpolated (or missing) flux is invented data: say so when it is much of the PSF
        made = np.where(finite, 0.0, np.abs(filled)).sum(axis=(1, 2))
        res.core_nan = int(np.sum(made > CORE_FLUX_WARN * np.abs(filled).sum(axis=(1, 2))))
        if plan.bad_pixels != "fill":
            sl[~finite] = 0.0
    # the edge matters where the window still weighs more than 1/e
    edge = np.minimum.reduce([bc[:, 0] + 0.5, nx - 0.5 - bc[:, 0],
                              bc[:, 1] + 0.5, ny - 0.5 - bc[:, 1]])
    res.n_clipped = int(np.sum(edge < win.radius))
    # cut-out and window in one pass: a view of the batch when one window serves it
    src, delta = cut_out(sl, bc, win.size, copy=False)
    cut = win.apply(src, delta, quantum=WINDOW_QUANTUM, out=np.empty(src.shape, op.dtype))
    re, im = op.apply(cut)
    ph = np.arctan2(im, re)
    # the sub-pixel remainder of the centre, as an exact phase ramp
    ramp = plan.ramp[iw]
    ph += delta[:, :1] * ramp[0]
    ph += delta[:, 1:] * ramp[1]
    _wrap_phases(ph)
    re *= re
    im *= im
    re += im
    amps = np.sqrt(re, out=re)
    amps /= cut.reshape(len(cut), -1).sum(axis=1, dtype=np.float64)[:, None]
    kp = ph @ plan.kernel_t
    if every:
        res.kp, res.phases, res.amplitudes, res.centres = kp, ph, amps, bc
    else:
        res.kp[good], res.phases[good], res.amplitudes[good], res.centres[good] = \
            kp, ph, amps, bc
    return res


def _wrap_phases(ph):
    """Bring phases within ``[-pi, pi)`` in place, as ``(ph + pi) % (2 pi) - pi`` does (to
    rounding) at a fraction of its cost: arctan2's range plus the sub-pixel ramp, less than
    2 pi at a sampled baseline, needs one turn at most."""
    if np.abs(ph).max() >= 3 * np.pi:       # not reached for sampled baselines
        ph[...] = (ph + np.pi) % (2 * np.pi) - np.pi
        return ph
    ph[ph >= np.pi] -= 2 * np.pi
    ph[ph < -np.pi] += 2 * np.pi
    return ph


def _centre_table(frames, wavelengths, centres):
    """The star centres used, as a `~astropy.table.QTable` (made when first read)."""
    from astropy.table import QTable      # not at import: the command line's start
    nwave = len(wavelengths)
    frame_idx, _ = np.meshgrid(frames, np.arange(nwave), indexing="ij")
    ctab = QTable([frame_idx.ravel(), np.broadcast_to(wavelengths, (len(frames), nwave)).ravel(),
                   centres[..., 0].ravel(), centres[..., 1].ravel()],
                  names=("frame", "wavelength", "x", "y"))
    ctab["x"].unit = ctab["y"].unit = u.pix
    return ctab


def _ranges(idx):
    """``[0, 1, 2, 5, 7, 8]`` -> ``'0-2, 5, 7-8'`` (frame lists in messages and cards)."""
    out, idx = [], sorted(int(i) for i in idx)
    for i in idx:
        if out and i == out[-1][1] + 1:
            out[-1][1] = i
        else:
            out.append([i, i])
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in out)


def _bad_frames(bad, wavelengths, policy, source):
    """Frames to drop from the per-image reasons *bad* ``(nframe, nwave)``; refuse per *policy*."""
    nframe = bad.shape[0]
    drop = np.flatnonzero((bad != "").any(axis=1))
    if not len(drop):
        return drop
    reasons = {}
    for f in drop:
        iw = int(np.flatnonzero(bad[f] != "")[0])
        reasons.setdefault(f"{bad[f, iw]} (first at {wavelengths[iw]:.3f})", []).append(f)
    what = "; ".join(f"frame(s) {_ranges(v)}: {k}" for k, v in reasons.items())
    if policy == "fail":
        raise KpifsError(f"{source}: {len(drop)} bad frame(s) of {nframe}: {what} "
                         f"(use bad_frames='drop' / --bad-frames drop to leave them out)")
    n_good = nframe - len(drop)
    if n_good == 0 or n_good < min(MIN_GOOD_FRAMES, nframe):
        raise KpifsError(f"{source}: only {n_good} good frame(s) of {nframe} ({what}): too few "
                         f"to use")
    warnings.warn(f"{source}: {len(drop)} bad frame(s) of {nframe} dropped: {what}",
                  KpifsWarning, stacklevel=3)
    return drop


def extract_kernel_phases(data, pupil, *, wavelengths, pixscale, window=None, centres=None,
                          mask=None, centroid="com", bad_pixels="fill", on_nyquist="drop",
                          batch_size=256, header=None, source="<array>", keep_phases=True,
                          detpa=None, progress=False, fourier="auto", bad_frames="drop",
                          precision="double"):
    """Kernel phases of every frame and channel of an IFS cube.

    Parameters
    ----------
    data : array-like, shape (nwave, ny, nx) or (nframe, nwave, ny, nx)
        Images (memory-mapped arrays are read one batch of frames at a time).
    pupil : `~kpifs.model.kernel.KernelModel`, `~kpifs.model.pupil.PupilModel` or str
        Kernel model, pupil model, telescope name or FITS file (see
        `~kpifs.model.kernel.load_kernel_model`).
    wavelengths : `~astropy.units.Quantity`, shape (nwave,)
    pixscale : `~astropy.units.Quantity`
        Angular pixel size.
    window : `~kpifs.model.window.ExtractionWindow`, optional
        Cut-out and apodisation; default `ExtractionWindow.default
        <kpifs.model.window.ExtractionWindow.default>` for the image size. Pixels of
        the cut-out outside the image count as excluded.
    centres : array-like, optional
        Star centres ``(x, y)`` in pixels, broadcastable to (nframe, nwave, 2);
        found with `~kpifs.extraction.prepare.find_centres` (method *centroid*) if omitted.
    mask : array-like of bool, optional
        True for bad pixels, broadcastable to the data; NaN pixels are bad too.
    centroid : str
        Centroid method when *centres* is omitted.
    bad_pixels : {'fill', 'exclude'}
        ``'fill'``: interpolate bad pixels from their neighbours
        (`~kpifs.extraction.prepare.fill_bad_pixels`); ``'exclude'``: leave them out of the
        Fourier sums (set to zero).
    on_nyquist : {'drop', 'raise', 'own'}
        What to do with uv points beyond the Nyquist limit of some channel
        (see `~kpifs.model.kernel.KernelModel.for_wavelengths`; ``'own'``: each
        channel keeps its own, ``meta['channel_n_kp']``).
    batch_size : int
        Frames processed together (bounds the memory in use).
    header : `~astropy.io.fits.Header`, optional
        Header of the input, kept in the result.
    source : str
        Name of the input, used in messages and provenance.
    keep_phases : bool
        Keep raw Fourier phases and amplitudes in the result.
    detpa : array-like, optional
        Detector position angle of each frame (deg; see `kpifs.io.angles`),
        carried into the result.
    progress : bool
        Show a progress bar over the channels (on a terminal).
    bad_frames : {'drop', 'fail'}
        What to do with a frame that is unusable at some channel (empty, more
        than half non-finite, no positive flux, centre outside the image):
        ``'drop'`` leaves it out with a `~kpifs.exceptions.KpifsWarning` naming
        the frames (a cube left with fewer than 3 good frames is refused),
        ``'fail'`` refuses the cube. The result's ``meta['dropped_frames']``
        lists the input indices of the frames left out.
    fourier : {'auto', 'separable', 'nufft', 'dense'}
        How the Fourier transform at the uv points is computed (see
        `kpifs.model.fourier`); every path gives the same phases to ~1e-9 rad.
        ``'auto'``: separable products when the uv points lie on a lattice
        (grid pupil models), else a non-uniform FFT when finufft is
        installed, else the dense DFT matrix.
    precision : {'double', 'single'}
        Precision of the Fourier products. ``'single'`` (float32) makes them
        ~2x faster and adds ~1e-6 rad to the kernel phases (at most 2.8e-6
        rad on a 300-frame, 22-channel CHARIS-like cube of 2e5 photons per
        image: 2e-4 of the frames' photon-noise scatter); ``'double'`` agrees
        with the dense reference to 1e-9 rad.

    Returns
    -------
    `~kpifs.data.KernelPhaseData`

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import extract_kernel_phases
    >>> from kpifs.simulation.simulate import simulate_psf
    >>> wl = [1.6] * u.um
    >>> cube = simulate_psf("subaru", wl, pixscale=10.42 * u.mas, shape=(40, 40))
    >>> kpd = extract_kernel_phases(cube, "subaru", wavelengths=wl, pixscale=10.42 * u.mas)
    >>> kpd.shape[:2], bool(np.abs(kpd.kp).max() < 1e-3), kpd.window.size
    ((1, 1), True, 40)
    """
    plan = _check_inputs(data, pupil, wavelengths=wavelengths, pixscale=pixscale,
                         centres=centres, mask=mask, window=window, centroid=centroid,
                         bad_pixels=bad_pixels, on_nyquist=on_nyquist, source=source,
                         fourier=fourier, precision=precision)
    km, win = plan.model, plan.window
    nframe = plan.cube.shape[0]
    detpa = _frame_angles(detpa, nframe, source)
    if bad_frames not in ("drop", "fail"):
        raise KpifsError(f"bad_frames must be 'drop' or 'fail', got {bad_frames!r}")
    kp, used_centres, bad, phases, amps, count = _extract_channels(
        plan, batch_size=batch_size, keep_phases=keep_phases, progress=progress, source=source)
    bad, kp, used_centres, wl, phases, amps, dead = drop_dead_channels(
        bad, kp, used_centres, plan.wavelengths, phases, amps, source=source)
    drop = _bad_frames(bad, wl, bad_frames, source)
    keep = np.setdiff1d(np.arange(nframe), drop)
    _warn_counts(count, len(keep) * len(wl), win, source)
    if len(drop):
        kp, used_centres = kp[keep], used_centres[keep]
        phases, amps = (None, None) if not keep_phases else (phases[keep], amps[keep])
        detpa = None if detpa is None else detpa[keep]
    ctab = functools.partial(_centre_table, keep, wl, used_centres)
    kp, own = measured_rows(kp, km, dead)      # --nyquist own: each channel its first rows
    meta = {"source": str(source), "centroid": centroid if centres is None else "given",
            "n_bad_pixels": count["n_bad_pixels"], "bad_pixels": bad_pixels, "bad_frames":
            bad_frames, "dropped_frames": list(map(int, drop)), "dropped_channels": dead,
            "channel_n_kp": own}
    return KernelPhaseData(kp, wl, plan.pixscale, km, window=win, phases=phases,
                           amplitudes=amps, centres=ctab, header=header, detpa=detpa, meta=meta)


def _frame_angles(detpa, nframe, source):
    """The frames' detector position angles (deg) as an array of one per frame, or None."""
    if detpa is None:
        return None
    detpa = np.atleast_1d(to_quantity(detpa, u.deg, name="detector position angle").value)
    if detpa.shape != (nframe,):
        raise KpifsError(f"{source}: {detpa.size} detector position angle(s) for {nframe} "
                         f"frame(s)")
    return detpa


#: What `_extract_batch` counts in each slice, summed over the cube (`_warn_counts`).
_COUNTS = ("n_bad_pixels", "n_inf", "n_clipped", "core_nan", "negative")


def _extract_channels(plan, *, batch_size, keep_phases, progress, source):
    """Every channel of *plan*'s cube, in batches of frames: kernel phases (and the raw
    phases and amplitudes), centres used, each slice's reason to be unusable (or ''), and
    the counts `_warn_counts` reports."""
    km, win, wl = plan.model, plan.window, plan.wavelengths
    nframe, nwave = plan.cube.shape[:2]
    kp = np.empty((nframe, nwave, km.n_kp))
    phases = np.empty((nframe, nwave, km.n_uv)) if keep_phases else None
    amps = np.empty((nframe, nwave, km.n_uv)) if keep_phases else None
    used_centres = np.empty((nframe, nwave, 2))
    bad = np.full((nframe, nwave), "", dtype=object)
    uv, prad = km.uv.to_value(u.m), plan.pixscale.to_value(u.mas) * MAS
    image_bytes, read, lock = plan.cube[0, 0].nbytes, [0], Lock()

    def channel(iw):
        # wavelength outermost: each operator is built (or fetched) once per call; the
        # channels are independent (each writes its own slices) and share the cores
        op = fourier_operator(uv, wl[iw].to_value(u.m), prad, (win.size, win.size),
                              method=plan.fourier, dtype=PRECISIONS[plan.precision])
        counts = np.zeros(len(_COUNTS), int)
        for f0 in range(0, nframe, batch_size):
            f1 = min(nframe, f0 + batch_size)
            res = _extract_batch(plan, iw, f0, f1, op)
            with lock:    # a memory-mapped input's pages go back every RELEASE_BYTES read
                read[0] += (f1 - f0) * image_bytes
                release = read[0] >= RELEASE_BYTES
                read[0] = 0 if release else read[0]
            if release:
                release_pages(plan.cube)
            kp[f0:f1, iw], used_centres[f0:f1, iw], bad[f0:f1, iw] = res.kp, res.centres, res.bad
            counts += [getattr(res, k) for k in _COUNTS]
            if keep_phases:
                phases[f0:f1, iw], amps[f0:f1, iw] = res.phases, res.amplitudes
        return counts
    # photutils' centroids run with the warnings filters changed: those channels in turn
    count = dict(zip(_COUNTS, np.sum(thread_map(channel, range(nwave), serial=(
        plan.centres is None and plan.centroid in ("quadratic", "2dg")), wrap=(
        lambda it: progress_bar(it, desc=f"extracting {source}"[:40], unit="channel",
                                total=nwave, enabled=progress))), axis=0).tolist()))
    return kp, used_centres, bad, phases, amps, count


def _warn_counts(count, n_slices, win, source):
    """The warnings (and the log line) that the counts of `_extract_channels` call for."""
    if count["n_clipped"]:
        warnings.warn(f"{source}: the star is closer to the image edge than the window radius "
                      f"({win.radius:.1f} pixels) in {count['n_clipped']} of {n_slices} "
                      f"slice(s); the edge cuts the window (use a smaller --window-radius)",
                      KpifsWarning, stacklevel=3)
    if count["core_nan"]:
        warnings.warn(f"{source}: bad or NaN pixels on the PSF core (more than "
                      f"{CORE_FLUX_WARN:.0%} of the flux interpolated) in {count['core_nan']} "
                      f"of {n_slices} slice(s): their kernel phases rest on interpolated or "
                      f"missing pixels", KpifsWarning, stacklevel=3)
    if count["n_inf"]:
        warnings.warn(f"{source}: {count['n_inf']} infinite pixel value(s), treated as bad "
                      f"pixels", KpifsWarning, stacklevel=3)
    if count["negative"]:
        warnings.warn(f"{source}: negative pixels hold more than "
                      f"{NEGATIVE_FLUX_WARN:.0%} of the positive flux in {count['negative']} "
                      f"slice(s) (background over-subtracted?)", KpifsWarning, stacklevel=3)
    if count["n_bad_pixels"]:
        log.info("%s: %d bad or NaN pixels excluded from the Fourier sums", source,
                 count["n_bad_pixels"])
