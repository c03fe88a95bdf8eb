"""Time blocks of a pupil-tracking sequence: calibrated data that keep the field rotation.

In pupil tracking the sky turns on the detector while the pupil and its
aberrations stay put. The mean of a sequence, taken in detector coordinates,
smears a companion fixed on the sky over the arc it swept (issue 29). The
calibrated product therefore also keeps **time blocks** over which the
rotation is small (the blocks of DESIGN.md section 6, one detector angle
``theta_b`` each):

- ``d_b = mean_b(target) - mean(calibrators)``: the block means, each minus
  the calibrators' mean (with the covariance ``Sigma_t / n_b + Sigma_c / N_c``:
  the calibrator term is shared by every block);
- the frames' deviations from their block means (target) and from their mean
  (calibrators): the frame-to-frame noise, from which the blocks' noise is
  modelled at detection (`kpifs.detect.blocks`).

At detection the blocks are split into their weighted mean
``d = sum_b n_b d_b / N`` (today's calibrated product, with its error model,
which carries the calibrator) and the centred block contrasts
``sqrt(n_b) (d_b - d)``: these are free of the calibrator and of anything
fixed on the detector (the angular-differential part), and a companion that
turns with the sky survives in them as ``sqrt(n_b) (s_b - s_mean)`` (its
self-subtraction). The search sums the correlations of both parts.

Examples
--------
>>> import numpy as np
>>> from kpifs.rotation import time_blocks
>>> time_blocks(np.linspace(0, 40, 20), width=5.0).tolist()
[0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3, 4, 4, 4, 5, 5, 5, 6, 6]
"""
import logging
from dataclasses import dataclass

import numpy as np
from astropy import units as u
from astropy.io import fits

from .exceptions import KpifsError
MAS = np.pi / 180 / 3600 / 1000      # one mas in radians (as kpifs.model.kernel.MAS)

__all__ = ["RotationBlocks", "time_blocks", "rotation_blocks", "block_width",
           "rotation_needed", "parallactic_angles", "sequence_angles", "noise_whitening",
           "NOISE_MODES",
           "SITES",
           "rotation_hdus", "rotation_from_hdul", "MIN_BLOCK_FRAMES", "MAX_BLOCKS",
           "BLOCK_FRACTION",
           "MIN_ROTATION_SPAN"]

log = logging.getLogger(__name__)

#: Fewest frames in a time block: a block's own frames show its noise.
MIN_BLOCK_FRAMES = 2

#: Most time blocks: the search's dimension, and its null's cost, grow with their number
#: (longer sequences get longer blocks).
MAX_BLOCKS = 10

#: Largest motion of a companion within one block at the largest separation searched,
#: in finest fringes (``lambda_min / B_max``): its signature loses < 10 % at that edge
#: in the bluest channel's longest baselines, and far less elsewhere.
BLOCK_FRACTION = 0.25

#: Smallest span (deg) of the target's angles for which blocks are kept.
MIN_ROTATION_SPAN = 1.0


@dataclass
class RotationBlocks:
    """Calibrated time blocks of a rotating sequence (see `kpifs.rotation`).

    Attributes
    ----------
    angles : ndarray (B,)
        Mean detector position angle of each block (deg).
    frames : ndarray (B,)
        Target frames in each block, ``n_b``.
    data : ndarray (B, q, p)
        Block means minus the calibrators' mean ``d_b`` (the target's block
        means when there is no calibrator).
    noise : ndarray (m, q, p)
        Frame deviations: the target's from its block means (first
        *n_target_noise* rows), then each calibrator's from its mean.
    n_target_noise : int
    calibrated : bool
        Whether a calibrator was subtracted.
    search : {'rotation', 'angular-differential'}
        How detection searches the blocks by default (`kpifs.detect.blocks`).
    """

    angles: np.ndarray
    frames: np.ndarray
    data: np.ndarray
    noise: np.ndarray
    n_target_noise: int
    calibrated: bool = True
    search: str = "rotation"

    @property
    def n_blocks(self):
        return len(self.angles)

    @property
    def span(self):
        """Span of the blocks' angles (deg)."""
        a = self.angles[0] + (self.angles - self.angles[0] + 180.0) % 360.0 - 180.0
        return float(np.ptp(a))

    def mean(self):
        """The frame-weighted mean of the blocks (the calibrated mean)."""
        return np.tensordot(self.frames / self.frames.sum(), self.data, axes=(0, 0))

    def contrasts(self):
        """``sqrt(n_b) (d_b - d)``: the blocks' departures from their mean (B, q, p)."""
        n = self.frames.astype(float)
        return np.sqrt(n)[:, None, None] * (self.data - self.mean())


