"""OIFITS2 for kernel phases that are closure phases (a non-redundant mask's model).

Every uv point of the model must be made by exactly one pair of holes, and the
kernel must span exactly the closure phases of the mask's triangles (what
`~kpifs.model.kernel.KernelModel.from_pupil` gives for a mask, and what
`kpifs.io.oifits` reads). The closure phases of every triangle ``(i, j, k)``,
``phi(r_i - r_j) + phi(r_j - r_k) - phi(r_i - r_k)``, are ``C K^+ kp``; their
covariance ``C K^+ Sigma K^+T C^T`` is singular (only (N-1)(N-2)/2 of them are
independent) and is written as T3PHIERR and the correlations of OI_CORR.
Full-pupil kernel phases have no OIFITS form: KPFITS is their exchange format.

Orientation: the model's detector ``(u', v')`` at detector angle ``t`` are
written East/North, ``u = -u' cos t + v' sin t``, ``v = u' sin t + v' cos t``
(`kpifs.detect.sky`), so that any OIFITS tool sees the companion on the sky.
"""
import datetime
import itertools
import warnings

import numpy as np
from astropy.io import fits

from .._meta import VERSION
from .._utils import write_hdulist
from ..covariance import empirical_covariance
from ..exceptions import KpifsError, KpifsWarning
from .angles import data_angles, mean_angle

__all__ = ["write_oifits", "closure_triangles"]

MAS = np.pi / 180 / 3600 / 1000
_ARCSEC = np.pi / 180 / 3600


def closure_triangles(kernel_model, *, source="data"):
    """Triangles of a closure-phase model: ``(stations (ntri, 3), C (ntri, nuv))``.

    Refuses (`~kpifs.KpifsError`) a model whose uv points are not single pairs
    of sub-apertures or whose kernel is not the closure phases of its triangles.

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.io.oifits_write import closure_triangles
    >>> sta, c = closure_triangles(KernelModel.from_pupil(make_pupil("sphere_sam7")))
    >>> sta.shape, c.shape
    ((35, 3), (35, 21))
    """
    sta, cmat, _ = _triangles(kernel_model, source)
    return sta, cmat


def _triangles(kernel_model, source):
    """Stations, closure matrix and the (uv point, sign) of legs AB and BC of each triangle."""
    km = kernel_model
    blm, red = np.asarray(km.blm, float), np.asarray(km.redundancy, float)
    single = (np.sum(blm == 1, axis=1) == 1) & (np.sum(blm == -1, axis=1) == 1) & \
        (np.sum(blm != 0, axis=1) == 2) & np.isclose(red, 1.0)
    refuse = (f"{source}: kernel phases of a pupil with {km.pupil.n_sub} sub-apertures and "
              f"{km.n_uv} uv points are not closure phases of a non-redundant mask, and "
              f"have no OIFITS form: KPFITS (format='kpfits') is their exchange format")
    if not single.all():
        raise KpifsError(refuse + f" ({int((~single).sum())} uv point(s) made by several "
                         f"pairs or grey sub-apertures)")
    pair = {}
    for b, row in enumerate(blm):
        p, q = int(np.flatnonzero(row == 1)[0]), int(np.flatnonzero(row == -1)[0])
        pair[(p, q)], pair[(q, p)] = (b, 1.0), (b, -1.0)
    sta, rows, legs = [], [], []
    for i, j, k in itertools.combinations(range(km.pupil.n_sub), 3):
        if (i, j) in pair and (j, k) in pair and (i, k) in pair:
            legs.append((pair[(i, j)], pair[(j, k)]))
            c = np.zeros(km.n_uv)
            for (p, q), coef in (((i, j), 1.0), ((j, k), 1.0), ((i, k), -1.0)):
                b, s = pair[(p, q)]
                c[b] += coef * s
            sta.append((i, j, k))
            rows.append(c)
    if not rows:
        raise KpifsError(refuse + " (no closed triangle)")
    cmat = np.array(rows)
    kern = np.asarray(km.kernel, float)
    s = np.linalg.svd(cmat, compute_uv=False)
    rank = int(np.sum(s > 1e-9 * s[0]))
    q = np.linalg.svd(cmat, full_matrices=False)[2][:rank]
    resid = np.abs(kern - (kern @ q.T) @ q).max() / max(np.abs(kern).max(), 1e-300)
    if rank != km.n_kp or resid > 1e-8:
        raise KpifsError(refuse + f" (its {km.n_kp} kernel phases are not the {rank} "
                         f"independent closure phases of its triangles)")
    return np.array(sta, int), cmat, legs


