"""kpifs detection products: maps, limits, curves and candidates in one FITS file.

This module knows the layout; `~kpifs.data.DetectionResult` connects it to
astropy's unified I/O registry (``DetectionResult.read(path)``).
"""

import numpy as np
from astropy import units as u
from astropy.io import fits

from .._meta import VERSION
from .._utils import write_hdulist
from ..exceptions import KpifsError
from .cube import open_fits
from ._kpfits_common import card

__all__ = ["field_cards", "field_from_header", "FIELD_CARDS", "detection_hdulist",
           "write_detection", "read_detection_parts", "detection_header_meta"]


#: Header cards of a detection product that record the field: key -> (card, comment).
FIELD_CARDS = {"inner": ("FLDIN", "[mas] smallest separation searched"),
               "outer": ("FLDOUT", "[mas] largest separation searched"),
               "limit": ("FLDLIM", "bound reached: model/window/image/grid"),
               "n_kp": ("FLDNKP", "kernel phases per channel"),
               "n_frames": ("FLDNFR", "frames of the target"),
               "alias": ("FLDALIAS", "[mas] model aliasing, .95 lam_min/(2 step)"),
               "window": ("FLDWIN", "[mas] extraction window radius"),
               "image": ("FLDIMG", "[mas] half the side of the images read"),
               "step": ("FLDSTEP", "[m] grid step of the pupil model"),
               "step_for": ("FLDSTEPR", "[m] grid step that reaches FLDREACH"),
               "reach": ("FLDREACH", "[mas] next bound beyond the model's")}


def field_cards(field, header):
    """Write *field* (`kpifs.model.field.search_field`) as cards of *header*.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.products import field_cards, field_from_header
    >>> f = {"inner": 20.0, "outer": 180.0, "limit": "window", "alias": None,
    ...      "window": 180.0, "image": 300.0, "step": None, "n_kp": 60, "n_frames": 8}
    >>> field_from_header(field_cards(f, fits.Header())) == f
    True
    """
    for key, (name, comment) in FIELD_CARDS.items():
        v = field.get(key)
        if isinstance(v, (int, np.integer)):
            header[name] = (int(v), comment)
        elif v is not None:
            header[name] = (v if isinstance(v, str) else round(float(v), 6), comment)
    return header


def field_from_header(header):
    """The field a product's cards record (`field_cards`), or None.

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.io.products import field_from_header
    >>> field_from_header(fits.Header()) is None                  # no FLD* cards
    True
    >>> field_from_header(fits.Header({"FLDOUT": 180.0, "FLDIN": 20.0}))["outer"]
    180.0
    """
    if "FLDOUT" not in header:
        return None
    out = {key: header.get(name) for key, (name, _) in FIELD_CARDS.items()}
    keep = ("alias", "window", "image", "step", "n_frames")
    return {k: v for k, v in out.items() if v is not None or k in keep}


def _image(data, name, wcs_header, bunit=None, comment=None):
    hdu = fits.ImageHDU(np.asarray(data, np.float64), header=wcs_header.copy(), name=name)
    if bunit:
        hdu.header["BUNIT"] = bunit
    if comment:
        hdu.header["COMMENT"] = comment
    return hdu


