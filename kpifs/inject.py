"""Injection-recovery on real data: companions made of each frame's own PSF.

A companion of contrast ``c`` at offset ``rho`` is injected as ``c`` times a copy
of each frame's own image, shifted by ``rho`` (a sub-pixel Fourier shift, the
images zero-padded so that nothing wraps round): the star's PSF at that
instant, aberrations included, as a real companion would have it. Offsets are
on the detector (x, y: columns, rows; mas) or on the sky (dRA East-positive,
dDec; mas), turned into detector offsets frame by frame with the detector
position angles (`kpifs.io.angles`).

`injection_limits` measures the contrast curve the way a user checks a claim:
companions injected at many position angles and contrasts around each
separation, the whole reduction rerun (extraction, calibration with the error
model, detection), and the detection probability at the requested false-alarm
probability counted; the contrast where half are found is the empirical 50 %
limit, to set beside the analytic one.
"""
import logging
import warnings

import numpy as np
from astropy import units as u
from astropy.table import QTable

from ._utils import progress as progress_bar
from ._utils import one_blas_thread, to_quantity
from .calibration.calibrate import calibrate
from .detect import detect
from .detect.sky import sky_to_detector   # noqa: F401  (kpifs.inject.sky_to_detector)
from .exceptions import KpifsError, KpifsWarning
from .extraction.extract import extract_kernel_phases

__all__ = ["shift_images", "inject_companion", "injection_limits", "limit_bracket",
           "injection_brackets", "BRACKET_ALPHA"]

log = logging.getLogger(__name__)


def shift_images(images, dx, dy, *, pad=None):
    """Images shifted by ``(dx, dy)`` pixels (sub-pixel, by the Fourier shift theorem).

    The images are zero-padded by *pad* pixels (default: the shift plus 8) so
    that what leaves one side does not come back on the other.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.inject import shift_images
    >>> img = np.zeros((16, 16)); img[8, 8] = 1.0
    >>> out = shift_images(img, 2.0, -3.0)
    >>> [int(i) for i in np.unravel_index(np.argmax(out), out.shape)]
    [5, 10]
    """
    images = np.asarray(images, float)
    ny, nx = images.shape[-2:]
    pad = int(np.ceil(max(abs(dx), abs(dy)))) + 8 if pad is None else int(pad)
    big = np.zeros(images.shape[:-2] + (ny + 2 * pad, nx + 2 * pad))
    big[..., pad:pad + ny, pad:pad + nx] = images
    fy = np.fft.fftfreq(ny + 2 * pad)[:, None]
    fx = np.fft.rfftfreq(nx + 2 * pad)[None, :]
    ramp = np.exp(-2j * np.pi * (fx * dx + fy * dy))
    out = np.fft.irfft2(np.fft.rfft2(big) * ramp, s=big.shape[-2:])
    return out[..., pad:pad + ny, pad:pad + nx]


