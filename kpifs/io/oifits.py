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
import datetime
import logging
import warnings

import numpy as np
from astropy.io import fits

from ..exceptions import KpifsError, KpifsWarning
from .cube import open_fits
from .oifits_bins import BIN_SMEAR, bin_closure_phases, search_field
from .oifits_noise import check_size, closure_covariance

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


def _unit(unit, where):
    """``'rad'`` or ``'deg'`` (the standard's default when no unit is given)."""
    unit = _text(unit).lower()
    if unit.startswith("rad"):
        return "rad"
    if unit and not unit.startswith("deg"):
        raise KpifsError(f"{where}: unit {unit!r} of the closure phases: expected degrees")
    return "deg"


def _phases(values, unit, flag, where):
    """Closure phases in rad, wrapped to (-pi, pi] before anything else; values that no
    phase has in the stated unit (beyond +-2 pi in radians: degrees labelled 'rad') are
    refused."""
    unit = _unit(unit, where)
    vals = np.asarray(values, float)
    used = ~flag & np.isfinite(vals)
    if unit == "rad" and used.any() and np.abs(vals[used]).max() > 2 * np.pi * (1 + 1e-9):
        raise KpifsError(f"{where}: T3PHI reaches {np.abs(vals[used]).max():.4g}, impossible "
                         f"for a phase in radians (its unit is 'rad'; degrees labelled as "
                         f"radians?)")
    rad = vals if unit == "rad" else np.deg2rad(vals)
    return np.pi - np.mod(np.pi - rad, 2 * np.pi)                    # (-pi, pi]


def _errors(values, unit, flag, where):
    """T3PHIERR in rad: finite and > 0 wherever a closure phase is used."""
    err = np.asarray(values, float)
    bad = ~flag & ~(np.isfinite(err) & (err > 0))
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise KpifsError(f"{where}: {int(bad.sum())} T3PHIERR value(s) are zero, negative or "
                         f"NaN where the closure phase is not flagged (first: row {r + 1}, "
                         f"channel {c + 1}, {float(err[r, c]):g}): an error must be > 0")
    return err if _unit(unit, where) == "rad" else np.deg2rad(err)


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
        check_size(8.0 * 4 * int(h.header.get("NAXIS2", 0) or 0), f"{where}: its rows", path,
                   "check the file")
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


def _t3_size(h, nw, where):
    """Refuse, before reading it, an OI_T3 table whose rows x channels need more memory
    than the machine has (a few float64 arrays of that size are made)."""
    nrow = int(h.header.get("NAXIS2", 0) or 0)
    check_size(8.0 * 12 * nrow * max(nw, 1), f"{nrow} OI_T3 rows x {nw} channel(s)", where,
               "read one INSNAME (insname=...)")
    return nrow


