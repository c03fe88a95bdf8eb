"""Frames whose kernel phases stand far from the rest of their sequence.

A frame whose phases wrapped (a uv point of small amplitude crossing +-pi), or
whose centring failed, gives kernel phases far off while its pixels look
normal: the extraction's bad-frame checks (empty, NaN, no flux) pass it. In
the error model (`kpifs.calibration.errormodel`) one such frame inflates the held-out
variance of every mode: on a simulated NIRCam F150W sequence (20 frames, one
frame 19 times the others' scatter) the modelled variances came out a
thousand times the frames', and the whitened energy of the calibrated data
0.17 of its degrees of freedom, which wastes depth.

`outlier_frames` scores each frame by its mean squared robust z-score
(deviation from the median frame over 1.4826 MAD, per channel and kernel
phase; about 1 for Gaussian frames) and flags scores above `THRESHOLD` times
the median score. `~kpifs.calibration.calibrate.calibrate` leaves them out with a
warning naming the file and the frames.
"""
import copy
import logging

import numpy as np

__all__ = ["outlier_frames", "without_outlier_frames", "THRESHOLD"]

log = logging.getLogger(__name__)

#: Flag a frame whose score is this many times the median frame's (a Gaussian frame
#: of p >= 15 kernel phases exceeds 5 with probability below 1e-9).
THRESHOLD = 10.0


def outlier_frames(kp, *, threshold=THRESHOLD):
    """Which frames of ``kp`` (nframe, nwave, nkp) are outliers, and every frame's score.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.calibration.outliers import outlier_frames
    >>> kp = np.random.default_rng(0).normal(0, 0.01, (20, 2, 30))
    >>> kp[7] += 0.3                                   # one frame far off
    >>> bad, score = outlier_frames(kp)
    >>> np.flatnonzero(bad).tolist(), bool(score[7] > 100)
    ([7], True)
    """
    x = np.asarray(kp, float)
    if len(x) < 5:
        return np.zeros(len(x), bool), np.ones(len(x))
    med = np.median(x, axis=0)
    mad = 1.4826 * np.median(np.abs(x - med), axis=0)
    use = mad > 0
    z2 = np.where(use, (x - med) / np.where(use, mad, 1.0), 0.0) ** 2
    score = z2.sum(axis=(1, 2)) / max(int(use.sum()), 1)
    return score > threshold * np.median(score), score


def without_outlier_frames(kpd, *, threshold=THRESHOLD):
    """*kpd* without its outlier frames (`outlier_frames`), and the indices left out.

    The frames' kernel phases, errors and angles follow; raw phases and
    centres are dropped from the copy (they describe every frame).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.calibration.outliers import without_outlier_frames
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> kp = np.random.default_rng(1).normal(0, 0.01, (12, 1, km.n_kp))
    >>> kp[3] += 0.5
    >>> kept, dropped = without_outlier_frames(KernelPhaseData(kp, [1.6] * u.um, 10 * u.mas, km))
    >>> kept.n_frame, dropped
    (11, [3])
    """
    bad, _ = outlier_frames(kpd.kp, threshold=threshold)
    if not bad.any():
        return kpd, []
    keep = ~bad
    out = copy.copy(kpd)
    out.kp = kpd.kp[keep]
    out.kp_err = None if kpd.kp_err is None else kpd.kp_err[keep]
    out.detpa = None if kpd.detpa is None else kpd.detpa[keep]
    out.phases = out.amplitudes = None
    out.centres = None
    out.meta = dict(kpd.meta)
    out.meta["outlier_frames"] = np.flatnonzero(bad).tolist()
    return out, np.flatnonzero(bad).tolist()
