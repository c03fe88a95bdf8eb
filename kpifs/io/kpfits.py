"""The KPFITS1 layout of the kernel-phase community: kernel models and kernel-phase data.

kpifs writes (`kpd_to_hdulist`): primary header ``CONTENT = 'KPFITS1'``,
``PROCSOFT``, ``INSTRUME``, ``TELESCOP``, ``DIAM`` (m), ``PSCALE`` (mas),
``WRAD`` (window radius, pixels), ``CALFLAG``, ``NFRAME``/``NWAVE`` and the
input cube's cards (``EXPTIME``, ``DATE-OBS``, ``MJD`` where known, with
``DATEOBS``/``MJD-OBS`` added for the readers that look for those names).
Extensions: APERTURE, UV-PLANE (redundancies as floats), KER-MAT, BLM-MAT
(all sub-apertures), KP-DATA ``(nframe, nwave, nkp)`` rad, KP-SIGM (same
shape), KP-COV ``(nframe, nwave, nkp, nkp)`` rad^2, CWAVEL (table CWAVEL,
BWIDTH, DWAVEL in m), DETPA ``(nframe,)`` deg (the position angle, East of
North, of the detector +y axis), optional CVIS-DATA ``(2, nframe, nwave, nuv)``
holding the real and imaginary parts of the flux-normalised visibilities
(float32),
and kpifs's own KP-COVROWS and KP-JCOV.

It reads (`read_kpfits_parts`) the variants other tools write as well:
BLM-MAT with one column fewer than sub-apertures (the first aperture is the
phase reference: its column is rebuilt as minus the row sums), KER-MAT rows
of any norm (kept as stored), integer or float redundancies, KP-DATA 1-D,
2-D ``(nframe, nkp)`` or 3-D, KP-SIGM as errors or per-frame covariance
matrices, KP-COV per frame or shared (NaN placeholders mean absent),
wavelengths from a CWAVEL table or image or the CWAVEL/CWAVE/CENWAVE/
ESO INS CWLEN cards, and detector position angles from a DETPA extension, a
TEL table (``DETPA`` or ``pa``), a KP-INFO table or a DETPA/ORIENTAT card.
What cannot be interpreted is refused with a `~kpifs.KpifsError` naming the
file and the part.

This module knows the layout, not the science: it turns objects into HDUs
(reading only the attributes it writes) and files into plain arrays and
headers. The containers (`~kpifs.kernel.KernelModel`,
`~kpifs.data.KernelPhaseData`) connect these functions to astropy's unified
I/O registry, so that ``KernelPhaseData.read(path)`` works.
"""
import logging

import numpy as np
from astropy import units as u
from astropy.io import fits
from astropy.table import Table

from .._meta import VERSION
from .._utils import write_hdulist
from ..exceptions import KpifsError
from .cube import open_fits
from .wavelengths import parse_wavelengths

__all__ = ["model_hdus", "model_hdulist", "read_model_parts", "read_model_file",
           "kpd_to_hdulist", "write_kpfits", "read_kpfits_parts", "has_kernel_model",
           "KPCOV_COPY_LIMIT"]

log = logging.getLogger(__name__)

#: Largest KP-COV (bytes) written with one copy of the (shared) covariance per
#: frame, so that readers indexing ``KP-COV[i]`` (fouriever) find it for every
#: frame. Larger ones are written once, ``(1, nwave, nkp, nkp)``, with
#: ``COVFRAME = 'FIRST'``: identical copies of a 303 x 303 x 22-channel matrix
#: cost 16 MB per frame, 1.6 GB for 100 frames.
KPCOV_COPY_LIMIT = 64 * 2 ** 20

