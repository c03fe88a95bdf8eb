"""Per-pixel noise of the images (JWST ``ERR``) propagated to the kernel phases.

The extraction is linear in the pixels to first order: a pixel noise of
variance ``var`` gives the kernel phases of one frame the covariance
``J diag(var) J^T``, ``J = dk/dI`` (`kernel_jacobian`). The
Jacobian of each channel is taken at the mean frame around its mean centre
(the frames of one star differ by far less than their Fourier amplitudes);
each frame's own variance, cut around its own centre, gives its errors.

`attach_pixel_noise` puts the result in the `~kpifs.data.KernelPhaseData`:
``kp_err`` (per frame, stored as KP-SIGM, as jwst-kpi writes it from
``ERR``) and ``meta['pixel_covariance']`` (one frame's covariance per
channel, ``(nwave, nkp, nkp)``), with ``meta['pixel_noise']`` naming the
source.

The frames' error model (`kpifs.calibration.errormodel`) keeps only the leading modes of
the frames' scatter, about half as many as the frames' degrees of freedom:
from few frames no more directions are measured. The rest of the kernel
phases is thrown away, and where the kernel phases' noise is uneven (the
uv points near the pupil's edge, where the transfer function is small) the
leading modes are the noisiest directions. `complement_rows` gives the
calibrated mean the propagated pixel noise in the directions the modes leave
out, so that a calibration keeps every kernel phase, each weighted by its
own noise (`~kpifs.calibration.calibrate.calibrate`, ``pixel_noise='auto'``).
"""
import logging
import warnings

import numpy as np
from astropy import units as u

from .._utils import to_quantity
from ..exceptions import KpifsError, KpifsWarning
from ..extraction.prepare import cut_out
from ..model.sampling import unmeasured

__all__ = ["attach_pixel_noise", "pixel_noise", "scatter_ratio", "calibrated_pixel_covariance",
           "complement_rows", "propagated_covariance", "kernel_jacobian",
           "MIN_SCATTER_RATIO", "MIN_SCATTER_DOF"]

log = logging.getLogger(__name__)

#: Frames read at a time (memory: one batch of images and variances).
BATCH = 64


def _channel_index(cube_wl, kpd_wl):
    """Indices in the cube of the data's channels (dead channels were dropped)."""
    cw = np.asarray(cube_wl.to_value(u.um))
    return [int(np.argmin(np.abs(cw - w))) for w in kpd_wl.to_value(u.um)]


