"""Kernel models in the KPFITS layout: the APERTURE, UV-PLANE, KER-MAT and BLM-MAT extensions."""
import logging

import numpy as np
from astropy import units as u
from astropy.io import fits

from .._meta import VERSION
from ..exceptions import KpifsError
from ._kpfits_common import _column, _label_columns, _number, _table_hdu
from .cube import open_fits

__all__ = ["model_hdus", "model_hdulist", "read_model_parts", "read_model_file", "has_kernel_model"]

log = logging.getLogger("kpifs.io.kpfits")


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
    ap = _table_hdu({"XXC": xy[:, 0], "YYC": xy[:, 1], "TRM": pupil.transmission},
                    "APERTURE", {"XXC": "m", "YYC": "m"})
    hap = _label_columns(ap, {
        "XXC": "sub-aperture x (along image columns) [m]",
        "YYC": "sub-aperture y (along image rows) [m]",
        "TRM": "sub-aperture transmission (0 < t <= 1)"})
    hap.header["PUPNAME"] = (pupil.name[:60], "pupil model name")
    if pupil.step is not None:
        hap.header["STEP"] = (pupil.step.to_value(u.m), "[m] grid step")
    uv = model.uv.to_value(u.m)
    uvt = _table_hdu({"UUC": uv[:, 0], "VVC": uv[:, 1], "RED": model.redundancy},
                     "UV-PLANE", {"UUC": "m", "VVC": "m"})
    huv = _label_columns(uvt, {
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
    ('KPFITS1', 37)
    """
    hdr = fits.Header()
    hdr["CONTENT"] = ("KPFITS1", "kernel-phase FITS exchange format")
    hdr["PROCSOFT"] = (f"kpifs {VERSION}", "writing software")
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
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = tmp.name + "/model.fits"
    >>> _ = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m)).write(path)
    >>> read_model_file(path)["kernel"].shape
    (37, 89)
    >>> tmp.cleanup()
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
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = tmp.name + "/model.fits"
    >>> _ = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m)).write(path)
    >>> has_kernel_model(path)
    True
    >>> tmp.cleanup()
    """
    try:
        with fits.open(path) as hdul:
            return "KER-MAT" in hdul
    except FileNotFoundError:
        raise KpifsError(f"{path}: file not found") from None
    except OSError as exc:
        raise KpifsError(f"{path}: cannot read: {exc}") from None


# --- kernel-phase data: writing ------------------------------------------------------
