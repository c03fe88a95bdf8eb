"""Detection statistics on whitened kernel phases and their laws.

Model (per channel ``i``, whitened): ``H0: y_i = e_i``, ``H1: y_i = x_i + e_i`` with
``e_i ~ N(0, I)``. Tests:

- Neyman-Pearson ``T_NP = sum_i y_i^T x_i`` (needs the true ``x``; the optimal
  reference): ``P_D = Q(Q^-1(P_FA) - ||x||)``.
- energy detector ``T_E = sum_i ||y_i||^2``: ``chi2_dof`` under H0, non-central
  ``chi2_dof(||x||^2)`` under H1.
- binary test at a known position, with ``z_i = s_i^T y_i / ||s_i||`` (N(0, 1)
  under H0): the generalised likelihood ratio ``T_B = sum_i max(z_i, 0)^2``
  ("B", the chi-bar-squared law ``P_FA = sum_k C(q, k) 2^-q chi2_k.sf``) and the
  seed paper's printed form ``T_B' = sum_i max(z_i, 0)`` ("B-paper",
  ``P_FA = sum_k C(q, k) 2^-q P(sum of k half-normals > xi)``). They coincide
  for one channel.

The tests themselves (their maps, nulls, limits and labels) are objects of
`kpifs.detect.statistics`, built on these laws.
"""
import numpy as np

from .._lazy import lazy_module
from ..exceptions import KpifsError
from . import spectral
from ._laws import chi2_isf, chi2_sf, ncx2_sf, norm_isf, norm_sf

optimize = lazy_module("scipy.optimize")
special = lazy_module("scipy.special")
stats = lazy_module("scipy.stats")

__all__ = ["check_probability", "np_threshold", "np_pd", "energy_threshold",
           "energy_pd", "binary_pfa", "binary_threshold", "binary_statistic", "np_statistic",
           "energy_statistic", "auc", "roc_curve", "known_position_subspace"]


