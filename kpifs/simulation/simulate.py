"""Simulated IFS observations of a star with a faint companion.

The optics: a pupil sampled on ``npup x npup`` points, a residual AO phase
screen (achromatic optical path, so the phase scales as ``1/lambda``), and a
matrix Fourier transform (Soummer et al. 2007) straight onto the detector
pixels, ``E(theta) = sum_r P(r) exp(i phi(r)) exp(+2 pi i r.theta / lambda)``.
With this propagation sign a pupil phase ``phi`` gives the Fourier phase
``R^-1 A phi`` of `~kpifs.model.kernel.KernelModel` (``phi_j - phi_k`` on baseline
``r_j - r_k``). A companion at ``(alpha, beta)`` is the same field evaluated at
``theta - (alpha, beta)``, so it shares the star's aberrations.

Photometry: a star of magnitude *mag* in the H band zero point (photon flux
9.3e9 ph s^-1 m^-2 um^-1 for mag 0, flat over the channels), the telescope's
collecting area, a total throughput, photon (Poisson) noise and Gaussian read
noise, in electrons.
"""
import logging
from dataclasses import dataclass, field

import numpy as np
from astropy import units as u

from .._memory import check_memory
from .._utils import as_rng, one_blas_thread, to_quantity
from .._utils import progress as progress_bar
from ..exceptions import KpifsError
from ..io.instruments import INSTRUMENTS
from ..model.kernel import MAS
from ..model.pupil import MASKS, TELESCOPES, pupil_image

__all__ = ["simulate_psf", "phase_screens", "SceneParameters", "PRESETS", "TYPICAL_STATIC",
           "simulate_scene",
           "SimulatedObservation"]

log = logging.getLogger(__name__)

#: Photon flux of a magnitude-0 star in H (ph / s / m^2 / um).
H_ZERO_POINT = 9.3e9


