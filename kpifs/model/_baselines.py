"""Baselines of a discrete pupil and the kernel of its phase-transfer matrix (private).

The pieces of `kpifs.model.kernel.KernelModel` that work on plain arrays: the unique
half-plane uv points with their redundancies and baseline-mapping matrix, the
mapping for given uv points (files without BLM-MAT), and the kernel from the
SVD, kept in a small cache (models rebuilt for every file of an archive share
their SVD).
"""
import hashlib
import threading
from collections import OrderedDict

import numpy as np

from .._lazy import lazy_module

spatial = lazy_module("scipy.spatial")


def _uv_from_pupil(xy, trans, tol):
    """Unique half-plane uv points, redundancies and baseline-mapping matrix."""
    n = len(xy)
    j, k = np.triu_indices(n, 1)
    b = xy[j] - xy[k]
    # fold into the half plane v > 0, or v == 0 and u > 0
    flip = (b[:, 1] < -tol) | ((np.abs(b[:, 1]) <= tol) & (b[:, 0] < 0))
    b[flip] *= -1
    j2 = np.where(flip, k, j)
    k2 = np.where(flip, j, k)
    keys = np.round(b / tol).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    nuv = len(first)
    w = trans[j2] * trans[k2]
    red = np.bincount(inverse, weights=w, minlength=nuv)
    # mean baseline of each group (exact for a grid model, robust otherwise)
    uv = np.column_stack([np.bincount(inverse, weights=b[:, 0] * w, minlength=nuv),
                          np.bincount(inverse, weights=b[:, 1] * w, minlength=nuv)]) / red[:, None]
    A = np.zeros((nuv, n))
    np.add.at(A, (inverse, j2), w)
    np.add.at(A, (inverse, k2), -w)
    # order by baseline length, then angle: a stable, readable ordering
    order = np.lexsort((np.arctan2(uv[:, 1], uv[:, 0]), np.round(np.hypot(*uv.T) / tol)))
    return uv[order], red[order], A[order]


def _blm_for_uv(xy, trans, uv, tol):
    """The baseline-mapping matrix of sub-apertures *xy* for given uv points, in their order.

    Each pair ``(j, k)`` whose baseline ``r_j - r_k`` is a uv point adds
    ``+t_j t_k`` to column j and ``-t_j t_k`` to column k of that row (the
    pair is turned round when ``r_k - r_j`` is the uv point): any half plane
    works. Returns ``(A, missing)`` with *missing* the uv points no pair makes.
    """
    n = len(xy)
    j, k = np.triu_indices(n, 1)
    b = xy[j] - xy[k]
    tree = spatial.cKDTree(uv)   # only for files without BLM-MAT
    w = trans[j] * trans[k]
    A = np.zeros((len(uv), n))
    hit = np.zeros(len(uv), bool)
    for sign in (1.0, -1.0):
        dist, idx = tree.query(sign * b, distance_upper_bound=tol)
        ok = np.isfinite(dist)
        plus, minus = (j, k) if sign > 0 else (k, j)
        np.add.at(A, (idx[ok], plus[ok]), w[ok])
        np.add.at(A, (idx[ok], minus[ok]), -w[ok])
        hit[idx[ok]] = True
    return A, np.flatnonzero(~hit)


#: Kernels of the last few phase-transfer matrices (models rebuilt for every file
#: of an archive share their SVD).
_KERNEL_CACHE_SIZE = 8
_kernel_cache = OrderedDict()
_kernel_lock = threading.Lock()


def _kernel_from_tfm(tfm, rtol):
    key = (hashlib.sha1(np.ascontiguousarray(tfm).tobytes()).hexdigest(), tfm.shape, rtol)
    with _kernel_lock:
        hit = _kernel_cache.get(key)
        if hit is not None:
            _kernel_cache.move_to_end(key)
            return hit
    U, s, _ = np.linalg.svd(tfm, full_matrices=True)
    rank = int(np.sum(s > rtol * s[0])) if s.size else 0
    out = (U[:, rank:].T.copy(), rank, s)
    out[0].flags.writeable = False
    with _kernel_lock:
        _kernel_cache[key] = out
        while len(_kernel_cache) > _KERNEL_CACHE_SIZE:
            _kernel_cache.popitem(last=False)
    return out
