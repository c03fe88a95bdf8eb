"""Which channels the detector samples too coarsely for their uv points.

A pixelated image's Fourier transform is the true one plus copies shifted by
multiples of ``1 / p`` (``p`` the pixel scale). The true transform, the optical
transfer function, reaches ``D / lam`` (``D`` the pupil's extent), so a uv
point ``b / lam`` is free of the copies only while it lies farther than ``D /
lam`` from every shifted origin ``(k, l) / p``. Dropping uv points beyond the
Nyquist limit ``1 / (2 p)`` (`kpifs.model.kernel.nyquist_usable`) is not enough when
``p > lam / (2 D)``: the points between ``lam / p - D`` and the Nyquist limit
then carry a piece of the star's aliased transfer function, which the binary
model does not contain. A companion's kernel phases there are biased (its
fitted contrast in those channels is not to be trusted), while the star's
aliased part varies with the aberrations like any residual and is measured by
the frames' covariance (the search stays honest).

`aliased_uv` marks those points, `aliased_channels` gives each channel's
share of them; detection flags the channels where the share is not zero
(`kpifs.detect.detect`'s ``aliased`` option).

Channels at different pixel scales (JWST filters as channels) sample different
uv points. `nested_kernel` gives them one kernel whose first rows are each
channel's own (DESIGN.md section 6: channels whose kernels differ).
"""
import numpy as np
from astropy import units as u

from .._utils import to_quantity
from ..exceptions import KpifsError

__all__ = ["aliased_uv", "aliased_channels", "pupil_extent", "nested_kernel",
           "channel_uv_mask", "unmeasured", "measured_rows"]

MAS = np.pi / 180 / 3600 / 1000


def pupil_extent(pupil):
    """The extent ``D`` of a discrete pupil: its longest baseline plus one cell.

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs import make_pupil
    >>> from kpifs.model.sampling import pupil_extent
    >>> round(float(pupil_extent(make_pupil("subaru", step=0.5 * u.m)).value), 1)
    8.6
    """
    xy = np.asarray(u.Quantity(pupil.xy, u.m).value, float)
    d = _max_distance(xy)
    step = 0.0 if pupil.step is None else float(pupil.step.to_value(u.m))
    return (d + step) * u.m


def _max_distance(xy, chunk=256):
    """Longest distance between points *xy* (n, 2): ``scipy.spatial.distance.pdist(xy).max()``
    (the same sums), without importing scipy.spatial (0.3 s of start-up for one call)."""
    best = 0.0
    for a in range(0, len(xy), chunk):
        d = xy[a:a + chunk, None, :] - xy[None, :, :]
        best = max(best, float(np.max(d[..., 0] ** 2 + d[..., 1] ** 2)))
    return float(np.sqrt(best))


def aliased_uv(uv, wavelengths, pixscale, *, diameter):
    """Which uv points see a copy of the transfer function at each wavelength.

    Parameters
    ----------
    uv : `~astropy.units.Quantity`, shape (nuv, 2)
        Baselines (m).
    wavelengths : `~astropy.units.Quantity`, shape (nwave,)
    pixscale : `~astropy.units.Quantity`
    diameter : `~astropy.units.Quantity`
        Extent of the pupil (the transfer function's reach times the wavelength).

    Returns
    -------
    ndarray of bool, shape (nwave, nuv)

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs.model.sampling import aliased_uv
    >>> aliased_uv([[7.0, 0.0], [3.0, 0.0]] * u.m, [1.16, 1.6] * u.um, 16.2 * u.mas,
    ...            diameter=8.2 * u.m)
    array([[ True, False],
           [False, False]])
    """
    f = to_quantity(uv, u.m, name="uv").value
    wl = np.atleast_1d(to_quantity(wavelengths, u.m, name="wavelengths").value)
    g = 1.0 / (to_quantity(pixscale, u.mas, name="pixel scale").value * MAS)
    d = to_quantity(diameter, u.m, name="diameter").value
    out = np.zeros((len(wl), len(f)), bool)
    for i, lam in enumerate(wl):
        fx, fy = f[:, 0] / lam, f[:, 1] / lam
        for k in (-1, 0, 1):
            for m in (-1, 0, 1):
                if k or m:
                    out[i] |= np.hypot(fx - k * g, fy - m * g) < d / lam
    return out


def aliased_channels(kernel_model, wavelengths, pixscale, *, uv_mask=None):
    """Fraction of the model's uv points, per channel, that the sampling aliases.

    *uv_mask* (nwave, nuv), when the channels measure different uv points
    (`channel_uv_mask`), restricts each channel to its own.

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.model.sampling import aliased_channels
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=0.5 * u.m))
    >>> frac = aliased_channels(km, [1.16, 1.6] * u.um, 16.2 * u.mas)
    >>> bool(frac[0] > 0), float(frac[1])
    (True, 0.0)
    """
    if kernel_model.pupil is None or len(kernel_model.pupil.xy) < 2:
        return np.zeros(len(np.atleast_1d(wavelengths)))
    hit = aliased_uv(kernel_model.uv, wavelengths, pixscale,
                     diameter=pupil_extent(kernel_model.pupil))
    if uv_mask is None:
        return hit.mean(axis=1)
    mask = np.asarray(uv_mask, bool)
    return (hit & mask).sum(axis=1) / np.maximum(mask.sum(axis=1), 1)


