"""Error model of calibrated mean kernel phases from few, temporally correlated frames.

On sky, the frames of a sequence are correlated in time (quasi-static
aberrations drift), the calibrator never matches the target exactly, and there
are often fewer frames than kernel phases. The covariance of the calibrated
mean ``d = mean(T) - (1/M) sum_m mean(C_m)`` is therefore modelled, channel by
channel, in a reduced basis:

.. math:: {\\rm Cov}(d) = V^T {\\rm diag}(c) V, \\qquad
          c_k = \\sum_s w_s^2 \\tau_{s,k} \\lambda^{\\rm cv}_{s,k} / N_s + r_k

- ``V`` (K x p): the K leading modes of the pooled frame deviations of all
  stars at that channel (weights ``w`` = 1 for the target, 1/M per calibrator). Only these
  modes are used (dimension control): from ``nu = sum_s (N_s - 1)`` frames no
  more than ~nu directions of a covariance are measured; K = ``n_modes`` x nu
  (default 0.5).
- ``lambda_cv``: the frame variance of each star along each mode, *cross-
  validated* (modes from all but one time block, variance from the held-out
  block). In-sample variances along a sample's own leading modes are biased
  *high* when frames are few (the top eigenvalues of a sample covariance
  spread out; the calibrated mean, independent of the frames' deviations,
  does not share that bias): on 22-channel CHARIS simulations of 10, 20 and
  40 frames they put the whitened energy at 0.12, 0.39 and 0.56 of its
  degrees of freedom. The held-out variances are used as they are, in both
  directions (1.05 and 1.00 with 20 and 40 independent frames).
- ``tau``: integrated autocorrelation time per star and group of modes, by
  batch means (batches of ~sqrt(N) consecutive frames), at least 1: the
  variance of a mean of correlated frames is ``tau lambda / N``.
- ``r``: the calibration residual (the null hypothesis ``y = r + eps`` of
  Ceau et al. 2019), measured on the data: from the differences between
  calibrators when there are several ('cal-vs-cal'). With one calibrator
  nothing in the frames shows the static difference between target and
  calibrator, and a star's own blocks do not predict it either (on the PHARO
  eps Her frames, blocks of 25 frames differ by 0.5-1.5 frame variances,
  blocks of 50 by 0.03-0.08, so that any extrapolation from within a
  sequence misses by an order of magnitude): it is measured where it shows,
  on the calibrated data themselves, by the detection's noise scale
  (``'chi2'``; `~kpifs.detect.channels.combined_scale`: the residual's
  reduced chi-square and its map's mean square, each against its law under
  the model). ``'split-halves'`` (on request) extrapolates the excess
  between adjacent halves and quarters of each star's sequence, out of sample.

The channels are tied together by the covariance rows: the pooled frame
deviations projected on each channel's modes and rescaled, mode by mode, to
the modelled variances, so that their Gram matrix is the model in every
channel and carries the channels' mutual correlations as the frames show them
(one optical-path error seen at every wavelength). The products store them
(KP-COVROWS); detection whitens with their per-channel blocks and draws its
Monte-Carlo null from them, so the two always agree (whitening channel by
channel projects the data exactly on the modelled subspace: a joint basis
would not). The remaining overall scale is measured at detection time by the
reduced chi-square of the whitened residual.
"""
import logging
from dataclasses import dataclass, field

import numpy as np

from .._utils import thread_map
from ..covariance import rows_covariance
from ..exceptions import KpifsError

__all__ = ["ErrorModel", "fit_error_model", "RESIDUAL_METHODS"]

log = logging.getLogger(__name__)

#: Calibration-residual estimators (``'auto'`` picks the first that the data allow).
RESIDUAL_METHODS = ("auto", "cal-vs-cal", "split-halves", "chi2", "none")
#: Fewest frames of every star for cross-validation and batch means.
MIN_FRAMES_CV = 6


