"""Pupil models: analytic telescope apertures and their discretisation into sub-apertures.

Coordinates are in metres in the pupil plane, ``x`` along the detector's
columns and ``y`` along its rows (same orientation as the image).

A discrete model is a set of sub-apertures on a square (or hexagonal) grid of
step ``s``. Each sub-aperture carries a transmission: the fraction of its cell
that lies inside the real pupil. By default models are *grey*: cells at least
``min_transmission`` = 0.2 inside are kept with their fractional transmission
as a weight, so that the light of partly covered cells (pupil edge, spiders)
is modelled and the kernel cancels its aberrations; uv points made only of
such cells (redundancy below ``min_redundancy`` = 0.5) are left out of the
kernel model (`~kpifs.model.kernel.KernelModel.from_pupil`). ``grey=False`` gives a
*binary* model (every kept cell counts 1; cut 0.9 by default). The defaults of
each built-in pupil (step, cut, orientation) are in `MODEL_DEFAULTS`, with
their sources.
"""
import logging
import numpy as np
from astropy import units as u
from astropy.io import fits

from .._utils import to_quantity
from .apertures import (BINARY_MIN_TRANSMISSION, MASKS, MODEL_DEFAULTS,  # noqa: F401
                        TELESCOPES, ApertureGeometry, MaskGeometry, ModelDefaults,
                        canonical_name, model_defaults)
from ..exceptions import KpifsError

__all__ = ["PupilModel", "ApertureGeometry", "TELESCOPES", "ModelDefaults", "MODEL_DEFAULTS",
           "model_defaults", "make_pupil", "pupil_image", "read_pupil_fits"]

__all__ += ["MASKS", "MaskGeometry", "canonical_name"]   # non-redundant masks

log = logging.getLogger(__name__)


class PupilModel:
    """A discrete pupil: sub-aperture positions (m) and transmissions.

    Parameters
    ----------
    xy : array-like or `~astropy.units.Quantity`, shape (n, 2)
        Sub-aperture centres in metres.
    transmission : array-like, shape (n,), optional
        Transmission of each sub-aperture (1 for a binary model).
    step : `~astropy.units.Quantity` or float, optional
        Grid step in metres (informational, used by plots and headers).
    name : str, optional
        Name of the model.

    Examples
    --------
    >>> from kpifs import make_pupil
    >>> pup = make_pupil("subaru")
    >>> pup.n_sub
    337
    >>> pup.xy.unit
    Unit("m")
    """

    def __init__(self, xy, transmission=None, *, step=None, name="pupil", meta=None):
        xy = np.asarray(u.Quantity(xy, u.m).value, float)
        if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) < 2:
            raise KpifsError(f"pupil {name!r}: need an (n, 2) array of at least two "
                             f"sub-aperture positions, got shape {xy.shape}")
        if transmission is None:
            transmission = np.ones(len(xy))
        transmission = np.asarray(transmission, float)
        if transmission.shape != (len(xy),):
            raise KpifsError(f"pupil {name!r}: transmission has shape {transmission.shape}, "
                             f"expected ({len(xy)},)")
        if np.any(~np.isfinite(transmission)) or np.any(transmission <= 0):
            raise KpifsError(f"pupil {name!r}: transmissions must be finite and > 0")
        self._xy = xy
        self._transmission = transmission
        self.step = None if step is None else to_quantity(step, u.m, name="step")
        self.name = name
        self.meta = dict(meta or {})

    @property
    def xy(self):
        """Sub-aperture centres, `~astropy.units.Quantity` (n, 2) in m."""
        return self._xy * u.m

    @property
    def transmission(self):
        """Sub-aperture transmissions (n,)."""
        return self._transmission

    @property
    def n_sub(self):
        """Number of sub-apertures."""
        return len(self._xy)

    @property
    def is_binary(self):
        """True when every transmission is 1."""
        return bool(np.all(self._transmission == 1))

    def is_centrosymmetric(self, *, atol=1e-6):
        """True when the set of sub-apertures is symmetric through the origin."""
        a = np.round(self._xy / atol).astype(np.int64)
        return {tuple(p) for p in a} == {tuple(-p) for p in a}

    def to_table(self):
        """Return the model as a `~astropy.table.QTable` (columns x, y, transmission)."""
        from astropy.table import QTable     # not at import: the command line's start
        t = QTable([self._xy[:, 0] * u.m, self._xy[:, 1] * u.m, self._transmission],
                   names=("x", "y", "transmission"))
        t.meta.update(self.meta)
        t.meta["name"] = self.name
        return t

    def __repr__(self):
        step = "" if self.step is None else f", step={self.step:.3f}"
        kind = "binary" if self.is_binary else "grey"
        return f"<PupilModel {self.name!r}: {self.n_sub} {kind} sub-apertures{step}>"


