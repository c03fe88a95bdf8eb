"""KPFITS files as other tools write them, and fouriever's way of reading them (tests only).

The layouts are those documented in the interoperability note (xara's
``KPO.save_as_kpfits``, jwst-kpi's ``calwebb_kpi3``, PyKernel/pynrm's NIRC2
files); the arrays come from kpifs's own simulator and extraction, so that
what is read back can be compared with what was written. No third-party file
or code is copied here.

- `write_xara`: SOFTWARE = 'XARA', PSCALE only; KP-DATA (nframe, 1, nkp); NaN
  placeholders for KP-SIGM and KP-COV when absent (KP-COV then has KP-DATA's
  shape); one DETPA broadcast to the frames; CVIS-DATA (real, imag);
  optionally KER-MAT rows scaled (older files) and no BLM-MAT.
- `write_jwstkpi`: PROCSOFT = 'CALWEBB_KPI3', CALFLAG the string 'False',
  RED int16, BLM-MAT without the reference column, KP-DATA 2-D for one
  wavelength, KP-SIGM (nframe, nwave, nkp), KP-COV per frame, CWAVEL table
  with BWIDTH, DETPA per frame.
- `write_pykernel`: images in the primary HDU, BP-MAP, TEL table (``pa``),
  RED int16, BLM-MAT without the reference column, KP-DATA (nframe, nkp),
  KP-SIGM = per-frame covariance matrices, wavelength in header cards; or the
  V410 Tau variant (3-D KP-DATA and KP-SIGM, a 1-element CWAVEL image, a
  DETPA extension).
- `fouriever_like_open`: the sequence of fouriever's kernel-phase reader
  (``inst.open``), failing where it would.
"""
import numpy as np
import astropy.units as u
from astropy.io import fits

MAS = np.pi / 180 / 3600 / 1000


def parts_of(kpd):
    """Plain arrays of a `~kpifs.KernelPhaseData`: model, data and angles."""
    km = kpd.kernel_model
    return dict(xy=km.pupil.xy.to_value(u.m), transmission=km.pupil.transmission,
                uv=km.uv.to_value(u.m), redundancy=km.redundancy, kernel=km.kernel,
                blm=km.blm, kp=kpd.kp, wavelengths=kpd.wavelengths.to_value(u.m),
                pixscale=kpd.pixscale.to_value(u.mas))


def sky_to_detector(dra, ddec, detpa):
    """Detector offsets (x, y) of a sky offset (dRA East-positive, dDec); DETPA in deg."""
    t = np.deg2rad(detpa)
    return -dra * np.cos(t) + ddec * np.sin(t), dra * np.sin(t) + ddec * np.cos(t)


def _model_hdus(p, *, blm="nap", red_int=False, kernel_scale=None, uv_sign=1.0):
    xy, uv = np.asarray(p["xy"], float), uv_sign * np.asarray(p["uv"], float)
    red = np.asarray(p["redundancy"], float)
    ap = fits.BinTableHDU.from_columns([
        fits.Column(name="XXC", format="D", array=xy[:, 0]),
        fits.Column(name="YYC", format="D", array=xy[:, 1]),
        fits.Column(name="TRM", format="D", array=np.asarray(p["transmission"], float))],
        name="APERTURE")
    r = np.rint(red).astype(np.int16) if red_int else red
    uvh = fits.BinTableHDU.from_columns([
        fits.Column(name="UUC", format="D", array=uv[:, 0]),
        fits.Column(name="VVC", format="D", array=uv[:, 1]),
        fits.Column(name="RED", format="I" if red_int else "D", array=r)], name="UV-PLANE")
    k = np.asarray(p["kernel"], float)
    if kernel_scale is not None:
        k = k * np.asarray(kernel_scale, float)[:, None]
    hdus = [ap, uvh, fits.ImageHDU(k, name="KER-MAT")]
    a = uv_sign * np.asarray(p["blm"], float)
    if blm == "nap":
        hdus.append(fits.ImageHDU(a, name="BLM-MAT"))
    elif blm == "nap-1":
        hdus.append(fits.ImageHDU(a[:, 1:], name="BLM-MAT"))
    return hdus


def _cvis(phases, amplitudes):
    return np.stack([amplitudes * np.cos(phases), amplitudes * np.sin(phases)])