@dataclass
class ErrorModel:
    """Covariance model of calibrated mean kernel phases (see `kpifs.calibration.errormodel`).

    Attributes
    ----------
    rows : ndarray (sum N_s, q, p)
        Covariance rows: ``rows[:, i]^T rows[:, i]`` is the modelled covariance
        of the mean at channel i, and cross products tie the channels.
    variance : ndarray (q K,)
        Modelled variance ``c_k`` along each mode, channel after channel.
    naive_variance : ndarray (q K,)
        What independent frames and in-sample eigenvalues would give.
    tau : ndarray (n_stars, q n_groups)
        Integrated autocorrelation times (target first).
    residual : ndarray (q K,)
        Calibration-residual variance ``r_k``.
    residual_method : str
    n_modes, dof : int
        K (per channel) and ``nu = sum (N_s - 1)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.calibration.errormodel import fit_error_model
    >>> rng = np.random.default_rng(1)
    >>> em = fit_error_model(rng.standard_normal((30, 1, 50)), [rng.standard_normal((30, 1, 50))])
    >>> em.covariance().shape, em.n_modes, em.dof, em.meta()["residual_method"]
    ((1, 50, 50), 29, 58, 'chi2')
    """

    rows: np.ndarray
    variance: np.ndarray
    naive_variance: np.ndarray
    tau: np.ndarray
    residual: np.ndarray
    residual_method: str
    n_modes: int
    dof: int
    mode_fraction: float
    beta: np.ndarray = field(default=None)

    @property
    def inflation(self):
        """Mean ratio of the modelled to the naive variance over the modes."""
        return float(np.mean(self.variance / self.naive_variance))

    def covariance(self, *, joint=False):
        """Per-channel covariances (q, p, p), or the joint one (q p, q p) with *joint*."""
        return rows_covariance(self.rows, joint=joint)

    def meta(self):
        """Plain numbers for product headers and ``meta['error_model']``."""
        return {"model": "modes", "n_modes": int(self.n_modes), "dof": int(self.dof),
                "mode_fraction": float(self.mode_fraction),
                "residual_method": self.residual_method,
                "tau_max": float(np.max(self.tau)), "tau_mean": float(np.mean(self.tau)),
                "residual_fraction": float(np.sum(self.residual) / np.sum(self.variance)),
                "inflation": self.inflation}


