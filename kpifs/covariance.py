"""Covariance of kernel phases and whitening operators.

Three estimators:

- `empirical_covariance`: the sample covariance of per-frame kernel phases,
  per channel (``(nwave, nkp, nkp)``) or joint across channels
  (``(nwave*nkp, nwave*nkp)``, which captures spectral cross-talk);
- Ledoit-Wolf shrinkage (`ledoit_wolf`) towards a scaled identity, used
  automatically (with a warning) when there are too few frames for the sample
  covariance to be invertible;
- `propagated_covariance`: photon and read noise propagated through the
  linear extraction (``phi = arg(M w I)``), for one frame.

`whitening_matrix` returns ``W = Sigma^(-1/2)`` (symmetric), so that
``y = W k`` has identity covariance.
"""
import logging
import warnings

import numpy as np

from .exceptions import KpifsError, KpifsWarning

__all__ = ["empirical_covariance", "ledoit_wolf", "hartlap_factor",
           "whitening_matrix", "whitening_range", "whiten", "calibrated_covariance",
           "filled_covariance", "unfilled_covariance", "COVFILL_FACTOR"]

log = logging.getLogger(__name__)

SHRINKAGE = ("auto", "ledoit-wolf", "none")


def ledoit_wolf(x):
    """Ledoit-Wolf (2004) shrinkage covariance of samples *x* (n, p).

    ``(1 - s) S + s mu I`` with ``S`` the (1/n) sample covariance, ``mu = tr(S)/p``
    and ``s = min(b2, d2) / d2`` where ``d2 = ||S - mu I||_F^2`` and
    ``b2 = (1/n^2) sum_k ||x_k x_k^T - S||_F^2``.

    Returns
    -------
    cov : ndarray (p, p)
    shrinkage : float

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.covariance import ledoit_wolf
    >>> x = np.random.default_rng(0).standard_normal((20, 50))
    >>> cov, s = ledoit_wolf(x)
    >>> bool(np.all(np.linalg.eigvalsh(cov) > 0)), bool(0.5 < s <= 1)
    (True, True)
    """
    x = np.asarray(x, float)
    n, p = x.shape
    if n < 2:
        raise KpifsError("at least two frames are needed to estimate a covariance")
    xc = x - x.mean(axis=0)
    s = xc.T @ xc / n
    mu = np.trace(s) / p
    d2 = np.sum(s ** 2) - 2 * mu * np.trace(s) + mu ** 2 * p
    # sum_k ||x_k x_k^T - S||_F^2 = sum_k ||x_k||^4 - n ||S||_F^2
    b2 = (np.sum(np.sum(xc ** 2, axis=1) ** 2) - n * np.sum(s ** 2)) / n ** 2
    shrink = 1.0 if d2 <= 0 else float(min(b2, d2) / d2)
    cov = (1 - shrink) * s
    cov[np.diag_indices(p)] += shrink * mu
    return cov, shrink


def hartlap_factor(n_frames, dim):
    """``(N - 1) / (N - p - 2)``: the bias of the inverse of a sample covariance.

    ``E[S^-1] = (N - 1) / (N - p - 2) Sigma^-1`` for the sample covariance ``S`` of
    ``N`` Gaussian frames in ``p`` dimensions (Hartlap, Simon & Schneider 2007,
    A&A 464, 399); multiplying ``S`` by this factor makes the whitened data
    have unit variance on average. Infinite when ``N <= p + 2``.

    Examples
    --------
    >>> from kpifs.covariance import hartlap_factor
    >>> round(hartlap_factor(100, 74), 3)
    4.125
    """
    return (n_frames - 1) / (n_frames - dim - 2) if n_frames > dim + 2 else np.inf


