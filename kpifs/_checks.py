"""Checks made before any work: inputs given twice or as outputs, searches too large for
the memory, data that no search can use. Reached through `kpifs.workflow` and the
command line; every refusal is a one-line `~kpifs.KpifsError` naming the file or the
option."""
import os
import warnings
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.io import fits

from ._memory import available_memory, check_memory  # noqa: F401  (kpifs._checks.*)
from .data import KernelPhaseData
from .exceptions import KpifsError, KpifsWarning
from .io.readers import observing_setup, setup_differences

__all__ = []

#: Milliarcseconds per radian.
_MAS = np.pi / 180 / 3600e3


def _real(path):
    return os.path.realpath(os.fspath(path))


def check_inputs(target, calibrators=(), *, outputs=()):
    """Refuse a target file given twice, a calibrator that is a target file, and an output
    that is an input (all compared by real path: symbolic links and ``./`` included).

    *target* is a list of files, *calibrators* a list of such lists.
    """
    target = [os.fspath(f) for f in target]
    seen = {}
    for f in target:
        r = _real(f)
        if r in seen:
            same = "" if seen[r] == f else f" (the same file as {seen[r]})"
            raise KpifsError(f"{f}: given twice as a target file{same}: its frames would "
                             f"count twice and the noise would look smaller than it is")
        seen[r] = f
    cal_seen = {}
    for files in calibrators:
        for f in files:
            r = _real(os.fspath(f))
            if r in seen:
                what = ("given as the target and as its calibrator" if seen[r] == f else
                        f"the calibrator is the target file {seen[r]}")
                raise KpifsError(f"{f}: {what}: a star cannot be its own calibrator")
            if r in cal_seen:
                raise KpifsError(f"{f}: given twice as a calibrator file: its frames would "
                                 f"count twice")
            cal_seen[r] = f
    inputs = {_real(os.fspath(f)): os.fspath(f)
              for f in target + [g for files in calibrators for g in files]}
    for out in outputs:
        if out is not None and _real(out) in inputs:
            raise KpifsError(f"{out}: refusing to overwrite an input file "
                             f"({inputs[_real(out)]})")


def check_same_setup(target, calibrator):
    """Refuse a calibrator observed in another set-up than its target (another instrument,
    filter, pupil element or mask, band or mode: `kpifs.io.readers.observing_setup` of
    their headers), naming both. *target* and *calibrator* are
    `~kpifs.data.KernelPhaseData` (their ``header`` is their cube's) or headers.

    Called where a target and its calibrator meet (`kpifs.calibration.calibrate.check_compatible`):
    every command and the Python API go through it.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs._checks import check_same_setup
    >>> from kpifs.exceptions import KpifsError
    >>> t = fits.Header({"INSTRUME": "NIRISS", "FILTER": "F480M", "PUPIL": "CLEARP"})
    >>> c = fits.Header({"INSTRUME": "NIRISS", "FILTER": "F480M", "PUPIL": "NRM"})
    >>> try:
    ...     check_same_setup(t, c)
    ... except KpifsError as err:
    ...     print(str(err).split(": a calibrator")[0])
    calibrator: pupil element NRM, but the target: CLEARP
    """
    def facts(x):
        if isinstance(x, fits.Header):
            return "", observing_setup(x)
        return f" {x.meta.get('source', getattr(x, 'name', '?'))}", observing_setup(x.header)
    tname, tset = facts(target)
    cname, cset = facts(calibrator)
    diff = setup_differences(tset, cset)
    if diff:
        raise KpifsError(f"calibrator{cname}: " + ", ".join(f"{k} {c}" for k, _, c in diff)
                         + f", but the target{tname}: " + ", ".join(f"{t}" for _, t, _ in diff)
                         + ": a calibrator must be observed through its target's instrument, "
                           "filter and pupil (its kernel phases are of another pupil)")


def check_seed(seed, option="--seed"):
    """Refuse a seed numpy cannot take (negative, not a whole number)."""
    if seed is None:
        return
    if isinstance(seed, np.random.Generator):
        return
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) \
            or seed < 0:
        raise KpifsError(f"{option} must be a whole number >= 0, got {seed!r}")


def check_draws_memory(n_draws, option="--draws"):
    """The null's maxima: a few float64 per draw and per form of the statistic."""
    check_memory(32.0 * float(n_draws), f"{option} {n_draws:g}",
                 "use fewer draws (5000 read through the fitted tail resolve P_FA 1e-3)")


