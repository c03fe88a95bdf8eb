"""Companions on the sky: detector/sky offsets and the binary model of a rotating sequence.

Convention (`kpifs.io.angles`): the detector position angle ``t`` (DETPA) of a
frame is the position angle, East of North, of the detector's +y axis; the
detector is not mirrored. A sky offset (``dRA`` East-positive, ``dDec``) lands
at detector offsets

    x = -dRA cos t + dDec sin t,    y = dRA sin t + dDec cos t,

a reflection, so the same formula maps detector offsets back to the sky. The
position angle on the sky is ``atan2(dRA, dDec)`` (East of North) and equals the
detector position angle ``atan2(-x, y)`` plus ``t``.

A companion fixed on the sky moves on the detector when the field rotates: the
kernel phases of a sequence are the mean over its frames of the per-frame
models. Frames are grouped into position-angle bins (`pa_bins`) narrow enough
that the companion's motion within a bin, at the largest separation
considered, stays a small fraction of the finest fringe ``lambda_min / B_max``.
"""
import numpy as np
from astropy import units as u

from .._utils import to_quantity
from ..exceptions import KpifsError
from ..io.angles import data_angles, mean_angle
from ..model.kernel import MAS

__all__ = ["sky_to_detector", "detector_to_sky", "separation_pa", "pa_bins",
           "rotated_binary_kernel_phases", "add_sky_columns",
           "search_frame", "sky_search_columns"]

#: Largest motion of a companion within one position-angle bin, in finest fringes.
SMEAR_FRACTION = 0.02


def sky_to_detector(dra, ddec, detpa):
    """Detector offsets ``(x, y)`` of sky offsets ``(dRA, dDec)`` at detector angle *detpa*.

    Parameters
    ----------
    dra, ddec : float or ndarray
        Offsets (any common unit, returned in the same), ``dRA`` East-positive.
    detpa : float or ndarray
        Detector position angle(s) in degrees; broadcast against the offsets.

    Examples
    --------
    >>> from kpifs.detect.sky import sky_to_detector
    >>> [round(float(v), 6) for v in sky_to_detector(10.0, 0.0, 0.0)]   # East is left
    [-10.0, 0.0]
    >>> [round(float(v), 6) for v in sky_to_detector(0.0, 10.0, 90.0)]  # North at +x
    [10.0, 0.0]
    """
    t = np.deg2rad(np.asarray(detpa, float))
    c, s = np.cos(t), np.sin(t)
    dra, ddec = np.asarray(dra, float), np.asarray(ddec, float)
    return -dra * c + ddec * s, dra * s + ddec * c


def detector_to_sky(x, y, detpa):
    """Sky offsets ``(dRA, dDec)`` of detector offsets ``(x, y)`` at detector angle *detpa*.

    The inverse of `sky_to_detector` (the map is its own inverse).

    Examples
    --------
    >>> from kpifs.detect.sky import detector_to_sky
    >>> [round(float(v), 6) for v in detector_to_sky(-10.0, 0.0, 0.0)]
    [10.0, 0.0]
    """
    return sky_to_detector(x, y, detpa)


def separation_pa(dra, ddec):
    """Separation and position angle (deg, East of North, in [0, 360)) of sky offsets.

    Examples
    --------
    >>> from kpifs.detect.sky import separation_pa
    >>> [round(float(v), 6) for v in separation_pa(1.0, 0.0)]   # due East
    [1.0, 90.0]
    """
    dra, ddec = np.asarray(dra, float), np.asarray(ddec, float)
    return np.hypot(dra, ddec), np.rad2deg(np.arctan2(dra, ddec)) % 360.0