def _mft_matrices(npup, dx, shape, pixscale_rad, wavelength, offset_rad=(0.0, 0.0)):
    ny, nx = shape
    r = (np.arange(npup) - (npup - 1) / 2) * dx
    tx = (np.arange(nx) - nx // 2) * pixscale_rad - offset_rad[0]
    ty = (np.arange(ny) - ny // 2) * pixscale_rad - offset_rad[1]
    ax = np.exp(2j * np.pi * np.outer(tx, r) / wavelength)
    ay = np.exp(2j * np.pi * np.outer(ty, r) / wavelength)
    return ay, ax


def _propagate(field, dx, shape, pixscale_rad, wavelength, offset_rad=(0.0, 0.0),
               centre_rad=(0.0, 0.0)):
    """Intensity on the detector, normalised so that an infinite field sums to 1."""
    npup = field.shape[-1]
    ay, ax = _mft_matrices(npup, dx, shape, pixscale_rad, wavelength,
                           (offset_rad[0] + centre_rad[0], offset_rad[1] + centre_rad[1]))
    e = ay @ field @ ax.T
    # Parseval: the field's energy over a whole period of theta is
    # (lam/dx)^2 sum|P|^2, and each pixel covers pixscale^2 of it
    norm = (pixscale_rad * dx / wavelength) ** 2 / np.sum(np.abs(field) ** 2)
    return np.abs(e) ** 2 * norm


def phase_screens(npup, dx, n, *, rms=100e-9, mask=None, cutoff=None, seed=None):
    """Residual-wavefront screens (optical path, m) with a ``f^-11/3`` spectrum.

    Frequencies below the AO *cutoff* (cycles/m, default ``1 / (2 * 0.4 m)``, a
    ~20x20 actuator system on 8 m) are damped, imitating AO correction; each
    screen is scaled to *rms* over *mask*, and has zero mean there.

    Examples
    --------
    >>> from kpifs.simulation.simulate import phase_screens
    >>> s = phase_screens(64, 0.125, 3, rms=50e-9, seed=1)
    >>> s.shape, round(float(s[0].std() * 1e9), 1)
    ((3, 64, 64), 50.0)
    """
    rng = as_rng(seed)
    if cutoff is None:
        cutoff = 1 / (2 * 0.4)
    nfft = 2 * npup
    f = np.fft.fftfreq(nfft, dx)
    fr = np.hypot(*np.meshgrid(f, f))
    psd = np.where(fr > 0, (fr ** 2 + (1 / 30.0) ** 2) ** (-11 / 6), 0.0)
    psd = np.where(fr < cutoff, psd * (fr / cutoff) ** 2 * 0.2, psd)
    amp = np.sqrt(psd)
    if mask is None:
        mask = np.ones((npup, npup), bool)
    mask = np.asarray(mask) > 0
    out = np.empty((n, npup, npup))
    for i in range(n):
        noise = rng.standard_normal((nfft, nfft)) + 1j * rng.standard_normal((nfft, nfft))
        scr = np.fft.ifft2(noise * amp).real[:npup, :npup]
        scr -= scr[mask].mean()
        scr *= rms / scr[mask].std()
        out[i] = scr
    return out


def simulate_psf(pupil, wavelengths, *, pixscale, shape=(64, 64), npup=128, opd=None,
                 centre=(0.0, 0.0), companions=(), pupil_rotation=0 * u.deg, supersample=1,
                 pupil_scale=None):
    """Noise-free images of a star (and companions) at each wavelength.

    Parameters
    ----------
    pupil : str
        Telescope name or FITS pupil image (see `~kpifs.model.pupil.pupil_image`).
    wavelengths : `~astropy.units.Quantity`, shape (nwave,)
    pixscale : `~astropy.units.Quantity`
    shape : tuple of int
        Image shape; the star is at pixel ``(nx // 2, ny // 2)`` plus *centre*.
    npup : int
        Pupil sampling.
    opd : ndarray, shape (npup, npup), optional
        Optical path difference across the pupil (m).
    centre : tuple of float
        Sub-pixel offset of the star from pixel ``(nx // 2, ny // 2)``, in pixels.
    companions : sequence of ``((alpha, beta), contrast)``
        Offsets in mas (or Quantity) and contrasts (scalar or per wavelength).
    pupil_rotation : `~astropy.units.Quantity`
        Turn of the pupil (counter-clockwise from +x to +y).
    supersample : int
        Anti-aliasing of the pupil (`~kpifs.model.pupil.pupil_image`).
    pupil_scale : `~astropy.units.Quantity`, optional
        Pixel size of a pupil image (m), overriding its ``PUPSCALE``.

    Returns
    -------
    ndarray, shape (nwave, ny, nx)
        Star flux normalised to 1 over an infinite field.

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs.simulation.simulate import simulate_psf
    >>> img = simulate_psf("subaru", [1.6] * u.um, pixscale=10.42 * u.mas, shape=(40, 40))
    >>> img.shape, bool(0.8 < img.sum() < 1.0)
    ((1, 40, 40), True)
    """
    wl = np.atleast_1d(to_quantity(wavelengths, u.m, name="wavelengths").value)
    p = to_quantity(pixscale, u.mas, name="pixel scale").value * MAS
    pimg, dx = pupil_image(pupil, npix=npup, rotation=pupil_rotation, supersample=supersample,
                           pupil_scale=pupil_scale)
    out = np.empty((len(wl),) + tuple(shape))
    cen = (centre[0] * p, centre[1] * p)
    comps = [(to_quantity(off, u.mas, name="companion offset").value * MAS,
              np.broadcast_to(np.asarray(c, float), wl.shape)) for off, c in companions]
    for i, lam in enumerate(wl):
        field = pimg if opd is None else pimg * np.exp(2j * np.pi * opd / lam)
        img = _propagate(field, dx, shape, p, lam, centre_rad=cen)
        for off, c in comps:
            img += c[i] * _propagate(field, dx, shape, p, lam, offset_rad=tuple(off),
                                     centre_rad=cen)
        out[i] = img
    return out


@dataclass
class SceneParameters:
    """Everything that defines a simulated observation (see `PRESETS`).

    Examples
    --------
    >>> from kpifs.simulation.simulate import SceneParameters
    >>> p = SceneParameters()
    >>> p.telescope, p.shape, round(float(p.contrasts.mean()), 6)
    ('subaru', (40, 40), 0.000631)
    """

    telescope: str = "subaru"
    wavelengths: u.Quantity = field(default_factory=lambda: [1.52, 1.60, 1.68] * u.um)
    pixscale: u.Quantity = 10.42 * u.mas
    shape: tuple = (40, 40)
    n_frames: int = 1000
    companion_offset: u.Quantity = field(default_factory=lambda: [80.0, 60.0] * u.mas)
    contrasts: np.ndarray = field(default_factory=lambda: 10 ** (-8 / 2.5)
                                  * np.array([1.3, 1.0, 0.7]))
    wavefront_rms: u.Quantity = 100 * u.nm
    star_mag: float = 5.0
    throughput: float = 0.1
    exptime: u.Quantity = 0.1 * u.s
    read_noise: float = 10.0
    jitter: float = 0.2
    npup: int = 128
    instrument: str = "generic"
    field: str = None          # an instrument's field (its `field_mask`), e.g. 'charis'
    n_dead: int = 0            # dead spaxels (garbage values, zero inverse variance)
    # quasi-static aberrations, as on sky: a part that drifts from frame to frame (AR(1)
    # screens of this rms, correlation exp(-1/drift_time) between consecutive frames,
    # one process per star), a static part common to both stars, and a static part
    # seen by the calibrator only (target != calibrator: a calibration residual)
    drift_rms: u.Quantity = 0 * u.nm
    drift_time: float = 10.0
    static_rms: u.Quantity = 0 * u.nm
    static_diff_rms: u.Quantity = 0 * u.nm
    # issue 39: the common static part at low order (no AO correction of its low spatial
    # frequencies), and a static part of the target's own (not the calibrator's)
    static_low_order: bool = False
    static_own_rms: u.Quantity = 0 * u.nm
    # the pupil as the detector sees it: turned by this angle (counter-clockwise from +x
    # to +y), as when a model is made for the textbook orientation
    pupil_rotation: u.Quantity = 0 * u.deg
    # a sequence whose frames turn on the sky (deg, one detector position angle per frame,
    # `kpifs.io.angles`): with *sky_offset* (dRA, dDec; mas) the companion of frame i sits
    # at that sky offset seen at detpa[i], and *companion_offset* is ignored
    detpa: object = None
    sky_offset: u.Quantity = None

    def bandwidths(self):
        wl = self.wavelengths.to_value(u.um)
        if len(wl) == 1:
            return np.array([0.05 * wl[0]]) * u.um
        return np.gradient(wl) * u.um

    def star_photons(self):
        """Photo-electrons from the star per frame and channel."""
        geo = TELESCOPES.get(self.telescope) or MASKS[self.telescope]
        area = getattr(geo, "area", None) or np.pi / 4 * (geo.diameter ** 2
                                                          - geo.obstruction ** 2)
        return (H_ZERO_POINT * 10 ** (-0.4 * self.star_mag) * area * self.throughput
                * self.bandwidths().to_value(u.um) * self.exptime.to_value(u.s))


def _apply_field(out, params, rng):
    """Blank spaxels outside the field (0, zero inverse variance) and add dead ones."""
    shape = tuple(params.shape)
    bad = np.zeros(shape, bool)
    if params.field is not None:
        # the field of the instrument it names (`kpifs.io.instrument.Instrument.field_mask`)
        inst = INSTRUMENTS.get(params.field)
        if inst is None or inst.field_mask is None:
            raise KpifsError(f"unknown field {params.field!r}")
        bad |= ~inst.field_mask(shape)
    dead = np.zeros(shape, bool)
    if params.n_dead:
        good = np.flatnonzero(~bad)
        dead.flat[rng.choice(good, params.n_dead, replace=False)] = True
    for k in ("target", "calibrator"):
        out[k][..., bad] = 0.0
        out[k][..., dead] = rng.uniform(-1e4, 1e4, out[k][..., dead].shape)
        out["var_" + k][..., bad | dead] = np.inf


#: Scene presets. ``paper``: the seed paper's scene (Subaru, 40x40 spaxels of
#: 10.42 mas, channels 1.52/1.60/1.68 um, T-type companion with mean contrast
#: 10^(-8/2.5) = 6.3e-4, brighter in the blue, at 100 mas). The registered
#: instruments add theirs (each module's ``scenes``: `kpifs.io.charis` ``charis``,
#: `kpifs.io.sphere` ``sphere``, ``sphere-yjh`` and ``sphere-sam``, `kpifs.io.jwst`
#: ``niriss`` and ``nircam``, `kpifs.io.gpi` ``gpi``, `kpifs.io.nirc2` ``nirc2``).
PRESETS = {"paper": dict(), **INSTRUMENTS.scenes()}


@dataclass
class SimulatedObservation:
    """A simulated target and calibrator with the truth used to make them.

    Examples
    --------
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> obs = simulate_scene("paper", n_frames=1, seed=3, npup=32)
    >>> obs.truth["KPSIMX"][0], obs.calibrator.shape
    (80.0, (1, 3, 40, 40))
    """

    target: np.ndarray        # (nframe, nwave, ny, nx), electrons
    calibrator: np.ndarray    # same shape, no companion
    variance_target: np.ndarray
    variance_calibrator: np.ndarray
    params: SceneParameters
    seed: int

    @property
    def wavelengths(self):
        return self.params.wavelengths

    @property
    def truth(self):
        """Header cards describing the truth (companion offset, contrasts, seed)."""
        p = self.params
        x0, y0 = _frame_offsets(p)[0]                     # the first frame's
        cards = {"KPSIMX": (float(x0), "[mas] true companion offset along image x"),
                 "KPSIMY": (float(y0), "[mas] true companion offset along image y"),
                 "KPSIMSEE": (int(self.seed), "simulation seed")}
        for i, c in enumerate(np.broadcast_to(p.contrasts, p.wavelengths.shape), 1):
            cards[f"KPSIMC{i}"] = (float(c), f"true contrast, channel {i}")
        cards["KPSIMWFE"] = (float(p.wavefront_rms.to_value(u.nm)), "[nm] rms wavefront error")
        for key, value, comment in (
                ("KPSIMDRF", p.drift_rms, "[nm] rms of the drifting aberrations"),
                ("KPSIMSTA", p.static_rms, "[nm] rms of the common static aberrations"),
                ("KPSIMSTD", p.static_diff_rms, "[nm] rms of the calibrator-only static"),
                ("KPSIMSTO", p.static_own_rms, "[nm] rms of the target-only static")):
            if u.Quantity(value, u.nm).value > 0:
                cards[key] = (float(u.Quantity(value, u.nm).value), comment)
        if p.static_low_order:
            cards["KPSIMSLO"] = (True, "common static aberrations at low order")
        if u.Quantity(p.drift_rms, u.nm).value > 0:
            cards["KPSIMDRT"] = (float(p.drift_time), "[frames] correlation time of the drift")
        if p.sky_offset is not None:
            for key, v, what in zip(("KPSIMRA", "KPSIMDE"), p.sky_offset.to_value(u.mas),
                                    ("dRA (East +)", "dDec")):
                cards[key] = (float(v), f"[mas] true companion {what} on the sky")
        return cards


class _QuasiStatic:
    """Slow aberrations of `SceneParameters` (none, and no random draw, when all are 0)."""

    def __init__(self, params, pimg, dx, rng):
        self.rng, self.npup, self.dx, self.mask = rng, params.npup, dx, pimg > 0
        self.drift = params.drift_rms.to_value(u.m)
        self.rho = float(np.exp(-1.0 / params.drift_time))
        self.state = {}
        stat, diff = params.static_rms.to_value(u.m), params.static_diff_rms.to_value(u.m)
        low = 1e-9 if params.static_low_order else None       # no AO damping: low orders
        common = self._screen(stat, cutoff=low)
        self._screen(stat)          # a second draw, unused: the random stream as before
        self.static = {"target": common, "calibrator": common}   # common to both stars
        for which, rms in (("calibrator", diff), ("target", params.static_own_rms.to_value(u.m))):
            d = self._screen(rms)
            if d is not None:
                base = self.static[which]
                self.static[which] = d if base is None else base + d

    def _screen(self, rms, cutoff=None):
        if rms <= 0:
            return None
        return phase_screens(self.npup, self.dx, 1, rms=rms, mask=self.mask, cutoff=cutoff,
                             seed=self.rng)[0]

    def add(self, opd, which):
        parts = [opd, self.static[which]]
        if self.drift > 0:
            new = self._screen(self.drift)
            prev = self.state.get(which)
            self.state[which] = new if prev is None else (
                self.rho * prev + np.sqrt(1 - self.rho ** 2) * new)
            parts.append(self.state[which])
        parts = [p for p in parts if p is not None]
        return sum(parts) if parts else None


def simulate_scene(preset="paper", *, seed=0, progress=False, **overrides):
    """Simulate a target (star + companion) and a calibrator (star alone).

    Both see the same optics with independent aberrations, new every frame.

    Parameters
    ----------
    preset : str
        Starting parameters (a key of `PRESETS`); any field of `SceneParameters`
        can be overridden by keyword (e.g. ``n_frames=50``).
    seed : int
        Seed of the random generator (aberrations, jitter, noise).
    progress : bool
        Show a progress bar (on a terminal).

    Returns
    -------
    `SimulatedObservation`

    Examples
    --------
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> obs = simulate_scene("paper", n_frames=2, seed=1)
    >>> obs.target.shape
    (2, 3, 40, 40)
    """
    if preset not in PRESETS:
        raise KpifsError(f"unknown preset {preset!r}: use one of {sorted(PRESETS)}")
    kw = dict(PRESETS[preset])
    kw.update(overrides)
    try:
        params = SceneParameters(**kw)
    except TypeError as exc:
        raise KpifsError(f"bad simulation parameter: {exc}") from None
    params.wavelengths = np.atleast_1d(to_quantity(params.wavelengths, u.um, name="wavelengths"))
    params.pixscale = to_quantity(params.pixscale, u.mas, name="pixel scale")
    params.companion_offset = to_quantity(params.companion_offset, u.mas, name="offset")
    params.wavefront_rms = to_quantity(params.wavefront_rms, u.nm, name="wavefront rms")
    params.exptime = to_quantity(params.exptime, u.s, name="exposure time")
    if not (np.isfinite(params.exptime.value) and params.exptime.value > 0):
        raise KpifsError(f"the exposure time must be > 0, got {params.exptime}")
    for name in ("drift_rms", "static_rms", "static_diff_rms", "static_own_rms"):
        setattr(params, name, to_quantity(getattr(params, name), u.nm, name=name))
    if not params.drift_time > 0:
        raise KpifsError(f"drift_time must be > 0 frames, got {params.drift_time}")
    params.contrasts = np.broadcast_to(np.asarray(params.contrasts, float),
                                       params.wavelengths.shape).copy()
    if params.n_frames < 1:
        raise KpifsError("n_frames must be at least 1")
    rng = as_rng(seed)
    nf, nw = params.n_frames, len(params.wavelengths)
    # target, calibrator and their variances (float32), bounded before they are made
    check_memory(16.0 * nf * nw * int(np.prod(params.shape)),
                 f"a simulation of {nf} frames x {nw} channels of {params.shape[0]} x "
                 f"{params.shape[1]} pixels", "simulate fewer frames (--frames) or smaller "
                 "images (--shape)")
    params.pupil_rotation = to_quantity(params.pupil_rotation, u.deg, name="pupil rotation")
    pimg, dx = pupil_image(params.telescope, npix=params.npup, rotation=params.pupil_rotation)
    nphot = params.star_photons()
    wl_m = params.wavelengths.to_value(u.m)
    p_rad = params.pixscale.to_value(u.mas) * MAS
    offs = _frame_offsets(params) * MAS
    shape = tuple(params.shape)
    out = {}
    iterator = progress_bar(range(2 * nf), desc="simulating frames", unit="frame",
                            enabled=progress)
    screens_rms = params.wavefront_rms.to_value(u.m)
    cubes = {k: np.empty((nf, nw) + shape, np.float32) for k in ("target", "calibrator")}
    slow = _QuasiStatic(params, pimg, dx, rng)
    with one_blas_thread():     # 96x96 products: BLAS threads only wait for each other
        for n in iterator:
            which = "target" if n < nf else "calibrator"
            i = n % nf
            opd = phase_screens(params.npup, dx, 1, rms=screens_rms, mask=pimg > 0,
                                seed=rng)[0] if screens_rms > 0 else None
            opd = slow.add(opd, which)
            jit = rng.normal(0, params.jitter, 2) * p_rad
            for iw, lam in enumerate(wl_m):
                fieldp = pimg if opd is None else pimg * np.exp(2j * np.pi * opd / lam)
                img = _propagate(fieldp, dx, shape, p_rad, lam, centre_rad=tuple(jit))
                if which == "target":
                    img = img + params.contrasts[iw] * _propagate(
                        fieldp, dx, shape, p_rad, lam, offset_rad=tuple(offs[i]),
                        centre_rad=tuple(jit))
                electrons = rng.poisson(img * nphot[iw]).astype(float)
                electrons += rng.normal(0, params.read_noise, shape)
                cubes[which][i, iw] = electrons
    for k in cubes:
        out[k] = cubes[k]
        out["var_" + k] = np.clip(cubes[k], 0, None) + params.read_noise ** 2
    _apply_field(out, params, rng)
    log.info("simulated %d target and %d calibrator frames, %d channels", nf, nf, nw)
    return SimulatedObservation(out["target"], out["calibrator"], out["var_target"],
                                out["var_calibrator"], params, seed if isinstance(seed, int)
                                else -1)


#: issue 39: a static aberration typical of the instruments, for sequences with no
#: calibrator (``simulate_scene(..., **TYPICAL_STATIC)``, ``kpifs simulate
#: --typical-static``): 50 nm common to both stars at low order, 15 nm of the target's
#: own, 10 nm drifting (correlation time 10 frames), on top of the fast residual.
TYPICAL_STATIC = dict(static_rms=50 * u.nm, static_low_order=True, static_own_rms=15 * u.nm,
                      drift_rms=10 * u.nm, drift_time=10.0)


def _frame_offsets(params):
    """The companion's detector offset (mas) in each frame: fixed, or fixed on the sky."""
    nf = params.n_frames
    if params.sky_offset is None or params.detpa is None:
        return np.tile(params.companion_offset.to_value(u.mas), (nf, 1))
    dra, ddec = to_quantity(params.sky_offset, u.mas, name="sky offset").value
    pa = np.atleast_1d(np.asarray(params.detpa, float))
    if pa.size not in (1, nf):            # a preset's span kept for another frame count
        pa = np.linspace(pa.min(), pa.max(), nf)
    params.detpa = np.broadcast_to(pa, (nf,)).copy()
    t = np.deg2rad(params.detpa)
    return np.column_stack([-dra * np.cos(t) + ddec * np.sin(t),
                            dra * np.sin(t) + ddec * np.cos(t)])
