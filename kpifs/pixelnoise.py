"""Per-pixel noise of the images (JWST ``ERR``) propagated to the kernel phases.

The extraction is linear in the pixels to first order: a pixel noise of
variance ``var`` gives the kernel phases of one frame the covariance
``J diag(var) J^T``, ``J = dk/dI`` (`kpifs.covariance.kernel_jacobian`). The
Jacobian of each channel is taken at the mean frame around its mean centre
(the frames of one star differ by far less than their Fourier amplitudes);
each frame's own variance, cut around its own centre, gives its errors.

`attach_pixel_noise` puts the result in the `~kpifs.data.KernelPhaseData`:
``kp_err`` (per frame, stored as KP-SIGM, as jwst-kpi writes it from
``ERR``) and ``meta['pixel_covariance']`` (one frame's covariance per
channel, ``(nwave, nkp, nkp)``), with ``meta['pixel_noise']`` naming the
source. The frames' error model (`kpifs.errormodel`) does not use them yet:
they are the floor that model can be checked against (``kpifs info`` prints
the ratio of the frames' scatter to it).
"""
import logging

import numpy as np
from astropy import units as u

from .covariance import kernel_jacobian
from .prepare import cut_out

__all__ = ["attach_pixel_noise", "pixel_noise"]

log = logging.getLogger(__name__)

#: Frames read at a time (memory: one batch of images and variances).
BATCH = 64


def _channel_index(cube_wl, kpd_wl):
    """Indices in the cube of the data's channels (dead channels were dropped)."""
    cw = np.asarray(cube_wl.to_value(u.um))
    return [int(np.argmin(np.abs(cw - w))) for w in kpd_wl.to_value(u.um)]


def pixel_noise(images, variance, kpd):
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

    Returns
    -------
    kp_err : ndarray, shape (kpd.n_frame, kpd.n_wave, kpd.n_kp)
    covariance : ndarray, shape (kpd.n_wave, kpd.n_kp, kpd.n_kp)
        Of one frame of mean variance.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import extract_kernel_phases
    >>> from kpifs.pixelnoise import pixel_noise
    >>> from kpifs.simulate import simulate_psf
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
            img = np.nan_to_num(np.asarray(images[idx, j], float))
            var = np.nan_to_num(np.asarray(variance[idx, j], float), nan=0.0, posinf=0.0)
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


def attach_pixel_noise(kpd, cube):
    """Propagate ``cube.variance`` (when the reader found one) into *kpd*.

    Sets ``kpd.kp_err``, ``kpd.meta['pixel_covariance']`` and
    ``kpd.meta['pixel_noise']`` (`pixel_noise`); does nothing without a
    variance. Returns *kpd*.

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.io import read_cube, write_observation
    >>> from kpifs.pixelnoise import attach_pixel_noise
    >>> from kpifs.simulate import simulate_scene
    >>> from kpifs.workflow import ExtractOptions, extract_observation
    >>> obs = simulate_scene("niriss", n_frames=3, npup=32, shape=(32, 32), seed=1)
    >>> files = write_observation(obs, tempfile.mkdtemp(), layout="jwst")
    >>> opts = ExtractOptions(pupil="niriss_nrm")
    >>> kpd = extract_observation(files["target"], opts)    # calls attach_pixel_noise
    >>> kpd.meta["pixel_noise"], kpd.kp_err.shape == kpd.shape
    ('ERR', True)
    """
    if getattr(cube, "variance", None) is None:
        return kpd
    chans = _channel_index(cube.wavelengths, kpd.wavelengths)
    images = _Channels(cube.data, chans)
    variance = _Channels(cube.variance, chans)
    kpd.kp_err, cov = pixel_noise(images, variance, kpd)
    kpd.meta["pixel_covariance"] = cov
    kpd.meta["pixel_noise"] = cube.variance_source or "variance"
    kpd.header["KPPIXNOI"] = (kpd.meta["pixel_noise"], "per-pixel noise propagated to KP-SIGM")
    log.info("%s: per-pixel noise (%s) propagated: median kernel-phase error %.3g rad per "
             "frame", cube.name, kpd.meta["pixel_noise"], float(np.median(kpd.kp_err)))
    return kpd


class _Channels:
    """A lazy (nframe, nwave, ny, nx) stack seen through a list of channels."""

    def __init__(self, stack, chans):
        self.stack, self.chans = stack, chans
        self.shape = (stack.shape[0], len(chans)) + tuple(stack.shape[2:])

    def __getitem__(self, key):
        idx, ic = key
        return np.asarray(self.stack[idx, self.chans[ic]], float)
