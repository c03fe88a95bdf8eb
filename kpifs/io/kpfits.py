"""The KPFITS1 layout of the kernel-phase community: kernel models and kernel-phase data.

Primary header ``CONTENT = 'KPFITS1'`` with ``PSCALE`` (mas), ``DIAM`` (m),
``PROCSOFT``, ``CALFLAG``; the input cube's header cards are kept. Extensions:
APERTURE, UV-PLANE, KER-MAT, BLM-MAT (the model), KP-DATA
``(nframe, nwave, nkp)`` in rad, optional KP-SIGM and KP-COV, CWAVEL (table of
wavelengths and bandwidths in m), DETPA (deg), and optional CVIS-DATA
``(2, nframe, nwave, nuv)`` holding the raw Fourier phases and amplitudes
(float32).

This module knows the layout, not the science: it turns objects into HDUs
(reading only the attributes it writes) and files into plain arrays and
headers. The containers (`~kpifs.kernel.KernelModel`,
`~kpifs.data.KernelPhaseData`) connect these functions to astropy's unified
I/O registry, so that ``KernelPhaseData.read(path)`` works.
"""
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.io import fits
from astropy.table import Table

from .._meta import VERSION
from .._utils import write_hdulist
from ..exceptions import KpifsError

__all__ = ["model_hdus", "model_hdulist", "read_model_parts", "kpd_to_hdulist",
           "write_kpfits", "read_kpfits_parts", "has_kernel_model"]

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


# --- kernel models ----------------------------------------------------------------
def model_hdus(model):
    """The model extensions APERTURE, UV-PLANE, KER-MAT, BLM-MAT of a kernel model.

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
    ap = Table([xy[:, 0], xy[:, 1], pupil.transmission], names=("XXC", "YYC", "TRM"))
    ap["XXC"].unit = ap["YYC"].unit = "m"
    hap = fits.BinTableHDU(ap, name="APERTURE")
    hap.header["PUPNAME"] = (pupil.name[:60], "pupil model name")
    if pupil.step is not None:
        hap.header["STEP"] = (pupil.step.to_value(u.m), "[m] grid step")
    uv = model.uv.to_value(u.m)
    uvt = Table([uv[:, 0], uv[:, 1], model.redundancy], names=("UUC", "VVC", "RED"))
    uvt["UUC"].unit = uvt["VVC"].unit = "m"
    huv = fits.BinTableHDU(uvt, name="UV-PLANE")
    hk = fits.ImageHDU(model.kernel, name="KER-MAT")
    hk.header["RANK"] = (model.rank, "rank of the phase-transfer matrix")
    hb = fits.ImageHDU(model.blm, name="BLM-MAT")
    hb.header["COMMENT"] = "baseline-mapping matrix A; phase transfer = A / RED"
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
        hdr["DIAM"] = (model.pupil.meta["diameter_m"], "[m] pupil diameter")
    hdr["HISTORY"] = f"kpifs {VERSION}: kernel model of pupil {model.pupil.name}"
    return fits.HDUList([fits.PrimaryHDU(header=hdr), *model_hdus(model)])


def read_model_parts(hdul, *, source="<memory>"):
    """The model extensions of an open KPFITS file as plain arrays.

    Returns a dict: ``xy`` (nsub, 2) and ``transmission`` of the sub-apertures,
    ``step`` (m or None), ``name``, ``uv`` (nuv, 2) m, ``redundancy``, ``blm``
    (nuv, nsub) or None when the file has no BLM-MAT, ``kernel`` (nkp, nuv) and
    ``rank`` (or None).

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
    try:
        ap = hdul["APERTURE"].data
        uvt = hdul["UV-PLANE"].data
        kmat = np.array(hdul["KER-MAT"].data, float)
    except KeyError as exc:
        raise KpifsError(f"{source}: not a kernel model: missing extension {exc}") from None
    trm = np.array(ap["TRM"], float) if "TRM" in ap.names else np.ones(len(ap))
    uv = np.column_stack([uvt["UUC"], uvt["VVC"]]).astype(float)
    if kmat.ndim != 2 or kmat.shape[1] != len(uv):
        raise KpifsError(f"{source}: KER-MAT has shape {kmat.shape} but UV-PLANE has "
                         f"{len(uv)} rows")
    return {"xy": np.column_stack([ap["XXC"], ap["YYC"]]).astype(float), "transmission": trm,
            "step": hdul["APERTURE"].header.get("STEP"),
            "name": hdul["APERTURE"].header.get("PUPNAME", str(source)),
            "uv": uv, "redundancy": np.array(uvt["RED"], float),
            "blm": np.array(hdul["BLM-MAT"].data, float) if "BLM-MAT" in hdul else None,
            "kernel": kmat, "rank": hdul["KER-MAT"].header.get("RANK")}


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