# INSTRUME and TELESCOP of kpifs's instrument readers (when the header has none)
_INSTRUMENT_CARDS = {"charis": ("CHARIS", "Subaru"), "sphere": ("SPHERE", "ESO-VLT-U3")}
# telescope name -> diameter (m), the table fouriever uses when DIAM is absent
#: Error-model parameters (``meta['error_model']``) <-> primary header cards.
_ERROR_MODEL_CARDS = {
    "model": ("EMMODEL", "error model: modes (kpifs.errormodel) or frames"),
    "n_modes": ("EMNMODES", "modes of the frame scatter kept"),
    "dof": ("EMDOF", "degrees of freedom nu = sum (N_s - 1)"),
    "mode_fraction": ("EMFRAC", "modes kept / nu"),
    "residual_method": ("EMRESID", "calibration-residual estimator"),
    "residual_fraction": ("EMRFRAC", "residual share of the modelled variance"),
    "tau_max": ("EMTAUMAX", "largest autocorrelation time (frames)"),
    "tau_mean": ("EMTAU", "mean autocorrelation time (frames)"),
    "inflation": ("EMINFL", "variance / independent-frame variance (mean)"),
    "hartlap": ("EMHARTL", "Hartlap factor applied (frames model)"),
}
_TELESCOPE_DIAMETERS = (("ESO-VLT", 8.2), ("KECK", 10.95))

# cards of an input header that describe its data array and must not be copied
_STRUCTURAL = {"SIMPLE", "BITPIX", "NAXIS", "EXTEND", "BSCALE", "BZERO", "PCOUNT", "GCOUNT",
               "XTENSION", "CHECKSUM", "DATASUM", "END"}


def _clean_header(header):
    out = fits.Header()
    for card in header.cards:
        key = card.keyword
        if key in _STRUCTURAL or key.startswith("NAXIS") or key in ("", "HISTORY", "COMMENT"):
            continue
        try:
            out.append(card)
        except (ValueError, fits.VerifyError):
            pass
    for key in ("HISTORY", "COMMENT"):
        for val in header.get(key, []):
            out.add_history(str(val)) if key == "HISTORY" else out.add_comment(str(val))
    return out


def card(value, comment):
    """A (value, comment) pair that fits one 80-character card (long paths keep their end)."""
    value = str(value)
    if len(value) > 66:
        value = "..." + value[-63:]
    return (value, comment) if len(value) + len(comment) < 64 else (value, "")


# --- small helpers ----------------------------------------------------------------
def _column(table_hdu, *names):
    """A column of a table HDU by any of *names* (case-insensitive), or None."""
    low = {n.lower(): n for n in table_hdu.columns.names}
    for n in names:
        if n.lower() in low:
            return np.asarray(table_hdu.data[low[n.lower()]])
    return None


def _number(value):
    """*value* as a finite float, or None (strings such as 'NONE', 'unavailable', NaN)."""
    if isinstance(value, bool):
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if np.isfinite(v) else None


def _flag(value):
    """A FITS flag written as a boolean or as a string ('False', 'T', ...)."""
    if isinstance(value, str):
        return value.strip().lower() in ("true", "t", "1", "yes", "y")
    return bool(value)


def _all_nan(data):
    a = np.asarray(data, float)
    return a.size > 0 and not np.any(np.isfinite(a))


def _label_columns(hdu, comments):
    """Comments of the TTYPEn cards of a table HDU: ``{column: comment}``."""
    for i, name in enumerate(hdu.columns.names, 1):
        if name in comments:
            hdu.header.comments[f"TTYPE{i}"] = comments[name]
    return hdu


# --- kernel models ----------------------------------------------------------------
def model_hdus(model):
    """The model extensions APERTURE, UV-PLANE, KER-MAT, BLM-MAT of a kernel model.

    Redundancies are written as floats (grey models would be truncated by
    integers) and BLM-MAT has one column per sub-aperture.

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.io.kpfits import model_hdus
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> [h.name for h in model_hdus(km)]
    ['APERTURE', 'UV-PLANE', 'KER-MAT', 'BLM-MAT']
    """
    pupil = model.pupil
    xy = pupil.xy.to_value(u.m)
    ap = Table([xy[:, 0], xy[:, 1], np.asarray(pupil.transmission, float)],
               names=("XXC", "YYC", "TRM"))
    ap["XXC"].unit = ap["YYC"].unit = "m"
    hap = _label_columns(fits.BinTableHDU(ap, name="APERTURE"), {
        "XXC": "sub-aperture x (along image columns) [m]",
        "YYC": "sub-aperture y (along image rows) [m]",
        "TRM": "sub-aperture transmission (0 < t <= 1)"})
    hap.header["PUPNAME"] = (pupil.name[:60], "pupil model name")
    if pupil.step is not None:
        hap.header["STEP"] = (pupil.step.to_value(u.m), "[m] grid step")
    uv = model.uv.to_value(u.m)
    uvt = Table([uv[:, 0], uv[:, 1], np.asarray(model.redundancy, float)],
                names=("UUC", "VVC", "RED"))
    uvt["UUC"].unit = uvt["VVC"].unit = "m"
    huv = _label_columns(fits.BinTableHDU(uvt, name="UV-PLANE"), {
        "UUC": "baseline u (along image columns) [m]",
        "VVC": "baseline v (along image rows) [m]",
        "RED": "redundancy: summed pair weights (float)"})
    hk = fits.ImageHDU(model.kernel, name="KER-MAT")
    hk.header["RANK"] = (model.rank, "rank of the phase-transfer matrix")
    hk.header["COMMENT"] = "kernel matrix K (nkp, nuv): kernel phases = K @ Fourier phases"
    hb = fits.ImageHDU(model.blm, name="BLM-MAT")
    hb.header["COMMENT"] = ("baseline-mapping matrix A (nuv, nsub), every sub-aperture; "
                            "phase transfer = A / RED")
    return [hap, huv, hk, hb]