def _mean_and_covariance(kpd):
    """One closure-phase measurement: the data's one frame, or the mean of its frames."""
    nw, nk = kpd.n_wave, kpd.n_kp
    if kpd.n_frame == 1:
        if kpd.joint_covariance is not None:
            return kpd.kp[0], kpd.joint_covariance, "the covariance of the data"
        if kpd.covariance is None:
            raise KpifsError(f"{kpd.name}: one frame and no covariance: the closure phases "
                             f"would have no errors (calibrate the data first)")
        joint = np.zeros((nw * nk, nw * nk))
        for w in range(nw):
            joint[w * nk:(w + 1) * nk, w * nk:(w + 1) * nk] = kpd.covariance[w]
        return kpd.kp[0], joint, "the covariance of the data"
    n = kpd.n_frame
    joint = empirical_covariance(kpd.kp, joint=True, debias=True) / n
    return kpd.kp.mean(axis=0), joint, f"the mean of {n} frames and their scatter / {n}"


def _orientation(kpd):
    """The detector angle (deg) the uv points are turned by, and a note."""
    ang = data_angles(kpd)
    if ang is None:
        warnings.warn(f"{kpd.name}: detector position angle unknown: (u, v) written as on "
                      f"the detector (North up, East left assumed)", KpifsWarning,
                      stacklevel=4)
        return 0.0, "detector angle unknown, 0 assumed"
    theta = float(mean_angle(ang))
    if np.ptp(ang) > 1.0:
        warnings.warn(f"{kpd.name}: the frames' detector angles span {np.ptp(ang):.1f} deg; "
                      f"(u, v) written at their mean, {theta:.2f} deg", KpifsWarning,
                      stacklevel=4)
    return theta, f"detector angle {theta:.3f} deg"


def _date_obs(hdr):
    for key in ("DATE-OBS", "DATE"):
        v = str(hdr.get(key, "")).strip()
        if len(v) >= 10:
            return v[:10]
    if "MJD-OBS" in hdr:
        return (datetime.datetime(1858, 11, 17)
                + datetime.timedelta(days=float(hdr["MJD-OBS"]))).strftime("%Y-%m-%d")
    return "2000-01-01"


def _mjd(date_obs):
    d = datetime.datetime.strptime(date_obs[:10], "%Y-%m-%d")
    return (d - datetime.datetime(1858, 11, 17)).days


def _table(name, cols, cards):
    hdu = fits.BinTableHDU.from_columns(cols, name=name)
    for k, v in cards.items():
        hdu.header[k] = v
    return hdu


