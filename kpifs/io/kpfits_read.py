"""Reading KPFITS files: kpifs's own and the variants other tools write (see `kpifs.io.kpfits`)."""
import logging

import numpy as np
from astropy import units as u
from astropy.io import fits

from ..covariance import unfilled_covariance
from ..exceptions import KpifsError
from ..rotation import rotation_from_hdul
from ._kpfits_common import (_ERROR_MODEL_CARDS, _TELESCOPE_DIAMETERS, _all_nan, _column, _flag,
                             _number)
from .cube import open_fits
from .kpfits_model import read_model_parts
from .wavelengths import parse_wavelengths

__all__ = ["is_kpfits", "read_kpfits_parts"]

log = logging.getLogger("kpifs.io.kpfits")


def is_kpfits(origin, path, fileobj, *args, **kwargs):
    """Identifier for astropy's I/O registry: a FITS file with a KP-DATA extension."""
    if path is not None and not str(path).lower().endswith((".fits", ".fit", ".fits.gz")):
        return False
    target = path if path is not None else fileobj
    if target is None:
        return False
    try:
        with fits.open(target) as hdul:
            return "KP-DATA" in hdul
    except Exception:  # anything unreadable is simply not this format
        return False


# --- kernel-phase data: reading ------------------------------------------------------
def _layout(hdr, names):
    """Which tool wrote the file, from its cards and extensions (for messages and meta)."""
    soft = str(hdr.get("PROCSOFT", "")).strip()
    if soft.lower().startswith("kpifs"):
        return "kpifs"
    if soft.upper().startswith("CALWEBB_KPI3"):
        return "jwst-kpi"
    if any(n.startswith("KP-DATA") and n[7:].isdigit() for n in names):
        return "xara-legacy"
    if "TEL" in names:
        return "pykernel"
    if str(hdr.get("SOFTWARE", "")).strip().upper() == "XARA":
        return "xara"
    return "unknown"


def _read_wavelengths(hdul, hdr, path):
    """(wavelengths um, bandwidths um or None, where): CWAVEL table or image, else cards."""
    values = bw = None
    where = None
    if "CWAVEL" in hdul and hdul["CWAVEL"].data is not None:
        h = hdul["CWAVEL"]
        if isinstance(h, fits.BinTableHDU):
            col = _column(h, "CWAVEL")
            if col is None:
                raise KpifsError(f"{path}: the CWAVEL table has no CWAVEL column (has "
                                 f"{h.columns.names})")
            values, where = np.asarray(col, float).ravel(), "CWAVEL table"
            for name in ("BWIDTH", "DWAVEL"):
                c = _column(h, name)
                if c is not None and not _all_nan(c):
                    bw = np.asarray(c, float).ravel()
                    break
        else:
            values, where = np.atleast_1d(np.asarray(h.data, float)).ravel(), "CWAVEL image"
        if _all_nan(values):
            values = bw = None
    if values is None:
        for key in ("CWAVEL", "CWAVE", "CENWAVE", "HIERARCH ESO INS CWLEN"):
            if key in hdr:
                v = _number(hdr[key])
                if v is None:
                    raise KpifsError(f"{path}: primary {key} = {hdr[key]!r} is not a "
                                     f"wavelength")
                values, where = np.array([v]), f"primary {key.replace('HIERARCH ', '')} card"
                break
    if values is None:
        raise KpifsError(f"{path}: no wavelength: neither a CWAVEL extension nor a CWAVEL, "
                         f"CWAVE, CENWAVE or ESO INS CWLEN card in the primary header")
    wl = parse_wavelengths(values, source=f"{path}: {where}")     # unit told from the values
    if bw is not None:
        if bw.size not in (1, wl.size):
            raise KpifsError(f"{path}: {bw.size} bandwidths for {wl.size} wavelengths in the "
                             f"CWAVEL table")
        bw = np.broadcast_to(bw * float(np.median(wl.value / values)), wl.shape) * u.um
    return wl, bw, where


def _frame_count_hint(hdul):
    """Frames according to the DETPA extension or a TEL table (None when neither says)."""
    if "DETPA" in hdul and hdul["DETPA"].data is not None:
        return int(np.size(hdul["DETPA"].data)) if hdul["DETPA"].is_image \
            else len(hdul["DETPA"].data)
    if "TEL" in hdul and hdul["TEL"].data is not None:
        return len(hdul["TEL"].data)
    return None


