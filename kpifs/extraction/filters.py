"""JWST filters of one target as the channels of one calibrated product.

Each filter has its own wavelength, pixel scale and sampling limit, and its
own integrations (exposures in different filters are neither simultaneous
nor equally many). Each filter keeps **its own kernel**: the kernel of the uv
points it samples (``|b| <= lambda / (2 pixscale)``). Those sets are nested,
so one kernel serves all (`~kpifs.model.sampling.nested_kernel`, DESIGN.md section 6):
its first rows are the kernel of the filter that samples least, the next ones
complete it to the next filter's, and so on. A filter measures its first
``n`` kernel phases (``meta['channel_n_kp']``, cards ``NKPCH<i>``); its other
rows are zero with zero covariance, and the whitening leaves them out, so
every test, limit and fit sees each filter's own kernel phases only.

- Each filter is extracted with its own model and a window of the same
  *angular* radius (its pixel radius scaled by the pixel scales), then
  calibrated by the same filter's calibrator frames: the driver,
  `kpifs.workflow.extract_filters`, runs those steps with the pieces here
  (`filter_groups`, `filter_models`, `filter_window_radius`, `stack_filters`),
  which import nothing of the driver's.
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
import warnings
from dataclasses import replace

import numpy as np
from astropy import units as u
from astropy.io import fits

from ..data import KernelPhaseData
from .._utils import to_quantity
from ..exceptions import KpifsError, KpifsWarning
from ..io.cube import open_fits
from ..io.jwst import INSTRUMENT     # the instrument whose filters these are
from ..io.jwst import JWST_FILTERS, is_jwst_header, jwst_mode, own_pixscale, pixscale_fits
from ..model.kernel import KernelModel, nyquist_usable
from ..model.sampling import nested_kernel
from ..model.window import DEFAULT_WINDOW_RADIUS, ExtractionWindow

__all__ = ["jwst_filters", "filter_groups", "filter_models", "filter_window_radius",
           "stack_filters", "INSTRUMENT"]

log = logging.getLogger(__name__)

#: Detector angles (deg) of the filters that still count as one.
MAX_ANGLE_DIFFERENCE = 0.5


def jwst_filters(paths):
    """``{filter: [files]}`` of JWST stage-2 files (empty for other files).

    Examples
    --------
    >>> from kpifs.extraction.filters import jwst_filters
    >>> jwst_filters([])
    {}
    """
    out = {}
    for p in paths:
        try:
            hdr = file_headers(p)[0]
        except KpifsError:                     # the reader names unreadable files
            return {}
        if not is_jwst_header(hdr):
            return {}
        out.setdefault(jwst_mode(hdr, source=str(p))[1], []).append(str(p))
    return out


def file_headers(path):
    """The primary and ``SCI`` headers of a file, read as the readers do (cards astropy
    cannot parse fixed silently, the readers then name what is wrong)."""
    with open_fits(path) as hdul:
        return (hdul[0].header.copy(),
                hdul["SCI"].header.copy() if "SCI" in hdul else fits.Header())


def _scale(path, given):
    """A filter's mean wavelength (um), pixel scale (mas: *given* where it fits the file's
    own, `kpifs.io.jwst.pixscale_fits`), image width, whether *given* fits and the file's
    own scale."""
    hdr, sci = file_headers(path)
    inst, filt, _ = jwst_mode(hdr, source=path)
    wl, _ = JWST_FILTERS[(inst, filt)]
    own = own_pixscale(hdr, sci, source=path)
    fit = given is not None and pixscale_fits(given, own)
    return wl, (given if fit else own[0]), sci["NAXIS1"], fit, own[0]


def filter_options(options, groups, order, scales):
    """Each filter's options: a pixel scale given is kept where it fits the filter's own,
    with a note for the filters it does not fit; refused when it fits none.

    ``order``, ``groups`` and ``scales`` come from `filter_groups` (called with
    the same pixel scale).
    """
    if options.pixscale is None:
        return {f: options for f in order}
    given = to_quantity(options.pixscale, u.mas, name="pixel scale").value
    fit = [f for f in order if scales[f][3]]
    own = ", ".join(f"{f} {scales[f][4]:g} mas ({groups[f][0]})" for f in order
                    if not scales[f][3])
    if not fit:
        raise KpifsError(f"the pixel scale given ({given:g} mas) fits none of the filters' own "
                         f"({own}): give one that does, or none")
    if len(fit) < len(order):
        warnings.warn(f"the pixel scale given ({given:g} mas) is applied to {', '.join(fit)} "
                      f"only: it contradicts the own scale of {own}, which is kept",
                      KpifsWarning, stacklevel=3)
    return {f: options if scales[f][3] else replace(options, pixscale=None) for f in order}


def filter_groups(targets, calibrators, *, pixscale=None):
    """The filters of a target's JWST files, their files and facts, after the refusals.

    Returns ``(order, groups, cal_groups, scales)``: the filters by wavelength,
    ``{filter: [target files]}``, one such dict per calibrator star, and
    ``{filter: (wavelength um, pixel scale mas, image side px, whether *pixscale*
    fits the file's own, the file's own scale mas)}``. Refused:
    fewer than two filters, files of different targets, no calibrator, and a
    calibrator without one of the target's filters.

    Examples
    --------
    >>> from kpifs.extraction.filters import filter_groups
    >>> from kpifs.exceptions import KpifsError
    >>> try:
    ...     filter_groups([], [])
    ... except KpifsError as err:
    ...     print(err)                                       # doctest: +ELLIPSIS
    no files: filters as channels need JWST files in two filters or more
    """
    groups = jwst_filters(targets)
    if len(groups) < 2:
        raise KpifsError(f"{targets[0] if targets else 'no files'}: filters as channels need "
                         f"JWST files in two filters or more")
    names = {str(p): str(file_headers(p)[0].get("TARGNAME", "") or "").strip() for p in targets}
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
    given = (None if pixscale is None
             else to_quantity(pixscale, u.mas, name="pixel scale").value)
    scales = {f: _scale(files[0], given) for f, files in groups.items()}
    order = sorted(groups, key=lambda f: scales[f][0])
    return order, groups, cal_groups, scales


def filter_models(km, order, groups, scales, *, filter_kernels="own"):
    """The nested kernel of the filters and each filter's own model.

    *km* is the pupil's kernel model (`kpifs.workflow.kernel_model_for`);
    ``order``, ``groups`` and ``scales`` come from `filter_groups`. Returns
    ``(model, {filter: own model})``: each filter keeps the kernel of the uv
    points it samples (``filter_kernels='own'``), or every filter the kernel
    of those all sample (``'common'``). A filter without kernel phase is
    refused.

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.extraction.filters import filter_models
    >>> km = KernelModel.from_pupil(make_pupil("niriss_nrm"))
    >>> scales = {"F277W": (2.8, 65.55, 80), "F480M": (4.82, 65.55, 80)}
    >>> model, own = filter_models(km, ["F277W", "F480M"], {}, scales)
    >>> [own[f].n_kp for f in ("F277W", "F480M")]
    [6, 15]
    """
    usable = np.array([nyquist_usable(km.uv, [scales[f][0]] * u.um, scales[f][1] * u.mas)[0]
                       for f in order])
    for f, m in zip(order, usable):
        if m.sum() < 2:
            raise KpifsError(f"{_first(groups, f)}: filter {f}: {int(m.sum())} of {km.n_uv} uv "
                             f"points within its sampling limit "
                             f"({_limit(scales[f]):.2f} m at {scales[f][1]:g} mas pixels): "
                             f"no kernel phase")
    if filter_kernels not in ("own", "common"):
        raise KpifsError(f"filter kernels must be 'own' or 'common', got {filter_kernels!r}")
    if filter_kernels == "common":      # every filter the uv points all sample
        usable = np.broadcast_to(usable.all(axis=0), usable.shape)
    model, counts = nested_kernel(km, usable)
    for f, m, n in zip(order, usable, counts):
        if n == 0:
            raise KpifsError(f"{_first(groups, f)}: filter {f}: the {int(m.sum())} uv points "
                             f"within its sampling limit ({_limit(scales[f]):.2f} m at "
                             f"{scales[f][1]:g} mas pixels) give no kernel phase")
    log.info("filters %s: %s kernel phases (each its own uv points, of %d)", ", ".join(order),
             ", ".join(map(str, counts)), model.n_uv)
    own = {f: _channel_model(model, n, m[usable.any(axis=0)])
           for f, m, n in zip(order, usable, counts)}
    return model, own


def _first(groups, f):
    return groups[f][0] if groups.get(f) else f"filter {f}"


def filter_window_radius(order, scales, window_radius=None):
    """``{filter: window radius in its pixels}``: one *angular* radius for every filter.

    Without *window_radius* (pixels), the default radius of the finest
    sampled filter, in mas, expressed in each filter's pixels; with it, that
    radius in every filter.

    Examples
    --------
    >>> from kpifs.extraction.filters import filter_window_radius
    >>> r = filter_window_radius(["F150W", "F480M"], {"F150W": (1.5, 31.0, 64),
    ...                                                "F480M": (4.8, 63.0, 64)})
    >>> round(r["F150W"] * 31.0, 6) == round(r["F480M"] * 63.0, 6)
    True
    """
    if window_radius is not None:
        return {f: window_radius for f in order}
    radius_mas = min(DEFAULT_WINDOW_RADIUS * min(scales[f][2], 64) / 2 * scales[f][1]
                     for f in order)
    return {f: radius_mas / scales[f][1] for f in order}


def _limit(scale):
    """A filter's sampling limit (m): the longest baseline it samples."""
    wl_um, pix_mas = scale[0], scale[1]
    return wl_um * 1e-6 / (2 * pix_mas * np.pi / 180 / 3600e3)


def _channel_model(model, n, mask):
    """One filter's own model: its uv points and the nested kernel's first *n* rows."""
    meta = {k: v for k, v in model.meta.items() if k != "nested_counts"}
    return KernelModel(model.pupil, model.uv[mask], model.redundancy[mask], model.blm[mask],
                       kernel=model.kernel[:n][:, mask], meta=meta)


def stack_filters(products, names, *, kernel_model=None):
    """Calibrated one-filter products as the channels of one.

    Parameters
    ----------
    products : list of `~kpifs.data.KernelPhaseData`
        One calibrated frame per filter.
    names : list of str
        The filters' names.
    kernel_model : `~kpifs.model.kernel.KernelModel`, optional
        The nested kernel (`~kpifs.model.sampling.nested_kernel`) when the filters have
        their own: each product's kernel must be its first rows on the product's
        uv points. Default: the products share one kernel.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.extraction.filters import stack_filters
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
