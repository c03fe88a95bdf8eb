"""JWST filters of one target as the channels of one calibrated product.

Each filter has its own wavelength, pixel scale and sampling limit, and its
own integrations (exposures in different filters are neither simultaneous
nor equally many). Each filter keeps **its own kernel**: the kernel of the uv
points it samples (``|b| <= lambda / (2 pixscale)``). Those sets are nested,
so one kernel serves all (`~kpifs.sampling.nested_kernel`, DESIGN.md section 6):
its first rows are the kernel of the filter that samples least, the next ones
complete it to the next filter's, and so on. A filter measures its first
``n`` kernel phases (``meta['channel_n_kp']``, cards ``NKPCH<i>``); its other
rows are zero with zero covariance, and the whitening leaves them out, so
every test, limit and fit sees each filter's own kernel phases only.

- Each filter is extracted with its own model and a window of the same
  *angular* radius (its pixel radius scaled by the pixel scales), then
  calibrated by the same filter's calibrator frames (`~kpifs.workflow`).
- The product carries the finest pixel scale and that filter's window: the
  window's attenuation of a companion, a function of angle, is then right in
  every channel, and its gain is computed on a grid where every filter's PSF
  is sampled.
- The filters are independent: covariances block-diagonal across channels
  (the error-model rows of each filter are zero in the others').
- Refused: one filter without calibrator frames, files of different targets,
  filters observed at different detector angles (field rotation between
  filters needs blocks), and a filter with no kernel phase.

``filter_kernels='common'`` (``--filter-kernels common``) gives every filter
the kernel of the uv points they all sample instead. With few frames that
can go deeper: the error model keeps the leading modes of the frames'
scatter, and the long baselines, near the pupil's edge, add noisy ones (see
docs/user/jwst.rst for the measured depths).
"""
import logging
from dataclasses import replace

import numpy as np
from astropy import units as u
from astropy.io import fits

from .data import KernelPhaseData
from .exceptions import KpifsError
from .io.jwst import JWST_FILTERS, JWST_PIXSCALES, jwst_mode
from .kernel import KernelModel, nyquist_usable
from .sampling import nested_kernel
from .window import DEFAULT_WINDOW_RADIUS, ExtractionWindow
from .workflow import calibrate_observation, extract_observation, kernel_model_for

__all__ = ["jwst_filters", "extract_filters", "stack_filters"]

log = logging.getLogger(__name__)

#: Detector angles (deg) of the filters that still count as one.
MAX_ANGLE_DIFFERENCE = 0.5


def jwst_filters(paths):
    """``{filter: [files]}`` of JWST stage-2 files (empty for other files).

    Examples
    --------
    >>> from kpifs.filters import jwst_filters
    >>> jwst_filters([])
    {}
    """
    out = {}
    for p in paths:
        try:
            hdr = fits.getheader(p)
        except (OSError, ValueError):          # the reader names unreadable files
            return {}
        if str(hdr.get("TELESCOP", "")).strip().upper() != "JWST":
            return {}
        out.setdefault(jwst_mode(hdr, source=str(p))[1], []).append(str(p))
    return out


def _scale(path):
    hdr = fits.getheader(path)
    inst, filt, _ = jwst_mode(hdr, source=path)
    chan = str(hdr.get("CHANNEL", "")).strip().upper() if inst == "NIRCAM" else None
    wl, _ = JWST_FILTERS[(inst, filt)]
    return wl, JWST_PIXSCALES.get((inst, chan)), fits.getval(path, "NAXIS1", "SCI")


