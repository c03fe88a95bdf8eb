"""GPI DRP spectral cubes (``*_spdc.fits``) written here in the pipeline's layout, with a
PSF simulated here, independently of kpifs's simulator and writer (issue 35, item 4).

Layout (GPI DRP documentation; as pyKLIP's GPI reader expects it): a header-only
primary HDU (``INSTRUME = 'GPI'``, ``IFSFILT``, ``DISPERSR``, ``OBSMODE``,
``APODIZER``, ``OCCULTER``, ``LYOTMASK``, ``IFSROTAT``, ``PAR_ANG``, ``DATE-OBS``,
``MJD-OBS``, ``OBJECT``); ``SCI`` of shape (37, 281, 281) float32 with ``BUNIT``,
``AVPARANG``, the wavelength WCS (``CTYPE3 = 'WAVE'``, ``CUNIT3 = 'microns'``,
``CRPIX3 = 1``, ``CRVAL3``, ``CD3_3``), ``PSFCENTX/Y`` (0-based), ``ITIME``,
``ITIME0`` (us), ``COADDS``, ``COADDS0``, ``EXPTIME`` and a mirrored celestial WCS
(``CRPIX1/2 = 141``, the array centre, not the star); ``DQ`` uint8 (bit 0 bad).
The lenslet field is a square of ``FIELD_SIDE`` lenslets turned by 24.5 deg inside the
281 x 281 grid: NaN outside.

The PSF: Gemini South as GPI sees it (7.7701 m, a 1.2968 m central obstruction, two
V-shaped spiders), one wavelength per channel, lenslets that integrate the focal plane
(``oversample`` sub-samples), a quasi-static wavefront shared by target and calibrator
with a drift per exposure, an AO halo (the mean of ``nscreen`` high-order screens per
exposure), photon and read noise, and the sky turning with the parallactic angle while
the pupil stays fixed on the detector.
"""
import numpy as np

MAS = np.pi / 180 / 3600 / 1000
PIXSCALE = 14.161                        # mas per lenslet
H_EDGES = (1.4904, 1.8016)
NCHAN = 37
SIZE = 281
FIELD_SIDE = 190
IFSROTAT = 23.5 + 0.25                  # deg: 23.5 + PACAL


def h_wavelengths():
    """The DRP's H-band channel centres (um): ``CRVAL3 + i * CD3_3``."""
    lo, hi = H_EDGES
    return lo + (np.arange(NCHAN) + 0.5) * (hi - lo) / NCHAN


def gemini_pupil(npix):
    """Gemini South through GPI on npix x npix pixels over 7.8 m: (image, pixel size m)."""
    dx = 7.8 / npix
    c = (np.arange(npix) - (npix - 1) / 2) * dx
    x, y = np.meshgrid(c, c)
    r = np.hypot(x, y)
    img = ((r <= 7.7701 / 2) & (r >= 1.2968 / 2)).astype(float)
    for sy in (1, -1):                    # V spiders: vertices 0.2179 m off centre
        for da in (-43.1, 43.1):
            a = np.deg2rad(sy * 90.0 + da)
            px, py = x, y - sy * 0.2179
            along = px * np.cos(a) + py * np.sin(a)
            across = -px * np.sin(a) + py * np.cos(a)
            img[(along > 0) & (np.abs(across) < 0.007)] = 0.0
    return img, dx


def _screen(rng, n, dx, rms, mask, slope):
    f = np.fft.fftfreq(2 * n, dx)
    fx, fy = np.meshgrid(f, f)
    k = np.hypot(fx, fy)
    amp = np.where(k > 0, (k + 0.1) ** -slope, 0)
    s = np.fft.ifft2(amp * (rng.normal(size=k.shape) + 1j * rng.normal(size=k.shape))).real
    s = s[:n, :n]
    s -= s[mask].mean()
    return s * rms / s[mask].std()