def _read_kp(raw, name, nkp, nwave, hint, sig_shape, path, notes):
    """KP-DATA as (nframe, nwave, nkp) from the 1-D, 2-D and 3-D forms in the wild."""
    a = np.asarray(raw, float)
    if a.ndim == 0 or a.shape[-1] != nkp:
        raise KpifsError(f"{path}: {name} has shape {a.shape} but KER-MAT has {nkp} rows: the "
                         f"last axis must hold the {nkp} kernel phases")
    if a.ndim == 1:
        a = a[None, None]
    elif a.ndim == 2:
        if nwave == 1:                                  # (nframe, nkp): xara, jwst-kpi
            a = a[:, None]
        elif a.shape[0] == nwave and (hint is None or hint == 1):
            a = a[None]                                 # (nwave, nkp) of one frame
            notes.append(f"2-D {name} {a.shape[1:]} read as one frame of {nwave} wavelengths")
        else:
            raise KpifsError(f"{path}: {name} is 2-D {a.shape} but there are {nwave} "
                             f"wavelengths: expected (nframe, {nwave}, {nkp})")
    elif a.ndim == 3:
        if a.shape[1] != nwave:
            if a.shape[0] == 1 and nwave == 1 and (sig_shape is None or
                                                   tuple(sig_shape[:2]) != (1, a.shape[1])):
                a = np.swapaxes(a, 0, 1)                # (1, nframe, nkp)
                notes.append(f"{name} of shape (1, {a.shape[0]}, {nkp}) read as "
                             f"{a.shape[0]} frames of one wavelength")
            else:
                raise KpifsError(f"{path}: {name} has shape {a.shape} but there are {nwave} "
                                 f"wavelength(s): expected (nframe, {nwave}, {nkp})")
    else:
        raise KpifsError(f"{path}: {name} has {a.ndim} dimensions: expected (nframe, nwave, "
                         f"nkp), (nframe, nkp) or (nkp)")
    if not np.all(np.isfinite(a)):
        raise KpifsError(f"{path}: {name} holds {int(np.sum(~np.isfinite(a)))} NaN or "
                         f"infinite kernel phases")
    return np.ascontiguousarray(a)


def _as_cov(c, what, nframe, nwave, nkp, path):
    """A covariance array as (nframe|1, nwave, nkp, nkp)."""
    c = np.asarray(c, float)
    ok = c.ndim >= 2 and c.shape[-2:] == (nkp, nkp)
    if ok and c.ndim == 2:
        c = c[None, None]
    elif ok and c.ndim == 3:
        if nwave == 1 and c.shape[0] in (1, nframe):
            c = c[:, None]                              # per frame, one wavelength
        elif c.shape[0] == nwave:
            c = c[None]                                 # per wavelength, every frame
        else:
            ok = False
    elif ok and c.ndim == 4:
        ok = c.shape[0] in (1, nframe) and c.shape[1] == nwave
    else:
        ok = False
    if not ok:
        raise KpifsError(f"{path}: {what} has shape {np.shape(c)}: expected ({nframe} or 1, "
                         f"{nwave}, {nkp}, {nkp}) covariance matrices")
    if not np.all(np.isfinite(c)):
        raise KpifsError(f"{path}: {what} holds NaN or infinite values")
    return c


