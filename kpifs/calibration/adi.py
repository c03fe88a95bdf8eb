"""Angular-differential kernel phases: only what turns with the sky is searched (issue 29).

In a pupil-tracking sequence whatever stays fixed on the detector (the static
aberrations, the calibrator's mismatch) cancels in the departures of the time
blocks from their mean, while a companion turns with the sky and survives, minus
a self-subtraction (`kpifs.rotation`, `kpifs.detect.blocks`; Laugier et al. 2020
for angular-differential kernel phase).
"""
import logging
import warnings

import numpy as np
from astropy import units as u

from ..data import KernelPhaseData
from ..exceptions import KpifsError, KpifsWarning
from ..rotation import (NOISE_MODES, _span, noise_whitening, rotation_blocks,
                        rotation_needed)

__all__ = ["angular_differential", "target_blocks", "inner_separation"]

log = logging.getLogger(__name__)


def angular_differential(target, calibrated=None, *, n_modes=NOISE_MODES):
    """A product searched by the blocks' departures only (``kpifs extract
    --angular-differential``).

    With *calibrated* (the target calibrated by `~kpifs.calibration.calibrate.calibrate`) its
    blocks are marked for the angular-differential search (the target's own
    spectral-differential product, `~kpifs.calibration.spectral_diff.spectral_differential`
    with no calibrator, gets the target's blocks: ASDI, searched by its channel
    combinations' mean and blocks), which then keeps the
    calibrated mean too, scaled by its own reduced chi-square (a static
    target-calibrator difference is in the mean alone; where the rotation moves
    a companion little, the calibrator still finds it); without, the
    target's own frames make the product: their mean (searched not at all), a
    covariance on the leading *n_modes* (fraction of the degrees of freedom
    within the blocks) modes of the frames' scatter within their blocks, and
    the blocks. Refused when the target's angles do not turn.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.calibration.adi import angular_differential
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> rng = np.random.default_rng(0)
    >>> t = KernelPhaseData(rng.normal(0, 0.1, (24, 1, km.n_kp)), [1.6] * u.um, 10 * u.mas,
    ...                     km, detpa=np.linspace(0, 60, 24))
    >>> adi = angular_differential(t)
    >>> adi.rotation.search, adi.kp.shape, adi.meta["calibrated"]
    ('angular-differential', (1, 1, 37), False)
    """
    name = target.meta.get("source", "target")
    _check_angles_known(target, name)
    if calibrated is not None and getattr(calibrated, "spectral", None) is not None \
            and not calibrated.meta.get("calibrated", True) and calibrated.rotation is None:
        return _with_own_blocks(target, calibrated, target_blocks(target))
    if calibrated is not None:
        if calibrated.rotation is None:
            raise KpifsError(f"{name}: --angular-differential needs frames whose angles turn "
                             f"(span {_span(target):.1f} deg: no time blocks to compare)")
        calibrated.rotation.search = "angular-differential"
        calibrated.meta["block_search"] = "angular-differential"
        return calibrated
    rb = target_blocks(target)
    comp = noise_whitening(rb, fraction=n_modes)                 # rows v_k / sqrt(var_k)
    # the product's covariance (of the frames' mean) on those modes, for its errors
    inv = np.sum(comp ** 2, axis=-1)
    var = np.divide(1.0, inv, out=np.zeros_like(inv), where=inv > 0)
    vec = comp * np.sqrt(var)[..., None]
    cov = np.einsum("ikp,ik,ikq->ipq", vec, var, vec) / target.n_frame
    k = comp.shape[1]
    meta = dict(target.meta)
    meta.update(calibrated=False, block_search="angular-differential",
                n_target_frames=target.n_frame, calibrators=[],
                detpa_frames=[float(v) for v in target.detpa],
                error_model={"model": "frames", "adi_modes": k})
    a = target.detpa
    pa = float(np.rad2deg(np.arctan2(np.sin(np.deg2rad(a)).mean(), np.cos(np.deg2rad(a)).mean())))
    out = KernelPhaseData(target.kp.mean(axis=0)[None], target.wavelengths, target.pixscale,
                          target.kernel_model, window=target.window, covariance=cov,
                          header=target.header, detpa=[pa], bandwidth=target.bandwidth,
                          meta=meta)
    out.rotation = rb
    out.header["BLKSRCH"] = ("angular-differential", "searched by its time blocks only")
    log.info("%s: angular-differential product: %d blocks over %.1f deg, %d modes per channel",
             name, rb.n_blocks, rb.span, k)
    return out