def grid_size(kpd, *, step=None, max_sep=None):
    """Side of the square search grid `kpifs.detect.default_grid` would make (positions
    along one axis), without making it."""
    km = kpd.kernel_model
    lam_min = kpd.wavelengths.to_value(u.m).min()
    diam = float(np.max(np.hypot(*km.uv.to_value(u.m).T)))
    res = lam_min / diam / _MAS
    if max_sep is None:
        limit = np.inf
        if km.pupil is not None and km.pupil.step is not None:
            limit = 0.95 * lam_min / (2 * km.pupil.step.to_value(u.m)) / _MAS
        if kpd.window is not None:
            limit = min(limit, kpd.window.radius * kpd.pixscale.to_value(u.mas))
        max_sep = limit if np.isfinite(limit) else 100 * res
    step = res / 4 if step is None else step
    if not (step > 0 and np.isfinite(max_sep)):
        return 1
    return 2 * int(np.floor(min(max_sep / step, 1e12))) + 1


def check_grid_memory(kpd, *, step=None, max_sep=None):
    """Refuse a search grid too large for the memory: per position, the maps and their
    channels (statistic, P_FA, contrasts and errors, limits; float64)."""
    n = grid_size(kpd, step=None if step is None else step.to_value(u.mas),
                  max_sep=None if max_sep is None else max_sep.to_value(u.mas))
    q = kpd.n_wave
    nbytes = 8.0 * n * n * (6 * q + 16) + 8.0 * n * kpd.kernel_model.n_uv * q * 4
    what = (f"--grid-step {step}" if step is not None else f"--max-sep {max_sep}")
    check_memory(nbytes, f"{what}: a search grid of {n} x {n} positions",
                 "give a coarser --grid-step or a smaller --max-sep")


def check_kernel_phase_data(kpd):
    """Refuse kernel-phase data with NaN or infinite values where a search needs numbers,
    naming the file and the extension."""
    for attr, ext in (("kp", "KP-DATA"), ("covariance", "KP-COV"),
                      ("covariance_rows", "KP-COVROWS"), ("fit_covariance_rows", "KP-FITROWS"),
                      ("block_rows", "KP-BLKROWS"), ("joint_covariance", "KP-JCOV")):
        a = getattr(kpd, attr, None)
        if a is None:
            continue
        bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
        if bad and (attr != "kp" or kpd.n_frame == 1):
            raise KpifsError(f"{kpd.name}: {ext} has {bad} NaN or infinite value(s) of "
                             f"{np.size(a)}: a search cannot use them")


def check_covariance(kpd):
    """Refuse a stored covariance that is not one (a negative eigenvalue), naming the file."""
    cov = kpd.covariance
    if cov is None or kpd.n_frame != 1 or kpd.covariance_rows is not None:
        return
    cov = np.asarray(cov, float)
    vals = np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    top = vals.max(axis=-1)
    low = vals.min(axis=-1)
    bad = np.flatnonzero((top <= 0) | (low < -1e-8 * np.abs(top)))
    if bad.size:
        i = int(bad[0])
        raise KpifsError(f"{kpd.name}: KP-COV is not a covariance at channel {i + 1} "
                         f"({kpd.wavelengths[i].to_value(u.um):.4f} um): it has negative "
                         f"eigenvalues (smallest {low[i]:.3g}, largest {top[i]:.3g})")


def peek_kpfits(path):
    """``(calibrated, has_angles)`` from the headers of a KPFITS file kpifs wrote (nothing
    else read), or None for other files (the full reader checks those and says why)."""
    try:
        with fits.open(path, memmap=True, lazy_load_hdus=True) as hdul:
            hdr = hdul[0].header
            names = [h.name for h in hdul]
            if "KP-DATA" not in names or not str(hdr.get("PROCSOFT", "")).startswith("kpifs"):
                return None
            flag = hdr.get("CALFLAG", False)
            calibrated = flag if isinstance(flag, bool) else \
                str(flag).strip().upper() in ("T", "TRUE", "1", "YES")
            angles = None
            if "DETPA" in names and hdul["DETPA"].is_image and hdul["DETPA"].data is not None:
                angles = bool(np.all(np.isfinite(np.asarray(hdul["DETPA"].data, float))))
            elif not any(n in names for n in ("TEL", "DETPA")) and not any(
                    n.startswith("KP-INFO") for n in names):
                angles = any(isinstance(hdr.get(k), (int, float)) and not isinstance(
                    hdr.get(k), bool) and np.isfinite(hdr[k]) for k in ("DETPA", "ORIENTAT"))
            return calibrated, angles
    except Exception:  # unreadable here: the full reader names the problem
        return None


