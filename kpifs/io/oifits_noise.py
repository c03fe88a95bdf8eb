"""The covariance of OIFITS closure phases, and the memory a file's sizes imply.

Sources, in the order they are applied (all in rad^2, over the closure phases
kept, index ``(channel, triangle)``):

- ``T3PHIERR``: every closure phase's standard deviation.
- The triangles of one exposure share baselines. A closure phase is
  ``t = C phi`` of its baselines' phases ``phi``; noise that is independent
  on each baseline, of one variance, gives ``cov(t) = s^2 C C^T``: every
  triangle sums three baselines, and two triangles sharing one are
  correlated by ``+-1/3``. Where a file states no correlations (no
  ``OI_CORR`` index, no ``CPCOV``), the triangles of each exposure that
  outnumber its independent closure phases get these correlations, scaled
  to their own ``T3PHIERR`` (``correlations='baselines'``, the default).
  Taking them as independent (``correlations='independent'``) gives the
  independent closure phases a variance ``N / 3`` times too small for an
  array of ``N`` stations that measures every triangle (the projection of
  `kpifs.io.oifits` on ``S^-1 U^T`` divides by ``S^2 = N``): the detection
  significance of a closure-phase search is then over-stated by
  ``sqrt(N / 3)``.
- ``OI_CORR`` (``CORRINDX_T3PHI``): the correlations a file states, within
  or across channels and exposures.
- ``CPCOV`` image extensions (fouriever): one ``(ntri nwave, ntri nwave)``
  matrix per observation, triangle-major.

The covariance is kept per channel ``(nwave, ntri, ntri)`` unless a source
correlates channels (then one joint matrix). Before anything of a size
implied by the file's numbers is allocated, its memory is estimated and the
read refused (`~kpifs.exceptions.KpifsError`) when it exceeds what the
machine has.
"""

import numpy as np

from .._memory import check_memory
from ..exceptions import KpifsError

__all__ = ["closure_covariance", "check_size", "CORRELATIONS"]

#: What closure phases that a file gives no correlations for are taken to share.
CORRELATIONS = ("baselines", "independent")


def check_size(nbytes, what, source, advice):
    """Refuse (`~kpifs.exceptions.KpifsError`) what needs more memory than is available.

    Examples
    --------
    >>> from kpifs.io.oifits_noise import check_size
    >>> check_size(1e3, "a table", "x.oifits", "read less")
    >>> try:
    ...     check_size(2e20, "a covariance", "x.oifits", "read one INSNAME")
    ... except Exception as exc:
    ...     print(str(exc)[:52])
    x.oifits: a covariance needs about 173 EiB of memory
    """
    check_memory(float(nbytes), f"{source}: {what}", advice)


def _baseline_correlation(cmat, epoch):
    """``C C^T / 3`` of each exposure, block-diagonal: the correlation of closure phases
    whose baselines carry independent noise of one variance."""
    ntri = len(cmat)
    r = np.zeros((ntri, ntri))
    for e in np.unique(epoch):
        ti = np.flatnonzero(epoch == e)
        c = cmat[ti]
        r[np.ix_(ti, ti)] = c @ c.T / 3.0
    return r


def _corr_entries(corrs, rows, starts, nw, path):
    """``(a, b, rho)``: the OI_CORR entries between kept closure phases, as flat indices
    ``tri * nw + w`` of the stacked rows (all rows, before any is dropped)."""
    lookup = {}
    for r, s in zip(rows, starts):
        if r["corr"] is None or not r["corrname"]:
            continue
        for i, c0 in enumerate(r["corr"]):
            for w in range(nw):
                lookup[(r["corrname"], int(c0) + w)] = (s + i) * nw + w
    a, b, rho, names = [], [], [], []
    for name, d in corrs.items():
        ki = [lookup.get((name, int(i))) for i in d["IINDX"]]
        kj = [lookup.get((name, int(j))) for j in d["JINDX"]]
        ok = np.array([x is not None and y is not None for x, y in zip(ki, kj)], bool)
        if not ok.any():
            continue
        a.append(np.array([x for x, o in zip(ki, ok) if o], int))
        b.append(np.array([y for y, o in zip(kj, ok) if o], int))
        rho.append(np.asarray(d["CORR"], float)[ok])
        names.append(name)
    if not a:
        return None, []
    return (np.concatenate(a), np.concatenate(b), np.concatenate(rho)), names


def _stated(rows, starts, cpcov_ins):
    """Rows whose correlations the file states (a CORRINDX with a CORRNAME, or a CPCOV)."""
    stated = np.zeros(int(starts[-1]), bool)
    for r, s in zip(rows, starts):
        n = len(r["err"])
        if (r["corr"] is not None and r["corrname"]) or (
                cpcov_ins is not None and ("" in cpcov_ins or r["ins"] in cpcov_ins)):
            stated[s:s + n] = True
    return stated