def extract_filters(targets, calibrators, options, *, progress=False):
    """Target and calibrator files in several JWST filters as one calibrated product.

    Parameters
    ----------
    targets : list of str
        The target's files, in two or more filters.
    calibrators : list of list of str
        Each calibrator star's files (in the same filters).
    options : `~kpifs.workflow.ExtractOptions`

    Returns
    -------
    `~kpifs.data.KernelPhaseData`
        One frame, one channel per filter (by wavelength), calibrated.

    Examples
    --------
    >>> import tempfile, warnings, astropy.units as u
    >>> from kpifs.filters import extract_filters
    >>> from kpifs.io import write_observation
    >>> from kpifs.simulate import simulate_scene
    >>> from kpifs.workflow import ExtractOptions
    >>> tmp = tempfile.TemporaryDirectory()
    >>> d, files = tmp.name, {"t": [], "c": []}
    >>> for wl, ps in ((1.5106, 31.0), (4.8213, 63.0)):
    ...     obs = simulate_scene("nircam", wavelengths=[wl] * u.um, pixscale=ps * u.mas,
    ...                          n_frames=6, npup=32, shape=(32, 32), seed=int(ps))
    ...     f = write_observation(obs, f"{d}/{ps}", layout="jwst")
    ...     files["t"] += f["target"]
    ...     files["c"] += f["calibrator"]
    >>> with warnings.catch_warnings():
    ...     warnings.simplefilter("ignore")
    ...     kpd = extract_filters(files["t"], [files["c"]], ExtractOptions(pupil="niriss_nrm"))
    >>> kpd.n_wave, kpd.meta["filters"]
    (2, ['F150W', 'F480M'])
    >>> tmp.cleanup()
    """
    groups = jwst_filters(targets)
    if len(groups) < 2:
        raise KpifsError(f"{targets[0] if targets else 'no files'}: filters as channels need "
                         f"JWST files in two filters or more")
    names = {str(p): str(fits.getval(p, "TARGNAME", default="") or "").strip() for p in targets}
    if len(set(names.values())) > 1:
        raise KpifsError("files of different targets: " + ", ".join(
            f"{p} ({t or '?'})" for p, t in names.items()) + ": give the calibrator with "
            "--calibrator")
    if not calibrators:
        raise KpifsError("files in different filters: " + ", ".join(
            f"{p} ({f})" for f, files in groups.items() for p in files) + ": their frames "
            "differ from filter to filter, so they become the channels of one product only "
            "once calibrated: give each filter's calibrator files with --calibrator")
    cal_groups = [jwst_filters(c) for c in calibrators]
    for star, cg in zip(calibrators, cal_groups):
        missing = [f for f in groups if f not in cg]
        if missing:
            raise KpifsError(f"calibrator {star[0]}: no files in filter(s) "
                             f"{', '.join(missing)} of the target")
    scales = {f: _scale(files[0]) for f, files in groups.items()}
    order = sorted(groups, key=lambda f: scales[f][0])
    first = groups[order[0]][0]
    km = kernel_model_for(options, "jwst", fits.getheader(first))
    usable = np.array([nyquist_usable(km.uv, [scales[f][0]] * u.um, scales[f][1] * u.mas)[0]
                       for f in order])
    for f, m in zip(order, usable):
        if m.sum() < 2:
            raise KpifsError(f"{groups[f][0]}: filter {f}: {int(m.sum())} of {km.n_uv} uv "
                             f"points within its sampling limit "
                             f"({_limit(scales[f]):.2f} m at {scales[f][1]:g} mas pixels): "
                             f"no kernel phase")
    if options.filter_kernels not in ("own", "common"):
        raise KpifsError(f"filter kernels must be 'own' or 'common', got "
                         f"{options.filter_kernels!r}")
    if options.filter_kernels == "common":      # every filter the uv points all sample
        usable = np.broadcast_to(usable.all(axis=0), usable.shape)
    model, counts = nested_kernel(km, usable)
    for f, m, n in zip(order, usable, counts):
        if n == 0:
            raise KpifsError(f"{groups[f][0]}: filter {f}: the {int(m.sum())} uv points "
                             f"within its sampling limit ({_limit(scales[f]):.2f} m at "
                             f"{scales[f][1]:g} mas pixels) give no kernel phase")
    log.info("filters %s: %s kernel phases (each its own uv points, of %d)", ", ".join(order),
             ", ".join(map(str, counts)), model.n_uv)
    own = {f: _channel_model(model, n, m[usable.any(axis=0)])
           for f, m, n in zip(order, usable, counts)}
    # windows of one angular radius: the default radius of the finest sampled filter
    radius_mas = min(DEFAULT_WINDOW_RADIUS * min(scales[f][2], 64) / 2 * scales[f][1]
                     for f in order) if options.window_radius is None else None
    products = []
    for f in order:
        opts = _with_window(options, radius_mas, scales[f][1])
        t = extract_observation(groups[f], opts, model=own[f], progress=progress)
        cals = [extract_observation(cg[f], opts, model=own[f], progress=progress)
                for cg in cal_groups]
        products.append(calibrate_observation(t, cals, opts))
    return stack_filters(products, order, kernel_model=model)


def _limit(scale):
    """A filter's sampling limit (m): the longest baseline it samples."""
    wl_um, pix_mas = scale[0], scale[1]
    return wl_um * 1e-6 / (2 * pix_mas * np.pi / 180 / 3600e3)


def _channel_model(model, n, mask):
    """One filter's own model: its uv points and the nested kernel's first *n* rows."""
    meta = {k: v for k, v in model.meta.items() if k != "nested_counts"}
    return KernelModel(model.pupil, model.uv[mask], model.redundancy[mask], model.blm[mask],
                       kernel=model.kernel[:n][:, mask], meta=meta)


def _with_window(options, radius_mas, pixscale):
    if radius_mas is None:
        return options
    return replace(options, window_radius=radius_mas / pixscale)


