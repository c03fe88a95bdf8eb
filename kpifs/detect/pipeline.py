"""`detect`: from calibrated kernel phases to maps, candidates, spectra and limits."""
import logging
import warnings

import numpy as np
from astropy import units as u

from ..covariance import empirical_covariance, rows_covariance, whiten, whitening_matrix
from ..data import DetectionGrid, DetectionResult, KernelPhaseData
from ..exceptions import KpifsError, KpifsWarning
from ..model.kernel import MAS, KernelModel
from ..simulation.aberrations import static_term
from ..calibration.adi import inner_separation
from ..model.pupil import make_pupil
from ._inputs import _aliased, _check_closure_dof, _drop_aliased, _measured, _wants_static
from ._laws import chi2_sf, norm_isf
from .search import _POWER, _chi2_red, _sequential_search
from .sky import (add_sky_columns, data_angles, pa_bins,
                  search_frame, sky_search_columns)
from .skyfit import refit_on_sky
from .limits import (energy_lambda, limit_binary, limit_binary_correlated_forms, limit_energy,
                     limit_np, mirror_half_map, radial_curves)
from .blocks import block_stack
from .sdk import SpectralStack
from .maps import DetectionModel
from .null import DEFAULT_DRAWS, check_draws, search_null
from .channels import (MIN_SCALE, NOISE_CONFIDENCE, combined_scale, correlated_inputs,
                       energy_null, energy_spread, map_noise, np_correlated, scale_block_rows,
                       subspace_scale, annulus_noise, ring_noise)
from .quality import add_spectrum_model, flag_candidates, resolution_mas
from ..model.field import search_field
from .spectral import limit_subspace, spectral_basis, spectrum_shape
from .stats import TESTS, check_probability, energy_threshold


__all__ = ["detect", "default_grid"]

log = logging.getLogger(__name__)


def default_grid(kpd, *, step=None, max_sep=None, min_sep=None, frame="detector"):
    """A grid suited to the data: out to the window radius (and the aliasing limit),
    from half a resolution element, in steps of a quarter of one.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import ExtractionWindow, KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.detect import default_grid
    >>> km = KernelModel.from_pupil(make_pupil("subaru"))
    >>> kpd = KernelPhaseData(np.zeros((1, 1, km.n_kp)), [1.6] * u.um, 10.42 * u.mas, km,
    ...                       window=ExtractionWindow(40, 16.0))
    >>> g = default_grid(kpd)
    >>> g.shape, round(float(g.max_sep))
    ((31, 31), 167)
    """
    km = kpd.kernel_model
    lam_min = kpd.wavelengths.to_value(u.m).min()
    diam = float(np.max(np.hypot(*km.uv.value.T)))
    res = lam_min / diam / MAS
    limit = np.inf
    if km.pupil.step is not None:
        limit = 0.95 * lam_min / (2 * km.pupil.step.to_value(u.m)) / MAS
    if kpd.window is not None:
        limit = min(limit, kpd.window.radius * kpd.pixscale.to_value(u.mas))
    step = res / 4 if step is None else u.Quantity(step, u.mas).value
    max_sep = limit if max_sep is None else u.Quantity(max_sep, u.mas).value
    min_sep = res / 2 if min_sep is None else u.Quantity(min_sep, u.mas).value
    return DetectionGrid.from_separation(max_sep * u.mas, step * u.mas, min_sep=min_sep * u.mas,
                                         frame=frame)


#: Largest motion of a companion within one PA bin of the *search* (in finest
#: fringes at the grid's edge): its signature loses ~1.5 % to the smearing, while
#: the bins, and with them the cost of every map, are several times fewer than the
#: fit's (`kpifs.detect.sky.SMEAR_FRACTION`).
SEARCH_SMEAR_FRACTION = 0.1


