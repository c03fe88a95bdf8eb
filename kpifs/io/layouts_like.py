"""Images written back into copies of the files they were read from: each instrument's layout.

A change made to a cube in kpifs's frame ``(nframe, nwave, ny, nx)`` (a companion
injected, `kpifs.inject`) must be read back as the input was: JWST's ``ERR``, ``DQ``,
``ROLL_REF`` and ``PUPIL``, GPI's mirror, crop and ``AVPARANG``, CHARIS's inverse variance
and ``PARANG``, a SPHERE cube's wave-first order, a plain cube's ``DETPA``. Written as a
generic cube instead, they are lost, and the re-extraction uses another pupil, angle or
noise than the calibrator's (issue 37). `source_layout` records, while the cube is open,
where each of its frames lives in which file; `write_added` writes a copy of each file
with an addition made in the cube's frame mapped back onto the file's own array, at the
pixels that were read as good (bad pixels, NaN and the zeros outside a CHARIS field are
left as they were).
"""
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from astropy.io import fits

from .._utils import write_hdulist
from ..exceptions import KpifsError
from .cube import FrameStack
from .instruments import INSTRUMENTS

__all__ = ["SourceFile", "source_layout", "write_added"]


@dataclass
class SourceFile:
    """Where frames ``start:start + nframe`` of a cube live: *path*, its HDU *hdu* (index
    or name) and how the cube's frame maps onto its array (*kind*; GPI: the crop *ys*,
    *xs* of the x-mirrored image)."""

    path: str
    hdu: object
    start: int
    nframe: int
    kind: str
    ys: slice = None
    xs: slice = None

    def to_file(self, block, shape):
        """A block ``(nframe, nwave, ny, nx)`` of the cube as an array of the file's *shape*
        (its instrument's ``to_file``, else a view of the file's own axes)."""
        inst = INSTRUMENTS.get(self.kind)
        if inst is not None and inst.to_file is not None:
            return inst.to_file(self, block, shape)
        return block.reshape(shape)


def _parts(cube):
    data = cube.data
    return data.parts if isinstance(data, FrameStack) else [data]


def source_layout(cube):
    """The `SourceFile` of each file of an open `~kpifs.io.IFSCube` (read by any reader).

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.io import read_cube, write_observation
    >>> from kpifs.io.layouts_like import source_layout
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> files = write_observation(simulate_scene("paper", n_frames=2, npup=32),
    ...                           tempfile.mkdtemp())
    >>> with read_cube(files["target"]) as cube:
    ...     [(s.hdu, s.start, s.nframe, s.kind) for s in source_layout(cube)]
    [(0, 0, 2, 'generic')]
    """
    parts = _parts(cube)
    if len(parts) != len(cube.source):
        raise KpifsError(f"{cube.name}: cannot tell which frames came from which file")
    kind = cube.instrument
    inst = INSTRUMENTS.get(kind, INSTRUMENTS["generic"])
    out, start = [], 0
    for path, part in zip(cube.source, parts):
        n = part.shape[0]
        hdu = inst.data_hdu
        if hdu is None:
            with fits.open(path) as hdul:
                hdu = next(i for i, h in enumerate(hdul) if h.is_image and h.data is not None
                           and h.data.ndim >= inst.data_ndim)
        out.append(SourceFile(str(path), hdu, start, n, kind, getattr(part, "ys", None),
                              getattr(part, "xs", None)))
        start += n
    return out


def write_added(sources, read, added, outputs, *, cards=None, history=None, overwrite=False):
    """Write a copy of each source file with *added* on its image.

    Parameters
    ----------
    sources : list of `SourceFile`
    read : ndarray (nframe, nwave, ny, nx)
        The cube as it was read (NaN at bad pixels): *added* goes where it is finite.
    added : ndarray (nframe, nwave, ny, nx)
        What to add, in the cube's frame.
    outputs : list of path
        One per source.
    cards : dict, optional
        Cards for each copy's primary header.
    history : str, optional
        A HISTORY line for each copy.

    Returns
    -------
    list of `~pathlib.Path`
    """
    added = np.where(np.isfinite(read), added, 0.0)
    written = []
    for src, out in zip(sources, outputs):
        with fits.open(src.path, memmap=False) as hdul:
            hdu = hdul[src.hdu]
            old = np.asarray(hdu.data)
            block = added[src.start:src.start + src.nframe]
            new = old.astype(float) + src.to_file(block, old.shape)
            if old.dtype.kind != "f":             # scaled integers: written as floats
                for key in ("BZERO", "BSCALE", "BLANK"):
                    hdu.header.remove(key, ignore_missing=True)
            hdu.data = new.astype(old.dtype if old.dtype.kind == "f" else np.float32)
            hdr = hdul[0].header
            for key, value in (cards or {}).items():
                hdr[key] = value
            if history:
                hdr.add_history(history)
            written.append(write_hdulist(hdul, Path(out), overwrite=overwrite))
    return written