def _report_cards(result, hdr, inputs):
    """The cards of the search's report (test, probabilities, null, energy test, noise
    scale, grid, channels, spectrum, calibrators, inputs), written into *hdr*;
    `detection_header_meta` reads them back."""
    hdr["TEST"] = (result.test, "detection test (kpifs.detect.statistics)")
    hdr["MAPTEST"] = (result.meta.get("map_test", result.test), "test of the DETECTION map")
    hdr["PFA"] = (result.pfa, "global false-alarm probability of the search")
    hdr["PD"] = (result.pd, "detection probability of the limits")
    hdr["THRESH"] = (result.threshold, "threshold of the map statistic at PFA")
    hdr["NDRAWS"] = (result.meta.get("n_draws", 0), "Monte-Carlo draws calibrating the search")
    hdr["MCSEED"] = (result.meta.get("seed", 0), "seed of those draws")
    hdr["PFAFLOOR"] = (10 / (result.meta.get("n_draws", 0) + 1),
                       "smaller P_FA: from the null's fitted tail")
    hdr["NCAND"] = (len(result.candidates), "candidates above the threshold")
    hdr["ESTAT"] = (result.energy.get("statistic", np.nan),
                    "energy statistic / NOISESC (as tested)")
    if result.energy.get("raw") is not None:
        hdr["ERAW"] = (result.energy["raw"], "whitened energy, frames' model alone")
    if result.energy.get("map_noise") is not None:
        hdr["MAPNOISE"] = (round(float(result.energy["map_noise"]), 6),
                           "mean square of the residual map")
    if result.energy.get("map_expectation") is not None:
        hdr["MAPEXPCT"] = (round(float(result.energy["map_expectation"]), 6),
                           "MAPNOISE expected from the null's rows")
    if result.energy.get("subspace_noise") is not None:
        hdr["SUBNOISE"] = (round(float(result.energy["subspace_noise"]), 6),
                           "same, of the spectral-model test's map")
    hdr["EDOF"] = (result.energy.get("dof", 0), "energy-detector degrees of freedom")
    hdr["EPFA"] = (result.energy.get("pfa", np.nan), "energy-detector P_FA of the data")
    hdr["ETHRESH"] = (result.energy.get("threshold", np.nan),
                      "energy-detector threshold at PFA")
    _channel_cards(result, hdr, inputs)


def _channel_cards(result, hdr, inputs):
    """The grid's, channels', null's, noise's and provenance cards of `_report_cards`."""
    hdr["GRIDFRM"] = (result.grid.frame, "maps on the sky (dRA, dDec) or the detector")
    hdr["GRIDMIN"] = (float(result.grid.min_sep), "[mas] smallest separation searched")
    hdr["GRIDMAX"] = (float(result.grid.max_sep) if np.isfinite(result.grid.max_sep) else -1.0,
                      "[mas] largest separation searched (-1: none)")
    for i, w in enumerate(result.wavelengths.to_value("um"), 1):
        hdr[f"WAVE{i}"] = (float(w), f"[um] wavelength of channel {i}")
    for i, f in enumerate(result.meta.get("aliased") or [], 1):
        if any(result.meta["aliased"]):
            hdr[f"ALIAS{i}"] = (round(float(f), 4), f"uv points aliased in channel {i} (fraction)")
    if result.meta.get("field"):
        field_cards(result.meta["field"], hdr)
    st = result.meta.get("static")
    if st:
        hdr["STATSHR"] = (round(float(st["share"]), 6), "static residual / frames' variance")
        hdr["STATAMP"] = (float(st["amplitude"]), "static residual amplitude (ML fit)")
        hdr["STATPUP"] = (str(st["pupil"]), "pupil the static residual was imaged through")
    sdk = result.meta.get("blocks") or {}
    if sdk.get("spectral"):                                # ASDI: the blocks' combinations
        hdr["SDKBLOCK"] = (True, "combinations searched by time blocks (ASDI)")
        sdk = sdk["spectral"]
    if sdk.get("profiles") is not None:                   # issue 39
        hdr["SDKBASIS"] = (str(sdk.get("basis")), "spectral-differential profiles")
        hdr["SDKNPROF"] = (int(sdk["profiles"]), "profiles projected out")
        hdr["SDKNCOMB"] = (int(sdk["combinations"]), "channel combinations searched")
        inner = sdk.get("inner_separation")
        hdr["SDKINNER"] = (round(float(inner), 3) if inner is not None and np.isfinite(inner)
                           else -1.0, "[mas] half kept from (-1: never)")
        for i, a in enumerate(sdk.get("static_amplitudes") or (), 1):
            hdr[f"SDKSTA{i}"] = (float(a), f"static term's amplitude, group {i} (ML fit)")
    chans = result.meta.get("channels") or []
    if result.meta.get("excluded_channels"):
        hdr["EXCLCHAN"] = (",".join(map(str, result.meta["excluded_channels"])),
                           "input channels left out (aliased)")
        for i, n in enumerate(chans, 1):
            hdr[f"CHAN{i}"] = (int(n), f"input channel of channel {i}")
    for i, a in enumerate(result.meta.get("spectrum", []), 1):
        hdr[f"SPEC{i}"] = (float(a), "companion spectrum shape used for limits")
    hdr["NULLCHAN"] = (result.meta.get("null_channels", "independent"),
                       "channel model: null, B/E limits")
    nul = result.meta.get("null") or {}
    if nul:
        hdr["NULLMETH"] = (nul["method"], "null of the grid maximum (THRESH: the larger)")
        for key, (name, comment) in NULL_CARDS.items():
            if nul.get(key) is not None:
                v = nul[key]
                hdr[name] = (round(float(v), 6) if isinstance(v, float) else int(v),
                             ("threshold at PFA: " if name.startswith("THR") else "") + comment)
    if result.meta.get("chi2_red") is not None:
        hdr["CHI2RED"] = (round(float(result.meta["chi2_red"]), 6),
                          "reduced chi2 of the whitened residual")
        hdr["NOISESC"] = (round(float(result.meta.get("noise_scale", 1.0)), 6),
                          "variance scale of every test (energy and map)")
    cals = result.meta.get("calibrators", [])
    hdr["CALIB"] = (len(cals) > 0, "calibrated with a calibrator star")
    for i, c in enumerate(cals, 1):
        hdr[f"KPCAL{i}"] = card(c, "calibrator")
    for i, name in enumerate(inputs, 1):
        hdr[f"KPIN{i}"] = card(name, "input file")
    hdr.add_history(f"kpifs {VERSION}: {result.test} search, P_FA {result.pfa:g}, "
                    f"P_D {result.pd:g}, {len(result.candidates)} candidate(s)")
    if "detpa" in result.candidates.meta:
        hdr["DETPA"] = (float(result.candidates.meta["detpa"]),
                        "[deg] detector +y position angle, East of North")