def inject_companion(cube, *, position, contrast, pixscale, frame="detector", detpa=None):
    """A copy of *cube* with a companion made of each frame's own PSF.

    Parameters
    ----------
    cube : array-like, shape (nframe, nwave, ny, nx)
    position : `~astropy.units.Quantity` (2,)
        ``(x, y)`` on the detector (*frame* 'detector') or ``(dRA, dDec)`` on the
        sky (*frame* 'sky', East positive), angular units.
    contrast : float or array-like (nwave,)
        Companion-to-star flux ratio per channel (its spectrum).
    pixscale : `~astropy.units.Quantity`
    frame : {'detector', 'sky'}
    detpa : array-like (nframe,), optional
        Detector position angles (deg), needed for *frame* 'sky'.

    Returns
    -------
    ndarray, shape (nframe, nwave, ny, nx)

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs.inject import inject_companion
    >>> cube = np.zeros((1, 1, 32, 32)); cube[0, 0, 16, 16] = 1.0
    >>> out = inject_companion(cube, position=[50, 0] * u.mas, contrast=0.1,
    ...                        pixscale=10 * u.mas)
    >>> round(float(out[0, 0, 16, 21]), 3)
    0.1
    """
    cube = np.asarray(cube, float)
    if cube.ndim != 4:
        raise KpifsError(f"inject: expected a cube (nframe, nwave, ny, nx), got shape "
                         f"{cube.shape}")
    nframe, nwave = cube.shape[:2]
    pos = to_quantity(position, u.mas, name="companion position").value
    if np.shape(pos) != (2,) or not np.all(np.isfinite(pos)):
        raise KpifsError(f"inject: a position is two finite offsets, got {position!r}")
    ps = to_quantity(pixscale, u.mas, name="pixel scale").value
    if np.max(np.abs(pos)) / ps > max(cube.shape[-2:]):      # issue 37: before any padding
        raise KpifsError(f"inject: a companion at ({pos[0]:g}, {pos[1]:g}) mas ({frame}) falls "
                         f"off the image: 100% of its flux would be lost (the image reaches "
                         f"about {0.5 * min(cube.shape[-2:]) * ps:.0f} mas from its centre)")
    c = np.atleast_1d(np.asarray(contrast, float))
    if c.ndim != 1 or c.size not in (1, nwave):
        raise KpifsError(f"inject: {c.size} contrasts for {nwave} channel(s): give one, or "
                         f"one per channel")
    c = np.broadcast_to(c, (nwave,))
    if not np.all(np.isfinite(c)) or np.any(c < 0) or np.any(c >= 1):
        raise KpifsError(f"inject: contrasts must be finite and in [0, 1) (companion/star "
                         f"flux), got {contrast!r}")
    if frame == "sky":
        if detpa is None or not np.all(np.isfinite(np.asarray(detpa, float))):
            raise KpifsError("inject: a sky position needs the detector position angle of "
                             "every frame (give --pa)")
        x, y = sky_to_detector(pos[0], pos[1], np.broadcast_to(detpa, (nframe,)))
    elif frame == "detector":
        x, y = np.full(nframe, pos[0]), np.full(nframe, pos[1])
    else:
        raise KpifsError(f"inject: frame must be 'detector' or 'sky', got {frame!r}")
    out = cube.copy()
    finite = np.nan_to_num(cube)
    kept = np.ones(nframe)
    for f in range(nframe):
        shifted = shift_images(finite[f], x[f] / ps, y[f] / ps)
        total = finite[f].sum()
        if total > 0:
            kept[f] = shifted.sum() / total
        out[f] += c[:, None, None] * shifted
    _check_flux_kept(kept, pos, frame, cube.shape[-2:], ps)
    return out


#: Largest share of an injected companion's flux that may fall off the image without a
#: warning; beyond `LOST_REFUSED` the injection is refused.
LOST_WARNED, LOST_REFUSED = 0.05, 0.5


def _check_flux_kept(kept, pos, frame, shape, ps):
    """Refuse a companion mostly off the image; warn, with the loss, when some of it is."""
    lost = 1.0 - float(np.median(np.clip(kept, 0.0, 1.0)))
    where = f"({pos[0]:g}, {pos[1]:g}) mas ({frame})"
    half = 0.5 * min(shape) * ps
    if lost > LOST_REFUSED:
        raise KpifsError(f"inject: a companion at {where} falls off the image: "
                         f"{100 * lost:.0f}% of its flux would be lost (the image reaches "
                         f"about {half:.0f} mas from its centre)")
    if lost > LOST_WARNED:
        warnings.warn(f"inject: {100 * lost:.0f}% of the flux of the companion at {where} "
                      f"falls off the image: the contrast on the image is that much lower than "
                      f"asked", KpifsWarning, stacklevel=3)


def _detected(result, x, y, radius):
    tab = result.candidates
    if not len(tab):
        return False
    cx = tab["fit_x"] if "fit_x" in tab.colnames else tab["x"]
    cy = tab["fit_y"] if "fit_y" in tab.colnames else tab["y"]
    return bool(np.any(np.hypot(cx.to_value(u.mas) - x, cy.to_value(u.mas) - y) < radius))