def nested_kernel(kernel_model, usable):
    """One kernel for channels that sample nested sets of uv points.

    A channel samples the uv points within its limit ``lam / (2 p)``
    (`~kpifs.model.kernel.nyquist_usable`), so the channels' sets are nested. The
    kernel of a smaller set, extended by zeros, lies in the kernel of a larger
    one. The rows returned are the smallest set's kernel, then the rows that
    complete it to the next set's kernel, and so on: channel ``c``'s kernel
    phases are the first ``counts[c]`` rows, which touch only its uv points.
    Every channel keeps all the kernel phases its own sampling allows.

    Parameters
    ----------
    kernel_model : `~kpifs.model.kernel.KernelModel`
    usable : array-like of bool, shape (nchan, nuv)
        The uv points each channel samples.

    Returns
    -------
    model : `~kpifs.model.kernel.KernelModel`
        The model on the uv points some channel samples, with the nested kernel.
    counts : ndarray of int, shape (nchan,)
        Each channel's number of kernel phases (0 where it has none).

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.model.kernel import nyquist_usable
    >>> from kpifs.model.sampling import nested_kernel
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> usable = nyquist_usable(km.uv, [1.2, 2.2] * u.um, 20 * u.mas)
    >>> model, counts = nested_kernel(km, usable)
    >>> int(counts[0]) < int(counts[1]) == km.n_kp
    True
    """
    usable = np.atleast_2d(np.asarray(usable, bool))
    if usable.shape[1:] != (kernel_model.n_uv,):
        raise KpifsError(f"uv selection has shape {usable.shape}, expected (nchan, "
                         f"{kernel_model.n_uv})")
    union = usable.any(axis=0)
    model = kernel_model.subset(union)
    masks = usable[:, union]
    counts = np.zeros(len(masks), int)
    rows = np.zeros((0, model.n_uv))
    done = np.zeros(model.n_uv, bool)
    for i in np.argsort(masks.sum(axis=1), kind="stable"):
        m = masks[i]
        if np.any(done & ~m):
            raise KpifsError("the channels' uv points are not nested: no kernel whose first "
                             "rows are each channel's own")
        if m.sum() >= 2 and (m & ~done).any():
            own = model.subset(m).kernel
            full = np.zeros((len(own), model.n_uv))
            full[:, m] = own
            # the part of this set's kernel not yet spanned: singular values 1 (new) or 0
            rest = full - (full @ rows.T) @ rows
            if len(rest):
                _, s, vt = np.linalg.svd(rest, full_matrices=False)
                rows = np.vstack([rows, vt[s > 0.5]])
            done = m
        counts[i] = len(rows)
    out = type(model)(model.pupil, model.uv, model.redundancy, model.blm, kernel=rows,
                      rtol=model.meta.get("rtol", 1e-9), meta=model.meta)
    out.meta["nested_counts"] = counts.tolist()
    return out, counts


def channel_uv_mask(kernel_model, counts):
    """The uv points each channel's kernel phases touch (the first *counts* rows).

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.model.sampling import channel_uv_mask
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> channel_uv_mask(km, [km.n_kp]).shape == (1, km.n_uv)
    True
    """
    k = np.abs(kernel_model.kernel)
    tol = 1e-9 * max(float(k.max(initial=0.0)), 1e-300)
    return np.array([np.any(k[:int(n)] > tol, axis=0) for n in np.atleast_1d(counts)])


def unmeasured(counts, n_kp):
    """``(nwave, n_kp)``: True where a channel measuring its first *counts* kernel phases
    has none.

    Examples
    --------
    >>> from kpifs.model.sampling import unmeasured
    >>> unmeasured([1, 2], 2).tolist()
    [[False, True], [False, False]]
    """
    return np.arange(n_kp)[None, :] >= np.asarray(counts, int)[:, None]


def measured_rows(kp, kernel_model, dropped=()):
    """Kernel phases ``(nframe, nwave, nkp)`` of a nested model (`nested_kernel`) with each
    channel's rows beyond its own set to zero, and the counts (None for other models).

    *dropped* are channels left out of *kp* since the model was made (dead channels).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.model.kernel import nyquist_usable
    >>> from kpifs.model.sampling import measured_rows, nested_kernel
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> model, counts = nested_kernel(km, nyquist_usable(km.uv, [1.2, 2.2] * u.um, 20 * u.mas))
    >>> kp, own = measured_rows(np.ones((1, 2, model.n_kp)), model)
    >>> own == counts.tolist(), int(kp[0, 0].sum()) == int(counts[0])
    (True, True)
    """
    counts = kernel_model.meta.get("nested_counts")
    if counts is None:
        return kp, None
    counts = np.delete(np.asarray(counts, int), list(dropped))
    if len(counts) != kp.shape[1] or np.all(counts == kp.shape[2]):
        return kp, None
    return np.where(unmeasured(counts, kp.shape[2]), 0.0, kp), counts.tolist()
