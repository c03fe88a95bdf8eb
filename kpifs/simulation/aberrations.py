"""The kernel-phase residual of static aberrations that no calibrator removed.

Kernel phases cancel a wavefront error only to first order, and only for the
discrete model: the real pupil differs from its cells, and the phase of the
transfer function is not linear in the wavefront. A static aberration thus
leaves kernel phases, and they are not noise of the frames: their scatter
does not show it, and the map sees it as companions at one to three
resolution elements. With no calibrator (``allow_uncalibrated``) it is the
largest error term; measured on 6-frame single-channel simulations with 30 nm
of static aberration, it gave a candidate at P_FA 1e-2 in 5 of 20
companion-free data sets.

Its *shape* comes from physics: `static_residual_rows` images the star
through the telescope's own pupil with random wavefronts (an AO residual's
spectrum, `kpifs.simulation.simulate.phase_screens`), extracts kernel phases with the
data's model, window and pixel scale, and keeps their scatter as covariance
rows, correlated across channels as one wavefront seen at every wavelength
is. A pupil that is not built in (a KPFITS of another telescope) is imaged as
the annulus its model's cells tile: the cells themselves would miss the real
pupil's edges, which make much of the residual (measured on the stand-in
below: 7 of 20 companion-free sets with a candidate imaged through the cells,
2 of 20 through the annulus, 0 of 20 through the true pupil).

Its *amplitude* is the data's: `fit_static_amplitude` is the maximum
likelihood of the data under the frames' covariance plus that term, fitted on
the term's leading modes only (`leading_static_rows`, DESIGN.md §8). The
rows of 200 screens span every direction of 100 kernel phases, and an
amplitude free in all of them explains a companion away (a 5.4 % companion
at 330 mas in 6 single-channel frames of 105 kernel phases, the V410 Tau-like
case of `tests/test_static_bright.py`: the term at 1e7 times the frames'
variance and no candidate). In the leading modes, a few per cent of the
data's dimension, a companion can only lift the amplitude by what it shares
with them; the whole term at that amplitude then leaves the rest of it to the
search (the same companion: found at statistic 1e4 for a threshold of 19;
companion-free stand-ins: a candidate at P_FA 1e-2 in 1 of 20).

Detection adds the term to the covariance before whitening (`static_term`), so the
search, its null, the limits and the fits' errors all carry it. It does so for
single-channel data: with several channels the residual, one wavefront seen at
every wavelength, correlates them, which a per-channel term does not model
(measured on 22-channel CHARIS simulations with 30 nm of static aberration
and no calibrator: a candidate in 3 of 6 companion-free sets with the term, 2
of 6 without, at P_FA 1e-2).
"""
import logging

import numpy as np
from astropy import units as u

from .._lazy import lazy_module
from .._utils import to_quantity
from ..model.apertures import MASKS, TELESCOPES
from ..covariance import whiten
from ..exceptions import KpifsError
from ..extraction.extract import extract_kernel_phases
from ..model.pupil import pupil_image
from .simulate import _mft_matrices, phase_screens
from ..model.window import ExtractionWindow

optimize = lazy_module("scipy.optimize")

__all__ = ["static_residual_rows", "leading_static_rows", "fit_static_amplitude",
           "fit_static_amplitudes", "static_term"]

log = logging.getLogger(__name__)

#: Screens imaged for the term's shape.
STATIC_SCREENS = 200
#: Their rms, as a fraction of the shortest wavelength (0.16 rad there: small
#: aberrations, where the residual's shape no longer depends on its level).
STATIC_RMS = 1 / 40
#: Pupil samples across the pupil for the imaging.
STATIC_NPUP = 64
#: A pupil that is not built in is imaged as the annulus its model's cells tile
#: (`_envelope`) when they cover at least this share of it (a filled pupil: the real
#: pupil's edges, which the cells leave out, make much of the residual); else (a
#: mask's holes) as the cells themselves.
ENVELOPE_FILL = 0.5
#: Share of the (whitened) term's variance its leading modes keep (`leading_static_rows`).
STATIC_VARIANCE = 0.999
#: Largest rank of the term, as a fraction of the data's dimension.
STATIC_MAX_RANK = 0.25