def block_width(kpd, max_separation=None, fraction=BLOCK_FRACTION):
    """Widest arc (deg) of one block: *fraction* of the finest fringe at *max_separation*.

    The default separation is the one a search reaches (the extraction window's
    radius, within the pupil grid's aliasing limit).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.rotation import block_width
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> kpd = KernelPhaseData(np.zeros((1, 1, km.n_kp)), [1.6] * u.um, 10 * u.mas, km)
    >>> round(block_width(kpd, 200 * u.mas), 2)
    3.1
    """
    lam = kpd.wavelengths.to_value(u.m).min()
    bmax = kpd.kernel_model.baseline_length.to_value(u.m).max()
    if max_separation is None:
        far = np.inf
        step = kpd.kernel_model.pupil.step
        if step is not None:
            far = 0.95 * lam / (2 * step.to_value(u.m)) / MAS
        if kpd.window is not None:
            far = min(far, kpd.window.radius * kpd.pixscale.to_value(u.mas))
        if not np.isfinite(far):
            far = 20 * lam / bmax / MAS
    else:
        far = u.Quantity(max_separation, u.mas).value
    return float(np.rad2deg(fraction * lam / bmax / MAS / far))


def time_blocks(detpa, *, width, min_frames=MIN_BLOCK_FRAMES):
    """Consecutive frames grouped into blocks spanning at most *width* deg.

    A block closes when the next frame's angle is more than *width* from the
    block's first; blocks of fewer than *min_frames* frames are merged with
    their smaller neighbour. Returns one block index per frame.
    """
    a = np.asarray(detpa, float)
    a = a[0] + np.unwrap(np.deg2rad(a - a[0]), period=2 * np.pi) * 180 / np.pi
    labels = np.zeros(a.size, int)
    start, b = a[0], 0
    for i in range(1, a.size):
        if abs(a[i] - start) > width:
            b, start = b + 1, a[i]
        labels[i] = b
    counts = np.bincount(labels)
    while counts.size > 1 and counts.min() < min_frames:
        k = int(np.argmin(counts))
        # with the smaller neighbour: short blocks pair up instead of piling onto one
        nbr = [j for j in (k - 1, k + 1) if 0 <= j < counts.size]
        labels[labels == k] = min(nbr, key=lambda j: counts[j])
        _, labels = np.unique(labels, return_inverse=True)
        counts = np.bincount(labels)
    return labels


def rotation_blocks(target, calibrators=(), *, width=None, min_frames=MIN_BLOCK_FRAMES):
    """`RotationBlocks` of a target's frames (minus the calibrators' mean), or None.

    None when the target's angles are unknown, span less than
    `MIN_ROTATION_SPAN`, or allow a single block.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.rotation import rotation_blocks
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> rng = np.random.default_rng(0)
    >>> t = KernelPhaseData(rng.normal(0, 0.1, (12, 1, km.n_kp)), [1.6] * u.um, 10 * u.mas,
    ...                     km, detpa=np.linspace(0, 33, 12))
    >>> c = KernelPhaseData(rng.normal(0, 0.1, (12, 1, km.n_kp)), [1.6] * u.um, 10 * u.mas, km)
    >>> rb = rotation_blocks(t, [c], width=6.0)
    >>> rb.frames.tolist(), rb.noise.shape
    ([3, 3, 3, 3], (24, 1, 37))
    """
    if target.detpa is None or not np.all(np.isfinite(target.detpa)):
        return None
    a = np.asarray(target.detpa, float)
    a = a[0] + np.unwrap(np.deg2rad(a - a[0]), period=2 * np.pi) * 180 / np.pi
    if np.ptp(a) < MIN_ROTATION_SPAN or target.n_frame < 2 * min_frames:
        return None
    width = block_width(target) if width is None else float(width)
    min_frames = max(min_frames, int(np.ceil(target.n_frame / MAX_BLOCKS)))
    labels = time_blocks(a, width=width, min_frames=min_frames)
    nb = labels.max() + 1
    if nb < 2:
        return None
    frames = np.bincount(labels)
    means = np.stack([target.kp[labels == b].mean(axis=0) for b in range(nb)])
    angles = np.array([a[labels == b].mean() for b in range(nb)])
    cal = np.mean([c.kp.mean(axis=0) for c in calibrators], axis=0) if calibrators else 0.0
    noise = [target.kp - means[labels]]
    noise += [c.kp - c.kp.mean(axis=0) for c in calibrators]
    log.info("%s: %d time blocks of %s frames over %.1f deg of rotation (at most %.2f deg "
             "each)", target.meta.get("source", "target"), nb, frames.tolist(), np.ptp(a),
             width)
    return RotationBlocks(angles, frames, means - cal, np.concatenate(noise), target.n_frame,
                          calibrated=bool(calibrators))