def _frame_and_poses(kpd, frame, grid):
    """Search frame ('sky' or 'detector') and, on the sky, the PA bins ``(angles, weights)``
    of the search and of the fit (finer)."""
    frame = search_frame(kpd, grid.frame if grid is not None else frame)
    if frame == "detector":
        return "detector", None, None
    ang = data_angles(kpd)
    far = grid.max_sep if grid is not None and np.isfinite(grid.max_sep) else \
        default_grid(kpd).max_sep
    kw = dict(wavelength_min=kpd.wavelengths.min(),
              baseline_max=kpd.kernel_model.baseline_length.max())
    return ("sky", pa_bins(ang, max_separation=far * u.mas,
                           fraction=SEARCH_SMEAR_FRACTION, **kw),
            pa_bins(ang, max_separation=1.5 * far * u.mas, **kw))


def _prepare(kpd, shrinkage, allow_uncalibrated):
    adi = getattr(kpd.rotation, "search", None) == "angular-differential" \
        or getattr(kpd, "spectral", None) is not None      # issue 39: nor what is static
    if not kpd.meta.get("calibrated") and not adi:     # ADI: only what turns is searched
        if not allow_uncalibrated:
            raise KpifsError(f"{kpd.name}: not calibrated (no calibrator star subtracted): "
                             f"give its calibrator (--calibrator CALIBRATOR_KP.fits), or "
                             f"--allow-uncalibrated to search the data as they are")
        warnings.warn(f"{kpd.name}: not calibrated: searched as it is (aberrations that a "
                      f"calibrator would remove look like companions)", KpifsWarning,
                      stacklevel=3)
    if kpd.n_frame > 1:
        log.info("%s: using the mean of %d frames with their covariance / N", kpd.name,
                 kpd.n_frame)
        cov = empirical_covariance(kpd.kp, shrinkage=shrinkage, debias=True) / kpd.n_frame
        return kpd.kp.mean(axis=0), cov, kpd
    if kpd.covariance is None:
        raise KpifsError(f"{kpd.meta.get('source', 'data')}: one frame and no covariance "
                         f"(KP-COV): cannot whiten")
    return kpd.kp[0], kpd.covariance, kpd