def _one_covariance(x, shrinkage, what):
    n, p = x.shape
    if n < 2:
        raise KpifsError(f"{what}: at least two frames are needed to estimate a covariance, "
                         f"got {n}")
    if shrinkage == "auto":
        shrinkage = "ledoit-wolf" if n <= p else "none"
        if n <= p:
            warnings.warn(f"{what}: {n} frames for {p} kernel phases: the sample covariance "
                          f"is singular; using Ledoit-Wolf shrinkage (false-alarm "
                          f"probabilities assume a known covariance and will be optimistic: "
                          f"use more frames than kernel phases, or a coarser pupil model)",
                          KpifsWarning, stacklevel=3)
    if shrinkage == "ledoit-wolf":
        cov, s = ledoit_wolf(x)
        return cov * n / (n - 1), s
    return np.cov(x, rowvar=False, ddof=1).reshape(p, p), 0.0


def empirical_covariance(kp, *, joint=False, shrinkage="auto", debias=False,
                         source="kernel phases"):
    """Covariance of one frame's kernel phases, estimated from many frames.

    Parameters
    ----------
    kp : ndarray, shape (nframe, nwave, nkp)
    joint : bool
        Estimate the joint ``(nwave*nkp, nwave*nkp)`` covariance (cross-channel
        correlations included) instead of one ``(nkp, nkp)`` block per channel.
    shrinkage : {'auto', 'ledoit-wolf', 'none'}
        ``'auto'`` uses Ledoit-Wolf (with a `~kpifs.KpifsWarning`) when the
        frames are not more than the dimension, the sample covariance otherwise.
    debias : bool
        Scale a sample covariance by `hartlap_factor`, so that whitening with
        it gives unit variance on average (what detection tests assume).

    Returns
    -------
    cov : ndarray, shape (nwave, nkp, nkp) or (nwave*nkp, nwave*nkp)

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.covariance import empirical_covariance
    >>> kp = np.random.default_rng(1).normal(0, 0.1, (500, 3, 10))
    >>> cov = empirical_covariance(kp)
    >>> cov.shape, round(float(np.mean(np.diagonal(cov, axis1=1, axis2=2))), 2)
    ((3, 10, 10), 0.01)
    """
    if shrinkage not in SHRINKAGE:
        raise KpifsError(f"shrinkage must be one of {SHRINKAGE}, got {shrinkage!r}")
    kp = np.asarray(kp, float)
    if kp.ndim != 3:
        raise KpifsError(f"{source}: expected kernel phases (nframe, nwave, nkp), got shape "
                         f"{kp.shape}")
    if not np.all(np.isfinite(kp)):
        raise KpifsError(f"{source}: kernel phases contain NaN or inf")
    nf, nw, nk = kp.shape
    if joint:
        cov, s = _one_covariance(kp.reshape(nf, nw * nk), shrinkage, source)
        log.debug("%s: joint covariance, shrinkage %.3f", source, s)
        if debias and s == 0:
            cov = cov * _checked_hartlap(nf, nw * nk, source)
        return cov
    out = np.empty((nw, nk, nk))
    shrunk = False
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", KpifsWarning)
        for i in range(nw):
            out[i], s = _one_covariance(kp[:, i], shrinkage, source)
            shrunk |= s > 0
    if caught:  # one warning for all channels, not one per channel
        warnings.warn(str(caught[0].message), KpifsWarning, stacklevel=2)
    if debias and not shrunk:
        out *= _checked_hartlap(nf, nk, source)
    return out


def _checked_hartlap(n, p, source):
    f = hartlap_factor(n, p)
    if np.isfinite(f) and f > 1.5:
        warnings.warn(f"{source}: {n} frames for {p} kernel phases: the inverse covariance is "
                      f"debiased by a factor {f:.2f} (Hartlap et al. 2007); its errors still "
                      f"give heavier tails than Gaussian, so false-alarm probabilities are "
                      f"optimistic: use several times more frames than kernel phases",
                      KpifsWarning, stacklevel=3)
    return f if np.isfinite(f) else 1.0