# --- kernel-phase data --------------------------------------------------------------
def kpd_to_hdulist(kpd, *, inputs=(), history=()):
    """Return kernel-phase data (`~kpifs.KernelPhaseData`) as a KPFITS1 HDUList.

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
    """
    km = kpd.kernel_model
    hdr = _clean_header(kpd.header)
    hdr["CONTENT"] = ("KPFITS1", "kernel-phase FITS exchange format")
    hdr["PSCALE"] = (float(kpd.pixscale.to_value(u.mas)), "[mas] pixel scale")
    if "diameter_m" in km.pupil.meta:
        hdr["DIAM"] = (float(km.pupil.meta["diameter_m"]), "[m] pupil diameter")
    hdr["PROCSOFT"] = (f"kpifs {VERSION}", "software that wrote this file")
    hdr["KPIFSVER"] = (VERSION, "kpifs version")
    hdr["CALFLAG"] = (bool(kpd.meta.get("calibrated", False)), "calibrator subtracted")
    hdr["NKP"] = (kpd.n_kp, "number of kernel phases")
    hdr["NUV"] = (km.n_uv, "number of uv points")
    if kpd.window is not None:
        kpd.window.to_header(hdr)
    for i, name in enumerate(inputs, 1):
        hdr[f"KPIN{i}"] = card(name, "input file")
    for i, name in enumerate(kpd.meta.get("calibrators", []), 1):
        hdr[f"KPCAL{i}"] = card(name, "calibrator")
    if kpd.meta.get("calibrated"):
        hdr["NFRTGT"] = (int(kpd.meta.get("n_target_frames", 0)), "target frames averaged")
        hdr.add_history(f"kpifs {VERSION}: calibrated with "
                        f"{len(kpd.meta.get('calibrators', []))} calibrator(s)")
    for line in history:
        hdr.add_history(line)
    hdr.add_history(f"kpifs {VERSION}: kernel phases of {kpd.meta.get('source', '?')}")
    hdus = [fits.PrimaryHDU(header=hdr), *model_hdus(km)]
    kd = fits.ImageHDU(kpd.kp.astype(np.float64), name="KP-DATA")
    kd.header["BUNIT"] = "rad"
    hdus.append(kd)
    cov = kpd.covariance
    if cov is not None:
        sig = np.broadcast_to(np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1)), kpd.kp.shape)
        hs = fits.ImageHDU(np.ascontiguousarray(sig), name="KP-SIGM")
        hs.header["BUNIT"] = "rad"
        hdus.append(hs)
        # one covariance shared by every frame: stored once, with a frame axis of 1
        hc = fits.ImageHDU(np.asarray(cov, float)[None], name="KP-COV")
        hc.header["BUNIT"] = "rad2"
        hc.header["COVSHARE"] = (True, "the same covariance applies to every frame")
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
    bw = (kpd.bandwidth.to_value(u.m) if kpd.bandwidth is not None
          else (np.gradient(wl) if len(wl) > 1 else 0.05 * wl))
    cw = Table([wl, np.broadcast_to(bw, wl.shape)], names=("CWAVEL", "BWIDTH"))
    cw["CWAVEL"].unit = cw["BWIDTH"].unit = "m"
    hdus.append(fits.BinTableHDU(cw, name="CWAVEL"))
    detpa = kpd.detpa if kpd.detpa is not None else np.zeros(kpd.n_frame)
    hdus.append(fits.ImageHDU(np.asarray(detpa, float), name="DETPA"))
    if kpd.phases is not None:
        # diagnostics, stored in float32 (1e-7 rad resolution): half the file and the time
        cv = np.empty((2,) + np.shape(kpd.phases), np.float32)
        cv[0], cv[1] = kpd.phases, kpd.amplitudes
        hdus.append(fits.ImageHDU(cv, name="CVIS-DATA"))
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