#: Modes of the frames' noise that whiten the blocks, as a fraction of its degrees of
#: freedom (the error model's default, `kpifs.calibration.errormodel`).
NOISE_MODES = 0.5

#: Folds of the cross-validated variances of `noise_whitening`.
NOISE_FOLDS = 5


def noise_whitening(blocks, *, fraction=NOISE_MODES):
    """Whitening of one frame's noise in its leading modes, per channel: (q, K, p).

    The modes are the leading ones of the frames' deviations (``blocks.noise``:
    the target's within its blocks, which hold none of a companion's turning,
    then the calibrators'); *fraction* of their degrees of freedom are kept.
    The variance along each mode is cross-validated: measured on frames the
    modes were not taken from (held-out time blocks), since a sample's own
    leading modes overstate its variance along them. Row ``k`` of channel
    ``i`` is ``v_k / sqrt(var_k)``: ``sqrt(n_b) C (d_b - d)`` has unit variance.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.rotation import RotationBlocks, noise_whitening
    >>> rng = np.random.default_rng(0)
    >>> rb = RotationBlocks(np.arange(6.0), np.full(6, 4), np.zeros((6, 1, 30)),
    ...                     rng.normal(0, 2.0, (24, 1, 30)), 24)
    >>> c = noise_whitening(rb)
    >>> c.shape, bool(0.3 < np.mean(np.linalg.norm(c, axis=-1)) < 0.7)   # 1 / sigma
    ((1, 9, 30), True)
    """
    noise = np.asarray(blocks.noise, float)
    nt = blocks.n_target_noise
    labels = np.repeat(np.arange(blocks.n_blocks), blocks.frames.astype(int))
    if labels.size != nt:
        raise KpifsError(f"{blocks.frames.sum()} frames in the blocks, {nt} target noise rows")
    ncal = len(noise) - nt
    # time groups: the target's blocks, then the calibrators' frames in runs of ~ a block
    groups = np.concatenate([labels, blocks.n_blocks + np.arange(ncal) // max(
        1, int(np.ceil(ncal / max(blocks.n_blocks, 1))))])
    dof = (nt - blocks.n_blocks) + max(ncal - 1, 0)
    k = max(1, min(int(round(fraction * dof)), noise.shape[2]))
    uniq = np.unique(groups)
    folds = np.array_split(uniq, min(NOISE_FOLDS, uniq.size))
    q, p = noise.shape[1:]
    out = np.zeros((q, k, p))
    for i in range(q):
        vt = _leading_modes(noise[:, i], k)
        var = np.zeros(k)
        for fold in folds:
            held = np.isin(groups, fold)
            vf = _leading_modes(noise[~held, i], k)
            var += np.sum((noise[held, i] @ vf.T) ** 2, axis=0)
        # nu / (nu - 2): the mean of 1 / (a variance estimated from nu squares) is that
        # much larger than 1 / the variance (on CHARIS simulations without it the
        # blocks' whitened energy was 1.12-1.15 of its dof)
        var = var / max(dof - 2, 1)
        good = var > 1e-12 * max(var.max(), 1e-300)
        out[i, good] = vt[good] / np.sqrt(var[good])[:, None]
    return out


