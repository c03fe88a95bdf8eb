"""Refit detected companions on the sky with the per-frame rotation of the model.

When the target's frames were taken at several detector angles (their angles
reach detection as ``kpd.meta['detpa_frames']``, set by
`~kpifs.calibration.calibrate.calibrate`), the candidates' sky offsets are refitted with
the mean of the per-frame models (`kpifs.detect.sky`) instead of being rotated
from the detector fit by the mean angle.
"""
import logging

import numpy as np
from astropy import units as u

from .fit import fit_binary
from .sky import detector_to_sky, mean_angle, pa_bins, separation_pa

__all__ = ["refit_on_sky"]

log = logging.getLogger(__name__)


def refit_on_sky(cands, kp, whitening, kpd, *, noise_rows=None, min_span=0.0):
    """Replace the sky columns of fitted candidates by a fit of the rotating model.

    Parameters
    ----------
    cands : `~astropy.table.QTable`
        Candidates with ``fit_x``, ``fit_y``, ``fit_contrast`` and the sky
        columns of `~kpifs.detect.sky.add_sky_columns`; changed in place.
    kp, whitening : ndarray
        The searched kernel phases ``(q, p)`` and whitening ``(q, p, p)``.
    kpd : `~kpifs.KernelPhaseData`
        The data; their ``meta['detpa_frames']`` are the frames' angles.
    noise_rows : ndarray, optional
        As in `~kpifs.detect.fit.fit_binary`.
    min_span : float
        Angles spanning at most this (deg) are left to the rotated detector fit.

    Returns
    -------
    bool
        Whether the candidates were refitted.
    """
    frames = kpd.meta.get("detpa_frames")
    if not len(cands) or frames is None or "fit_x" not in cands.colnames:
        return False
    frames = np.asarray(frames, float)
    frames = frames[np.isfinite(frames)]
    if frames.size < 2:
        return False
    centre = mean_angle(frames)
    dev = (frames - centre + 180.0) % 360.0 - 180.0
    if np.ptp(dev) <= min_span:
        return False
    sep = u.Quantity(cands["fit_separation"], u.mas).value
    ang, aw = pa_bins(frames, max_separation=1.5 * float(sep.max()) * u.mas,
                      wavelength_min=kpd.wavelengths.min(),
                      baseline_max=kpd.kernel_model.baseline_length.max())
    log.info("refitting %d candidate(s) on the sky over %d position-angle bins "
             "(%d frames spanning %.1f deg)", len(cands), ang.size, frames.size, np.ptp(dev))
    keys = ("fit_dra", "fit_ddec", "fit_dra_err", "fit_ddec_err", "fit_separation",
            "fit_pa_sky", "fit_pa_sky_err")
    cols = {k: [] for k in keys}
    for row in cands:
        # the detector fit of smeared data can be off by up to the arc swept
        box = 20.0 + row["fit_separation"].to_value(u.mas) * np.deg2rad(np.ptp(dev))
        start = detector_to_sky(row["fit_x"].to_value(u.mas), row["fit_y"].to_value(u.mas),
                                centre)
        r = fit_binary(kp, whitening, kpd.kernel_model, kpd.wavelengths,
                       tuple(float(v) for v in start), np.asarray(row["fit_contrast"]),
                       pixscale=kpd.pixscale, window=kpd.window, bounds_mas=box,
                       noise_rows=noise_rows, detpa=ang, detpa_weights=aw)
        s, pa = separation_pa(r["x"], r["y"])
        perp = np.hypot(r["y"] * r["x_err"], r["x"] * r["y_err"]) / max(s, 1e-12)
        for k, v in zip(keys, (r["x"], r["y"], r["x_err"], r["y_err"], s, pa,
                               np.rad2deg(perp / max(s, 1e-12)))):
            cols[k].append(float(v))
    for k in keys:
        cands[k] = np.array(cols[k]) * (u.deg if "pa_sky" in k else u.mas)
    cands.meta["sky_fit"] = (f"rotating model: {frames.size} frames in {ang.size} "
                             f"position-angle bins")
    return True
