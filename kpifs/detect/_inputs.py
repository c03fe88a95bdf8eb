"""What a search is given besides the data: the channels it keeps (aliased ones
flagged or left out, `kpifs.model.sampling`), each channel's own kernel phases (filters
as channels), and whether the static-aberration term is added
(`kpifs.simulation.aberrations`)."""
import logging
import warnings

import numpy as np

from .._lazy import lazy_module
from ..exceptions import KpifsError, KpifsWarning
from ..model.sampling import aliased_channels, channel_uv_mask, unmeasured

log = logging.getLogger(__name__)
stats = lazy_module("scipy.stats")


def _wants_static(kpd, static):
    if static not in ("auto", "none"):
        raise KpifsError(f"static must be 'auto' or 'none', got {static!r}")
    adi = getattr(kpd.rotation, "search", None) == "angular-differential"
    # several channels: the residual correlates them, a per-channel term does not model it
    return static == "auto" and not kpd.meta.get("calibrated") and not adi and kpd.n_wave == 1


def _aliased(kpd):
    # interferometric data (OIFITS) have no pixels to alias
    if kpd.meta.get("closure_phases"):
        return np.zeros(kpd.n_wave)
    mask = None
    if kpd.meta.get("channel_n_kp") is not None:
        mask = channel_uv_mask(kpd.kernel_model, kpd.channel_n_kp)
    return aliased_channels(kpd.kernel_model, kpd.wavelengths, kpd.pixscale, uv_mask=mask)


def _measured(kpd, kp, cov):
    """*kp* and *cov* with each channel's rows beyond its own kernel phases (filters as
    channels, `kpifs.model.sampling.nested_kernel`) set to zero: the whitening then leaves them
    out, and a model signature there (a uv point that channel does not sample) is never
    compared with anything."""
    n = kpd.channel_n_kp
    if np.all(n == kpd.n_kp):
        return kp, cov
    q, p = kp.shape
    off = unmeasured(n, p)
    kp = np.where(off, 0.0, kp)
    cov = np.array(cov, float)
    if cov.shape == (q, p, p):
        cov[off[:, :, None] | off[:, None, :]] = 0.0
    else:                                                    # joint (q p, q p)
        flat = off.ravel()
        cov[flat, :] = 0.0
        cov[:, flat] = 0.0
    log.info("%s: channels measure %s of %d kernel phases", kpd.name, n.tolist(), p)
    return kp, cov


def _drop_aliased(kpd, aliased):
    """*kpd* without its aliased channels (``aliased='exclude'``) and the indices kept,
    else *kpd* and None."""
    if aliased not in ("keep", "exclude"):
        raise KpifsError(f"aliased must be 'keep' or 'exclude', got {aliased!r}")
    frac = _aliased(kpd)
    bad = frac > 0
    numbers = list(kpd.meta.get("channels") or range(1, kpd.n_wave + 1))
    if bad.any():
        log.info("%s: channel(s) %s alias %s of their uv points", kpd.name,
                 [numbers[i] for i in np.flatnonzero(bad)],
                 [f"{f:.0%}" for f in frac[bad]])
    if aliased == "keep" or not bad.any():
        return kpd, None
    if bad.all():
        warnings.warn(f"{kpd.name}: every channel aliases some of its uv points (pixels "
                      f"coarser than the pupil needs): none is left out", KpifsWarning,
                      stacklevel=3)
        return kpd, None
    out = kpd.select_channels(~bad)
    out.meta["excluded_channels"] = [numbers[i] for i in np.flatnonzero(bad)]
    return out, np.flatnonzero(~bad)


def _check_closure_dof(kpd, test, rank, n_basis, kp, w):
    """Refuse a search of closure phases with fewer independent values than a companion
    has parameters (its offset and its contrasts, `DetectionTest.n_params
    <kpifs.detect.statistics.DetectionTest.n_params>`: one for NP and E, the spectral
    model's for S, one per channel for B): the grid maximum then fits noise exactly
    (3 telescopes: one closure phase per channel gave candidates at P_FA 1e-15 on
    noise). The refusal answers with the energy test alone (the whitened chi-square
    of the closure phases, which needs no position)."""
    if not kpd.meta.get("closure_phases"):
        return
    q = kpd.n_wave
    params = test.n_params(q, n_basis)
    n = int(np.sum(rank))
    if n >= params:
        return
    energy = float(np.sum(np.einsum("wij,wj->wi", np.asarray(w), np.asarray(kp)) ** 2))
    pfa = float(stats.chi2.sf(energy, n))
    raise KpifsError(f"{kpd.name}: {n} independent closure phase(s) ({kpd.n_kp} per channel "
                     f"x {q} channel(s)) for the {params} parameters of a companion in test "
                     f"{test.name} (its offset and contrasts): no position search is meaningful; "
                     f"the energy test alone: chi2 {energy:.3g} for {n} dof, P_FA {pfa:.2g}")