def _leading_modes(a, k):
    """The *k* leading right singular vectors of *a* (n, p) as rows (k, p), from the
    eigenvectors of its n x n Gram matrix (few frames, many kernel phases: several
    times faster than an SVD); rows beyond its rank are zero."""
    vals, vecs = np.linalg.eigh(a @ a.T)
    order = np.argsort(vals)[::-1][:k]
    vals, vecs = vals[order], vecs[:, order]
    ok = vals > 1e-12 * max(vals[0], 1e-300)
    out = np.zeros((k, a.shape[1]))
    out[:len(vals)][ok] = (vecs[:, ok].T @ a) / np.sqrt(vals[ok])[:, None]
    return out


_HDUS = ("KP-ROTBLK", "KP-ROTNOISE")


def rotation_hdus(kpd):
    """KP-ROTBLK (block data, with each block's angle and frames) and KP-ROTNOISE.

    Empty when *kpd* carries no `RotationBlocks` (``kpd.rotation``).
    """
    rb = getattr(kpd, "rotation", None)
    if rb is None:
        return []
    h = fits.ImageHDU(np.asarray(rb.data, float), name=_HDUS[0])
    h.header["BUNIT"] = "rad"
    h.header["NBLOCK"] = (rb.n_blocks, "time blocks of small rotation")
    h.header["BLKCAL"] = (bool(rb.calibrated), "calibrators' mean subtracted")
    h.header["BLKSRCH"] = (rb.search, "how the blocks are searched")
    for b, (ang, n) in enumerate(zip(rb.angles, rb.frames)):
        h.header[f"BLKPA{b}"] = (round(float(ang), 6), "[deg] detector angle")
        h.header[f"BLKNF{b}"] = (int(n), "target frames")
    h.header["COMMENT"] = "calibrated time-block means (nblock, nwave, nkp)"
    hn = fits.ImageHDU(np.asarray(rb.noise, float), name=_HDUS[1])
    hn.header["BUNIT"] = "rad"
    hn.header["NTARGET"] = (int(rb.n_target_noise), "first rows: the target's")
    hn.header["COMMENT"] = "frame deviations from block (target) or star (calibrator) means"
    return [h, hn]


def rotation_from_hdul(hdul, source="<file>"):
    """The `RotationBlocks` stored by `rotation_hdus`, or None."""
    if _HDUS[0] not in hdul or _HDUS[1] not in hdul:
        return None
    h, hn = hdul[_HDUS[0]], hdul[_HDUS[1]]
    try:
        nb = int(h.header["NBLOCK"])
        angles = np.array([float(h.header[f"BLKPA{b}"]) for b in range(nb)])
        frames = np.array([int(h.header[f"BLKNF{b}"]) for b in range(nb)])
        data, noise = np.array(h.data, float), np.array(hn.data, float)
        ntgt = int(hn.header["NTARGET"])
    except (KeyError, ValueError, TypeError) as exc:
        raise KpifsError(f"{source}: {_HDUS[0]}/{_HDUS[1]} unreadable ({exc})") from None
    if data.ndim != 3 or data.shape[0] != nb or noise.ndim != 3 \
            or noise.shape[1:] != data.shape[1:]:
        raise KpifsError(f"{source}: {_HDUS[0]} of shape {data.shape} and {_HDUS[1]} of shape "
                         f"{noise.shape} do not match {nb} blocks")
    search = str(h.header.get("BLKSRCH", "rotation"))
    if search not in ("rotation", "angular-differential"):
        raise KpifsError(f"{source}: unknown block search BLKSRCH = {search!r}")
    return RotationBlocks(angles, frames, data, noise, ntgt,
                          calibrated=bool(h.header.get("BLKCAL", True)), search=search)


def rotation_needed(separation, wavelength, diameter, *, fraction=1.0):
    """Rotation (deg) over which a companion at *separation* moves *fraction* x lambda/D.

    An angular-differential search keeps a companion only in so far as it moves
    between blocks: over an arc of ``lambda / D`` about half its signal
    survives the removal of what stays fixed on the detector (the classical ADI
    rule of thumb; `kpifs.detect.blocks` computes the exact fraction).

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs.rotation import rotation_needed
    >>> round(rotation_needed(150 * u.mas, 1.6 * u.um, 7.92 * u.m), 1)
    15.9
    """
    lam_d = u.Quantity(wavelength, u.m).value / u.Quantity(diameter, u.m).value / MAS
    return float(np.rad2deg(fraction * lam_d / u.Quantity(separation, u.mas).value))


