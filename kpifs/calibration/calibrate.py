"""Calibration: subtract a calibrator star's kernel phases from the target's.

The calibrated kernel phases are ``mean(target) - mean over calibrators of
mean(calibrator)`` per channel, with covariance
``Sigma_t / N_t + (1/M^2) sum_m Sigma_m / N_m`` (``Sigma`` the covariance of
one frame, estimated from the frames; ``N`` the numbers of frames).

The average is taken in detector coordinates. The result's detector position
angle is the (circular) mean of the target frames'; when they span more than
`MAX_DETPA_SPAN`, a companion fixed on the sky moved on the detector during
the sequence and its signal is smeared by the average: a `~kpifs.KpifsWarning`
says so.
"""
import logging
import warnings

import numpy as np
from astropy import units as u

from .._checks import check_same_setup
from ..covariance import (calibrated_covariance, empirical_covariance, hartlap_factor,
                          rows_covariance)
from ..data import KernelPhaseData
from .errormodel import fit_error_model
from ..exceptions import KpifsError, KpifsWarning
from .outliers import THRESHOLD as OUTLIER_THRESHOLD, without_outlier_frames
from .pixelnoise import calibrated_pixel_covariance, complement_rows
from ..rotation import rotation_blocks

__all__ = ["calibrate", "check_compatible", "check_calibration", "mean_detpa", "block_rows",
           "covariance_rows",
           "MAX_DETPA_SPAN"]

log = logging.getLogger(__name__)


def _name(kpd):
    return kpd.meta.get("source", "<kernel-phase data>")


def check_compatible(target, other):
    """Raise `~kpifs.KpifsError` unless *other* has the target's set-up
    (`kpifs._checks.check_same_setup`), channels, scale and kernel.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, KpifsError, make_pupil
    >>> from kpifs.calibration.calibrate import check_compatible
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> a = KernelPhaseData(np.zeros((2, 1, km.n_kp)), [1.6] * u.um, 10 * u.mas, km)
    >>> b = KernelPhaseData(np.zeros((2, 1, km.n_kp)), [1.6] * u.um, 12 * u.mas, km)
    >>> try:
    ...     check_compatible(a, b)
    ... except KpifsError as err:
    ...     print("pixel scale" in str(err))
    True
    """
    check_same_setup(target, other)          # instrument, filter, pupil element (issue 37)
    t, o = _name(target), _name(other)
    if other.n_wave != target.n_wave or not np.allclose(
            other.wavelengths.to_value(u.um), target.wavelengths.to_value(u.um), rtol=1e-4):
        raise KpifsError(f"calibrator {o} has channels {_fmt(other.wavelengths)}, the target "
                         f"{t} has channels {_fmt(target.wavelengths)}")
    if abs(other.pixscale / target.pixscale - 1) > 1e-3:
        raise KpifsError(f"calibrator {o} has pixel scale {other.pixscale:.3f}, the target "
                         f"{t} has {target.pixscale:.3f}")
    if other.n_kp != target.n_kp or not np.allclose(other.kernel_model.kernel,
                                                    target.kernel_model.kernel, atol=1e-8):
        raise KpifsError(f"calibrator {o} was extracted with another kernel model "
                         f"({other.n_kp} kernel phases, target {target.n_kp})")


def _fmt(wl):
    wl = wl.to_value(u.um)
    if len(wl) == 1:
        return f"{wl[0]:.4f} um (1 channel)"
    return f"{wl.min():.4f}-{wl.max():.4f} um ({len(wl)} channels)"