def read_kpfits_parts(path):
    """Read a KPFITS1 file of kernel-phase data into plain arrays.

    Kernel rows need not be unit-normalised and redundancies may be integers
    or floats (files written by other tools). Returns a dict with ``model``
    (see `read_model_parts`), ``kp`` (nframe, nwave, nkp), ``wavelengths`` and
    ``bandwidth`` (Quantity or None), ``pixscale`` (Quantity), ``covariance``,
    ``joint_covariance``, ``covariance_rows``, ``detpa``, ``phases``,
    ``amplitudes`` (arrays or None), ``header`` and ``meta``.

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.io.kpfits import read_kpfits_parts
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> path = tempfile.mkdtemp() + "/kp.fits"
    >>> _ = KernelPhaseData(np.zeros((2, 1, km.n_kp)), [1.6] * u.um, 10 * u.mas, km).write(path)
    >>> read_kpfits_parts(path)["kp"].shape
    (2, 1, 44)
    """
    path = str(path)
    if Path(path).is_dir():
        raise KpifsError(f"{path}: is a directory, expected a KPFITS file")
    if not Path(path).exists():
        raise KpifsError(f"{path}: file not found")
    try:
        with fits.open(path, memmap=False) as hdul:
            if "KP-DATA" not in hdul:
                raise KpifsError(f"{path}: no KP-DATA extension: not kernel-phase data")
            model = read_model_parts(hdul, source=path)
            hdr = hdul[0].header.copy()
            kp = np.array(hdul["KP-DATA"].data, float)
            if kp.ndim == 2:
                kp = kp[:, None, :] if "CWAVEL" in hdul and len(hdul["CWAVEL"].data) == 1 \
                    else kp[None]
            if "CWAVEL" in hdul:
                cw = hdul["CWAVEL"].data
                wl = np.array(cw["CWAVEL"], float) * u.m
                bw = np.array(cw["BWIDTH"], float) * u.m if "BWIDTH" in cw.names else None
            elif "CWAVEL" in hdr:
                wl = np.atleast_1d(hdr["CWAVEL"]) * u.m
                bw = None
            else:
                raise KpifsError(f"{path}: no wavelengths (CWAVEL)")
            cov = np.array(hdul["KP-COV"].data, float) if "KP-COV" in hdul else None
            jcov = np.array(hdul["KP-JCOV"].data, float) if "KP-JCOV" in hdul else None
            rows = (np.array(hdul["KP-COVROWS"].data, float) if "KP-COVROWS" in hdul
                    else None)
            detpa = np.array(hdul["DETPA"].data, float) if "DETPA" in hdul else None
            phases = amps = None
            if "CVIS-DATA" in hdul:
                cv = np.array(hdul["CVIS-DATA"].data, float)
                phases, amps = cv[0], cv[1]
    except (OSError, TypeError, KeyError, ValueError) as exc:
        if isinstance(exc, KpifsError):
            raise
        raise KpifsError(f"{path}: cannot read KPFITS: {exc}") from None
    if "PSCALE" not in hdr:
        raise KpifsError(f"{path}: no pixel scale (PSCALE) in the primary header")
    meta = {"source": str(path), "calibrated": bool(hdr.get("CALFLAG", False))}
    meta["calibrators"] = [hdr[k] for k in hdr if k.startswith("KPCAL") and k[5:].isdigit()]
    if cov is not None and cov.ndim == 4 and cov.shape[0] > 1 and not hdr.get("COVSHARE"):
        cov = cov.mean(axis=0)   # per-frame covariances from another tool: their mean
    return {"model": model, "kp": kp, "wavelengths": wl.to(u.um), "bandwidth": bw,
            "pixscale": hdr["PSCALE"] * u.mas, "covariance": cov, "joint_covariance": jcov,
            "covariance_rows": rows, "detpa": detpa, "phases": phases, "amplitudes": amps,
            "header": hdr, "meta": meta}