def _grid_centres(radius, step, offset, hexagonal):
    """Cell centres of a square or hexagonal grid covering a disk of *radius*."""
    if hexagonal:
        dy = step * np.sqrt(3) / 2
        nrow = int(np.ceil(radius / dy)) + 2
        pts = []
        for j in range(-nrow, nrow + 1):
            shift = 0.5 * step * (j % 2)
            ncol = int(np.ceil(radius / step)) + 2
            i = np.arange(-ncol, ncol + 1)
            pts.append(np.column_stack([i * step + shift, np.full(i.shape, j * dy)]))
        c = np.concatenate(pts)
    else:
        n = int(np.ceil(radius / step)) + 2
        i = np.arange(-n, n + 1) * step
        gx, gy = np.meshgrid(i, i)
        c = np.column_stack([gx.ravel(), gy.ravel()])
    c = c + np.asarray(offset, float)
    keep = np.hypot(c[:, 0], c[:, 1]) <= radius + step
    return c[keep]


def _cell_samples(step, hexagonal, nsamp):
    """Offsets of sample points filling one cell (for the area fraction)."""
    g = (np.arange(nsamp) + 0.5) / nsamp - 0.5
    if hexagonal:
        # Voronoi cell of the hexagonal lattice: a pointy-top hexagon of
        # inradius step/2 (flat sides at x = +-step/2).
        span = 2 * step / np.sqrt(3)
        sx, sy = np.meshgrid(g * span, g * span)
        sx, sy = sx.ravel(), sy.ravel()
        ok = (np.abs(sx) <= step / 2) & (0.5 * np.abs(sx) + np.sqrt(3) / 2 * np.abs(sy)
                                         <= step / 2)
        return sx[ok], sy[ok]
    sx, sy = np.meshgrid(g * step, g * step)
    return sx.ravel(), sy.ravel()


def _discretise(transmission_fn, radius, step, offset, *, hexagonal, min_transmission,
                grey, nsamp=12):
    centres = _grid_centres(radius, step, offset, hexagonal)
    sx, sy = _cell_samples(step, hexagonal, nsamp)
    frac = transmission_fn(centres[:, :1] + sx[None, :], centres[:, 1:] + sy[None, :]).mean(axis=1)
    keep = frac >= min_transmission
    if keep.sum() < 2:
        raise KpifsError(f"fewer than two sub-apertures have transmission >= {min_transmission} "
                         f"with a step of {step} m: choose a smaller step")
    trans = frac[keep] if grey else np.ones(int(keep.sum()))
    return centres[keep], trans