def model_hdulist(model):
    """A kernel model alone as a KPFITS1 file (primary header and model extensions).

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.io.kpfits import model_hdulist
    >>> hdul = model_hdulist(KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m)))
    >>> hdul[0].header["CONTENT"], hdul[0].header["NKP"]
    ('KPFITS1', 44)
    """
    hdr = fits.Header()
    hdr["CONTENT"] = ("KPFITS1", "kernel-phase FITS exchange format")
    hdr["PROCSOFT"] = (f"kpifs {VERSION}", "software that wrote this file")
    hdr["KPIFSVER"] = (VERSION, "kpifs version")
    hdr["NSUB"] = (model.pupil.n_sub, "number of sub-apertures")
    hdr["NUV"] = (model.n_uv, "number of uv points")
    hdr["NKP"] = (model.n_kp, "number of kernel phases")
    if "diameter_m" in model.pupil.meta:
        hdr["DIAM"] = (float(model.pupil.meta["diameter_m"]), "[m] telescope diameter")
    hdr["HISTORY"] = f"kpifs {VERSION}: kernel model of pupil {model.pupil.name}"
    return fits.HDUList([fits.PrimaryHDU(header=hdr), *model_hdus(model)])


def read_model_parts(hdul, *, source="<memory>"):
    """The model extensions of an open KPFITS file as plain arrays.

    Accepts the variants other tools write: integer redundancies, KER-MAT
    rows of any norm (kept as stored: kernel phases, errors and covariances
    of the same file are in the same units), grey transmissions, and a
    BLM-MAT with one column fewer than sub-apertures (the first aperture is
    the phase reference; its column is rebuilt as minus the row sums, since
    every pair adds ``+w`` and ``-w`` to its row).

    Returns a dict: ``xy`` (nsub, 2) and ``transmission`` of the sub-apertures,
    ``step`` (m or None), ``name``, ``uv`` (nuv, 2) m, ``redundancy``, ``blm``
    (nuv, nsub) or None when the file has no BLM-MAT, ``blm_rebuilt`` (the
    reference column was rebuilt), ``kernel`` (nkp, nuv), ``rank`` (or None),
    ``diameter`` (m, primary ``DIAM``, or None) and ``notes`` (what was
    adapted, for the log).

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.io.kpfits import model_hdulist, read_model_parts
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> parts = read_model_parts(model_hdulist(km))
    >>> parts["kernel"].shape == (km.n_kp, km.n_uv), parts["name"]
    (True, 'subaru')
    """
    notes = []
    for ext, what in (("UV-PLANE", "the uv coordinates"), ("KER-MAT", "the kernel matrix"),
                      ("APERTURE", "the sub-aperture positions")):
        if ext not in hdul:
            raise KpifsError(f"{source}: not a kernel model: no {ext} extension ({what})")
    uvh, aph = hdul["UV-PLANE"], hdul["APERTURE"]
    for h, cols in ((uvh, ("UUC", "VVC")), (aph, ("XXC", "YYC"))):
        if not isinstance(h, fits.BinTableHDU) or any(_column(h, c) is None for c in cols):
            have = h.columns.names if isinstance(h, fits.BinTableHDU) else "an image"
            raise KpifsError(f"{source}: {h.name} lacks the {'/'.join(cols)} columns "
                             f"(has {have})")
    uv = np.column_stack([_column(uvh, "UUC"), _column(uvh, "VVC")]).astype(float)
    nuv = len(uv)
    red = _column(uvh, "RED")
    if red is None:
        notes.append("UV-PLANE has no RED column: redundancies set to 1")
        red = np.ones(nuv)
    red = np.asarray(red, float)
    bad = ~(np.isfinite(red) & (red > 0))
    if bad.any():
        hint = " (integer redundancies of a grey model?)" if np.all(red == np.rint(red)) else ""
        raise KpifsError(f"{source}: UV-PLANE RED has {int(bad.sum())} value(s) that are not "
                         f"> 0{hint}")
    xy = np.column_stack([_column(aph, "XXC"), _column(aph, "YYC")]).astype(float)
    nap = len(xy)
    trm = _column(aph, "TRM")
    trm = np.ones(nap) if trm is None else np.asarray(trm, float)
    if hdul["KER-MAT"].data is None:
        raise KpifsError(f"{source}: KER-MAT has no data")
    kmat = np.array(hdul["KER-MAT"].data, float)
    if kmat.ndim != 2 or kmat.shape[1] != nuv:
        raise KpifsError(f"{source}: KER-MAT has shape {kmat.shape} but UV-PLANE has {nuv} "
                         f"rows: expected (nkp, {nuv})")
    if not np.all(np.isfinite(kmat)) or not np.all(np.isfinite(uv)) or \
            not np.all(np.isfinite(xy)):
        raise KpifsError(f"{source}: KER-MAT, UV-PLANE or APERTURE holds NaN or inf")
    norms = np.linalg.norm(kmat, axis=1)
    if not np.allclose(norms, 1.0, rtol=1e-6):
        notes.append(f"KER-MAT rows are not unit-normalised (norms {norms.min():.3g} to "
                     f"{norms.max():.3g}): kept as stored")
    blm, rebuilt = None, False
    if "BLM-MAT" in hdul and hdul["BLM-MAT"].data is not None:
        b = np.array(hdul["BLM-MAT"].data, float)
        if b.ndim != 2 or b.shape[0] != nuv:
            raise KpifsError(f"{source}: BLM-MAT has shape {b.shape} but UV-PLANE has {nuv} "
                             f"rows: expected ({nuv}, {nap}) or ({nuv}, {nap - 1})")
        if b.shape[1] == nap:
            blm = b
        elif b.shape[1] == nap - 1:
            # the first aperture is the phase reference of xara, PyKernel and jwst-kpi
            blm, rebuilt = np.column_stack([-b.sum(axis=1), b]), True
            notes.append(f"BLM-MAT has {nap - 1} columns for {nap} sub-apertures: the first "
                         f"(reference) aperture's column rebuilt")
        else:
            raise KpifsError(f"{source}: BLM-MAT has {b.shape[1]} columns but APERTURE has "
                             f"{nap} sub-apertures: expected {nap} or {nap - 1}")
    return {"xy": xy, "transmission": trm,
            "step": _number(aph.header.get("STEP")),
            "name": str(aph.header.get("PUPNAME", source)),
            "uv": uv, "redundancy": red, "blm": blm, "blm_rebuilt": rebuilt,
            "kernel": kmat, "rank": hdul["KER-MAT"].header.get("RANK"),
            "diameter": _number(hdul[0].header.get("DIAM")), "notes": notes}