def oifits_hdulist(kpd, *, target=None, insname=None, arrname=None, history=()):
    """The OIFITS2 `~astropy.io.fits.HDUList` of closure-phase data *kpd*.

    See `write_oifits`.
    """
    km = kpd.kernel_model
    sta, cmat, legs = _triangles(km, kpd.name)
    kp, joint, how = _mean_and_covariance(kpd)
    nw, ntri = kpd.n_wave, len(sta)
    m = cmat @ np.linalg.pinv(km.kernel)                            # kernel -> closure
    t3 = (m @ kp.T).T                                                # (nw, ntri)
    big = np.kron(np.eye(nw), m)
    cov = big @ joint @ big.T                                        # index w * ntri + tri
    sig = np.sqrt(np.clip(np.diag(cov), 0, None))
    if not np.all(sig > 0):
        raise KpifsError(f"{kpd.name}: some closure phases have zero variance")
    theta, orient = _orientation(kpd)
    t = np.deg2rad(theta)
    rot = np.array([[-np.cos(t), np.sin(t)], [np.sin(t), np.cos(t)]])
    uv = km.uv.value @ rot.T                                         # East/North
    hdr = kpd.header
    date_obs = _date_obs(hdr)
    names = dict(
        obj=str(target or hdr.get("OBJECT", "") or "UNKNOWN").strip() or "UNKNOWN",
        ins=insname or str(kpd.meta.get("instrument") or hdr.get("INSTRUME", "") or "KPIFS"),
        mask=km.pupil.name, arr=arrname or f"{km.pupil.name}".upper()[:60])
    prim = _primary(kpd, names, date_obs, orient, [
        f"kpifs {VERSION}: closure phases from {kpd.name}; {how}", *map(str, history)])
    wl = kpd.wavelengths.to_value("m")
    corr, (lo, hi, i, j) = _correlations(cov, sig, nw, ntri)
    mjd = float(_mjd(date_obs))
    cards = {"OI_REVN": 2, "DATE-OBS": date_obs, "ARRNAME": names["arr"],
             "INSNAME": names["ins"]}
    if len(lo):
        cards["CORRNAME"] = "KPIFS"
    t3tab = _t3_table(t3, sig, uv, legs, sta, cards, mjd, float(hdr.get("EXPTIME", 0.0) or 0.0),
                      correlated=bool(len(lo)))
    hdus = [prim, _target_table(names["obj"], hdr),
            _array_table(km, km.pupil.xy.value @ rot.T, wl, names["arr"]),
            _wavelength_table(kpd, wl, names["ins"]), t3tab]
    vis2 = _vis2(kpd, uv, cards, mjd, nw)
    if vis2 is not None:
        hdus.append(vis2)
    if len(lo):
        hdus.append(_table("OI_CORR", [
            fits.Column("IINDX", "J", array=lo), fits.Column("JINDX", "J", array=hi),
            fits.Column("CORR", "D", array=corr[i, j])],
            {"OI_REVN": 1, "CORRNAME": "KPIFS", "NDATA": ntri * nw}))
    return fits.HDUList(hdus)


def _primary(kpd, names, date_obs, orient, history):
    """The primary HDU: who wrote the file, when, what was observed and how."""
    hdr, obj, ins, mask = kpd.header, names["obj"], names["ins"], names["mask"]
    prim = fits.PrimaryHDU()
    ph = prim.header
    for key, value, comment in (
            ("ORIGIN", "kpifs", "institution or software that wrote the file"),
            ("DATE", datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S"),
             "UTC date the file was written"),
            ("DATE-OBS", date_obs, "start of the observation"),
            ("CONTENT", "OIFITS2", "OIFITS version 2 (Duvert et al. 2017)"),
            ("TELESCOP", str(hdr.get("TELESCOP", "") or kpd.meta.get("telescope") or mask)
             or "UNKNOWN", ""),
            ("INSTRUME", ins, ""), ("OBSERVER", str(hdr.get("OBSERVER", "") or "UNKNOWN"), ""),
            ("OBJECT", obj, ""), ("INSMODE", f"mask {mask}", ""),
            ("KPIFSVER", VERSION, "kpifs version"),
            ("CALFLAG", bool(kpd.meta.get("calibrated", False)), "calibrator subtracted"),
            ("KPORIENT", orient, "orientation of (u, v) East/North")):
        ph[key] = (value, comment)
    for h in history:
        ph.add_history(h)
    return prim


def _target_table(obj, hdr):
    """OI_TARGET: the one target."""
    return _table("OI_TARGET", [
        fits.Column("TARGET_ID", "I", array=[1]),
        fits.Column("TARGET", "32A", array=[obj[:32]]),
        fits.Column("RAEP0", "D", unit="deg", array=[float(hdr.get("RA", 0.0) or 0.0)]),
        fits.Column("DECEP0", "D", unit="deg", array=[float(hdr.get("DEC", 0.0) or 0.0)]),
        fits.Column("EQUINOX", "E", unit="yr", array=[2000.0]),
        fits.Column("RA_ERR", "D", unit="deg", array=[0.0]),
        fits.Column("DEC_ERR", "D", unit="deg", array=[0.0]),
        fits.Column("SYSVEL", "D", unit="m/s", array=[0.0]),
        fits.Column("VELTYP", "8A", array=["UNKNOWN"]),
        fits.Column("VELDEF", "8A", array=["OPTICAL"]),
        fits.Column("PMRA", "D", unit="deg/yr", array=[0.0]),
        fits.Column("PMDEC", "D", unit="deg/yr", array=[0.0]),
        fits.Column("PMRA_ERR", "D", unit="deg/yr", array=[0.0]),
        fits.Column("PMDEC_ERR", "D", unit="deg/yr", array=[0.0]),
        fits.Column("PARALLAX", "E", unit="deg", array=[0.0]),
        fits.Column("PARA_ERR", "E", unit="deg", array=[0.0]),
        fits.Column("SPECTYP", "32A", array=["UNKNOWN"])], {"OI_REVN": 2})


