"""The binary tests' elementwise loops: compiled where the package was built with its C
extension (``kpifs/detect/_kernels.c``), numpy otherwise, with the same numbers.

The binary forms ``sum_i max(z_i, 0)^power`` are clipped and summed element by
element, for every draw of the null and every Newton step of the limits. numpy
makes each operation a pass over the arrays (seven per channel for the null's
reduction, more than the matrix product that made the projections); the
extension reads each element once. `binary_forms` and `binary_maxima` perform
exactly numpy's operations in numpy's order (their results are the same bit for
bit); `newton_crossings` takes the limits' Newton steps as `crossing_sums` and
`kpifs.detect.limits` do in numpy, summing over the channels in order as numpy's
``einsum`` does where it makes no fused multiply-adds (it may elsewhere: the two
agree to single-precision rounding). `COMPILED` says which runs;
``KPIFS_PURE_NUMPY=1`` in the environment forces numpy.

Examples
--------
>>> import numpy as np
>>> from kpifs.detect._elementwise import binary_forms
>>> z = np.array([[-2.0, 1.0, 3.0]], np.float32)
>>> pos, sq, neg = (np.zeros_like(z) for _ in range(3))
>>> binary_forms(z, pos, sq, neg)
>>> pos.tolist(), sq.tolist(), neg.tolist()
([[0.0, 1.0, 3.0]], [[0.0, 1.0, 9.0]], [[4.0, 0.0, 0.0]])
"""
import os

import numpy as np

try:
    from . import _kernels
except ImportError:                           # not built (a source checkout, no compiler)
    _kernels = None

__all__ = ["binary_forms", "binary_maxima", "crossing_sums", "newton_crossings", "COMPILED",
           "TILE"]

#: Whether the compiled loops run (the extension was built and numpy is not forced).
COMPILED = _kernels is not None and os.environ.get("KPIFS_PURE_NUMPY", "") in ("", "0")

#: Rows (draws) per tile of numpy's loops: their work arrays stay in the processor's cache.
TILE = 32


def _ready(a):
    return a is None or (a.dtype == np.float32 and a.flags.c_contiguous)


def binary_forms(z, positive, square, negative):
    """Add ``max(z, 0)`` to *positive*, ``max(z, 0)^2`` to *square* and ``min(z, 0)^2``
    to *negative*, in place (float32 arrays (n, npos) of *z*'s shape; any may be None).
    numpy goes `TILE` rows at a time, whose work arrays stay in the cache."""
    if COMPILED and all(map(_ready, (z, positive, square, negative))):
        _kernels.binary_forms(z, positive, square, negative)
        return
    rows = min(TILE, len(z))
    # against an array of zeros, not the scalar 0: numpy's faster loop (same values)
    zero, w, v = (np.zeros((rows,) + z.shape[1:], np.float32) for _ in range(3))
    for a in range(0, len(z), TILE):
        b = min(a + TILE, len(z))
        zt, wt, vt = z[a:b], w[:b - a], v[:b - a]
        np.maximum(zt, zero[:b - a], out=wt)
        if positive is not None:
            positive[a:b] += wt
        if square is not None:
            wt *= wt
            square[a:b] += wt
        if negative is not None:
            np.minimum(zt, zero[:b - a], out=vt)
            vt *= vt
            negative[a:b] += vt


def binary_maxima(z, tot=None):
    """For each draw of *z* (m, q, npos), every channel's projections on the grid (float32),
    the grid maxima of the binary forms summed over the channels in order: ``max_p
    sum_j max(z_j, 0)^2``, ``max_p sum_j min(z_j, 0)^2``, ``max_p sum_j max(z_j, 0)`` and,
    with *tot* (m, npos), ``max_p (sum_j max(z_j, 0) - tot)`` (else -inf): (m, 4), float32.

    Compiled, the sums stay in the processor's cache, block of positions by block, and
    nothing of size (m, npos) is written; numpy accumulates channel by channel
    (`binary_forms`). The numbers are the same.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect._elementwise import binary_maxima
    >>> z = np.array([[[1.0, -2.0], [2.0, 0.5]]], np.float32)    # 1 draw, 2 channels
    >>> binary_maxima(z, np.array([[3.0, 0.0]], np.float32)).tolist()
    [[5.0, 4.0, 3.0, 0.5]]
    """
    m, q, npos = z.shape
    out = np.empty((m, 4), np.float32)
    if COMPILED and _ready(z) and _ready(tot) and m > 0:
        _kernels.binary_maxima(z, tot, out, m, q, npos)
        return out
    pos, sq, neg = (np.zeros((m, npos), np.float32) for _ in range(3))
    for j in range(q):
        binary_forms(z[:, j], pos, sq, neg)
    out[:, 0], out[:, 1], out[:, 2] = sq.max(axis=1), neg.max(axis=1), pos.max(axis=1)
    out[:, 3] = -np.inf if tot is None else (pos - tot).max(axis=1)
    return out


def crossing_sums(z, m32, c, power, *, u=None, zero=None):
    """``f = sum_j u_j^power`` and ``g = sum_j m_j u_j`` (power 2) or ``sum_j m_j
    [u_j > 0]`` (power 1), with ``u_j = max(z_j + m_j c, 0)``, for draws *z* (k, q, n),
    the signal per unit contrast *m32* (k, q) and contrasts *c* (k, n), all float32:
    the sums of a Newton step of the binary limits (`kpifs.detect.limits`), in numpy
    (compiled, `newton_crossings` makes them inside its steps). *u* (k, q, n) and
    *zero* (its zeros) are work arrays.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect._elementwise import crossing_sums
    >>> z = np.array([[[-1.0], [0.5]]], np.float32)       # one position, 2 channels
    >>> f, g = crossing_sums(z, np.ones((1, 2), np.float32), np.ones((1, 1), np.float32), 2)
    >>> f.tolist(), g.tolist()                             # u = (0, 1.5)
    ([[2.25]], [[1.5]])
    """
    c = np.ascontiguousarray(c, np.float32)
    u = np.empty(z.shape, np.float32) if u is None else u
    zero = np.zeros_like(u) if zero is None else zero
    np.einsum("kq,kn->kqn", m32, c, out=u)          # m c (an outer product: no sum)
    u += z
    np.maximum(u, zero, out=u)
    if power == 2:
        return np.einsum("kqn,kqn->kn", u, u), np.einsum("kq,kqn->kn", m32, u)
    return u.sum(axis=1), np.einsum("kq,kqn->kn", m32, (u > 0).astype(np.float32))


def newton_crossings(z, m32, c, threshold, power, *, n_iter, rtol, chunk):
    """The Newton steps of `kpifs.detect.limits._crossings`, compiled: *c* (k, N) updated
    in place, chunk of positions by chunk, each until its draws have converged. Returns
    False (and does nothing) where the extension does not run: the caller steps in numpy
    (`crossing_sums`)."""
    if not (COMPILED and _ready(z) and _ready(m32) and _ready(c)) or c.size == 0:
        return False
    k, q, n = z.shape
    _kernels.newton_crossings(z, m32, c, float(threshold), float(threshold ** (1 / power)),
                              int(power), int(n_iter), float(rtol), int(chunk), k, q, n)
    return True