def check_probability(value, name):
    """Return *value* as a float in (0, 1), else raise a `~kpifs.KpifsError`.

    Examples
    --------
    >>> from kpifs.detect.stats import check_probability
    >>> check_probability("1e-3", "P_FA")
    0.001
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise KpifsError(f"{name} must be a number in (0, 1), got {value!r}") from None
    if not 0 < v < 1:
        raise KpifsError(f"{name} must be in (0, 1), got {v}")
    return v


# --- Neyman-Pearson ------------------------------------------------------------
def np_statistic(y, x):
    """``T_NP = sum y x`` over the last two axes (channels, kernels).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.stats import np_statistic
    >>> float(np_statistic(np.ones((2, 3)), np.full((2, 3), 0.5)))
    3.0
    """
    return np.sum(np.asarray(y) * np.asarray(x), axis=(-2, -1))


def np_threshold(pfa, norm_x):
    """Threshold of ``T_NP`` at false-alarm probability *pfa*: ``||x|| Q^-1(P_FA)``.

    Examples
    --------
    >>> from kpifs.detect.stats import np_threshold
    >>> round(float(np_threshold(0.01, 3.0)), 4)
    6.979
    """
    return norm_x * norm_isf(check_probability(pfa, "P_FA"))


def np_pd(pfa, norm_x):
    """Detection probability of ``T_NP``: ``Q(Q^-1(P_FA) - ||x||)``.

    Examples
    --------
    >>> from kpifs.detect.stats import np_pd
    >>> round(float(np_pd(0.01, 3.0)), 4)
    0.7497
    """
    return norm_sf(norm_isf(check_probability(pfa, "P_FA")) - np.asarray(norm_x))


# --- energy detector -----------------------------------------------------------
def energy_statistic(y):
    """``T_E = ||y||^2`` over the last two axes.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.stats import energy_statistic
    >>> float(energy_statistic(np.full((2, 3), 2.0)))
    24.0
    """
    return np.sum(np.asarray(y) ** 2, axis=(-2, -1))


def energy_threshold(pfa, dof):
    """Threshold of ``T_E``: the ``chi2_dof`` quantile.

    Examples
    --------
    >>> from kpifs.detect.stats import energy_threshold
    >>> round(float(energy_threshold(0.01, 303)), 3)
    363.191
    """
    return chi2_isf(check_probability(pfa, "P_FA"), dof)


def energy_pd(pfa, dof, norm_x):
    """Detection probability of ``T_E``: ``ncx2.sf(xi, dof, ||x||^2)``.

    Examples
    --------
    >>> from kpifs.detect.stats import energy_pd
    >>> round(float(energy_pd(0.01, 303, 3.0)), 4)
    0.0258
    """
    return ncx2_sf(energy_threshold(pfa, dof), dof, np.asarray(norm_x) ** 2)


# --- binary test at a known position --------------------------------------------
def binary_statistic(z, form="B"):
    """``sum_i max(z_i, 0)^2`` (``'B'``) or ``sum_i max(z_i, 0)`` (``'B-paper'``) over axis -1.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.stats import binary_statistic
    >>> z = np.array([2.0, -1.0, 1.0])
    >>> float(binary_statistic(z, "B")), float(binary_statistic(z, "B-paper"))
    (5.0, 3.0)
    """
    zp = np.clip(z, 0, None)
    if form == "B":
        return np.sum(zp ** 2, axis=-1)
    if form == "B-paper":
        return np.sum(zp, axis=-1)
    raise KpifsError(f"unknown binary-test form {form!r}: 'B' or 'B-paper'")


def _half_normal_sum_sf(xi, k):
    """P(sum of k independent half-normals > xi), by numerical convolution.

    Each variable is discretised into exact bin probabilities placed at the bin
    midpoints (rounding errors average out: second-order accurate).
    """
    if k == 0:
        return np.where(np.asarray(xi) < 0, 1.0, 0.0)
    if k == 1:
        return 2 * norm_sf(np.clip(xi, 0, None))
    from scipy.signal import fftconvolve
    dx = 0.001
    edges = np.arange(0, 8.5 + 2 * np.sqrt(k) + dx, dx)
    masses = np.diff(special.erf(edges / np.sqrt(2)))
    dist = masses
    for _ in range(k - 1):
        dist = np.clip(fftconvolve(dist, masses)[:len(masses)], 0, None)
    loc = (np.arange(len(dist)) + 0.5 * k) * dx
    sf = 1 - np.cumsum(dist)            # P(S > loc[j])
    return np.interp(np.clip(xi, 0, None), loc, sf, left=1.0, right=0.0)


def binary_pfa(xi, n_channels, form="B"):
    """False-alarm probability of the binary test at one known position.

    ``'B'``: ``sum_k C(q, k) 2^-q chi2_k.sf(xi)``; ``'B-paper'``:
    ``sum_k C(q, k) 2^-q P(sum of k half-normals > xi)`` (numerical for k >= 2).

    Examples
    --------
    >>> from kpifs.detect.stats import binary_pfa
    >>> round(float(binary_pfa(8.7464, 3, "B")), 4)
    0.01
    >>> round(float(binary_pfa(4.1544, 3, "B-paper")), 4)
    0.01
    """
    xi = np.asarray(xi, float)
    q = int(n_channels)
    if form not in ("B", "B-paper"):
        raise KpifsError(f"unknown binary-test form {form!r}: 'B' or 'B-paper'")
    weights = special.comb(q, np.arange(1, q + 1)) / 2 ** q
    if form == "B":
        # one ufunc call over (degrees of freedom, values)
        total = np.tensordot(weights, chi2_sf(xi[None], np.arange(1, q + 1).reshape(
            (q,) + (1,) * xi.ndim)), axes=(0, 0))
    else:
        total = np.zeros_like(xi)
        for k in range(1, q + 1):
            total = total + weights[k - 1] * _half_normal_sum_sf(xi, k)
    return np.where(xi <= 0, 1.0, total)


def binary_threshold(pfa, n_channels, form="B"):
    """Threshold of the binary test at one known position (inverse of `binary_pfa`).

    Examples
    --------
    >>> from kpifs.detect.stats import binary_threshold
    >>> round(binary_threshold(0.01, 3, "B"), 3)
    8.746
    """
    pfa = check_probability(pfa, "P_FA")
    if pfa >= 1 - 2.0 ** -n_channels:
        raise KpifsError(f"P_FA = {pfa} is not reachable: the statistic is 0 with "
                         f"probability {2.0 ** -n_channels}")
    hi = 1.0
    while binary_pfa(hi, n_channels, form) > pfa:
        hi *= 2
    return optimize.brentq(lambda t: binary_pfa(t, n_channels, form) - pfa, 1e-12, hi,
                           xtol=1e-10)


# --- ROC ------------------------------------------------------------------------
def roc_curve(t0, t1, pfa=None):
    """Empirical ROC from statistics under H0 (*t0*) and H1 (*t1*).

    Returns ``(pfa, pd)`` with *pd* the fraction of *t1* above the thresholds that
    give the false-alarm rates *pfa* on *t0* (default: a log grid 1e-4..1).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.stats import roc_curve
    >>> rng = np.random.default_rng(0)
    >>> pfa, pd = roc_curve(rng.normal(0, 1, 10000), rng.normal(3, 1, 10000), pfa=[0.01])
    >>> abs(float(pd[0]) - 0.7497) < 0.02        # theory: Q(Q^-1(0.01) - 3)
    True
    """
    t0 = np.sort(np.asarray(t0, float))
    t1 = np.asarray(t1, float)
    if pfa is None:
        pfa = np.unique(np.concatenate([np.logspace(-4, 0, 81), np.linspace(0, 1, 101)[1:]]))
    pfa = np.asarray(pfa, float)
    thr = np.quantile(t0, 1 - pfa, method="higher")
    pd = np.mean(t1[None, :] > thr[:, None], axis=1)
    return pfa, pd


def auc(t0, t1):
    """Area under the ROC curve: ``P(T1 > T0)`` (Mann-Whitney), ties counted half.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.stats import auc
    >>> rng = np.random.default_rng(0)
    >>> round(auc(rng.normal(0, 1, 20000), rng.normal(1, 1, 20000)), 2)
    0.76
    """
    t0 = np.asarray(t0, float)
    t1 = np.asarray(t1, float)
    ranks = stats.rankdata(np.concatenate([t0, t1]))
    r1 = ranks[len(t0):].sum()
    return float((r1 - len(t1) * (len(t1) + 1) / 2) / (len(t0) * len(t1)))


def known_position_subspace(norms):
    """Weights ``W`` (r, q) and sign vector ``h`` (r,) of the subspace test at a known
    position whose channels' signal norms are *norms*: a smooth spectrum over the
    channels' order, of fewer dimensions than channels (detect's ``'auto'`` rule, else
    B is the better test), and a spectrum of positive mean only (``h^T W z > 0``,
    `kpifs.detect.spectral.subspace_sign`).

    Examples
    --------
    >>> from kpifs.detect.stats import known_position_subspace
    >>> w, h = known_position_subspace([1.0, 1.0, 1.0, 1.0])
    >>> w.shape, h.shape
    ((3, 4), (3,))
    """
    norms = np.asarray(norms, float)
    q = len(norms)
    basis = spectral.smooth_basis(np.arange(1.0, q + 1), max(1, min(3, q - 1)))
    n2 = norms[:, None] ** 2
    w = spectral.subspace_weights(n2, basis)
    return w[:, :, 0], spectral.subspace_sign(w, n2, basis)[:, 0]