def read_model_file(path):
    """`read_model_parts` of a file (checksums verified).

    Examples
    --------
    >>> import tempfile, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.io.kpfits import read_model_file
    >>> path = tempfile.mkdtemp() + "/model.fits"
    >>> _ = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m)).write(path)
    >>> read_model_file(path)["kernel"].shape
    (44, 66)
    """
    try:
        with open_fits(path, verify=True) as hdul:
            return read_model_parts(hdul, source=path)
    except (OSError, TypeError, ValueError) as exc:
        if isinstance(exc, KpifsError):
            raise
        raise KpifsError(f"{path}: cannot read kernel model: {exc}") from None


def has_kernel_model(path):
    """True when the FITS file *path* holds a KER-MAT extension (a kernel model).

    Examples
    --------
    >>> import tempfile, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.io.kpfits import has_kernel_model
    >>> path = tempfile.mkdtemp() + "/model.fits"
    >>> _ = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m)).write(path)
    >>> has_kernel_model(path)
    True
    """
    try:
        with fits.open(path) as hdul:
            return "KER-MAT" in hdul
    except FileNotFoundError:
        raise KpifsError(f"{path}: file not found") from None
    except OSError as exc:
        raise KpifsError(f"{path}: cannot read: {exc}") from None


# --- kernel-phase data: writing ------------------------------------------------------
def _instrument_cards(kpd):
    """INSTRUME and TELESCOP: the input header's, else those of kpifs's reader, else UNKNOWN."""
    hdr = kpd.header
    inst, tel = _INSTRUMENT_CARDS.get(str(kpd.meta.get("instrument", "")).lower(),
                                      ("UNKNOWN", "UNKNOWN"))
    for key in ("INSTRUME", "CURRINST"):
        if str(hdr.get(key, "")).strip():
            inst = str(hdr[key]).strip()
            break
    if str(hdr.get("TELESCOP", "")).strip():
        tel = str(hdr["TELESCOP"]).strip()
    return inst, tel