def detection_hdulist(result, *, header=None, inputs=()):
    """Build the products of a `~kpifs.data.DetectionResult` as an HDUList.

    *header* (default ``result.header``): the searched data's header, whose
    cards the primary header keeps.

    Examples
    --------
    >>> from kpifs.detect.pipeline import _example_result
    >>> from kpifs.io.products import detection_hdulist
    >>> hdul = detection_hdulist(_example_result())
    >>> hdul[0].header["CONTENT"], "CANDIDATES" in hdul
    ('KPIFS-DETECTION', True)
    """
    header = result.header if header is None else header
    hdr = fits.Header() if header is None else _strip(header)
    hdr["KPIFSVER"] = (VERSION, "kpifs version")
    hdr["CONTENT"] = ("KPIFS-DETECTION", "kpifs detection products")
    _report_cards(result, hdr, inputs)
    wcs_hdr = result.grid.wcs().to_header()
    q = len(result.wavelengths)
    wcs3 = wcs_hdr.copy()
    wcs3["CTYPE3"], wcs3["CUNIT3"] = "CHANNEL", ""
    wcs3["CRPIX3"], wcs3["CRVAL3"], wcs3["CDELT3"] = 1.0, 1.0, 1.0
    hdus = [fits.PrimaryHDU(header=hdr),
            _image(result.statistic, "DETECTION", wcs_hdr, comment="local map statistic"),
            _image(result.pfa_global, "PFA", wcs_hdr, comment="global false-alarm probability"),
            _image(result.pfa_local, "PFA_LOCAL", wcs_hdr,
                   comment="false-alarm probability at a known position"),
            *([] if result.search_map is None else [
                _image(result.search_map, "SEARCH", wcs_hdr,
                       comment="residual map the search stopped on")]),
            _image(result.contrast, "CONTRAST", wcs3, comment=f"{q} channels"),
            _image(result.contrast_err, "CONTRAST_ERR", wcs3, comment="1-sigma"),
            *([] if result.limit is None else [
                _image(result.limit, "LIMIT", wcs_hdr,
                       comment=f"{result.test} limit at P_FA {result.pfa:g}, P_D {result.pd:g}")])]
    for name, lim in result.limits.items():
        hdu = _image(lim, f"LIMIT_{name.upper().replace('-', '_')}", wcs_hdr)
        hdu.header["LIMTEST"] = (name, "test of this limit map")
        hdus.append(hdu)
    curves = fits.table_to_hdu(result.curves)
    curves.name = "CURVES"
    hdus.append(curves)
    cand = result.candidates.copy()
    cand.meta = {"TEST": result.test, "THRESH": float(result.threshold)}
    if "detpa" in result.candidates.meta:
        cand.meta["DETPA"] = float(result.candidates.meta["detpa"])
    ch = fits.table_to_hdu(cand)
    ch.name = "CANDIDATES"
    hdus.append(ch)
    return fits.HDUList(hdus)


