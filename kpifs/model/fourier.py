"""Fourier transforms of image cut-outs at a kernel model's uv points.

All paths compute, for images ``I`` of shape ``(ny, nx)`` whose pixel
``(ny // 2, nx // 2)`` is the origin,

``V(u, v) = sum_pixels I(x, y) exp(-2 pi i (u x + v y) / lam)``

(DESIGN.md section 3), with ``(x, y)`` the pixel offsets times the pixel
scale in radians. Three ways, one result:

``'dense'``
    The reference: one explicit ``(2 nuv, ny nx)`` real matrix (cos rows,
    then -sin rows) applied to the flattened images, ``4 nuv ny nx`` flops
    per image.
``'separable'``
    When every uv point lies on a rectangular lattice, ``u = m s_x`` and
    ``v = n s_y`` with integer ``m, n`` (every square-grid pupil model,
    whatever its grid offset, since baselines are differences of grid
    points; hexagonal grids too, on the lattice ``(s/2, s sqrt(3)/2)``), the
    transform factorises: one product along x for the distinct ``m``, one
    along y for the distinct ``n``, then a gather of the uv points. About
    ``4 N_y ny nx + 8 N_y nx M_x`` flops per image (y first; x first when
    that is cheaper), ``M_x`` the number of distinct ``|m|`` (cos is even
    and sin odd in m: the sign is applied in the gather): ~18x fewer than
    dense for the usual models.
``'nufft'``
    Any other model (a grid rotated on the detector, irregular
    sub-apertures): a type-2 non-uniform FFT with `finufft` (optional
    dependency, ``pip install kpifs[nufft]``), accuracy ``nufft_eps``.

`fourier_operator` picks a path (``'auto'``: separable when the lattice is
found and pays, else nufft when finufft is installed, else dense) and keeps
the operators in a bounded module-level cache keyed by the uv points' digest,
wavelength, pixel scale, shape and path, so that models rebuilt for every
file reuse them.
"""
import hashlib
import threading
from collections import OrderedDict

import numpy as np

from ..exceptions import KpifsError

__all__ = ["FourierOperator", "fourier_operator", "uv_lattice", "METHODS",
           "clear_cache", "cache_info"]

#: Fourier paths that `fourier_operator` accepts.
METHODS = ("auto", "separable", "nufft", "dense")

#: Memory budget of the cache of operators (bytes). Separable operators are
#: small (tens of kB); a dense one of 610 uv points for a 64x64 cut-out is 40 MB.
CACHE_BYTES = 512 * 2 ** 20

#: Largest number of operators kept, whatever their size.
CACHE_ENTRIES = 256

_cache = OrderedDict()
_cache_lock = threading.Lock()


def _axis_lattice(c, scale, rtol, max_div=8):
    """Step ``s`` and integers ``k`` with ``c == k s`` (to ``rtol * scale``), or None."""
    tol = rtol * scale
    a = np.abs(c)
    nz = a[a > tol]
    if nz.size == 0:
        return 1.0, np.zeros(len(c), np.int64)
    s0 = nz.min()
    for div in range(1, max_div + 1):
        s = s0 / div
        k = np.rint(c / s)
        if np.all(np.abs(c - k * s) <= tol):
            # least-squares step over all points (exact grids: the same to rounding)
            nzk = k != 0
            s = float(np.sum(c[nzk] * k[nzk]) / np.sum(k[nzk] ** 2))
            return s, k.astype(np.int64)
    return None