def _groups(k, n_groups):
    """Contiguous groups of mode ranks (about equal sizes, at least 3 modes each)."""
    return np.array_split(np.arange(k), max(1, min(n_groups, k // 3)))


def _per_mode(values, groups):
    return np.concatenate([np.full(len(g), v) for g, v in zip(groups, values)])


def _cross_validated(sets, w, n, k, n_blocks):
    """Frame variance of each set along the K leading modes, held-out time blocks."""
    blocks = [np.array_split(np.arange(ni), min(n_blocks, ni // 2)) for ni in n]
    nb = min(len(b) for b in blocks)
    num, den = np.zeros((len(sets), k)), np.zeros(len(sets))
    for b in range(nb):
        train, held = [], []
        for si, (x, ni) in enumerate(zip(sets, n)):
            idx = blocks[si][b]
            xt = np.delete(x, idx, axis=0)
            train.append(w[si] * (xt - xt.mean(0)) / np.sqrt(ni * (len(xt) - 1)))
            held.append(x[idx] - x[idx].mean(0))
        vb = np.linalg.svd(np.vstack(train), full_matrices=False)[2][:k]
        for si, h in enumerate(held):
            num[si] += np.sum((h @ vb.T) ** 2, 0)
            den[si] += len(h) - 1
    return num / den[:, None]


def _smooth(ratio, width=5):
    if ratio.shape[1] <= width:
        return ratio
    ker = np.ones(width) / width
    pad = width // 2
    return np.array([np.convolve(np.pad(r, pad, mode="edge"), ker, "valid")[:ratio.shape[1]]
                     for r in ratio])


def _tau(proj, lam, n, groups):
    """Autocorrelation time per set and group of modes by batch means (>= 1)."""
    tau = np.ones((len(proj), len(groups)))
    for si, (a, ni) in enumerate(zip(proj, n)):
        bl = max(2, int(round(np.sqrt(ni))))
        nbat = ni // bl
        if nbat < 3:
            continue
        bm = a[:nbat * bl].reshape(nbat, bl, -1).mean(1)
        r = bl * bm.var(0, ddof=1) / np.where(lam[si] > 0, lam[si], np.inf)
        tau[si] = [max(1.0, float(np.mean(r[g]))) for g in groups]
    return tau


def _segment_excess(x, m, tau, n_groups):
    """Excess of the difference of adjacent segment means over the frame noise, per group
    of mode ranks, as a fraction of the frame variance (a star's frames, *m* segments).

    Out of sample: for each pair of adjacent segments, the modes are those of
    one segment's own deviations (independent of both means) and the frame
    variance along them is the other segment's. Returns (n_groups,) or None when
    the segments are too short.
    """
    segs = np.array_split(np.arange(len(x)), m)
    num, den = np.zeros(n_groups), np.zeros(n_groups)
    for a, b in zip(segs[:-1], segs[1:]):
        for tr, ho in ((a, b), (b, a)):
            kk = len(tr) - 1
            if kk < n_groups or len(ho) < 2:
                return None
            vt = np.linalg.svd(x[tr] - x[tr].mean(0), full_matrices=False)[2][:kk]
            lam = np.sum(((x[ho] - x[ho].mean(0)) @ vt.T) ** 2, 0) / (len(ho) - 1)
            delta2 = ((x[tr].mean(0) - x[ho].mean(0)) @ vt.T) ** 2
            excess = delta2 - tau * lam * (1 / len(tr) + 1 / len(ho))
            for g, idx in enumerate(np.array_split(np.arange(kk), n_groups)):
                num[g] += np.sum(excess[idx])
                den[g] += np.sum(lam[idx])
    return num / np.where(den > 0, den, np.inf)


def _drift_residual(sets, n, tau, n_groups):
    """The calibration residual of drifting aberrations, per star and group of mode ranks.

    The excess ``e(L)`` of the difference of the means of two adjacent blocks
    of ``L`` frames over their frame noise is measured within each star for
    halves (``L = N/2``) and quarters (``N/4``) of its sequence, out of sample
    (`_segment_excess`); ``e(L) ~ L^kappa`` (``-1 <= kappa <= 1``: -1 for noise
    correlated over a few frames, which averages out, +1 for a random walk)
    is extrapolated to the target's and calibrators' whole sequences, ``L =
    N``, as for adjacent sequences. Returns (n_stars, n_groups): the residual's
    variance as a fraction of each star's frame variance.
    """
    out = np.zeros((len(sets), n_groups))
    for si, (x, t) in enumerate(zip(sets, tau)):
        half = _segment_excess(x, 2, float(np.mean(t)), n_groups)
        if half is None:
            continue
        quarter = _segment_excess(x, 4, float(np.mean(t)), n_groups)
        half = np.clip(half, 0, None)
        if quarter is None:
            kappa = np.ones(n_groups)                 # growth not measurable: the steepest
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                kappa = np.log2(half / np.clip(quarter, 0, None))
            kappa = np.clip(np.nan_to_num(kappa, nan=0.0, posinf=1.0, neginf=-1.0), -1, 1)
        out[si] = half * 2.0 ** kappa
    return out


def _channel_model(sets, w, n, k, n_groups, cv_blocks, residual):
    """The modes, variances and parameters of one channel (`fit_error_model`)."""
    nu = int(np.sum(n - 1))
    means = [x.mean(0) for x in sets]
    devs = [x - mu for x, mu in zip(sets, means)]
    pooled = np.vstack([wi * dv / np.sqrt(ni * (ni - 1)) for wi, dv, ni in zip(w, devs, n)])
    _, s, vt = np.linalg.svd(pooled, full_matrices=False)
    e_all = s ** 2
    rank = int(np.sum(e_all > 1e-12 * e_all[0])) if e_all.size and e_all[0] > 0 else 0
    if rank == 0:
        return None
    k = int(np.clip(k, 1, max(1, min(rank, nu - 2))))
    v, e = vt[:k], e_all[:k]
    proj = [dv @ v.T for dv in devs]
    lam = np.array([np.sum(a ** 2, 0) / (ni - 1) for a, ni in zip(proj, n)])   # (S, K)
    groups = _groups(k, n_groups)
    if np.all(n >= MIN_FRAMES_CV):
        lcv = _cross_validated(sets, w, n, k, cv_blocks)
        ratio = _smooth(np.where(lam > 0, lcv / np.where(lam > 0, lam, 1.0), 1.0))
        # out-of-sample variances, in both directions: in-sample variances along a
        # sample's own leading modes are biased *high* when frames are few
        lcv = lam * ratio
        tau = _tau(proj, lam, n, groups)
    else:
        lcv, tau = lam, np.ones((len(sets), len(groups)))
    tau_k = np.stack([_per_mode(ti, groups) for ti in tau])
    noise = np.sum((w ** 2 / n)[:, None] * tau_k * lcv, 0)
    beta = np.zeros((1, len(groups)))
    if residual == "cal-vs-cal":
        fr = []
        for a in range(1, len(sets)):
            for b in range(a + 1, len(sets)):
                delta = (means[a] - means[b]) @ v.T
                pred = tau_k[a] * lcv[a] / n[a] + tau_k[b] * lcv[b] / n[b]
                fr.append((delta ** 2 - pred) / (lcv[a] + lcv[b]))
        frac = np.mean(fr, axis=0)
        beta = np.clip([[np.mean(frac[g]) for g in groups]], 0, None)
        r_k = np.sum((w ** 2)[:, None] * _per_mode(beta[0], groups) * lcv, 0)
    elif residual == "split-halves":
        # each star's drift between its own blocks, extrapolated to whole sequences; the
        # target-calibrator difference carries half of it from each side
        beta = _drift_residual(sets, n, tau, len(groups))
        share = np.array([0.5] + [0.5 / (len(sets) - 1)] * (len(sets) - 1))
        r_k = np.sum(share[:, None] * np.stack([_per_mode(b, groups) for b in beta]) * lcv, 0)
    else:
        r_k = np.zeros(k)
    return {"v": v, "c": noise + r_k, "e": e, "tau": tau, "beta": beta, "r": r_k, "k": k}


def fit_error_model(target, calibrators, *, n_modes=0.5, residual="auto", n_groups=4,
                    cv_blocks=10, source="target"):
    """Fit the error model of `kpifs.calibration.errormodel` to the frames of a target and
    calibrators.

    The modes are those of each channel (so that whitening channel by channel
    projects the data exactly onto the modelled subspace); the covariance rows
    are the pooled frame deviations projected on them and rescaled to the
    modelled variances, so that they carry the channels' mutual correlations
    as the frames show them.

    Parameters
    ----------
    target : array-like (N_t, q, p)
        Kernel phases of the target's frames, in time order.
    calibrators : list of array-like (N_c, q, p)
        Kernel phases of each calibrator's frames, in time order.
    n_modes : float or int
        Modes kept per channel: a fraction of ``nu = sum (N_s - 1)`` (float <= 1)
        or a number.
    residual : {'auto', 'cal-vs-cal', 'split-halves', 'chi2', 'none'}
        Calibration-residual estimator. ``'auto'``: 'cal-vs-cal' with two or
        more calibrators, else 'chi2' (measured at detection on the calibrated
        data, `~kpifs.detect.channels.combined_scale`).
    n_groups : int
        Groups of mode ranks sharing one autocorrelation time and one residual fraction.
    cv_blocks : int
        Time blocks of the cross-validation.

    Returns
    -------
    `ErrorModel`

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.calibration.errormodel import fit_error_model
    >>> rng = np.random.default_rng(0)
    >>> mix = rng.standard_normal((6, 2 * 40))          # 6 aberration modes, 2 channels
    >>> def frames(n):                                     # drifting: a random walk
    ...     drift = np.cumsum(rng.standard_normal((n, 6)), axis=0) * 0.3
    ...     return (drift @ mix + rng.standard_normal((n, 80))).reshape(n, 2, 40)
    >>> em = fit_error_model(frames(40), [frames(40)])
    >>> em.rows.shape, em.n_modes, em.residual_method, bool(em.tau.max() > 1.5)
    ((80, 2, 40), 39, 'chi2', True)
    """
    if residual not in RESIDUAL_METHODS:
        raise KpifsError(f"unknown residual estimator {residual!r}: use one of "
                         f"{RESIDUAL_METHODS}")
    t = np.asarray(target, float)
    cals = [np.asarray(c, float) for c in calibrators]
    if not cals:
        raise KpifsError(f"{source}: the error model needs at least one calibrator")
    shape = t.shape[1:]
    for x in [t] + cals:
        if x.ndim != 3 or x.shape[1:] != shape:
            raise KpifsError(f"{source}: frame sets of shapes {t.shape} and {x.shape} do not "
                             f"match")
        if len(x) < 3:
            raise KpifsError(f"{source}: {len(x)} frame(s) are too few for an error model")
    q, p = shape
    m = len(cals)
    sets = [t] + cals
    w = np.array([1.0] + [1.0 / m] * m)
    n = np.array([len(x) for x in sets])
    nu = int(np.sum(n - 1))
    k = int(np.floor(n_modes * nu)) if isinstance(n_modes, float) and n_modes <= 1 \
        else int(n_modes)
    method = residual
    if method == "auto":
        method = "cal-vs-cal" if m >= 2 else "chi2"
    if method == "cal-vs-cal" and m < 2:
        raise KpifsError(f"{source}: 'cal-vs-cal' needs two calibrators or more")
    if method == "split-halves" and not np.all(n >= 4):
        raise KpifsError(f"{source}: 'split-halves' needs at least 4 frames per star")
    pooled = np.concatenate([wi * (x - x.mean(0)) / np.sqrt(ni * (ni - 1))
                             for wi, x, ni in zip(w, sets, n)])         # (sum N, q, p)
    rows = np.zeros_like(pooled)
    # the channels' models are independent: side by side on the cores
    chans = thread_map(lambda i: _channel_model([x[:, i] for x in sets], w, n, k, n_groups,
                                                cv_blocks, method), range(q))
    for i, ch in enumerate(chans):
        if ch is None:
            raise KpifsError(f"{source}: the frames do not vary at channel {i}: no noise to "
                             f"model")
        # pooled deviations on the channel's modes, each mode rescaled to its model variance
        coef = (pooled[:, i] @ ch["v"].T) * np.sqrt(ch["c"] / ch["e"])
        rows[:, i] = coef @ ch["v"]
    if method == "chi2":
        log.info("%s: one calibrator: the calibration residual is measured at detection, on "
                 "the calibrated data (errors and limits are scaled by it)", source)
    c = np.concatenate([ch["c"] for ch in chans])
    e = np.concatenate([ch["e"] for ch in chans])
    tau = np.concatenate([ch["tau"] for ch in chans], axis=1)
    kk = int(np.max([ch["k"] for ch in chans]))
    log.info("%s: error model of %d modes per channel (nu = %d): autocorrelation times up to "
             "%.2f, residual by %s, variance x%.2f over independent frames", source, kk, nu,
             float(tau.max()), method, float(np.mean(c / e)))
    return ErrorModel(rows=rows, variance=c, naive_variance=e, tau=tau,
                      residual=np.concatenate([ch["r"] for ch in chans]),
                      residual_method=method, n_modes=kk, dof=nu,
                      mode_fraction=float(kk / nu),
                      beta=np.concatenate([ch["beta"] for ch in chans], axis=1))
