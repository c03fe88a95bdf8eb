"""``read``/``write`` methods of kpifs's containers through astropy's unified I/O registry.

A container class sets ``_io_format`` (its default format name) and
``read, write = io_methods("Name")``; the module that knows how to build it
registers the functions with `astropy.io.registry`, as `~astropy.table.Table`
and `~astropy.nddata.CCDData` do. Each class gets its own reader and writer
classes, because the registry writes the list of formats into their
docstrings.
"""
import os

from astropy.io import registry

__all__ = []


class _Reader(registry.UnifiedReadWrite):
    def __init__(self, instance, cls):
        super().__init__(instance, cls, "read", registry=None)

    def __call__(self, *args, format=None, **kwargs):
        return self.registry.read(self._cls, *args,
                                  format=format or _identified(self, "read", args, kwargs),
                                  **kwargs)


class _Writer(registry.UnifiedReadWrite):
    def __init__(self, instance, cls):
        super().__init__(instance, cls, "write", registry=None)

    def __call__(self, *args, format=None, **kwargs):
        return self.registry.write(self._instance, *args,
                                   format=format or _identified(self, "write", args, kwargs),
                                   **kwargs)


def _identified(rw, origin, args, kwargs):
    """The one format whose identifier claims the file (an OIFITS name or content), else
    the class's own."""
    first = args[0][0] if args and isinstance(args[0], (list, tuple)) and args[0] else \
        (args[0] if args else None)                  # several files: the first one's format
    if isinstance(first, (str, os.PathLike)):
        found = rw.registry.identify_format(origin, rw._cls, str(first), None, args[1:],
                                            kwargs)
        if len(found) == 1:
            return found[0]
    return rw._cls._io_format


def io_methods(name):
    """``(read, write)`` descriptors for the container class called *name*."""
    read_doc = f"""Read a `{name}` from a file.

    ``{name}.read(path, format=None, **kwargs)``: the class's own format
    unless *format* names another registered one.
    """
    write_doc = f"""Write this `{name}` to a file (atomically; never over an input).

    ``obj.write(path, format=None, overwrite=False, **kwargs)``: the class's
    own format unless *format* names another registered one.
    """
    reader = type(f"{name}Read", (_Reader,), {"__doc__": read_doc, "_base_doc": read_doc})
    writer = type(f"{name}Write", (_Writer,), {"__doc__": write_doc, "_base_doc": write_doc})
    return (registry.UnifiedReadWriteMethod(reader), registry.UnifiedReadWriteMethod(writer))


def register(cls, fmt, reader=None, writer=None, identifier=None):
    """Register *reader*/*writer*/*identifier* for *cls* under format *fmt*.

    The registry would rewrite the ``read``/``write`` docstrings with a table of
    the formats at each registration, importing `astropy.table` (a tenth of a
    second of the command line's start, for a docstring): the docstrings are
    written with the formats in plain text instead (`_document`).
    """
    delayed = getattr(registry.compat.default_registry, "_delayed_docs_classes", None)
    if delayed is not None:
        delayed.add(cls)
    try:
        if reader is not None:
            registry.register_reader(fmt, cls, reader, force=True)
        if writer is not None:
            registry.register_writer(fmt, cls, writer, force=True)
        if identifier is not None:
            registry.register_identifier(fmt, cls, identifier, force=True)
    finally:
        if delayed is not None:
            delayed.discard(cls)
    _document(cls)


def _document(cls):
    """Name the formats registered for *cls* in its ``read``/``write`` docstrings."""
    readers = getattr(registry.compat, "_readers", {})
    writers = getattr(registry.compat, "_writers", {})
    for method, table in (("read", readers), ("write", writers)):
        rw = cls.__dict__.get(method)
        if rw is None:
            continue
        kind = type(rw.fget(None, cls)) if hasattr(rw, "fget") else None
        base = getattr(kind, "_base_doc", None)
        if kind is None or base is None:
            continue
        formats = sorted(f for f, c in table if c is cls)
        kind.__doc__ = base + f"\n    Formats: {', '.join(formats)}.\n"