def pixel_noise(images, variance, kpd, *, counts=None):
    """Kernel-phase errors of each frame and one frame's covariance, from pixel variances.

    Parameters
    ----------
    images, variance : array-like, shape (nframe, kpd.n_wave, ny, nx)
        The frames extracted into *kpd* (every frame of the cube, in order,
        at *kpd*'s channels; read in batches) and their per-pixel variance
        (NaN counts 0).
    kpd : `~kpifs.data.KernelPhaseData`
        Their extraction: its kernel model, window, channels and centres
        (``kpd.centres``: the frames kept, by index).
    counts : dict, optional
        Filled with ``'pixels'``, the pixels of the cut-outs whose image is
        finite, and ``'invalid'``, those of them whose variance is not a number
        > 0 (NaN, infinite, zero or negative: no pixel is noiseless). Those are
        given the largest valid variance of their cut-out (never less noise
        than their neighbours).

    Returns
    -------
    kp_err : ndarray, shape (kpd.n_frame, kpd.n_wave, kpd.n_kp)
    covariance : ndarray, shape (kpd.n_wave, kpd.n_kp, kpd.n_kp)
        Of one frame of mean variance.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import extract_kernel_phases
    >>> from kpifs.calibration.pixelnoise import pixel_noise
    >>> from kpifs.simulation.simulate import simulate_psf
    >>> psf = 1e6 * simulate_psf("niriss_nrm", [1.6] * u.um, pixscale=10.42 * u.mas,
    ...                          shape=(32, 32), npup=48)
    >>> frames = np.stack([psf, psf])
    >>> kpd = extract_kernel_phases(frames, "niriss_nrm", wavelengths=[1.6] * u.um,
    ...                             pixscale=10.42 * u.mas, centres=(16, 16))
    >>> err, cov = pixel_noise(frames, frames + 100.0, kpd)
    >>> err.shape == (2, 1, kpd.n_kp), bool(np.allclose(err[0, 0] ** 2, np.diag(cov[0])))
    (True, True)
    """
    km, win = kpd.kernel_model, kpd.window
    ws = win.size
    ctab = kpd.centres
    frames = np.unique(np.asarray(ctab["frame"], int))
    cen = np.stack([np.asarray(ctab["x"].value, float), np.asarray(ctab["y"].value, float)],
                   -1).reshape(len(frames), kpd.n_wave, 2)
    err = np.empty((len(frames), kpd.n_wave, km.n_kp))
    cov = np.empty((kpd.n_wave, km.n_kp, km.n_kp))
    for j in range(kpd.n_wave):
        # the mean frame, each frame cut around its own centre: the PSF the Jacobian is of
        total, vtot, dsum = np.zeros((ws, ws)), np.zeros((ws, ws)), np.zeros(2)
        vcuts = []
        for b in range(0, len(frames), BATCH):
            idx = frames[b:b + BATCH]
            img = np.asarray(images[idx, j], float)
            good = np.isfinite(img)
            # bad pixels (NaN or infinite) count 0 in the Jacobian's PSF, as no flux
            img = np.where(good, img, 0.0)
            var = _valid_variance(np.asarray(variance[idx, j], float), good, counts)
            cut, delta = cut_out(img, cen[b:b + BATCH, j], ws)
            vcut, _ = cut_out(var, cen[b:b + BATCH, j], ws)
            total += cut.sum(0)
            vtot += vcut.sum(0)
            dsum += delta.sum(0)
            vcuts.append(vcut.reshape(len(idx), -1))
        mat = km.dft_matrix(kpd.wavelengths[j], kpd.pixscale, (ws, ws))
        jk = kernel_jacobian(total / len(frames), win.weights((dsum / len(frames))[None])[0],
                             mat, km)
        err[:, j] = np.sqrt(np.concatenate(vcuts) @ (jk ** 2).T)
        cov[j] = (jk * (vtot.ravel() / len(frames))[None, :]) @ jk.T
    return err, cov


def _valid_variance(var, good, counts):
    """Variances of a batch of images: 0 at bad pixels (their flux is filled in, not
    measured); at good pixels whose variance is not a number > 0, the largest valid one of
    their image; counted in *counts*."""
    valid = np.isfinite(var) & (var > 0)
    bad = good & ~valid
    if counts is not None:
        counts["pixels"] = counts.get("pixels", 0) + int(good.sum())
        counts["invalid"] = counts.get("invalid", 0) + int(bad.sum())
        counts["negative"] = counts.get("negative", 0) + int((good & (var < 0)).sum())
        counts["zero"] = counts.get("zero", 0) + int((good & (var == 0)).sum())
    out = np.where(valid & good, var, 0.0)
    if bad.any():
        top = out.reshape(len(out), -1).max(axis=1)
        out = np.where(bad, top[:, None, None], out)
    return out


#: Frames' scatter over propagated pixel noise (mean ratio of variances over the kernel
#: phases) below which the per-pixel noise contradicts the data: a pixel noise over twice
#: the frames' whole scatter (which it is part of). Under pixel noise alone the ratio
#: follows chi2_d / d with d >= `MIN_SCATTER_DOF` degrees of freedom: below 0.25 with
#: probability < 1e-4.
MIN_SCATTER_RATIO = 0.25
#: Fewest degrees of freedom (kernel phases x (frames - 1)) of the comparison.
MIN_SCATTER_DOF = 20