def _pupil_name(kernel_model, telescope=None):
    """A pupil the simulator can image: the model's own telescope when built in."""
    for name in (telescope, getattr(kernel_model.pupil, "name", None)):
        key = str(name or "").lower().strip()
        if key in TELESCOPES or key in MASKS:
            return key
    return None


def _cells(kernel_model):
    """The model's cell centres (m), transmissions and step (m)."""
    pupil = kernel_model.pupil
    xy = np.asarray(u.Quantity(pupil.xy, u.m).value, float)
    t = np.asarray(pupil.transmission, float)
    step = float(pupil.step.to_value(u.m)) if pupil.step is not None else \
        float(np.min(np.hypot(*(xy[1:] - xy[0]).T))) if len(xy) > 1 else 1.0
    return xy, t, step


def _envelope(kernel_model):
    """The annulus ``(r_in, r_out)`` (m) a filled model's cells tile, or None for a sparse one.

    A cell of transmission ``t`` on the edge has the edge ``(t - 1/2)`` steps beyond its
    centre (a full cell: half a step; a grey one: where its covered part ends).
    """
    xy, t, step = _cells(kernel_model)
    r = np.hypot(*xy.T)
    r_out = float(np.max(r + step * (t - 0.5)))
    r_in = max(0.0, float(np.min(r - step * (t - 0.5))))
    area = np.pi * (r_out ** 2 - r_in ** 2)
    # a mask's few holes cover a small part of their annulus: those are the pupil
    if area <= 0 or np.sum(t) * step ** 2 < ENVELOPE_FILL * area:
        return None
    return r_in, r_out


def _model_field(kernel_model, npup):
    """A picture of a pupil that is not built in, from its model (`ENVELOPE_FILL`)."""
    xy, t, step = _cells(kernel_model)
    env = _envelope(kernel_model)
    half = np.abs(xy).max() + step / 2 if env is None else env[1]
    dx = 2 * half / npup
    g = (np.arange(npup) - (npup - 1) / 2) * dx
    if env is not None:
        rr = np.hypot(*np.meshgrid(g, g))
        return ((rr <= env[1]) & (rr >= env[0])).astype(float), dx
    img = np.zeros((npup, npup))
    for (x, y), tt in zip(xy, t):
        img[np.ix_(np.abs(g - y) <= step / 2, np.abs(g - x) <= step / 2)] = tt
    return img, dx


def static_residual_rows(kernel_model, wavelengths, pixscale, *, window=None, telescope=None,
                         n_screens=STATIC_SCREENS, rms=None, seed=0, cutoff=None):
    """Covariance rows ``R`` (n, q, p) of the kernel phases a static aberration leaves.

    ``R^T R`` is the covariance, across all channels, of the kernel phases of a
    star imaged through the pupil with random wavefronts of *rms* (default
    `STATIC_RMS` of the shortest wavelength), extracted like the data.

    Parameters
    ----------
    kernel_model : `~kpifs.KernelModel`
    wavelengths : `~astropy.units.Quantity` (q,)
    pixscale : `~astropy.units.Quantity`
    window : `~kpifs.ExtractionWindow`, optional
        The data's window (default: the default window of a 64-pixel image).
    telescope : str, optional
        The pupil to image (default: the model's, when it is a built-in one;
        else the model's cells, a coarser picture of the real pupil).
    n_screens : int
    rms : `~astropy.units.Quantity`, optional
    seed : int or `numpy.random.Generator`
    cutoff : float, optional
        The screens' spatial spectrum: frequencies (cycles/m) below it damped as by
        an AO system (`~kpifs.simulation.simulate.phase_screens`; its default when
        None); a tiny value leaves the low orders undamped (an uncorrected, low-order
        aberration).

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.simulation.aberrations import static_residual_rows
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1.0 * u.m))
    >>> rows = static_residual_rows(km, [2.12] * u.um, 10 * u.mas, n_screens=20)
    >>> rows.shape == (20, 1, km.n_kp), bool(abs(rows).max() > 0)
    (True, True)
    """
    wl = np.atleast_1d(to_quantity(wavelengths, u.m, name="wavelengths").value)
    ps = to_quantity(pixscale, u.mas, name="pixel scale")
    if n_screens < 10:
        raise KpifsError(f"static residual: {n_screens} screens are too few (at least 10)")
    size = 64 if window is None else int(window.size)
    if window is None:
        window = ExtractionWindow.default((size, size))
    name = _pupil_name(kernel_model, telescope)
    if name is not None:
        img, dx = pupil_image(name, npix=STATIC_NPUP)
    else:
        img, dx = _model_field(kernel_model, STATIC_NPUP)
    rms_m = wl.min() * STATIC_RMS if rms is None else to_quantity(rms, u.m, name="rms").value
    screens = phase_screens(STATIC_NPUP, dx, n_screens, rms=rms_m, mask=img > 0, seed=seed,
                            cutoff=cutoff)
    p = ps.to_value(u.mas) * np.pi / 180 / 3600e3
    cube = np.empty((n_screens, len(wl), size, size))
    # one pair of MFT matrices per wavelength for every screen
    # (`kpifs.simulation.simulate._propagate`,
    # batched); the field's energy is the pupil's whatever the phase
    norm = (p * dx) ** 2 / np.sum(img ** 2)
    for i, lam in enumerate(wl):
        ay, ax = _mft_matrices(STATIC_NPUP, dx, (size, size), p, lam)
        e = ay @ (img * np.exp(2j * np.pi * screens / lam)) @ ax.T
        cube[:, i] = (e.real ** 2 + e.imag ** 2) * (norm / lam ** 2)
    kpd = extract_kernel_phases(cube, kernel_model, wavelengths=wl * u.m, pixscale=ps,
                                window=window, keep_phases=False, source="static residual")
    kp = kpd.kp - kpd.kp.mean(axis=0)
    return kp / np.sqrt(n_screens - 1)