def target_blocks(target):
    """The time blocks of a target's own frames (no calibrator), marked for the
    angular-differential search; refused, saying why, when the frames' angles are not
    known or do not turn.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.calibration.adi import target_blocks
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> t = KernelPhaseData(np.zeros((24, 1, km.n_kp)), [1.6] * u.um, 10 * u.mas, km,
    ...                     detpa=np.linspace(0, 60, 24))
    >>> rb = target_blocks(t)
    >>> rb.search, int(rb.frames.sum())
    ('angular-differential', 24)
    """
    name = target.meta.get("source", "target")
    _check_angles_known(target, name)
    rb = rotation_blocks(target, [])
    if rb is None:
        raise KpifsError(f"{name}: --angular-differential needs frames whose angles turn "
                         f"(span {_span(target):.1f} deg: no time blocks to compare)")
    rb.search = "angular-differential"
    return rb


def _with_own_blocks(target, product, rb):
    """ASDI without a calibrator (issue 39): the target's own spectral-differential product
    (`~kpifs.calibration.spectral_diff.spectral_differential`: the frames' mean, whose
    channel combinations are free of the static profiles, its covariance and rows) with
    the target's time blocks *rb*, searched by the combinations' mean and departures."""
    name = target.meta.get("source", "target")
    product.rotation = rb
    product.meta["block_search"] = "angular-differential"
    product.meta["detpa_frames"] = [float(v) for v in target.detpa]
    product.header["BLKSRCH"] = ("angular-differential", "searched by its time blocks")
    log.info("%s: spectral- and angular-differential product (ASDI): %d blocks over %.1f deg",
             name, rb.n_blocks, rb.span)
    return product


def _check_angles_known(target, name):
    """Refuse frames whose angles are unknown, saying so (issue 37: they were reported as
    "angles do not turn (span 0.0 deg)")."""
    a = None if target.detpa is None else np.asarray(target.detpa, float)
    bad = target.n_frame if a is None else int(np.sum(~np.isfinite(a)))
    if bad:
        where = target.meta.get("detpa_source") or "the header"
        raise KpifsError(f"{name}: --angular-differential needs the detector position angle "
                         f"of every frame: unknown for {bad} of {target.n_frame} ({where}: "
                         f"missing, NaN or 'unavailable'); give them with --pa")


#: An angular-differential search is refused when it keeps less than this fraction of a
#: companion's squared signal even at the grid's largest separations, and warned about
#: when it keeps less than `ADI_WARN` at the smallest.
ADI_REFUSE, ADI_WARN = 0.05, 0.5