def _array_table(km, xy, wl, arr):
    """OI_ARRAY: one station per sub-aperture, at its East/North position *xy* (m)."""
    n = len(xy)
    # the hole size (a mask's meta; a read OIFITS model's step is half its aperture)
    diam = float(km.pupil.meta.get("hole_diameter_m") or (2 * km.pupil.step.to_value("m")
                 if km.pupil.step is not None else 0.0))
    fov = 1.22 * wl.max() / diam / _ARCSEC if diam > 0 else 0.0
    return _table("OI_ARRAY", [
        fits.Column("TEL_NAME", "16A", array=[f"H{i + 1}" for i in range(n)]),
        fits.Column("STA_NAME", "16A", array=[f"H{i + 1}" for i in range(n)]),
        fits.Column("STA_INDEX", "I", array=np.arange(1, n + 1)),
        fits.Column("DIAMETER", "E", unit="m", array=np.full(n, diam)),
        fits.Column("STAXYZ", "3D", unit="m",
                    array=np.column_stack([xy, np.zeros(n)])),
        fits.Column("FOV", "D", unit="arcsec", array=np.full(n, fov)),
        fits.Column("FOVTYPE", "6A", array=["FWHM"] * n)],
        {"OI_REVN": 2, "ARRNAME": arr, "FRAME": "SKY", "ARRAYX": 0.0, "ARRAYY": 0.0,
         "ARRAYZ": 0.0})


def _wavelength_table(kpd, wl, ins):
    """OI_WAVELENGTH: the channels, with their bandwidths (from their spacing when the
    data give none)."""
    nw = len(wl)
    band = (np.full(nw, np.nan) if kpd.bandwidth is None
            else np.broadcast_to(np.asarray(kpd.bandwidth.to_value("m"), float), (nw,)))
    if not np.all(np.isfinite(band)):
        band = np.gradient(wl) if nw > 1 else 0.05 * wl
    return _table("OI_WAVELENGTH", [
        fits.Column("EFF_WAVE", "E", unit="m", array=wl),
        fits.Column("EFF_BAND", "E", unit="m", array=band)], {"OI_REVN": 2, "INSNAME": ins})


def _correlations(cov, sig, nw, ntri):
    """The correlation matrix, and one entry per correlated pair of closure phases: the
    1-based indices into T3PHI's elements (row r, channel w is element r * nw + w + 1),
    and the pairs' indices into the matrix."""
    corr = cov / np.outer(sig, sig)
    i, j = np.triu_indices(nw * ntri, k=1)
    keep = np.abs(corr[i, j]) > 1e-12
    i, j = i[keep], j[keep]
    elem = lambda a: (a % ntri) * nw + a // ntri + 1    # noqa: E731  (w*ntri+tri -> 1-based)
    ei, ej = elem(i), elem(j)
    return corr, (np.minimum(ei, ej), np.maximum(ei, ej), i, j)


