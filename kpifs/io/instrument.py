"""What kpifs knows of an instrument, in one object per instrument module.

Each instrument module (`kpifs.io.nirc2`, for one) ends with an `Instrument`
named ``INSTRUMENT``: its recognition from a file's headers (an identifier, as
in astropy's I/O registry), its reader to `~kpifs.io.IFSCube`, its angle
convention, its default pupil and pixel scale, the facts its calibrator must
share (`setup`), its simulator layout, scenes, field and rotating sequences,
how the injector writes copies of its files, and the ``TELESCOP`` of its
products. `kpifs.io.instruments` lists them once; the command line, the
driver's default pupil, `header_pupil`, the simulator, the injector and the
KPFITS writer read that list, and no other module names an instrument.
"""
from dataclasses import dataclass, field

import numpy as np
from astropy import units as u
from astropy.io import fits

from .._meta import VERSION
from ..exceptions import KpifsError
from .cube import FrameStack, IFSCube

__all__ = ["Instrument", "read_each", "simulated_header", "add_truth", "frame_angles",
           "header_card"]


def header_card(header, key):
    """A header card as an upper-case stripped string ('' when missing or empty).

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.instrument import header_card
    >>> header_card(fits.Header({"INSTRUME": " nirc2 "}), "INSTRUME")
    'NIRC2'
    """
    if header is None:
        return ""
    try:
        value = header.get(key, "")
    except (fits.VerifyError, ValueError):
        return ""
    return str(value if value is not None else "").strip().upper()


@dataclass(frozen=True)
class Instrument:
    """One instrument as kpifs reads it (see the module's docstring).

    Attributes
    ----------
    name : str
        The name ``--instrument`` takes (lower case).
    title : str
        The instrument as people write it (``'Keck/NIRC2'``).
    identify : callable
        ``identify(hdul) -> bool``: True when an open file is one of this
        instrument's (astropy's registry identifiers).
    read : callable
        ``read(paths, *, wavelengths, pixscale, angles, dq_bits, pa_given)``
        -> `~kpifs.io.IFSCube` of the files (their frames, in order).
    pupil : str
        The built-in pupil of its cubes when the header names none.
    instrume : tuple of str
        ``INSTRUME`` values of its headers (upper case).
    keywords : tuple of str
        Cards that name it in headers without such an ``INSTRUME``.
    header_pupil : callable or None
        ``header_pupil(header) -> str or None``: the pupil a header names
        (a mask, a pupil-plane element).
    pupils : tuple of str
        The built-in pupils that fit its telescope: another one given with its
        headers is warned about.
    setup : callable or None
        ``setup(header) -> dict``: what a target's and its calibrator's files
        must share (filter, mode, pupil element), as far as the header says.
    pixscale : str
        Its pixel scale(s), in words, for ``kpifs info --instruments``.
    angles : str
        Its angle convention: where each frame's detector position angle comes
        from.
    layout : str or None
        The name of its simulator layout (``kpifs simulate --layout``).
    write : callable or None
        ``write(obs, role, outdir, common) -> list of paths``: a simulated star
        (``role`` 'target' or 'calibrator' of a
        `~kpifs.simulation.simulate.SimulatedObservation`) in its files.
    scenes : dict
        Simulator presets it adds (name -> `~kpifs.simulation.simulate.SceneParameters`
        fields).
    hint : callable or None
        ``hint(hdul, path)``: called for a file no instrument claims, to warn when
        its header almost names this one.
    telescop : str
        The ``TELESCOP`` of its products when its headers have none ('': unknown).
    field_mask : callable or None
        ``field_mask(shape) -> bool array``: the illuminated field of its cubes, which the
        simulator blanks outside (a scene's ``field``, named after the instrument).
    sequence : tuple or None
        ``(detector angle at parallactic angle 0 in deg, site)`` of the pupil-tracking
        sequences simulated with its scenes (``kpifs simulate --rotation`` or
        ``--hour-angle``; a site of `kpifs.rotation.SITES`); None: 0 deg at Maunakea.
    data_hdu : int, str or None
        The HDU of its files that holds the frames, for a copy of them (the injector,
        `kpifs.io.layouts_like`); None: the first image of at least `data_ndim` axes.
    data_ndim : int
        The fewest axes of its frames' image (with `data_hdu` None).
    to_file : callable or None
        ``to_file(source, block, shape) -> array``: a block ``(nframe, nwave, ny, nx)``
        of the cube as the array of its file (a `~kpifs.io.layouts_like.SourceFile`,
        *shape*); None: the cube's own axes, reshaped.
    copy_note : str or None
        What a copy of one of its files lacks, said by the injector before the input's
        name (its reader finds more in the files beside the cube).

    Examples
    --------
    >>> from kpifs.io.instruments import INSTRUMENTS
    >>> INSTRUMENTS["nirc2"].title, INSTRUMENTS["nirc2"].pupil
    ('Keck/NIRC2', 'keck')
    """

    name: str
    title: str
    identify: object
    read: object
    pupil: str = "subaru"
    instrume: tuple = ()
    keywords: tuple = ()
    header_pupil: object = None
    pupils: tuple = ()
    setup: object = None
    pixscale: str = ""
    angles: str = ""
    layout: str = None
    write: object = None
    scenes: dict = field(default_factory=dict)
    hint: object = None
    telescop: str = ""
    field_mask: object = None
    sequence: tuple = None
    data_hdu: object = None
    data_ndim: int = 2
    to_file: object = None
    copy_note: str = None

    def names(self, header):
        """True when *header*'s ``INSTRUME`` is this instrument's."""
        return header_card(header, "INSTRUME") in self.instrume

    def suggests(self, header):
        """True when *header* has one of this instrument's own cards (`keywords`)."""
        return header is not None and any(k in header for k in self.keywords)