#: ``result.meta['null']`` entries written as cards: key -> (card, comment).
NULL_CARDS = {"threshold_gaussian": ("THRGAUS", "Gaussian Monte-Carlo"),
              "threshold_empirical": ("THREMP", "sign flips of time blocks"),
              "n_blocks": ("NBLOCKS", "time blocks of the stars' frames"),
              "empirical_draws": ("NEMPDRAW", "sign-flip draws")}

# cards the products write themselves: an inherited copy is dropped, so that the
# products' own cards come in one order however often a result is written
_PRODUCT_CARDS = {"KPIFSVER", "CONTENT", "TEST", "MAPTEST", "PFA", "PD", "THRESH", "NDRAWS",
                  "PFAFLOOR", "MCSEED", "NCAND", "ESTAT", "EDOF", "EPFA", "ETHRESH", "GRIDFRM",
                  "ERAW", "MAPNOISE", "MAPEXPCT", "SUBNOISE", "EXCLCHAN", "STATSHR", "STATAMP",
                  "STATPUP", "GRIDMIN", "GRIDMAX",
                  "NULLCHAN", "CALIB", "CHI2RED", "NOISESC", "DETPA", "NULLMETH",
                  *(name for name, _ in NULL_CARDS.values()),
                  *(name for name, _ in FIELD_CARDS.values())}
_PRODUCT_PREFIXES = ("WAVE", "SPEC", "KPCAL", "KPIN", "ALIAS", "CHAN", "SDKSTA")


def _strip(header):
    out = fits.Header()
    skip = {"SIMPLE", "BITPIX", "EXTEND", "CHECKSUM", "DATASUM", "PCOUNT", "GCOUNT",
            "XTENSION", "END"} | _PRODUCT_CARDS
    for c in header.cards:
        key = c.keyword
        if key in skip or key.startswith("NAXIS") or any(
                key.startswith(p) and key[len(p):].isdigit() for p in _PRODUCT_PREFIXES):
            continue
        try:
            out.append(c)
        except (ValueError, fits.VerifyError):
            pass
    return out


def write_detection(result, path, *, header=None, inputs=(), overwrite=False):
    """Write detection products atomically (never over an input).

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.detect.pipeline import _example_result
    >>> from kpifs.io.products import write_detection
    >>> tmp = tempfile.TemporaryDirectory()
    >>> write_detection(_example_result(), tmp.name + "/det.fits").name
    'det.fits'
    >>> tmp.cleanup()
    """
    return write_hdulist(detection_hdulist(result, header=header, inputs=inputs), path,
                         overwrite=overwrite, inputs=inputs)


def is_detection(origin, path, fileobj, *args, **kwargs):
    """Identifier for astropy's I/O registry: a FITS file with CONTENT = 'KPIFS-DETECTION'."""
    target = path if path is not None else fileobj
    if target is None:
        return False
    try:
        with fits.open(target) as hdul:
            return hdul[0].header.get("CONTENT") == "KPIFS-DETECTION"
    except Exception:  # anything unreadable is simply not this format
        return False


def read_detection_parts(path):
    """Read detection products: ``header``, ``images`` (by extension name),
    ``limits`` (by test name) and ``tables`` (CURVES, CANDIDATES as QTable).

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.detect.pipeline import _example_result
    >>> from kpifs.io.products import read_detection_parts, write_detection
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = write_detection(_example_result(), tmp.name + "/det.fits")
    >>> parts = read_detection_parts(path)
    >>> parts["header"]["TEST"], parts["images"]["DETECTION"].ndim, sorted(parts["limits"])
    ('B', 2, ['B', 'B-paper', 'E', 'NP', 'S'])
    >>> tmp.cleanup()
    """
    path = str(path)
    from astropy.table import QTable     # not at import: the command line's start
    out = {"images": {}, "limits": {}, "tables": {}}
    try:
        with open_fits(path, verify=True) as hdul:
            out["header"] = hdul[0].header.copy()
            if out["header"].get("CONTENT") != "KPIFS-DETECTION":
                raise KpifsError(f"{path}: not kpifs detection products (CONTENT is not "
                                 f"'KPIFS-DETECTION')")
            for h in hdul[1:]:
                if isinstance(h, fits.BinTableHDU):
                    out["tables"][h.name] = QTable.read(h)
                elif "LIMTEST" in h.header:
                    out["limits"][h.header["LIMTEST"]] = np.array(h.data)
                else:
                    out["images"][h.name] = np.array(h.data)
                    if h.name == "DETECTION":
                        out["grid_header"] = h.header.copy()
    except (OSError, ValueError, TypeError) as exc:
        if isinstance(exc, KpifsError):
            raise
        raise KpifsError(f"{path}: cannot read detection products: {exc}") from None
    return out