def _read_uncertainties(hdul, kp, raw_shape, path, notes):
    """(kp_err (nframe, nwave, nkp) or None, covariance (nwave, nkp, nkp) or None, where)."""
    nframe, nwave, nkp = kp.shape
    kp_err = cov = None
    where = None
    sigma_derived = False
    if "KP-SIGM" in hdul and hdul["KP-SIGM"].data is not None \
            and not _all_nan(hdul["KP-SIGM"].data):
        d = np.asarray(hdul["KP-SIGM"].data, float)
        sigma_derived = str(hdul["KP-SIGM"].header.get("SIGMFROM", "")).strip() == "KP-COV"
        if d.shape != tuple(raw_shape) and d.ndim >= 2 and d.shape[-2:] == (nkp, nkp):
            cov = _as_cov(d, "KP-SIGM", nframe, nwave, nkp, path)
            where = "KP-SIGM (covariance matrices)"
        elif d.size == kp.size:
            kp_err = d.reshape(kp.shape)
        elif d.size == nwave * nkp:
            kp_err = np.broadcast_to(d.reshape(1, nwave, nkp), kp.shape).copy()
        else:
            raise KpifsError(f"{path}: KP-SIGM has shape {d.shape} but KP-DATA has {raw_shape}: "
                             f"expected errors of KP-DATA's shape or (nframe, {nkp}, {nkp}) "
                             f"covariance matrices")
        if kp_err is not None and not np.all(np.isfinite(kp_err) & (kp_err >= 0)):
            raise KpifsError(f"{path}: KP-SIGM holds negative, NaN or infinite errors")
    shared = False
    if "KP-COV" in hdul and hdul["KP-COV"].data is not None \
            and not _all_nan(hdul["KP-COV"].data):
        cov = _as_cov(hdul["KP-COV"].data, "KP-COV", nframe, nwave, nkp, path)
        shared = bool(hdul["KP-COV"].header.get("COVSHARE", False))
        where = "KP-COV"
        fill = _number(hdul["KP-COV"].header.get("COVFILL"))
        if fill:               # kpifs's fill of the directions its model leaves out
            cov = unfilled_covariance(cov, fill)
    if sigma_derived:
        kp_err = None                         # kpifs wrote sqrt(diag(KP-COV)): nothing new
    if cov is not None:
        if not shared and cov.shape[0] > 1:
            if kp_err is None:                # per-frame errors from per-frame covariances
                kp_err = np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1)).copy()
            notes.append(f"{where}: {cov.shape[0]} per-frame covariances; the covariance of "
                         f"one frame is their mean")
            where = f"{where}, mean of {cov.shape[0]} frames"
        cov = cov[0] if (shared or cov.shape[0] == 1) else cov.mean(axis=0)
    elif kp_err is not None:
        cov = np.zeros((nwave, nkp, nkp))
        idx = np.arange(nkp)
        cov[:, idx, idx] = np.mean(kp_err ** 2, axis=0)
        where = "KP-SIGM (diagonal)"
        notes.append("no KP-COV: the covariance is diagonal, from KP-SIGM")
    return kp_err, cov, where


def _read_detpa(hdul, hdr, kp_name, nframe, override, path):
    """(detpa (nframe,) deg or None, where), from the first source that has them."""
    values, where = None, None
    if override is not None:
        values, where = np.ravel(np.asarray(override, float)), "given"
    elif "DETPA" in hdul and hdul["DETPA"].data is not None:
        h = hdul["DETPA"]
        values = (np.ravel(np.asarray(h.data, float)) if h.is_image
                  else _column(h, "DETPA", "PA"))
        where = h.header.get("PASRC", "DETPA extension") if h.is_image else "DETPA table"
    elif "TEL" in hdul and isinstance(hdul["TEL"], fits.BinTableHDU):
        values, where = _column(hdul["TEL"], "DETPA", "pa"), "TEL table"
        if values is None:
            log.info("%s: the TEL table has no DETPA or pa column", path)
    elif f"KP-INFO{kp_name[7:]}" in hdul:
        values, where = _column(hdul[f"KP-INFO{kp_name[7:]}"], "DETPA"), "KP-INFO table"
    if values is None:
        for key in ("DETPA", "ORIENTAT"):
            if _number(hdr.get(key)) is not None:
                values, where = np.array([_number(hdr[key])]), f"primary {key} card"
                break
    if values is None:
        return None, None
    values = np.ravel(np.asarray(values, float))
    if values.size == 1:
        values = np.full(nframe, values[0])
    if values.size != nframe:
        raise KpifsError(f"{path}: {values.size} detector position angles ({where}) for "
                         f"{nframe} frames of KP-DATA; give them explicitly (detpa=...)")
    return values, str(where)


