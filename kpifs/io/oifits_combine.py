"""Several OIFITS files of one target, and OI_T3 tables on different wavelength grids.

`read_oifits` reads each file (`~kpifs.io.oifits.read_oifits_parts`; a file
whose INSNAMEs have different wavelength grids is read one INSNAME at a time)
and stacks the reads as the epochs of one file are stacked: their kernel
phases side by side, the kernel operator, baselines and stations
block-diagonal, the covariance block-diagonal (reads are independent).

- Same channels everywhere: the channels are kept (a spectrum per channel).
- Different grids: a closure phase depends on the baselines through ``u /
  lambda`` only, so the closure phases of channel ``lambda`` are those of
  baselines ``u lambda_0 / lambda`` at one reference ``lambda_0`` (the
  shortest wavelength). Every (read, channel) then becomes kernel phases of
  one *achromatic* channel, with its correlations across channels kept inside
  that channel's covariance: exact for the phases, with one contrast for every
  wavelength (a grey companion, as CANDID fits by default). A
  `~kpifs.exceptions.KpifsWarning` says so; ``insname=`` reads one grid with
  its channels instead.
"""
import logging
import warnings

import numpy as np

from ..exceptions import KpifsError, KpifsWarning
from .cube import open_fits
from .oifits import _text, _wavelengths, read_oifits_parts

__all__ = ["read_oifits", "stack_parts", "achromatic_parts", "SCIENCE_SHARE"]

log = logging.getLogger(__name__)


def _block_diag(mats):
    rows = sum(m.shape[0] for m in mats)
    cols = sum(m.shape[1] for m in mats)
    out = np.zeros((rows, cols))
    r = c = 0
    for m in mats:
        out[r:r + m.shape[0], c:c + m.shape[1]] = m
        r, c = r + m.shape[0], c + m.shape[1]
    return out


def _joint(p):
    """A read's channel-major joint covariance ``(nw nk, nw nk)`` (block-diagonal without
    one)."""
    if p["joint_covariance"] is not None:
        return p["joint_covariance"]
    return _block_diag(list(p["covariance"]))


def stack_parts(parts, *, source="OIFITS"):
    """Reads with the same channels as one: kernel phases side by side, models and
    covariances block-diagonal.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.io.oifits_combine import stack_parts
    >>> def part(nk):
    ...     return {"kp": np.zeros((1, 2, nk)), "wavelengths": np.array([1e-6, 2e-6]),
    ...             "bandwidth": np.array([1e-8, 1e-8]), "pixscale": 5.0,
    ...             "model": {"uv": np.ones((3, 2)), "xy": np.zeros((3, 2)),
    ...                       "blm": np.eye(3), "kernel": np.ones((nk, 3)), "step": 1.0,
    ...                       "name": "a", "rank": 3},
    ...             "covariance": np.stack([np.eye(nk)] * 2), "joint_covariance": None,
    ...             "covariance_rows": None, "kp_err": np.ones((1, 2, nk)),
    ...             "header": None, "detpa": np.zeros(1), "meta": {"notes": []}}
    >>> s = stack_parts([part(1), part(2)])
    >>> s["kp"].shape, s["model"]["kernel"].shape, s["covariance"].shape
    ((1, 2, 3), (3, 6), (2, 3, 3))
    """
    first = parts[0]
    nw = len(first["wavelengths"])
    for p in parts[1:]:
        if len(p["wavelengths"]) != nw or not np.allclose(p["wavelengths"],
                                                          first["wavelengths"], rtol=1e-6):
            raise KpifsError(f"{source}: reads of different channels cannot be stacked "
                             f"with their channels (use achromatic_parts)")
    nks = [p["kp"].shape[2] for p in parts]
    off = np.cumsum([0] + nks)
    nk = int(off[-1])
    kp = np.concatenate([p["kp"] for p in parts], axis=2)
    cov = np.stack([_block_diag([p["covariance"][w] for p in parts]) for w in range(nw)])
    coupled = any(p["joint_covariance"] is not None for p in parts)
    joint = rows = None
    if coupled:
        joint = np.zeros((nw * nk, nw * nk))
        for p, o, n in zip(parts, off, nks):
            idx = (np.arange(nw)[:, None] * nk + o + np.arange(n)[None, :]).ravel()
            joint[np.ix_(idx, idx)] = _joint(p)
        ev, vec = np.linalg.eigh(joint)
        good = ev > 1e-12 * ev.max()
        rows = (np.sqrt(ev[good])[:, None] * vec[:, good].T).reshape(-1, nw, nk)
    m = [p["model"] for p in parts]
    model = {"uv": np.vstack([x["uv"] for x in m]), "xy": np.vstack([x["xy"] for x in m]),
             "blm": _block_diag([x["blm"] for x in m]),
             "kernel": _block_diag([x["kernel"] for x in m]),
             "step": float(min(x["step"] for x in m)),
             "name": " + ".join(dict.fromkeys(x["name"] for x in m)),
             "rank": int(sum(x["rank"] for x in m))}
    meta = dict(first["meta"])
    meta["source"] = ", ".join(dict.fromkeys(str(p["meta"].get("source")) for p in parts))
    meta["notes"] = [n for p in parts for n in p["meta"].get("notes", [])]
    meta["n_reads"] = len(parts)
    return {"kp": kp, "wavelengths": first["wavelengths"], "bandwidth": first["bandwidth"],
            "pixscale": float(min(p["pixscale"] for p in parts)), "model": model,
            "covariance": cov, "joint_covariance": joint, "covariance_rows": rows,
            "kp_err": np.concatenate([p["kp_err"] for p in parts], axis=2),
            "header": first["header"], "detpa": np.zeros(1), "meta": meta}