def pa_bins(detpa, *, max_separation, wavelength_min, baseline_max, weights=None,
            fraction=SMEAR_FRACTION):
    """Group frames' detector angles into bins with negligible smearing.

    Parameters
    ----------
    detpa : array-like (nframe,)
        Detector position angles (deg); NaN are not allowed.
    max_separation : `~astropy.units.Quantity`
        Largest separation considered.
    wavelength_min, baseline_max : `~astropy.units.Quantity`
        The finest fringe is ``wavelength_min / baseline_max``.
    weights : array-like (nframe,), optional
        Frame weights (default equal).
    fraction : float
        Largest motion within a bin, in finest fringes.

    Returns
    -------
    angles, weights : ndarray
        The weighted mean angle of each non-empty bin (deg, on the branch of
        the first frame) and the bin weights (summing to 1).

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs.detect.sky import pa_bins
    >>> a, w = pa_bins([0, 0.001, 20], max_separation=200 * u.mas,
    ...                wavelength_min=1.6 * u.um, baseline_max=8 * u.m)
    >>> a.round(4).tolist(), w.round(3).tolist()
    ([0.0005, 20.0], [0.667, 0.333])
    """
    a = np.atleast_1d(np.asarray(u.Quantity(detpa, u.deg).value, float))
    if a.size == 0 or not np.all(np.isfinite(a)):
        raise KpifsError("detector position angles must be finite numbers (deg), one per frame")
    w = np.ones(a.size) if weights is None else np.asarray(weights, float)
    if w.shape != a.shape or np.any(w < 0) or w.sum() <= 0:
        raise KpifsError(f"{w.size} weights for {a.size} frames (need non-negative, not all 0)")
    a = a[0] + (a - a[0] + 180.0) % 360.0 - 180.0             # unwrapped about the first
    r = to_quantity(max_separation, u.mas, name="max_separation").value
    fringe = (to_quantity(wavelength_min, u.m, name="wavelength_min").value
              / to_quantity(baseline_max, u.m, name="baseline_max").value / MAS)
    width = np.rad2deg(fraction * fringe / max(r, 1e-9))         # deg
    idx = np.floor((a - a.min()) / width).astype(int)
    keys, inv = np.unique(idx, return_inverse=True)
    wb = np.bincount(inv, weights=w, minlength=keys.size)
    ab = np.bincount(inv, weights=w * a, minlength=keys.size)
    keep = wb > 0
    return ab[keep] / wb[keep], wb[keep] / wb.sum()


def rotated_binary_kernel_phases(kernel_model, sky_offset, contrast, wavelengths, angles,
                                 weights=None):
    """Kernel phases of a binary fixed on the sky, averaged over detector angles.

    Parameters
    ----------
    kernel_model : `~kpifs.model.kernel.KernelModel`
    sky_offset : `~astropy.units.Quantity` (2,)
        ``(dRA, dDec)`` of the companion.
    contrast : float or array-like (nwave,)
    wavelengths : `~astropy.units.Quantity` (nwave,)
    angles : array-like
        Detector position angles (deg), e.g. from `pa_bins`.
    weights : array-like, optional
        Weights of the angles (default equal).

    Returns
    -------
    ndarray, shape (nwave, nkp)

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.detect.sky import rotated_binary_kernel_phases
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> a = rotated_binary_kernel_phases(km, [30, 40] * u.mas, 0.01, [1.6] * u.um, [0.0])
    >>> b = km.binary_kernel_phases([-30, 40] * u.mas, 0.01, [1.6] * u.um)
    >>> bool(np.allclose(a, b))
    True
    """
    dra, ddec = to_quantity(sky_offset, u.mas, name="sky_offset").value
    ang = np.atleast_1d(np.asarray(angles, float))
    w = np.ones(ang.size) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    x, y = sky_to_detector(dra, ddec, ang)
    out = 0.0
    for xi, yi, wi in zip(x, y, w):
        out = out + wi * kernel_model.binary_kernel_phases([xi, yi] * u.mas, contrast,
                                                           wavelengths)
    return out


def add_sky_columns(table, detpa):
    """Add sky offsets and position angles to a candidate table (in place).

    From the detector columns ``x``, ``y`` (and ``fit_x``, ``fit_y`` with their
    errors when present) and the data's detector position angle (the circular
    mean of *detpa*), adds ``dra``, ``ddec``, ``pa_sky`` (deg East of North)
    and ``fit_dra``, ``fit_ddec``, ``fit_dra_err``, ``fit_ddec_err``,
    ``fit_separation``, ``fit_pa_sky``, ``fit_pa_sky_err``. The angle used is
    recorded in ``table.meta['detpa']``. Nothing is added when no angle is
    known.

    Examples
    --------
    >>> import astropy.units as u
    >>> from astropy.table import QTable
    >>> from kpifs.detect.sky import add_sky_columns
    >>> t = QTable({"x": [-10.0] * u.mas, "y": [0.0] * u.mas})
    >>> add_sky_columns(t, [0.0])
    >>> round(float(t["dra"][0].value), 6), round(float(t["pa_sky"][0].value), 6)
    (10.0, 90.0)
    """
    t = mean_angle(np.atleast_1d(np.asarray(detpa if detpa is not None else [], float)))
    if not np.isfinite(t):
        return
    table.meta["detpa"] = t
    table.meta["frame"] = "sky offsets: dRA East-positive, dDec; PA East of North"
    for pre in ("", "fit_"):
        if pre + "x" not in table.colnames:
            continue
        x = u.Quantity(table[pre + "x"], u.mas).value
        y = u.Quantity(table[pre + "y"], u.mas).value
        dra, ddec = detector_to_sky(x, y, t)
        sep, pa = separation_pa(dra, ddec)
        table[pre + "dra"] = dra * u.mas
        table[pre + "ddec"] = ddec * u.mas
        if pre:
            table["fit_separation"] = sep * u.mas
        table[pre + "pa_sky"] = pa * u.deg
        if pre and "fit_x_err" in table.colnames:
            c, s = np.cos(np.deg2rad(t)), np.sin(np.deg2rad(t))
            xe = u.Quantity(table["fit_x_err"], u.mas).value
            ye = u.Quantity(table["fit_y_err"], u.mas).value
            table["fit_dra_err"] = np.hypot(c * xe, s * ye) * u.mas
            table["fit_ddec_err"] = np.hypot(s * xe, c * ye) * u.mas
            # PA error: the offset's error across the line of sight, over the separation
            ux, uy = np.divide(-y, sep, out=np.zeros_like(sep), where=sep > 0), \
                np.divide(x, sep, out=np.zeros_like(sep), where=sep > 0)
            perp = np.hypot(ux * xe, uy * ye)
            table["fit_pa_sky_err"] = np.rad2deg(
                np.divide(perp, sep, out=np.full_like(sep, np.nan), where=sep > 0)) * u.deg


