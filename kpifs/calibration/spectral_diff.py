"""Spectral-differential kernel phases: what varies like a static aberration across the
channels is projected out, kernel phase by kernel phase (issue 39).

Each kernel phase is a fixed combination of pupil baselines in metres. A static
aberration is the same optical path at every wavelength, so its kernel-phase
residual changes smoothly with the wavelength: its first-order phase goes as
``1/lambda``, the residual (second order) roughly as ``1/lambda**2``. A companion
fixed on the sky adds ``K sin(2 pi b.x / lambda)``, which oscillates across the
band at a rate set by ``b.|x|``. Projecting out of every kernel phase a few
profiles along the channels (`nuisance_profiles`: low-order polynomials in
``1/lambda``, the leading channel profiles of the imaged static residual
`~kpifs.simulation.aberrations.static_residual_rows`, or both) removes the
static residual and keeps most of a companion beyond an inner separation, with
no calibrator (Chaushev et al. 2023, JATIS 9, 028004, calibrated CHARIS
kernel phases this way for spectral lines).

The step records the profiles on the data (``kpd.spectral``, KPFITS extension
``KP-SDK``); it changes no kernel phase. Detection (`kpifs.detect.sdk`) applies
the projection to the data, their covariance and the companion's signatures
alike (DESIGN.md section 8: a nuisance projected out of data and signatures),
searches the ``q - m`` channel combinations that are left, whitened in that
kept space, and reports what the projection keeps of a companion
(`retained_fraction`, `inner_separation`).
"""
import logging

import numpy as np
from astropy import units as u

from ..covariance import empirical_covariance
from ..data import KernelPhaseData
from ..exceptions import KpifsError
from .calibrate import block_rows, covariance_rows

__all__ = ["spectral_differential", "frames_autocorrelation", "nuisance_profiles",
           "kept_combinations", "retained_fraction", "retained_by_separation", "inner_separation",
           "SDK_BASES", "SDK_ORDER"]

log = logging.getLogger(__name__)

#: The nuisance profiles along the channels: polynomials in ``1/lambda`` ('poly'), the
#: leading channel profiles of the imaged static residual ('static'), or both.
SDK_BASES = ("poly", "static", "both")
#: Degree of the polynomials in ``1/lambda`` (0 to this: the constant, the first-order
#: phase of a fixed path, and the second-order residual).
SDK_ORDER = 2
#: Channel profiles of the static residual kept by the 'static' basis.
SDK_STATIC_PROFILES = 3
#: The inner separation: where the projection keeps this fraction of a companion's
#: squared signal (median over position angles).
SDK_LEVEL = 0.5


def _poly_profiles(wavelengths, order):
    x = 1.0 / np.asarray(wavelengths, float)
    x = 2 * (x - x.min()) / max(np.ptp(x), 1e-300) - 1
    return np.polynomial.legendre.legvander(x, order)


def _static_profiles(rows, n):
    rows = np.asarray(rows, float)
    q = rows.shape[1]
    mat = rows.transpose(1, 0, 2).reshape(q, -1)
    u_, _, _ = np.linalg.svd(mat, full_matrices=False)
    u_ = u_[:, :n]
    # each profile's sign fixed (its largest entry positive), not left to the SVD
    big = u_[np.argmax(np.abs(u_), axis=0), np.arange(u_.shape[1])]
    return u_ * np.where(big < 0, -1.0, 1.0)


