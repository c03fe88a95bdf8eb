"""`detect`: from calibrated kernel phases to maps, candidates, spectra and limits.

The search runs as stages, each a function of the previous stages' dataclasses:
prepare -> whiten and error model -> null -> sequential search and fits -> maps
and limits -> report (`detect`).
"""
import logging
import warnings
from dataclasses import dataclass

import numpy as np
from astropy import units as u

from ..calibration.adi import inner_separation
from ..covariance import empirical_covariance, rows_covariance, whiten, whitening_matrix
from ..data import DetectionGrid, DetectionResult, KernelPhaseData
from ..exceptions import KpifsError, KpifsWarning
from ..model.field import search_field
from ..model.kernel import MAS, KernelModel
from ..model.pupil import make_pupil
from ..simulation.aberrations import static_term
from ._inputs import _aliased, _check_closure_dof, _drop_aliased, _measured, _wants_static
from ._laws import chi2_sf
from .blocks import block_stack
from .sdk import SpectralStack
from .channels import (MIN_SCALE, NOISE_CONFIDENCE, annulus_noise, channel_correlation,
                       combined_scale, energy_null, energy_spread, map_expectation, map_noise,
                       ring_noise, scale_block_rows)
from .limits import energy_lambda, radial_curves
from .maps import DetectionModel
from .null import check_draws, search_null
from .options import SearchOptions
from .quality import add_spectrum_model, flag_candidates, resolution_mas
from ..report import DetectionReport, LimitsReport, NullReport
from .search import _chi2_red, _sequential_search
from .sky import add_sky_columns, data_angles, pa_bins, search_frame, sky_search_columns
from .skyfit import refit_on_sky
from .spectral import spectral_basis, spectrum_shape
from .statistics import (REGISTRY, DetectionTest, LimitInputs, auto_test, get_test,
                         subspace_test)
from .stats import check_probability, energy_threshold


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


def detect(kpd, options=None, /, **keywords):
    """Search calibrated kernel phases for a companion.

    ``detect(kpd, options)`` with a `~kpifs.detect.options.SearchOptions`, or
    ``detect(kpd, test=..., pfa=...)`` with its fields as keywords. The search
    runs as stages: prepare the data (`_prepare_stage`), whiten them and take the
    error model (`_whiten_stage`), draw the null (`_null_stage`), search and fit
    the candidates one by one (`_search_stage`), make the maps and the limits
    (`_maps_stage`, `_limits_stage`) and report (`_report`).

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
        With its typed report (``result.report``, a
        `~kpifs.report.DetectionReport`; ``result.meta`` is made from it).

    Examples
    --------
    >>> from kpifs.detect.pipeline import _example_result
    >>> res = _example_result()          # detect() on a simulated calibrated data set
    >>> len(res.candidates), res.test      # 'auto': two channels, B (see *test*)
    (1, 'B')
    """
    if options is not None and keywords:
        raise KpifsError("detect: give the options or keywords, not both")
    opts = options if options is not None else SearchOptions.from_keywords(**keywords)
    prep = _prepare_stage(kpd, opts)
    white = _whiten_stage(prep, opts)
    null = _null_stage(prep, white, opts)
    found = _search_stage(prep, white, null, opts)
    maps = _maps_stage(prep, white, null, found, opts)
    limits = _limits_stage(prep, white, null, found, maps, opts) if opts.limits else None
    log.info("detect: %d candidate(s) above the %s threshold %.3f (global P_FA %.1e)",
             len(found.candidates), prep.test.map_name, null.threshold, opts.pfa)
    return _report(prep, white, null, found, maps, limits, opts)


# --- stage 1: prepare ----------------------------------------------------------------
@dataclass
class _Prepared:
    """The data to search: aliased channels dropped (*spectrum* and *basis* following
    the channels kept), frames averaged, the measured error model and the static
    term (*static_rows*, *static_info*), the test chosen and the spectrum shape *a*."""

    kpd: KernelPhaseData
    kp: np.ndarray
    cov: np.ndarray
    spectrum: object
    basis: object
    n_basis: int
    test: DetectionTest
    a: np.ndarray
    static_rows: np.ndarray = None
    static_info: dict = None