def achromatic_parts(part, reference):
    """One read's channels as kernel phases of one channel at wavelength *reference* (m):
    each channel's baselines scaled by ``reference / lambda``.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.io.oifits_combine import achromatic_parts
    >>> p = {"kp": np.arange(4.0).reshape(1, 2, 2), "wavelengths": np.array([1e-6, 2e-6]),
    ...      "bandwidth": np.array([1e-8, 2e-8]), "pixscale": 5.0,
    ...      "model": {"uv": np.ones((3, 2)), "xy": np.zeros((3, 2)), "blm": np.eye(3),
    ...                "kernel": np.ones((2, 3)), "step": 1.0, "name": "a", "rank": 3},
    ...      "covariance": np.stack([np.eye(2)] * 2), "joint_covariance": None,
    ...      "covariance_rows": None, "kp_err": np.ones((1, 2, 2)), "header": None,
    ...      "detpa": np.zeros(1), "meta": {"notes": []}}
    >>> a = achromatic_parts(p, 1e-6)
    >>> a["kp"].tolist(), a["model"]["uv"][3:, 0].tolist()
    ([[[0.0, 1.0, 2.0, 3.0]]], [0.5, 0.5, 0.5])
    """
    wl = np.asarray(part["wavelengths"], float)
    nw, nk = len(wl), part["kp"].shape[2]
    m = part["model"]
    scale = reference / wl
    joint = _joint(part)
    model = {"uv": np.vstack([m["uv"] * s for s in scale]),
             "xy": np.vstack([m["xy"] * s for s in scale]),
             "blm": _block_diag([m["blm"]] * nw), "kernel": _block_diag([m["kernel"]] * nw),
             "step": float(m["step"]), "name": m["name"], "rank": int(m["rank"]) * nw}
    band = np.asarray(part["bandwidth"], float)
    rel = np.nanmin(band / wl) if np.any(np.isfinite(band)) else np.nan
    meta = dict(part["meta"])
    meta["notes"] = list(meta.get("notes", [])) + [
        f"{nw} channel(s) {wl.min() * 1e6:.4f}-{wl.max() * 1e6:.4f} um read as one "
        f"achromatic channel at {reference * 1e6:.4f} um (baselines x lambda_0 / lambda)"]
    return {"kp": part["kp"].reshape(1, 1, nw * nk), "wavelengths": np.array([reference]),
            "bandwidth": np.array([rel * reference]),
            "pixscale": float(part["pixscale"]) * reference / wl.min(), "model": model,
            "covariance": joint[None], "joint_covariance": None, "covariance_rows": None,
            "kp_err": part["kp_err"].reshape(1, 1, nw * nk), "header": part["header"],
            "detpa": np.zeros(1), "meta": meta}


def _grids(path):
    """``{INSNAME: (wavelengths, closure-phase values)}`` of the instruments with closure
    phases in a file (values: OI_T3 rows x channels, from the headers)."""
    with open_fits(path) as hdul:          # names truncated and unreadable files
        waves = _wavelengths(hdul, str(path))
        count = {}
        for h in hdul:
            if h.name == "OI_T3":
                ins = _text(h.header.get("INSNAME"))
                count[ins] = count.get(ins, 0) + int(h.header.get("NAXIS2", 0) or 0)
    return {k: (v[0], count[k] * len(v[0])) for k, v in waves.items() if k in count}


#: One instrument of a file "holds the science" when its closure phases outnumber all the
#: others' together this many times (a fringe tracker's few channels beside a spectrograph's
#: hundreds): its channels are then kept and the others left out, with a note, rather than
#: every channel read as one achromatic channel.
SCIENCE_SHARE = 10


