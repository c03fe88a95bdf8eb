"""Kernel-phase data in the KPFITS1 layout used by the kernel-phase community.

Primary header ``CONTENT = 'KPFITS1'`` with ``PSCALE`` (mas), ``DIAM`` (m),
``PROCSOFT``, ``CALFLAG``; the input cube's header cards are kept. Extensions:
APERTURE, UV-PLANE, KER-MAT, BLM-MAT (the model), KP-DATA
``(nframe, nwave, nkp)`` in rad, optional KP-SIGM and KP-COV, CWAVEL (table of
wavelengths and bandwidths in m), DETPA (deg), and optional CVIS-DATA
``(2, nframe, nwave, nuv)`` holding the raw Fourier phases and amplitudes.
"""
import numpy as np
from astropy import units as u
from astropy.io import fits
from astropy.table import Table

from .._utils import write_hdulist
from ..exceptions import KpifsError

__all__ = ["kpd_to_hdulist", "write_kpfits", "read_kpfits"]

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


def _card(value, comment):
    """A (value, comment) pair that fits one 80-character card (long paths keep their end)."""
    value = str(value)
    if len(value) > 66:
        value = "..." + value[-63:]
    return (value, comment) if len(value) + len(comment) < 64 else (value, "")


def kpd_to_hdulist(kpd, *, inputs=(), history=()):
    """Return *kpd* (`~kpifs.KernelPhaseData`) as a KPFITS1 `~astropy.io.fits.HDUList`.

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
    from .. import __version__
    km = kpd.kernel_model
    hdr = _clean_header(kpd.header)
    hdr["CONTENT"] = ("KPFITS1", "kernel-phase FITS exchange format")
    hdr["PSCALE"] = (float(kpd.pixscale.to_value(u.mas)), "[mas] pixel scale")
    if "diameter_m" in km.pupil.meta:
        hdr["DIAM"] = (float(km.pupil.meta["diameter_m"]), "[m] pupil diameter")
    hdr["PROCSOFT"] = (f"kpifs {__version__}", "software that wrote this file")
    hdr["KPIFSVER"] = (__version__, "kpifs version")
    hdr["CALFLAG"] = (bool(kpd.meta.get("calibrated", False)), "calibrator subtracted")
    hdr["NKP"] = (kpd.n_kp, "number of kernel phases")
    hdr["NUV"] = (km.n_uv, "number of uv points")
    for key, val in (("WINSIZE", kpd.meta.get("window_size")),
                     ("WINRAD", kpd.meta.get("window_radius")),
                     ("WINORD", kpd.meta.get("window_order"))):
        if val is not None:
            hdr[key] = (val, "extraction window (pixels)")
    for i, name in enumerate(inputs, 1):
        hdr[f"KPIN{i}"] = _card(name, "input file")
    for i, name in enumerate(kpd.meta.get("calibrators", []), 1):
        hdr[f"KPCAL{i}"] = _card(name, "calibrator")
    if kpd.meta.get("calibrated"):
        hdr["NFRTGT"] = (int(kpd.meta.get("n_target_frames", 0)), "target frames averaged")
        hdr.add_history(f"kpifs {__version__}: calibrated with "
                        f"{len(kpd.meta.get('calibrators', []))} calibrator(s)")
    for line in history:
        hdr.add_history(line)
    hdr.add_history(f"kpifs {__version__}: kernel phases of {kpd.meta.get('source', '?')}")
    hdus = [fits.PrimaryHDU(header=hdr), *km.to_hdus()]
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
        hdus.append(fits.ImageHDU(np.stack([kpd.phases, kpd.amplitudes]), name="CVIS-DATA"))
    return fits.HDUList(hdus)


def write_kpfits(kpd, path, *, overwrite=False, inputs=(), history=()):
    """Write *kpd* to *path* (atomically; never over an input).

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


def read_kpfits(path):
    """Read a KPFITS1 file into `~kpifs.KernelPhaseData`.

    Kernel rows need not be unit-normalised and redundancies may be integers
    or floats (files written by other tools).

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.io import read_kpfits
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> path = tempfile.mkdtemp() + "/kp.fits"
    >>> _ = KernelPhaseData(np.zeros((2, 1, km.n_kp)), [1.6] * u.um, 10 * u.mas, km).write(path)
    >>> read_kpfits(path).shape
    (2, 1, 44)
    """
    from ..extract import KernelPhaseData
    from ..kernel import KernelModel
    try:
        with fits.open(path, memmap=False) as hdul:
            if "KP-DATA" not in hdul:
                raise KpifsError(f"{path}: no KP-DATA extension: not kernel-phase data")
            km = KernelModel.from_hdulist(hdul, source=path)
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
    except (OSError, TypeError, KeyError) as exc:
        raise KpifsError(f"{path}: cannot read KPFITS: {exc}") from None
    if "PSCALE" not in hdr:
        raise KpifsError(f"{path}: no pixel scale (PSCALE) in the primary header")
    meta = {"source": str(path), "calibrated": bool(hdr.get("CALFLAG", False))}
    for key, name in (("WINSIZE", "window_size"), ("WINRAD", "window_radius"),
                      ("WINORD", "window_order")):
        if key in hdr:
            meta[name] = hdr[key]
    meta["calibrators"] = [hdr[k] for k in hdr if k.startswith("KPCAL") and k[5:].isdigit()]
    if cov is not None and cov.ndim == 4 and cov.shape[0] > 1 and not hdr.get("COVSHARE"):
        cov = cov.mean(axis=0)   # per-frame covariances from another tool: their mean
    return KernelPhaseData(kp, wl.to(u.um), hdr["PSCALE"] * u.mas, km, phases=phases,
                           amplitudes=amps, covariance=cov, joint_covariance=jcov,
                           covariance_rows=rows, header=hdr,
                           detpa=detpa, bandwidth=bw, meta=meta)