def parallactic_angles(hour_angle, declination, latitude):
    """Parallactic angle (deg) of a star at *hour_angle*, *declination*, from *latitude*.

    ``q = atan2(sin H, tan(phi) cos(delta) - sin(delta) cos(H))`` (e.g. Meeus,
    Astronomical Algorithms, eq. 14.1): the angle at the star from the
    direction of the celestial pole to that of the zenith, East positive.

    Parameters
    ----------
    hour_angle : `~astropy.units.Quantity` (angle or time: 1 h = 15 deg)
    declination, latitude : `~astropy.units.Quantity` (angle)

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs.rotation import parallactic_angles
    >>> parallactic_angles([-1, 0, 1] * u.hourangle, -20 * u.deg, 19.8 * u.deg).round(1)
    array([-21.2,   0. ,  21.2])
    """
    h = u.Quantity(hour_angle)
    h = h.to_value(u.h) * np.pi / 12 if h.unit.physical_type == "time" else h.to_value(u.rad)
    d = u.Quantity(declination, u.deg).to_value(u.rad)
    phi = u.Quantity(latitude, u.deg).to_value(u.rad)
    return np.rad2deg(np.arctan2(np.sin(h), np.tan(phi) * np.cos(d) - np.sin(d) * np.cos(h)))


#: Latitudes (deg) of observatories (for `sequence_angles`): Maunakea (Subaru: CHARIS),
#: Cerro Paranal (VLT: SPHERE), Cerro Pachon (Gemini South: GPI), Palomar (PHARO).
SITES = {"maunakea": 19.8255, "paranal": -24.6272, "pachon": -30.2407, "palomar": 33.3563}


def sequence_angles(n_frames, *, span=None, hour_angle=None, declination=None,
                    latitude=None, start=0.0):
    """Detector angles (deg) of a pupil-tracking sequence of *n_frames*.

    Either a plain *span* (deg) from *start*, or the parallactic angles from
    *hour_angle* = (start, end) (`~astropy.units.Quantity`, e.g. ``[-1, 1] * u.hourangle``)
    of a star at *declination* seen from *latitude* (a Quantity or a name in
    `SITES`), plus *start* (the instrument's offset: the detector angle at
    parallactic angle 0).

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs.rotation import sequence_angles
    >>> sequence_angles(3, span=40.0, start=100.0).tolist()
    [100.0, 120.0, 140.0]
    >>> sequence_angles(3, hour_angle=[-0.5, 0.5] * u.hourangle, declination=-20 * u.deg,
    ...                 latitude="maunakea").round(1).tolist()
    [-10.9, 0.0, 10.9]
    """
    if n_frames < 1:
        raise KpifsError("a sequence needs at least one frame")
    if (span is None) == (hour_angle is None):
        raise KpifsError("give either a rotation span or hour angles (with a declination "
                         "and a site)")
    if span is not None:
        return start + np.linspace(0.0, u.Quantity(span, u.deg).value, n_frames)
    if declination is None or latitude is None:
        raise KpifsError("parallactic angles need the star's declination and the site's "
                         "latitude")
    if isinstance(latitude, str):
        if latitude.lower() not in SITES:
            raise KpifsError(f"unknown site {latitude!r}: use one of {sorted(SITES)} or a "
                             f"latitude")
        latitude = SITES[latitude.lower()] * u.deg
    h = u.Quantity(hour_angle)
    if h.shape != (2,):
        raise KpifsError(f"hour angles: give the start and the end, got {hour_angle!r}")
    h = h.to(u.hourangle) if h.unit.physical_type != "time" else h.to_value(u.h) * u.hourangle
    q = parallactic_angles(np.linspace(h[0], h[1], n_frames), declination, latitude)
    q = q[0] + np.unwrap(np.deg2rad(q - q[0])) * 180 / np.pi        # continuous through 180
    return start + q


def _span(kpd):
    """Span (deg) of a data set's frame angles, 0 when unknown."""
    if kpd.detpa is None or not np.all(np.isfinite(kpd.detpa)):
        return 0.0
    a = np.asarray(kpd.detpa, float)
    return float(np.ptp(a[0] + np.unwrap(np.deg2rad(a - a[0])) * 180 / np.pi))
