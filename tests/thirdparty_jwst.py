"""JWST NIRCam stand-ins written by the JWST datamodels library (stdatamodels), with a PSF
simulated here, independently of kpifs's simulator (issue 35, item 9).

What a real stage-2 ``*_calints.fits`` holds and kpifs's own stand-in does not:

- light over the filter's band (a top-hat of ``nlam`` wavelengths), not one wavelength;
- pixels that integrate the PSF (``oversample`` sub-pixels summed), not point samples;
- pointing jitter within an integration (a Gaussian blur) and between them (a shift);
- the star anywhere in the subarray (a sub-pixel position, not the central pixel);
- values in DN/s (electrons / gain / EFFINTTM), ``ERR`` and ``VAR_*`` in the same units;
- ``DQ`` flags (DO_NOT_USE pixels NaN in SCI, SATURATED-only pixels left as they are);
- the pupil turned by ``V3I_YANG`` on the detector, ``DETPA = ROLL_REF - V3I_YANG * VPARITY``.

Each effect can be switched off (`Effects`), to find which one a result depends on.
"""
import dataclasses

import numpy as np

MAS = np.pi / 180 / 3600 / 1000

#: (mean wavelength um, effective width um, pixel scale mas, channel, detector)
NIRCAM = {"F150W": (1.5106, 0.2892, 31.0, "SHORT", "NRCA1"),
          "F480M": (4.8213, 0.3141, 63.0, "LONG", "NRCALONG")}


@dataclasses.dataclass
class Effects:
    """What the stand-in simulates (each True by default)."""

    band: bool = True            # polychromatic light over the filter's width
    pixels: bool = True          # pixel integration (oversampled, then binned)
    jitter: bool = True          # blur within an integration and shifts between them
    offcentre: bool = True       # the star at a sub-pixel position off the subarray centre
    dq: bool = True              # flagged and NaN pixels
    pupil_turn: bool = True      # the pupil turned by V3I_YANG on the detector


def jwst_pupil(npix, *, turn_deg=0.0):
    """18 hexagonal segments (1.32 m flat to flat, centres 1.3235 m apart) and three struts,
    sampled on ``npix`` x ``npix`` pixels over 6.8 m. Returns (image, pixel size m)."""
    size = 6.8
    dx = size / npix
    c = (np.arange(npix) - (npix - 1) / 2) * dx
    x, y = np.meshgrid(c, c)
    t = np.deg2rad(turn_deg)
    x, y = np.cos(t) * x + np.sin(t) * y, -np.sin(t) * x + np.cos(t) * y
    pitch = 1.3235
    centres = []
    for q in range(-2, 3):
        for r in range(-2, 3):
            s = -q - r
            if max(abs(q), abs(r), abs(s)) in (1, 2):
                # flat sides of neighbours face each other along +-V3 (y)
                centres.append((pitch * np.sqrt(3) / 2 * q, pitch * (r + q / 2)))
    img = np.zeros_like(x)
    half = 1.32 / 2
    for cx, cy in centres:
        dxs, dys = np.abs(x - cx), np.abs(y - cy)
        inside = (dys <= half) & (np.sqrt(3) / 2 * dxs + 0.5 * dys <= half)
        img[inside] = 1.0
    for ang, width in ((90.0, 0.11), (240.0, 0.12), (-60.0, 0.12)):
        a = np.deg2rad(ang)
        along = x * np.cos(a) + y * np.sin(a)
        across = -x * np.sin(a) + y * np.cos(a)
        img[(along > 0) & (np.abs(across) < width / 2)] = 0.0
    return img, dx


def _mft(field, dx, lam, coords_rad):
    """Complex amplitude at image angles *coords_rad* (x axis, y axis) of a pupil field."""
    n = field.shape[0]
    r = (np.arange(n) - (n - 1) / 2) * dx
    ax = np.exp(-2j * np.pi * np.outer(coords_rad[0], r) / lam)
    ay = np.exp(-2j * np.pi * np.outer(coords_rad[1], r) / lam)
    return ay @ field @ ax.T