def _t3_table(h, k, path, waves, arrays):
    """One OI_T3 table: closure phases (wrapped, rad), errors, flags, uv, stations."""
    ins = _text(h.header.get("INSNAME"))
    where = f"{path}: OI_T3 #{k} (INSNAME {ins!r})"
    if ins not in waves:
        raise KpifsError(f"{where}: no OI_WAVELENGTH table for this INSNAME")
    nw = len(waves[ins][0])
    if _t3_size(h, nw, where) == 0 or h.data is None or len(h.data) == 0:
        return None
    nrow = len(h.data)
    shape = (nrow, nw)
    flag = _column(h, "FLAG", shape, where, required=False)
    flag = np.zeros(shape, bool) if flag is None else np.asarray(flag, bool)
    raw = np.asarray(_column(h, "T3PHI", shape, where), float)
    bad = ~flag & ~np.isfinite(raw)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise KpifsError(f"{where}: {int(bad.sum())} closure phase(s) are NaN but not "
                         f"flagged (first: row {r + 1}, channel {c + 1})")
    phi = _phases(raw, h.columns["T3PHI"].unit, flag, where)
    err = _errors(_column(h, "T3PHIERR", shape, where), h.columns["T3PHIERR"].unit, flag,
                  where)
    sta = np.asarray(_column(h, "STA_INDEX", (nrow, 3), where), int)
    if any(len(set(x)) != 3 for x in sta.tolist()):
        raise KpifsError(f"{where}: STA_INDEX must name three different stations in "
                         f"every row")
    arr = _text(h.header.get("ARRNAME"))
    known = arrays.get(arr)
    if known is not None:
        missing = sorted(set(np.unique(sta).tolist()) - set(known))
        if missing:
            raise KpifsError(f"{where}: STA_INDEX {missing} not in the OI_ARRAY table of "
                             f"ARRNAME {arr!r} (its stations: {sorted(known)})")
    uv = np.column_stack([np.asarray(h.data[c], float) for c in
                          ("U1COORD", "V1COORD", "U2COORD", "V2COORD")
                          if c in h.columns.names])
    if uv.shape[1] != 4 or not np.all(np.isfinite(uv)):
        raise KpifsError(f"{where}: U1COORD, V1COORD, U2COORD, V2COORD must be present "
                         f"and finite")
    mjd = (np.asarray(h.data["MJD"], float) if "MJD" in h.columns.names
           else np.zeros(nrow))
    if not np.all(np.isfinite(mjd)):
        raise KpifsError(f"{where}: MJD is NaN or infinite in {int((~np.isfinite(mjd)).sum())} "
                         f"row(s) (first: row {int(np.argmax(~np.isfinite(mjd))) + 1}): the "
                         f"exposures the closure phases belong to are unknown")
    corr = (np.asarray(h.data["CORRINDX_T3PHI"], int)
            if "CORRINDX_T3PHI" in h.columns.names else None)
    return dict(ins=ins, arr=arr, phi=phi, err=err, flag=flag, sta=sta, uv=uv,
                mjd=mjd, corr=corr, corrname=_text(h.header.get("CORRNAME")), where=where,
                nw=nw)


def _read_t3(hdul, path, waves, insname, arrays):
    """Every OI_T3 row, stacked: phases and errors (rad), flags, uv, stations, epochs."""
    tables = [h for h in hdul if h.name == "OI_T3"]
    if not tables:
        present = ", ".join(h.name for h in hdul[1:] if h.name) or "none"
        raise KpifsError(f"{path}: no OI_T3 table: kpifs reads closure phases (tables "
                         f"present: {present})")
    rows = []
    for k, h in enumerate(tables, 1):
        if insname is not None and _text(h.header.get("INSNAME")) != insname:
            continue
        r = _t3_table(h, k, path, waves, arrays)
        if r is not None:
            rows.append(r)
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


def _corr_tables(hdul, path, rows):
    """``{CORRNAME: data}`` of the OI_CORR tables, their indices checked: within 1..NDATA,
    IINDX != JINDX, CORR finite in [-1, 1], and every CORRINDX_T3PHI's channels inside."""
    out = {}
    for h in hdul:
        if h.name != "OI_CORR" or h.data is None:
            continue
        name = _text(h.header.get("CORRNAME"))
        where = f"{path}: OI_CORR {name!r}"
        d = h.data
        for c in ("IINDX", "JINDX", "CORR"):
            if c not in h.columns.names:
                raise KpifsError(f"{where}: no {c} column")
        ndata = h.header.get("NDATA")
        i, j = np.asarray(d["IINDX"], np.int64), np.asarray(d["JINDX"], np.int64)
        rho = np.asarray(d["CORR"], float)
        top = int(ndata) if isinstance(ndata, (int, np.integer)) and ndata > 0 else None
        if top is None:
            raise KpifsError(f"{where}: NDATA (the number of correlated data) missing or "
                             f"not a positive integer")
        bad = (i < 1) | (j < 1) | (i > top) | (j > top)
        if bad.any():
            k = int(np.argmax(bad))
            raise KpifsError(f"{where}: {int(bad.sum())} IINDX/JINDX value(s) outside "
                             f"1..NDATA = {top} (first: row {k + 1}, {int(i[k])}, {int(j[k])})")
        if np.any(i == j) or not np.all(np.isfinite(rho) & (np.abs(rho) <= 1 + 1e-9)):
            raise KpifsError(f"{where}: CORR must be finite and within [-1, 1] between two "
                             f"different data (IINDX != JINDX)")
        out[name] = d
        for r in rows:
            if r["corrname"] != name or r["corr"] is None:
                continue
            lo, hi = int(r["corr"].min()), int(r["corr"].max()) + r["nw"] - 1
            if lo < 1 or hi > top:
                raise KpifsError(f"{r['where']}: CORRINDX_T3PHI points outside OI_CORR "
                                 f"{name!r} (indices {lo}..{hi}, NDATA = {top})")
    for r in rows:
        if r["corr"] is not None and r["corrname"] and r["corrname"] not in out:
            raise KpifsError(f"{r['where']}: CORRNAME {r['corrname']!r} has no OI_CORR table")
    return out