def _prepare_stage(kpd, opts):
    if opts.test != "auto":
        get_test(opts.test)
    check_probability(opts.pfa, "P_FA")
    check_probability(opts.pd, "P_D")
    check_draws(opts.n_draws)
    q0, spectrum, basis = kpd.n_wave, opts.spectrum, opts.basis
    kpd, kept = _drop_aliased(kpd, opts.aliased)
    if kept is not None:     # a per-channel spectrum or basis follows the channels kept
        if spectrum is not None and np.size(spectrum) == q0:
            spectrum = np.asarray(spectrum, float).ravel()[kept]
        if isinstance(basis, np.ndarray) and basis.ndim == 2 and len(basis) == q0:
            basis = basis[kept]
    kp, cov, kpd = _prepare(kpd, opts.shrinkage, opts.allow_uncalibrated)
    kp, cov = _measured(kpd, kp, cov)
    static_rows, static_info = None, None
    if _wants_static(kpd, opts.static):
        cov, static_rows, static_info = static_term(
            kpd, kp, cov, whitening_matrix(cov, source="covariance of the data"),
            seed=opts.seed)
    q = kp.shape[0]
    n_basis = spectral_basis(basis, kpd.wavelengths).shape[1]
    test = auto_test(n_basis, q) if opts.test == "auto" else get_test(opts.test)
    return _Prepared(kpd, kp, cov, spectrum, basis, n_basis, test, spectrum_shape(spectrum, q),
                     static_rows, static_info)


# --- stage 2: whiten, and the error model ----------------------------------------------
@dataclass
class _Whitened:
    """The whitened data and what the error model gives the search: the whitening
    *w* and its *rank*, the frame, PA bins of the search and of the fit (*poses*),
    the grid, the time blocks' stack, the `DetectionModel`, the whitened covariance
    *rows* and time *blocks*, and the characterisation's error model (made on first
    use, `_Characterisation`)."""

    kp: np.ndarray
    w: np.ndarray
    rank: np.ndarray
    y: np.ndarray
    frame: str
    search_poses: object
    poses: object
    grid: DetectionGrid
    stack: object
    model: DetectionModel
    rows: np.ndarray = None
    blocks: np.ndarray = None
    block_energy: float = None
    characterise: object = None


def _whiten_stage(prep, opts):
    kpd, kp = prep.kpd, prep.kp
    if getattr(kpd, "spectral", None) is not None and not kpd.meta.get("closure_phases"):
        # searched by channel combinations, whitened by their own error model (`SpectralStack`,
        # alone or in ASDI's `BlockStack`): the channels' whitening would not be used
        w = rank = None
    else:
        w, rank = whitening_matrix(prep.cov, return_rank=True, source="covariance of the data")
        rank = np.atleast_1d(rank)
        _check_closure_dof(kpd, prep.test, rank, prep.n_basis, kp, w)
    frame, search_poses, poses = _frame_and_poses(kpd, opts.frame, opts.grid)
    cov_rows, blk_rows, fit_rows = kpd.covariance_rows, kpd.block_rows, kpd.fit_covariance_rows
    if prep.static_rows is not None and cov_rows is not None:
        cov_rows = np.concatenate([cov_rows, prep.static_rows])
    # issue 29: a rotating sequence's time blocks, stacked (None: the one mean, as before)
    stack = block_stack(kpd, kp, w, rank, frame=frame, mode=opts.blocks, cov=prep.cov,
                        spectrum=prep.spectrum)
    if stack is None and getattr(kpd, "spectral", None) is not None:
        # issue 39: the channel combinations free of the static profiles (`kpifs.detect.sdk`)
        stack = SpectralStack(kpd, kp, prep.cov, spectrum=prep.spectrum, poses=search_poses)
    if getattr(stack, "mixing", None) is not None:       # searched by channel combinations
        prep.spectrum, prep.basis, prep.a = None, np.ones((stack.n_comb, 1)), \
            np.ones(stack.n_comb)
    if stack is not None:
        kp, w, rank = stack.kp, stack.whitening, stack.rank
        cov_rows, blk_rows, fit_rows = stack.rows, stack.block_rows, None
    grid, model = _search_model(prep, opts, frame, search_poses, stack, w, rank)
    out = _Whitened(kp, w, rank, kp if stack is not None else whiten(kp, w), frame,
                    search_poses, poses, grid, stack, model)
    if cov_rows is not None:
        out.rows = whiten(cov_rows, w)
        model.correlate(out.rows)
    else:
        log.info("no covariance rows: channels taken as independent in the null model")
    if blk_rows is not None:       # the empirical null: its scale from the error model
        out.blocks, out.block_energy = scale_block_rows(whiten(blk_rows, w), rank)
    if opts.fit and cov_rows is not None and fit_rows is not None:
        # positions and contrasts from the error model with more modes (calibrate's
        # fit_modes), whose rows also carry its channel correlations
        out.characterise = _Characterisation(fit_rows)
    return out