def _diameter_card(km, header):
    """(DIAM, comment): the pupil model's diameter, the input's DIAM, or the pupil extent."""
    d = _number(km.pupil.meta.get("diameter_m"))
    if d is not None:
        return d, "[m] telescope diameter (pupil model)"
    d = _number(header.get("DIAM"))
    if d is not None:
        return d, "[m] telescope diameter"
    step = 0.0 if km.pupil.step is None else float(km.pupil.step.to_value(u.m))
    return (float(km.baseline_length.to_value(u.m).max()) + step,
            "[m] pupil extent: longest baseline + grid step")


def kpd_to_hdulist(kpd, *, inputs=(), history=()):
    """Return kernel-phase data (`~kpifs.KernelPhaseData`) as a KPFITS1 HDUList.

    The file opens in the kernel-phase community's readers (fouriever's
    PROCSOFT branch, xara's KPFITS reader): see the module docstring for the
    cards and extensions. A shared covariance is written as KP-COV with one
    copy per frame up to `KPCOV_COPY_LIMIT` bytes (``COVFRAME = 'EVERY'``),
    beyond that once (``COVFRAME = 'FIRST'``); ``COVSHARE = T`` says that it
    is the same for every frame. KP-SIGM holds ``kpd.kp_err`` when known, else
    the square root of the covariance's diagonal (``SIGMFROM = 'KP-COV'``).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.io.kpfits import kpd_to_hdulist
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> hdul = kpd_to_hdulist(KernelPhaseData(np.zeros((1, 1, km.n_kp)), [1.6] * u.um,
    ...                                       10 * u.mas, km))
    >>> [h.name for h in hdul][:6]
    ['PRIMARY', 'APERTURE', 'UV-PLANE', 'KER-MAT', 'BLM-MAT', 'KP-DATA']
    >>> hdul[0].header["INSTRUME"], hdul[0].header["DIAM"]
    ('UNKNOWN', 7.92)
    """
    km = kpd.kernel_model
    nframe, nwave, nkp = kpd.kp.shape
    hdr = _clean_header(kpd.header)
    inst, tel = _instrument_cards(kpd)
    hdr["CONTENT"] = ("KPFITS1", "kernel-phase FITS exchange format")
    hdr["PROCSOFT"] = (f"kpifs {VERSION}", "software that wrote this file")
    hdr["KPIFSVER"] = (VERSION, "kpifs version")
    hdr["INSTRUME"] = (inst, "instrument")
    hdr["TELESCOP"] = (tel, "telescope")
    hdr["DIAM"] = _diameter_card(km, kpd.header)
    hdr["PSCALE"] = (float(kpd.pixscale.to_value(u.mas)), "[mas] pixel scale")
    if kpd.window is not None:
        hdr["WRAD"] = (kpd.window.radius, "[pix] radius of the extraction window")
        kpd.window.to_header(hdr)
    else:
        hdr["WRAD"] = ("NONE", "no extraction window recorded")
    if "DATE-OBS" in hdr and "DATEOBS" not in hdr:
        hdr["DATEOBS"] = (str(hdr["DATE-OBS"]), "same as DATE-OBS (jwst-kpi's name)")
    if "MJD-OBS" not in hdr and _number(hdr.get("MJD")) is not None:
        hdr["MJD-OBS"] = (_number(hdr["MJD"]), "[d] MJD of the (first) exposure")
    hdr["CALFLAG"] = (bool(kpd.meta.get("calibrated", False)), "calibrator subtracted")
    hdr["NFRAME"] = (nframe, "number of frames")
    hdr["NWAVE"] = (nwave, "number of wavelengths")
    hdr["NKP"] = (nkp, "number of kernel phases")
    hdr["NUV"] = (km.n_uv, "number of uv points")
    if kpd.meta.get("bad_frames"):
        dropped = list(kpd.meta.get("dropped_frames") or [])
        hdr["BADFRMS"] = (str(kpd.meta["bad_frames"]), "bad-frame policy (drop or fail)")
        hdr["NDROPFR"] = (len(dropped), "bad input frames left out")
        if dropped:
            hdr.add_history(f"kpifs {VERSION}: input frames left out (bad): "
                            + ", ".join(map(str, dropped)))
    for i, name in enumerate(inputs, 1):
        hdr[f"KPIN{i}"] = card(name, "input file")
    for i, name in enumerate(kpd.meta.get("calibrators", []), 1):
        hdr[f"KPCAL{i}"] = card(name, "calibrator")
    if kpd.meta.get("calibrated"):
        hdr["NFRTGT"] = (int(kpd.meta.get("n_target_frames", 0)), "target frames averaged")
        if kpd.meta.get("detpa_span") is not None:
            hdr["PASPAN"] = (float(kpd.meta["detpa_span"]),
                             "[deg] DETPA span of the averaged target frames")
        hdr.add_history(f"kpifs {VERSION}: calibrated with "
                        f"{len(kpd.meta.get('calibrators', []))} calibrator(s)")
    em = kpd.meta.get("error_model") or {}
    for key, (name, comment) in _ERROR_MODEL_CARDS.items():
        if em.get(key) is not None:
            value = em[key]
            hdr[name] = (round(value, 6) if isinstance(value, float) else value, comment)
    for line in history:
        hdr.add_history(line)
    hdr.add_history(f"kpifs {VERSION}: kernel phases of {kpd.meta.get('source', '?')}")
    hdus = [fits.PrimaryHDU(header=hdr), *model_hdus(km)]
    kd = fits.ImageHDU(kpd.kp.astype(np.float64), name="KP-DATA")
    kd.header["BUNIT"] = "rad"
    kd.header["COMMENT"] = "kernel phases (nframe, nwave, nkp)"
    hdus.append(kd)
    cov = kpd.covariance
    if kpd.kp_err is not None or cov is not None:
        if kpd.kp_err is not None:
            sig = np.asarray(kpd.kp_err, float)
        else:
            sig = np.broadcast_to(np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1)), kpd.kp.shape)
        hs = fits.ImageHDU(np.ascontiguousarray(sig, dtype=np.float64), name="KP-SIGM")
        hs.header["BUNIT"] = "rad"
        hs.header["COMMENT"] = "1-sigma errors of KP-DATA (nframe, nwave, nkp)"
        if kpd.kp_err is None:
            hs.header["SIGMFROM"] = ("KP-COV", "errors are sqrt(diag(KP-COV))")
        hdus.append(hs)
    if cov is not None:
        cov = np.asarray(cov, float)
        every = nframe == 1 or nframe * cov.nbytes <= KPCOV_COPY_LIMIT
        data = np.broadcast_to(cov, (nframe if every else 1,) + cov.shape)
        hc = fits.ImageHDU(np.ascontiguousarray(data), name="KP-COV")
        hc.header["BUNIT"] = "rad2"
        hc.header["COVSHARE"] = (True, "the same covariance applies to every frame")
        hc.header["COVFRAME"] = ("EVERY" if every else "FIRST",
                                 "one copy per frame" if every else
                                 "written once (too large to copy per frame)")
        hc.header["COMMENT"] = "covariance of one frame's KP-DATA (nframe|1, nwave, nkp, nkp)"
        if not every:
            log.info("%s: KP-COV written once, not per frame (%d frames x %.0f MB): readers "
                     "indexing it per frame find it for frame 0 only", kpd.name, nframe,
                     cov.nbytes / 2 ** 20)
        hdus.append(hc)
    if kpd.covariance_rows is not None:
        hr = fits.ImageHDU(np.asarray(kpd.covariance_rows, float), name="KP-COVROWS")
        hr.header["BUNIT"] = "rad"
        hr.header["COMMENT"] = "rows R with R^T R = covariance of KP-DATA across all channels"
        hdus.append(hr)
    if kpd.joint_covariance is not None:
        hj = fits.ImageHDU(np.asarray(kpd.joint_covariance, float), name="KP-JCOV")
        hj.header["BUNIT"] = "rad2"
        hj.header["COMMENT"] = "joint covariance across channels, index = iwave * nkp + ikp"
        hdus.append(hj)
    wl = kpd.wavelengths.to_value(u.m)
    bw = (u.Quantity(kpd.bandwidth, u.um).to_value(u.m) if kpd.bandwidth is not None
          else (np.gradient(wl) if len(wl) > 1 else 0.05 * wl))
    bw = np.broadcast_to(np.asarray(bw, float), wl.shape)
    cw = Table([wl, bw, bw], names=("CWAVEL", "BWIDTH", "DWAVEL"))
    for name in cw.colnames:
        cw[name].unit = "m"
    hdus.append(_label_columns(fits.BinTableHDU(cw, name="CWAVEL"), {
        "CWAVEL": "central wavelength of the channel [m]",
        "BWIDTH": "channel bandwidth [m]",
        "DWAVEL": "channel bandwidth [m] (same as BWIDTH)"}))
    if kpd.detpa is not None:
        detpa, where = np.asarray(kpd.detpa, float), kpd.meta.get("detpa_source", "given")
    else:
        detpa, where = np.zeros(nframe), "unknown (0 written)"
    hp = fits.ImageHDU(detpa, name="DETPA")
    hp.header["BUNIT"] = "deg"
    hp.header["PASRC"] = card(where, "where the angles come from")
    hp.header["COMMENT"] = "position angle (East of North) of the detector +y axis, per frame"
    hdus.append(hp)
    if kpd.phases is not None and kpd.amplitudes is not None:
        ph, amp = np.asarray(kpd.phases), np.asarray(kpd.amplitudes)
        # diagnostics, stored in float32 (~1e-7 relative): half the file and the write
        cv = np.empty((2,) + ph.shape, np.float32)
        np.multiply(amp, np.cos(ph), out=cv[0], casting="same_kind")
        np.multiply(amp, np.sin(ph), out=cv[1], casting="same_kind")
        hv = fits.ImageHDU(cv, name="CVIS-DATA")
        hv.header["CVISFORM"] = ("REIM", "real and imaginary parts")
        hv.header["COMMENT"] = ("flux-normalised complex visibilities (2, nframe, nwave, nuv): "
                                "real, imaginary")
        hdus.append(hv)
    return fits.HDUList(hdus)


