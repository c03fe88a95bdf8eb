"""Check a pupil model against the data: orientation, pixel scale, transmission cut and step.

The pupil on the detector is never exactly the textbook one: the mask turns by
a degree or two, the plate scale is known to a per cent, and partly covered
cells at the pupil's edge and along the spiders are modelled more or less well.
`check_pupil_model` measures all of this on frames of a star without a known
companion (a calibrator, two calibrators, or the two halves of one sequence).

Two measures, each for what it is good at:

- **Orientation and scale** are fitted to the Fourier *amplitudes*. Averaged
  over frames, the amplitude at each uv point is the telescope's transfer
  function there, which the model predicts up to a smooth attenuation
  (aberrations, pixels): the redundancy. A turned or scaled model samples
  the transfer function off its peaks and edges and the agreement drops. The
  mismatch is the weighted rms of ``log(amplitude / redundancy)`` about a
  fitted ``a - b |u|^2`` per channel; it is scanned on a coarse grid and the
  minimum refined by a 1-D bounded search (rotation, then scale, then rotation
  again).

  Kernel phases are a poor guide here: a scale that pushes uv points beyond
  the real transfer function's edge only adds noise, which the calibrated
  reduced chi2 (normalised by that noise) hides and the raw scatter rewards
  moving the points inwards.
- **Transmission cut and step** change the kernel itself, so they are
  compared by the *calibrated reduced chi2*: the residual between the two
  stars (or halves) in the leading modes of the frame scatter, relative to
  that scatter. The default is kept unless another model lowers it by more
  than twice the standard deviation of the difference (a chi2 of ``n`` modes
  scatters by ``sqrt(2 n)``). The same test decides whether a fitted
  orientation and scale that the textbook pupil does not describe to within
  the amplitudes' noise are worth using.
"""
import logging
from dataclasses import dataclass, field

import numpy as np
from astropy import units as u
from astropy.table import QTable

from ._lazy import lazy_module
from ._utils import one_blas_thread, to_quantity
from ._utils import progress as progress_bar
from .exceptions import KpifsError
from .extraction.extract import extract_kernel_phases
from .model.kernel import KernelModel
from .model.pupil import BINARY_MIN_TRANSMISSION, make_pupil, model_defaults
from .simulation.simulate import simulate_psf

optimize = lazy_module("scipy.optimize")

__all__ = ["ModelCheck", "check_pupil_model"]

log = logging.getLogger(__name__)

#: A model replaces the default only when it lowers the calibrated reduced chi2 by
#: more than this many standard deviations of the difference (`_chi2_difference_sd`).
CHI2_SIGMAS = 2.0


def _chi2_difference_sd(row, ref):
    """Standard deviation of the difference of two models' calibrated reduced chi2.

    A chi2 of ``n`` degrees of freedom (the modes) has a standard deviation
    ``sqrt(2 n)``; one ``chi2_red`` times larger than its law (noise the frames'
    scatter does not show) ``chi2_red * sqrt(2 n)``: in reduced units
    ``chi2_red * sqrt(2 / n)``. The two models see the same frames, but not
    the same kernels: their chi2 are taken as independent, which errs towards
    keeping the default.
    """
    return float(np.sqrt(2 * ref["chi2_red"] ** 2 / ref["n_modes"]
                         + 2 * row["chi2_red"] ** 2 / row["n_modes"]))


def _significantly_lower(row, ref):
    return ref["chi2_red"] - row["chi2_red"] > CHI2_SIGMAS * _chi2_difference_sd(row, ref)


#: The fitted geometry is trusted outright when the amplitude mismatch is within
#: this factor of its noise.
SHAPE_TOLERANCE = 3.0

#: Amplitudes are compared where the predicted transfer is at least this fraction
#: of its peak.
MIN_TRANSFER = 0.2

#: The aberrations' attenuation of the amplitudes is a polynomial of this degree
#: in baseline length / wavelength (in units of ATTENUATION_SCALE m/um): an AO
#: halo is not a Gaussian.
ATTENUATION_DEGREE = 3
ATTENUATION_SCALE = 1e6

#: Evaluations a bounded 1-D refinement takes, about (for the progress estimate).
_REFINE_EVALUATIONS = 8

#: Pupil sampling of the model images (a coarser pupil turns in jumps).
MODEL_NPUP = 256