class _Characterisation:
    """The characterisation's error model from its covariance *rows*: its `whitening`,
    the rows whitened (`whitened_rows`) and its degrees of freedom (`dof`), made on
    first use: only candidates need it (a search that finds none skips its
    eigen-decompositions)."""

    def __init__(self, rows):
        self._rows, self._model = rows, None

    def _made(self):
        if self._model is None:
            fw, frank = whitening_matrix(rows_covariance(self._rows), return_rank=True,
                                         source="characterisation covariance")
            self._model = (fw, whiten(self._rows, fw), int(np.sum(frank)))
        return self._model

    @property
    def whitening(self):
        """The whitening matrices, one per channel."""
        return self._made()[0]

    @property
    def whitened_rows(self):
        """The covariance rows, whitened."""
        return self._made()[1]

    @property
    def dof(self):
        """The whitened dimension (degrees of freedom of a fit's chi-square)."""
        return self._made()[2]


def _search_model(prep, opts, frame, search_poses, stack, w, rank):
    """The search grid and its `DetectionModel` (a time-block stack's own, whose
    angular-differential search starts where the rotation keeps half a companion's
    signal, `kpifs.calibration.adi.inner_separation`)."""
    kpd, grid = prep.kpd, opts.grid
    if grid is None:
        grid = default_grid(kpd, frame=frame)
    if stack is None:
        return grid, DetectionModel(kpd.kernel_model, kpd.wavelengths, w, grid,
                                    pixscale=kpd.pixscale, window=kpd.window, dof=rank,
                                    detpa=search_poses, basis=prep.basis)
    model = stack.detection_model(grid, basis=prep.basis)
    inner = inner_separation(model) if stack.mode == "angular-differential" else np.nan
    if opts.grid is None and np.isfinite(inner) and inner > float(grid.min_sep):
        grid = default_grid(kpd, frame=frame, min_sep=inner * u.mas)
        model = stack.detection_model(grid, basis=prep.basis)
        stack.info["inner_separation"] = inner
    return grid, model


# --- stage 3: the null ---------------------------------------------------------------
@dataclass
class _Null:
    """The search's null (*null*, its *parts* by name) and threshold, its report, the
    noise model's spread and map floor; `for_test` gives another test's null from
    the same draws (the limits')."""

    null: object
    parts: dict
    threshold: float
    report: NullReport
    spread: float
    map_low: float
    make: object
    map_mean: float = 1.0

    def for_test(self, name):
        return self.null if name == self.null.form else self.make(name)[0]


def _null_stage(prep, white, opts):
    form = prep.test.map_name
    # only what is needed is reduced: the search's test, and the nulls the limits read
    # (drawn together; a null that depends on the spectrum shape is drawn on its own)
    shared = tuple(t.name for t in REGISTRY.values()
                   if _has_null(t) and not t.spectral_null) if opts.limits else ()

    def make(name):
        own = get_test(name).spectral_null
        return search_null(white.model, form=name, noise_rows=white.rows,
                           block_rows=white.blocks, method=opts.null, n_draws=opts.n_draws,
                           seed=opts.seed, spectrum=prep.spectrum if own else None,
                           progress=opts.progress, source=prep.kpd.name,
                           also=() if own else shared)
    null, parts = make(form)
    threshold = null.threshold(opts.pfa)
    blocks = white.blocks
    report = NullReport("+".join(parts), threshold,
                        {k: v.threshold(opts.pfa) for k, v in parts.items()},
                        None if blocks is None else len(blocks), white.block_energy,
                        parts["empirical"].n_draws if "empirical" in parts else None)
    if len(parts) > 1:
        log.info("null of the grid maximum at P_FA %.1e: Gaussian %.2f, empirical (sign flips "
                 "of %d time blocks) %.2f", opts.pfa, report.thresholds["gaussian"],
                 len(blocks), report.thresholds["empirical"])
    return _Null(null, parts, threshold, report, energy_spread(white.rows, int(white.rank.sum())),
                 float(np.quantile(null.noise_draws(), NOISE_CONFIDENCE)), make,
                 map_expectation(white.model))