def _science(path, grids):
    """The INSNAME that holds the science of a file with several grids, else None."""
    counts = {k: n for k, (_, n) in grids.items()}
    best = max(counts, key=counts.get)
    rest = sum(n for k, n in counts.items() if k != best)
    if counts[best] < SCIENCE_SHARE * rest:
        return None
    left = ", ".join(f"{k!r} ({len(grids[k][0])} channel(s))" for k in counts if k != best)
    warnings.warn(f"{path}: INSNAME {best!r} holds the science ({counts[best]} closure "
                  f"phases, {len(grids[best][0])} channels, kept); {left} left out (read it "
                  f"with insname=...)", KpifsWarning, stacklevel=4)
    return best


def _same(a, b):
    return len(a) == len(b) and np.allclose(a, b, rtol=1e-6)


def read_oifits(paths, *, insname=None, correlations="baselines", binning="auto"):
    """Closure phases of one or several OIFITS files of one target, as one set of parts.

    Parameters
    ----------
    paths : str or list of str
    insname : str, optional
        Read only this INSNAME's tables (its own channels) from every file.
        By default, a file whose instruments have different wavelength grids
        is read by the one that holds the science (`SCIENCE_SHARE`), with its
        channels; otherwise every grid is read and all become one achromatic
        channel.
    correlations : {'baselines', 'independent'}
    binning : {'auto', 'none'}
        See `~kpifs.io.oifits.read_oifits_parts`.

    Returns
    -------
    dict
        As `~kpifs.io.oifits.read_oifits_parts`; ``meta['achromatic']`` is
        True when grids differed and every channel became one.

    Examples
    --------
    >>> import tempfile, numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.io.oifits_combine import read_oifits
    >>> km = KernelModel.from_pupil(make_pupil("niriss_nrm"))
    >>> rng = np.random.default_rng(0)
    >>> files = []
    >>> tmp = tempfile.TemporaryDirectory()
    >>> for i in range(2):
    ...     kpd = KernelPhaseData(rng.normal(0, 0.01, (1, 1, 15)), [4.8] * u.um,
    ...                           65.55 * u.mas, km, covariance=np.eye(15)[None] * 1e-4,
    ...                           detpa=[10.0 * i])
    ...     kpd.meta["calibrated"] = True
    ...     files.append(kpd.write(f"{tmp.name}/e{i}.oifits"))
    >>> parts = read_oifits(files)
    >>> parts["kp"].shape, parts["meta"]["n_reads"]
    ((1, 1, 30), 2)
    >>> tmp.cleanup()
    """
    if isinstance(paths, (str, bytes)) or not hasattr(paths, "__iter__"):
        paths = [paths]
    paths = [str(p) for p in paths]
    reads = []
    for p in paths:
        grids = {} if insname is not None else _grids(p)
        names = list(grids)
        if insname is not None or all(_same(grids[n][0], grids[names[0]][0]) for n in names):
            reads.append(read_oifits_parts(p, insname=insname, correlations=correlations,
                                           binning=binning))
            continue
        best = _science(p, grids)
        reads.extend(read_oifits_parts(p, insname=n, correlations=correlations, binning=binning)
                     for n in ([best] if best is not None else names))
        if best is not None:
            reads[-1]["meta"]["notes"].append(
                f"{p}: INSNAME {best!r} read with its channels; "
                + ", ".join(repr(n) for n in names if n != best) + " left out")
    _check_target(reads)
    if len(reads) == 1:
        return reads[0]
    first = reads[0]["wavelengths"]
    if all(_same(r["wavelengths"], first) for r in reads[1:]):
        out = stack_parts(reads, source=paths[0])
        out["meta"]["achromatic"] = False
        return out
    ref = float(min(r["wavelengths"].min() for r in reads))
    grids = "; ".join(f"{r['meta']['source']} {'/'.join(r['meta']['closure_phases']['insname'])}"
                      f": {len(r['wavelengths'])} channel(s)" for r in reads)
    warnings.warn(f"{', '.join(paths)}: the closure phases are on different wavelength grids "
                  f"({grids}): read as one achromatic channel at {ref * 1e6:.4f} um (one "
                  f"contrast for every wavelength); read one grid with insname=... to keep "
                  f"its channels", KpifsWarning, stacklevel=3)
    out = stack_parts([achromatic_parts(r, ref) for r in reads], source=paths[0])
    out["meta"]["achromatic"] = True
    log.info("%d read(s) on different grids: one achromatic channel at %.4f um, %d kernel "
             "phases", len(reads), ref * 1e6, out["kp"].shape[2])
    return out


def _check_target(reads):
    """Files of different targets (``OBJECT``) are refused, naming them."""
    objs = {}
    for r in reads:
        obj = _text((r["header"] or {}).get("OBJECT"))
        if obj and obj.upper() != "MULTI":
            objs.setdefault(obj, r["meta"]["source"])
    if len(objs) > 1:
        raise KpifsError("OIFITS files of different targets: " + ", ".join(
            f"{src} ({obj})" for obj, src in objs.items()) + ": give one target's files")