def detection_header_meta(hdr, path):
    """``(wavelengths, energy, meta)`` of a detection product from its primary header
    *hdr*: the reverse of the cards `detection_hdulist` writes.

    Examples
    --------
    >>> import tempfile
    >>> from astropy.io import fits
    >>> from kpifs.detect.pipeline import _example_result
    >>> from kpifs.io.products import detection_header_meta, write_detection
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = write_detection(_example_result(), tmp.name + "/det.fits")
    >>> wl, energy, meta = detection_header_meta(fits.getheader(path), path)
    >>> len(wl), meta["test"], meta["channels"]
    (2, 'B', [1, 2])
    >>> tmp.cleanup()
    """
    nwave = sum(1 for k in hdr if k.startswith("WAVE") and k[4:].isdigit())
    wl = [hdr[f"WAVE{i}"] for i in range(1, nwave + 1)] * u.um
    energy = {"statistic": hdr["ESTAT"], "dof": hdr["EDOF"], "pfa": hdr["EPFA"],
              "threshold": hdr.get("ETHRESH", np.nan), "pd": hdr["PD"]}
    for key, name in (("raw", "ERAW"), ("map_noise", "MAPNOISE"), ("noise_scale", "NOISESC"),
                      ("subspace_noise", "SUBNOISE"), ("map_expectation", "MAPEXPCT")):
        if name in hdr:
            energy[key] = hdr[name]
    meta = {"test": hdr["TEST"], "map_test": hdr.get("MAPTEST", hdr["TEST"]), "pfa": hdr["PFA"],
            "pd": hdr["PD"], "n_draws": hdr["NDRAWS"], "frame": hdr.get("GRIDFRM"),
            "seed": hdr["MCSEED"], "null_channels": hdr["NULLCHAN"],
            "calibrators": [hdr[k] for k in hdr if k.startswith("KPCAL") and k[5:].isdigit()],
            "spectrum": [hdr[f"SPEC{i}"] for i in range(1, nwave + 1) if f"SPEC{i}" in hdr],
            "aliased": [hdr.get(f"ALIAS{i}", 0.0) for i in range(1, nwave + 1)],
            "channels": [hdr.get(f"CHAN{i}", i) for i in range(1, nwave + 1)],
            "excluded_channels": [int(v) for v in str(hdr.get("EXCLCHAN", "")).split(",") if v],
            "source": str(path)}
    if "CHI2RED" in hdr:
        meta.update(chi2_red=hdr["CHI2RED"], noise_scale=hdr.get("NOISESC", 1.0))
    if field_from_header(hdr):
        meta["field"] = field_from_header(hdr)
    if "SDKNPROF" in hdr:
        sdk = {"basis": hdr.get("SDKBASIS"), "profiles": hdr["SDKNPROF"],
               "combinations": hdr.get("SDKNCOMB"), "inner_separation": hdr.get("SDKINNER", -1.0)}
        amps = []
        while f"SDKSTA{len(amps) + 1}" in hdr:
            amps.append(float(hdr[f"SDKSTA{len(amps) + 1}"]))
        if amps:
            sdk["static_amplitudes"] = amps
        meta["blocks"] = ({"mode": "angular-differential", "spectral": sdk}
                          if hdr.get("SDKBLOCK") else dict(mode="spectral-differential", **sdk))
    if "STATSHR" in hdr:
        meta["static"] = {"share": hdr["STATSHR"], "amplitude": hdr.get("STATAMP"),
                          "pupil": hdr.get("STATPUP")}
    if "NULLMETH" in hdr:
        meta["null"] = {"method": hdr["NULLMETH"], "threshold": hdr["THRESH"],
                        **{key: hdr[name] for key, (name, _) in NULL_CARDS.items()
                           if name in hdr}}
    return wl, energy, meta