def _has_null(test):
    """Whether a test's limit reads the threshold of its own null (a map test with a
    reduction of the draws, and a limit)."""
    own = type(test)
    return test.map_name == test.name and own.null_reducer is not DetectionTest.null_reducer \
        and own.limit is not DetectionTest.limit


# --- stage 4: the sequential search and the fits ---------------------------------------
class _NoiseJudge:
    """How a residual is judged: its reduced chi-square and noise scale (`scale`), and
    the noise of its annulus (`ring`); the last residual judged and its measures are
    kept (the maps and limits use those of the search's final residual)."""

    def __init__(self, prep, white, null):
        self.test, self.white, self.null = prep.test, white, null
        self.ring_width = resolution_mas(prep.kpd.kernel_model, prep.kpd.wavelengths)
        self.residual = self.map = self.common = self.subspace = None
        self._rings = {}           # per annulus, by subspace: (the residual, its map)

    def scale(self, res, n_par):
        w, model = self.white.w, self.white.model
        kappa = _chi2_red(res, w, int(self.white.rank.sum()), n_par)
        yr = whiten(res, w)
        self.residual, self.map = res, map_noise(model, yr)
        self.common = combined_scale(kappa, self.null.spread, self.map, self.null.map_low,
                                     self.null.map_mean)
        # the subspace test is judged by its own map's noise too (a smooth residual)
        self.subspace = map_noise(model, yr, subspace=True)
        return kappa, self.test.scale(self.common, self.subspace,
                                      lambda: self.null.null.noise_draws("G2"))

    def ring(self, res, peak, subspace=None):
        """The annulus noise around *peak* (None: per annulus, as a map); only ever up
        (an annulus's chance excess errs on the safe side)."""
        subspace = self.test.subspace_map if subspace is None else subspace
        if peak is None and self._rings.get(subspace, (None,))[0] is res:
            return self._rings[subspace][1]             # the maps' and the limits' residual
        model, yr = self.white.model, whiten(res, self.white.w)
        if peak is None:
            self._rings[subspace] = (res, annulus_noise(model, yr, subspace=subspace))
            return self._rings[subspace][1]
        return float(np.nan_to_num(ring_noise(model, yr, peak, width=self.ring_width,
                                              radius=1.5 * self.ring_width, subspace=subspace),
                                   nan=1.0))


@dataclass
class _Found:
    """The candidates, the final residual's reduced chi-square and noise scale, and its
    judge (the measures of that residual)."""

    candidates: object
    chi2_red: float
    scale: float
    judge: _NoiseJudge