def write_kpfits(kpd, path, *, overwrite=False, inputs=(), history=()):
    """Write kernel-phase data to *path* in the KPFITS1 layout (atomically; never over an input).

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.io import write_kpfits
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> kpd = KernelPhaseData(np.zeros((2, 1, km.n_kp)), [1.6] * u.um, 10 * u.mas, km)
    >>> path = write_kpfits(kpd, tempfile.mkdtemp() + "/kp.fits")
    >>> path.name
    'kp.fits'
    """
    return write_hdulist(kpd_to_hdulist(kpd, inputs=inputs, history=history), path,
                         overwrite=overwrite, inputs=inputs)


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
    >>> path = tempfile.mkdtemp() + "/kp.fits"
    >>> _ = KernelPhaseData(np.zeros((2, 1, km.n_kp)), [1.6] * u.um, 10 * u.mas, km).write(path)
    >>> parts = read_kpfits_parts(path)
    >>> parts["kp"].shape, parts["meta"]["layout"]
    ((2, 1, 44), 'kpifs')
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
    pixscale = _read_pixscale(hdr, path)
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
    if "BADFRMS" in hdr:
        meta["bad_frames"] = str(hdr["BADFRMS"])
        meta["n_dropped_frames"] = int(hdr.get("NDROPFR", 0))
    return {"model": model, "kp": kp, "wavelengths": wl, "bandwidth": bw,
            "pixscale": pixscale, "covariance": cov, "kp_err": kp_err,
            "joint_covariance": jcov, "covariance_rows": rows, "detpa": pa,
            "phases": phases, "amplitudes": amps, "header": hdr, "meta": meta}