def read_pupil_fits(path, *, pupil_scale=None):
    """Read a pupil image from FITS; return ``(image, pixel size in m)``.

    The pixel size comes from *pupil_scale* or the header keyword ``PUPSCALE``
    (metres per pixel).

    Examples
    --------
    >>> import tempfile, numpy as np
    >>> from astropy.io import fits
    >>> from kpifs.model.pupil import read_pupil_fits
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = tmp.name + "/pupil.fits"
    >>> fits.writeto(path, np.ones((8, 8)), fits.Header({"PUPSCALE": 0.5}))
    >>> image, scale = read_pupil_fits(path)
    >>> image.shape, scale
    ((8, 8), 0.5)
    >>> tmp.cleanup()
    """
    try:
        with fits.open(path) as hdul:
            hdu = next((h for h in hdul if getattr(h, "data", None) is not None
                        and h.is_image and h.data.ndim == 2), None)
            if hdu is None:
                raise KpifsError(f"{path}: no 2-D image HDU holding a pupil")
            image = np.array(hdu.data, float)
            scale = hdu.header.get("PUPSCALE", hdul[0].header.get("PUPSCALE"))
    except (OSError, TypeError) as exc:
        raise KpifsError(f"{path}: cannot read pupil image: {exc}") from None
    if pupil_scale is not None:
        scale = to_quantity(pupil_scale, u.m, name="pupil scale").value
    if scale is None:
        raise KpifsError(f"{path}: no pixel size: add header keyword PUPSCALE (m/pixel) "
                         f"or give --pupil-scale")
    if not np.all(np.isfinite(image)) or image.max() <= 0:
        raise KpifsError(f"{path}: the pupil image must be finite with some positive pixels")
    return image / image.max(), float(scale)


def _image_transmission_fn(image, scale):
    ny, nx = image.shape
    cy, cx = (ny - 1) / 2, (nx - 1) / 2

    def fn(x, y):
        i = np.rint(y / scale + cy).astype(int)
        j = np.rint(x / scale + cx).astype(int)
        ok = (i >= 0) & (i < ny) & (j >= 0) & (j < nx)
        out = np.zeros(np.broadcast(x, y).shape)
        out[ok] = image[i[ok], j[ok]]
        return out

    radius = 0.5 * scale * np.hypot(nx, ny)
    return fn, radius


def _rotated(fn, rotation_deg):
    """Wrap a transmission function so that the pupil turns by *rotation_deg*."""
    if not rotation_deg:
        return fn
    c, s = np.cos(np.deg2rad(rotation_deg)), np.sin(np.deg2rad(rotation_deg))
    return lambda x, y: fn(c * x + s * y, -s * x + c * y)


def _resolve_aperture(pupil, *, diameter=None, obstruction=None, pupil_scale=None):
    """Return ``(transmission function, radius in m, name)`` for any pupil spec."""
    if isinstance(pupil, (ApertureGeometry, MaskGeometry)):
        return pupil.transmission, pupil.diameter / 2, pupil.name
    key = str(pupil).lower()
    if key in MASKS or key in TELESCOPES:
        geo = MASKS.get(key) or TELESCOPES[key]
        return geo.transmission, geo.diameter / 2, canonical_name(key)
    if key in ("circular", "annular", "disk"):
        if diameter is None:
            raise KpifsError(f"pupil {pupil!r} needs a diameter")
        d = to_quantity(diameter, u.m, name="diameter").value
        obs = 0.0 if obstruction is None else to_quantity(obstruction, u.m,
                                                          name="obstruction").value
        geo = ApertureGeometry(d, obs, (), name=key)
        return geo.transmission, d / 2, key
    if key.endswith((".fits", ".fit", ".fits.gz")):
        image, scale = read_pupil_fits(pupil, pupil_scale=pupil_scale)
        fn, radius = _image_transmission_fn(image, scale)
        return fn, radius, str(pupil)
    raise KpifsError(f"unknown pupil {pupil!r}: use one of {sorted(TELESCOPES)}, a mask "
                     f"({', '.join(sorted(MASKS))}), 'circular'/'annular' with a diameter, "
                     f"or a FITS pupil image")