def preflight_detect(kp, calibrators, output, options):
    """What ``kpifs detect`` refuses, checked on the files' headers before reading them."""
    calibrators = list(calibrators or [])
    check_inputs([kp], [[c] for c in calibrators], outputs=[output])
    for f in [kp] + calibrators:
        if not Path(f).is_file():
            return                                # the reader says "file not found"
    first = peek_kpfits(kp)
    if first is None:
        return
    calibrated, angles = first
    if calibrated and calibrators:
        raise KpifsError(f"{kp}: already calibrated (CALFLAG true): calibrating it again "
                         f"subtracts a star twice; give it without --calibrator")
    hdr = fits.getheader(kp) if not calibrated else {}
    if not calibrated and not calibrators and not options.allow_uncalibrated \
            and hdr.get("BLKSRCH") != "angular-differential" \
            and "SDKNPROF" not in hdr:                            # issues 29 and 39
        raise KpifsError(f"{kp}: not calibrated (no calibrator star subtracted): give its "
                         f"calibrator (--calibrator CALIBRATOR_KP.fits), or --allow-uncalibrated "
                         f"to search the data as they are")
    for c in calibrators:
        peek = peek_kpfits(c)
        if peek is not None and peek[0]:
            raise KpifsError(f"calibrator {c}: already calibrated (CALFLAG true): a "
                             f"calibrator must be a star's own kernel phases")
    if options.frame == "sky" and angles is False:
        raise KpifsError(f"{kp}: --frame sky needs the detector position angle of every "
                         f"frame (DETPA); search on the detector, or extract with --pa")


def drop_dead_channels(bad, kp, centres, wavelengths, phases, amplitudes, *, source):
    """Leave out the channels unusable in every frame (a dead channel) while others are
    not, with a warning naming them; the arrays' channel axis is 1. Returns the arrays
    and the list of channels dropped."""
    dead = np.flatnonzero((bad != "").all(axis=0))
    if len(dead) in (0, bad.shape[1]):
        return bad, kp, centres, wavelengths, phases, amplitudes, []
    which = ", ".join(f"{i} ({wavelengths[i].to_value(u.um):.3f} um: {bad[0, i]})"
                      for i in dead)
    warnings.warn(f"{source}: {len(dead)} dead channel(s) of {bad.shape[1]} dropped (unusable "
                  f"in every frame): channel(s) {which}", KpifsWarning, stacklevel=3)
    live = np.setdiff1d(np.arange(bad.shape[1]), dead)
    pick = [None if a is None else a[:, live] for a in (bad, kp, centres, phases, amplitudes)]
    return (pick[0], pick[1], pick[2], wavelengths[live], pick[3], pick[4],
            [int(i) for i in dead])


def match_dead_channels(target, calibrators):
    """When a star's extraction dropped dead channels (``meta['dropped_channels']``), the
    other stars' same channels are left out too (with a warning), so that calibration
    compares like with like; anything else is left to
    `~kpifs.calibration.calibrate.check_compatible`."""
    stars = [target] + list(calibrators)
    if not any(k.meta.get("dropped_channels") for k in stars):
        return target, list(calibrators)
    common = [w for w in target.wavelengths.to_value(u.um)
              if all(np.any(np.isclose(k.wavelengths.to_value(u.um), w, rtol=1e-6))
                     for k in stars)]
    if not common:
        return target, list(calibrators)
    out = []
    for k in stars:
        wl = k.wavelengths.to_value(u.um)
        keep = [int(np.argmin(np.abs(wl - w))) for w in common]
        if len(keep) == k.n_wave:
            out.append(k)
            continue
        gone = ", ".join(f"{v:.3f} um" for v in np.delete(wl, keep))
        warnings.warn(f"{k.name}: channel(s) {gone} left out: dead in another star of the "
                      f"calibration", KpifsWarning, stacklevel=3)
        out.append(KernelPhaseData(k.kp[:, keep], k.wavelengths[keep], k.pixscale,
                                   k.kernel_model, window=k.window, header=k.header,
                                   detpa=k.detpa, meta=dict(k.meta),
                                   bandwidth=k.bandwidth if np.ndim(k.bandwidth) == 0
                                   else k.bandwidth[keep]))
    return out[0], out[1:]
