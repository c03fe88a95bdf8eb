"""Noise for tests that holds on any machine.

The kernel's rows are an orthonormal basis of the phase-transfer matrix's left null
space, returned by the SVD: which basis depends on the linear-algebra library and the
processor (OpenBLAS picks its kernels by CPU). White noise drawn directly in the kernel
basis is therefore a different realisation on each machine. Drawn on the uv points and
projected by the kernel, it has the same law (white, unit variance: ``K K^T = I``) and
the same realisation wherever the tests run, since every statistic is a function of the
projector ``K^T K``.
"""


def kernel_noise(kernel_model, rng, shape):
    """Standard normal kernel phases of *shape* (``(..., n_kp)``), drawn on the uv points.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1.0 * u.m))
    >>> kernel_noise(km, np.random.default_rng(0), (4, km.n_kp)).shape == (4, km.n_kp)
    True
    """
    k = kernel_model.kernel
    if shape[-1] != k.shape[0]:
        raise ValueError(f"last axis {shape[-1]}: the model has {k.shape[0]} kernel phases")
    return rng.normal(size=tuple(shape[:-1]) + (k.shape[1],)) @ k.T
