"""OIFITS (v1 and v2) closure phases read as kernel phases.

The closure phases of a non-redundant array are its kernel phases: a triangle
``(A, B, C)`` measures ``phi(AB) + phi(BC) - phi(AC)`` of the baseline phases,
whatever the station phases. Rows of one *epoch* (same INSNAME, ARRNAME and
MJD) share their baselines; N stations give N(N-1)(N-2)/6 triangles but only
(N-1)(N-2)/2 independent ones, so a covariance over every triangle is
singular. The reader projects each epoch's triangles onto an orthonormal basis
of their row space (``C = U S V^T``: kernel ``K = V^T``, kernel phases
``S^-1 U^T t``, covariance ``S^-1 U^T Sigma_t U S^-1``), so that no singular
matrix is ever inverted.

Sky frame (FORMATS.md, as CANDID, fouriever and PMOIRED): ``u``, ``v`` (m)
point East and North and a companion at ``(dRA, dDec)`` (East positive) of
flux ratio ``f`` gives ``V = (1 + f exp(-2 pi i (u dRA + v dDec) / lam)) / (1 +
f)``. kpifs's model at detector angle 0 is ``exp(-2 pi i (x u' + y v') /
lam)`` with ``x = -dRA``, ``y = dDec``: the model's uv points are ``(-u, v)``
and the data carry DETPA = 0 (known), so searches run on the sky directly.

Errors come from T3PHIERR, correlations from OI_CORR (``CORRINDX_T3PHI``) and
from the non-standard CPCOV image extensions (fouriever: one ``(ntri nwave,
ntri nwave)`` matrix in rad^2 per observation, triangle-major), read by name.
"""
import logging
import warnings

import numpy as np
from astropy.io import fits

from ..exceptions import KpifsError, KpifsWarning
from .cube import open_fits

__all__ = ["is_oifits", "read_oifits_parts", "OIFITS_SUFFIXES"]

log = logging.getLogger(__name__)

MAS = np.pi / 180 / 3600 / 1000
#: File names that are OIFITS whatever their content.
OIFITS_SUFFIXES = (".oifits", ".oifits.gz", ".oifits.fits")


def is_oifits(origin, path, fileobj, *args, **kwargs):
    """Identifier for astropy's I/O registry: an ``.oifits`` name, or a FITS file with OI_T3.

    Examples
    --------
    >>> from kpifs.io.oifits import is_oifits
    >>> is_oifits("write", "target.oifits", None), is_oifits("write", "kp.fits", None)
    (True, False)
    """
    if path is None:
        return False
    name = str(path).lower()
    if name.endswith(OIFITS_SUFFIXES):
        return True
    if origin == "write" or not name.endswith((".fits", ".fit", ".fits.gz")):
        return False
    try:
        with fits.open(path) as hdul:
            return any(h.name == "OI_T3" for h in hdul)
    except Exception:  # anything unreadable is simply not this format
        return False


def _text(value):
    return "" if value is None else str(value).strip()


def _to_rad(values, unit, where):
    unit = _text(unit).lower()
    if unit.startswith("rad"):
        return values
    if unit and not unit.startswith("deg"):
        raise KpifsError(f"{where}: unit {unit!r} of the closure phases: expected degrees")
    return np.deg2rad(values)


def _metres(values, unit):
    unit = _text(unit).lower()
    scale = {"um": 1e-6, "micron": 1e-6, "microns": 1e-6, "nm": 1e-9}.get(unit, 1.0)
    return np.asarray(values, float) * scale


def _column(hdu, name, shape, where, *, required=True):
    """Column *name* of *hdu* as an array of *shape*, or None if absent and optional."""
    if name not in hdu.columns.names:
        if required:
            raise KpifsError(f"{where}: no {name} column")
        return None
    data = np.asarray(hdu.data[name])
    if data.size != int(np.prod(shape)):
        per_row = data.size // max(shape[0], 1)
        raise KpifsError(f"{where}: {name} has {per_row} value(s) per row but its "
                         f"OI_WAVELENGTH table has NWAVE = {shape[1]} (mismatched NWAVE)")
    return data.reshape(shape)