@dataclass
class ModelCheck:
    """What `check_pupil_model` found.

    Attributes
    ----------
    table : `~astropy.table.QTable`
        Every model tried: ``scan`` ('default', 'rotation', 'scale', 'refine',
        'fitted', 'cut', 'step'), ``rotation`` (deg), ``scale`` (pixel-scale factor),
        ``grey``, ``min_transmission``, ``step`` (m), ``n_kp``,
        ``amp_mismatch``, ``chi2_red`` (over ``n_modes`` modes), ``residual`` (rad, rms of the
        calibrated mean) and ``scatter`` (rad, rms per frame).
    rotation : `~astropy.units.Quantity`
        Fitted turn of the model (deg).
    scale : float
        Fitted pixel-scale factor: the data's pixel scale is ``scale`` times
        the one given.
    recommended : dict
        Options of the recommended model (`~kpifs.model.pupil.make_pupil` keywords,
        plus ``pixscale``).
    reason : str
        Why.
    """

    table: QTable
    rotation: u.Quantity
    scale: float
    recommended: dict
    reason: str
    meta: dict = field(default_factory=dict)

    def summary(self):
        """A few lines for a terminal."""
        rec = self.recommended
        kind = "grey" if rec["grey"] else "binary"
        opts = (f"--rotation {rec['rotation'].to_value(u.deg):.2f}deg --pixscale "
                f"{rec['pixscale'].to_value(u.mas):.3f}mas --step {rec['step'].to_value(u.m)}m "
                f"--{kind} --min-transmission {rec['min_transmission']}")
        return (f"rotation {self.rotation.to_value(u.deg):+.2f} deg, pixel-scale factor "
                f"{self.scale:.4f}\nrecommended: {opts}\nwhy: {self.reason}")


def _frames(data, name):
    data = np.asarray(data, float)
    if data.ndim == 3:
        data = data[:, None]
    if data.ndim != 4 or len(data) < 4:
        raise KpifsError(f"{name}: need at least 4 frames (nframe, [nwave,] ny, nx), got "
                         f"shape {data.shape}")
    return data


def _amp_mismatch(amps, pred, model, wavelengths, *, floor=False):
    """Weighted rms of log(mean amplitude / predicted amplitude) about a smooth attenuation.

    *pred* (nwave, nuv) are the amplitudes of the aberration-free image of the
    hypothesis, extracted exactly as the data (window, pixels and all): what is
    left is the aberrations' smooth attenuation."""
    q2 = np.sum(model.uv.to_value(u.m) ** 2, axis=1)
    out = []
    for i, lam in enumerate(wavelengths.to_value(u.m)):
        a = np.nanmean(amps[:, i], axis=0)
        if floor:
            # what the mismatch would be from the frames' scatter alone
            with np.errstate(divide="ignore", invalid="ignore"):
                sig = np.nanstd(np.log(amps[:, i]), axis=0) / np.sqrt(len(amps))
        red = pred[i] / np.nanmax(pred[i])
        # where the transfer is low the mean amplitude is mostly noise (and biased
        # up by it): such points would pull the scale outwards
        ok = np.isfinite(a) & (a > 0) & np.isfinite(red) & (red > MIN_TRANSFER)
        y = np.log(a[ok] / red[ok])
        q = np.sqrt(q2[ok]) / lam / ATTENUATION_SCALE
        x = np.column_stack([q ** k for k in range(ATTENUATION_DEGREE + 1)])
        w = red[ok]
        coef = np.linalg.lstsq(x * w[:, None], y * w, rcond=None)[0]
        r = sig[ok] * w if floor else (y - x @ coef) * w
        out.append(np.nansum(r ** 2) / np.sum(w ** 2))
    return float(np.sqrt(np.mean(out)))