def nuisance_profiles(kpd, *, basis="poly", order=SDK_ORDER, n_static=SDK_STATIC_PROFILES,
                      static_rows=None):
    """Channel profiles ``T`` (q, m) whose span is removed from every kernel phase.

    Parameters
    ----------
    kpd : `~kpifs.KernelPhaseData`
    basis : {'poly', 'static', 'both'}
        Polynomials in ``1/lambda`` of degree 0 to *order*; the *n_static* leading
        channel profiles of the static residual imaged through the data's pupil
        (*static_rows*, `~kpifs.simulation.aberrations.static_residual_rows`; shared by
        every kernel phase); or both.
    order, n_static : int
    static_rows : ndarray (n, q, p), optional
        The imaged static residual (needed by 'static' and 'both').

    Returns
    -------
    ndarray (q, m)
        Orthonormal columns (in the plain channel metric).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.calibration.spectral_diff import nuisance_profiles
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> kpd = KernelPhaseData(np.zeros((1, 8, km.n_kp)), np.linspace(1.2, 2.3, 8) * u.um,
    ...                       16.2 * u.mas, km)
    >>> t = nuisance_profiles(kpd)
    >>> t.shape, bool(np.allclose(t.T @ t, np.eye(3)))
    ((8, 3), True)
    """
    if basis not in SDK_BASES:
        raise KpifsError(f"spectral-differential basis must be one of {SDK_BASES}, got "
                         f"{basis!r}")
    lam = kpd.wavelengths.to_value(u.um)
    parts = []
    if basis in ("poly", "both"):
        parts.append(_poly_profiles(lam, int(order)))
    if basis in ("static", "both"):
        if static_rows is None:
            raise KpifsError(f"the spectral-differential basis {basis!r} needs the imaged "
                             f"static residual (static_rows)")
        parts.append(_static_profiles(static_rows, int(n_static)))
    t = np.concatenate(parts, axis=1)
    # orthonormal by Gram-Schmidt in the columns' order (QR, signs from R's diagonal),
    # dropping a column its predecessors already span: an SVD of columns already
    # orthonormal (the static basis) returns any rotation of their span, which moved
    # with the last bits of the imaged residual from run to run
    qm, r = np.linalg.qr(t)
    d = np.diag(r)
    keep = np.abs(d) > 1e-8 * np.abs(d).max()
    return (qm * np.where(d < 0, -1.0, 1.0))[:, keep]


def kept_combinations(profiles, scale):
    """The channel combinations searched: ``V`` (q, q - m) with orthonormal columns
    orthogonal to the nuisance *profiles* (q, m) once each channel is divided by its
    noise *scale* (q,). A combination's kernel phases are ``sum_c V[c, k] kp_c /
    scale_c``: free of anything in the profiles' span, and, for channels whose noise
    differs by a scale only, independent from one combination to the next.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.calibration.spectral_diff import kept_combinations
    >>> t = np.ones((5, 1)) / np.sqrt(5)                  # the mean over the channels
    >>> v = kept_combinations(t, np.ones(5))
    >>> v.shape, bool(np.allclose(v.T @ t, 0))
    ((5, 4), True)
    """
    t = np.asarray(profiles, float) / np.asarray(scale, float)[:, None]
    q, m = t.shape
    full, _ = np.linalg.qr(np.column_stack([t, np.eye(q)]))
    return full[:, m:q]


def retained_fraction(kernel_model, wavelengths, positions, mixing, *, spectrum=None,
                      scale=None):
    """Fraction of a companion's squared signal the projection keeps, per position.

    ``||sum_c V[c, k] a_c K sin(theta_c) / scale_c||^2`` summed over the kept
    combinations, over ``sum_c ||a_c K sin(theta_c) / scale_c||^2`` (white noise
    in each channel, at the channel's *scale*).

    Parameters
    ----------
    kernel_model : `~kpifs.KernelModel`
    wavelengths : `~astropy.units.Quantity` (q,)
    positions : array-like (n, 2)
        Detector offsets (mas).
    mixing : ndarray (q, k)
        The kept combinations (`kept_combinations`).
    spectrum : array-like (q,), optional
        The companion's contrast shape (flat by default).
    scale : array-like (q,), optional
        The channels' noise scales (ones by default).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.calibration.spectral_diff import kept_combinations, retained_fraction
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> wl = np.linspace(1.16, 2.37, 22) * u.um
    >>> v = kept_combinations(np.ones((22, 1)) / np.sqrt(22), np.ones(22))
    >>> np.round(retained_fraction(km, wl, [[10.0, 0.0], [300.0, 0.0]], v), 2)
    array([0.29, 0.86])
    """
    lam = np.atleast_1d(u.Quantity(wavelengths, u.um).to_value(u.m))
    q = len(lam)
    a = np.ones(q) if spectrum is None else np.asarray(spectrum, float)
    s = np.ones(q) if scale is None else np.asarray(scale, float)
    pos = np.atleast_2d(np.asarray(positions, float)) * np.pi / 180 / 3600e3
    uv = kernel_model.uv.value
    theta = 2 * np.pi * (pos @ uv.T)                                  # (n, nuv) x lambda
    sig = np.sin(theta[None] / lam[:, None, None]) @ kernel_model.kernel.T   # (q, n, p)
    sig *= (a / s)[:, None, None]
    kept = np.einsum("ck,cnp->knp", mixing, sig)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sum(kept ** 2, axis=(0, 2)) / np.sum(sig ** 2, axis=(0, 2))