def write_xara(path, p, *, detpa=0.0, sigma=None, phases=None, amplitudes=None,
               kernel_scale=None, blm="nap", uv_sign=1.0, bandwidth=None):
    """xara's ``save_as_kpfits`` layout, for channel 0 of ``p['kp']``."""
    kp = np.asarray(p["kp"], float)[:, :1]
    nf, _, nkp = kp.shape
    scale = np.ones(nkp) if kernel_scale is None else np.asarray(kernel_scale, float)
    hdr = fits.Header()
    hdr["SOFTWARE"] = "XARA"
    hdr["PSCALE"] = (float(p["pixscale"]), "Pixel scale (mas)")
    hdus = [fits.PrimaryHDU(header=hdr),
            *_model_hdus(p, blm=blm, kernel_scale=kernel_scale, uv_sign=uv_sign)]
    hdus.append(fits.ImageHDU(kp * scale, name="KP-DATA"))
    sig = np.full(kp.shape, np.nan) if sigma is None else np.asarray(sigma)[:, :1] * scale
    hdus.append(fits.ImageHDU(sig, name="KP-SIGM"))
    hdus.append(fits.ImageHDU(np.full(kp.shape, np.nan), name="KP-COV"))   # xara's placeholder
    bw = np.nan if bandwidth is None else bandwidth
    hdus.append(fits.BinTableHDU.from_columns([
        fits.Column(name="CWAVEL", format="D", array=[p["wavelengths"][0]]),
        fits.Column(name="BWIDTH", format="D", array=[bw])], name="CWAVEL"))
    angles = np.broadcast_to(np.asarray(detpa, float), (nf,)).copy()
    hdus.append(fits.ImageHDU(angles, name="DETPA"))
    if phases is not None:
        hdus.append(fits.ImageHDU(_cvis(phases[:, :1], amplitudes[:, :1]), name="CVIS-DATA"))
    fits.HDUList(hdus).writeto(path)
    return path


def write_jwstkpi(path, p, *, detpa, cov=None, calflag="False", phases=None,
                  amplitudes=None, kp_ndim=None, red_int=True, bandwidth_column="BWIDTH",
                  kernel_scale=None, wrad="NONE", image_size=8):
    """jwst-kpi's ``calwebb_kpi3`` layout (all channels of ``p['kp']``).

    *wrad*: the window radius card (pixels; ``'NONE'`` when not windowed), with
    SCI frames of *image_size* pixels.

    *kernel_scale* multiplies the kernel's rows, and the kernel phases and
    covariances alike (a file whose KER-MAT rows are not unit-normalised).
    """
    kp = np.asarray(p["kp"], float)
    nf, nw, nkp = kp.shape
    if kernel_scale is not None:
        d = np.asarray(kernel_scale, float)
        p = dict(p, kernel=np.asarray(p["kernel"]) * d[:, None])
        kp = kp * d
        cov = None if cov is None else np.asarray(cov) * np.outer(d, d)
    hdr = fits.Header()
    for key, val in (("TELESCOP", "JWST"), ("INSTRUME", "NIRISS"), ("PSCALE", p["pixscale"]),
                     ("GAIN", 1.61), ("DIAM", 6.559348), ("EXPTIME", 10.0),
                     ("DATEOBS", "2022-07-01T00:00:00.000"), ("PROCSOFT", "CALWEBB_KPI3"),
                     ("WRAD", wrad), ("CALFLAG", calflag), ("CONTENT", "KPFITS1")):
        hdr[key] = val
    hdus = [fits.PrimaryHDU(header=hdr),
            fits.ImageHDU(np.zeros((nf, 1, image_size, image_size), np.float32), name="SCI"),
            *_model_hdus(p, blm="nap-1", red_int=red_int)]
    ndim = kp_ndim or (2 if nw == 1 else 3)
    hdus.append(fits.ImageHDU(kp[:, 0] if ndim == 2 else kp, name="KP-DATA"))
    if cov is not None:
        c = np.broadcast_to(cov, (nf, nw, nkp, nkp))
        hdus.append(fits.ImageHDU(np.sqrt(np.diagonal(c, axis1=-2, axis2=-1)), name="KP-SIGM"))
        hdus.append(fits.ImageHDU(np.ascontiguousarray(c), name="KP-COV"))
    wl = np.asarray(p["wavelengths"], float)
    hdus.append(fits.BinTableHDU.from_columns([
        fits.Column(name="CWAVEL", format="D", array=wl),
        fits.Column(name=bandwidth_column, format="D", array=0.1 * wl)], name="CWAVEL"))
    hdus.append(fits.ImageHDU(np.broadcast_to(np.asarray(detpa, float), (nf,)).copy(),
                              name="DETPA"))
    if phases is not None:
        hdus.append(fits.ImageHDU(_cvis(phases, amplitudes), name="CVIS-DATA"))
    fits.HDUList(hdus).writeto(path)
    return path


