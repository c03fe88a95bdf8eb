"""The kernel phases' response to the pixels the extraction fills in every frame.

A pixel bad in every frame (dead: non-finite or masked) is filled by
`~kpifs.extraction.prepare.fill_bad_pixels` from its neighbours; near the star's core
the fill misses the steep PSF, and the error is a faint source fixed on the detector,
the same in every frame, which no frame-to-frame scatter measures.
`filled_pixel_rows` images it: each such pixel's response of the kernel phases, one
channel at a time, by finite differences through `extract_kernel_phases` of the
frames' mean cube (issue 39: the spectral-differential search fits an amplitude to
them, `kpifs.detect.sdk.SpectralStack`).
"""
import numpy as np

from .extract import extract_kernel_phases
from .prepare import fill_bad_pixels, find_centres

__all__ = ["filled_pixel_rows", "always_bad_pixels"]

#: The finite-difference step of a filled pixel: this fraction of its filled value...
FILLED_STEP = 0.01
#: ...and at least this fraction of its channel's brightest pixel.
FILLED_STEP_FLOOR = 1e-3
#: Perturbed pixels extracted at a time (each one frame of the mean cube).
FILLED_CHUNK = 16


def always_bad_pixels(data, mask=None, *, frames=None, channels=None):
    """The frames' mean cube and the pixels bad in all of them, channel by channel.

    Parameters
    ----------
    data : array-like (nframe, nwave, ny, nx)
        Images (memory-mapped arrays are read one channel at a time).
    mask : array-like of bool, optional
        True for bad pixels, broadcastable to *data*; non-finite pixels are bad too.
    frames, channels : array-like of int, optional
        The frames and channels to read (all by default).

    Returns
    -------
    mean : ndarray (q, ny, nx)
        Each pixel's mean over the frames where it is good, NaN where it is bad in all.
    bad : ndarray of bool (q, ny, nx)
        The pixels bad in every frame.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.extraction.filled import always_bad_pixels
    >>> d = np.ones((3, 1, 4, 4)); d[:, 0, 1, 2] = np.nan; d[0, 0, 3, 3] = np.inf
    >>> mean, bad = always_bad_pixels(d)
    >>> np.argwhere(bad).tolist(), float(mean[0, 3, 3])
    ([[0, 1, 2]], 1.0)
    """
    shape = np.shape(data)
    frames = np.arange(shape[0]) if frames is None else np.asarray(frames, int)
    channels = np.arange(shape[1]) if channels is None else np.asarray(channels, int)
    if mask is not None:
        mask = np.broadcast_to(np.asarray(mask, bool), shape)
    mean = np.empty((len(channels),) + tuple(shape[2:]))
    bad = np.empty(mean.shape, bool)
    for i, c in enumerate(channels):
        sl = np.array(data[:, c], dtype=float)[frames]
        good = np.isfinite(sl)
        if mask is not None:
            good &= ~mask[frames, c]
        n = good.sum(axis=0)
        bad[i] = n == 0
        with np.errstate(invalid="ignore", divide="ignore"):
            mean[i] = np.where(good, sl, 0.0).sum(axis=0) / n
        mean[i][bad[i]] = np.nan
    return mean, bad


def filled_pixel_rows(data, kernel_model, *, wavelengths, pixscale, window, mask=None,
                      frames=None, channels=None, radius=None, centroid="com",
                      on_nyquist="drop"):
    """Rows (n, q, p) of the kernel phases' response to each pixel bad in every frame
    within *radius* of the star, one row per pixel and channel (that channel's response
    only, the others 0), and the pixels ``(y, x)``.

    The response is a finite difference through `extract_kernel_phases` (the
    extraction's own window, kernel model, centroid and fill) of the frames' mean cube,
    its bad pixels filled (`~kpifs.extraction.prepare.fill_bad_pixels`): the pixel raised
    by `FILLED_STEP` of its filled value (at least `FILLED_STEP_FLOOR` of its channel's
    brightest pixel), the kernel phases' change -- the scale of a fill error of that
    size, which a search fits with an amplitude of its own.

    Parameters
    ----------
    data : array-like (nframe, nwave, ny, nx)
    kernel_model : `~kpifs.model.kernel.KernelModel`
        The extraction's (its uv points kept).
    wavelengths, pixscale, window
        The extraction's channels (those of *channels*), pixels and window.
    mask, frames, channels
        `always_bad_pixels`.
    radius : float, optional
        Pixels from the star's centre (in each channel's mean image); the window's
        radius by default.
    centroid, on_nyquist : str
        The extraction's.

    Returns
    -------
    rows : ndarray (n, q, p) or None
        None when no pixel is bad in every frame within *radius*.
    pixels : ndarray of int (m, 2)
        The pixels ``(y, x)`` with rows, each once (its rows the channels where it is
        bad, in order).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs.extraction.filled import filled_pixel_rows
    >>> from kpifs.model.window import ExtractionWindow
    >>> from kpifs.simulation.simulate import simulate_psf
    >>> wl = [1.6, 1.7] * u.um
    >>> psf = simulate_psf("subaru", wl, pixscale=10.42 * u.mas, shape=(40, 40))
    >>> d = np.repeat(psf[None], 3, axis=0); d[:, :, 21, 22] = np.nan
    >>> rows, pix = filled_pixel_rows(d, "subaru", wavelengths=wl,
    ...                               pixscale=10.42 * u.mas,
    ...                               window=ExtractionWindow.default((40, 40)))
    >>> rows.shape[:2], pix.tolist(), bool(np.all(rows[0, 1] == 0))
    ((2, 2), [[21, 22]], True)
    """
    mean, bad = always_bad_pixels(data, mask, frames=frames, channels=channels)
    radius = window.radius if radius is None else float(radius)
    base = fill_bad_pixels(mean.copy())
    centre = find_centres(base, method=centroid)             # (q, 2): x, y
    yy, xx = np.indices(base.shape[1:])
    near = bad & (np.hypot(xx - centre[:, :1, None], yy - centre[:, 1:, None]) < radius)
    pixels = np.argwhere(near.any(axis=0))
    if not len(pixels):
        return None, pixels
    kw = dict(wavelengths=wavelengths, pixscale=pixscale, window=window, centroid=centroid,
              on_nyquist=on_nyquist, keep_phases=False, bad_frames="fail", source="filled")
    k0 = extract_kernel_phases(base[None], kernel_model, **kw).kp[0]
    top = base.max(axis=(1, 2))
    rows = []
    for start in range(0, len(pixels), FILLED_CHUNK):
        chunk = pixels[start:start + FILLED_CHUNK]
        pert = np.repeat(base[None], len(chunk), axis=0)
        for j, (y, x) in enumerate(chunk):
            on = near[:, y, x]
            pert[j, on, y, x] += np.maximum(FILLED_STEP * np.abs(base[on, y, x]),
                                            FILLED_STEP_FLOOR * top[on])
        k1 = extract_kernel_phases(pert, kernel_model, **kw).kp
        for j, (y, x) in enumerate(chunk):
            for c in np.flatnonzero(near[:, y, x]):
                row = np.zeros_like(k0)
                row[c] = k1[j, c] - k0[c]
                rows.append(row)
    return np.array(rows), pixels