def inner_separation(separations, fraction, *, level=SDK_LEVEL):
    """The separation (mas) from which the median *fraction* kept over each separation's
    position angles stays at or above *level*; NaN when it never does.

    Examples
    --------
    >>> from kpifs.calibration.spectral_diff import inner_separation
    >>> inner_separation([50, 50, 100, 100, 200], [0.1, 0.2, 0.55, 0.45, 0.9])
    100.0
    """
    sep, frac = np.asarray(separations, float), np.asarray(fraction, float)
    rings = np.unique(sep)
    med = np.array([np.nanmedian(frac[sep == r]) for r in rings])
    low = np.flatnonzero(~(med >= level))
    if not low.size:
        return float(rings[0])
    if low[-1] == len(rings) - 1:
        return float("nan")
    return float(rings[low[-1] + 1])


def retained_by_separation(kernel_model, wavelengths, grid, combinations, *, spectrum=None,
                           scale=None, angles=16):
    """What the projection keeps of a companion on *grid*, ring by ring: ``{'retained':
    [[sep, median fraction], ...], 'inner_separation': sep}`` (`retained_fraction` at
    *angles* position angles per ring one grid step wide, `inner_separation`).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.calibration.spectral_diff import kept_combinations, retained_by_separation
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> wl = np.linspace(1.16, 2.37, 22) * u.um
    >>> v = kept_combinations(np.ones((22, 1)) / np.sqrt(22), np.ones(22))
    >>> out = retained_by_separation(km, wl, DetectionGrid.from_separation(150, 30), v)
    >>> out["inner_separation"], out["retained"][-1]
    (120.0, [150.0, 0.6419])
    """
    sel = grid.valid
    seps = np.unique(np.round(grid.sep[sel], 6))
    step = float(max(abs(grid.step[0]), abs(grid.step[1])))
    rings = np.arange(seps.min(), seps.max() + step / 2, step)
    ang = np.arange(angles) * np.pi / angles
    pos = np.stack([np.outer(rings, np.cos(ang)).ravel(),
                    np.outer(rings, np.sin(ang)).ravel()], axis=1)
    frac = retained_fraction(kernel_model, wavelengths, pos, combinations, spectrum=spectrum,
                             scale=scale)
    sep = np.repeat(rings, len(ang))
    med = [float(np.median(frac[sep == r])) for r in rings]
    return {"retained": [[round(float(r), 1), round(m, 4)] for r, m in zip(rings, med)],
            "inner_separation": inner_separation(sep, frac)}


def frames_autocorrelation(rows, blocks):
    """Integrated autocorrelation time of a sequence's frames, by batch means: the
    variance of its time blocks' means against its frames' over their number
    (``tr(B^T B) / tr(R^T R)`` of its block and covariance rows,
    `~kpifs.calibration.calibrate.block_rows` and
    `~kpifs.calibration.calibrate.covariance_rows`), at least 1. The mean of frames
    that drift together varies ``tau`` times more than independent frames say.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.calibration.calibrate import block_rows, covariance_rows
    >>> from kpifs.calibration.spectral_diff import frames_autocorrelation
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> rng = np.random.default_rng(0)
    >>> walk = np.cumsum(rng.normal(0, 1, (64, 1, km.n_kp)), axis=0)   # a drift
    >>> t = KernelPhaseData(walk, [1.6] * u.um, 10 * u.mas, km)
    >>> bool(frames_autocorrelation(covariance_rows(t), block_rows(t, [])) > 3)
    True
    """
    if rows is None or blocks is None:
        return 1.0
    var = float(np.sum(np.square(rows)))
    return float(max(1.0, np.sum(np.square(blocks)) / var)) if var > 0 else 1.0