def leading_static_rows(rows, whitening, *, variance=STATIC_VARIANCE, max_rank=STATIC_MAX_RANK):
    """The term's leading modes: rows (k, q, p) whose span is a small part of the data's.

    Its amplitude is fitted on these (`static_term`). A term whose rows span
    every direction of the data (as many screens as kernel phases or more)
    explains anything once its amplitude is free: its weakest directions,
    numerical dust of the screens, are inflated until they hold a companion,
    and the strongest with them. Kept are the leading modes, in the space
    whitened by *whitening* (q, p, p), that hold *variance* of the whitened
    term's trace, at most *max_rank* of the data's dimension ``q p`` (a
    fraction, or a number when above 1). What a companion shares with them is
    then all it can add to the amplitude.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.simulation.aberrations import leading_static_rows
    >>> rng = np.random.default_rng(0)
    >>> modes = rng.standard_normal((5, 100))              # a term of 5 strong directions
    >>> rows = (rng.standard_normal((200, 5)) @ modes + 1e-3 * rng.standard_normal((200, 100)))
    >>> leading_static_rows(rows[:, None] / 200 ** 0.5, np.eye(100)[None]).shape
    (5, 1, 100)
    """
    w = np.asarray(whitening, float)
    r = np.asarray(rows, float)
    n, q, p = r.shape
    rw = whiten(r, w).reshape(n, -1)
    # the whitened rows' leading left singular vectors, from their Gram matrix (n x n:
    # the screens, fewer than the kernel phases); the same combinations of the rows
    # themselves are the modes in the data's space (whitened, ``s_i v_i``)
    s2, vec = np.linalg.eigh(rw @ rw.T)
    s2, vec = np.clip(s2[::-1], 0, None), vec[:, ::-1]
    e = np.cumsum(s2)
    if not len(e) or e[-1] <= 0:
        return r[:0]
    k = int(np.searchsorted(e / e[-1], variance) + 1)
    k = max(1, min(k, int(max_rank * q * p) if max_rank < 1 else int(max_rank)))
    return (vec[:, :k].T @ r.reshape(n, -1)).reshape(k, q, p)