def calibrated_covariance(target_cov, n_target, calibrator_covs, n_calibrators):
    """Covariance of ``mean(target) - mean over calibrators of mean(calibrator)``.

    ``Sigma_t / N_t + (1/M^2) sum_m Sigma_m / N_m`` for *M* calibrators.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.covariance import calibrated_covariance
    >>> calibrated_covariance(np.eye(2), 100, [np.eye(2)], [50])
    array([[0.03, 0.  ],
           [0.  , 0.03]])
    """
    m = len(calibrator_covs)
    cal = sum(c / n for c, n in zip(calibrator_covs, n_calibrators)) / m ** 2
    return target_cov / n_target + cal


def whitening_matrix(cov, *, rtol=1e-6, return_rank=False, source="covariance"):
    """Whitening operator ``W = Sigma^(-1/2)`` of one covariance or a stack of them.

    Eigen-modes whose variance is below ``rtol`` times the largest are left out
    (their rows of ``W`` are zero): kernel phases measured on a field of view
    too small for the model's uv sampling, or from fewer frames than kernels
    without shrinkage, have such (near-)null modes, which carry neither noise
    nor measurable signal. The number of modes kept is the effective number
    of degrees of freedom of the whitened data.

    Parameters
    ----------
    cov : ndarray, shape (..., n, n)
    rtol : float
        Relative eigenvalue threshold.
    return_rank : bool
        Also return the number of modes kept (an int, or an array for a stack).

    Raises
    ------
    `~kpifs.KpifsError`
        If a matrix is not symmetric, not finite, or has a clearly negative
        eigenvalue (not a covariance).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.covariance import whitening_matrix
    >>> w = whitening_matrix(np.array([[4.0, 0.0], [0.0, 0.25]]))
    >>> np.round(w, 3)
    array([[0.5, 0. ],
           [0. , 2. ]])
    """
    cov = np.asarray(cov, float)
    if cov.ndim < 2 or cov.shape[-1] != cov.shape[-2]:
        raise KpifsError(f"{source}: a covariance must be square, got shape {cov.shape}")
    if not np.all(np.isfinite(cov)):
        raise KpifsError(f"{source}: covariance contains NaN or inf")
    if not np.allclose(cov, np.swapaxes(cov, -1, -2), rtol=1e-8,
                       atol=1e-12 * np.abs(cov).max()):
        raise KpifsError(f"{source}: covariance is not symmetric")
    sym = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    vals, vecs = np.linalg.eigh(sym)
    top = vals.max(axis=-1, keepdims=True)
    if np.any(top <= 0) or np.any(vals < -1e-8 * top):
        worst = float(np.min(vals / np.where(top > 0, top, 1)))
        raise KpifsError(f"{source}: not a covariance: it is not positive (semi-)definite "
                         f"(smallest/largest eigenvalue {worst:.2e})")
    keep = vals > rtol * top
    rank = keep.sum(axis=-1)
    n = cov.shape[-1]
    if np.any(rank < n):
        log.info("%s: %s of %d modes kept for whitening (eigenvalues above %.0e of the "
                 "largest)", source, np.unique(rank).tolist(), n, rtol)
    inv_sqrt = np.where(keep, 1 / np.sqrt(np.where(keep, vals, 1.0)), 0.0)
    w = _from_modes(vecs, inv_sqrt, keep)
    if return_rank:
        return w, (int(rank) if np.ndim(rank) == 0 else rank)
    return w