def closure_covariance(ctx, *, correlations="baselines"):
    """Covariance of the kept closure phases and the names of its sources.

    *ctx* holds ``path``, ``rows`` (the OI_T3 tables read), ``keep`` (rows
    kept), ``keep_ch`` (channels kept), ``err`` (kept, (ntri, nw) rad),
    ``cmat`` and ``epoch`` (the kept triangles' closure operator and
    exposures), ``corrs`` (``{CORRNAME: OI_CORR data}``) and ``cpcov``
    (``[(INSNAME, data (nobs, m, m) rad^2)]``).

    Returns
    -------
    per : ndarray (nw, ntri, ntri) or None
        Per-channel covariance when no source correlates channels.
    joint : ndarray (nw ntri, nw ntri) or None
        Else the joint covariance, channel-major: index ``w * ntri + tri``.
    sources : list of str
    """
    if correlations not in CORRELATIONS:
        raise KpifsError(f"correlations must be one of {CORRELATIONS}, got {correlations!r}")
    path, rows, err = ctx["path"], ctx["rows"], ctx["err"]
    ntri, nw = err.shape
    nw0 = len(ctx["keep_ch"])
    starts = np.cumsum([0] + [len(r["err"]) for r in rows])
    kept_rows = np.flatnonzero(ctx["keep"])
    kept_ch = np.flatnonzero(ctx["keep_ch"])
    where_row = np.full(int(starts[-1]), -1)
    where_row[kept_rows] = np.arange(ntri)
    where_ch = np.full(nw0, -1)
    where_ch[kept_ch] = np.arange(nw)
    entries, names = _corr_entries(ctx["corrs"], rows, starts, nw0, path)
    sources = ["T3PHIERR"]
    cpcov = ctx["cpcov"]
    cross = bool(cpcov)
    if entries is not None:
        a, b, rho = entries
        ra, wa = where_row[a // nw0], where_ch[a % nw0]
        rb, wb = where_row[b // nw0], where_ch[b % nw0]
        ok = (ra >= 0) & (rb >= 0) & (wa >= 0) & (wb >= 0)
        entries = (ra[ok], wa[ok], rb[ok], wb[ok], rho[ok])
        cross = cross or bool(np.any(wa[ok] != wb[ok]))
        sources += [f"OI_CORR {n!r}" for n in names]
    n = ntri * nw
    check_size(8.0 * (3 * n * n if cross else 3 * nw * ntri * ntri),
               f"the covariance of {ntri} closure phases x {nw} channel(s)"
               + (" correlated across channels" if cross else ""), path,
               "read one INSNAME (insname=...) or fewer files at once")
    corr = np.zeros((ntri, ntri))
    stated = _stated(rows, starts, None if not cpcov else {i for i, _ in cpcov})[kept_rows]
    if correlations == "baselines":
        free = ~stated
        if free.any():
            base = _baseline_correlation(ctx["cmat"], ctx["epoch"])
            corr[np.ix_(free, free)] = base[np.ix_(free, free)]
            if np.any(np.abs(corr - np.diag(np.diag(corr))) > 0):
                sources.append("shared baselines")
    np.fill_diagonal(corr, 1.0)
    per = err.T[:, :, None] * corr[None] * err.T[:, None, :]             # (nw, ntri, ntri)
    if not cross:
        if entries is not None:
            ra, wa, rb, _, rho = entries
            c = rho * err[ra, wa] * err[rb, wa]
            per[wa, ra, rb] = c
            per[wa, rb, ra] = c
        return per, None, sources
    joint = np.zeros((n, n))
    for w in range(nw):
        joint[w * ntri:(w + 1) * ntri, w * ntri:(w + 1) * ntri] = per[w]
    del per
    if entries is not None:
        ra, wa, rb, wb, rho = entries
        i, j = wa * ntri + ra, wb * ntri + rb
        c = rho * err[ra, wa] * err[rb, wb]
        joint[i, j] = c
        joint[j, i] = c
    for ins, data in cpcov:
        _apply_cpcov(joint, ins, data, rows, starts, where_row, where_ch, ntri, path)
        sources.append("CPCOV")
    return None, joint, sources


def _apply_cpcov(joint, ins, data, rows, starts, where_row, where_ch, ntri, path):
    """Write one CPCOV extension's blocks (triangle-major, per observation) in *joint*."""
    nw0 = len(where_ch)
    sel = [np.arange(s, s + len(r["err"])) for r, s in zip(rows, starts)
           if not ins or r["ins"] == ins]
    sel = np.concatenate(sel) if sel else np.zeros(0, int)
    nobs, m = data.shape[0], data.shape[-1]
    if data.shape[1] != m or m % nw0 or nobs * (m // nw0) != len(sel):
        raise KpifsError(f"{path}: CPCOV {ins!r} has shape {data.shape}, which does not "
                         f"match the {len(sel)} OI_T3 rows x {nw0} channels it covers")
    per = m // nw0
    for o in range(nobs):
        tri = where_row[sel[o * per:(o + 1) * per]]
        t_idx = np.repeat(tri, nw0)                          # triangle-major
        w_idx = np.tile(where_ch, per)
        ok = (t_idx >= 0) & (w_idx >= 0)
        idx = (w_idx * ntri + t_idx)[ok]
        joint[np.ix_(idx, idx)] = data[o][np.ix_(ok, ok)]