def make_pupil(pupil="subaru", *, step=None, offset=None, min_transmission=None, grey=None,
               min_redundancy=None, hexagonal=False, rotation=None, diameter=None,
               obstruction=None, pupil_scale=None):
    """Discretise a telescope pupil into a `PupilModel`.

    Parameters
    ----------
    pupil : str, `ApertureGeometry` or `MaskGeometry`
        A telescope name (``'subaru'``, ``'vlt'``, ``'pharo'``, ``'jwst'``,
        ``'niriss_clearp'``, ``'gpi'``; ``'scexao'``, ``'charis'``, ``'sphere'``,
        ``'nircam_clear'`` and ``'gemini_south'`` are aliases), a mask
        (`MASKS`: ``'niriss_nrm'``, ``'sphere_sam7'``, ``'gpi_nrm'``; one
        sub-aperture per hole unless a *step* is given), ``'circular'`` or
        ``'annular'`` (with *diameter* and *obstruction*), or the path of a FITS
        pupil image whose pixel size (m) is in keyword ``PUPSCALE`` or
        *pupil_scale*.
    step : `~astropy.units.Quantity`, optional
        Grid step (m). Default: the pupil's (`MODEL_DEFAULTS`; 0.38 m for
        Subaru and the VLT, about 300 sub-apertures as in the seed paper;
        0.16 m for PHARO).
    offset : `~astropy.units.Quantity`, shape (2,), optional
        Shift of the grid relative to the pupil centre (m), default (0.17,
        0.11) m. It makes the model non centro-symmetric, so that the phase
        transfer matrix has rank ``n_sub - 1``; ``offset=(0, 0)`` with a
        symmetric pupil gives a centro-symmetric model whose rank is about
        ``n_sub/2`` (even pupil phases produce no Fourier phase to first order).
    min_transmission : float, optional
        Keep cells whose area inside the pupil is at least this fraction
        (default 0.2 for a grey model, 0.9 for a binary one).
    grey : bool, optional
        Keep the fractional transmissions (a grey model, the default) or
        count every kept cell 1 (``False``: a binary model).
    min_redundancy : float, optional
        Recorded in the model's ``meta`` for `~kpifs.model.kernel.KernelModel.from_pupil`:
        uv points of smaller redundancy are left out (default 0.5 for a grey
        model, 0 for a binary one).
    hexagonal : bool
        Use a hexagonal grid (flat-to-flat cell width = *step*).
    rotation : `~astropy.units.Quantity`, optional
        Turn of the whole model, grid and aperture together (deg,
        counter-clockwise from +x to +y), to match the pupil as the detector
        sees it (`kpifs.modelcheck.check_pupil_model` measures it). Default:
        the pupil's (0 for the built-in ones).
    diameter, obstruction : `~astropy.units.Quantity`, optional
        For ``'circular'``/``'annular'`` pupils.
    pupil_scale : `~astropy.units.Quantity`, optional
        Pixel size (m) of a pupil image, overriding ``PUPSCALE``.

    Returns
    -------
    `PupilModel`

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs import make_pupil
    >>> make_pupil("annular", diameter=8 * u.m, obstruction=1.2 * u.m, step=1 * u.m,
    ...            grey=False)
    <PupilModel 'annular': 38 binary sub-apertures, step=1.000 m>
    """
    mask = pupil if isinstance(pupil, MaskGeometry) else (
        MASKS.get(pupil) if isinstance(pupil, str) else None)
    if mask is not None and (step is None or to_quantity(step, u.m, name="step").value == 0):
        # one sub-aperture per hole (step 0 m, its default, says the same); a step
        # discretises the holes on a grid instead
        return _mask_pupil(mask, rotation)
    defaults = model_defaults(pupil)
    grey = defaults.grey if grey is None else bool(grey)
    if min_transmission is None:
        min_transmission = defaults.min_transmission if grey else BINARY_MIN_TRANSMISSION
    if min_redundancy is None:
        min_redundancy = defaults.min_redundancy if grey else 0.0
    if not (np.isfinite(min_redundancy) and min_redundancy >= 0):
        raise KpifsError(f"min_redundancy must be >= 0, got {min_redundancy}")
    step = defaults.step * u.m if step is None else step
    offset = defaults.offset * u.m if offset is None else offset
    rotation = defaults.rotation * u.deg if rotation is None else rotation
    step_m = to_quantity(step, u.m, name="step").value
    if not np.isfinite(step_m) or step_m <= 0:
        raise KpifsError(f"grid step must be > 0, got {step}")
    off = to_quantity(offset, u.m, name="offset").value
    off = np.broadcast_to(np.asarray(off, float), (2,))
    if not 0 < min_transmission <= 1:
        raise KpifsError(f"min_transmission must be in (0, 1], got {min_transmission}")
    rot = to_quantity(rotation, u.deg, name="rotation").value
    fn, radius, name = _resolve_aperture(pupil, diameter=diameter, obstruction=obstruction,
                                         pupil_scale=pupil_scale)
    xy, trans = _discretise(fn, radius, step_m, off, hexagonal=hexagonal,
                            min_transmission=min_transmission, grey=grey)
    if rot:
        c, s = np.cos(np.deg2rad(rot)), np.sin(np.deg2rad(rot))
        xy = xy @ np.array([[c, -s], [s, c]]).T
    meta = {"step_m": step_m, "offset_m": tuple(off.tolist()),
            "min_transmission": min_transmission, "grey": grey,
            "min_redundancy": float(min_redundancy), "hexagonal": hexagonal,
            "rotation_deg": rot, "diameter_m": 2 * radius}
    log.debug("pupil %s: %d sub-apertures (step %.3f m)", name, len(xy), step_m)
    return PupilModel(xy, trans, step=step_m * u.m, name=name, meta=meta)