def uv_lattice(uv, *, rtol=1e-10):
    """Rectangular lattice holding every uv point, or None.

    Parameters
    ----------
    uv : array-like, shape (nuv, 2)
        uv points (any unit).
    rtol : float
        Largest distance of a point from the lattice, relative to the longest
        baseline component.

    Returns
    -------
    tuple ``(sx, sy, m, n)`` or None
        Steps along u and v and the integer indices of each point
        (``uv[:, 0] = m sx``, ``uv[:, 1] = n sy``); None when no lattice with a
        step at least 1/8 of the smallest non-zero component fits.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.model.fourier import uv_lattice
    >>> sx, sy, m, n = uv_lattice([[0.38, 0.0], [-0.76, 0.38], [1.14, 1.14]])
    >>> round(sx, 2), m.tolist(), n.tolist()
    (0.38, [1, -2, 3], [0, 1, 3])
    >>> t = np.deg2rad(2.0)          # the same points turned by 2 degrees
    >>> rot = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    >>> uv_lattice(np.array([[0.38, 0.0], [-0.76, 0.38], [1.14, 1.14]]) @ rot.T) is None
    True
    """
    uv = np.asarray(uv, float)
    if uv.ndim != 2 or uv.shape[1] != 2 or len(uv) == 0:
        raise KpifsError(f"uv must have shape (nuv, 2), got {uv.shape}")
    scale = float(np.abs(uv).max()) or 1.0
    ax = _axis_lattice(uv[:, 0], scale, rtol)
    ay = _axis_lattice(uv[:, 1], scale, rtol)
    if ax is None or ay is None:
        return None
    return ax[0], ay[0], ax[1], ay[1]


def _digest(uv):
    return hashlib.sha1(np.ascontiguousarray(uv, float).tobytes()).hexdigest()