def write_pykernel(path, p, *, detpa, cov, v410tau=False, tel_rows=None, mjd=59000.0):
    """PyKernel/pynrm's NIRC2 layout for channel 0 of ``p['kp']``.

    *cov* is one frame's covariance (nkp, nkp) or per frame (nframe, nkp, nkp).
    ``v410tau=True``: the variant of the kp_fits example file (KP-DATA and
    KP-SIGM 3-D, CWAVEL a 1-element image, a DETPA extension, no TEL table).
    """
    kp = np.asarray(p["kp"], float)[:, 0]
    nf, nkp = kp.shape
    cov = np.broadcast_to(np.asarray(cov, float).reshape(-1, nkp, nkp), (nf, nkp, nkp))
    wl = float(p["wavelengths"][0])
    hdr = fits.Header()
    hdr["TELESCOP"] = "Keck II"
    hdr["CURRINST"] = "NIRC2"
    hdr["CWAVE"] = (wl, "Central filter wavelength (meters)")
    hdr["CENWAVE"] = (wl * 1e6, "central wavelength (microns)")
    hdr["PSCALE"] = (float(p["pixscale"]), "Pixel scale (mas)")
    hdus = [fits.PrimaryHDU(np.zeros((nf, 16, 16), np.float32), header=hdr),
            fits.ImageHDU(np.zeros((16, 16), np.uint8), name="BP-MAP")]
    pa = np.broadcast_to(np.asarray(detpa, float), (nf,))
    if not v410tau:
        n = nf if tel_rows is None else tel_rows
        pa_col = np.resize(pa, n)
        hdus.append(fits.BinTableHDU.from_columns([
            fits.Column(name="xpeak", format="E", array=np.zeros(n)),
            fits.Column(name="ypeak", format="E", array=np.zeros(n)),
            fits.Column(name="pa", format="E", array=pa_col),
            fits.Column(name="max", format="E", array=np.ones(n)),
            fits.Column(name="background", format="E", array=np.zeros(n)),
            fits.Column(name="MJD", format="D", array=np.full(n, mjd))], name="TEL"))
    hdus += _model_hdus(p, blm="nap-1", red_int=True)
    if v410tau:
        hdus.append(fits.ImageHDU(kp[:, None], name="KP-DATA"))
        hdus.append(fits.ImageHDU(np.ascontiguousarray(cov[:, None]), name="KP-SIGM"))
        hdus.append(fits.ImageHDU(np.array([wl]), name="CWAVEL"))
        hdus.append(fits.ImageHDU(pa.copy(), name="DETPA"))
    else:
        hdus.append(fits.ImageHDU(kp, name="KP-DATA"))
        hdus.append(fits.ImageHDU(np.ascontiguousarray(cov), name="KP-SIGM"))
    fits.HDUList(hdus).writeto(path)
    return path


def fouriever_like_open(path, *, strict_dwavel=False):
    """Open *path* in the order fouriever's kernel-phase reader does; one dict per frame.

    With ``PROCSOFT`` in the primary header (the branch kpifs's files take):
    ``nobs = KP-DATA.shape[0]``, ``INSTRUME`` (required), per frame the
    CWAVEL table's CWAVEL and DWAVEL (else BWIDTH; *strict_dwavel*: DWAVEL
    required), ``DETPA[i]``, ``swapaxes(KP-DATA[i], 0, 1)``, the same of
    ``EKP-SIGM`` or else ``KP-SIGM``, ``kpu = -UUC``, ``kpv = VVC``,
    ``KP-COV[i, 0]`` when it exists (first wavelength only), KER-MAT and
    ``DIAM`` (required). Raises KeyError/IndexError/AxisError where it would.
    """
    out = []
    with fits.open(path, memmap=False) as hdul:
        if "KP-DATA" not in hdul:
            raise UserWarning("Unknown file type")
        h0 = hdul[0].header
        if "PROCSOFT" not in h0:
            raise NotImplementedError("only the PROCSOFT branch is imitated")
        nobs = hdul["KP-DATA"].data.shape[0]
        inst = h0["INSTRUME"]
        for i in range(nobs):
            t = {"inst": inst, "wave": np.asarray(hdul["CWAVEL"].data["CWAVEL"], float)}
            if strict_dwavel:
                t["dwave"] = hdul["CWAVEL"].data["DWAVEL"]
            else:
                try:
                    t["dwave"] = hdul["CWAVEL"].data["DWAVEL"]
                except KeyError:
                    t["dwave"] = hdul["CWAVEL"].data["BWIDTH"]
            t["pa"] = float(hdul["DETPA"].data[i])
            t["kp"] = np.swapaxes(np.asarray(hdul["KP-DATA"].data[i], float), 0, 1)
            try:
                t["dkp"] = np.swapaxes(hdul["EKP-SIGM"].data[i], 0, 1)
            except KeyError:
                t["dkp"] = np.swapaxes(hdul["KP-SIGM"].data[i], 0, 1)
            t["kpu"] = -np.asarray(hdul["UV-PLANE"].data["UUC"], float)
            t["kpv"] = np.asarray(hdul["UV-PLANE"].data["VVC"], float)
            t["uu"] = t["kpu"][:, None] / t["wave"][None, :]
            t["vv"] = t["kpv"][:, None] / t["wave"][None, :]
            try:
                t["kpcov"] = np.asarray(hdul["KP-COV"].data[i, 0], float)
            except (KeyError, IndexError, TypeError):
                pass
            t["kpmat"] = np.asarray(hdul["KER-MAT"].data, float)
            t["diam"] = h0["DIAM"]
            out.append(t)
    return out


def fouriever_like_kernel_model(obs, dra, ddec, contrast):
    """fouriever's binary kernel phases (nkp, nwave) of one frame dict (``pa_mtoc = '-'``)."""
    rho = np.hypot(dra, ddec)
    phi = np.degrees(np.arctan2(dra, ddec)) - obs["pa"]
    x, y = rho * np.sin(np.radians(phi)), rho * np.cos(np.radians(phi))
    vis = (1 + contrast * np.exp(-2j * np.pi * MAS * (obs["uu"] * x + obs["vv"] * y))) \
        / (1 + contrast)
    return obs["kpmat"] @ np.angle(vis)
