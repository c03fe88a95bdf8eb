"""The separable factors of a block search's signatures on its grid (`kpifs.detect.blocks`).

A rotating sequence's search turns the uv plane once per time block, so its
grid needs ``sin`` and ``cos`` of ``2 pi x u'_b / lambda`` for every block
``b``: ten times the transcendental functions of a fixed sequence. On a
uniform axis ``exp(i a x_k)`` is the product of ``exp(i a x_0 + i a m j dx)``
and ``exp(i a l dx)`` (``k = m j + l``, ``m ~ sqrt(n)``): about ``2 sqrt(n)``
exponentials per frequency instead of ``n``, and one rounding more (1e-16,
far below the single precision the factors are stored in).
"""
import math

import numpy as np

from ..model.kernel import MAS

__all__ = ["axis_exp", "block_trig"]


def axis_exp(x, freq):
    """``exp(i outer(x, freq))`` (n, k), complex.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect._blocktrig import axis_exp
    >>> x, f = np.arange(-40, 41) * 7.5, np.array([0.013, -0.21, 0.5])
    >>> bool(np.allclose(axis_exp(x, f), np.exp(1j * np.outer(x, f)), rtol=0, atol=1e-13))
    True
    """
    x = np.asarray(x, float)
    freq = np.asarray(freq, float)
    n = x.size
    step = (x[-1] - x[0]) / (n - 1) if n > 1 else 0.0
    # a non-uniform axis (a grid given point by point): the plain exponentials
    if n < 16 or not np.allclose(np.diff(x), step, rtol=1e-9, atol=0):
        return np.exp(1j * np.outer(x, freq))
    m = int(math.ceil(math.sqrt(n)))
    fine = np.exp(1j * np.outer(np.arange(m) * step, freq))                    # (m, k)
    coarse = np.exp(1j * np.outer(x[0] + np.arange(0, n, m) * step, freq))    # (n/m, k)
    return (coarse[:, None, :] * fine[None, :, :]).reshape(-1, freq.size)[:n]


def block_trig(grid, uv, angles, lam):
    """``(sx, cx, sy, cy)`` of every block side by side along the uv axis, float32.

    ``sx[k, b * nuv + j] = sin(2 pi grid.x[k] u'_bj / lam)`` with ``u'_b = -u cos(a_b)
    + v sin(a_b)`` (``v'_b = u sin(a_b) + v cos(a_b)`` for ``sy``, ``cy``): the
    factors ``sin(theta) = sx cy + cx sy`` of each block's pose on the sky
    (as `kpifs.detect.DetectionModel`'s, per pose).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect._blocktrig import block_trig
    >>> grid = DetectionGrid.from_separation(100, 10, frame="sky")
    >>> sx, cx, sy, cy = block_trig(grid, np.array([[3.0, 1.0], [0.5, -2.0]]), [0, 30], 1.6e-6)
    >>> sx.shape, sx.dtype
    ((21, 4), dtype('float32'))
    """
    a = np.deg2rad(np.asarray(angles, float))[:, None]
    c, s = np.cos(a), np.sin(a)
    uu = (-c * uv[:, 0] + s * uv[:, 1]).ravel()
    vv = (s * uv[:, 0] + c * uv[:, 1]).ravel()
    out = []
    for axis, f in ((grid.x, uu), (grid.y, vv)):
        e = axis_exp(axis * MAS, 2 * np.pi * f / lam)
        out += [np.ascontiguousarray(e.imag, np.float32),
                np.ascontiguousarray(e.real, np.float32)]
    return tuple(out)