def scatter_ratio(kpd):
    """Mean, over the kernel phases each channel measures, of the frames' sample variance
    over the propagated pixel noise's (``kpd.kp_err**2`` averaged over the frames), and
    its degrees of freedom; ``(nan, 0)`` without per-frame errors or with one frame.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.calibration.pixelnoise import scatter_ratio
    >>> km = KernelModel.from_pupil(make_pupil("niriss_nrm"))
    >>> kp = np.random.default_rng(1).normal(0, 0.1, (50, 1, 15))
    >>> kpd = KernelPhaseData(kp, [4.8] * u.um, 65.6 * u.mas, km)
    >>> kpd.kp_err = np.full(kp.shape, 10.0)                 # 100 times the scatter
    >>> ratio, dof = scatter_ratio(kpd)
    >>> round(ratio, 5), dof
    (0.0001, 735)
    """
    if kpd.kp_err is None or kpd.n_frame < 2:
        return np.nan, 0
    err2 = np.mean(np.asarray(kpd.kp_err, float) ** 2, axis=0)
    var = np.nanvar(np.asarray(kpd.kp, float), axis=0, ddof=1)
    use = (err2 > 0) & np.isfinite(err2) & np.isfinite(var)
    if not use.any():
        return np.nan, 0
    return float(np.mean(var[use] / err2[use])), int(use.sum() * (kpd.n_frame - 1))


def _check_variance(kpd, cube, counts):
    """Whether *cube*'s per-pixel noise can be used for *kpd*: ``(None, 1)`` when it can,
    ``(why, 1)`` when it cannot (a sentence), ``(why, factor)`` when its variance must be
    scaled by *factor* to match the frames' own scatter."""
    src = cube.variance_source or "the variance"
    n, bad = counts.get("pixels", 0), counts.get("invalid", 0)
    if n and bad == n:
        kind = ("negative" if counts.get("negative") == n else "zero" if counts.get("zero")
                == n else "NaN, infinite, zero or negative")
        return f"{src} is {kind} at every pixel used: no noise can be read from it", None
    if bad:
        warnings.warn(f"{cube.name}: {src} is NaN, infinite, zero or negative at {bad} of the "
                      f"{n} good pixels used: given the largest {src} of their image",
                      KpifsWarning, stacklevel=3)
    ratio, dof = scatter_ratio(kpd)
    if dof >= MIN_SCATTER_DOF and ratio < MIN_SCATTER_RATIO:
        return (f"{src} predicts kernel-phase errors {1 / np.sqrt(ratio):.3g} times the "
                f"frames' own scatter ({kpd.n_frame} frames), which they are part of: it "
                f"contradicts the data (another unit than SCI, e.g. SCI normalised and "
                f"{src} not?)"), ratio
    return None, 1.0