def _wavelengths(hdul, path):
    waves = {}
    for h in hdul:
        if h.name != "OI_WAVELENGTH":
            continue
        ins = _text(h.header.get("INSNAME"))
        where = f"{path}: OI_WAVELENGTH {ins!r}"
        if h.data is None or "EFF_WAVE" not in h.columns.names:
            raise KpifsError(f"{where}: no EFF_WAVE column")
        wl = _metres(h.data["EFF_WAVE"], h.columns["EFF_WAVE"].unit)
        band = (_metres(h.data["EFF_BAND"], h.columns["EFF_BAND"].unit)
                if "EFF_BAND" in h.columns.names else np.full(wl.shape, np.nan))
        if wl.size == 0 or not np.all(np.isfinite(wl) & (wl > 0)):
            raise KpifsError(f"{where}: EFF_WAVE must be finite and > 0")
        waves[ins] = (wl, band)
    if not waves:
        raise KpifsError(f"{path}: no OI_WAVELENGTH table: the wavelengths of the closure "
                         f"phases are unknown")
    return waves


def _stations(hdul):
    """``{ARRNAME: {STA_INDEX: (diameter m, fov radius rad or nan)}}`` from OI_ARRAY."""
    out = {}
    for h in hdul:
        if h.name != "OI_ARRAY" or h.data is None:
            continue
        cols = h.columns.names
        n = len(h.data)
        diam = np.asarray(h.data["DIAMETER"], float) if "DIAMETER" in cols else np.zeros(n)
        fov = np.full(n, np.nan)
        if "FOV" in cols:
            fwhm = [_text(t).upper() == "FWHM" for t in
                    (h.data["FOVTYPE"] if "FOVTYPE" in cols else ["RADIUS"] * n)]
            fov = np.asarray(h.data["FOV"], float) * 1000 * MAS * np.where(fwhm, 0.5, 1.0)
        idx = h.data["STA_INDEX"] if "STA_INDEX" in cols else np.arange(1, n + 1)
        out[_text(h.header.get("ARRNAME"))] = {int(i): (float(d), float(f))
                                               for i, d, f in zip(idx, diam, fov)}
    return out


