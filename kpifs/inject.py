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
from ._utils import to_quantity
from .calibrate import calibrate
from .detect import detect
from .detect.sky import sky_to_detector   # noqa: F401  (kpifs.inject.sky_to_detector)
from .exceptions import KpifsError, KpifsWarning
from .extract import extract_kernel_phases

__all__ = ["shift_images", "inject_companion", "injection_limits"]

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


def injection_limits(target, calibrators, model, *, wavelengths, pixscale, window,
                     separations, contrasts, n_angles=6, pfa=1e-3, pd=0.5, seed=0,
                     n_draws=5000, progress=False):
    """Empirical contrast curve from companions injected into the target's frames.

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
    contrasts : array-like (ncon,)
        Contrast ladder (flat spectrum) tried at every separation.
    n_angles : int
        Position angles per (separation, contrast), random (seeded).
    pfa, pd : float
        False-alarm probability of the detection and the detection probability
        of the reported limit.

    Returns
    -------
    `~astropy.table.QTable`
        One row per (separation, contrast): ``separation``, ``contrast``,
        ``n_injected``, ``n_detected``, ``pd``; ``meta['limits']`` the contrast
        at P_D = *pd* per separation (interpolated in log contrast; NaN when the
        ladder does not bracket it), with the options in ``meta``.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, extract_kernel_phases, make_pupil
    >>> from kpifs.inject import injection_limits
    >>> from kpifs.simulate import simulate_scene
    >>> obs = simulate_scene("paper", n_frames=12, seed=4, npup=32, contrasts=0.0)
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=0.8 * u.m))
    >>> args = dict(wavelengths=obs.wavelengths, pixscale=obs.params.pixscale)
    >>> cal = extract_kernel_phases(obs.calibrator, km, **args)
    >>> tab = injection_limits(obs.target, [cal], km, window=cal.window, **args,
    ...                        separations=[60] * u.mas, contrasts=[0.05], n_angles=2,
    ...                        n_draws=1000)
    >>> tab["n_injected"].tolist(), bool(tab["pd"][0] == 1.0)
    ([2], True)
    """
    target = np.asarray(target, float)
    seps = np.atleast_1d(to_quantity(separations, u.mas, name="separations").value)
    ladder = np.sort(np.atleast_1d(np.asarray(contrasts, float)))
    if ladder.size == 0 or np.any(ladder <= 0) or seps.size == 0 or np.any(seps <= 0):
        raise KpifsError("injection limits: separations and contrasts must be > 0")
    rng = np.random.default_rng(seed)
    ps = to_quantity(pixscale, u.mas, name="pixel scale").value
    resolution = to_quantity(wavelengths, u.um).to_value(u.m).min() / float(
        np.max(np.hypot(*model.uv.to_value(u.m).T))) / (np.pi / 180 / 3600e3)
    rows = []
    todo = [(s, c) for s in seps for c in ladder]
    for s, c in progress_bar(todo, desc="injections", unit="step", enabled=progress):
        hits = 0
        for th in rng.uniform(0, 2 * np.pi, n_angles):
            x, y = s * np.cos(th), s * np.sin(th)
            cube = inject_companion(target, position=[x, y] * u.mas, contrast=c,
                                    pixscale=ps * u.mas)
            kpd = extract_kernel_phases(cube, model, wavelengths=wavelengths, pixscale=pixscale,
                                        window=window, keep_phases=False, source="injected")
            res = detect(calibrate(kpd, calibrators), pfa=pfa, pd=pd, n_draws=n_draws,
                         seed=int(rng.integers(2 ** 31)), limits=False)
            hits += _detected(res, x, y, max(resolution, 2 * ps))
        rows.append((s, c, n_angles, hits, hits / n_angles))
        log.info("injected %.3g at %.0f mas: %d of %d found", c, s, hits, n_angles)
    tab = QTable(rows=rows, names=("separation", "contrast", "n_injected", "n_detected", "pd"))
    tab["separation"].unit = u.mas
    limits = []
    for s in seps:
        sel = tab[tab["separation"].value == s]
        p = np.maximum.accumulate(np.asarray(sel["pd"], float))     # monotone in contrast
        k = np.flatnonzero(p >= pd)
        if not len(k) or k[0] == 0:
            limits.append(np.nan if not len(k) else float(sel["contrast"][0]))
            continue
        i = k[0]
        lc = np.log(np.asarray(sel["contrast"], float))
        f = (pd - p[i - 1]) / (p[i] - p[i - 1])
        limits.append(float(np.exp(lc[i - 1] + f * (lc[i] - lc[i - 1]))))
    tab.meta.update(limits=limits, pfa=pfa, pd=pd, n_angles=n_angles, seed=seed,
                    n_draws=n_draws, separations_mas=seps.tolist(),
                    method="companions made of each frame's own PSF, whole reduction rerun")
    return tab