def _mask_pupil(mask, rotation=None):
    """One sub-aperture per hole of a non-redundant mask (its kernel phases: closure
    phases); the grid options (step, offset, cut, grey) do not apply. The step is half
    the hole diameter, so that the default search and the aliasing guard (``lambda / (2
    step)``) reach ``lambda / D_hole``, about the holes' primary-beam FWHM."""
    xy = np.asarray(mask.holes, float)
    rot = 0.0 if rotation is None else to_quantity(rotation, u.deg, name="rotation").value
    if rot:
        c, s = np.cos(np.deg2rad(rot)), np.sin(np.deg2rad(rot))
        xy = xy @ np.array([[c, -s], [s, c]]).T
    meta = {"hole_diameter_m": mask.hole_diameter, "mask": mask.name, "rotation_deg": rot,
            "diameter_m": mask.diameter, "source": mask.source, "holes": True,
            "step_m": mask.hole_diameter / 2, "grey": False, "min_redundancy": 0.0}
    return PupilModel(xy, step=mask.hole_diameter / 2 * u.m, name=mask.name, meta=meta)


def pupil_image(pupil="subaru", *, npix=256, pixel_size=None, rotation=0 * u.deg,
                diameter=None, obstruction=None, pupil_scale=None, supersample=1):
    """Sample a continuous pupil on an ``npix x npix`` grid.

    Returns ``(image, pixel size in m)``. Used by the simulator; pixel centres
    are symmetric about the pupil centre. With *supersample* ``n > 1`` each
    pixel is the mean of ``n x n`` samples (an anti-aliased, grey edge: a
    turned pupil then changes smoothly with the angle).

    Examples
    --------
    >>> from kpifs.model.pupil import pupil_image
    >>> img, dx = pupil_image("subaru", npix=128)
    >>> img.shape, round(float(dx), 4)
    ((128, 128), 0.0619)
    """
    fn, radius, name = _resolve_aperture(pupil, diameter=diameter, obstruction=obstruction,
                                         pupil_scale=pupil_scale)
    if pixel_size is None:
        pixel_size = float(2 * radius / npix)
    dx = to_quantity(pixel_size, u.m, name="pixel size").value
    ss = int(supersample)
    if ss < 1:
        raise KpifsError(f"supersample must be a positive integer, got {supersample}")
    c = (np.arange(npix * ss) - (npix * ss - 1) / 2) * dx / ss
    gx, gy = np.meshgrid(c, c)
    rot = to_quantity(rotation, u.deg, name="rotation").value
    img = _rotated(fn, rot)(gx, gy)
    if ss > 1:
        img = img.reshape(npix, ss, npix, ss).mean(axis=(1, 3))
    return img, dx