class FourierOperator:
    """Fourier transform at fixed uv points of image cut-outs of one shape.

    Made by `fourier_operator` (which caches them); `apply` is the only
    operation.

    Attributes
    ----------
    method : str
        ``'dense'``, ``'separable'`` or ``'nufft'``.
    n_uv : int
    shape : tuple
        ``(ny, nx)`` of the images.
    flops : float
        Floating-point operations per image of the matrix products (0 for nufft).
    nbytes : int
        Memory held by the operator.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.model.fourier import fourier_operator
    >>> uv = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])    # baselines (m)
    >>> op = fourier_operator(uv, 1.6e-6, 4.85e-8, (8, 8), method="dense")
    >>> re, im = op.apply(np.ones((2, 8, 8)))
    >>> op.method, re.shape
    ('dense', (2, 3))
    """

    def __init__(self, uv, wavelength, pixscale, shape, method, *, dtype=np.float64,
                 lattice=None, nufft_eps=1e-9):
        self.n_uv = len(uv)
        self.shape = (int(shape[0]), int(shape[1]))
        self.method = method
        self.dtype = np.dtype(dtype)
        ny, nx = self.shape
        k = 2 * np.pi * pixscale / wavelength       # phase per (metre of baseline x pixel)
        xs = np.arange(nx) - nx // 2
        ys = np.arange(ny) - ny // 2
        self.flops = 0.0
        if method == "dense":
            ax = k * np.outer(uv[:, 0], xs)
            ay = k * np.outer(uv[:, 1], ys)
            cx, sx = np.cos(ax)[:, None, :], np.sin(ax)[:, None, :]
            cy, sy = np.cos(ay)[:, :, None], np.sin(ay)[:, :, None]
            nuv = self.n_uv
            mat = np.empty((2 * nuv, ny, nx))
            # cos(a + b) and -sin(a + b) by the angle-addition formulas, in chunks
            for a in range(0, nuv, 32):
                b = min(nuv, a + 32)
                mat[a:b] = cy[a:b] * cx[a:b] - sy[a:b] * sx[a:b]
                mat[nuv + a:nuv + b] = -(sy[a:b] * cx[a:b] + cy[a:b] * sx[a:b])
            #: the real-stacked matrix (2 nuv, ny nx): cos rows, then -sin rows
            self.matrix = mat.reshape(2 * nuv, ny * nx).astype(self.dtype, copy=False)
            self.flops = 4.0 * nuv * ny * nx
            self.nbytes = self.matrix.nbytes
        elif method == "separable":
            sxm, sym, m, n = lattice
            # cos(m x) is even and sin(m x) odd in m: products for |m| only, the sign of
            # m applied in the gather (exact: a negation), half the x columns
            mu, mi = np.unique(np.abs(m), return_inverse=True)
            nu, ni = np.unique(n, return_inverse=True)
            ax = k * sxm * np.outer(mu, xs)                        # (Mx, nx)
            ay = k * sym * np.outer(nu, ys)                        # (Ny, ny)
            self._ex = np.ascontiguousarray(np.vstack([np.cos(ax), np.sin(ax)]).T,
                                            dtype=self.dtype)     # (nx, 2 Mx)
            self._ey = np.ascontiguousarray(np.vstack([np.cos(ay), np.sin(ay)]),
                                            dtype=self.dtype)     # (2 Ny, ny)
            Mx, Ny = len(mu), len(nu)
            # flat indices of the four blocks [cy; sy] x [A_c | A_s] at each uv point
            w = 2 * Mx
            self._i_cc = (ni * w + mi).astype(np.intp)
            self._i_cs = self._i_cc + Mx
            self._i_sc = self._i_cc + Ny * w
            self._i_ss = self._i_sc + Mx
            self._sign = np.where(m < 0, -1.0, 1.0).astype(self.dtype)
            self._flip = bool((m < 0).any())
            # contract the axis with fewer frequencies first (y: the uv points fill a
            # half plane, so N_y ~ M_x / 2 for a pupil model)
            fx_first = 4.0 * ny * nx * Mx + 8.0 * Ny * ny * Mx
            fy_first = 4.0 * Ny * ny * nx + 8.0 * Ny * nx * Mx
            self._y_first = fy_first <= fx_first
            self.flops = min(fx_first, fy_first)
            self.nbytes = self._ex.nbytes + self._ey.nbytes + 4 * self._i_cc.nbytes
        elif method == "nufft":
            # finufft type 2: c_j = sum_k f[k1, k2] exp(-i (k1 ty_j + k2 tx_j)), k1 along y
            self._ty = np.ascontiguousarray(k * uv[:, 1])
            self._tx = np.ascontiguousarray(k * uv[:, 0])
            if self.dtype == np.float32:
                self._ty, self._tx = self._ty.astype(np.float32), self._tx.astype(np.float32)
            self._eps = float(nufft_eps)
            self.nbytes = self._tx.nbytes * 2
        else:
            raise KpifsError(f"unknown Fourier method {method!r}: use one of {METHODS}")

    def __repr__(self):
        return (f"<FourierOperator {self.method}: {self.n_uv} uv points, "
                f"{self.shape[0]}x{self.shape[1]} pixels, {self.dtype.name}>")

    def apply(self, images):
        """``(Re V, Im V)`` of *images* (n, ny, nx), each of shape (n, nuv), float64."""
        images = np.asarray(images)
        n = images.shape[0]
        ny, nx = self.shape
        if images.shape[1:] != self.shape:
            raise KpifsError(f"images of shape {images.shape[1:]}, operator for {self.shape}")
        x = images.astype(self.dtype, copy=False)
        if self.method == "dense":
            ri = x.reshape(n, ny * nx) @ self.matrix.T
            return (ri[:, :self.n_uv].astype(float, copy=False),
                    ri[:, self.n_uv:].astype(float, copy=False))
        if self.method == "separable":
            # four blocks per image: [cy; sy] @ I @ [cx | sx], rows (cy, sy), columns (cx, sx)
            if self._y_first:
                p = (np.matmul(self._ey, x).reshape(-1, nx) @ self._ex).reshape(n, -1)
            else:
                p = np.matmul(self._ey, (x.reshape(n * ny, nx) @ self._ex).reshape(n, ny, -1))
                p = p.reshape(n, -1)
            # Re V = cc - sgn(m) ss, Im V = -(sgn(m) cs + sc)
            ss, cs = p[:, self._i_ss], p[:, self._i_cs]
            if self._flip:
                ss *= self._sign
                cs *= self._sign
            re = p[:, self._i_cc] - ss
            im = cs + p[:, self._i_sc]
            np.negative(im, out=im)
            return re.astype(float, copy=False), im.astype(float, copy=False)
        import finufft
        cdt = np.complex64 if self.dtype == np.float32 else np.complex128
        v = finufft.nufft2d2(self._ty, self._tx, x.astype(cdt), eps=self._eps, isign=-1)
        v = v.reshape(n, self.n_uv)
        return v.real.astype(float), v.imag.astype(float)


def _have_finufft():
    try:
        import finufft  # noqa: F401
    except ImportError:
        return False
    return True


