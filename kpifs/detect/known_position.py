"""Every registered test at one known position, by Monte-Carlo (the ROC experiment's
draws, `kpifs.detect.roc`)."""
import numpy as np

from .statistics import KnownPositionDraws, get_test, registered_names

__all__ = ["monte_carlo_roc"]


def monte_carlo_roc(x, *, n_draws=30000, seed=None, dof=None, tests=None, basis=None):
    """Statistics of every test under H0 and H1 for a signal *x*, by Monte-Carlo.

    Parameters
    ----------
    x : ndarray, shape (q, p)
        Whitened signal per channel (the binary test uses its direction as the
        template, i.e. the companion's position is known).
    n_draws : int
        Draws under each hypothesis.
    seed : int or `numpy.random.Generator`
    dof : sequence of int, optional
        Noise dimension kept per channel (rank of the whitening); default p.
    tests : sequence of str, optional
        Registered tests (`kpifs.detect.statistics`) with a known-position
        statistic; default every one (``'S'`` is the subspace test with a
        smooth spectrum over the channels, `kpifs.detect.spectral`, quadratic
        or of rank ``q - 1`` when there are fewer than four channels).
    basis : list of ndarray (p, r_i), optional
        Orthonormal bases of the whitened subspaces (noise is drawn in them);
        default the full space.

    Returns
    -------
    dict
        ``{test: (t0, t1)}`` with arrays of length *n_draws*.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.known_position import monte_carlo_roc
    >>> from kpifs.detect.stats import auc
    >>> x = np.full((1, 9), 1.0)                         # ||x|| = 3
    >>> res = monte_carlo_roc(x, n_draws=20000, seed=0)
    >>> round(auc(*res["NP"]), 2)
    0.98
    """
    rng = np.random.default_rng(seed)
    x = np.atleast_2d(np.asarray(x, float))
    q, p = x.shape
    if basis is None:
        basis = [None] * q
    ex0, ex1, ee0, ee1 = (np.zeros(n_draws) for _ in range(4))
    z0 = np.empty((n_draws, q))
    z1 = np.empty((n_draws, q))
    chunk = max(1, min(n_draws, 2 ** 24 // max(p, 1)))
    for i in range(q):
        norm = np.linalg.norm(x[i])
        for a in range(0, n_draws, chunk):
            b = min(n_draws, a + chunk)
            if basis[i] is None:
                e = rng.standard_normal((b - a, p))
            else:
                e = rng.standard_normal((b - a, basis[i].shape[1])) @ basis[i].T
            ex = e @ x[i]
            ex0[a:b] += ex
            ex1[a:b] += ex + norm ** 2
            ee = np.einsum("ij,ij->i", e, e)
            ee0[a:b] += ee
            ee1[a:b] += ee + 2 * ex + norm ** 2
            zi = ex / norm if norm > 0 else np.zeros(b - a)
            z0[a:b, i] = zi
            z1[a:b, i] = zi + norm
    draws = KnownPositionDraws((ex0, ex1), (ee0, ee1), (z0, z1), np.linalg.norm(x, axis=1))
    out = {}
    for name in registered_names() if tests is None else tests:
        stat = get_test(name).known_position(draws)
        if stat is not None:
            out[name] = stat
    return out