def _phase_measures(kt, kc):
    """Calibrated reduced chi2 in the leading modes, residual rms and frame scatter."""
    dev = np.concatenate([kt - kt.mean(0), kc - kc.mean(0)])
    d = kt.mean(0) - kc.mean(0)
    nu = len(dev) - 2
    chi2 = 0.0
    m_all = 0
    for i in range(d.shape[0]):
        _, s, vt = np.linalg.svd(dev[:, i], full_matrices=False)
        m = max(1, min(nu // 2, len(s)))
        var = s[:m] ** 2 / nu * (1 / len(kt) + 1 / len(kc))
        chi2 += float(np.sum((vt[:m] @ d[i]) ** 2 / var))
        m_all += m
    return (chi2 / m_all, m_all, float(np.sqrt(np.mean(d ** 2))),
            float(np.sqrt(np.mean(dev ** 2))))


class _Evaluator:
    def __init__(self, pupil, target, calibrator, wavelengths, pixscale, window, centroid,
                 pupil_scale=None):
        self.pupil, self.pupil_scale = pupil, pupil_scale
        self.target, self.calibrator = target, calibrator
        self.wl, self.ps = wavelengths, pixscale
        self.kw = dict(window=window, centroid=centroid, bad_frames="drop")
        self.rows = []
        self.bar = None
        self.floor = None
        self.ideal = {}

    def __call__(self, scan, model, rotation, scale, options):
        # the model turns; the scale is the pixel scale's (uv points stay in metres)
        km = model.transformed(rotation=rotation * u.deg)
        ps = self.ps * scale
        args = dict(wavelengths=self.wl, pixscale=ps, keep_phases=True, **self.kw)
        kt = extract_kernel_phases(self.target, km, source="target", **args)
        kc = extract_kernel_phases(self.calibrator, kt.kernel_model, source="calibrator",
                                   **args)
        amps = np.concatenate([kt.amplitudes, kc.amplitudes])
        # the hypothesis: the textbook pupil turned by *rotation*, at pixel scale *ps*
        # (the same for every cut and step tried at one geometry: made once)
        ideal = self.ideal.get((rotation, scale))
        if ideal is None:
            ideal = self.ideal[(rotation, scale)] = simulate_psf(
                self.pupil, self.wl, pixscale=ps, shape=self.target.shape[-2:],
                pupil_rotation=rotation * u.deg, npup=MODEL_NPUP, supersample=4,
                pupil_scale=self.pupil_scale)
        pred = extract_kernel_phases(ideal[None], kt.kernel_model, source="model image",
                                     **args).amplitudes[0]
        mis = _amp_mismatch(amps, pred, kt.kernel_model, self.wl)
        if self.floor is None:
            self.floor = _amp_mismatch(amps, pred, kt.kernel_model, self.wl, floor=True)
        chi2, n_modes, resid, scat = _phase_measures(kt.kp, kc.kp)
        self.rows.append(dict(scan=scan, rotation=rotation, scale=scale,
                              grey=options["grey"],
                              min_transmission=options["min_transmission"],
                              step=options["step"], n_kp=kt.kernel_model.n_kp,
                              amp_mismatch=mis, chi2_red=chi2, n_modes=n_modes,
                              residual=resid,
                              scatter=scat))
        log.info("model check %s: rotation %.2f deg, scale %.4f, %s: mismatch %.5f, "
                 "chi2_red %.2f", scan, rotation, scale, options, mis, chi2)
        if self.bar is not None:
            if self.bar.n + 1 >= self.bar.total:     # the refinements took more steps
                self.bar.total += 1
            self.bar.update(1)
        return mis


def _scan_and_refine(fn, grid, xatol):
    vals = np.array([fn(x) for x in grid])
    i = int(np.argmin(vals))
    lo = grid[max(i - 1, 0)]
    hi = grid[min(i + 1, len(grid) - 1)]
    if hi <= lo:
        return float(grid[i])
    res = optimize.minimize_scalar(fn, bounds=(lo, hi), method="bounded",
                                   options={"xatol": xatol})
    return float(res.x) if res.fun <= vals[i] else float(grid[i])


def check_pupil_model(target, calibrator=None, *, wavelengths, pixscale, pupil="subaru",
                      window=None, rotations=np.arange(-6.0, 6.01, 1.5) * u.deg,
                      scales=np.arange(0.97, 1.0301, 0.01), cuts=(0.05, 0.1, 0.2, 0.3, 0.5),
                      binary=True, steps=None, centroid="com", pupil_scale=None,
                      progress=False):
    """Fit the pupil model's orientation and scale to a star's frames and compare models.

    Parameters
    ----------
    target : array-like, shape (nframe, nwave, ny, nx) or (nframe, ny, nx)
        Frames of a star without a known companion.
    calibrator : array-like, optional
        Frames of another such star. Without, the two halves of *target*
        are compared (first against second).
    wavelengths : `~astropy.units.Quantity` (nwave,)
    pixscale : `~astropy.units.Quantity`
        The pixel scale as known (the fitted factor multiplies it).
    pupil : str
        Telescope name or pupil image (see `~kpifs.model.pupil.make_pupil`); its
        defaults (`~kpifs.model.pupil.MODEL_DEFAULTS`) are the starting model.
    window : `~kpifs.model.window.ExtractionWindow`, optional
    rotations : `~astropy.units.Quantity`
        Coarse grid of model turns (deg).
    scales : array-like
        Coarse grid of pixel-scale factors.
    cuts : sequence of float
        Transmission cuts of grey models to compare.
    binary : bool
        Also compare the binary model (cut 0.9).
    steps : `~astropy.units.Quantity`, optional
        Grid steps to compare (default: only the pupil's).
    centroid : str
        Star-centre method of the extraction.
    pupil_scale : `~astropy.units.Quantity`, optional
        Pixel size (m) of a pupil image *pupil*, overriding its ``PUPSCALE``.
    progress : bool
        Progress on stderr (a bar on a terminal, otherwise a line every few
        seconds with the time left).

    Returns
    -------
    `ModelCheck`

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs.modelcheck import check_pupil_model
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> obs = simulate_scene("paper", n_frames=12, contrasts=0.0, npup=64, seed=2,
    ...                      pupil_rotation=2 * u.deg)
    >>> chk = check_pupil_model(obs.target, obs.calibrator, wavelengths=obs.wavelengths,
    ...                         pixscale=obs.params.pixscale, scales=[1.0], cuts=(0.1,),
    ...                         binary=False)
    >>> bool(abs(chk.rotation.to_value(u.deg) - 2) < 0.5)
    True
    """
    target, calibrator, pair = _pair(target, calibrator)
    wl = np.atleast_1d(to_quantity(wavelengths, u.um, name="wavelengths"))
    ps = to_quantity(pixscale, u.mas, name="pixel scale")
    if target.shape[1] != len(wl) or calibrator.shape[1:] != target.shape[1:]:
        raise KpifsError(f"frames of shapes {target.shape[1:]} and {calibrator.shape[1:]} "
                         f"with {len(wl)} wavelength(s): they must agree")
    defaults = model_defaults(pupil)
    base = dict(grey=defaults.grey, min_transmission=defaults.min_transmission,
                step=defaults.step * u.m, offset=defaults.offset * u.m)
    ev = _Evaluator(pupil, target, calibrator, wl, ps, window, centroid, pupil_scale)
    n_steps = np.size(rotations) + np.size(scales) + len(cuts) + 2 * _REFINE_EVALUATIONS + (
        0 if steps is None else np.size(steps)) + 5
    ev.bar = progress_bar(desc="model check", unit="model", total=n_steps, enabled=progress)

    def model_for(options):
        return KernelModel.from_pupil(make_pupil(pupil, rotation=0 * u.deg,
                                                 pupil_scale=pupil_scale, **options))

    # every model is a few small products: BLAS's threads would only wait for each other
    with ev.bar, one_blas_thread():
        rot, scale = _fit_geometry(ev, model_for(base), rotations, scales, defaults.rotation,
                                   base)
        geo_rot, geo_scale, geo_reason, shape_ok = _geometry_choice(ev, rot, scale,
                                                                    defaults.rotation)
        variants = _variants(base, cuts, binary, steps)
        rows = []
        for opts in variants:
            scan = "step" if opts["step"] != base["step"] else "cut"
            ev(scan, model_for(opts), geo_rot, geo_scale, opts)
            rows.append(ev.rows[-1])
    pick, reason = _model_choice(rows, variants, base, geo_reason, pair)
    chosen = variants[pick]
    recommended = dict(pupil=str(pupil), rotation=geo_rot * u.deg, pixscale=ps * geo_scale,
                       grey=chosen["grey"], min_transmission=chosen["min_transmission"],
                       step=u.Quantity(chosen["step"], u.m), offset=chosen["offset"])
    table = _table(ev.rows)
    table.meta.update(pupil=str(pupil), pair=pair, pixscale_given=str(ps),
                      rotation_deg=rot, scale=scale, amp_noise=ev.floor)
    return ModelCheck(table, rot * u.deg, scale, recommended, reason,
                      meta={"pair": pair, "n_target": len(target),
                            "n_calibrator": len(calibrator), "shape_ok": bool(shape_ok),
                            "amp_noise": ev.floor})


def _pair(target, calibrator):
    """The two sets of frames compared, and their description: a calibrator, or the two
    halves of the target's sequence."""
    target = _frames(target, "target")
    if calibrator is None:
        half = len(target) // 2
        return target[:half], target[half:], "the two halves of the sequence"
    return target, _frames(calibrator, "calibrator"), "target and calibrator"


def _fit_geometry(ev, km, rotations, scales, rot0, base):
    """The model's rotation (deg) and pixel-scale factor fitted to the Fourier amplitudes:
    coarse scans refined, then the rotation refined again at the fitted scale."""
    rot_grid = np.atleast_1d(to_quantity(rotations, u.deg, name="rotations").value)
    scale_grid = np.atleast_1d(np.asarray(scales, float))
    ev("default", km, rot0, 1.0, base)
    rot = _scan_and_refine(lambda r: ev("rotation", km, rot0 + r, 1.0, base), rot_grid, 0.05)
    rot += rot0
    scale = _scan_and_refine(lambda f: ev("scale", km, rot, f, base), scale_grid, 5e-4)
    if len(scale_grid) > 1 and len(rot_grid) > 1:
        span = rot_grid[1] - rot_grid[0]
        rot = _scan_and_refine(lambda r: ev("refine", km, r, scale, base),
                               np.array([rot - span / 2, rot, rot + span / 2]), 0.05)
    ev("fitted", km, rot, scale, base)
    return rot, scale


def _geometry_choice(ev, rot, scale, rot0):
    """The geometry to use (rotation, scale), why, and whether the textbook pupil describes
    the amplitudes. The fitted geometry is trusted when the textbook pupil describes the
    amplitudes to within their noise; otherwise only when the kernel phases agree that it
    is better."""
    fitted, default = ev.rows[-1], ev.rows[0]
    shape_ok = fitted["amp_mismatch"] < SHAPE_TOLERANCE * ev.floor
    better = _significantly_lower(fitted, default)
    geo_rot, geo_scale = (rot, scale) if (shape_ok or better) else (rot0, 1.0)
    if shape_ok:
        reason = (f"rotation and pixel scale fitted to the Fourier amplitudes, which the "
                  f"textbook pupil describes to within their noise (mismatch "
                  f"{fitted['amp_mismatch']:.4f}, noise {ev.floor:.4f})")
    else:
        reason = (f"the textbook pupil does not describe the Fourier amplitudes "
                  f"(mismatch {fitted['amp_mismatch']:.4f} against a noise of "
                  f"{ev.floor:.4f}): the fitted rotation {rot:+.2f} deg and scale "
                  f"{scale:.4f} are indicative, and the calibrated reduced chi2 "
                  f"{fitted['chi2_red']:.2f} against {default['chi2_red']:.2f} for the "
                  f"default geometry "
                  + ("confirms them" if better else "does not confirm them: default kept"))
    return geo_rot, geo_scale, reason, shape_ok


def _variants(base, cuts, binary, steps):
    """The models compared at the chosen geometry: transmission cuts, the binary model,
    grid steps, and the default."""
    variants = [dict(base, min_transmission=c) for c in cuts]
    if binary:
        variants.append(dict(base, grey=False, min_transmission=BINARY_MIN_TRANSMISSION))
    for st in ([] if steps is None else np.atleast_1d(to_quantity(steps, u.m, name="steps"))):
        variants.append(dict(base, step=st))
    if not any(v == base for v in variants):
        variants.append(dict(base))
    return variants


def _model_choice(rows, variants, base, geo_reason, pair):
    """The variant recommended (its index) and the sentence that says why: the default
    unless another is lower by `CHI2_SIGMAS` standard deviations of the difference."""
    chi2 = [r["chi2_red"] for r in rows]
    i_base = next(i for i, v in enumerate(variants) if v == base)
    i_best = int(np.argmin(chi2))
    pick = i_best if _significantly_lower(rows[i_best], rows[i_base]) else i_base

    def kind(o):
        return (f"{'grey' if o['grey'] else 'binary'} cut {o['min_transmission']} step "
                f"{u.Quantity(o['step'], u.m).value:g} m")
    reason = (f"{geo_reason}; between {pair} the {kind(variants[pick])} model gives "
              f"calibrated reduced chi2 {chi2[pick]:.2f}")
    sd = _chi2_difference_sd(rows[i_best], rows[i_base])
    if pick == i_base:
        reason += (f" (the default; the best other, {kind(variants[i_best])}, "
                   f"{chi2[i_best]:.2f}, is not lower by {CHI2_SIGMAS:g} standard deviations "
                   f"of the difference, {CHI2_SIGMAS * sd:.2f})"
                   if i_best != i_base else " (the default, and the lowest)")
    else:
        reason += (f", below the default's {chi2[i_base]:.2f} by "
                   f"{(chi2[i_base] - chi2[pick]) / sd:.1f} standard deviations of the "
                   f"difference")
    return pick, reason


def _table(rows):
    """The evaluations as a table with units."""
    table = QTable(rows=[[r[k] for k in rows[0]] for r in rows], names=list(rows[0]))
    table["rotation"].unit = u.deg
    table["step"] = u.Quantity([u.Quantity(v, u.m).value for v in table["step"]], u.m)
    for name in ("residual", "scatter"):
        table[name].unit = u.rad
    return table