def _cpcov(hdul, path, nw):
    """``[(INSNAME, data (nobs, m, m) rad^2)]`` of the CPCOV extensions (fouriever), their
    size checked before they are read."""
    out = []
    for h in hdul:
        if h.name != "CPCOV":
            continue
        shape = [int(h.header.get(f"NAXIS{k}", 0) or 0)
                 for k in range(1, int(h.header.get("NAXIS", 0) or 0) + 1)]
        check_size(8.0 * float(np.prod(shape, dtype=float)), f"CPCOV of shape {shape[::-1]}",
                   path, "read one INSNAME (insname=...)")
        if h.data is None:
            continue
        ins = _text(h.header.get("INSNAME"))
        data = np.asarray(h.data, float)
        data = data[None] if data.ndim == 2 else data
        if data.ndim != 3 or data.shape[1] != data.shape[2]:
            raise KpifsError(f"{path}: CPCOV {ins!r} has shape {data.shape}: expected square "
                             f"matrices")
        unit = _text(h.header.get("BUNIT")).lower()
        out.append((ins, data * ((np.pi / 180) ** 2 if unit.startswith("deg") else 1.0)))
    return out


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


def _drop_flagged(path, flag):
    """Closure phases flagged everywhere in a channel or a triangle go; of the others, the
    channels or the triangles holding a flagged value go, whichever loses fewer values
    (a few flagged channels of a spectrum leave every triangle)."""
    keep_ch, keep_row = ~flag.all(axis=0), ~flag.all(axis=1)
    if not keep_ch.any():
        raise KpifsError(f"{path}: OI_T3: every closure phase is flagged")
    sub = flag[np.ix_(keep_row, keep_ch)]
    bad_ch, bad_row = sub.any(axis=0), sub.any(axis=1)
    if bad_ch.sum() * keep_row.sum() <= bad_row.sum() * keep_ch.sum():
        keep_ch[np.flatnonzero(keep_ch)[bad_ch]] = False
        how = "channel(s)"
    else:
        keep_row[np.flatnonzero(keep_row)[bad_row]] = False
        how = "triangle(s)"
    if not keep_ch.any() or not keep_row.any():
        raise KpifsError(f"{path}: OI_T3: every triangle is flagged in some channel and every "
                         f"channel in some triangle")
    if flag.any():
        warnings.warn(f"{path}: OI_T3: {int(flag.sum())} flagged closure phase(s): "
                      f"{int((~keep_ch).sum())} channel(s) and {int((~keep_row).sum())} "
                      f"triangle(s) left out (the {how} holding them)", KpifsWarning,
                      stacklevel=4)
    return keep_ch, keep_row