#: The first steps of a ladder, as factors of the separation's starting contrast (the
#: analytic limit); the ladder grows by `LADDER_RATIO` beyond its ends until it brackets
#: the detection probability.
LADDER_FACTORS = (0.5, 1.0, 2.0)
LADDER_RATIO = 2.0

#: Candidates each injection search reports at most: the injected companion, a real
#: one and a side lobe fit well within, and the search stops early.
INJECTION_CANDIDATES = 5


def _limit(contrasts, fractions, pd):
    """The contrast where the found fraction reaches *pd* (log interpolation) and how it is
    known: '=' bracketed, '<' found at every step (the lowest step is an upper bound),
    '>' never found enough (the highest step is a lower bound)."""
    p = np.maximum.accumulate(np.asarray(fractions, float))     # monotone in contrast
    c = np.asarray(contrasts, float)
    k = np.flatnonzero(p >= pd)
    if not len(k):
        return float(c[-1]), ">"
    i = k[0]
    if i == 0:
        return float(c[0]), "<"
    f = (pd - p[i - 1]) / (p[i] - p[i - 1])
    lc = np.log(c)
    return float(np.exp(lc[i - 1] + f * (lc[i] - lc[i - 1]))), "="


#: One-sided binomial level of `limit_bracket`: a step's count is taken as below (above)
#: the detection probability when a count that low (high) would be rarer than this if the
#: step were at the limit. With 4 angles, 0 of 4 and 4 of 4 (1/16 each) are; 1 of 4 is not.
BRACKET_ALPHA = 0.1


def limit_bracket(contrasts, n_detected, n_injected, pd=0.5, *, alpha=BRACKET_ALPHA):
    """Where the injection steps put the limit, and what they allow one to say of it.

    A step whose count of found companions is significantly below *pd* (a count
    that low has a binomial probability below *alpha* at the limit) lies below
    the limit; one significantly above lies above it. The limit is bracketed
    by the highest step below and the lowest step above (NaN where the ladder
    has none). Steps in between are inconclusive for their number of angles.
    An interpolated value (log interpolation of the found fractions) is given
    only when the two ends are adjacent steps and at least one of them was
    found neither never nor always (else the fractions say nothing of where
    between them the limit lies), else NaN.

    Returns
    -------
    low, high, value : float

    Examples
    --------
    >>> from kpifs.inject import limit_bracket
    >>> # 4 angles: 0, 2 and 4 of 4 found at 0.5, 1 and 2 times 1e-4
    >>> limit_bracket([0.5e-4, 1e-4, 2e-4], [0, 2, 4], [4, 4, 4])   # no value: 1e-4 is inside
    (5e-05, 0.0002, nan)
    >>> # 20 angles: 4 and 16 of 20 found at adjacent steps
    >>> [round(v, 7) for v in limit_bracket([1e-4, 2e-4], [4, 16], [20, 20])]
    [0.0001, 0.0002, 0.0001414]
    """
    from scipy.stats import binom
    c = np.asarray(contrasts, float)
    k = np.asarray(n_detected, int)
    n = np.asarray(n_injected, int)
    order = np.argsort(c)
    c, k, n = c[order], k[order], n[order]
    below = binom.cdf(k, n, pd) < alpha                 # so few found: under the limit
    above = binom.sf(k - 1, n, pd) < alpha              # so many found: over it
    lo = np.flatnonzero(below)
    hi = np.flatnonzero(above)
    i = lo[-1] if len(lo) else None
    j = hi[hi > i][0] if len(hi) and i is not None and np.any(hi > i) else \
        (hi[0] if len(hi) and i is None else None)
    low = float(c[i]) if i is not None else np.nan
    high = float(c[j]) if j is not None else np.nan
    value = np.nan
    # adjacent ends, not both saturated (never and always found say nothing of the slope)
    if i is not None and j is not None and j == i + 1 and (k[i] > 0 or k[j] < n[j]):
        f = np.clip((pd - k[i] / n[i]) / (k[j] / n[j] - k[i] / n[i]), 0.0, 1.0)
        value = float(np.exp(np.log(c[i]) + f * (np.log(c[j]) - np.log(c[i]))))
    return low, high, value


