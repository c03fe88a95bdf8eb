"""Calibration: subtract a calibrator star's kernel phases from the target's.

The calibrated kernel phases are ``mean(target) - mean over calibrators of
mean(calibrator)`` per channel, with covariance
``Sigma_t / N_t + (1/M^2) sum_m Sigma_m / N_m`` (``Sigma`` the covariance of
one frame, estimated from the frames; ``N`` the numbers of frames).
"""
import logging

import numpy as np
from astropy import units as u

from .covariance import calibrated_covariance, empirical_covariance
from .exceptions import KpifsError
from .extract import KernelPhaseData

__all__ = ["calibrate", "check_compatible"]

log = logging.getLogger(__name__)


def _name(kpd):
    return kpd.meta.get("source", "<kernel-phase data>")


def check_compatible(target, other):
    """Raise `~kpifs.KpifsError` unless *other* has the target's channels, scale and kernel."""
    t, o = _name(target), _name(other)
    if other.n_wave != target.n_wave or not np.allclose(
            other.wavelengths.to_value(u.um), target.wavelengths.to_value(u.um), rtol=1e-4):
        raise KpifsError(f"calibrator {o} has channels {_fmt(other.wavelengths)}, the target "
                         f"{t} has {_fmt(target.wavelengths)}")
    if abs(other.pixscale / target.pixscale - 1) > 1e-3:
        raise KpifsError(f"calibrator {o} has pixel scale {other.pixscale:.3f}, the target "
                         f"{t} has {target.pixscale:.3f}")
    if other.n_kp != target.n_kp or not np.allclose(other.kernel_model.kernel,
                                                    target.kernel_model.kernel, atol=1e-8):
        raise KpifsError(f"calibrator {o} was extracted with another kernel model "
                         f"({other.n_kp} kernel phases, target {target.n_kp})")


def _fmt(wl):
    wl = wl.to_value(u.um)
    return f"{len(wl)} channels {wl.min():.4f}-{wl.max():.4f} um"


def _mean_and_cov(kpd, shrinkage, joint):
    """Mean kernel phases and the covariance of one frame (N = number of frames)."""
    if kpd.n_frame > 1:
        cov = empirical_covariance(kpd.kp, joint=joint, shrinkage=shrinkage,
                                   source=_name(kpd))
        return kpd.kp.mean(axis=0), cov, kpd.n_frame
    cov = kpd.joint_covariance if joint else kpd.covariance
    if cov is None:
        raise KpifsError(f"{_name(kpd)}: a single frame without a covariance: cannot "
                         f"calibrate (give several frames, or data with KP-COV)")
    return kpd.kp[0], cov, 1


def calibrate(target, calibrators, *, shrinkage="auto", joint=False):
    """Calibrated kernel phases of a target, with their covariance.

    Parameters
    ----------
    target : `~kpifs.KernelPhaseData`
        Frames of the target star.
    calibrators : `~kpifs.KernelPhaseData` or list of them
        Frames of one or several calibrator stars (same channels, pixel scale
        and kernel model).
    shrinkage : {'auto', 'ledoit-wolf', 'none'}
        Covariance estimator (see `~kpifs.covariance.empirical_covariance`).
    joint : bool
        Also estimate the joint cross-channel covariance
        (``result.joint_covariance``).

    Returns
    -------
    `~kpifs.KernelPhaseData`
        One frame: ``kp`` of shape (1, nwave, nkp), ``covariance`` (nwave, nkp,
        nkp), ``meta['calibrated'] = True`` and the calibrators' names.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.calibrate import calibrate
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> rng = np.random.default_rng(0)
    >>> tgt = KernelPhaseData(rng.normal(0.01, 0.1, (50, 2, km.n_kp)), [1.6, 1.7] * u.um,
    ...                       10 * u.mas, km)
    >>> cal = KernelPhaseData(rng.normal(0.0, 0.1, (50, 2, km.n_kp)), [1.6, 1.7] * u.um,
    ...                       10 * u.mas, km)
    >>> res = calibrate(tgt, cal)
    >>> res.kp.shape, res.covariance.shape == (2, km.n_kp, km.n_kp)
    ((1, 2, 44), True)
    """
    if isinstance(calibrators, KernelPhaseData):
        calibrators = [calibrators]
    calibrators = list(calibrators)
    if not calibrators:
        raise KpifsError("no calibrator given")
    for cal in calibrators:
        check_compatible(target, cal)
    t_mean, t_cov, n_t = _mean_and_cov(target, shrinkage, False)
    cal_stats = [_mean_and_cov(c, shrinkage, False) for c in calibrators]
    c_mean = np.mean([m for m, _, _ in cal_stats], axis=0)
    cov = calibrated_covariance(t_cov, n_t, [c for _, c, _ in cal_stats],
                                [n for _, _, n in cal_stats])
    jcov = None
    if joint:
        _, tj, _ = _mean_and_cov(target, shrinkage, True)
        cj = [_mean_and_cov(c, shrinkage, True) for c in calibrators]
        jcov = calibrated_covariance(tj, n_t, [c for _, c, _ in cj], [n for _, _, n in cj])
    names = [_name(c) for c in calibrators]
    meta = dict(target.meta)
    meta.update(calibrated=True, calibrators=names, n_target_frames=n_t,
                n_calibrator_frames=[n for _, _, n in cal_stats])
    log.info("calibrated %s (%d frames) with %d calibrator(s)", _name(target), n_t,
             len(calibrators))
    return KernelPhaseData((t_mean - c_mean)[None], target.wavelengths, target.pixscale,
                           target.kernel_model, covariance=cov, joint_covariance=jcov,
                           header=target.header, bandwidth=target.bandwidth, meta=meta)