def _read_cvis(hdul, layout, shape, path, notes):
    """(phases, amplitudes), each (nframe, nwave, nuv), or (None, None)."""
    if "CVIS-DATA" not in hdul or hdul["CVIS-DATA"].data is None:
        return None, None
    h = hdul["CVIS-DATA"]
    c = np.asarray(h.data, float)
    form = str(h.header.get("CVISFORM", "PHAMP" if layout == "kpifs" else "REIM")).upper()
    if c.ndim == 4 and c.shape[0] == 2:
        a, b = c[0], c[1]
    elif c.ndim == 3 and c.shape[0] == 2 and shape[1] == 1:
        a, b = c[0][:, None], c[1][:, None]            # (2, nframe, nuv)
    elif c.ndim == 3 and c.shape[1] == 2 and shape[1] == 1:
        a, b = c[:, 0][:, None], c[:, 1][:, None]      # older jwst-kpi: (nframe, 2, nuv)
    else:
        a = b = None
    if a is None or a.shape != tuple(shape):
        notes.append(f"CVIS-DATA of shape {c.shape} does not match (2, {shape[0]}, {shape[1]}, "
                     f"{shape[2]}): ignored")
        return None, None
    if form == "PHAMP":                                 # kpifs files before CVISFORM
        return np.ascontiguousarray(a), np.ascontiguousarray(b)
    return np.arctan2(b, a), np.hypot(a, b)


def _read_pixscale(hdr, path):
    v = _number(hdr.get("PSCALE"))
    if v is None:
        for key in ("HIERARCH ESO INS PIXSCALE", "PIXSCALE"):
            v = _number(hdr.get(key))
            if v is not None:
                v = v * 1000.0 if v < 1 else v           # arcsec or mas
                break
    if v is None:
        raise KpifsError(f"{path}: no pixel scale (PSCALE) in the primary header")
    if v <= 0:
        raise KpifsError(f"{path}: pixel scale PSCALE = {v} must be > 0")
    return v * u.mas


#: Order of xara's super-Gaussian window ``exp(-(r / WRAD) ** 4)`` (jwst-kpi's ``WRAD``).
XARA_WINDOW_ORDER = 4.0


def _foreign_window(hdul, hdr, notes):
    """jwst-kpi's window (``WRAD`` pixels, xara's ``exp(-(r / WRAD) ** 4)``) as kpifs's
    ``WINRAD``/``WINSIZE``/``WINORD`` cards of *hdr* (a copy), so that fits and limits
    model its attenuation of a companion; a ``WRAD`` that names no window is noted."""
    if "WINRAD" in hdr or "WRAD" not in hdr:
        return
    wrad = _number(hdr.get("WRAD"))
    if _flag(hdr.get("S_WINDOW", True)) is False or (wrad is None and str(
            hdr["WRAD"]).strip().upper() in ("NONE", "")):
        notes.append("no extraction window (WRAD NONE or S_WINDOW False)")
        return
    if wrad is None or not np.isfinite(wrad) or wrad <= 0:
        notes.append(f"WRAD {hdr['WRAD']!r} is no window radius: ignored (no window "
                     f"modelled)")
        return
    sci = hdul["SCI"] if "SCI" in hdul and hdul["SCI"].is_image else None
    shape = np.shape(sci.data) if sci is not None and sci.data is not None else ()
    size = int(min(shape[-2:])) if len(shape) >= 2 else int(np.ceil(4 * wrad))
    hdr["WINRAD"] = (float(wrad), "[pix] window radius (from WRAD)")
    hdr["WINSIZE"] = (max(size, 4), "[pix] window size (the SCI frames')")
    hdr["WINORD"] = (XARA_WINDOW_ORDER, "window exp(-(r/WINRAD)**WINORD)")
    notes.append(f"extraction window from WRAD: exp(-(r / {wrad:g} pix)^4) on {size} pixels")