def _t3_table(t3, sig, uv, legs, sta, cards, mjd, exptime, *, correlated):
    """OI_T3: the closure phases and their errors (deg), the triangles' legs."""
    nw, ntri = t3.shape
    # legs AB = r_A - r_B and BC, each +-1 times one uv point: as the closure matrix has them
    u1 = np.array([s1 * uv[b1] for (b1, s1), _ in legs])
    u2 = np.array([s2 * uv[b2] for _, (b2, s2) in legs])
    phi = np.rad2deg(t3.T)                                            # (ntri, nw)
    err = np.rad2deg(sig.reshape(nw, ntri).T)
    nan = np.full((ntri, nw), np.nan)
    t3cols = [
        fits.Column("TARGET_ID", "I", array=np.ones(ntri, int)),
        fits.Column("TIME", "D", unit="s", array=np.zeros(ntri)),
        fits.Column("MJD", "D", unit="day", array=np.full(ntri, mjd)),
        fits.Column("INT_TIME", "D", unit="s", array=np.full(ntri, exptime)),
        fits.Column("T3AMP", f"{nw}D", array=nan),
        fits.Column("T3AMPERR", f"{nw}D", array=nan),
        fits.Column("T3PHI", f"{nw}D", unit="deg", array=phi),
        fits.Column("T3PHIERR", f"{nw}D", unit="deg", array=err),
        fits.Column("U1COORD", "D", unit="m", array=u1[:, 0]),
        fits.Column("V1COORD", "D", unit="m", array=u1[:, 1]),
        fits.Column("U2COORD", "D", unit="m", array=u2[:, 0]),
        fits.Column("V2COORD", "D", unit="m", array=u2[:, 1]),
        fits.Column("STA_INDEX", "3I", array=sta + 1),
        fits.Column("FLAG", f"{nw}L", array=np.zeros((ntri, nw), bool))]
    if correlated:
        # with CORRNAME, OIFITSlib reads both indices: T3AMP (not measured) has none, null
        t3cols += [fits.Column("CORRINDX_T3AMP", "J", null=-1, array=np.full(ntri, -1)),
                   fits.Column("CORRINDX_T3PHI", "J", array=np.arange(ntri) * nw + 1)]
    return _table("OI_T3", t3cols, cards)


def _vis2(kpd, uv, cards, mjd, nw):
    """OI_VIS2 from the frames' Fourier amplitudes, when measured in several frames."""
    amp = kpd.amplitudes
    if amp is None or kpd.n_frame < 2:
        return None
    km = kpd.kernel_model
    a2 = np.asarray(amp, float) ** 2                                  # (nframe, nw, nuv)
    v2 = a2.mean(axis=0).T
    err = (a2.std(axis=0, ddof=1) / np.sqrt(kpd.n_frame)).T
    pairs = [(int(np.flatnonzero(r == 1)[0]) + 1, int(np.flatnonzero(r == -1)[0]) + 1)
             for r in km.blm]
    c = {k: v for k, v in cards.items() if k != "CORRNAME"}
    nuv = len(uv)
    return _table("OI_VIS2", [
        fits.Column("TARGET_ID", "I", array=np.ones(nuv, int)),
        fits.Column("TIME", "D", unit="s", array=np.zeros(nuv)),
        fits.Column("MJD", "D", unit="day", array=np.full(nuv, mjd)),
        fits.Column("INT_TIME", "D", unit="s", array=np.zeros(nuv)),
        fits.Column("VIS2DATA", f"{nw}D", array=v2),
        fits.Column("VIS2ERR", f"{nw}D", array=err),
        fits.Column("UCOORD", "D", unit="m", array=uv[:, 0]),
        fits.Column("VCOORD", "D", unit="m", array=uv[:, 1]),
        fits.Column("STA_INDEX", "2I", array=np.array(pairs)),
        fits.Column("FLAG", f"{nw}L", array=np.zeros((nuv, nw), bool))], c)


def write_oifits(kpd, path, *, overwrite=False, inputs=(), history=(), target=None,
                 insname=None, arrname=None):
    """Write closure-phase data *kpd* as OIFITS2 (atomically; never over an input).

    Tables: OI_TARGET, OI_ARRAY (the holes, DIAMETER = hole size, FOV/FOVTYPE),
    OI_WAVELENGTH, OI_T3 (every triangle, degrees), OI_CORR (the triangles'
    correlations, within and across channels) and OI_VIS2 when amplitudes
    were measured in several frames. Several frames are written as their mean
    with the covariance of the mean. Full-pupil kernel phases are refused:
    KPFITS is their exchange format.

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> km = KernelModel.from_pupil(make_pupil("niriss_nrm"))
    >>> kpd = KernelPhaseData(np.zeros((1, 1, km.n_kp)), [4.8] * u.um, 65.6 * u.mas, km,
    ...                       covariance=np.eye(km.n_kp)[None] * 1e-4, detpa=[0.0])
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = kpd.write(tmp.name + "/x.oifits")
    >>> KernelPhaseData.read(path).n_kp
    15
    >>> tmp.cleanup()
    """
    return write_hdulist(oifits_hdulist(kpd, target=target, insname=insname, arrname=arrname,
                                        history=history), path, overwrite=overwrite,
                         inputs=inputs)