def _search_stage(prep, white, null, opts):
    kpd, judge = prep.kpd, _NoiseJudge(prep, white, null)
    cands, kappa, scale = _sequential_search(
        white.model, white.kp, white.w, kpd, threshold=null.threshold, null=null.null,
        spectrum=prep.spectrum, fit=opts.fit, max_candidates=opts.max_candidates,
        scaler=judge.scale, ring=judge.ring, poses=white.poses,
        characterise=white.characterise, stack=white.stack)
    _warn_clamped(kpd, scale)
    if white.frame == "sky":
        sky_search_columns(cands, white.poses)
    else:
        # sky offsets only from angles the data know (not the 0 assumed without any)
        add_sky_columns(cands, kpd.detpa if data_angles(kpd) is not None else None)
    char = white.characterise
    fit_w, fit_rows = (white.w, null.null.noise_rows) if char is None or not len(cands) \
        else (char.whitening, char.whitened_rows)
    if white.frame == "detector" and opts.fit and refit_on_sky(
            cands, white.kp, fit_w, kpd, noise_rows=fit_rows) and "chi2_red" in cands.colnames:
        # the rotating fit's errors, scaled like the detector fit's
        chi2 = cands["fit_chi2_red" if char is not None else "chi2_red"]
        k = np.sqrt(np.maximum(1.0, np.asarray(chi2, float)))
        for col in ("fit_dra_err", "fit_ddec_err", "fit_pa_sky_err"):
            cands[col] = cands[col] * k
    if hasattr(white.stack, "channel_table"):           # issue 39: combinations -> channels
        white.stack.channel_table(cands)
    flag_candidates(cands, white.grid, noise_scale=scale,
                    resolution=resolution_mas(kpd.kernel_model, kpd.wavelengths))
    add_spectrum_model(cands, white.model.basis)
    return _Found(cands, kappa, scale, judge)


# --- stage 5: maps and limits --------------------------------------------------------
@dataclass
class _Maps:
    """The maps at the noise scale the data show against the model: statistic, local
    and global P_FA, contrasts and errors, the search's residual map; the energy
    test's numbers (*energy*) and the noise scale common to every test."""

    statistic: np.ndarray
    pfa_local: np.ndarray
    pfa_global: np.ndarray
    contrast: np.ndarray
    contrast_err: np.ndarray
    search_map: np.ndarray
    energy: dict
    common: float


def _maps_stage(prep, white, null, found, opts):
    model, form, judge = white.model, prep.test.map_name, found.judge
    power = get_test(form).power
    # the noise level the data show against the model (the residual after the candidates,
    # in all its modes and on the map): statistics, errors and limits are scaled by it
    t, c, cerr = model.maps(white.y, form, prep.spectrum)
    if hasattr(white.stack, "channel_contrasts"):       # issue 39: combinations -> channels
        c, cerr = white.stack.channel_contrasts(c, cerr)
    # per annulus, the map's own noise where it exceeds the scale (`annulus_noise`)
    smap = np.fmax(found.scale, np.nan_to_num(judge.ring(judge.residual, None), nan=0.0))
    t = t / smap ** power
    # what decided: the map of the residual the search stopped on (the candidates
    # subtracted), at the same noise scale (`DetectionResult.search_map`)
    search_map = model.maps(whiten(judge.residual, white.w), form, prep.spectrum)[0] \
        / smap ** power
    cerr = cerr * np.sqrt(judge.common)
    valid = white.grid.valid
    dof = int(white.rank.sum())
    t_e = float(np.sum(white.y ** 2))
    # the raw energy is the error model's diagnostic (dof when it is calibrated); its P_FA,
    # like every test's, is judged with the noise scale the search applies (the test's
    # own: S's map's too)
    common = found.scale if not prep.test.subspace_map else judge.common
    t_es = t_e / common
    energy = {"statistic": t_es, "raw": t_e, "dof": dof, "pfa": float(chi2_sf(t_es, dof)),
              "threshold": float(energy_threshold(opts.pfa, dof)), "pd": opts.pd,
              "noise_scale": common, "map_noise": judge.map, "map_expectation": null.map_mean,
              "subspace_noise": judge.subspace}
    return _Maps(t, np.where(valid, model.local_pfa(t, form), np.nan),
                 np.where(valid, null.null.pfa(t), np.nan), c, cerr, search_map, energy, common)


@dataclass
class _Limits:
    """Every registered test's limit map, scaled by its noise, its radial curves, the
    subspace test's noise scale and the energy's correlated draws."""

    maps: dict
    curves: object
    scale_subspace: float