def _read_tables(path, insname):
    hdul = open_fits(path)
    with hdul:
        waves = _wavelengths(hdul, path)
        arrays = _stations(hdul)
        rows = _read_t3(hdul, path, waves, insname,
                        {a: set(v) for a, v in arrays.items()})
        nw = len(waves[rows[0]["ins"]][0])
        return {"waves": waves, "arrays": arrays, "rows": rows,
                "corrs": _corr_tables(hdul, path, rows), "cpcov": _cpcov(hdul, path, nw),
                "header": hdul[0].header.copy()}


def _full_rank(per):
    ev = np.linalg.eigvalsh(per)
    return bool(np.all(ev[:, 0] > 1e-10 * ev[:, -1]))


def _project_covariance(phi, per, joint, proj, nw, ntri, path):
    """The independent closure phases ``(1, nw, nk)`` and their covariance: per channel
    ``(nw, nk, nk)``, and the joint one with its rows when channels are correlated.

    A covariance of full rank (independent triangles: every closure phase has noise of
    its own) gives the best linear unbiased estimate of the independent ones,
    ``k = (A^T W A)^-1 A^T W t`` with ``A = (S^-1 U^T)^+``, ``W`` its inverse (what a fit
    of every triangle with that covariance weighs); a singular one (noise on the
    baselines) lies in the triangles' row space, and ``k = S^-1 U^T t`` loses nothing."""
    nk = len(proj)
    if joint is None and ntri > nk and _full_rank(per):
        a = np.linalg.pinv(proj)                                      # (ntri, nk)
        wt = np.linalg.inv(per)                                       # (nw, ntri, ntri)
        cov = np.linalg.inv(np.einsum("tk,wts,sl->wkl", a, wt, a, optimize=True))
        gain = np.einsum("wkl,tl,wts->wks", cov, a, wt, optimize=True)   # (nw, nk, ntri)
        return np.einsum("wks,sw->wk", gain, phi)[None], 0.5 * (cov + cov.transpose(0, 2, 1)), \
            None, None
    kp = (proj @ phi).T[None]
    if joint is None:
        return kp, np.einsum("ka,wab,lb->wkl", proj, per, proj, optimize=True), None, None
    check_size(8.0 * 4 * (nw * nk) ** 2, f"the joint covariance of {nk} independent closure "
               f"phases x {nw} channels", path, "read one INSNAME (insname=...)")
    c4 = joint.reshape(nw, ntri, nw, ntri)
    joint = np.einsum("ka,wavb,lb->wkvl", proj, c4, proj, optimize=True).reshape(nw * nk, -1)
    per = np.stack([joint[w * nk:(w + 1) * nk, w * nk:(w + 1) * nk] for w in range(nw)])
    off = joint.copy()
    for w in range(nw):
        off[w * nk:(w + 1) * nk, w * nk:(w + 1) * nk] = 0
    if not np.abs(off).max() > 1e-12 * np.abs(joint).max():
        return kp, per, None, None
    ev, vec = np.linalg.eigh(joint)
    good = ev > 1e-12 * ev.max()
    rows = (np.sqrt(ev[good])[:, None] * vec[:, good].T).reshape(-1, nw, nk)
    return kp, per, joint, rows