def _retained(model):
    """The fraction of a companion's squared signal the rotation keeps, per position."""
    num, den = np.nansum(model.norm2, axis=0), np.nansum(model.norm2_free, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return num / den


def inner_separation(model, *, level=ADI_WARN):
    """The separation (mas) from which the rotation keeps at least *level* of a
    companion's squared signal in every annulus one grid step wide (median over
    the annulus; *model*: the angular-differential
    `~kpifs.detect.blocks.BlockModel`); the grid's own inner edge when it does
    everywhere, NaN when it never does.

    Inside it the companion hardly moves between blocks: what the model keeps
    of its signal is a small difference of large terms, and the search there
    answers to the residual's own structure more than to the noise model
    (measured: the three false alarms of 20 companion-free 40-frame sequences
    over 60 deg all lay within 41 mas, where less than 40 % is kept).

    Examples
    --------
    >>> import warnings
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.calibration.adi import angular_differential
    >>> from kpifs.detect import detect
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1.0 * u.m))
    >>> pa = np.linspace(100.0, 140.0, 16)                  # 40 deg of rotation
    >>> kp = np.random.default_rng(0).normal(0, 0.01, (16, 2, km.n_kp))
    >>> kpd = KernelPhaseData(kp, [1.6, 1.7] * u.um, 10 * u.mas, km, detpa=pa)
    >>> with warnings.catch_warnings():
    ...     warnings.simplefilter("ignore")                 # "keep x % ... at y mas"
    ...     res = detect(angular_differential(kpd), n_draws=1000, limits=False)
    >>> edge = res.meta["blocks"]["inner_separation"]       # where the search starts
    >>> bool(50 < edge < 100), float(res.grid.min_sep) == edge
    (True, True)
    """
    g = model.grid
    frac = _retained(model)
    ok = g.valid & np.isfinite(frac)
    if not ok.any():
        return float("nan")
    step = float(max(abs(g.step[0]), abs(g.step[1])))
    ring = np.floor((g.sep[ok] - g.sep[ok].min()) / step).astype(int)
    med = np.array([np.median(frac[ok][ring == k]) if np.any(ring == k) else np.nan
                    for k in range(ring.max() + 1)])
    low = np.flatnonzero(~(med >= level))
    if not low.size:
        return float(g.sep[ok].min())
    if low[-1] == len(med) - 1:
        return float("nan")
    return float(g.sep[ok].min() + (low[-1] + 1) * step)


def _check_rotation(model, kpd, blocks):
    """The fraction of signal kept by separation (``[[sep, fraction], ...]``, mas), after
    refusing or warning when the rotation is too small for the grid (*model*: the
    angular-differential `~kpifs.detect.blocks.BlockModel`)."""
    g = model.grid
    frac = _retained(model)
    edges = np.linspace(g.sep[g.valid].min(), g.sep[g.valid].max(), 6)
    curve = []
    for a, b in zip(edges[:-1], edges[1:]):
        sel = g.valid & (g.sep >= a) & (g.sep <= b) & np.isfinite(frac)
        if sel.any():
            curve.append([round(float(0.5 * (a + b)), 1), round(float(np.median(frac[sel])), 4)])
    diam = float(np.max(np.hypot(*kpd.kernel_model.uv.value.T)))
    lam = kpd.wavelengths.max()
    need = rotation_needed(curve[0][0] * u.mas, lam, diam * u.m)
    if curve[-1][1] < ADI_REFUSE:
        raise KpifsError(
            f"{kpd.name}: {blocks.span:.1f} deg of rotation keep {100 * curve[-1][1]:.1f} % of a "
            f"companion's signal even at {curve[-1][0]:.0f} mas: an angular-differential search "
            f"cannot find anything (a companion must move about lambda/D between blocks: "
            f"{rotation_needed(curve[-1][0] * u.mas, lam, diam * u.m):.0f} deg at "
            f"{curve[-1][0]:.0f} mas); search with the calibrator instead")
    if curve[0][1] < ADI_WARN:
        inner = next((c[0] for c in curve if c[1] >= ADI_WARN), None)
        warnings.warn(
            f"{kpd.name}: {blocks.span:.1f} deg of rotation keep {100 * curve[0][1]:.0f} % of a "
            f"companion's signal at {curve[0][0]:.0f} mas in the angular-differential search "
            f"(self-subtraction; half of it "
            + (f"from {inner:.0f} mas" if inner else "nowhere on the grid")
            + f"); about {need:.0f} deg are needed there: limits and contrasts account for it",
            KpifsWarning, stacklevel=4)
    return curve