def read_kpfits_parts(path, *, detpa=None):
    """Read a KPFITS file of kernel-phase data (kpifs's or another tool's) into plain arrays.

    Parameters
    ----------
    path : str or Path
    detpa : float or array-like, optional
        Detector position angles (deg; one, or one per frame) replacing the
        file's (for files whose angles are missing or inconsistent).

    Returns
    -------
    dict
        ``model`` (see `read_model_parts`), ``kp`` (nframe, nwave, nkp),
        ``wavelengths`` and ``bandwidth`` (Quantity in um, or None),
        ``pixscale`` (Quantity), ``covariance`` (nwave, nkp, nkp: one frame's;
        the mean when the file has one per frame), ``kp_err`` (nframe, nwave,
        nkp: per-frame errors from KP-SIGM or per-frame covariances, or None),
        ``joint_covariance``, ``covariance_rows``, ``detpa`` (nframe,),
        ``phases``, ``amplitudes`` (arrays or None), ``header`` and ``meta``
        (``layout``, ``instrument``, ``telescope``, ``diameter``,
        ``detpa_source``, ``covariance_source``, ``wavelength_source``,
        ``notes``, ...).

    Raises
    ------
    `~kpifs.KpifsError`
        Naming the file and the missing or inconsistent part.

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.io.kpfits import read_kpfits_parts
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = tmp.name + "/kp.fits"
    >>> _ = KernelPhaseData(np.zeros((2, 1, km.n_kp)), [1.6] * u.um, 10 * u.mas, km).write(path)
    >>> parts = read_kpfits_parts(path)
    >>> parts["kp"].shape, parts["meta"]["layout"]
    ((2, 1, 37), 'kpifs')
    >>> tmp.cleanup()
    """
    path = str(path)
    try:
        with open_fits(path, verify=True) as hdul:
            return _read_data(hdul, path, detpa)
    except (OSError, TypeError, KeyError, ValueError, IndexError) as exc:
        if isinstance(exc, KpifsError):
            raise
        raise KpifsError(f"{path}: cannot read KPFITS: {exc}") from None


def _read_data(hdul, path, detpa):
    names = [h.name for h in hdul]
    hdr = hdul[0].header.copy()
    if "KP-DATA" in names:
        kp_name = "KP-DATA"
    else:
        legacy = sorted((n for n in names if n.startswith("KP-DATA") and n[7:].isdigit()),
                        key=lambda n: int(n[7:]))
        if not legacy:
            raise KpifsError(f"{path}: no KP-DATA extension: not kernel-phase data")
        if len(legacy) > 1:
            raise KpifsError(f"{path}: {len(legacy)} data sets ({', '.join(legacy)}; xara's "
                             f"legacy layout): kpifs reads one star per file")
        kp_name = legacy[0]
    if hdul[kp_name].data is None:
        raise KpifsError(f"{path}: {kp_name} has no data")
    layout = _layout(hdr, names)
    model = read_model_parts(hdul, source=path)
    notes = list(model["notes"])
    nkp = model["kernel"].shape[0]
    wl, bw, wsrc = _read_wavelengths(hdul, hdr, path)
    raw = hdul[kp_name].data
    sig_shape = (np.shape(hdul["KP-SIGM"].data) if "KP-SIGM" in hdul
                 and hdul["KP-SIGM"].data is not None else None)
    kp = _read_kp(raw, kp_name, nkp, len(wl), _frame_count_hint(hdul), sig_shape, path,
                  notes)
    kp_err, cov, csrc = _read_uncertainties(hdul, kp, np.shape(raw), path, notes)
    pa, dsrc = _read_detpa(hdul, hdr, kp_name, kp.shape[0], detpa, path)
    if pa is None:
        notes.append("no detector position angle (DETPA extension, TEL table or card): "
                     "sky orientation unknown")
    phases, amps = _read_cvis(hdul, layout, (kp.shape[0], kp.shape[1], len(model["uv"])),
                              path, notes)
    jcov = np.array(hdul["KP-JCOV"].data, float) if "KP-JCOV" in hdul else None
    rows = np.array(hdul["KP-COVROWS"].data, float) if "KP-COVROWS" in hdul else None
    fit_rows = np.array(hdul["KP-FITROWS"].data, float) if "KP-FITROWS" in hdul else None
    blk_rows = np.array(hdul["KP-BLKROWS"].data, float) if "KP-BLKROWS" in hdul else None
    pixscale = _read_pixscale(hdr, path)
    _foreign_window(hdul, hdr, notes)
    inst = next((str(hdr[k]).strip() for k in ("INSTRUME", "CURRINST")
                 if str(hdr.get(k, "")).strip()), None)
    tel = str(hdr["TELESCOP"]).strip() if str(hdr.get("TELESCOP", "")).strip() else None
    diam = model["diameter"]
    if diam is None and tel is not None:
        diam = next((d for key, d in _TELESCOPE_DIAMETERS if key in tel.upper()), None)
    for note in notes:
        log.info("%s: %s", path, note)
    meta = {"source": path, "layout": layout,
            "calibrated": _flag(hdr.get("CALFLAG", False)),
            "calibrators": [hdr[k] for k in hdr if k.startswith("KPCAL") and k[5:].isdigit()],
            "instrument": inst, "telescope": tel, "diameter": diam,
            "detpa_source": dsrc, "covariance_source": csrc, "wavelength_source": wsrc,
            "notes": notes}
    if "NFRTGT" in hdr:
        meta["n_target_frames"] = int(hdr["NFRTGT"])
    if _number(hdr.get("PASPAN")) is not None:
        meta["detpa_span"] = _number(hdr["PASPAN"])
    em = {key: hdr[name] for key, (name, _) in _ERROR_MODEL_CARDS.items() if name in hdr}
    if em:
        meta["error_model"] = em
    if "DETPA-FR" in hdul and hdul["DETPA-FR"].data is not None:
        meta["detpa_frames"] = [float(v) for v in np.ravel(hdul["DETPA-FR"].data)]
    if "NKPCH1" in hdr:
        meta["channel_n_kp"] = [int(hdr[f"NKPCH{i}"]) for i in range(1, len(wl) + 1)
                                if f"NKPCH{i}" in hdr]
        if len(meta["channel_n_kp"]) != len(wl) or max(meta["channel_n_kp"]) > kp.shape[-1]:
            raise KpifsError(f"{path}: NKPCH<i> cards do not give one count of at most "
                             f"{kp.shape[-1]} kernel phases per channel ({len(wl)})")
    if "BADFRMS" in hdr:
        meta["bad_frames"] = str(hdr["BADFRMS"])
        meta["n_dropped_frames"] = int(hdr.get("NDROPFR", 0))
    return {"model": model, "kp": kp, "wavelengths": wl, "bandwidth": bw,
            "pixscale": pixscale, "covariance": cov, "kp_err": kp_err,
            "joint_covariance": jcov, "covariance_rows": rows,
            "fit_covariance_rows": fit_rows, "block_rows": blk_rows, "detpa": pa,
            "rotation": rotation_from_hdul(hdul, path),
            "spectral": _spectral_from_hdul(hdul, len(wl), path),
            "phases": phases, "amplitudes": amps, "header": hdr, "meta": meta}