def _read_t3(hdul, path, waves, insname):
    """Every OI_T3 row, stacked: phases and errors (rad), flags, uv, stations, epochs."""
    tables = [h for h in hdul if h.name == "OI_T3"]
    if not tables:
        present = ", ".join(h.name for h in hdul[1:] if h.name) or "none"
        raise KpifsError(f"{path}: no OI_T3 table: kpifs reads closure phases (tables "
                         f"present: {present})")
    rows = []
    for k, h in enumerate(tables, 1):
        ins = _text(h.header.get("INSNAME"))
        where = f"{path}: OI_T3 #{k} (INSNAME {ins!r})"
        if insname is not None and ins != insname:
            continue
        if ins not in waves:
            raise KpifsError(f"{where}: no OI_WAVELENGTH table for this INSNAME")
        nw = len(waves[ins][0])
        nrow = 0 if h.data is None else len(h.data)
        if nrow == 0:
            continue
        shape = (nrow, nw)
        phi = _to_rad(np.asarray(_column(h, "T3PHI", shape, where), float),
                      h.columns["T3PHI"].unit, where)
        err = _to_rad(np.asarray(_column(h, "T3PHIERR", shape, where), float),
                      h.columns["T3PHIERR"].unit, where)
        flag = _column(h, "FLAG", shape, where, required=False)
        flag = np.zeros(shape, bool) if flag is None else np.asarray(flag, bool)
        bad = ~flag & ~np.isfinite(phi)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise KpifsError(f"{where}: {int(bad.sum())} closure phase(s) are NaN but not "
                             f"flagged (first: row {r + 1}, channel {c + 1})")
        sta = _column(h, "STA_INDEX", (nrow, 3), where)
        if any(len(set(s)) != 3 for s in sta.tolist()):
            raise KpifsError(f"{where}: STA_INDEX must name three different stations in "
                             f"every row")
        uv = np.column_stack([np.asarray(h.data[c], float) for c in
                              ("U1COORD", "V1COORD", "U2COORD", "V2COORD")
                              if c in h.columns.names])
        if uv.shape[1] != 4 or not np.all(np.isfinite(uv)):
            raise KpifsError(f"{where}: U1COORD, V1COORD, U2COORD, V2COORD must be present "
                             f"and finite")
        mjd = (np.asarray(h.data["MJD"], float) if "MJD" in h.columns.names
               else np.zeros(nrow))
        corr = (np.asarray(h.data["CORRINDX_T3PHI"], int)
                if "CORRINDX_T3PHI" in h.columns.names else None)
        rows.append(dict(ins=ins, arr=_text(h.header.get("ARRNAME")), phi=phi, err=err,
                         flag=flag, sta=sta.astype(int), uv=uv, mjd=mjd, corr=corr,
                         corrname=_text(h.header.get("CORRNAME")), where=where, nw=nw))
    if not rows:
        names = sorted({_text(h.header.get("INSNAME")) for h in tables})
        raise KpifsError(f"{path}: no OI_T3 rows for INSNAME {insname!r} (the file has "
                         f"{', '.join(map(repr, names))})")
    first = waves[rows[0]["ins"]][0]
    for r in rows[1:]:
        wl = waves[r["ins"]][0]
        if len(wl) != len(first) or not np.allclose(wl, first, rtol=1e-6):
            desc = "; ".join(f"{ins!r}: {len(waves[ins][0])} channel(s)"
                             for ins in dict.fromkeys(x["ins"] for x in rows))
            raise KpifsError(f"{path}: the OI_T3 tables have different wavelengths ({desc}): "
                             f"kernel-phase data hold one set of channels; read one "
                             f"INSNAME (KernelPhaseData.read(path, insname=...))")
    return rows


