"""JWST, Keck and Gemini/GPI apertures: hexagonal segments, struts and hole masks.

Published geometry (FORMATS.md "JWST stage-2 products" and "Gemini Planet
Imager"; jwst-kpi, stpsf/webbpsf, ImPlaneIA, gpipsfs). Coordinates in metres,
``x`` along the detector columns, ``y`` along the rows, V3 (JWST) along +y.
The segments are flat-topped hexagons (edge normals at 30, 90 and 150 deg):
ring A at 1.3235 m from the centre at 30 + 60k deg, ring B at twice that
distance at the same angles, ring C at sqrt(3) times it at 60k deg; this
puts the three-segment wings at x = +-2.29 m and segment B4 at -V3, as in
the NIRISS mask's coordinates. `kpifs.model.apertures` registers the shapes
below in `~kpifs.model.pupil.TELESCOPES`.
"""
from dataclasses import dataclass, field

import numpy as np

__all__ = ["SegmentedAperture", "MaskGeometry", "JWST_SEGMENTS", "SEGMENTED_TELESCOPES"]

#: Centre-to-centre distance of adjacent JWST segments (m).
JWST_PITCH = 1.3235
#: Flat-to-flat width of one JWST segment (m).
JWST_SEGMENT = 1.32


def _rings(pitch):
    a = np.deg2rad(30 + 60 * np.arange(6))
    c = np.deg2rad(60 * np.arange(6))
    ring_a = pitch * np.column_stack([np.cos(a), np.sin(a)])
    return np.concatenate([ring_a, 2 * ring_a,
                           np.sqrt(3) * pitch * np.column_stack([np.cos(c), np.sin(c)])])


#: Centres of the 18 JWST segments (rings A, B, C), m.
JWST_SEGMENTS = _rings(JWST_PITCH)


def _in_hexagons(x, y, centres, flat):
    """True inside any flat-topped hexagon of flat-to-flat width *flat* at *centres*."""
    inside = np.zeros(np.broadcast(x, y).shape, bool)
    half = flat / 2
    for cx, cy in centres:
        dx, dy = x - cx, y - cy
        ok = np.abs(dy) <= half
        for ang in (30.0, 150.0):
            t = np.deg2rad(ang)
            ok &= np.abs(dx * np.cos(t) + dy * np.sin(t)) <= half
        inside |= ok
    return inside


def _vanes(x, y, vanes):
    """True on any vane ``(x0, y0, angle_deg, width)`` (a half-line of a width)."""
    hit = np.zeros(np.broadcast(x, y).shape, bool)
    for x0, y0, ang, width in vanes:
        dx, dy = np.cos(np.deg2rad(ang)), np.sin(np.deg2rad(ang))
        along = (x - x0) * dx + (y - y0) * dy
        across = -(x - x0) * dy + (y - y0) * dx
        hit |= (along >= 0) & (np.abs(across) <= width / 2)
    return hit


@dataclass(frozen=True)
class SegmentedAperture:
    """A segmented primary (hexagons), struts and an optional pupil-mask obscuration.

    Parameters
    ----------
    segments : tuple of (x, y)
        Segment centres (m).
    flat : float
        Flat-to-flat width of a segment (m).
    diameter : float
        Circumscribed diameter (m): the extent of the discrete model.
    vanes : tuple
        Struts ``(x0, y0, angle_deg, width)``.
    disc : tuple
        ``(x0, y0, radius)`` of a central obscuration (NIRISS CLEARP), or ().
    disc_vanes : tuple
        Supports of that obscuration, as *vanes*.
    area : float
        Collecting area (m^2), for photometry.
    name : str

    Examples
    --------
    >>> from kpifs.model.pupil import TELESCOPES
    >>> jwst = TELESCOPES["jwst"]
    >>> jwst.transmission([0.0, 1.3235, 0.0], [0.0, 0.0, -1.3235]).tolist()
    [0.0, 0.0, 1.0]
    """

    segments: tuple
    flat: float
    diameter: float
    vanes: tuple = field(default_factory=tuple)
    disc: tuple = ()
    disc_vanes: tuple = field(default_factory=tuple)
    area: float = 25.4
    name: str = "segmented"
    obstruction: float = 0.0

    def transmission(self, x, y):
        """Return 1 inside the aperture and 0 outside, at points ``(x, y)`` in metres."""
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        inside = _in_hexagons(x, y, self.segments, self.flat) & ~_vanes(x, y, self.vanes)
        if self.disc:
            x0, y0, r = self.disc
            inside &= (x - x0) ** 2 + (y - y0) ** 2 > r * r
            inside &= ~_vanes(x, y, tuple((x0 + a, y0 + b, ang, w)
                                          for a, b, ang, w in self.disc_vanes))
        return inside.astype(float)