def attach_pixel_noise(kpd, cube):
    """Propagate ``cube.variance`` (when the reader found one) into *kpd*.

    Sets ``kpd.kp_err``, ``kpd.meta['pixel_covariance']`` and
    ``kpd.meta['pixel_noise']`` (`pixel_noise`); does nothing without a
    variance. A variance that cannot be a noise (NaN, zero or negative at
    every pixel used) is not used; one whose propagated errors exceed the
    frames' own scatter by more than a factor ``1 / sqrt(MIN_SCATTER_RATIO)``
    (`scatter_ratio`: a pixel noise larger than the whole noise, e.g. SCI
    normalised and ERR left in DN/s) is scaled down to that scatter; a
    warning says which. Returns *kpd*.

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.io import read_cube, write_observation
    >>> from kpifs.calibration.pixelnoise import attach_pixel_noise
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> from kpifs.workflow import ExtractOptions, extract_observation
    >>> obs = simulate_scene("niriss", n_frames=3, npup=32, shape=(32, 32), seed=1)
    >>> tmp = tempfile.TemporaryDirectory()
    >>> files = write_observation(obs, tmp.name, layout="jwst")
    >>> opts = ExtractOptions(pupil="niriss_nrm")
    >>> kpd = extract_observation(files["target"], opts)    # calls attach_pixel_noise
    >>> kpd.meta["pixel_noise"], kpd.kp_err.shape == kpd.shape
    ('ERR', True)
    >>> tmp.cleanup()
    """
    if getattr(cube, "variance", None) is None:
        return kpd
    chans = _channel_index(cube.wavelengths, kpd.wavelengths)
    images = _Channels(cube.data, chans)
    variance = _Channels(cube.variance, chans)
    counts = {}
    kpd.kp_err, cov = pixel_noise(images, variance, kpd, counts=counts)
    if kpd.meta.get("channel_n_kp") is not None:      # rows a channel does not measure
        off = unmeasured(kpd.channel_n_kp, kpd.n_kp)
        kpd.kp_err = np.where(off, 0.0, kpd.kp_err)
        cov[off[:, :, None] | off[:, None, :]] = 0.0
    why, factor = _check_variance(kpd, cube, counts)
    if factor is None:
        kpd.kp_err = None
        warnings.warn(f"{cube.name}: {why}; not used: the kernel phases' noise is taken "
                      f"from the frames' scatter alone", KpifsWarning, stacklevel=2)
        kpd.header["KPPIXNOI"] = ("none", "per-pixel noise unusable: not propagated")
        return kpd
    if why is not None:
        warnings.warn(f"{cube.name}: {why}; its variance is scaled by {factor:.3g} to the "
                      f"frames' scatter (conservative: that scatter holds more than pixel "
                      f"noise)", KpifsWarning, stacklevel=2)
        kpd.kp_err = kpd.kp_err * np.sqrt(factor)
        cov = cov * factor
        kpd.header["KPPIXSCL"] = (float(f"{factor:.6g}"), "pixel variance scaled to frame scatter")
    kpd.meta["pixel_covariance"] = cov
    kpd.meta["pixel_noise"] = cube.variance_source or "variance"
    kpd.header["KPPIXNOI"] = (kpd.meta["pixel_noise"], "per-pixel noise propagated to KP-SIGM")
    log.info("%s: per-pixel noise (%s) propagated: median kernel-phase error %.3g rad per "
             "frame", cube.name, kpd.meta["pixel_noise"], float(np.median(kpd.kp_err)))
    return kpd


def calibrated_pixel_covariance(target, calibrators):
    """The pixel noise of a calibrated mean, per channel, or None when a star has none.

    ``P_t / N_t + sum_m P_m / (M^2 N_m)`` from each star's
    ``meta['pixel_covariance']`` (one frame's, `attach_pixel_noise`).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.calibration.pixelnoise import calibrated_pixel_covariance
    >>> km = KernelModel.from_pupil(make_pupil("niriss_nrm"))
    >>> def star(n):
    ...     return KernelPhaseData(np.zeros((n, 1, 15)), [4.8] * u.um, 65.6 * u.mas, km,
    ...                            meta={"pixel_covariance": np.eye(15)[None]})
    >>> float(calibrated_pixel_covariance(star(10), [star(5)])[0, 0, 0])
    0.30000000000000004
    """
    stars = [target, *calibrators]
    if any(k.meta.get("pixel_covariance") is None for k in stars):
        return None
    m = len(calibrators)
    out = np.asarray(target.meta["pixel_covariance"], float) / target.n_frame
    for c in calibrators:
        out = out + np.asarray(c.meta["pixel_covariance"], float) / (m * m * c.n_frame)
    return out