def _choose(uv, shape, method):
    ny, nx = shape
    lattice = uv_lattice(uv) if method in ("auto", "separable") else None
    if method == "separable" and lattice is None:
        raise KpifsError("the uv points are not on a rectangular lattice: no separable "
                         "transform (use 'auto', 'nufft' or 'dense')")
    if method == "auto":
        if lattice is not None:
            Mx, Ny = len(np.unique(np.abs(lattice[2]))), len(np.unique(lattice[3]))
            sep = 4.0 * ny * nx * Mx + 8.0 * Ny * ny * Mx
            if sep < 0.5 * 4.0 * len(uv) * ny * nx:
                return "separable", lattice
        method = "nufft" if _have_finufft() else "dense"
    if method == "nufft" and not _have_finufft():
        raise KpifsError("the 'nufft' Fourier path needs finufft (pip install finufft)")
    return method, lattice


def fourier_operator(uv, wavelength, pixscale, shape, *, method="auto", dtype=np.float64,
                     nufft_eps=1e-9):
    """The (cached) `FourierOperator` of uv points for images of *shape*.

    Parameters
    ----------
    uv : ndarray, shape (nuv, 2)
        Baselines (m).
    wavelength : float
        Wavelength (m).
    pixscale : float
        Pixel size (radians).
    shape : tuple
        ``(ny, nx)`` of the images; pixel ``(ny // 2, nx // 2)`` is the origin.
    method : {'auto', 'separable', 'nufft', 'dense'}
        Path (see the module's description).
    dtype : {numpy.float64, numpy.float32}
        Precision of the products (float32: ~2x faster, relative error ~1e-6).
    nufft_eps : float
        Requested accuracy of the non-uniform FFT.

    Returns
    -------
    `FourierOperator`

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.model.fourier import fourier_operator
    >>> i, j = np.meshgrid(np.arange(-4, 5), np.arange(0, 5))
    >>> uv = 0.38 * np.column_stack([i.ravel(), j.ravel()])[5:]     # a half plane
    >>> op = fourier_operator(uv, 1.6e-6, 5e-8, (16, 16))
    >>> dense = fourier_operator(uv, 1.6e-6, 5e-8, (16, 16), method="dense")
    >>> op.method, dense.method
    ('separable', 'dense')
    >>> img = np.random.default_rng(0).random((2, 16, 16))
    >>> np.allclose(op.apply(img), dense.apply(img), rtol=0, atol=1e-10)
    True
    """
    if method not in METHODS:
        raise KpifsError(f"unknown Fourier method {method!r}: use one of {METHODS}")
    uv = np.asarray(uv, float)
    dtype = np.dtype(dtype)
    if dtype not in (np.float32, np.float64):
        raise KpifsError(f"Fourier precision must be float32 or float64, got {dtype}")
    shape = (int(shape[0]), int(shape[1]))
    key = (_digest(uv), round(float(wavelength) * 1e15), round(float(pixscale) * 1e18),
           shape, method, dtype.str, float(nufft_eps))
    with _cache_lock:
        op = _cache.get(key)
        if op is not None:
            _cache.move_to_end(key)
            return op
    path, lattice = _choose(uv, shape, method)
    op = FourierOperator(uv, float(wavelength), float(pixscale), shape, path, dtype=dtype,
                         lattice=lattice, nufft_eps=nufft_eps)
    with _cache_lock:
        _cache[key] = op
        total = sum(o.nbytes for o in _cache.values())
        while len(_cache) > 1 and (total > CACHE_BYTES or len(_cache) > CACHE_ENTRIES):
            _, old = _cache.popitem(last=False)
            total -= old.nbytes
    return op


def clear_cache():
    """Empty the module-level cache of Fourier operators.

    Examples
    --------
    >>> from kpifs.model.fourier import cache_info, clear_cache
    >>> clear_cache()
    >>> cache_info()[0]
    0
    """
    with _cache_lock:
        _cache.clear()


def cache_info():
    """``(entries, bytes)`` held by the cache of Fourier operators.

    Examples
    --------
    >>> from kpifs.model.fourier import cache_info, clear_cache
    >>> clear_cache(); cache_info()
    (0, 0)
    """
    with _cache_lock:
        return len(_cache), sum(o.nbytes for o in _cache.values())