def detect(kpd, *, test="auto", pfa=1e-3, pd=0.5, grid=None, spectrum=None, basis=None,
           n_draws=DEFAULT_DRAWS, seed=0, shrinkage="auto", fit=True, max_candidates=20,
           allow_uncalibrated=False, frame="auto", limits=True, null="auto", progress=False,
           blocks="auto", aliased="keep", static="auto"):
    """Search calibrated kernel phases for a companion.

    Parameters
    ----------
    kpd : `~kpifs.KernelPhaseData`
        Calibrated data (one frame with a covariance, from
        `~kpifs.calibration.calibrate.calibrate`). Uncalibrated data are refused unless
        *allow_uncalibrated* (the frames' mean is then searched, with a
        warning).
    test : {'auto', 'B', 'B-paper', 'S', 'NP', 'E'}
        ``'auto'`` (default): ``'S'`` when its spectral model (*basis*) has
        fewer dimensions than the data have channels, else ``'B'`` (on one
        channel the two are the same test; with as many dimensions as
        channels, B's all-positive contrasts constrain more). ``'B'``: the GLR binary
        test ``sum_i max(z_i, 0)^2``; ``'B-paper'``: the seed paper's
        ``sum_i max(z_i, 0)``; ``'S'``: the spectral-model (subspace) test, the
        GLR for a contrast spectrum in the span of *basis*
        (`kpifs.detect.spectral`); ``'NP'``: the matched filter for the
        given *spectrum* shape; these give the detection map. ``'E'``: the
        energy detector (a single statistic for the whole data set, reported in
        ``result.energy``); its map is that of ``'B'``.
    pfa, pd : float
        False-alarm probability (global, over the grid) and detection
        probability for candidates and limits.
    grid : `~kpifs.data.DetectionGrid`, optional
        Default `default_grid`.
    spectrum : array-like, optional
        Companion spectrum shape (per channel, any scale) for limits and the
        matched filter; flat by default.
    basis : optional
        Spectral model of test ``'S'`` (`~kpifs.detect.spectral.spectral_basis`):
        None for a smooth quadratic in wavelength, a rank, ``'blackbody'``, a
        file of template spectra or an array (q, r).
    n_draws, seed : int
        Monte-Carlo draws calibrating the grid search, and their seed.
    fit : bool
        Refine each candidate with `~kpifs.detect.fit.fit_binary`.
    max_candidates : int
        Candidates are searched one at a time: the strongest peak above the
        threshold is fitted and its model subtracted before the map is
        recomputed, so that side lobes of a companion are not reported. Each
        is judged, and its errors given, with the noise scaled by the reduced
        chi-square of the residual (``chi2_red`` column, never below 1); maps
        and limits use that of the final residual (``result.meta['chi2_red']``).
        A warning says when the search stops at this number.
    allow_uncalibrated : bool
        Search data that no calibrator star was subtracted from.
    frame : {'auto', 'sky', 'detector'}
        Where the search grid and the maps are. ``'sky'``: offsets dRA (East
        positive, maps East left) and dDec, with the model turned by each
        frame's detector position angle (grouped in PA bins, `pa_bins
        <kpifs.detect.sky.pa_bins>`), so that a rotating sequence adds up; maps
        carry a celestial WCS. ``'detector'``: image x and y. ``'auto'``
        (default): the sky when every frame's angle is known
        (`kpifs.detect.sky.data_angles`),
        else the detector. A *grid* given decides by its own frame.
    null : {'auto', 'gaussian', 'empirical', 'both'}
        What the grid maximum's threshold and global P_FA are calibrated on
        (`~kpifs.detect.null.search_null`): the Gaussian Monte-Carlo draws of the
        error model's covariance rows, the sign-flip (empirical) draws of the
        stars' time blocks (KP-BLKROWS, `~kpifs.calibration.calibrate.block_rows`), or
        the more conservative of the two (``'both'``, what ``'auto'`` picks when
        the data carry block rows). Both thresholds are reported
        (``result.meta['null']``).
    blocks : {'auto', 'rotation', 'angular-differential'}
        Data carrying the time blocks of a rotating sequence (`kpifs.rotation`)
        are searched on the sky block by block (`kpifs.detect.blocks`): the
        calibrated mean and the blocks' departures from it (``'rotation'``), or
        (``'angular-differential'``) the departures, nothing fixed on the
        detector, with a calibrated mean, when there is one, at its own reduced
        chi-square. ``'auto'``: the data's own choice.
    limits : bool
        Compute the detection limits (default). Without (as the injection
        curves do, which only need the candidates) ``result.limits`` is empty.
    aliased : {'keep', 'exclude'}
        Channels whose pixels alias some of their uv points (`kpifs.model.sampling`)
        are flagged in the result (``meta['aliased']``, the fraction per
        channel; cards ``ALIAS<i>`` of the products): a companion's contrast
        there is biased. ``'keep'`` (default) searches them, their noise is
        measured like any other's; ``'exclude'`` leaves them out of the search,
        the limits and the fits (``meta['excluded_channels']``), unless every
        channel is aliased.
    static : {'auto', 'none'}
        ``'auto'``: single-channel data no calibrator was subtracted from, whose
        frames cannot show their static aberrations, carry the kernel-phase
        residual of those in their covariance, its shape imaged through the
        pupil and its amplitude fitted to the data (`kpifs.simulation.aberrations`;
        ``result.meta['static']``). (Calibrated data carry the calibrated error
        model, whose modes the term would not respect; several channels are
        correlated by it, which the term does not model.)

    Returns
    -------
    `DetectionResult`

    Examples
    --------
    >>> from kpifs.detect.pipeline import _example_result
    >>> res = _example_result()          # detect() on a simulated calibrated data set
    >>> len(res.candidates), res.test      # 'auto': two channels, B (see *test*)
    (1, 'B')
    """
    if test not in TESTS + ("auto",):
        raise KpifsError(f"unknown test {test!r}: use one of {TESTS} or 'auto'")
    pfa = check_probability(pfa, "P_FA")
    pd = check_probability(pd, "P_D")
    check_draws(n_draws)
    q0 = kpd.n_wave
    kpd, kept = _drop_aliased(kpd, aliased)
    if kept is not None:     # a per-channel spectrum or basis follows the channels kept
        if spectrum is not None and np.size(spectrum) == q0:
            spectrum = np.asarray(spectrum, float).ravel()[kept]
        if isinstance(basis, np.ndarray) and basis.ndim == 2 and len(basis) == q0:
            basis = basis[kept]
    kp, cov, kpd = _prepare(kpd, shrinkage, allow_uncalibrated)
    kp, cov = _measured(kpd, kp, cov)
    static_rows, static_info = None, None
    if _wants_static(kpd, static):
        cov, static_rows, static_info = static_term(
            kpd, kp, cov, whitening_matrix(cov, source="covariance of the data"), seed=seed)
    q, p = kp.shape
    if test == "auto":     # measured: `docs/user/choosing_test.rst`
        # S only constrains the spectrum when its model has fewer dimensions than the
        # channels; with as many, B's all-positive contrasts are the stronger constraint
        test = "S" if spectral_basis(basis, kpd.wavelengths).shape[1] < q else "B"
    a = spectrum_shape(spectrum, q)
    w, rank = whitening_matrix(cov, return_rank=True, source="covariance of the data")
    rank = np.atleast_1d(rank)
    _check_closure_dof(kpd, test, rank, spectral_basis(basis, kpd.wavelengths).shape[1], kp, w)
    y = whiten(kp, w)
    frame, search_poses, poses = _frame_and_poses(kpd, frame, grid)
    own_grid = grid is None
    if grid is None:
        grid = default_grid(kpd, frame=frame)
    window = kpd.window
    # issue 29: a rotating sequence's time blocks, stacked (None: the one mean, as before)
    stack = block_stack(kpd, kp, w, rank, frame=frame, mode=blocks)
    if stack is None and getattr(kpd, "spectral", None) is not None:
        # issue 39: the channel combinations free of the static profiles (`kpifs.detect.sdk`)
        stack = SpectralStack(kpd, kp, cov, spectrum=spectrum, poses=search_poses)
        spectrum, basis, a = None, stack.basis, np.ones(stack.n_comb)
    cov_rows, blk_rows, fit_rows = kpd.covariance_rows, kpd.block_rows, kpd.fit_covariance_rows
    if static_rows is not None and cov_rows is not None:
        cov_rows = np.concatenate([cov_rows, static_rows])
    if stack is not None:
        kp, w, rank, y = stack.kp, stack.whitening, stack.rank, stack.kp
        cov_rows, blk_rows, fit_rows = stack.rows, stack.block_rows, None
        model = stack.detection_model(grid, basis=basis)
        inner = inner_separation(model) if stack.mode == "angular-differential" else np.nan
        if own_grid and np.isfinite(inner) and inner > float(grid.min_sep):
            # the angular-differential search starts where the rotation keeps half a
            # companion's signal (`kpifs.calibration.adi.inner_separation`)
            grid = default_grid(kpd, frame=frame, min_sep=inner * u.mas)
            model = stack.detection_model(grid, basis=basis)
            stack.info["inner_separation"] = inner
    else:
        model = DetectionModel(kpd.kernel_model, kpd.wavelengths, w, grid, pixscale=kpd.pixscale,
                               window=window, dof=rank, detpa=search_poses, basis=basis)
    form = "B" if test == "E" else test
    rows = None
    if cov_rows is not None:
        rows = whiten(cov_rows, w)
        model.correlate(rows)
    else:
        log.info("no covariance rows: channels taken as independent in the null model")
    blocks, block_energy = None, None
    if blk_rows is not None:       # the empirical null: its scale from the error model
        blocks, block_energy = scale_block_rows(whiten(blk_rows, w), rank)
    null_method = null

    def make_null(f):
        return search_null(model, form=f, noise_rows=rows, block_rows=blocks, method=null_method,
                           n_draws=n_draws, seed=seed, spectrum=spectrum if f == "NP" else None,
                           progress=progress, source=kpd.name)
    null, parts = make_null(form)
    threshold = null.threshold(pfa)
    null_info = {"method": "+".join(parts), "threshold": threshold,
                 **{f"threshold_{k}": v.threshold(pfa) for k, v in parts.items()},
                 "n_blocks": None if blocks is None else len(blocks),
                 "block_energy": block_energy,
                 "empirical_draws": parts["empirical"].n_draws if "empirical" in parts else None}
    if len(parts) > 1:
        log.info("null of the grid maximum at P_FA %.1e: Gaussian %.2f, empirical (sign flips "
                 "of %d time blocks) %.2f", pfa, null_info["threshold_gaussian"], len(blocks),
                 null_info["threshold_empirical"])
    spread = energy_spread(rows, int(rank.sum()))
    characterise = None
    if fit and cov_rows is not None and fit_rows is not None:
        # positions and contrasts from the error model with more modes (calibrate's
        # fit_modes), whose rows also carry its channel correlations
        fw, frank = whitening_matrix(rows_covariance(fit_rows), return_rank=True,
                                     source="characterisation covariance")
        characterise = (fw, whiten(fit_rows, fw), int(np.sum(frank)))
    map_low = float(np.quantile(null.noise_draws(), NOISE_CONFIDENCE))
    last = {}

    def scaler(res, n_par):
        kappa = _chi2_red(res, w, int(rank.sum()), n_par)
        last["res"] = res
        yr = whiten(res, w)
        last["map"] = map_noise(model, yr)
        last["scale"] = combined_scale(kappa, spread, last["map"], map_low)
        # the subspace test is judged by its own map's noise too (a smooth residual)
        last["sub"] = map_noise(model, yr, subspace=True)
        if form != "S":
            return kappa, last["scale"]
        return kappa, subspace_scale(last["scale"], last["sub"], null.noise_draws("G2"))
    ring_width = resolution_mas(kpd.kernel_model, kpd.wavelengths)

    def ring(res, peak, subspace=form == "S"):
        # only ever up (an annulus's chance excess errs on the safe side)
        if peak is None:
            return annulus_noise(model, whiten(res, w), subspace=subspace)
        return float(np.nan_to_num(ring_noise(model, whiten(res, w), peak, width=ring_width,
                                              radius=1.5 * ring_width, subspace=subspace),
                                   nan=1.0))
    cands, kappa, scale = _sequential_search(
        model, kp, w, kpd, threshold=threshold, null=null, spectrum=spectrum, fit=fit,
        max_candidates=max_candidates, scaler=scaler, ring=ring, poses=poses,
        characterise=characterise, stack=stack)
    _warn_clamped(kpd, scale)
    if frame == "sky":
        sky_search_columns(cands, poses)
    else:
        # sky offsets only from angles the data know (not the 0 assumed without any)
        add_sky_columns(cands, kpd.detpa if data_angles(kpd) is not None else None)
    fit_w, fit_rows = (w, null.noise_rows) if characterise is None else characterise[:2]
    if frame == "detector" and fit and refit_on_sky(cands, kp, fit_w, kpd, noise_rows=fit_rows) \
            and "chi2_red" in cands.colnames:
        # the rotating fit's errors, scaled like the detector fit's
        chi2 = cands["fit_chi2_red" if characterise is not None else "chi2_red"]
        k = np.sqrt(np.maximum(1.0, np.asarray(chi2, float)))
        for col in ("fit_dra_err", "fit_ddec_err", "fit_pa_sky_err"):
            cands[col] = cands[col] * k
    flag_candidates(cands, grid, resolution=resolution_mas(kpd.kernel_model, kpd.wavelengths),
                    noise_scale=scale)
    add_spectrum_model(cands, model.basis)
    # the noise level the data show against the model (the residual after the candidates,
    # in all its modes and on the map): statistics, errors and limits are scaled by it
    t, c, cerr = model.maps(y, form, spectrum)
    if hasattr(stack, "channel_contrasts"):       # issue 39: combinations -> channels
        c, cerr = stack.channel_contrasts(c, cerr)
        stack.channel_table(cands)
    # per annulus, the map's own noise where it exceeds the scale (`annulus_noise`)
    smap = np.fmax(scale, np.nan_to_num(ring(last["res"], None), nan=0.0))
    t = t / smap ** _POWER[form]
    # what decided: the map of the residual the search stopped on (the candidates
    # subtracted), at the same noise scale (`DetectionResult.search_map`)
    search_map = model.maps(whiten(last["res"], w), form, spectrum)[0] / smap ** _POWER[form]
    cerr = cerr * np.sqrt(last["scale"])
    valid = grid.valid
    pglob = np.where(valid, null.pfa(t), np.nan)
    ploc = np.where(valid, model.local_pfa(t, form), np.nan)

    dof = int(rank.sum())
    t_e = float(np.sum(y ** 2))
    # the raw energy is the error model's diagnostic (dof when it is calibrated); its P_FA,
    # like every test's, is judged with the noise scale the search applies
    # the search's scale is the test's own (S: its map's too)
    common = scale if form != "S" else last["scale"]
    t_es = t_e / common
    energy = {"statistic": t_es, "raw": t_e, "dof": dof, "pfa": float(chi2_sf(t_es, dof)),
              "threshold": float(energy_threshold(pfa, dof)), "pd": pd,
              "noise_scale": common, "map_noise": last["map"],
              "subspace_noise": last.get("sub")}
    te = None
    if not limits:
        return _result(kpd, grid, test, pfa, pd, t, ploc, pglob, c, cerr, {}, cands, threshold,
                       energy, {"search_map": search_map, "frame": frame, "chi2_red": kappa,
                                "noise_scale": scale,
                                "n_draws": n_draws, "seed": seed, "test": test, "pfa": pfa,
                                "pd": pd, "null": null_info, "static": static_info,
                                "blocks": None if stack is None else stack.info})
    if rows is not None:   # correlated channels: the energy's law from the same null model
        # a one-number statistic: its draws are cheap, and its threshold is read directly
        te = energy_null(rows, max(n_draws, ENERGY_DRAWS), seed)
        energy["pfa"] = float((np.sum(te["energy"] >= t_es) + 1) / (len(te["energy"]) + 1))
        if pfa * len(te["energy"]) >= 10:
            energy["threshold"] = float(np.quantile(te["energy"], 1 - pfa))
    limits = {"NP": limit_np(model.norm2, pfa, pd, a)}
    corr = None
    if rows is None:
        limits["E"] = limit_energy(model.norm2, pfa, pd, dof, a)
    else:
        corr, limits["E"] = correlated_inputs(model, rows, a, energy, te, seed)
    thr = {f: threshold if f == form else make_null(f)[0].threshold(pfa)
           for f in ("B", "B-paper", "S")}
    if corr is None:
        for f in ("B", "B-paper"):
            limits[f] = limit_binary(model.norm2, thr[f], pd, form=f, spectrum=a, seed=seed)
    else:       # the correlated draws of each position serve both forms
        limits.update(limit_binary_correlated_forms(
            model.norm2, {f: thr[f] for f in ("B", "B-paper")}, pd, spectrum=a, seed=seed,
            correlation=corr))
    limits["S"] = limit_subspace(model.subspace, model.norm2, thr["S"], pd, spectrum=a,
                                 correlation=corr, seed=seed)
    if corr is not None:    # the known-spectrum reference with the same correlation
        limits["NP"] = np_correlated(model.norm2, corr, a, pfa, pd)
    # the NP reference uses the local threshold; with the grid search its own global one
    if form == "NP":
        limits["NP"] = (threshold - norm_isf(pd)) / np.sqrt(
            np.tensordot(a ** 2, model.norm2, axes=(0, 0)))
    if corr is not None and model.half_positions()[1]:
        for f in ("E", "B", "B-paper", "S"):
            limits[f] = mirror_half_map(limits[f])
    scales = {k: common for k in limits}
    scales["S"] = subspace_scale(common, last["sub"], make_null("S")[0].noise_draws("G2"))
    if form == "S":
        scales["S"] = max(scales["S"], scale)
    zmap = np.nan_to_num(ring(last["res"], None, subspace=False), nan=0.0)
    gmap = np.nan_to_num(ring(last["res"], None, subspace=True), nan=0.0)
    limits = {k: np.where(valid, v * np.sqrt(np.fmax(scales[k], gmap if k == "S" else zmap)),
                          np.nan) for k, v in limits.items()}
    curves = radial_curves(limits, grid)
    meta = {"search_map": search_map, "test": test, "pfa": pfa, "pd": pd, "n_draws": n_draws,
            "seed": seed,
            "chi2_red": kappa, "noise_scale": scale, "noise_scale_common": common,
            "noise_scale_S": scales["S"], "error_model": kpd.meta.get("error_model"),
            "energy_spread": spread, "map_noise_low": map_low,
            "calibrators": kpd.meta.get("calibrators", []),
            "source": kpd.meta.get("source", ""),
            "spectrum": np.asarray(getattr(stack, "spectrum", a)).tolist(),   # issue 39
            "lambda_energy": energy_lambda(pfa, pd, dof),
            "null_channels": "covariance rows" if rows is not None else "independent",
            "null": null_info,
            "frame": frame,
            "pa_bins": None if poses is None else [np.asarray(p).tolist() for p in poses],
            "pa_bins_search": None if search_poses is None
            else [np.asarray(p).tolist() for p in search_poses],
            "blocks": None if stack is None else stack.info, "static": static_info}
    log.info("detect: %d candidate(s) above the %s threshold %.3f (global P_FA %.1e)",
             len(cands), form, threshold, pfa)
    return _result(kpd, grid, test, pfa, pd, t, ploc, pglob, c, cerr, limits, cands,
                   threshold, energy, meta, curves)