def _spectral_from_hdul(hdul, n_wave, path):
    """The spectral-differential record of KP-SDK (issue 39), or None."""
    if "KP-SDK" not in hdul:
        return None
    h = hdul["KP-SDK"]
    prof = None if h.data is None else np.asarray(h.data, float)
    if prof is None or prof.ndim != 2 or prof.shape[0] != n_wave or not prof.shape[1] \
            or not np.all(np.isfinite(prof)):
        raise KpifsError(f"{path}: KP-SDK must hold finite profiles (nwave={n_wave}, "
                         f"nprofile), got {None if prof is None else prof.shape}")
    out = {"profiles": prof, "basis": str(h.header.get("SDKBASIS", "")),
           "order": int(h.header.get("SDKORDER", -1))}
    if "KP-SDKSTAT" in hdul:
        rows = hdul["KP-SDKSTAT"].data
        rows = None if rows is None else np.asarray(rows, float)
        if rows is None or rows.ndim != 3 or rows.shape[1] != n_wave \
                or not np.all(np.isfinite(rows)):
            raise KpifsError(f"{path}: KP-SDKSTAT must hold finite rows (nrow, nwave={n_wave}, "
                             f"nkp), got {None if rows is None else rows.shape}")
        out["static_rows"] = rows
        hdr = hdul["KP-SDKSTAT"].header
        sizes = []
        while f"SDKGRP{len(sizes) + 1}" in hdr:
            sizes.append(int(hdr[f"SDKGRP{len(sizes) + 1}"]))
        if sizes:
            if sum(sizes) != len(rows) or min(sizes) < 1:
                raise KpifsError(f"{path}: KP-SDKSTAT's groups (SDKGRPn: {sizes}) must "
                                 f"share its {len(rows)} rows")
            out["static_groups"] = sizes
        if "SDKFILL" in hdr:
            out["static_filled"] = int(hdr["SDKFILL"])
    return out
