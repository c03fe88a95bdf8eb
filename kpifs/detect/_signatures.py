"""Signature norms and unit signatures, chunk by chunk (shared by the detection
model and the block model of a rotating sequence)."""
import numpy as np


def _norm_chunks(rows, size, signatures, at, wf, unit, basis=None):
    """``||s||^2`` of ``signatures(chunk)`` (len(chunk), p) over flat *rows*, *size*
    at a time; the unit signatures of rows *at* go into *unit* (None: not kept).
    With *basis* (p, r), orthonormal, the signatures are given in its coordinates
    (len(chunk), r): the norms are theirs, the unit signatures ``s @ basis.T``."""
    raw = np.empty(len(rows))
    for a in range(0, len(rows), size):
        s = signatures(rows[a:a + size])
        raw[a:a + len(s)] = np.einsum("ij,ij->i", s, s)
        if unit is not None:
            sel = (at >= a) & (at < a + len(s))
            kept = s[at[sel] - a]
            unit[sel] = _unit(kept if basis is None else kept @ basis.T, raw[at[sel]],
                              wf[sel])
    return raw


def _unit(s, norm2, wf):
    """Unit signatures ``-s / ||s||`` from ``s = sin(theta) L`` and its squared norms
    (NaN where the window factor *wf* is 0, as the norms there are)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return -s / np.where(wf > 0, np.sqrt(norm2), 0.0)[:, None]
