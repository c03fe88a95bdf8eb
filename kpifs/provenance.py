"""Provenance of products: options as plain values and digests of options and inputs.

``KPXOPTS``/``KPDOPTS`` (the options), ``KPINHASH`` (the inputs) and ``KPHASH``
(all of them) in the products come from here; ``kpifs batch`` redoes an entry
whose ``KPHASH`` changed. Reached through `kpifs.workflow`.
"""
import dataclasses
import hashlib
import json
import os
from pathlib import Path

import numpy as np
from astropy import units as u

__all__ = ["options_record", "file_digest", "combined_digest", "inputs_digest",
           "observation_digest", "products_digest"]


def options_record(options):
    """The options as a dict of plain values (units written out), for provenance.

    Examples
    --------
    >>> from kpifs.workflow import ExtractOptions, options_record
    >>> options_record(ExtractOptions(step="0.8m"))["step"]
    '0.8m'
    """
    out = {}
    for f in dataclasses.fields(options):
        v = getattr(options, f.name)
        if isinstance(v, u.Quantity):
            v = v.to_string() if v.isscalar else [q.to_string() for q in v]
        elif isinstance(v, np.ndarray):
            v = "sha1:" + hashlib.sha1(np.ascontiguousarray(v).tobytes()).hexdigest()[:12]
        elif isinstance(v, Path):
            v = str(v)
        if isinstance(v, str) and v and os.path.isfile(v):
            # an option given as a file (wavelengths, pupil, spectrum, angles): its content
            # counts, so that a rerun after the file changed redoes the work
            v = f"{os.path.abspath(v)} (sha256:{_file_sha256(v)})"
        elif not isinstance(v, (int, float, str, bool, list, tuple, type(None))):
            v = repr(v)
        out[f.name] = v
    return out


#: sha256 of files already read by this process, by their status (device, inode, size,
#: modification and change times): a file replaced or rewritten, even with its size and
#: modification time put back, has another change time and is read again.
_DIGESTS = {}


def file_digest(path):
    """The sha256 of a file's content (hex), or None when it cannot be read.

    Read once per process while the file's status is unchanged (``_DIGESTS``).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kpifs.provenance import file_digest
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "a.txt"
    >>> _ = p.write_bytes(b"x")
    >>> file_digest(p)[:16]
    '2d711642b726b044'
    """
    try:
        st = os.stat(path)
        key = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
        if key not in _DIGESTS:
            h = hashlib.sha256()
            with open(path, "rb") as f:
                for chunk in iter(lambda: f.read(1 << 22), b""):
                    h.update(chunk)
            if len(_DIGESTS) > 100000:
                _DIGESTS.clear()
            _DIGESTS[key] = h.hexdigest()
        return _DIGESTS[key]
    except OSError:
        return None


def _file_sha256(path):
    return (file_digest(path) or "unreadable")[:16]


def combined_digest(payload):
    """A short digest of any JSON-able *payload* (digests of several inputs, ...).

    Examples
    --------
    >>> from kpifs.provenance import combined_digest
    >>> a, b = combined_digest(["a", "b"]), combined_digest(["b", "a"])
    >>> a == combined_digest(["a", "b"]) and a != b
    True
    """
    text = json.dumps(payload, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def inputs_digest(files):
    """A digest of input files: their absolute paths and contents (sha256, `file_digest`),
    so that a file replaced with the same size and modification time counts as changed.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kpifs.workflow import inputs_digest
    >>> tmp = tempfile.TemporaryDirectory()
    >>> p = pathlib.Path(tmp.name) / "a.fits"
    >>> _ = p.write_bytes(b"x")
    >>> inputs_digest([p]) == inputs_digest([str(p)]), len(inputs_digest([p]))
    (True, 20)
    >>> tmp.cleanup()
    """
    return combined_digest([[os.path.abspath(f), file_digest(f)] for f in files])


def observation_digest(target, calibrators, extract_options, detect_options):
    """The ``KPHASH`` that `process_observation` gives the products of these inputs and
    options (without running anything).

    Examples
    --------
    >>> from kpifs.workflow import DetectOptions, ExtractOptions, observation_digest
    >>> len(observation_digest(["t.fits"], [["c.fits"]], ExtractOptions(), DetectOptions()))
    20
    """
    # as the product's KPINHASH: the target's own digest alone without calibrator (an
    # angular-differential product), else combined with the calibrators'
    inputs = (combined_digest([inputs_digest(target)] + [inputs_digest(c) for c in calibrators])
              if calibrators else inputs_digest(target))
    return products_digest(options_record(extract_options), inputs,
                           options_record(detect_options))


def products_digest(extract_record, inputs, detect_record):
    """Digest of what makes a detection product: extraction options, input digest(s) and
    detection options (``KPHASH`` in the products; ``kpifs batch`` redoes an entry whose
    digest changed).

    Examples
    --------
    >>> from kpifs.workflow import (DetectOptions, ExtractOptions, options_record,
    ...                             products_digest)
    >>> a = products_digest(options_record(ExtractOptions()), "x", options_record(DetectOptions()))
    >>> b = products_digest(options_record(ExtractOptions()), "x",
    ...                     options_record(DetectOptions(pfa=1e-4)))
    >>> a == b
    False
    """
    return combined_digest({"extract": extract_record, "inputs": inputs, "detect": detect_record})