def read_each(read_one):
    """A reader of several files from *read_one(path, **options)*, one file at a time,
    the cubes joined as more frames of one (wavelengths and pixel scale must agree).

    Examples
    --------
    >>> from kpifs.io.instrument import read_each
    >>> from kpifs.io.cube import read_generic
    >>> read = read_each(lambda p, **kw: read_generic(p, wavelengths=kw["wavelengths"],
    ...                                               pixscale=kw["pixscale"]))
    >>> callable(read)
    True
    """
    def read(paths, **options):
        cubes = []
        try:
            for p in paths:
                cubes.append(read_one(p, **options))
            return cubes[0] if len(cubes) == 1 else _concatenate(cubes)
        except BaseException:
            for c in cubes:
                c.close()
            raise
    return read


def _concatenate(cubes):
    first = cubes[0]
    for c in cubes[1:]:
        if len(c.wavelengths) != len(first.wavelengths) or not np.allclose(
                c.wavelengths, first.wavelengths, rtol=1e-5):
            raise KpifsError(f"{c.name}: its wavelengths differ from those of {first.name}")
        if abs(c.pixscale / first.pixscale - 1) > 1e-3:
            raise KpifsError(f"{c.name}: pixel scale {c.pixscale} differs from {first.pixscale}")
    stack = FrameStack([c.data for c in cubes])
    files = [f for c in cubes for f in c._files]
    angles = detpa = None
    if all(c.angles is not None for c in cubes):
        angles = np.concatenate([c.angles.to_value(u.deg) for c in cubes]) * u.deg
    if all(c.detpa is not None for c in cubes):
        detpa = np.concatenate([c.detpa.to_value(u.deg) for c in cubes]) * u.deg
    sources = list(dict.fromkeys(c.detpa_source for c in cubes))
    return IFSCube(data=stack, wavelengths=first.wavelengths, pixscale=first.pixscale,
                   header=first.header, angles=angles, detpa=detpa,
                   detpa_source="; ".join(str(s) for s in sources), instrument=first.instrument,
                   source=[s for c in cubes for s in c.source], _files=files)


def simulated_header(cards, *, instrument, pixscale, exptime=None, obj="SIMULATED"):
    """The primary header of a simulated file: ``OBJECT``, ``INSTRUME``, ``PIXSCALE``
    (mas), ``EXPTIME``, the simulation's *cards* and kpifs's version.

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs.io.instrument import simulated_header
    >>> simulated_header({}, instrument="nirc2", pixscale=9.971 * u.mas)["INSTRUME"]
    'NIRC2'
    """
    hdr = fits.Header()
    hdr["OBJECT"] = (obj, "target name")
    hdr["INSTRUME"] = (instrument.upper(), "instrument")
    hdr["PIXSCALE"] = (float(pixscale.to_value(u.mas)), "[mas] pixel scale")
    if exptime is not None:
        hdr["EXPTIME"] = (float(exptime.to_value(u.s)), "[s] exposure time")
    for key, val in cards.items():
        hdr[key] = val
    hdr["KPIFSVER"] = (VERSION, "kpifs version")
    hdr.add_history(f"simulated by kpifs {VERSION}")
    return hdr


def add_truth(hdr, cards, obj):
    """Put a simulation's *cards*, ``TARGNAME`` and kpifs's version in *hdr* (in place).

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.instrument import add_truth
    >>> hdr = fits.Header()
    >>> add_truth(hdr, {"KPSIMROL": "target"}, "SIM-TARGET")
    >>> hdr["TARGNAME"], hdr["KPSIMROL"]
    ('SIM-TARGET', 'target')
    """
    hdr["TARGNAME"] = (obj, "target name")
    for key, val in (cards or {}).items():
        hdr[key] = val
    hdr["KPIFSVER"] = (VERSION, "kpifs version")
    hdr.add_history(f"simulated by kpifs {VERSION}")


def frame_angles(params, nframe, offset):
    """The instrument's angle of each simulated frame (its DETPA minus *offset*, deg), or
    None when the scene has no detector angles (issue 29).

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> from kpifs.io.instrument import frame_angles
    >>> frame_angles(SimpleNamespace(detpa=[120.0]), 2, 113.0)
    array([7., 7.])
    """
    if params.detpa is None:
        return None
    return np.broadcast_to(np.asarray(params.detpa, float), (nframe,)) - offset