def fit_static_amplitude(y, whitening, rows):
    """Maximum-likelihood amplitude ``a >= 0`` of ``y ~ N(0, C + a R^T R)``.

    *y* (q, p) the data, *whitening* (q, p, p) the per-channel ``C^(-1/2)``,
    *rows* (n, q, p) the term's rows (`static_residual_rows`). Computed in the
    rows' n dimensions (Woodbury), however many kernel phases there are.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.simulation.aberrations import fit_static_amplitude
    >>> rng = np.random.default_rng(0)
    >>> rows = rng.standard_normal((30, 1, 200)) / 30 ** 0.5
    >>> y = rng.standard_normal((1, 200)) + 2.0 * rng.standard_normal(30) @ rows[:, 0]
    >>> a = fit_static_amplitude(y, np.eye(200)[None], rows)
    >>> bool(1.5 < a < 8)          # truth 4 = 2 ** 2
    True
    """
    yw = whiten(np.asarray(y, float), whitening).ravel()
    rows = np.asarray(rows, float)
    rw = whiten(rows, whitening).reshape(len(rows), -1)
    s2, vec = np.linalg.eigh(rw @ rw.T)
    good = s2 > 1e-12 * max(s2.max(), 1e-300)
    s2, vec = s2[good], vec[:, good]
    proj2 = (vec.T @ (rw @ yw)) ** 2 / s2

    def nll(log_a):
        a = np.exp(log_a)
        return float(np.sum(np.log1p(a * s2)) - np.sum(a * s2 / (1 + a * s2) * proj2))

    if not len(s2):
        return 0.0
    scale = 1.0 / np.median(s2)
    lo, hi = np.log(scale) - 25, np.log(scale) + 25
    t = optimize.minimize_scalar(nll, bounds=(lo, hi), method="bounded").x
    # polished by Newton's steps in log a to the minimum itself (the search stops within
    # 1e-5 of it, wherever rounding led it): the same amplitude on any machine
    for _ in range(8):
        g = 1 / (1 + 1 / (np.exp(t) * s2))                      # a s / (1 + a s)
        d1 = np.sum(g) - np.sum(proj2 * g * (1 - g))
        d2 = np.sum(g * (1 - g)) - np.sum(proj2 * g * (1 - g) * (1 - 2 * g))
        step = d1 / d2 if d2 > 0 else np.nan
        if not lo < t - step < hi:
            break
        t -= step
        if abs(step) < 1e-13 * max(1.0, abs(t)):
            break
    return float(np.exp(t)) if nll(t) < nll(lo) - 1e-9 else 0.0


def _amplitudes_nll(a, gram, b, group):
    """``-2 log L`` (constants dropped) of whitened data under ``I + sum_g a_g R_g^T R_g``,
    with its gradient and Hessian in *a* (g,), from the rows' Gram matrix *gram* (N, N),
    their products with the data *b* (N,) and each row's group *group* (N,): in the
    rows' N dimensions (Woodbury), ``C^-1 = I - R^T S^1/2 M^-1 S^1/2 R`` with
    ``M = I + S^1/2 G S^1/2`` and ``S`` the rows' amplitudes."""
    sq = np.sqrt(a[group])
    m = np.eye(len(b)) + sq[:, None] * gram * sq[None]
    cho = np.linalg.cholesky(m)
    c = np.linalg.solve(cho, sq * b)
    nll = 2 * np.sum(np.log(np.diag(cho))) - c @ c
    h = sq[:, None] * np.linalg.solve(m, np.diag(sq))            # S^1/2 M^-1 S^1/2
    z = b - gram @ (h @ b)                                        # R C^-1 y
    q = gram - gram @ h @ gram                                    # R C^-1 R^T
    ng = len(a)
    onehot = np.equal.outer(np.arange(ng), group).astype(float)   # (g, N)
    grad = onehot @ np.diag(q) - onehot @ z ** 2
    hess = -(onehot @ (q * q) @ onehot.T) + 2 * (onehot * z) @ q @ (onehot * z).T
    return nll, grad, hess