def spectral_differential(target, calibrated=None, *, basis="poly", order=SDK_ORDER,
                          n_static=SDK_STATIC_PROFILES, static_rows=None, shrinkage="auto"):
    """A product searched by the channel combinations free of the static residual's
    profiles (``kpifs extract --spectral-differential``).

    With *calibrated* (the target calibrated by `~kpifs.calibration.calibrate.calibrate`,
    or an angular-differential product) the profiles are recorded on it (the
    projection then also protects against the calibrator's own static
    difference; *basis*, *order*, *n_static* and *static_rows*: `nuisance_profiles`);
    without, the target's frames make the product: their mean, its covariance (the
    frames' per channel, over their number, times their autocorrelation time
    `frames_autocorrelation`), and the frames' deviations (likewise) and time
    blocks as covariance and block rows
    (`~kpifs.calibration.calibrate.covariance_rows`,
    `~kpifs.calibration.calibrate.block_rows`), which carry the channels'
    correlations to the search's null and limits. Refused for single-channel data
    and for fewer channels than the profiles plus one.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.calibration.spectral_diff import spectral_differential
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> rng = np.random.default_rng(0)
    >>> t = KernelPhaseData(rng.normal(0, 0.1, (400, 6, km.n_kp)),
    ...                     np.linspace(1.2, 2.3, 6) * u.um, 16.2 * u.mas, km)
    >>> sdk = spectral_differential(t)
    >>> sdk.kp.shape, sdk.spectral["profiles"].shape, sdk.meta["spectral_differential"]["m"]
    ((1, 6, 37), (6, 3), 3)
    """
    name = target.meta.get("source", "target")
    base = target if calibrated is None else calibrated
    q = base.n_wave
    if q < 2:
        raise KpifsError(f"{name}: --spectral-differential needs several channels (an IFS "
                         f"cube); these data have one channel")
    prof = nuisance_profiles(base, basis=basis, order=order, n_static=n_static,
                             static_rows=static_rows)
    m = prof.shape[1]
    if q - m < 1:
        raise KpifsError(f"{name}: --spectral-differential removes {m} profile(s) along the "
                         f"channels and leaves nothing of {q} channel(s): use a lower order "
                         f"or more channels")
    if calibrated is not None:
        out = calibrated
    else:
        if target.n_frame < 2:
            raise KpifsError(f"{name}: --spectral-differential without a calibrator needs "
                             f"several frames (their scatter is the noise), got 1")
        rows, blocks = covariance_rows(target), block_rows(target, [])
        tau = frames_autocorrelation(rows, blocks)
        meta = dict(target.meta)
        meta.update(calibrated=False, n_target_frames=target.n_frame, calibrators=[],
                    error_model={"model": "frames", "tau": tau})
        cov = empirical_covariance(target.kp, shrinkage=shrinkage, debias=True) \
            * (tau / target.n_frame)
        detpa = None
        if target.detpa is not None and np.all(np.isfinite(target.detpa)):
            a = np.deg2rad(target.detpa)
            detpa = [float(np.rad2deg(np.arctan2(np.sin(a).mean(), np.cos(a).mean())))]
            meta["detpa_frames"] = [float(v) for v in target.detpa]
        # the frames' deviations and time blocks carry the channels' correlations (a
        # static or drifting aberration is shared by every channel, and most of it
        # cancels in a combination, not all) to the search's null and limits
        out = KernelPhaseData(target.kp.mean(axis=0)[None], target.wavelengths,
                              target.pixscale, target.kernel_model, window=target.window,
                              covariance=cov, covariance_rows=rows * np.sqrt(tau),
                              block_rows=blocks, header=target.header,
                              detpa=detpa, bandwidth=target.bandwidth, meta=meta)
    out.spectral = {"profiles": prof, "basis": basis, "order": int(order)}
    out.meta["spectral_differential"] = {"basis": basis, "order": int(order), "m": int(m),
                                         "channels": int(q)}
    out.header["SDKBASIS"] = (basis, "spectral-differential profiles")
    out.header["SDKNPROF"] = (int(m), "profiles projected out")
    log.info("%s: spectral-differential product: %d profile(s) (%s) out of %d channels",
             name, m, basis, q)
    return out
