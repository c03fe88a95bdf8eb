"""Published telescope apertures and the defaults of their discrete models.

`ApertureGeometry` describes a circular aperture with a central obstruction and
spider vanes; `TELESCOPES` holds the published ones (FORMATS.md); and
`MODEL_DEFAULTS` says how `kpifs.model.pupil.make_pupil` discretises each of them
by default, with the source of every number. `kpifs.model.pupil` re-exports all of
them.
"""
from dataclasses import dataclass, field

import numpy as np

from .._utils import canonical_name
from ._segmented import (GPI_MASK_MAGNIFICATION, GPI_NRM_HOLES_MM, NIRISS_NRM_HOLES,
                         SEGMENTED_TELESCOPES, MaskGeometry)

__all__ = ["ApertureGeometry", "TELESCOPES", "ModelDefaults", "MODEL_DEFAULTS",
           "BINARY_MIN_TRANSMISSION", "model_defaults"]


class _Names(dict):
    """A dict of built-in names that looks keys up in either spelling (`canonical_name`)."""

    def __getitem__(self, key):
        return super().__getitem__(canonical_name(key))

    def __contains__(self, key):
        return super().__contains__(canonical_name(key))

    def get(self, key, default=None):
        return super().get(canonical_name(key), default)

    def __setitem__(self, key, value):
        super().__setitem__(canonical_name(key), value)

    def update(self, other=(), **kw):
        for k, v in dict(other, **kw).items():
            self[k] = v


@dataclass(frozen=True)
class ApertureGeometry:
    """A circular telescope aperture with central obstruction and straight spider vanes.

    Parameters
    ----------
    diameter : float
        Outer diameter in metres.
    obstruction : float
        Diameter of the central obstruction in metres (0 for none).
    vanes : tuple of tuple
        Each vane is ``(x0, y0, angle_deg, width)``: a half-line of the given
        width (m) starting at ``(x0, y0)`` (m) in the direction ``angle_deg``
        (degrees from +x towards +y).
    name : str
        Human-readable name.

    Examples
    --------
    >>> from kpifs.model.pupil import ApertureGeometry
    >>> geo = ApertureGeometry(diameter=4.0, obstruction=1.0, name="small")
    >>> geo.transmission([0.0, 1.0, 3.0], [0.0, 0.0, 0.0])
    array([0., 1., 0.])
    """

    diameter: float
    obstruction: float = 0.0
    vanes: tuple = field(default_factory=tuple)
    name: str = "custom"

    def transmission(self, x, y):
        """Return 1 inside the aperture and 0 outside, at points ``(x, y)`` in metres."""
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        r2 = x * x + y * y
        inside = (r2 <= (self.diameter / 2) ** 2) & (r2 >= (self.obstruction / 2) ** 2)
        for x0, y0, ang, width in self.vanes:
            dx, dy = np.cos(np.deg2rad(ang)), np.sin(np.deg2rad(ang))
            along = (x - x0) * dx + (y - y0) * dy
            across = -(x - x0) * dy + (y - y0) * dx
            inside &= ~((along >= 0) & (np.abs(across) <= width / 2))
        return inside.astype(float)


def _four_vanes(offset, angle, width):
    """Four vanes starting at ``(±offset, 0)`` at angles ±``angle`` from the x axis."""
    vanes = []
    for sx in (1, -1):
        for sy in (1, -1):
            ang = np.rad2deg(np.arctan2(sy * np.sin(np.deg2rad(angle)),
                                        sx * np.cos(np.deg2rad(angle))))
            vanes.append((sx * offset, 0.0, ang, width))
    return tuple(vanes)


#: Published pupil geometries (FORMATS.md): Subaru/SCExAO, VLT UT3/SPHERE and
#: the Palomar PHARO "med" cross Lyot mask.
TELESCOPES = _Names({
    "subaru": ApertureGeometry(diameter=7.92, obstruction=2.3,
                               vanes=_four_vanes(1.0, 51.75, 0.22), name="Subaru/SCExAO"),
    "vlt": ApertureGeometry(diameter=8.0, obstruction=1.116,
                            vanes=_four_vanes(0.40, 50.5, 0.04), name="VLT UT3/SPHERE"),
    "pharo": ApertureGeometry(
        diameter=4.646, obstruction=2.293,
        vanes=tuple((0.0, 0.0, a, 0.25) for a in (-2.0, 88.0, 178.0, 268.0)),
        name="Palomar/PHARO med cross"),
})
TELESCOPES["scexao"] = TELESCOPES["subaru"]
TELESCOPES["charis"] = TELESCOPES["subaru"]
TELESCOPES["sphere"] = TELESCOPES["vlt"]


