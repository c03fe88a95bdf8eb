"""Resident memory of memory-mapped inputs.

Reading a memory-mapped file maps every page touched into the process, so its
resident set grows to the size of the file over one pass (a 2.9 GB cube read
batch by batch ends with 2.9 GB resident, although only one batch is in use).
`release_pages`, called after each batch, gives those pages back: they stay in
the operating system's file cache, so reading them again costs no disk access.
"""
import mmap

__all__ = ["release_pages"]


def _mapping_of(array):
    """The `mmap.mmap` behind a memory-mapped array (or a view of one), or None."""
    base = array
    for _ in range(32):
        if base is None or isinstance(base, mmap.mmap):
            return base
        base = getattr(base, "base", None)
    return None


def release_pages(data):
    """Unmap the pages of memory-mapped arrays behind *data* that were read.

    *data* is an array (a view of a memory-mapped FITS HDU, a `numpy.memmap`)
    or a `~kpifs.io.FrameStack`, whose parts (and bad-pixel parts) are
    released one by one. Anything not memory-mapped is left alone. The data
    stay valid: a page read again is mapped again from the file cache.

    Examples
    --------
    >>> import tempfile, numpy as np
    >>> from astropy.io import fits
    >>> from kpifs.io.pages import release_pages
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = tmp.name + "/c.fits"
    >>> fits.writeto(path, np.ones((4, 64, 64), np.float32))
    >>> with fits.open(path, memmap=True) as hdul:
    ...     first = float(hdul[0].data.sum()); release_pages(hdul[0].data)
    ...     again = float(hdul[0].data.sum())
    >>> first, again
    (16384.0, 16384.0)
    >>> tmp.cleanup()
    """
    parts = getattr(data, "parts", None)
    if parts is not None and not hasattr(data, "base"):      # a FrameStack
        for part in list(parts) + list(getattr(data, "bad", None) or []):
            release_pages(getattr(part, "cube", getattr(part, "ivar", part)))
        return
    mm = _mapping_of(data)
    if mm is None or not hasattr(mm, "madvise"):
        return
    try:
        mm.madvise(mmap.MADV_DONTNEED)
    except (ValueError, OSError):   # closed, or refused: only memory is at stake
        pass