def whitening_range(w, rank, *, oversample=8, seed=0):
    """An orthonormal basis of the range of a whitening operator of low *rank*.

    A covariance measured on few frames keeps few modes (`whitening_matrix`):
    the whitened data and every whitened signature then lie in a subspace of
    dimension *rank*, and products through the operator can be made in that
    subspace's coordinates. The basis is found as in randomised range finders
    (Halko, Martinsson & Tropp 2011, algorithm 4.1): the left singular vectors
    of ``w @ Omega`` for a Gaussian ``Omega`` of ``rank + oversample`` columns
    (drawn from *seed*: the same basis on every call), those above ``1e-10`` of
    the largest singular value kept.

    Returns ``Q`` (p, r) with ``Q Q^T w = w`` to rounding, or None when the range
    is wider than ``rank + oversample`` columns can show (the operator is not of
    that low rank) or more than half the dimension (nothing to gain).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.covariance import whitening_matrix, whitening_range
    >>> x = np.random.default_rng(1).standard_normal((5, 40))
    >>> w, rank = whitening_matrix(x.T @ x, return_rank=True)      # 5 frames, 40 kernels
    >>> q = whitening_range(w, rank)
    >>> rank, q.shape, bool(np.allclose(q @ (q.T @ w), w))
    (5, (40, 5), True)
    >>> whitening_range(np.eye(40), 40) is None                     # full rank: none
    True
    """
    w = np.asarray(w, float)
    p = w.shape[-1]
    k = int(rank) + oversample
    if k > p // 2:
        return None
    omega = np.random.default_rng(seed).standard_normal((p, k))
    u, s, _ = np.linalg.svd(w @ omega, full_matrices=False)
    if not s[0] > 0:
        return None
    r = int(np.sum(s > 1e-10 * s[0]))
    return u[:, :r] if r < k else None


#: A covariance written for other tools (KP-COV) gives the directions it leaves out
#: this many times the larger of its largest variance and the data's mean square there
#: (`filled_covariance`).
COVFILL_FACTOR = 1e6


def filled_covariance(cov, *, data=None, rtol=1e-6, factor=COVFILL_FACTOR):
    """A positive-definite covariance that weighs data as `whitening_matrix` does.

    An error model of few frames keeps only its best-measured modes
    (`kpifs.calibration.errormodel`): its covariance is singular, and `whitening_matrix`
    leaves the other directions out (those below *rtol* of the largest
    variance). A tool that inverts the covariance needs it definite: each
    left-out direction is given the variance ``fill``, *factor* times the larger
    of the largest variance and the mean square of *data* (..., q, p) there, so
    that it weighs next to nothing (the data's chi-square grows by at most
    ``1 / factor`` per such direction), as in the search.

    Returns ``(filled, fill)``: *cov* itself and 0.0 when nothing is left out.
    `unfilled_covariance` takes the fill back out.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.covariance import filled_covariance, whitening_matrix, whiten
    >>> cov = np.diag([4.0, 1.0, 0.0])[None]              # one direction unmeasured
    >>> d = np.array([[2.0, 1.0, 5.0]])
    >>> full, fill = filled_covariance(cov, data=d)
    >>> fill, bool(np.all(np.linalg.eigvalsh(full) > 0))
    (25000000.0, True)
    >>> chi2 = float(d[0] @ np.linalg.inv(full[0]) @ d[0])
    >>> round(chi2, 6), float(np.sum(whiten(d, whitening_matrix(cov)) ** 2))
    (2.000001, 2.0)
    """
    cov = np.asarray(cov, float)
    vals, vecs = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    top = vals.max(axis=-1, keepdims=True)
    out = vals <= rtol * top                                    # (..., p)
    if not out.any():
        return cov, 0.0
    level = float(top.max())
    if data is not None:
        d = np.asarray(data, float).reshape((-1,) + cov.shape[:-1])
        proj = np.einsum("...ij,n...i->n...j", vecs, d) ** 2   # (n, ..., p) on the modes
        n_out = np.maximum(out.sum(axis=-1), 1)
        level = max(level, float(np.max(np.sum(np.where(out, proj, 0.0), axis=-1) / n_out)))
    fill = factor * level
    new = np.where(out, fill, vals)
    return (vecs * new[..., None, :]) @ np.swapaxes(vecs, -1, -2), fill