def read_oifits_parts(path, *, insname=None, correlations="baselines", binning="auto"):
    """Read the closure phases of an OIFITS file as the parts of kernel-phase data.

    Parameters
    ----------
    path : str
    insname : str, optional
        Read only the OI_T3 tables of this INSNAME (needed when the file's
        instruments have different wavelengths).
    correlations : {'baselines', 'independent'}
        What the triangles of one exposure share where the file states no
        correlations (`kpifs.io.oifits_noise`): their baselines' noise
        (default), or nothing.
    binning : {'auto', 'none'}
        ``'auto'``: channels finer than a companion search resolves are
        averaged (`kpifs.io.oifits_bins`); ``'none'`` keeps every channel.

    Returns
    -------
    dict
        ``kp`` (1, nwave, nkp), ``wavelengths`` (m), ``bandwidth`` (m),
        ``pixscale`` (mas), ``model`` (``uv``, ``xy``, ``blm``, ``kernel``,
        ``step``, ``name``), ``covariance``, ``joint_covariance``,
        ``covariance_rows``, ``kp_err``, ``header``, ``detpa`` and ``meta``.
    """
    path = str(path)
    t = _read_tables(path, insname)
    rows, header = t["rows"], t["header"]
    wl, band = t["waves"][rows[0]["ins"]]
    flag = np.concatenate([r["flag"] for r in rows])
    keep_ch, keep = _drop_flagged(path, flag)
    phi = np.concatenate([r["phi"] for r in rows])[keep][:, keep_ch]
    err = np.concatenate([r["err"] for r in rows])[keep][:, keep_ch]
    wl, band = wl[keep_ch], band[keep_ch]
    nw, ntri = len(wl), len(phi)
    sta = np.concatenate([r["sta"] for r in rows])[keep]
    uv = np.concatenate([r["uv"] for r in rows])[keep]
    epoch = _epochs(rows, keep)
    uv_en, blm, cmat, inst, bl_epoch = _closure_model(epoch, sta, uv)
    kern, proj = _project(cmat, epoch, bl_epoch)
    nk = len(kern)
    # the model in kpifs's frame: (-u, v), so that detector angle 0 is the sky
    uv_k = uv_en * np.array([-1.0, 1.0])
    lengths = np.hypot(*uv_k.T)
    step, step_note = _aperture(t["arrays"], rows, inst, wl, lengths)
    per, joint, sources = closure_covariance(
        {"path": path, "rows": rows, "keep": keep, "keep_ch": keep_ch, "err": err,
         "cmat": cmat, "epoch": epoch, "corrs": t["corrs"], "cpcov": t["cpcov"]},
        correlations=correlations)
    field, bins, field_note = search_field(wl, lengths.max(), 0.95 * wl.min() / (2 * step),
                                           nk, binning=binning if joint is None else "none")
    step = 0.95 * wl.min() / (2 * field)          # the default grid's limit is the field
    bin_note = None
    if bins is not None:
        n0 = nw
        phi, err, per, wl, band = bin_closure_phases(phi, err, per, wl, band, bins)
        nw = len(wl)
        bin_note = (f"{n0} channels binned to {nw} (at most {BIN_SMEAR:g} fringe of smearing "
                    f"at the field's edge, {field / MAS:.0f} mas; binning='none' keeps them)")
    kp, per, joint, rows_cov = _project_covariance(phi, per, joint, proj, nw, ntri,
                                                   path)
    var = np.diagonal(per, axis1=1, axis2=2)
    if not np.all(np.isfinite(per)) or not np.all(var > 0):
        w = int(np.argmax(~(var > 0).all(axis=1))) if np.all(np.isfinite(var)) else 0
        raise KpifsError(f"{path}: OI_T3: zero, negative or undefined closure-phase errors "
                         f"at {wl[w] * 1e6:.4f} um (T3PHIERR or covariance)")
    xy = np.linalg.lstsq(blm, uv_k, rcond=None)[0]
    meta = _meta(path, header, rows, epoch, ntri, nk, sources, step_note, flag)
    meta["notes"] += [n for n in (field_note, bin_note) if n]
    if bin_note:
        meta["binned_channels"] = np.bincount(bins).tolist()
    names = meta["closure_phases"]["arrname"] or meta["closure_phases"]["insname"]
    log.info("%s: %d triangles, %d epochs -> %d independent closure phases x %d channels",
             path, ntri, int(epoch.max()) + 1, nk, nw)
    return {"kp": kp, "wavelengths": wl, "bandwidth": band, "pixscale":
            float(wl.min() / (2 * lengths.max()) / MAS),
            "model": {"uv": uv_k, "xy": xy, "blm": blm, "kernel": kern, "step": step,
                      "name": f"OIFITS {'/'.join(names)}",
                      "rank": int(np.linalg.matrix_rank(blm))},
            "covariance": per, "joint_covariance": joint, "covariance_rows": rows_cov,
            "kp_err": np.sqrt(np.diagonal(per, axis1=1, axis2=2))[None],
            "header": header, "detpa": np.zeros(1), "meta": meta}


