"""Memory a computation needs, checked before it is allocated. Imports nothing of kpifs but
its exceptions, so that every module can use it, the readers included (`kpifs._checks`
re-exports it)."""
import os

from .exceptions import KpifsError

__all__ = []


def available_memory():
    """Bytes of memory available to a new allocation (MemAvailable; else physical)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 2 ** 40


def _size(nbytes):
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB"):
        if nbytes < 1024 or unit == "EiB":
            return f"{nbytes:.0f} {unit}" if nbytes >= 1000 else f"{nbytes:.3g} {unit}"
        nbytes /= 1024


def check_memory(nbytes, what, advice):
    """Refuse a computation whose estimated memory exceeds what is available (or cannot
    be estimated: not finite)."""
    avail = available_memory()
    if not nbytes <= avail:
        raise KpifsError(f"{what} needs about {_size(nbytes)} of memory ({_size(avail)} "
                         f"available): {advice}")