@dataclass(frozen=True)
class ModelDefaults:
    """Default discretisation of a pupil (see `MODEL_DEFAULTS`).

    Attributes
    ----------
    step : float
        Grid step (m).
    min_transmission : float
        Cut of a grey model: cells at least this fraction inside the pupil.
    min_redundancy : float
        Of a grey model: uv points whose redundancy (summed transmission
        products) is below this are left out of the kernel model: there the
        real transfer function is near zero and the phase is no signal.
    grey : bool
        Grey (fractional transmissions) or binary model.
    rotation : float
        Turn of the whole model (deg, counter-clockwise from +x to +y) to the
        pupil as the detector sees it.
    offset : tuple
        Shift of the grid from the pupil centre (m).
    source : str
        Where the numbers come from.

    Examples
    --------
    >>> from kpifs.model.pupil import MODEL_DEFAULTS
    >>> MODEL_DEFAULTS["subaru"].step, MODEL_DEFAULTS["subaru"].min_redundancy
    (0.38, 0.5)
    """

    step: float
    min_transmission: float = 0.2
    min_redundancy: float = 0.5
    grey: bool = True
    rotation: float = 0.0
    offset: tuple = (0.17, 0.11)
    source: str = ""


#: Cut of a binary model when none is given: a cell counts when 90 % of it is
#: inside the pupil.
BINARY_MIN_TRANSMISSION = 0.9

_GREY_SOURCE = ("grey, cut 0.2, uv points of redundancy >= 0.5: on simulations the kernel "
                "rejects smooth aberrations 5x better than the binary model's, and on the "
                "real PHARO frames alpha Oph's residual reduced chi2 drops from 54 to 43 and "
                "its contrast from 0.030 to 0.039 (literature 0.033-0.048; docs: choosing a "
                "pupil model)")

#: Per-pupil defaults of `make_pupil` (keys as `TELESCOPES`; ``'generic'`` for
#: circular/annular apertures and pupil images).
MODEL_DEFAULTS = _Names({
    "subaru": ModelDefaults(
        0.38, source="step: seed paper (Subaru in ~300 sub-apertures, ~300 kernel phases); "
        + _GREY_SOURCE),
    "vlt": ModelDefaults(
        0.38, source="step: as Subaru (8 m, Nyquist-sampled SPHERE-IFS channels); "
        + _GREY_SOURCE),
    "pharo": ModelDefaults(
        0.16, source="step 0.16 m: the discrete model published with these frames (xara "
        "PHARO data); spider arms at -2 deg in the geometry (Hayward et al. 2001); "
        + _GREY_SOURCE),
    "generic": ModelDefaults(0.38, source="kpifs: as Subaru; " + _GREY_SOURCE),
})
for _alias, _key in (("scexao", "subaru"), ("charis", "subaru"), ("sphere", "vlt")):
    MODEL_DEFAULTS[_alias] = MODEL_DEFAULTS[_key]


def model_defaults(pupil):
    """The `ModelDefaults` of a pupil specification (telescope name, else ``'generic'``).

    Examples
    --------
    >>> from kpifs.model.pupil import model_defaults
    >>> d = model_defaults("pharo")
    >>> d.step, d.grey, d.min_transmission
    (0.16, True, 0.2)
    """
    if isinstance(pupil, MaskGeometry):
        return MODEL_DEFAULTS["niriss_nrm"]
    if not isinstance(pupil, str):
        return MODEL_DEFAULTS["generic"]
    return MODEL_DEFAULTS.get(pupil, MODEL_DEFAULTS["generic"])