def injection_brackets(table):
    """`limit_bracket` at each separation of an `injection_limits` *table*.

    Returns
    -------
    `~astropy.table.QTable`
        ``separation``, ``limit_low``, ``limit_high`` and ``limit_interpolated``
        (NaN where the steps do not allow it), one row per separation.

    Examples
    --------
    >>> import astropy.units as u
    >>> from astropy.table import QTable
    >>> from kpifs.inject import injection_brackets
    >>> tab = QTable({"separation": [60, 60, 60] * u.mas, "contrast": [1e-4, 2e-4, 4e-4],
    ...               "n_injected": [4, 4, 4], "n_detected": [0, 2, 4]})
    >>> tab.meta["pd"] = 0.5
    >>> row = injection_brackets(tab)[0]
    >>> float(row["limit_low"]), float(row["limit_high"]), bool(row["limit_interpolated"] > 0)
    (0.0001, 0.0004, False)
    """
    sep = u.Quantity(table["separation"], u.mas).value
    pd = float(table.meta.get("pd", 0.5))
    rows = []
    for s in dict.fromkeys(sep.tolist()):
        m = sep == s
        rows.append((s, *limit_bracket(np.asarray(table["contrast"])[m],
                                       np.asarray(table["n_detected"])[m],
                                       np.asarray(table["n_injected"])[m], pd)))
    out = QTable(rows=rows, names=("separation", "limit_low", "limit_high",
                                   "limit_interpolated"))
    out["separation"].unit = u.mas
    return out


def _next_contrast(contrasts, fractions, pd, max_steps):
    """The next step of an adaptive ladder, or None once it brackets *pd* (or is full)."""
    if len(contrasts) >= max_steps:
        return None
    flag = _limit(contrasts, fractions, pd)[1]
    if flag == "<":
        return min(contrasts) / LADDER_RATIO
    if flag == ">":
        return max(contrasts) * LADDER_RATIO
    return None


class _Injector:
    """One injection at a time: the companion into the target's frames, the target
    re-extracted, calibrated against the calibrators' kernel phases (extracted once) and
    searched; returns whether a candidate lies within *radius* of the injection."""

    def __init__(self, target, calibrators, model, *, wavelengths, pixscale, window, pfa, pd,
                 n_draws, reference=None, extract_kwargs=None):
        self.target, self.calibrators, self.model = target, calibrators, model
        self.reference, self.kwargs = reference, dict(extract_kwargs or {})
        self.wl, self.ps, self.window = wavelengths, pixscale, window
        self.pfa, self.pd, self.n_draws = pfa, pd, n_draws
        ps = to_quantity(pixscale, u.mas, name="pixel scale").value
        resolution = to_quantity(wavelengths, u.um).to_value(u.m).min() / float(
            np.max(np.hypot(*model.uv.to_value(u.m).T))) / (np.pi / 180 / 3600e3)
        self.radius = max(resolution, 2 * ps)

    def __call__(self, x, y, contrast, seed):
        cube = inject_companion(self.target, position=[x, y] * u.mas, contrast=contrast,
                                pixscale=self.ps)
        ref = self.reference
        kpd = extract_kernel_phases(cube, self.model, wavelengths=self.wl, pixscale=self.ps,
                                    window=self.window, keep_phases=False, source="injected",
                                    header=None if ref is None else ref.header, **self.kwargs)
        _reuse_pixel_noise(kpd, ref)
        # found or not is all that is asked: one error model (no characterisation model),
        # no limits, and a search that stops after a few candidates
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*max_candidates", category=KpifsWarning)
            res = detect(calibrate(kpd, self.calibrators, fit_modes=None), pfa=self.pfa,
                         pd=self.pd, n_draws=self.n_draws, seed=seed, limits=False,
                         max_candidates=INJECTION_CANDIDATES)
        return _detected(res, x, y, self.radius)