def lenslet_field(size=SIZE, side=FIELD_SIDE, turn=24.5):
    """True inside the turned square of lenslets (the file's frame)."""
    c = np.arange(size) - (size - 1) / 2
    x, y = np.meshgrid(c, c)
    t = np.deg2rad(turn)
    u, v = np.cos(t) * x + np.sin(t) * y, -np.sin(t) * x + np.cos(t) * y
    return (np.abs(u) < side / 2) & (np.abs(v) < side / 2)


def exposures(rng, n, *, parang, sky_offset=None, contrast=0.0, static=None, npup=64,
              box=96, oversample=2, nscreen=3, flux=2e6, read_noise=8.0, drift_nm=6.0):
    """*n* exposures (37, 281, 281) in the kpifs frame (x not yet mirrored), star flux
    *flux* photons per channel, and the star's pixel (x, y) in that frame.

    *parang* (deg, one per exposure): the sky turns on the detector by
    ``AVPARANG + IFSROTAT - 90``. *sky_offset* (dRA, dDec) mas of a companion.
    """
    pup, dx = gemini_pupil(npup)
    mask = pup > 0
    lams = h_wavelengths() * 1e-6
    field = lenslet_field()
    star = np.array([140.0 + 0.31, 140.0 - 0.27])
    x0, y0 = int(star[0]) - box // 2, int(star[1]) - box // 2
    sub = (np.arange(box * oversample) + 0.5) / oversample - 0.5
    out = np.empty((n, NCHAN, SIZE, SIZE), np.float32)
    for i in range(n):
        stat = (static if static is not None else 0) + _screen(rng, npup, dx, drift_nm * 1e-9,
                                                               mask, 2.0)
        halos = [_screen(rng, npup, dx, 90e-9, mask, 1.2) for _ in range(nscreen)]
        detpa = np.deg2rad(parang[i] + IFSROTAT - 90)
        comp = None
        if sky_offset is not None and contrast:
            dra, ddec = sky_offset
            comp = np.array([-dra * np.cos(detpa) + ddec * np.sin(detpa),
                             dra * np.sin(detpa) + ddec * np.cos(detpa)]) / PIXSCALE
        jit = rng.normal(0, 0.1, 2)
        img = np.zeros((NCHAN, SIZE, SIZE))
        for k, lam in enumerate(lams):
            acc = np.zeros((box * oversample,) * 2)
            for h in halos:
                e = pup * np.exp(2j * np.pi * (stat + h) / lam)
                norm = (PIXSCALE * MAS / oversample * dx / lam) ** 2 / np.sum(pup)
                for pos, amp in (((star + jit), 1.0),) + (
                        ((star + jit + comp, contrast),) if comp is not None else ()):
                    ax = np.exp(-2j * np.pi * np.outer((x0 + sub - pos[0]) * PIXSCALE * MAS,
                                                       (np.arange(npup) - (npup - 1) / 2) * dx)
                                / lam)
                    ay = np.exp(-2j * np.pi * np.outer((y0 + sub - pos[1]) * PIXSCALE * MAS,
                                                       (np.arange(npup) - (npup - 1) / 2) * dx)
                                / lam)
                    acc += amp * np.abs(ay @ e @ ax.T) ** 2 * norm / nscreen
            psf = acc.reshape(box, oversample, box, oversample).sum(axis=(1, 3))
            img[k, y0:y0 + box, x0:x0 + box] = psf
        photons = rng.poisson(np.clip(img, 0, None) * flux + 5.0).astype(float)
        photons += rng.normal(0, read_noise, photons.shape)
        out[i] = np.where(field[None], photons, np.nan)
    return out, star