def search_frame(kpd, frame="auto"):
    """The frame a search of *kpd* runs in: 'sky' or 'detector'.

    See the *frame* option of `kpifs.detect.detect`.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.detect.sky import search_frame
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> kpd = KernelPhaseData(np.zeros((3, 1, km.n_kp)), [1.6] * u.um, 10 * u.mas, km,
    ...                       detpa=[10.0, 20.0, 30.0])
    >>> search_frame(kpd), search_frame(kpd, "detector")
    ('sky', 'detector')
    """
    if frame not in ("auto", "sky", "detector"):
        raise KpifsError(f"frame must be 'auto', 'sky' or 'detector', got {frame!r}")
    ang = data_angles(kpd)
    if frame == "auto":
        return "sky" if ang is not None else "detector"
    if frame == "sky" and ang is None:
        raise KpifsError(f"{kpd.name}: a search on the sky needs the detector position angle "
                         f"of every frame (DETPA, the instrument's keywords or --pa)")
    return frame


def sky_search_columns(table, poses):
    """Candidates of a sky search: grid and fit columns become ``dra``/``ddec``/``pa_sky``
    (and ``fit_...``), and the detector columns ``x``/``y`` (``fit_x``...) are those
    offsets at the mean detector angle of the PA bins *poses* ``(angles, weights)``
    (in place).

    Examples
    --------
    >>> import astropy.units as u
    >>> from astropy.table import QTable
    >>> from kpifs.detect.sky import sky_search_columns
    >>> t = QTable({"x": [10.0] * u.mas, "y": [0.0] * u.mas})       # dRA 10 mas (East)
    >>> sky_search_columns(t, ([0.0], [1.0]))
    >>> float(t["dra"][0].value), round(float(t["x"][0].value), 6), float(t["pa_sky"][0].value)
    (10.0, -10.0, 90.0)
    """
    t = mean_angle(poses[0]) if len(poses[0]) else 0.0
    table.meta["detpa"] = t
    table.meta["frame"] = "sky offsets: dRA East-positive, dDec; PA East of North"
    table.meta["sky_fit"] = (f"searched and fitted on the sky with the rotating model over "
                             f"{len(poses[0])} position-angle bin(s)")
    table.meta["position_angle"] = "degrees East of North"
    c, s = np.cos(np.deg2rad(t)), np.sin(np.deg2rad(t))
    for pre in ("", "fit_"):
        if pre + "x" not in table.colnames:
            continue
        dra = u.Quantity(table[pre + "x"], u.mas).value
        ddec = u.Quantity(table[pre + "y"], u.mas).value
        table[pre + "dra"], table[pre + "ddec"] = dra * u.mas, ddec * u.mas
        sep, pa = separation_pa(dra, ddec)
        table[pre + "pa_sky"] = pa * u.deg
        x, y = sky_to_detector(dra, ddec, t)
        table[pre + "x"], table[pre + "y"] = x * u.mas, y * u.mas
        if pre:
            table["fit_separation"] = sep * u.mas
        if pre and "fit_x_err" in table.colnames:
            de = u.Quantity(table["fit_x_err"], u.mas).value
            ne = u.Quantity(table["fit_y_err"], u.mas).value
            table["fit_dra_err"], table["fit_ddec_err"] = de * u.mas, ne * u.mas
            table["fit_x_err"] = np.hypot(c * de, s * ne) * u.mas
            table["fit_y_err"] = np.hypot(s * de, c * ne) * u.mas
            ux = np.divide(ddec, sep, out=np.zeros_like(sep), where=sep > 0)
            uy = np.divide(-dra, sep, out=np.zeros_like(sep), where=sep > 0)
            perp = np.hypot(ux * de, uy * ne)
            table["fit_pa_sky_err"] = np.rad2deg(
                np.divide(perp, sep, out=np.full_like(sep, np.nan), where=sep > 0)) * u.deg
    if "position_angle" in table.colnames:
        del table["position_angle"]