def unfilled_covariance(cov, fill):
    """*cov* without the variance *fill* that `filled_covariance` gave the directions its
    covariance left out (those are 0 again; 0 *fill*: *cov* itself).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.covariance import filled_covariance, unfilled_covariance
    >>> cov = np.diag([4.0, 1.0, 0.0])[None]
    >>> back = unfilled_covariance(*filled_covariance(cov))
    >>> bool(np.allclose(back, cov, atol=1e-6))
    True
    """
    cov = np.asarray(cov, float)
    if not fill:
        return cov
    vals, vecs = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    kept = vals <= 0.5 * fill
    return _from_modes(vecs, np.where(kept, vals, 0.0), kept)


def _from_modes(vecs, weights, keep):
    """``V diag(weights) V^T`` from the eigenvectors *vecs* (..., n, n) and weights (..., n)
    that are 0 where *keep* is False: through the kept modes only (a covariance of few
    frames keeps a few of hundreds), in their order."""
    r = int(keep.sum(axis=-1).max()) if keep.size else 0
    if r >= keep.shape[-1] // 2:
        return (vecs * weights[..., None, :]) @ np.swapaxes(vecs, -1, -2)
    # the kept modes first, in order; a matrix of fewer pads with dropped ones (weight 0)
    idx = np.argsort(~keep, axis=-1, kind="stable")[..., :r]
    v = np.take_along_axis(vecs, idx[..., None, :], axis=-1)
    wt = np.take_along_axis(weights, idx, axis=-1)
    return (v * wt[..., None, :]) @ np.swapaxes(v, -1, -2)


def rows_covariance(rows, *, joint=False):
    """The covariance ``R^T R`` that covariance rows ``(nrow, nwave, nkp)`` carry: per
    channel ``(nwave, nkp, nkp)``, or across channels ``(nwave*nkp, nwave*nkp)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.covariance import rows_covariance
    >>> rows = np.zeros((2, 1, 2)); rows[0, 0, 0], rows[1, 0, 1] = 2.0, 3.0
    >>> rows_covariance(rows)[0].tolist(), rows_covariance(rows, joint=True).shape
    ([[4.0, 0.0], [0.0, 9.0]], (2, 2))
    """
    rows = np.asarray(rows, float)
    if joint:
        flat = rows.reshape(len(rows), -1)
        return flat.T @ flat
    return np.matmul(rows.transpose(1, 2, 0), rows.transpose(1, 0, 2))


def whiten(kp, w):
    """Apply whitening operators: ``y = W k`` per channel, or jointly.

    Parameters
    ----------
    kp : ndarray, shape (..., nwave, nkp)
    w : ndarray, shape (nwave, nkp, nkp) (per channel) or (nwave*nkp, nwave*nkp)

    Returns
    -------
    ndarray, shape (..., nwave, nkp)

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.covariance import whiten
    >>> w = np.stack([np.diag([2.0, 0.5])])            # one channel, two kernel phases
    >>> whiten(np.array([[1.0, 4.0]]), w)
    array([[2., 2.]])
    """
    kp = np.asarray(kp, float)
    nw, nk = kp.shape[-2:]
    if w.shape == (nw, nk, nk):
        lead = kp.shape[:-2]
        if int(np.prod(lead)) < 8:
            return np.einsum("wij,...wj->...wi", w, kp)
        # many rows (noise rows, a term's rows): one matrix product per channel (BLAS),
        # not einsum's loop
        flat = np.moveaxis(kp.reshape((-1, nw, nk)), 1, 0)                  # (nw, M, nk)
        out = np.matmul(flat, np.swapaxes(w, 1, 2))
        return np.moveaxis(out, 0, 1).reshape(kp.shape)
    if w.shape == (nw * nk, nw * nk):
        flat = kp.reshape(kp.shape[:-2] + (nw * nk,))
        return (flat @ w.T).reshape(kp.shape)
    raise KpifsError(f"whitening operator of shape {w.shape} does not fit kernel phases "
                     f"({nw} channels x {nk})")