def fit_static_amplitudes(y, whitening, groups):
    """Maximum-likelihood amplitudes ``a_g >= 0`` of ``y ~ N(0, C + sum_g a_g R_g^T R_g)``.

    The several-amplitude `fit_static_amplitude`: *groups* is a sequence of rows
    (n_g, q, p), e.g. the imaged residuals of aberrations of different spatial
    spectra (each a group's leading modes, `leading_static_rows`), fitted jointly
    (their rows need not be orthogonal); *y* (q, p) and *whitening* (q, p, p) as
    there. The likelihood is maximised on ``a >= 0`` from each group's own
    amplitude (the best of those starts), by projected Newton steps (an amplitude
    at 0 stays there while the likelihood's slope pushes it below) with a halving
    line search, in the rows' dimensions (Woodbury). With one group it is
    `fit_static_amplitude`.

    Returns
    -------
    ndarray (g,)

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.simulation.aberrations import fit_static_amplitudes
    >>> rng = np.random.default_rng(0)
    >>> r1 = rng.standard_normal((20, 1, 300)) / 20 ** 0.5
    >>> r2 = rng.standard_normal((20, 1, 300)) / 20 ** 0.5
    >>> y = rng.standard_normal((1, 300)) + 3.0 * rng.standard_normal(20) @ r1[:, 0]
    >>> a = fit_static_amplitudes(y, np.eye(300)[None], [r1, r2])
    >>> bool(4 < a[0] < 20), bool(a[1] < 1)       # truth 9 and 0
    (True, True)
    """
    yw = whiten(np.asarray(y, float), whitening).ravel()
    rw = [whiten(np.asarray(r, float), whitening).reshape(len(r), -1) for r in groups]
    ng = len(rw)
    if not ng:
        return np.zeros(0)
    single = np.array([fit_static_amplitude(y, whitening, r) if len(r) else 0.0
                       for r in groups])
    group = np.concatenate([np.full(len(r), g) for g, r in enumerate(rw)]).astype(int)
    big = np.concatenate(rw)
    if ng == 1 or not len(big):
        return single
    gram, b = big @ big.T, big @ yw
    # each group's own amplitude as a start (and all of them at once): the best
    starts = [np.where(np.arange(ng) == g, single, 0.0) for g in range(ng)] + [single]
    a = min(starts, key=lambda v: _amplitudes_nll(v, gram, b, group)[0])
    f, grad, hess = _amplitudes_nll(a, gram, b, group)
    for _ in range(100):
        free = (a > 0) | (grad < 0)
        if not free.any():
            break
        step = np.zeros(ng)
        hf = hess[np.ix_(free, free)]
        try:
            ev = np.linalg.eigvalsh(hf)
            shift = max(0.0, -ev.min() + 1e-12 * max(abs(ev).max(), 1e-300))
            step[free] = np.linalg.solve(hf + shift * np.eye(free.sum()), grad[free])
        except np.linalg.LinAlgError:
            break
        t, done = 1.0, False
        for _ in range(60):
            trial = np.clip(a - t * step, 0, None)
            ft = _amplitudes_nll(trial, gram, b, group)
            if ft[0] < f:
                done = True
                break
            t /= 2
        if not done:
            break
        moved = np.max(np.abs(trial - a) / np.maximum(np.abs(a), 1e-300))
        a, (f, grad, hess) = trial, ft
        if moved < 1e-12:
            break
    return a


def static_term(kpd, y, cov, whitening, *, seed=0):
    """The static residual term of *kpd*'s mean *y* (q, p) with frames' covariance *cov*.

    Returns ``(covariance, rows, info)``: the covariance with the term added per
    channel, the term's rows scaled by its amplitude (to add to the data's
    covariance rows, for the channels' correlation), and what was measured
    (``amplitude``, ``share`` of the covariance's trace, ``pupil``, ``screens``
    and ``rank``, the leading modes the amplitude is fitted on).
    """
    rows = static_residual_rows(kpd.kernel_model, kpd.wavelengths, kpd.pixscale,
                                window=kpd.window, telescope=kpd.meta.get("telescope"),
                                seed=seed)
    lead = leading_static_rows(rows, whitening)
    a = fit_static_amplitude(y, whitening, lead)
    rows = rows * np.sqrt(a)
    add = np.einsum("nqi,nqj->qij", rows, rows)
    share = float(np.trace(add, axis1=1, axis2=2).sum()
                  / max(np.trace(cov, axis1=1, axis2=2).sum(), 1e-300))
    pupil = _pupil_name(kpd.kernel_model, kpd.meta.get("telescope")) or \
        ("model cells" if _envelope(kpd.kernel_model) is None else "annulus of the model")
    log.info("%s: static residual term, %.2f of the frames' variance (pupil %s)",
             kpd.name, share, pupil)
    return cov + add, rows, {"amplitude": a, "share": share, "pupil": pupil,
                             "screens": len(rows), "rank": len(lead)}