def _warn_clamped(kpd, scale):
    """Never clamp the noise scale silently (issue 37)."""
    if scale <= MIN_SCALE:
        warnings.warn(f"{kpd.name}: the data scatter less than a tenth of what their errors "
                      f"say (noise scale clamped at {MIN_SCALE}): the errors (KP-SIGM, KP-COV "
                      f"or the pixel noise) are too large for these data, and every test and "
                      f"limit is too conservative", KpifsWarning, stacklevel=4)


def _result(kpd, grid, test, pfa, pd, t, ploc, pglob, c, cerr, limits, cands, threshold,
            energy, meta, curves=None):
    valid = grid.valid
    meta["aliased"] = _aliased(kpd).tolist()
    meta["channels"] = list(kpd.meta.get("channels") or range(1, kpd.n_wave + 1))
    meta["excluded_channels"] = list(kpd.meta.get("excluded_channels", []))
    meta["field"] = search_field(kpd, grid)
    if curves is None:
        curves = radial_curves(limits, grid)
    search = meta.pop("search_map", None)
    return DetectionResult(grid=grid, test=test, pfa=pfa, pd=pd, statistic=t, pfa_local=ploc,
                           pfa_global=pglob, contrast=np.where(valid, c, np.nan),
                           contrast_err=np.where(valid, cerr, np.nan), limits=limits,
                           curves=curves, candidates=cands, threshold=threshold,
                           wavelengths=kpd.wavelengths, energy=energy, meta=meta,
                           header=kpd.header.copy(),
                           search_map=None if search is None else np.where(valid, search, np.nan))


#: Draws of the energy detector's correlated null (its threshold read from them).
ENERGY_DRAWS = 30000

_EXAMPLE = {}


def _example_result():
    """A small, cached `DetectionResult` for the documentation's examples.

    Two channels, a 0.6 m Subaru model, a companion with contrasts (4e-3, 3e-3)
    at (60, -40) mas in white noise of 1e-3 rad, searched out to 100 mas.
    """
    if "result" not in _EXAMPLE:
        km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
        wl = [1.6, 1.7] * u.um
        rng = np.random.default_rng(1)
        kp = km.binary_kernel_phases([60, -40] * u.mas, [4e-3, 3e-3], wl)
        kp = kp + rng.normal(0, 1e-3, kp.shape)
        cov = np.stack([np.eye(km.n_kp) * 1e-6] * 2)
        kpd = KernelPhaseData(kp[None], wl, 10.42 * u.mas, km, covariance=cov,
                              meta={"calibrated": True})
        grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
        _EXAMPLE["result"] = detect(kpd, grid=grid, n_draws=2000, seed=0)
    return _EXAMPLE["result"]