@dataclass(frozen=True)
class MaskGeometry:
    """A non-redundant aperture mask: holes (circles or flat-topped hexagons) projected
    on the primary mirror.

    Its discrete model is one sub-aperture per hole (`kpifs.model.pupil.make_pupil`),
    so that its kernel phases are closure phases. The built-in masks are in
    `kpifs.model.pupil.MASKS`.

    Parameters
    ----------
    holes : tuple of (x, y)
        Hole centres (m, on the primary).
    hole_diameter : float
        Hole diameter (m; flat to flat for hexagons).
    shape : {'circle', 'hex'}
        Hole shape (what the simulator draws; the model is the centres).
    name, source : str

    Examples
    --------
    >>> from kpifs.model.pupil import MASKS
    >>> m = MASKS["niriss_nrm"]
    >>> len(m.holes), m.shape, m.transmission([0.0, 0.0], [-2.64, 0.0]).tolist()
    (7, 'hex', [1.0, 0.0])
    """

    holes: tuple
    hole_diameter: float
    shape: str = "circle"
    name: str = "mask"
    source: str = ""

    @property
    def diameter(self):
        """Diameter (m) of the smallest centred circle holding every hole."""
        h = np.asarray(self.holes, float)
        reach = self.hole_diameter * (2 / np.sqrt(3) if self.shape == "hex" else 1.0)
        return float(2 * np.hypot(h[:, 0], h[:, 1]).max() + reach)

    @property
    def obstruction(self):
        return 0.0

    @property
    def area(self):
        """Collecting area (m^2) of the holes."""
        one = (np.sqrt(3) / 2 * self.hole_diameter ** 2 if self.shape == "hex"
               else np.pi / 4 * self.hole_diameter ** 2)
        return float(len(self.holes) * one)

    def transmission(self, x, y):
        """Return 1 inside a hole and 0 elsewhere, at points ``(x, y)`` in metres."""
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        if self.shape == "hex":
            return _in_hexagons(x, y, self.holes, self.hole_diameter).astype(float)
        inside = np.zeros(np.broadcast(x, y).shape, bool)
        for cx, cy in self.holes:
            inside |= (x - cx) ** 2 + (y - cy) ** 2 <= (self.hole_diameter / 2) ** 2
        return inside.astype(float)


_STRUTS = ((0.0, 0.0, 90.0, 0.11), (0.0, 0.0, 240.0, 0.12), (0.0, 0.0, -60.0, 0.12))
_SEGS = tuple(map(tuple, JWST_SEGMENTS))

#: NIRISS NRM (g7s6c) hole centres as built (m on the primary, V2 reversed;
#: ImPlaneIA/jwst ``ami``): over segments B4, C2, B5, B2, C1, B6, C6.
NIRISS_NRM_HOLES = ((0.0, -2.64), (2.28631, 0.0), (-2.28631, -1.32), (2.28631, 1.32),
                    (1.14315, 1.98), (-2.28631, 1.32), (-1.14315, 1.98))

#: GPI g10s40 mask hole centres (mm at the mask; x 647.62 to the primary).
GPI_NRM_HOLES_MM = ((-1.061, -3.882), (-0.389, -5.192), (2.814, -0.243), (3.616, 0.995),
                    (-4.419, 2.676), (-1.342, 5.077), (-4.672, -2.421), (4.157, -2.864),
                    (5.091, 0.920), (1.599, 4.929))
GPI_MASK_MAGNIFICATION = 647.62

#: The shapes registered in `kpifs.model.pupil.TELESCOPES` by `kpifs.model.apertures`.
SEGMENTED_TELESCOPES = {
    "jwst": SegmentedAperture(_SEGS, JWST_SEGMENT, 6.603464, _STRUTS,
                              name="JWST (18 segments, struts)"),
    "niriss_clearp": SegmentedAperture(
        _SEGS, JWST_SEGMENT, 6.603464, _STRUTS, disc=(0.026, 0.013, 1.02),
        disc_vanes=tuple((0.0, 0.0, a, 0.33) for a in (90.0, 240.0, -60.0)), area=22.2,
        name="JWST/NIRISS CLEARP"),
}
SEGMENTED_TELESCOPES["nircam_clear"] = SEGMENTED_TELESCOPES["jwst"]

#: Keck segments: 1.8 m corner to corner (1.5588 m flat to flat), 3 mm gaps.
KECK_SEGMENT = 1.8 * np.sqrt(3) / 2
KECK_PITCH = KECK_SEGMENT + 0.003


def _hex_rings(pitch, rings):
    """Centres of the segments of *rings* rings around a missing central one, flat-topped
    hexagons (neighbours along 30 + 60k deg)."""
    e1 = pitch * np.array([np.cos(np.pi / 6), np.sin(np.pi / 6)])
    e2 = pitch * np.array([0.0, 1.0])
    return tuple(tuple(q * e1 + r * e2) for q in range(-rings, rings + 1)
                 for r in range(-rings, rings + 1)
                 if 1 <= (abs(q) + abs(r) + abs(q + r)) // 2 <= rings)


_KECK_SEGS = _hex_rings(KECK_PITCH, 3)
#: Keck I/II primary as NIRC2 sees it through its ``largehex``/``open`` stops: 36 segments
#: (10.95 m across corners), the secondary's 2.65 m obscuration and six 25 mm spider
#: vanes at 60 deg steps (Keck NGAO pupil notes, as hcipy's Keck aperture cites them).
#: Its turn on the detector is assumed (flat-topped segments): measure it with
#: ``kpifs model-check``.
SEGMENTED_TELESCOPES["keck"] = SegmentedAperture(
    _KECK_SEGS, KECK_SEGMENT, 10.95, tuple((0.0, 0.0, a, 0.025) for a in range(0, 360, 60)),
    disc=(0.0, 0.0, 1.325), area=71.9,          # m^2, summed on a 1 cm grid
    name="Keck (36 segments, secondary, spiders)")