def _calibrated(header):
    """kpifs's own CALFLAG when present, else not a raw ESO product."""
    if "CALFLAG" in header:
        return _text(header["CALFLAG"]).upper() in ("T", "TRUE", "1")
    return "RAW" not in _text(header.get("HIERARCH ESO PRO CATG")).upper()


def _mjd_note(header, rows):
    """A note when the rows' MJD and the primary DATE-OBS disagree by more than a day
    (MJD only groups the exposures)."""
    date = _text(header.get("DATE-OBS"))[:10]
    try:
        d = datetime.date.fromisoformat(date)
    except ValueError:
        return None
    mjd = float(np.median(np.concatenate([r["mjd"] for r in rows])))
    ref = (d - datetime.date(1858, 11, 17)).days
    if not mjd or abs(mjd - ref) <= 1.5:
        return None
    return (f"OI_T3 MJD {mjd:.2f} is {mjd - ref:+.0f} days from DATE-OBS {date}: ignored "
            f"(MJD only groups the exposures)")


def _meta(path, header, rows, epoch, ntri, nk, sources, step_note, flag):
    ins = list(dict.fromkeys(r["ins"] for r in rows))
    arr = list(dict.fromkeys(r["arr"] for r in rows if r["arr"]))
    tel = _text(header.get("TELESCOP")) or (arr[0] if arr else "")
    notes = [f"{ntri} closure phases in {int(epoch.max()) + 1} epoch(s) projected on {nk} "
             f"independent ones; errors from {' + '.join(sources)}", step_note,
             _mjd_note(header, rows)]
    return {"source": path, "layout": "oifits", "calibrated": _calibrated(header),
            "detpa_source": "OIFITS (u, v) East/North: the sky frame",
            "instrument": _text(header.get("INSTRUME")) or ", ".join(ins),
            "telescope": tel, "covariance_source": " + ".join(sources),
            "closure_phases": {"n_triangles": ntri, "n_epochs": int(epoch.max()) + 1,
                               "n_tables": len(rows), "insname": ins, "arrname": arr,
                               "n_flagged": int(flag.sum())},
            "notes": [n for n in notes if n]}


def _aperture(arrays, rows, inst, wl, lengths):
    """The model's step (m) and a note: half the aperture diameter ``D``, so that the
    default search reaches ``lambda / D``, about the primary beam's FWHM.

    An OI_ARRAY FOV smaller than the resolution ``lambda / B_max`` contradicts the
    baselines measured (written carelessly: AMICAL and the JWST AMI reduction write
    ~2e-8 arcsec): it is ignored, with a note saying so."""
    arr = {r["arr"] for r in rows}
    used = {s for _, s in inst}
    info = [v for a in arr for i, v in arrays.get(a, {}).items() if i in used]
    diam = max((d for d, _ in info if np.isfinite(d)), default=0.0)
    if diam > 0:
        return diam / 2, f"aperture diameter {diam:.3f} m (OI_ARRAY DIAMETER)"
    fov = min((f for _, f in info if np.isfinite(f) and f > 0), default=np.nan)
    res = wl.min() / lengths.max()
    ignored = ""
    if np.isfinite(fov) and fov < res:
        ignored = (f"OI_ARRAY FOV {fov / MAS:.3g} mas ignored: smaller than the resolution "
                   f"lambda / B_max = {res / MAS:.1f} mas; ")
    elif np.isfinite(fov):
        return 0.95 * wl.min() / (2 * fov), (f"search radius from OI_ARRAY FOV "
                                             f"({fov / MAS:.0f} mas)")
    d = float(lengths.min()) / 2
    return d / 2, (f"{ignored}no aperture diameter (OI_ARRAY DIAMETER 0 or missing): half "
                   f"the shortest baseline, {d:.3f} m, taken as the aperture size")