def _covariance(hdul, path, rows, nw):
    """Closure-phase covariance (rad^2), channel-major: index ``w * ntri + tri``."""
    err = np.concatenate([r["err"] for r in rows])             # (ntri, nw)
    ntri = len(err)
    flat = lambda tri, w: np.asarray(w) * ntri + np.asarray(tri)  # noqa: E731
    cov = np.diag((err.T.ravel()) ** 2)
    sources = ["T3PHIERR"]
    starts = np.cumsum([0] + [len(r["err"]) for r in rows])
    corrs = {_text(h.header.get("CORRNAME")): h for h in hdul if h.name == "OI_CORR"}
    lookup = {}
    for r, s in zip(rows, starts):
        if r["corr"] is None or not r["corrname"]:
            continue
        if r["corrname"] not in corrs:
            raise KpifsError(f"{r['where']}: CORRNAME {r['corrname']!r} has no OI_CORR table")
        for i, c0 in enumerate(r["corr"]):
            for w in range(nw):
                lookup[(r["corrname"], int(c0) + w)] = flat(s + i, w)
    for name, h in corrs.items():
        d = h.data
        keys_i = [lookup.get((name, int(i))) for i in d["IINDX"]]
        keys_j = [lookup.get((name, int(j))) for j in d["JINDX"]]
        ok = [a is not None and b is not None for a, b in zip(keys_i, keys_j)]
        if not any(ok):
            continue
        a = np.array([k for k, o in zip(keys_i, ok) if o])
        b = np.array([k for k, o in zip(keys_j, ok) if o])
        c = np.asarray(d["CORR"], float)[np.asarray(ok)]
        sig = np.sqrt(np.diag(cov))
        cov[a, b] = cov[b, a] = c * sig[a] * sig[b]
        sources.append(f"OI_CORR {name!r}")
    for h in hdul:
        if h.name != "CPCOV" or h.data is None:
            continue
        ins = _text(h.header.get("INSNAME"))
        sel = [np.arange(s, s + len(r["err"])) for r, s in zip(rows, starts)
               if not ins or r["ins"] == ins]
        sel = np.concatenate(sel) if sel else np.zeros(0, int)
        data = np.asarray(h.data, float)
        data = data[None] if data.ndim == 2 else data
        m = data.shape[-1]
        nobs = data.shape[0]
        if (data.ndim != 3 or data.shape[1] != m or m % nw or nobs * (m // nw) != len(sel)):
            raise KpifsError(f"{path}: CPCOV {ins!r} has shape {data.shape}, which does not "
                             f"match the {len(sel)} OI_T3 rows x {nw} channels it covers")
        scale = (np.pi / 180) ** 2 if _text(h.header.get("BUNIT")).lower().startswith("deg") \
            else 1.0
        per = m // nw
        for o in range(nobs):
            tri = sel[o * per:(o + 1) * per]
            idx = flat(np.repeat(tri, nw), np.tile(np.arange(nw), per))   # triangle-major
            cov[np.ix_(idx, idx)] = data[o] * scale
        sources.append("CPCOV")
    return cov, sources


def _epochs(rows, keep):
    """Epoch index of every kept row: same INSNAME, ARRNAME and MJD (to 0.1 s)."""
    keys = [(r["ins"], r["arr"], round(float(m) * 864000)) for r in rows for m in r["mjd"]]
    keys = [k for k, ok in zip(keys, keep) if ok]
    ids = {k: i for i, k in enumerate(dict.fromkeys(keys))}
    return np.array([ids[k] for k in keys], int)


def _closure_model(epoch, sta, uv):
    """Baselines, station instances and the closure operator of the kept rows.

    Returns ``uv`` (nbl, 2, East/North), ``blm`` (nbl, nsta), the triangle
    matrix ``C`` (ntri, nbl), the station instances ``(epoch, station)`` and
    each baseline's epoch.
    """
    base, uvs, pairs = {}, [], []
    C = []
    for e, (a, b, c), (u1, v1, u2, v2) in zip(epoch, sta, uv):
        row = {}
        for p, q, bu, bv, coef in ((a, b, u1, v1, 1.0), (b, c, u2, v2, 1.0),
                                   (a, c, u1 + u2, v1 + v2, -1.0)):
            sign = 1.0 if p < q else -1.0
            key = (int(e), min(p, q), max(p, q))
            if key not in base:
                base[key] = len(uvs)
                uvs.append((sign * bu, sign * bv))
                pairs.append(key)
            row[base[key]] = row.get(base[key], 0.0) + coef * sign
        C.append(row)
    nbl = len(uvs)
    cmat = np.zeros((len(C), nbl))
    for i, row in enumerate(C):
        for j, v in row.items():
            cmat[i, j] = v
    inst = {}
    for e, p, q in pairs:
        inst.setdefault((e, p), len(inst))
        inst.setdefault((e, q), len(inst))
    blm = np.zeros((nbl, len(inst)))
    for j, (e, p, q) in enumerate(pairs):
        blm[j, inst[(e, p)]] = 1.0      # uv = r_p - r_q
        blm[j, inst[(e, q)]] = -1.0
    return np.array(uvs, float), blm, cmat, list(inst), np.array([p[0] for p in pairs])


def _project(cmat, epoch, bl_epoch):
    """Per epoch, the SVD of its triangles: kernel ``V^T`` and projector ``S^-1 U^T``."""
    krows, prows = [], []
    ntri, nbl = cmat.shape
    for e in np.unique(epoch):
        ti, bi = np.flatnonzero(epoch == e), np.flatnonzero(bl_epoch == e)
        uu, s, vt = np.linalg.svd(cmat[np.ix_(ti, bi)], full_matrices=False)
        r = int(np.sum(s > 1e-9 * s[0]))
        k = np.zeros((r, nbl))
        k[:, bi] = vt[:r]
        p = np.zeros((r, ntri))
        p[:, ti] = uu[:, :r].T / s[:r, None]
        krows.append(k)
        prows.append(p)
    return np.vstack(krows), np.vstack(prows)


def _drop_flagged(path, phi, flag):
    """Channels flagged everywhere are dropped, then rows flagged in any channel left."""
    keep_ch = ~flag.all(axis=0)
    if not keep_ch.any():
        raise KpifsError(f"{path}: OI_T3: every closure phase is flagged")
    keep_row = ~flag[:, keep_ch].any(axis=1)
    if not keep_row.any():
        raise KpifsError(f"{path}: OI_T3: every triangle is flagged in some channel")
    if flag.any():
        warnings.warn(f"{path}: OI_T3: {int(flag.sum())} flagged closure phase(s) dropped "
                      f"({int((~keep_ch).sum())} channel(s) flagged in every triangle; "
                      f"{int((~keep_row).sum())} triangle(s) flagged in some channel, "
                      f"removed from every channel)", KpifsWarning, stacklevel=4)
    return keep_ch, keep_row


def read_oifits_parts(path, *, insname=None):
    """Read the closure phases of an OIFITS file as the parts of kernel-phase data.

    Parameters
    ----------
    path : str
    insname : str, optional
        Read only the OI_T3 tables of this INSNAME (needed when the file's
        instruments have different wavelengths).

    Returns
    -------
    dict
        ``kp`` (1, nwave, nkp), ``wavelengths`` (m), ``bandwidth`` (m),
        ``pixscale`` (mas), ``model`` (``uv``, ``xy``, ``blm``, ``kernel``,
        ``step``, ``name``), ``covariance``, ``joint_covariance``,
        ``covariance_rows``, ``kp_err``, ``header``, ``detpa`` and ``meta``.
    """
    hdul = open_fits(path)
    with hdul:
        path = str(path)
        waves = _wavelengths(hdul, path)
        rows = _read_t3(hdul, path, waves, insname)
        wl, band = waves[rows[0]["ins"]]
        nw = len(wl)
        cov_t, sources = _covariance(hdul, path, rows, nw)
        arrays = _stations(hdul)
        header = hdul[0].header.copy()
    phi = np.concatenate([r["phi"] for r in rows])
    flag = np.concatenate([r["flag"] for r in rows])
    keep_ch, keep = _drop_flagged(path, phi, flag)
    ntri0 = len(phi)
    sel = (np.arange(nw)[keep_ch][:, None] * ntri0 + np.flatnonzero(keep)[None, :]).ravel()
    cov_t = cov_t[np.ix_(sel, sel)]
    phi, wl, band = phi[keep][:, keep_ch], wl[keep_ch], band[keep_ch]
    nw, ntri = len(wl), len(phi)
    sta = np.concatenate([r["sta"] for r in rows])[keep]
    uv = np.concatenate([r["uv"] for r in rows])[keep]
    epoch = _epochs(rows, keep)
    uv_en, blm, cmat, inst, bl_epoch = _closure_model(epoch, sta, uv)
    kern, proj = _project(cmat, epoch, bl_epoch)
    nk = len(kern)
    kp = (proj @ phi).T[None]                                        # (1, nw, nk)
    c4 = cov_t.reshape(nw, ntri, nw, ntri)
    joint = np.einsum("ka,wavb,lb->wkvl", proj, c4, proj, optimize=True).reshape(nw * nk, -1)
    per = np.stack([joint[w * nk:(w + 1) * nk, w * nk:(w + 1) * nk] for w in range(nw)])
    # a covariance of rank below nkp is kpifs's own calibrated form (few frames): detection
    # whitens on its range; only zero or undefined errors are refused
    var = np.diagonal(per, axis1=1, axis2=2)
    if not np.all(np.isfinite(per)) or not np.all(var > 0):
        w = int(np.argmax(~(var > 0).all(axis=1))) if np.all(np.isfinite(var)) else 0
        raise KpifsError(f"{path}: OI_T3: zero, negative or undefined closure-phase errors "
                         f"at {wl[w] * 1e6:.4f} um (T3PHIERR or covariance)")
    off = joint.copy()
    for w in range(nw):
        off[w * nk:(w + 1) * nk, w * nk:(w + 1) * nk] = 0
    rows_cov = None
    if np.abs(off).max() > 1e-12 * np.abs(joint).max():
        ev, vec = np.linalg.eigh(joint)
        good = ev > 1e-12 * ev.max()
        rows_cov = (np.sqrt(ev[good])[:, None] * vec[:, good].T).reshape(-1, nw, nk)
    else:
        joint = None
    # the model in kpifs's frame: (-u, v), so that detector angle 0 is the sky
    uv_k = uv_en * np.array([-1.0, 1.0])
    xy = np.linalg.lstsq(blm, uv_k, rcond=None)[0]
    lengths = np.hypot(*uv_k.T)
    step, step_note = _aperture(arrays, rows, inst, epoch, wl, lengths)
    ins = list(dict.fromkeys(r["ins"] for r in rows))
    arr = list(dict.fromkeys(r["arr"] for r in rows if r["arr"]))
    tel = _text(header.get("TELESCOP")) or (arr[0] if arr else "")
    catg = _text(header.get("HIERARCH ESO PRO CATG")).upper()
    meta = {"source": path, "layout": "oifits", "calibrated": "RAW" not in catg,
            "detpa_source": "OIFITS (u, v) East/North: the sky frame",
            "instrument": _text(header.get("INSTRUME")) or ", ".join(ins),
            "telescope": tel, "covariance_source": " + ".join(sources),
            "closure_phases": {"n_triangles": ntri, "n_epochs": int(epoch.max()) + 1,
                               "n_tables": len(rows), "insname": ins, "arrname": arr,
                               "n_flagged": int(flag.sum())},
            "notes": [f"{ntri} closure phases in {int(epoch.max()) + 1} epoch(s) projected "
                      f"on {nk} independent ones; errors from {' + '.join(sources)}",
                      step_note]}
    log.info("%s: %d triangles, %d epochs -> %d independent closure phases x %d channels",
             path, ntri, int(epoch.max()) + 1, nk, nw)
    return {"kp": kp, "wavelengths": wl, "bandwidth": band, "pixscale":
            float(wl.min() / (2 * lengths.max()) / MAS),
            "model": {"uv": uv_k, "xy": xy, "blm": blm, "kernel": kern, "step": step,
                      "name": f"OIFITS {'/'.join(arr or ins)}",
                      "rank": int(np.linalg.matrix_rank(blm))},
            "covariance": per, "joint_covariance": joint, "covariance_rows": rows_cov,
            "kp_err": np.sqrt(np.diagonal(per, axis1=1, axis2=2))[None],
            "header": header, "detpa": np.zeros(1), "meta": meta}


def _aperture(arrays, rows, inst, epoch, wl, lengths):
    """The model's step (m) and a note: half the aperture diameter ``D``, so that the
    default search reaches ``lambda / D``, about the primary beam's FWHM."""
    arr = {r["arr"] for r in rows}
    used = {s for _, s in inst}
    info = [v for a in arr for i, v in arrays.get(a, {}).items() if i in used]
    diam = max((d for d, _ in info if np.isfinite(d)), default=0.0)
    if diam > 0:
        return diam / 2, f"aperture diameter {diam:.3f} m (OI_ARRAY DIAMETER)"
    fov = min((f for _, f in info if np.isfinite(f) and f > 0), default=np.nan)
    if np.isfinite(fov):
        return 0.95 * wl.min() / (2 * fov), (f"search radius from OI_ARRAY FOV "
                                             f"({fov / MAS:.0f} mas)")
    d = float(lengths.min()) / 2
    return d / 2, (f"no aperture diameter (OI_ARRAY DIAMETER 0 or missing): half the "
                   f"shortest baseline, {d:.3f} m, taken as the aperture size")