def _limits_stage(prep, white, null, found, maps, opts):
    model, rows, energy = white.model, white.rows, maps.energy
    te = None
    if rows is not None:   # correlated channels: the energy's law from the same null model
        # a one-number statistic: its draws are cheap, and its threshold is read directly
        te = energy_null(rows, max(opts.n_draws, ENERGY_DRAWS), opts.seed)
        energy["pfa"] = float((np.sum(te["energy"] >= energy["statistic"]) + 1)
                              / (len(te["energy"]) + 1))
        if opts.pfa * len(te["energy"]) >= 10:
            energy["threshold"] = float(np.quantile(te["energy"], 1 - opts.pfa))
    tests = list(REGISTRY.values())
    inputs = LimitInputs(model, opts.pfa, opts.pd, prep.a, int(white.rank.sum()), opts.seed,
                         lambda name: null.for_test(name).threshold(opts.pfa),
                         prep.test.map_name, null.threshold, tuple(t.name for t in tests),
                         None if rows is None else channel_correlation(model, rows), rows,
                         te, energy["threshold"])
    raw = {t.name: t.limit(inputs) for t in tests}
    judge, scales = found.judge, {}
    # the subspace map's null draws come with the subspace test's null
    g2 = (lambda: null.for_test(subspace_test().name).noise_draws("G2"))
    maps_noise = {s: np.nan_to_num(judge.ring(judge.residual, None, subspace=s), nan=0.0)
                  for s in (False, True)}
    out = {}
    for t in tests:
        if raw[t.name] is None:
            continue
        scales[t.name] = t.scale(maps.common, judge.subspace, g2)
        if t.name == prep.test.map_name:
            scales[t.name] = max(scales[t.name], found.scale)
        out[t.name] = np.where(white.grid.valid, raw[t.name] * np.sqrt(
            np.fmax(scales[t.name], maps_noise[t.subspace_map])), np.nan)
    sub = [scales[t.name] for t in tests if t.subspace_map and t.name in scales]
    return _Limits(out, radial_curves(out, white.grid), sub[0] if sub else maps.common)


# --- stage 6: the report -------------------------------------------------------------
def _report(prep, white, null, found, maps, limits, opts):
    kpd, grid, valid = prep.kpd, white.grid, white.grid.valid
    poses = white.poses
    lim = None if limits is None else LimitsReport(
        maps.common, limits.scale_subspace, kpd.meta.get("error_model"), null.spread,
        null.map_low, kpd.meta.get("calibrators", []), kpd.meta.get("source", ""),
        np.asarray(getattr(white.stack, "spectrum", prep.a)).tolist(),
        energy_lambda(opts.pfa, opts.pd, int(white.rank.sum())),
        "covariance rows" if white.rows is not None else "independent",
        None if poses is None else [np.asarray(p).tolist() for p in poses],
        None if white.search_poses is None
        else [np.asarray(p).tolist() for p in white.search_poses])
    report = DetectionReport(
        prep.test.name, prep.test.map_name, opts.pfa, opts.pd, opts.n_draws, opts.seed, white.frame,
        found.chi2_red, found.scale, null.report, prep.static_info,
        None if white.stack is None else white.stack.info, _aliased(kpd).tolist(),
        list(kpd.meta.get("channels") or range(1, kpd.n_wave + 1)),
        list(kpd.meta.get("excluded_channels", [])), search_field(kpd, grid), lim)
    limit_maps = {} if limits is None else limits.maps
    return DetectionResult(
        grid=grid, test=prep.test.name, pfa=opts.pfa, pd=opts.pd, statistic=maps.statistic,
        pfa_local=maps.pfa_local, pfa_global=maps.pfa_global,
        contrast=np.where(valid, maps.contrast, np.nan),
        contrast_err=np.where(valid, maps.contrast_err, np.nan), limits=limit_maps,
        curves=radial_curves(limit_maps, grid) if limits is None else limits.curves,
        candidates=found.candidates, threshold=null.threshold, wavelengths=kpd.wavelengths,
        energy=maps.energy, header=kpd.header.copy(), report=report,
        search_map=np.where(valid, maps.search_map, np.nan))


def _warn_clamped(kpd, scale):
    """Never clamp the noise scale silently (issue 37)."""
    if scale <= MIN_SCALE:
        warnings.warn(f"{kpd.name}: the data scatter less than a tenth of what their errors "
                      f"say (noise scale clamped at {MIN_SCALE}): the errors (KP-SIGM, KP-COV "
                      f"or the pixel noise) are too large for these data, and every test and "
                      f"limit is too conservative", KpifsWarning, stacklevel=4)


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