def _screen(rng, n, dx, rms, mask):
    """A smooth wavefront (m): random low-order modes with a steep spectrum."""
    f = np.fft.fftfreq(2 * n, dx)
    fx, fy = np.meshgrid(f, f)
    k = np.hypot(fx, fy)
    amp = np.where(k > 0, (k + 0.2) ** -2.0, 0)
    s = np.fft.ifft2(amp * (rng.normal(size=k.shape) + 1j * rng.normal(size=k.shape))).real
    s = s[:n, :n]
    s -= s[mask].mean()
    return s * rms / s[mask].std()


def psf_cube(rng, filt, nints, *, shape=(64, 64), sky_offset=None, contrast=0.0, detpa=0.0,
             effects=Effects(), static=None, npup=96, nlam=7, oversample=3,
             drift_nm=5.0, shift=(0.0, 0.0)):
    """Noise-free images (electrons per second, star flux 1) of a star and companion.

    *sky_offset* (dRA, dDec) mas; *static* the wavefront shared by a target and its
    calibrator (m), to which each integration adds a drift of *drift_nm* rms.
    """
    lam0, width, ps, _, _ = NIRCAM[filt]
    turn = -0.03 if effects.pupil_turn else 0.0
    pup, dx = jwst_pupil(npup, turn_deg=turn)
    mask = pup > 0
    lams = (lam0 + width * (np.arange(nlam) + 0.5 - nlam / 2) / nlam if effects.band
            else np.array([lam0])) * 1e-6
    os_ = oversample if effects.pixels else 1
    ny, nx = shape
    star = np.array([nx / 2 - 0.5 + 2.37, ny / 2 - 0.5 - 1.61]) if effects.offcentre else \
        np.array([nx // 2, ny // 2], float)
    star = star + (np.asarray(shift, float) if effects.offcentre else 0.0)
    comp = None
    if sky_offset is not None and contrast:
        t = np.deg2rad(detpa)
        dra, ddec = sky_offset
        comp = np.array([-dra * np.cos(t) + ddec * np.sin(t), dra * np.sin(t) + ddec * np.cos(t)])
    out = np.zeros((nints,) + tuple(shape))
    for i in range(nints):
        opd = (static if static is not None else 0) + _screen(rng, npup, dx, drift_nm * 1e-9,
                                                              mask)
        jit = rng.normal(0, 0.05, 2) if effects.jitter else np.zeros(2)
        img = np.zeros((ny * os_, nx * os_))
        for lam in lams:
            field = pup * np.exp(2j * np.pi * opd / lam)
            sub = (np.arange(nx * os_) + 0.5) / os_ - 0.5          # sub-pixel centres (pix)
            suby = (np.arange(ny * os_) + 0.5) / os_ - 0.5
            for pos, amp in ((star + jit, 1.0), ) + (
                    ((star + jit + comp / ps, contrast),) if comp is not None else ()):
                coords = ((sub - pos[0]) * ps * MAS, (suby - pos[1]) * ps * MAS)
                e = _mft(field, dx, lam, coords)
                norm = (ps * MAS / os_ * dx / lam) ** 2 / np.sum(np.abs(field) ** 2)
                img += amp * np.abs(e) ** 2 * norm / len(lams)
        if effects.jitter:
            from scipy.ndimage import gaussian_filter
            img = gaussian_filter(img, 6.0 / ps * os_, mode="constant")   # 6 mas rms
        out[i] = img.reshape(ny, os_, nx, os_).sum(axis=(1, 3))
    return out


def write_calints(path, filt, images, *, rng, flux_e=3e7, effinttm=2.7, gain=2.0,
                  read_noise=12.0, roll_ref=250.0, targname="W0336", effects=Effects(),
                  photmjsr=None):
    """Add noise to *images* (star flux 1) and write them with stdatamodels' CubeModel.

    In DN/s, or with *photmjsr* (MJy/sr per DN/s) calibrated to MJy/sr as the
    photometric step of imaging pipelines leaves them (``PHOTMJSR`` card)."""
    from stdatamodels.jwst.datamodels import CubeModel
    lam0, width, ps, channel, detector = NIRCAM[filt]
    e = rng.poisson(np.clip(images, 0, None) * flux_e).astype(float)
    e += rng.normal(0, read_noise, e.shape)
    sci = (e / gain / effinttm).astype(np.float32)
    var_p = (np.clip(images * flux_e, 0, None) / gain ** 2 / effinttm ** 2).astype(np.float32)
    var_r = np.full(e.shape, (read_noise / gain / effinttm) ** 2, np.float32)
    var_f = np.zeros(e.shape, np.float32)
    err = np.sqrt(var_p + var_r + var_f).astype(np.float32)
    dq = np.zeros(e.shape, np.uint32)
    if effects.dq:
        n = e.shape[1] * e.shape[2]
        bad = rng.choice(n, max(1, n // 400), replace=False)          # dead: DO_NOT_USE, NaN
        dq.reshape(len(e), -1)[:, bad] |= 1 | 1024
        sci.reshape(len(e), -1)[:, bad] = np.nan
        hot = rng.choice(n, max(1, n // 800), replace=False)          # warm: flagged only
        dq.reshape(len(e), -1)[:, hot] |= 4096
    unit = "DN/s"
    if photmjsr is not None:
        sci, err = sci * np.float32(photmjsr), err * np.float32(photmjsr)
        var_p, var_r = var_p * np.float32(photmjsr) ** 2, var_r * np.float32(photmjsr) ** 2
        unit = "MJy/sr"
    m = CubeModel(data=sci, err=err, dq=dq)
    m.var_poisson, m.var_rnoise, m.var_flat = var_p, var_r, var_f
    m.meta.telescope = "JWST"
    m.meta.instrument.name = "NIRCAM"
    m.meta.instrument.channel = channel
    m.meta.instrument.detector = detector
    m.meta.instrument.filter = filt
    m.meta.instrument.pupil = "CLEAR"
    m.meta.exposure.type = "NRC_IMAGE"
    m.meta.exposure.nints = len(e)
    m.meta.exposure.integration_time = effinttm
    ny, nx = e.shape[1:]
    m.meta.subarray.name = "SUB64P"
    m.meta.subarray.xstart, m.meta.subarray.ystart = 1, 1
    m.meta.subarray.xsize, m.meta.subarray.ysize = nx, ny
    yang = -0.03 if effects.pupil_turn else 0.0
    m.meta.wcsinfo.roll_ref = roll_ref + yang * -1
    m.meta.wcsinfo.v3yangle = yang
    m.meta.wcsinfo.vparity = -1
    m.meta.photometry.pixelarea_arcsecsq = (ps / 1000) ** 2
    m.meta.bunit_data = m.meta.bunit_err = unit
    if photmjsr is not None:
        m.meta.photometry.conversion_megajanskys = float(photmjsr)
    m.meta.target.catalog_name = targname
    m.meta.observation.date = "2026-01-01"
    m.meta.observation.time = "00:00:00"
    m.save(str(path))
    return str(path)


def nircam_pair(outdir, *, contrasts=(0.076, 0.19), sky_offset=None, nints=20, seed=0,
                effects=Effects(), detpa=250.0, cal_shift=(0.31, -0.22)):
    """Target (W0336-like binary) and calibrator ``*_calints.fits`` in F150W and F480M.

    Returns (target files, calibrator files, (dRA, dDec) mas). Default companion: 84 mas
    at PA 295 deg. The calibrator's star sits *cal_shift* pixels from the target's.
    """
    if sky_offset is None:
        pa = np.deg2rad(295.0)
        sky_offset = (84.0 * np.sin(pa), 84.0 * np.cos(pa))
    rng = np.random.default_rng(seed)
    t, c = [], []
    for k, (filt, con) in enumerate(zip(("F150W", "F480M"), contrasts)):
        npup = 96
        pup, dx = jwst_pupil(npup)
        static = _screen(rng, npup, dx, 60e-9, pup > 0)
        static_c = static + _screen(rng, npup, dx, 8e-9, pup > 0)
        img_t = psf_cube(rng, filt, nints, sky_offset=sky_offset, contrast=con, detpa=detpa,
                         effects=effects, static=static)
        img_c = psf_cube(rng, filt, nints, detpa=detpa, effects=effects, static=static_c,
                         shift=cal_shift)
        t.append(write_calints(f"{outdir}/jw0{k}001_nrc_{filt.lower()}_00001_calints.fits",
                               filt, img_t, rng=rng, roll_ref=detpa, effects=effects))
        c.append(write_calints(f"{outdir}/jw0{k}002_nrc_{filt.lower()}_00002_calints.fits",
                               filt, img_c, rng=rng, roll_ref=detpa, targname="CAL",
                               effects=effects))
    return t, c, sky_offset