def complement_rows(rows, pixel_covariance, *, data=None, groups=8, rtol=1e-9):
    """Rows of the pixel noise in the directions an error model's rows leave out.

    Pixel noise is a floor: the frames' scatter there is mostly pixel noise, but
    a calibrated mean also carries the target's and calibrator's static
    difference. Given the calibrated *data*, each channel's rows are scaled by
    the data's own mean square there, whitened by that floor (at least 1): a
    companion raises it too, which makes the term conservative, never
    optimistic.

    Parameters
    ----------
    rows : ndarray, shape (nrow, q, p)
        The error model's covariance rows (`~kpifs.calibration.errormodel.ErrorModel.rows`).
    pixel_covariance : ndarray, shape (q, p, p)
        The calibrated mean's pixel noise (`calibrated_pixel_covariance`).
    data : ndarray, shape (q, p), optional
        The calibrated mean kernel phases.

    Returns
    -------
    rows : ndarray, shape (n, q, p)
        ``R^T R = Q P Q`` per channel (``Q`` the projector on the complement of
        the rows' span), zero across channels (pixel noise is independent
        between them); to be appended to *rows*.
    scale : ndarray, shape (q,)
        The factor applied to each channel's pixel noise (1 without *data*).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.calibration.pixelnoise import complement_rows
    >>> rows = np.zeros((1, 1, 3)); rows[0, 0, 0] = 2.0          # one mode: the first axis
    >>> extra, scale = complement_rows(rows, np.eye(3)[None])
    >>> extra.shape, np.round(extra[:, 0].T @ extra[:, 0], 12)[0].tolist()
    ((2, 1, 3), [0.0, 0.0, 0.0])
    """
    rows = np.asarray(rows, float)
    _, q, p = rows.shape
    parts, scale = [], np.ones(q)
    for i in range(q):
        _, s, vt = np.linalg.svd(rows[:, i], full_matrices=False)
        basis = vt[s > 1e-10 * s.max()] if s.size and s.max() > 0 else np.zeros((0, p))
        proj = np.eye(p) - basis.T @ basis
        c = proj @ pixel_covariance[i] @ proj
        vals, vecs = np.linalg.eigh(0.5 * (c + c.T))
        keep = vals > rtol * max(float(vals.max()), 0.0)       # none when all vanish
        fac = np.ones(int(keep.sum()))
        if data is not None and keep.any():
            z2 = ((vecs[:, keep].T @ np.asarray(data, float)[i]) / np.sqrt(vals[keep])) ** 2
            # groups of directions by their pixel noise: where the uv points' transfer
            # function is small, the static difference is large too
            for g in np.array_split(np.arange(len(z2)), max(1, min(groups, len(z2) // 20))):
                fac[g] = max(1.0, float(np.mean(z2[g])))
            scale[i] = float(np.mean(fac))
        parts.append((vecs[:, keep] * np.sqrt(fac * vals[keep])).T)
    out = np.zeros((sum(len(r) for r in parts), q, p))
    i0 = 0
    for i, r in enumerate(parts):
        out[i0:i0 + len(r), i] = r
        i0 += len(r)
    return out, scale


class _Channels:
    """A lazy (nframe, nwave, ny, nx) stack seen through a list of channels."""

    def __init__(self, stack, chans):
        self.stack, self.chans = stack, chans
        self.shape = (stack.shape[0], len(chans)) + tuple(stack.shape[2:])

    def __getitem__(self, key):
        idx, ic = key
        return np.asarray(self.stack[idx, self.chans[ic]], float)


def propagated_covariance(images, variance, kernel_model, *, wavelengths, pixscale, centres,
                          window):
    """Photon and read noise propagated through the linear extraction, for one frame.

    To first order ``dphi_b = Im(dV_b / V_b)`` with ``dV = M (w dI)``; with
    independent pixel noise of variance ``var`` this gives
    ``cov(phi) = J diag(var) J^T`` and ``cov(k) = K cov(phi) K^T``.

    Parameters
    ----------
    images, variance : ndarray, shape (nwave, ny, nx)
        A (mean) frame and its per-pixel variance.
    kernel_model : `~kpifs.model.kernel.KernelModel`
        The model used for the extraction (after any Nyquist cut).
    wavelengths, pixscale
        As for `~kpifs.extract_kernel_phases`.
    centres : array-like, shape (nwave, 2) or (2,)
        Star centres ``(x, y)``.
    window : `~kpifs.model.window.ExtractionWindow`
        The extraction's window (``kpd.window``).

    Returns
    -------
    ndarray, shape (nwave, nkp, nkp)

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs import ExtractionWindow, KernelModel, make_pupil
    >>> from kpifs.calibration.pixelnoise import propagated_covariance
    >>> from kpifs.simulation.simulate import simulate_psf
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> img = 1e6 * simulate_psf("subaru", [1.6] * u.um, pixscale=10.42 * u.mas,
    ...                          shape=(32, 32), npup=48)
    >>> cov = propagated_covariance(img, img + 100, km, wavelengths=[1.6] * u.um,
    ...                             pixscale=10.42 * u.mas, centres=(16, 16),
    ...                             window=ExtractionWindow(32, 12.8))
    >>> cov.shape
    (1, 37, 37)
    """
    wl = np.atleast_1d(to_quantity(wavelengths, u.m, name="wavelengths"))
    ps = to_quantity(pixscale, u.mas, name="pixel scale")
    images = np.asarray(images, float)
    variance = np.asarray(variance, float)
    if images.shape != variance.shape or images.ndim != 3 or images.shape[0] != len(wl):
        raise KpifsError(f"images {images.shape} and variance {variance.shape} must both be "
                         f"(nwave={len(wl)}, ny, nx)")
    centres = np.broadcast_to(np.asarray(centres, float), (len(wl), 2))
    km = kernel_model
    ws = window.size
    out = np.empty((len(wl), km.n_kp, km.n_kp))
    for i in range(len(wl)):
        img = np.nan_to_num(images[i:i + 1])
        var = np.nan_to_num(variance[i:i + 1], nan=0.0, posinf=0.0)
        cut, delta = cut_out(img, centres[i:i + 1], ws)
        vcut, _ = cut_out(var, centres[i:i + 1], ws)
        jk = kernel_jacobian(cut[0], window.weights(delta)[0],
                             km.dft_matrix(wl[i], ps, (ws, ws)), km)
        out[i] = (jk * vcut[0].ravel()[None, :]) @ jk.T
    return out


def kernel_jacobian(cut, weights, mat, kernel_model):
    """``d k / d I``: the kernel phases' derivatives with respect to a cut-out's pixels.

    ``dphi_b = Im(dV_b / V_b) = (Re V dIm V - Im V dRe V) / |V|^2`` with ``dV = M (w dI)``,
    then ``dk = K dphi``. *mat* is the model's stacked real/imaginary DFT matrix
    (`~kpifs.model.kernel.KernelModel.dft_matrix`), *weights* the window over the cut-out.
    Returns ``(nkp, npix)``.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.calibration.pixelnoise import kernel_jacobian
    >>> km = KernelModel.from_pupil(make_pupil("niriss_nrm"))
    >>> psf = np.zeros((16, 16)); psf[8, 8] = 1.0               # a point source at the origin
    >>> mat = km.dft_matrix(4.8 * u.um, 65.55 * u.mas, (16, 16))
    >>> kernel_jacobian(psf + 1e-3, np.ones((16, 16)), mat, km).shape
    (15, 256)
    """
    km = kernel_model
    w = np.asarray(weights, float).ravel()
    ri = mat @ (np.asarray(cut, float).ravel() * w)
    re, im = ri[:km.n_uv], ri[km.n_uv:]
    jac = (re[:, None] * mat[km.n_uv:] - im[:, None] * mat[:km.n_uv]) * w[None, :]
    jac /= (re ** 2 + im ** 2)[:, None]
    return km.kernel @ jac