def stack_filters(products, names, *, kernel_model=None):
    """Calibrated one-filter products as the channels of one.

    Parameters
    ----------
    products : list of `~kpifs.data.KernelPhaseData`
        One calibrated frame per filter.
    names : list of str
        The filters' names.
    kernel_model : `~kpifs.kernel.KernelModel`, optional
        The nested kernel (`~kpifs.sampling.nested_kernel`) when the filters have
        their own: each product's kernel must be its first rows on the product's
        uv points. Default: the products share one kernel.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.filters import stack_filters
    >>> km = KernelModel.from_pupil(make_pupil("niriss_nrm"))
    >>> one = [KernelPhaseData(np.zeros((1, 1, 15)), [w] * u.um, ps * u.mas, km,
    ...                        covariance=np.eye(15)[None], covariance_rows=np.eye(15)[:, None],
    ...                        meta={"calibrated": True}) for w, ps in ((1.5, 31), (4.8, 63))]
    >>> kpd = stack_filters(one, ["F150W", "F480M"])
    >>> kpd.shape, kpd.covariance_rows.shape, kpd.pixscale
    ((1, 2, 15), (30, 2, 15), <Quantity 31. mas>)
    """
    km = products[0].kernel_model if kernel_model is None else kernel_model
    counts = []
    for p, name in zip(products, names):
        if p.n_frame != 1 or not p.meta.get("calibrated"):
            raise KpifsError(f"{p.name}: filter {name} is not one calibrated frame")
        if not _first_rows(km, p.kernel_model):
            raise KpifsError(f"{p.name}: filter {name} has another kernel model")
        counts.append(p.n_kp)
    pas = [None if p.detpa is None else float(p.detpa[0]) for p in products]
    known = [a for a in pas if a is not None and np.isfinite(a)]
    if known and (len(known) < len(pas) or np.ptp(np.unwrap(np.deg2rad(known))) * 180 / np.pi
                  > MAX_ANGLE_DIFFERENCE):
        raise KpifsError("filters at different detector angles (" + ", ".join(
            f"{n} {a} deg in {p.name}" for n, a, p in zip(names, pas, products))
            + "): one product needs one angle (field rotation between filters needs "
            "blocks: DESIGN.md 6)")
    nk, nf = km.n_kp, len(products)
    # a filter's rows beyond its own kernel phases: zero data, zero covariance
    kp = np.zeros((1, nf, nk))
    cov = np.zeros((nf, nk, nk))
    for j, (p, n) in enumerate(zip(products, counts)):
        kp[:, j, :n] = p.kp[:, 0]
        cov[j, :n, :n] = p.covariance[0]

    def rows(attr):
        parts = [getattr(p, attr) for p in products]
        if any(r is None for r in parts):
            return None
        out = np.zeros((sum(len(r) for r in parts), nf, nk))
        i = 0
        for j, (r, n) in enumerate(zip(parts, counts)):
            out[i:i + len(r), j, :n] = r[:, 0]
            i += len(r)
        return out

    # the finest sampling: the window's gain is computed on its pixel grid, where every
    # filter's PSF is sampled (on a coarser grid the shortest filter's would alias)
    base = products[int(np.argmin([p.pixscale.to_value(u.mas) for p in products]))]
    meta = dict(products[0].meta)
    meta["filters"] = list(names)
    meta["filter_error_models"] = {n: p.meta.get("error_model") for n, p in zip(names, products)}
    meta["filter_pixscales"] = {n: float(p.pixscale.to_value(u.mas))
                                for n, p in zip(names, products)}
    meta["source"] = ", ".join(p.name for p in products)
    if any(n != nk for n in counts):
        meta["channel_n_kp"] = counts
    header = products[0].header.copy()
    header["KPFILTER"] = ("+".join(names), "filters as channels")
    bw = [p.bandwidth for p in products]
    band = (None if any(b is None for b in bw)
            else np.concatenate([u.Quantity(b, u.um).value for b in bw]) * u.um)
    window = base.window if base.window is None else ExtractionWindow(
        base.window.size, base.window.radius, base.window.order)
    out = KernelPhaseData(kp, np.concatenate([p.wavelengths.to_value(u.um) for p in products])
                          * u.um, base.pixscale, km, window=window, covariance=cov,
                          covariance_rows=rows("covariance_rows"),
                          fit_covariance_rows=rows("fit_covariance_rows"),
                          block_rows=rows("block_rows"), header=header,
                          detpa=None if not known else [known[0]], bandwidth=band, meta=meta)
    log.info("filters %s as %d channels of %s kernel phases", "+".join(names), nf,
             "/".join(map(str, counts)))
    return out


def _first_rows(model, own):
    """Whether *own*'s kernel is *model*'s first rows on *own*'s uv points (and those rows
    touch no other uv point)."""
    if own is model:
        return True
    n = own.n_kp
    if n > model.n_kp or own.n_uv > model.n_uv:
        return False
    uv, sub = model.uv.to_value(u.m), own.uv.to_value(u.m)
    d = np.hypot(*(uv[None, :, :] - sub[:, None, :]).transpose(2, 0, 1))
    idx = np.argmin(d, axis=1)
    if np.any(d[np.arange(len(idx)), idx] > 1e-9) or len(set(idx.tolist())) != len(idx):
        return False
    k = model.kernel[:n]
    rest = np.delete(k, idx, axis=1)
    return bool(np.allclose(k[:, idx], own.kernel, atol=1e-8)
                and (rest.size == 0 or np.abs(rest).max() < 1e-8))