def _reuse_pixel_noise(kpd, reference):
    """The target's own per-pixel noise (ERR) for its injected copy: a faint companion
    changes neither the frames kept nor their noise (issue 37: without it the injected
    target was calibrated on its frames' scatter alone, the analytic limit with ERR)."""
    if reference is None or reference.meta.get("pixel_covariance") is None:
        return
    if reference.kp_err is not None and reference.kp_err.shape == kpd.shape:
        kpd.kp_err = reference.kp_err
    kpd.meta["pixel_covariance"] = reference.meta["pixel_covariance"]
    kpd.meta["pixel_noise"] = reference.meta.get("pixel_noise")


def injection_limits(target, calibrators, model, *, wavelengths, pixscale, window,
                     separations, contrasts=None, start=None, n_angles=4, pfa=1e-3, pd=0.5,
                     seed=0, n_draws=1000, max_steps=8, progress=False, reference=None,
                     extract_kwargs=None):
    """Empirical contrast curve from companions injected into the target's frames.

    At each separation, companions of one contrast are injected at *n_angles*
    position angles (evenly spaced from a seeded random start), each into the
    target's frames alone, and the whole reduction is rerun: extraction,
    calibration against the calibrators' kernel phases (extracted once), the
    search at *pfa*. The fraction found is counted per contrast step, and the
    contrast where it reaches *pd* is interpolated in log contrast.

    The ladder is either given (*contrasts*, tried at every separation) or
    made to bracket the limit by itself: it starts at *start* times
    `LADDER_FACTORS` (give the analytic limit) and grows by `LADDER_RATIO`
    below its lowest step while every step is found, above its highest while
    none is found often enough, up to *max_steps* steps. A limit that the
    ladder does not bracket is censored: flag ``'<'`` (the lowest step was found
    at least *pd* of the time: an upper bound) or ``'>'`` (the highest was not:
    a lower bound).

    Parameters
    ----------
    target : array-like (nframe, nwave, ny, nx)
        The target's images (companion-free, or with companions far away).
    calibrators : list of `~kpifs.KernelPhaseData`
        Extracted calibrator frames.
    model : `~kpifs.KernelModel`
        The kernel model the calibrators were extracted with.
    wavelengths, pixscale, window
        As for `~kpifs.extract_kernel_phases`.
    separations : `~astropy.units.Quantity` (nsep,)
    contrasts : array-like (ncon,), optional
        A fixed contrast ladder (flat spectrum) tried at every separation.
    start : array-like (nsep,), optional
        Without *contrasts*: the contrast each separation's ladder starts
        from (the analytic limit).
    n_angles : int
        Position angles per (separation, contrast).
    pfa, pd : float
        False-alarm probability of the detection and the detection probability
        of the reported limit.
    seed : int
        Seed of the angles and of the searches' null draws.
    n_draws : int
        Monte-Carlo draws calibrating each injection's search.
    max_steps : int
        Most contrast steps of an adaptive ladder.
    progress : bool
        Progress on stderr (a bar on a terminal, otherwise a line every few
        seconds with the time left).
    reference : `~kpifs.KernelPhaseData`, optional
        The target's own extraction (`~kpifs.workflow.extract_observation`, as
        for the analytic limit): every injected extraction gets its header (the
        instrument's facts, checked against the calibrators') and its per-pixel
        noise (ERR), so that the injections are reduced as the target is.
    extract_kwargs : dict, optional
        More options of `~kpifs.extract_kernel_phases` (centroid, bad pixels
        and frames, Nyquist, precision), as the target's extraction used.

    Returns
    -------
    `~astropy.table.QTable`
        One row per (separation, contrast): ``separation``, ``contrast``,
        ``n_injected``, ``n_detected``, ``pd``; ``meta['limits']`` the contrast
        at P_D = *pd* per separation and ``meta['flags']`` how each is known
        ('=', '<' or '>'), with the options in ``meta``.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, extract_kernel_phases, make_pupil
    >>> from kpifs.inject import injection_limits
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> obs = simulate_scene("paper", n_frames=12, seed=4, npup=32, contrasts=0.0)
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=0.8 * u.m))
    >>> args = dict(wavelengths=obs.wavelengths, pixscale=obs.params.pixscale)
    >>> cal = extract_kernel_phases(obs.calibrator, km, **args)
    >>> tab = injection_limits(obs.target, [cal], km, window=cal.window, **args,
    ...                        separations=[60] * u.mas, contrasts=[0.05], n_angles=2)
    >>> tab["n_injected"].tolist(), bool(tab["pd"][0] == 1.0), tab.meta["flags"]
    ([2], True, ['<'])
    """
    target = np.asarray(target, float)
    seps = np.atleast_1d(to_quantity(separations, u.mas, name="separations").value)
    if seps.size == 0 or np.any(~np.isfinite(seps)) or np.any(seps <= 0):
        raise KpifsError("injection limits: separations must be > 0")
    if contrasts is not None:
        ladders = [list(np.sort(np.atleast_1d(np.asarray(contrasts, float))))] * len(seps)
    elif start is not None:
        s0 = np.broadcast_to(np.asarray(start, float), seps.shape)
        ladders = [list(c * np.asarray(LADDER_FACTORS)) for c in s0]
    else:
        raise KpifsError("injection limits: give a contrast ladder or the contrasts to start "
                         "from (the analytic limits)")
    if any(len(lad) == 0 or not np.all(np.isfinite(lad)) or min(lad) <= 0 for lad in ladders):
        raise KpifsError("injection limits: contrasts must be finite and > 0")
    rng = np.random.default_rng(seed)
    inject = _Injector(target, calibrators, model, wavelengths=wavelengths, pixscale=pixscale,
                       window=window, pfa=pfa, pd=pd, n_draws=n_draws, reference=reference,
                       extract_kwargs=extract_kwargs)
    bar = progress_bar(desc="injections", unit="injection",
                       total=sum(len(lad) for lad in ladders) * n_angles, enabled=progress)
    rows, limits, flags = [], [], []
    # the searches' own threads share the cores: BLAS's on top would oversubscribe them
    with one_blas_thread():
        for s, ladder in zip(seps, ladders):
            done = {}
            todo = list(ladder)
            while todo:
                c = todo.pop(0)
                th = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(n_angles) / n_angles
                hits = 0
                for t in th:
                    hits += inject(s * np.cos(t), s * np.sin(t), c, int(rng.integers(2 ** 31)))
                    bar.update(1)
                done[c] = hits
                log.info("injected %.3g at %.0f mas: %d of %d found", c, s, hits, n_angles)
                if not todo and contrasts is None:
                    cs = sorted(done)
                    nxt = _next_contrast(cs, [done[k] / n_angles for k in cs], pd, max_steps)
                    if nxt is not None:
                        todo.append(nxt)
                        bar.total += n_angles
            cs = sorted(done)
            rows += [(s, c, n_angles, done[c], done[c] / n_angles) for c in cs]
            lim, flag = _limit(cs, [done[k] / n_angles for k in cs], pd)
            limits.append(lim)
            flags.append(flag)
    bar.close()
    tab = QTable(rows=rows, names=("separation", "contrast", "n_injected", "n_detected", "pd"))
    tab["separation"].unit = u.mas
    tab.meta.update(limits=limits, flags=flags, pfa=pfa, pd=pd, n_angles=n_angles, seed=seed,
                    n_draws=n_draws, separations_mas=seps.tolist(),
                    ladder="given" if contrasts is not None else "adaptive",
                    method="companions made of each frame's own PSF, whole reduction rerun")
    return tab