def check_calibration(target, calibrators):
    """Refuse a calibration that would be wrong: twice, or of a star by itself.

    Already-calibrated data (CALFLAG true) are not calibrated again, nor used
    as a calibrator (the calibrator's own calibrator would be subtracted back),
    and a calibrator whose kernel phases are those of the target (the same
    frames: calibrated kernel phases of exactly 0) is refused.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, KpifsError, make_pupil
    >>> from kpifs.calibration.calibrate import check_calibration
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> a = KernelPhaseData(np.ones((4, 1, km.n_kp)), [1.6] * u.um, 10 * u.mas, km)
    >>> try:
    ...     check_calibration(a, [a])
    ... except KpifsError as err:
    ...     print("its own calibrator" in str(err))
    True
    """
    t = _name(target)
    if target.meta.get("calibrated"):
        raise KpifsError(f"{t}: already calibrated (CALFLAG true): calibrating it again "
                         f"subtracts a star twice; give it without a calibrator")
    for cal in calibrators:
        if cal.meta.get("calibrated"):
            raise KpifsError(f"calibrator {_name(cal)}: already calibrated (CALFLAG true): "
                             f"a calibrator must be a star's own kernel phases")
        if cal is target or (cal.kp.shape == target.kp.shape
                             and np.array_equal(cal.kp, target.kp)):
            raise KpifsError(f"calibrator {_name(cal)}: its kernel phases are the target "
                             f"{t}'s own: a star cannot be its own calibrator (calibrated "
                             f"kernel phases would be exactly 0)")


#: Fewest frames of a star from which its frame-to-frame scatter is estimated.
MIN_FRAMES = 3

#: Largest span (deg) of the target's detector position angles averaged without a warning.
MAX_DETPA_SPAN = 1.0


def mean_detpa(detpa):
    """Mean and span (deg) of detector position angles, NaN ignored, across 0/360.

    The angles are unwrapped about their circular mean and averaged; the
    result is on the branch of the first angle (1 and 359 average to 0, 359
    and 1 to 360). Returns ``(nan, nan)`` when no angle is known.

    Examples
    --------
    >>> from kpifs.calibration.calibrate import mean_detpa
    >>> [round(float(v), 6) for v in mean_detpa([1.0, 359.0, 3.0])]
    [1.0, 4.0]
    """
    a = np.asarray(detpa, float)
    a = a[np.isfinite(a)]
    if a.size == 0:
        return np.nan, np.nan
    r = np.deg2rad(a)
    centre = float(np.rad2deg(np.arctan2(np.mean(np.sin(r)), np.mean(np.cos(r)))))
    centre = a[0] + (centre - a[0] + 180.0) % 360.0 - 180.0
    dev = (a - centre + 180.0) % 360.0 - 180.0        # the angles unwrapped about it
    return float(centre + dev.mean()), float(dev.max() - dev.min())


def _mean_and_cov(kpd, shrinkage, joint, debias=True):
    """Mean kernel phases and the covariance of one frame (N = number of frames)."""
    if 1 < kpd.n_frame < MIN_FRAMES:
        raise KpifsError(f"{_name(kpd)}: {kpd.n_frame} frames are too few to estimate the "
                         f"noise of {kpd.n_kp} kernel phases (at least {MIN_FRAMES} per star; "
                         f"false alarms would not be controlled)")
    if kpd.n_frame > 1:
        cov = empirical_covariance(kpd.kp, joint=joint, shrinkage=shrinkage, debias=debias,
                                   source=_name(kpd))
        return kpd.kp.mean(axis=0), cov, kpd.n_frame
    cov = kpd.joint_covariance if joint else kpd.covariance
    if cov is None:
        raise KpifsError(f"{_name(kpd)}: a single frame without a covariance: cannot "
                         f"calibrate (give several frames, or data with KP-COV)")
    return kpd.kp[0], cov, 1


#: Error models of `calibrate`.
ERROR_MODELS = ("auto", "modes", "frames")


#: Modes (fraction of the frames' degrees of freedom) of the error model that
#: characterises candidates (`calibrate`'s *fit_modes*): on the PHARO injections,
#: pulls of rms 1.33, 1.26, 1.27, 1.27 for 0.6, 0.7, 0.8, 0.9 (1.6 with the search's
#: 0.5), while searching with those models adds false alarms.
FIT_MODES = 0.8