# --- non-redundant masks (issues 27 and 28) ------------------------------------------
#: Built-in non-redundant masks (`MaskGeometry`, hole centres in m on the primary,
#: x along the detector columns, y along its rows), one model per mask.
#: NIRISS: the g7s6 mask as built (the as-designed centres with V2 reversed, as
#: ImPlaneIA's and jwst ``ami``'s live centres before their Fourier-convention turn;
#: the as-designed set is its mirror image), hexagonal holes of 0.82 m flat to flat
#: over segments B4, C2, B5, B2, C1, B6, C6. SPHERE: the 7-hole SAM mask as the IFS
#: sees it (AMICAL's SPHERE-IFS g7 centres), holes of about 1.2 m. GPI: the g10s40
#: mask's centres at the mask times 647.62 (FORMATS.md), holes of 0.596 m; its turn
#: on the detector differs between tools (gpipsfs, ImPlaneIA): measure it with
#: ``kpifs model-check``.
MASKS = _Names({
    "niriss_nrm": MaskGeometry(
        NIRISS_NRM_HOLES, 0.82, shape="hex", name="niriss_nrm",
        source="JWST NIRISS AMI g7s6 mask as built (V2-reversed as-designed centres; "
               "ImPlaneIA, jwst ami)"),
    "sphere_sam7": MaskGeometry(
        ((-2.07, 2.71), (0.98, 3.27), (-3.11, -0.2), (-1.43, -0.81), (-2.79, -1.96),
         (3.3, -0.85), (0.58, -3.17)), 1.2, name="sphere_sam7",
        source="VLT SPHERE 7-hole SAM mask as seen by the IFS (AMICAL 'SPHERE-IFS' g7); "
               "hole diameter approximate"),
    "gpi_nrm": MaskGeometry(
        tuple((x * GPI_MASK_MAGNIFICATION / 1000, y * GPI_MASK_MAGNIFICATION / 1000)
              for x, y in GPI_NRM_HOLES_MM), 0.920 * GPI_MASK_MAGNIFICATION / 1000,
        name="gpi_nrm",
        source="Gemini GPI g10s40 10-hole mask on the primary (FORMATS.md; Greenbaum et "
               "al. 2015); turn on the detector to be measured"),
})
__all__ += ["MaskGeometry", "MASKS", "canonical_name"]


# --- JWST and Gemini/GPI (issue 27) ---------------------------------------------------
def _gpi_vanes():
    """Gemini South's two V spiders as GPI sees them (gpipsfs: arms at 90 +- 43.1 deg
    and 270 +- 43.1 deg from vertices 0.2179 m off centre, 0.01 m wide)."""
    return tuple((0.0, sy * 0.2179, sy * 90.0 + da, 0.01) for sy in (1, -1)
                 for da in (-43.1, 43.1))


def _register_segmented():
    TELESCOPES.update(SEGMENTED_TELESCOPES)
    TELESCOPES["gemini_south"] = ApertureGeometry(
        diameter=7.7701, obstruction=1.2968, vanes=_gpi_vanes(), name="Gemini South/GPI")
    TELESCOPES["gpi"] = TELESCOPES["gemini_south"]
    jw = ("step 0.3 m: about 350 cells over the 18 segments, sub-aperture spacing below "
          "half the 0.82 m NRM holes; " + _GREY_SOURCE)
    MODEL_DEFAULTS["jwst"] = ModelDefaults(0.3, source=jw)
    MODEL_DEFAULTS["niriss_clearp"] = ModelDefaults(0.3, source=jw)
    MODEL_DEFAULTS["nircam_clear"] = MODEL_DEFAULTS["jwst"]
    MODEL_DEFAULTS["gemini_south"] = ModelDefaults(
        0.8, source="step 0.8 m (60 kernel phases per channel, not 314 at 0.38 m): GPI "
        "sequences are a few 60 s exposures, and on 8-exposure simulations the frames' "
        "(Ledoit-Wolf) covariance of 314 kernel phases gave 2 and 7 false candidates in "
        "companion-free sequences, that of 60 none in 10 (and found the companion in 5 of "
        "5); " + _GREY_SOURCE)
    MODEL_DEFAULTS["gpi"] = MODEL_DEFAULTS["gemini_south"]
    for key in MASKS:
        MODEL_DEFAULTS[key] = ModelDefaults(
            0.0, grey=False, min_redundancy=0.0, offset=(0.0, 0.0),
            source="one sub-aperture per hole (no grid): kernel phases = closure phases")


_register_segmented()