def write_spdc(outdir, cubes, star, parang, *, prefix="S20231015S", first=1, obj="HD 1",
               itime=59.6, mirrored=True):
    """Write each exposure (37, 281, 281, kpifs frame) as a DRP ``*_spdc.fits``."""
    from astropy.io import fits
    paths = []
    lams = h_wavelengths()
    s = PIXSCALE / 3.6e6
    for i, cube in enumerate(cubes):
        data = cube[..., ::-1] if mirrored else cube
        cx = (SIZE - 1 - star[0]) if mirrored else star[0]
        phu = fits.Header()
        phu["INSTRUME"] = "GPI"
        phu["TELESCOP"] = "Gemini South"
        phu["OBJECT"] = obj
        phu["IFSFILT"] = "IFSFILT_H_G1213"
        phu["DISPERSR"] = "DISP_PRISM_G6262"
        phu["OBSMODE"] = "H_direct"
        phu["APODIZER"] = "APOD_CLEAR_G6201"
        phu["OCCULTER"] = "FPM_SCIENCE_G6225"
        phu["LYOTMASK"] = "LYOT_OPEN_G6231"
        phu["IFSROTAT"] = IFSROTAT
        phu["PAR_ANG"] = float(parang[i]) + 0.3          # instantaneous, not the mean
        phu["DATE-OBS"] = "2023-10-15"
        phu["MJD-OBS"] = 60232.1 + i * 7e-4
        phu["RA"], phu["DEC"] = 52.3, -41.2
        sci = fits.ImageHDU(data.astype(np.float32), name="SCI")
        h = sci.header
        h["BUNIT"] = "ADU per coadd"
        h["AVPARANG"] = float(parang[i])
        h["CTYPE3"], h["CUNIT3"], h["CRPIX3"] = "WAVE", "microns", 1
        h["CRVAL3"], h["CD3_3"] = float(lams[0]), float(lams[1] - lams[0])
        h["PSFCENTX"], h["PSFCENTY"] = float(cx), float(star[1])
        h["ITIME"], h["ITIME0"] = itime, int(itime * 1e6)
        h["COADDS"], h["COADDS0"], h["EXPTIME"] = 1, 1, itime
        vert = np.deg2rad(parang[i] - 360 + IFSROTAT - 90)
        h["CTYPE1"], h["CTYPE2"] = "RA---TAN", "DEC--TAN"
        h["CRPIX1"], h["CRPIX2"] = 141.0, 141.0
        h["CRVAL1"], h["CRVAL2"] = 52.3, -41.2
        h["CD1_1"], h["CD1_2"] = s * np.cos(vert), s * np.sin(vert)
        h["CD2_1"], h["CD2_2"] = -s * np.sin(vert), s * np.cos(vert)     # det > 0: mirrored
        dq = (~np.isfinite(data)).astype(np.uint8)
        hdul = fits.HDUList([fits.PrimaryHDU(header=phu), sci, fits.ImageHDU(dq, name="DQ")])
        p = f"{outdir}/{prefix}{first + i:04d}_spdc.fits"
        hdul.writeto(p)
        paths.append(p)
    return paths


def sequence(outdir, *, n=8, contrast=5e-3, sep=300.0, pa=40.0, seed=0, rotation=20.0,
             **kw):
    """8 target and 8 calibrator exposures (H band); returns (target paths, calibrator
    paths, (dRA, dDec) of the companion). *kw* go to `exposures` (``nscreen``,
    ``oversample``, ``box``: fewer is faster)."""
    rng = np.random.default_rng(seed)
    pup, dx = gemini_pupil(64)
    static = _screen(rng, 64, dx, 40e-9, pup > 0, 2.0)
    static_c = static + _screen(rng, 64, dx, 8e-9, pup > 0, 2.0)
    off = (sep * np.sin(np.deg2rad(pa)), sep * np.cos(np.deg2rad(pa)))
    par_t = -20.0 + np.linspace(0, rotation, n)
    par_c = 10.0 + np.linspace(0, rotation, n)
    ct, star = exposures(rng, n, parang=par_t, sky_offset=off, contrast=contrast,
                         static=static, **kw)
    t = write_spdc(outdir, ct, star, par_t, first=1)
    cc, star = exposures(rng, n, parang=par_c, static=static_c, **kw)
    c = write_spdc(outdir, cc, star, par_c, first=101, obj="HD 2")
    return t, c, off