def calibrate(target, calibrators, *, shrinkage="auto", joint=False, debias=True,
              error_model="auto", n_modes=0.5, residual="auto", fit_modes=FIT_MODES,
              pixel_noise="auto"):
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
    debias : bool
        Scale sample covariances by the Hartlap factor ``(N-1)/(N-p-2)``
        (`~kpifs.covariance.hartlap_factor`), so that data whitened with the
        result have unit variance on average, as the detection tests assume
        (``error_model='frames'`` only).
    error_model : {'auto', 'modes', 'frames'}
        ``'modes'``: the model of `kpifs.calibration.errormodel` (temporal correlation,
        calibration residual, the leading modes only), jointly across channels;
        ``'frames'``: the frames' sample covariance / N (independent frames,
        no calibration residual). ``'auto'``: 'modes' when every star has
        several frames, else 'frames' (single frames with KP-COV).
    n_modes, residual
        Options of `~kpifs.calibration.errormodel.fit_error_model`.
    fit_modes : float or None
        With the 'modes' error model, a second model of this many modes (a
        fraction of the frames' degrees of freedom, default `FIT_MODES`)
        characterises the candidates (``fit_covariance_rows``): the search
        keeps the conservative *n_modes*, whose variances are well measured,
        while positions and contrasts use the modes beyond, which carry much
        of their information. On the PHARO injections this brings the pulls'
        rms from 1.6 to 1.2 without changing what is found. None: one model.
    pixel_noise : {'auto', 'none'}
        With the 'modes' error model, ``'auto'`` gives the directions its modes
        leave out the propagated pixel noise when every star has it (JWST ``ERR``,
        `~kpifs.calibration.pixelnoise.complement_rows`): every kernel phase is then used,
        weighted by its noise, instead of the modes alone.

    Returns
    -------
    `~kpifs.KernelPhaseData`
        One frame: ``kp`` of shape (1, nwave, nkp), ``covariance`` (nwave, nkp,
        nkp), ``meta['calibrated'] = True`` and the calibrators' names.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.calibration.calibrate import calibrate
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> rng = np.random.default_rng(0)
    >>> tgt = KernelPhaseData(rng.normal(0.01, 0.1, (300, 2, km.n_kp)), [1.6, 1.7] * u.um,
    ...                       10 * u.mas, km)
    >>> cal = KernelPhaseData(rng.normal(0.0, 0.1, (300, 2, km.n_kp)), [1.6, 1.7] * u.um,
    ...                       10 * u.mas, km)
    >>> res = calibrate(tgt, cal)
    >>> res.kp.shape, res.covariance.shape == (2, km.n_kp, km.n_kp)
    ((1, 2, 37), True)
    """
    if isinstance(calibrators, KernelPhaseData):
        calibrators = [calibrators]
    calibrators = list(calibrators)
    if not calibrators:
        raise KpifsError("no calibrator given")
    for cal in calibrators:
        check_compatible(target, cal)
    if error_model not in ERROR_MODELS:
        raise KpifsError(f"unknown error model {error_model!r}: use one of {ERROR_MODELS}")
    if error_model == "auto":
        error_model = "modes" if min(k.n_frame for k in [target, *calibrators]) > 1 \
            else "frames"
    if error_model == "modes":
        target, *calibrators = [_drop_outliers(k) for k in [target, *calibrators]]
        return _calibrate_modes(target, calibrators, n_modes=n_modes, residual=residual,
                                joint=joint, fit_modes=fit_modes, pixel_noise=pixel_noise)
    t_mean, t_cov, n_t = _mean_and_cov(target, shrinkage, False, False)
    cal_stats = [_mean_and_cov(c, shrinkage, False, False) for c in calibrators]
    c_mean = np.mean([m for m, _, _ in cal_stats], axis=0)
    covs = [t_cov] + [c for _, c, _ in cal_stats]
    frames = [n_t] + [n for _, _, n in cal_stats]
    cov = calibrated_covariance(t_cov, n_t, covs[1:], frames[1:])
    h = _effective_hartlap(covs, frames, target.n_kp, _name(target)) if debias else 1.0
    cov = cov * h
    jcov = None
    if joint:
        _, tj, _ = _mean_and_cov(target, shrinkage, True, False)
        cj = [_mean_and_cov(c, shrinkage, True, False) for c in calibrators]
        jcov = calibrated_covariance(tj, n_t, [c for _, c, _ in cj], [n for _, _, n in cj])
        if debias:
            jcov = jcov * _effective_hartlap([tj] + [c for _, c, _ in cj], frames,
                                             target.n_kp * target.n_wave, _name(target))
    rows = covariance_rows(target, calibrators, hartlap=h)
    meta = {"error_model": {"model": "frames", "hartlap": float(h)}}
    return _result(target, calibrators, t_mean - c_mean, cov, jcov, rows, meta,
                   [n for _, _, n in cal_stats])


def _calibrate_modes(target, calibrators, *, n_modes, residual, joint, fit_modes=None,
                     pixel_noise="auto"):
    """`calibrate` with the error model of `kpifs.calibration.errormodel`."""
    for kpd in [target, *calibrators]:
        if kpd.n_frame < MIN_FRAMES:
            raise KpifsError(f"{_name(kpd)}: {kpd.n_frame} frames are too few to estimate the "
                             f"noise of {kpd.n_kp} kernel phases (at least {MIN_FRAMES} per "
                             f"star; false alarms would not be controlled)")
    em = fit_error_model(target.kp, [c.kp for c in calibrators], n_modes=n_modes,
                         residual=residual, source=_name(target))
    d = target.kp.mean(axis=0) - np.mean([c.kp.mean(axis=0) for c in calibrators], axis=0)
    fit_rows = None
    if fit_modes is not None and fit_modes != n_modes:
        with warnings.catch_warnings():       # the search's model has said it already
            warnings.simplefilter("ignore", KpifsWarning)
            fit_rows = fit_error_model(target.kp, [c.kp for c in calibrators],
                                       n_modes=fit_modes, residual=residual,
                                       source=_name(target)).rows
    rows, extra = em.rows, {"error_model": em.meta()}
    pix = _pixel_term(target, calibrators, pixel_noise)
    if pix is not None:
        comp, scale = complement_rows(rows, pix, data=d)
        rows = np.concatenate([rows, comp])
        if fit_rows is not None:
            fit_rows = np.concatenate([fit_rows, complement_rows(fit_rows, pix, data=d)[0]])
        em_meta = extra["error_model"]
        em_meta["pixel_modes"] = int(len(comp) // max(target.n_wave, 1))
        em_meta["pixel_scale"] = float(np.mean(scale))
        log.info("%s: pixel noise (%s) x %s in the %d directions the error model's modes "
                 "leave out, per channel", _name(target), target.meta.get("pixel_noise"),
                 np.round(scale, 2).tolist(), em_meta["pixel_modes"])
    out = _result(target, calibrators, d, rows_covariance(rows),
                  rows_covariance(rows, joint=True) if joint else None, rows, extra,
                  [c.n_frame for c in calibrators])
    out.fit_covariance_rows = fit_rows
    if fit_rows is not None:
        out.meta["error_model"]["fit_modes"] = fit_modes
    return out


def _drop_outliers(kpd):
    """*kpd* without frames far from the rest (`kpifs.calibration.outliers`), with a warning."""
    kept, dropped = without_outlier_frames(kpd)
    if dropped and kept.n_frame >= MIN_FRAMES:
        warnings.warn(f"{_name(kpd)}: frame(s) {dropped} (0-based, of {kpd.n_frame}) left out: "
                      f"their kernel phases stand {OUTLIER_THRESHOLD:g}x or more farther from "
                      f"the median frame than a typical frame's (phase wrapping or a failed "
                      f"centring)", KpifsWarning, stacklevel=3)
        return kept
    return kpd


def _pixel_term(target, calibrators, pixel_noise):
    """The calibrated mean's pixel noise for `complement_rows`, or None."""
    if pixel_noise not in ("auto", "none"):
        raise KpifsError(f"pixel_noise must be 'auto' or 'none', got {pixel_noise!r}")
    if pixel_noise == "none":
        return None
    pix = calibrated_pixel_covariance(target, calibrators)
    q, p = target.n_wave, target.n_kp
    if pix is None or pix.shape != (q, p, p):
        return None
    if q * q * p * p > 5e7:     # rows (q (p - K), q, p): too large to hold; modes alone
        log.info("%s: pixel noise not added (%d channels x %d kernel phases: too large)",
                 _name(target), q, p)
        return None
    return pix


def _result(target, calibrators, d, cov, jcov, rows, extra, n_cal):
    """The calibrated `~kpifs.KernelPhaseData` (one frame) and its provenance."""
    n_t = target.n_frame
    names = [_name(c) for c in calibrators]
    meta = dict(target.meta)
    meta.update(calibrated=True, calibrators=names, n_target_frames=n_t,
                n_calibrator_frames=n_cal, **extra)
    detpa = None
    if target.detpa is not None:
        pa, span = mean_detpa(target.detpa)
        detpa = [pa]
        meta["detpa_span"] = None if np.isnan(span) else span
        meta["detpa_frames"] = [float(v) for v in target.detpa]   # for the sky fit
        meta["detpa_source"] = (f"mean of {target.n_frame} target frame(s) "
                                f"({target.meta.get('detpa_source', 'given')})")
        if span > MAX_DETPA_SPAN:
            warnings.warn(f"{_name(target)}: the target's detector position angle spans "
                          f"{span:.1f} deg over its {target.n_frame} frames: they are averaged "
                          f"in detector coordinates; a search on the sky (detect's default "
                          f"when the angles are known) turns the model frame by frame, one on "
                          f"the detector smears a companion fixed on the sky over that arc "
                          f"(its signal is lost beyond ~{_smear_limit(target, span):.0f} mas); "
                          f"the result carries the mean angle {pa:.1f} deg (and the time "
                          f"blocks, searched block by block: kpifs.rotation)",
                          KpifsWarning,
                          stacklevel=2)
    log.info("calibrated %s (%d frames) with %d calibrator(s)", _name(target), n_t,
             len(calibrators))
    out = KernelPhaseData(d[None], target.wavelengths, target.pixscale,
                          target.kernel_model, window=target.window, covariance=cov,
                          joint_covariance=jcov, covariance_rows=rows,
                          block_rows=block_rows(target, calibrators), header=target.header,
                          detpa=detpa, bandwidth=target.bandwidth, meta=meta)
    out.rotation = rotation_blocks(target, calibrators)     # issue 29: the rotation kept
    return out


def _smear_limit(kpd, span):
    """Separation (mas) at which an arc of *span* deg is a quarter of the finest fringe.

    The finest fringe is ``lambda_min / B_max``; along an arc of angle *span* a
    companion at separation ``r`` moves ``r * span``.
    """
    lam = kpd.wavelengths.to_value(u.m).min()
    bmax = kpd.kernel_model.baseline_length.to_value(u.m).max()
    fringe = lam / bmax / (np.pi / 180 / 3600 / 1000)
    return 0.25 * fringe / np.deg2rad(span)


def _effective_hartlap(covs, frames, dim, source):
    """Hartlap factor of a sum of covariance estimates ``sum_k Sigma_k / N_k``.

    The degrees of freedom of the sum follow Welch-Satterthwaite,
    ``nu = (sum a_k)^2 / sum (a_k^2 / (N_k - 1))`` with ``a_k = tr(Sigma_k) / N_k``
    (calibrator terms carry their ``1/M^2``), and the factor is
    ``nu / (nu - p - 1)`` (`~kpifs.covariance.hartlap_factor` with ``N - 1 = nu``).
    Shrunk covariances (frames <= p) are not debiased.
    """
    m = len(covs) - 1
    if any(n <= dim + 2 for n in frames):
        return 1.0
    a = [np.trace(c, axis1=-2, axis2=-1).sum() / n * (1 if k == 0 else 1 / m ** 2)
         for k, (c, n) in enumerate(zip(covs, frames))]
    nu = sum(a) ** 2 / sum(ak ** 2 / (n - 1) for ak, n in zip(a, frames))
    h = hartlap_factor(nu + 1, dim)
    if not np.isfinite(h):
        return 1.0
    if h > 1.5:
        warnings.warn(f"{source}: {nu:.0f} effective frames for {dim} kernel phases: the "
                      f"inverse covariance is debiased by a factor {h:.2f} (Hartlap et al. "
                      f"2007); its errors still give heavier tails than Gaussian, so false-"
                      f"alarm probabilities are optimistic: use several times more frames "
                      f"than kernel phases", KpifsWarning, stacklevel=3)
    return h


def covariance_rows(target, calibrators=(), *, hartlap=1.0):
    """Scaled frame deviations whose Gram matrix is the covariance of the (calibrated) mean.

    ``R = sqrt(h) [dt_f / sqrt(N_t (N_t - 1)); dc_f / (M sqrt(N_c (N_c - 1)))]``, with
    ``h`` the Hartlap factor (*hartlap*) applied to the covariance: ``R^T R`` is the
    covariance of the calibrated mean (of the target's mean with no *calibrators*)
    across *all* channels (its per-channel blocks equal the sample covariance over
    the frames' number), so random combinations of the rows are noise with the
    data's own spectral correlations. ``None`` when a data set has a single frame.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.calibration.calibrate import covariance_rows
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> kp = np.random.default_rng(0).normal(0, 0.1, (30, 2, km.n_kp))
    >>> rows = covariance_rows(KernelPhaseData(kp, [1.5, 1.6] * u.um, 10 * u.mas, km))
    >>> gram = np.einsum("ncp,ncr->cpr", rows, rows)
    >>> rows.shape, bool(np.allclose(gram[0], np.cov(kp[:, 0], rowvar=False) / 30))
    ((30, 2, 37), True)
    """
    if isinstance(calibrators, KernelPhaseData):
        calibrators = [calibrators]
    parts = []
    m = len(calibrators)
    for kpd, scale in [(target, 1.0)] + [(c, 1.0 / m) for c in calibrators]:
        n = kpd.n_frame
        if n < 2:
            return None
        dev = kpd.kp - kpd.kp.mean(axis=0)
        parts.append(dev * (scale * np.sqrt(hartlap / (n * (n - 1)))))
    return np.concatenate(parts)


def _n_blocks(n):
    """Time blocks of a star's *n* frames for the empirical null: about sqrt(n) (long
    blocks keep the drifts), at least 6 (the sign-flip draws need patterns), at most
    16 and *n*."""
    return int(min(n, max(6, min(16, round(np.sqrt(n))))))


def block_rows(target, calibrators, *, n_blocks=None):
    """Centred time-block means of every star, scaled for the empirical null.

    Each star's frames (in time order) are cut into *n_blocks* consecutive
    blocks (default about ``sqrt(N)``, at least 6, at most 16); the rows are
    ``w_s sqrt(B/(B-1)) (n_b/N) (m_b - mean)`` with ``m_b`` the block means and
    ``w_s`` 1 for the target and ``1/M`` per calibrator, so that a random sign
    combination of the rows has, on average, the covariance of the calibrated
    mean's frame noise as the blocks show it: drifts shorter than a block
    included, with their own shape rather than a Gaussian's. They are the
    empirical null of `~kpifs.detect.detect` (stored as KP-BLKROWS). None when
    a star has fewer than 2 frames.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.calibration.calibrate import block_rows
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> rng = np.random.default_rng(0)
    >>> t, c = (KernelPhaseData(rng.normal(0, 0.1, (36, 1, km.n_kp)), [1.6] * u.um,
    ...                         10 * u.mas, km) for _ in range(2))
    >>> block_rows(t, c).shape          # 6 blocks of each star
    (12, 1, 37)
    """
    if isinstance(calibrators, KernelPhaseData):
        calibrators = [calibrators]
    parts = []
    m = len(calibrators)
    for kpd, w in [(target, 1.0)] + [(c, 1.0 / m) for c in calibrators]:
        n = kpd.n_frame
        if n < 2:
            return None
        b = _n_blocks(n) if n_blocks is None else int(min(n, n_blocks))
        blocks = np.array_split(np.arange(n), b)
        mean = kpd.kp.mean(axis=0)
        for idx in blocks:
            parts.append(w * np.sqrt(b / (b - 1)) * len(idx) / n
                         * (kpd.kp[idx].mean(axis=0) - mean))
    return np.stack(parts)
