"""The few distribution functions a search needs, from `scipy.special`.

``scipy.stats`` would give the same numbers (its normal and chi-square
functions are these ufuncs), but importing it costs ~0.35 s of a search that
should take seconds; the analysis tools (ROC curves, rank tests) still use it.
"""
import numpy as np

from .._lazy import lazy_module

special = lazy_module("scipy.special")


def norm_sf(x):
    """Standard normal survival function ``Q(x)``."""
    return special.ndtr(-np.asarray(x, float))


def norm_isf(p):
    """Inverse of `norm_sf`: ``Q^-1(p)``."""
    return -special.ndtri(p)


def norm_cdf(x):
    """Standard normal distribution function."""
    return special.ndtr(x)


def norm_ppf(p):
    """Standard normal quantile."""
    return special.ndtri(p)


def chi2_sf(x, k):
    """Chi-square survival function with *k* degrees of freedom (1 at ``x <= 0``)."""
    x = np.asarray(x, float)
    return np.where(x <= 0, 1.0, special.chdtrc(k, np.maximum(x, 0)))


def chi2_isf(p, k):
    """Inverse of `chi2_sf`."""
    return special.chdtri(k, p)


def chi2_cdf(x, k):
    """Chi-square distribution function."""
    return 1.0 - chi2_sf(x, k)


def chi2_ppf(p, k):
    """Chi-square quantile."""
    return special.chdtri(k, 1.0 - np.asarray(p, float))


def ncx2_sf(x, k, nc):
    """Non-central chi-square survival function (to ~1e-16 absolute: probabilities of
    detection, not tails)."""
    return 1.0 - special.chndtr(x, k, nc)


def lhs_normal(n, d, seed):
    """*n* standard normal draws in *d* dimensions by Latin hypercube sampling.

    Every dimension has exactly one draw at the middle of each of *n*
    equiprobable strata (in an independent random order): its marginal law is
    reproduced to ``1 / n`` and the variance of any sum of one-dimensional
    functions, which the binary statistic nearly is, falls far below plain
    Monte Carlo's (McKay, Beckman & Conover 1979; Stein 1987).
    """
    rng = np.random.default_rng(seed)
    strata = rng.permuted(np.tile(np.arange(n), (d, 1)), axis=1).T
    return special.ndtri((strata + 0.5) / n)


def order_quantile(crossings, pd):
    """Smallest contrast detected in a fraction *pd* of the draws (axis -1): an order
    statistic of their crossing contrasts (NaN where that is never reached)."""
    n = crossings.shape[-1]
    k = min(n - 1, max(0, int(np.ceil(pd * n)) - 1))
    out = np.partition(crossings, k, axis=-1)[..., k]
    return np.where(np.isfinite(out), out, np.nan)
