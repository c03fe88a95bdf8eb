"""The instruments kpifs reads, registered once: one line each.

Each is an `~kpifs.io.instrument.Instrument` that its own module defines (its
recognition from headers, reader, angle convention, default pupil, calibrator
checks and simulator layout). A file is claimed by the first whose identifier
accepts it, in the order below; ``generic`` (any FITS cube, the wavelengths
and pixel scale given) takes what no other claims. Adding an instrument is its
module plus one line here.

Examples
--------
>>> from kpifs.io.instruments import INSTRUMENTS
>>> INSTRUMENTS["nirc2"].title, list(INSTRUMENTS)[-1]
('Keck/NIRC2', 'generic')
>>> INSTRUMENTS.by_layout("nirc2") is INSTRUMENTS["nirc2"]
True
>>> INSTRUMENTS.of_scene("sphere-sam").name, INSTRUMENTS.of_scene("paper")
('sphere', None)
"""
from ..exceptions import KpifsError
from . import charis, generic, gpi, jwst, nirc2, sphere

__all__ = ["INSTRUMENTS", "Registry"]


class Registry(dict):
    """Instruments by name, in the order files are recognised (see the module)."""

    def __init__(self, *modules):
        super().__init__((m.INSTRUMENT.name, m.INSTRUMENT) for m in modules)

    def get_instrument(self, name):
        """The instrument called *name* (an error naming the others when there is none)."""
        if name not in self:
            raise KpifsError(f"unknown instrument {name!r}: use one of "
                             f"{', '.join(('auto',) + tuple(self))}")
        return self[name]

    def identify(self, hdul, path):
        """The name of the first instrument whose identifier claims the open file."""
        for inst in self.values():
            if inst.name != "generic" and inst.identify(hdul):
                return inst.name
        for inst in self.values():
            if inst.hint is not None:
                inst.hint(hdul, path)
        return "generic"

    def of_header(self, header):
        """The instrument a header names (``INSTRUME``, else one of its own cards), or None.
        """
        if header is None:
            return None
        named = [i for i in self.values() if i.names(header)]
        return (named or [i for i in self.values() if i.suggests(header)] or [None])[0]

    def layouts(self):
        """The simulator's layout names (``kpifs simulate --layout``)."""
        return tuple(i.layout for i in self.values() if i.write is not None)

    def by_layout(self, layout):
        """The instrument whose simulator layout is *layout*."""
        found = [i for i in self.values() if i.layout == layout and i.write is not None]
        if not found:
            raise KpifsError(f"unknown layout {layout!r}: use one of {self.layouts()}")
        return found[0]

    def scenes(self):
        """The simulator presets the instruments add (name -> scene parameters)."""
        return {k: v for i in self.values() for k, v in i.scenes.items()}

    def of_scene(self, scene):
        """The instrument that adds the simulator preset *scene*, or None."""
        return next((i for i in self.values() if scene in i.scenes), None)


#: Every instrument, in the order a file's headers are tried (one line each).
INSTRUMENTS = Registry(
    charis,
    sphere,
    jwst,
    gpi,
    nirc2,
    generic,
)
