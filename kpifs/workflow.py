"""One observation, from files to products: the driver behind ``kpifs extract``,
``kpifs detect``, ``kpifs batch`` and ``kpifs demo``.

Options live in two typed objects, `ExtractOptions` (how cubes are read and
reduced to kernel phases) and `DetectOptions` (how calibrated kernel phases
are searched). The steps are functions that every interface calls:

- `kernel_model_for`: the pupil/kernel model the options ask for;
- `extract_observation`: read cube file(s) and extract kernel phases;
- `calibrate_observation`: the one place a calibrator is subtracted (else the covariance);
- `detect_observation`: the search, maps, candidates and limits;
- `extract_filters`: JWST files in several filters as the channels of one product;
- `reduce_observation`: the product of one target and its calibrators, every option
  included (filters, angular-differential): what ``kpifs extract`` writes;
- `process_observation`: all of them for one target and its calibrators, writing
  ``calibrated_kp.fits`` and ``detection.fits`` as ``kpifs extract … --calibrator …``
  and ``kpifs detect`` would.
"""
import dataclasses
import json
import logging
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from astropy import units as u

from . import _checks
from .extraction import filters as _filters
from ._defaults import DETECT as _DETECT, EXTRACT as _EXTRACT
from ._utils import check_output_dir, check_output_path, to_quantity
from .calibration.adi import angular_differential, target_blocks
from .calibration.spectral_diff import SDK_BASES, spectral_differential
from .calibration.calibrate import calibrate, check_calibration
from .covariance import empirical_covariance
from .data import KernelPhaseData
from .detect import null as _null, pipeline as _pipeline, sky as _sky
from .detect import sdk as _sdk, spectral as _spectral, stats as _stats
from .detect import statistics as _statistics
from .exceptions import KpifsError, KpifsWarning
from .extraction.extract import extract_kernel_phases
from .extraction.filled import filled_pixel_rows
from .io.angles import frame_detpa, parse_angles
from .io.instruments import INSTRUMENTS as _INSTRUMENTS
from .io.readers import check_pupil_header, header_pupil, read_cube
from .io.wavelengths import parse_wavelengths
from .model.kernel import load_kernel_model
from .calibration.pixelnoise import attach_pixel_noise
from .provenance import (combined_digest, inputs_digest, observation_digest, options_record,
                         products_digest)
from .model.window import ExtractionWindow
from .simulation.aberrations import static_residual_rows

__all__ = ["ExtractOptions", "DetectOptions", "DEFAULT_PUPIL", "kernel_model_for",
           "default_pupil",
           "calibrator_options",
           "extract_observation", "calibrate_observation", "extract_filters",
           "reduce_observation", "detect_observation",
           "process_observation", "options_record", "inputs_digest",
           "products_digest", "observation_digest"]

log = logging.getLogger(__name__)

#: The telescope pupil of each registered instrument's cubes (plain cubes: Subaru; JWST,
#: GPI and NIRC2 headers name theirs, `kpifs.io.readers.header_pupil`), as each
#: instrument's module says (`kpifs.io.instruments.INSTRUMENTS`).
DEFAULT_PUPIL = {name: inst.pupil for name, inst in _INSTRUMENTS.items()}


@dataclass
class ExtractOptions:
    """How cubes are read, which kernel model is used and how phases are extracted.

    Every field has the command line's default; strings with units are
    accepted wherever a Quantity is (``step="0.38m"``). ``pa`` overrides the
    detector position angles of the cubes read (deg: one value, one per
    frame, or a text/FITS file; see `kpifs.io.parse_angles`); calibrators are
    read without it (`calibrator_options`). ``filter_kernels`` applies to
    JWST files in several filters (`extract_filters`), and
    ``angular_differential`` makes the product of a rotating sequence that is
    searched by what turns with the sky, and ``spectral_differential`` (a basis
    name, ``kpifs.calibration.spectral_diff.SDK_BASES``) one searched by the
    channel combinations free of the static residual's profiles
    (`reduce_observation`). The defaults
    are written once, in ``kpifs._defaults``, for the command line too.

    Examples
    --------
    >>> from kpifs.workflow import ExtractOptions
    >>> opts = ExtractOptions(step="0.8m", window_radius=12)
    >>> opts.instrument, opts.centroid
    ('auto', 'com')
    """

    instrument: str = _EXTRACT["instrument"]
    wavelengths: object = _EXTRACT["wavelengths"]
    pixscale: object = _EXTRACT["pixscale"]
    pa: object = _EXTRACT["pa"]
    dq_bits: object = _EXTRACT["dq_bits"]      # JWST: DQ flags read as bad (`jwst.parse_dq_bits`)
    # pupil (None: the instrument's telescope) and model (None: `pupil.MODEL_DEFAULTS`)
    pupil: object = _EXTRACT["pupil"]
    pupil_scale: object = _EXTRACT["pupil_scale"]
    step: object = _EXTRACT["step"]
    offset: object = _EXTRACT["offset"]
    min_transmission: float = _EXTRACT["min_transmission"]
    grey: bool = _EXTRACT["grey"]
    min_redundancy: float = _EXTRACT["min_redundancy"]
    rotation: object = _EXTRACT["rotation"]
    hexagonal: bool = _EXTRACT["hexagonal"]
    window_size: int = _EXTRACT["window_size"]
    window_radius: float = _EXTRACT["window_radius"]
    window_order: float = _EXTRACT["window_order"]
    centroid: str = _EXTRACT["centroid"]
    bad_pixels: str = _EXTRACT["bad_pixels"]
    bad_frames: str = _EXTRACT["bad_frames"]
    on_nyquist: str = _EXTRACT["on_nyquist"]
    mask: object = _EXTRACT["mask"]
    precision: str = _EXTRACT["precision"]
    shrinkage: str = _EXTRACT["shrinkage"]
    joint_covariance: bool = _EXTRACT["joint_covariance"]
    covariance: bool = _EXTRACT["covariance"]
    # `~kpifs.calibration.calibrate.calibrate`: beyond modes
    pixel_noise: str = _EXTRACT["pixel_noise"]
    filter_kernels: str = _EXTRACT["filter_kernels"]   # `extract_filters`
    angular_differential: bool = _EXTRACT["angular_differential"]   # `reduce_observation`
    spectral_differential: object = _EXTRACT["spectral_differential"]   # issue 39

    def __post_init__(self):
        # the registry's names: one check, one message, for the command line, a batch and
        # Python alike
        if self.instrument != "auto":
            _INSTRUMENTS.get_instrument(self.instrument)

    def window_for(self, image_shape):
        """The `~kpifs.model.window.ExtractionWindow` these options give for images of a
        shape."""
        return ExtractionWindow.default(image_shape, size=self.window_size,
                                        radius=self.window_radius, order=self.window_order)


@dataclass
class DetectOptions:
    """How calibrated kernel phases are searched (see `~kpifs.detect.detect`).

    ``max_sep``, ``min_sep`` and ``grid_step`` (mas) override the default grid;
    ``spectrum`` is 'flat' (None), a list of per-channel values or a text file;
    ``basis`` the spectral model of test S (`~kpifs.detect.spectral.spectral_basis`:
    None, ``'smooth:R'``, ``'blackbody'``, spectra in a file); ``blocks``, ``aliased``,
    ``static``: `~kpifs.detect.detect`.

    Examples
    --------
    >>> from kpifs.workflow import DetectOptions
    >>> DetectOptions(pfa=1e-4).test, DetectOptions().aliased
    ('auto', 'keep')
    """

    test: str = _DETECT["test"]
    pfa: float = _DETECT["pfa"]
    pd: float = _DETECT["pd"]
    max_sep: object = _DETECT["max_sep"]
    min_sep: object = _DETECT["min_sep"]
    grid_step: object = _DETECT["grid_step"]
    spectrum: object = _DETECT["spectrum"]
    basis: object = _DETECT["basis"]
    draws: int = _DETECT["draws"]
    seed: int = _DETECT["seed"]
    shrinkage: str = _DETECT["shrinkage"]
    fit: bool = _DETECT["fit"]
    max_candidates: int = _DETECT["max_candidates"]
    allow_uncalibrated: bool = _DETECT["allow_uncalibrated"]
    frame: str = _DETECT["frame"]
    null: str = _DETECT["null"]
    blocks: str = _DETECT["blocks"]
    aliased: str = _DETECT["aliased"]
    static: str = _DETECT["static"]

    def validate(self):
        """Refuse options no search can run with (before any work); return self."""
        check_probability = _stats.check_probability
        if self.test != "auto":
            _statistics.get_test(self.test)         # a registered test, else refused
        check_probability(self.pfa, "P_FA")
        check_probability(self.pd, "P_D")
        _null.check_draws(self.draws)
        if self.frame not in ("auto", "sky", "detector"):
            raise KpifsError(f"unknown frame {self.frame!r}: use auto, sky or detector")
        if self.null not in _null.NULL_METHODS:
            raise KpifsError(f"unknown null {self.null!r}: use one of {_null.NULL_METHODS}")
        _checks.check_seed(self.seed, "--seed")
        _checks.check_draws_memory(self.draws)
        seps = {k: _mas(getattr(self, k), f"--{k.replace('_', '-')}")
                for k in ("max_sep", "min_sep", "grid_step")}
        for k, v in seps.items():
            if v is not None and not (np.isfinite(v.value) and (
                    v.value > 0 or (k == "min_sep" and v.value == 0))):
                raise KpifsError(f"--{k.replace('_', '-')} must be > 0, got {v}")
        if seps["max_sep"] is not None and seps["min_sep"] is not None \
                and seps["max_sep"] <= seps["min_sep"]:
            raise KpifsError(f"--max-sep {seps['max_sep']} must be larger than --min-sep "
                             f"{seps['min_sep']}")
        return self


def calibrator_options(options):
    """The options for a calibrator's cubes: *options* without the ``pa`` override.

    The override gives the angles of the target's frames; a calibrator keeps
    the angles of its own headers.

    Examples
    --------
    >>> from kpifs.workflow import ExtractOptions, calibrator_options
    >>> calibrator_options(ExtractOptions(pa="10,20")).pa is None
    True
    """
    return dataclasses.replace(options, pa=None)


def default_pupil(instrument="generic", header=None):
    """The pupil of cubes of *instrument* whose header is *header* (when --pupil is not given).

    Examples
    --------
    >>> from astropy.io import fits
    >>> from kpifs.workflow import default_pupil
    >>> default_pupil("generic", fits.Header({"INSTRUME": "NIRISS", "PUPIL": "CLEARP"}))
    'niriss_clearp'
    """
    return (header_pupil(header) if header is not None else None) or \
        DEFAULT_PUPIL.get(instrument, DEFAULT_PUPIL["generic"])


def kernel_model_for(options, instrument="generic", header=None):
    """The kernel model *options* ask for, for cubes of *instrument* (with *header*).

    Examples
    --------
    >>> from kpifs.workflow import ExtractOptions, kernel_model_for
    >>> kernel_model_for(ExtractOptions(step="0.8m"), "sphere")
    <KernelModel 'vlt': ... kernel phases>
    """
    pupil = options.pupil if options.pupil is not None else default_pupil(instrument, header)
    if header is not None:
        check_pupil_header(pupil, header, source=header.get("FILENAME", "cube"))
    offset = None if options.offset is None else \
        to_quantity(options.offset, u.m, name="grid offset")
    if offset is not None and offset.size != 2:
        raise KpifsError(f"the grid offset needs two values x,y, got {options.offset!r}")
    step = None if options.step is None else to_quantity(options.step, u.m, name="grid step")
    rotation = (None if options.rotation is None
                else to_quantity(options.rotation, u.deg, name="pupil rotation"))
    return load_kernel_model(pupil, pupil_scale=options.pupil_scale, step=step,
                             offset=offset, min_transmission=options.min_transmission,
                             grey=options.grey, min_redundancy=options.min_redundancy,
                             rotation=rotation, hexagonal=options.hexagonal)


def _pixscale(options):
    return None if options.pixscale is None else \
        to_quantity(options.pixscale, u.mas, name="pixel scale")


def extract_observation(files, options=None, *, model=None, progress=False):
    """Read cube file(s) of one star and extract their kernel phases.

    Parameters
    ----------
    files : str or list of str
        Cube files; several are more frames of the same star.
    options : `ExtractOptions`, optional
    model : `~kpifs.model.kernel.KernelModel`, optional
        Use this model (e.g. the target's, for its calibrators) instead of
        the one *options* describe.
    progress : bool
        Progress bar on a terminal.

    Returns
    -------
    `~kpifs.data.KernelPhaseData`

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.io import write_observation
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> from kpifs.workflow import ExtractOptions, extract_observation
    >>> tmp = tempfile.TemporaryDirectory()
    >>> files = write_observation(simulate_scene("paper", n_frames=2, npup=32),
    ...                           tmp.name)
    >>> extract_observation(files["target"], ExtractOptions(step="0.8m")).shape
    (2, 3, 65)
    >>> tmp.cleanup()
    """
    options = options or ExtractOptions()
    files = [str(files)] if isinstance(files, (str, Path)) else [str(f) for f in files]
    _checks.check_inputs(files)
    pa = parse_angles(options.pa, source="--pa")
    with read_cube(files, instrument=options.instrument, dq_bits=options.dq_bits,
                   wavelengths=parse_wavelengths(options.wavelengths, source="--wavelengths"),
                   pixscale=_pixscale(options), pa_given=pa is not None) as cube:
        log.info("%s read as %s: %s", cube.name, cube.instrument, cube.shape)
        km = model or kernel_model_for(options, cube.instrument, cube.header)
        try:
            window = options.window_for(cube.shape)
        except KpifsError as exc:
            raise KpifsError(f"{cube.name}: {exc}") from None
        mask = cube.mask if options.mask is None else options.mask
        detpa, pa_source = _detpa(cube, pa)
        kpd = extract_kernel_phases(
            cube.data, km, wavelengths=cube.wavelengths, pixscale=cube.pixscale,
            window=window, mask=mask, centroid=options.centroid,
            bad_pixels=options.bad_pixels, bad_frames=options.bad_frames,
            on_nyquist=options.on_nyquist, precision=options.precision,
            header=cube.header, source=cube.name, detpa=detpa, progress=progress)
        attach_pixel_noise(kpd, cube)
    kpd.meta["instrument"] = cube.instrument
    kpd.meta["detpa_source"] = pa_source
    kpd.header["KPXOPTS"] = (json.dumps(options_record(options), sort_keys=True),
                             "kpifs extraction options")
    kpd.header["KPINHASH"] = (inputs_digest(files), "digest of the input files")
    return kpd


def _detpa(cube, override):
    """The detector position angle of each frame of *cube* (deg) and where it came from."""
    if override is not None:
        return frame_detpa(override, cube.shape[0], source=f"{cube.name}: --pa"), "--pa"
    if cube.detpa is None:
        log.warning("%s: no detector position angle: sky orientation unknown (give --pa)",
                    cube.name)
        return np.full(cube.shape[0], np.nan), "unknown"
    detpa = cube.detpa.to_value(u.deg)
    n_nan = int(np.isnan(detpa).sum())
    if n_nan:
        log.warning("%s: detector position angle unknown for %d of %d frame(s) (%s): sky "
                    "orientation unknown there (give --pa)", cube.name, n_nan, len(detpa),
                    cube.detpa_source)
    elif str(cube.detpa_source).startswith("none"):
        log.info("%s: no detector position angle in the file: 0 deg assumed (North up, East "
                 "left; give --pa)", cube.name)
    return detpa, cube.detpa_source


def calibrate_observation(target, calibrators=(), options=None):
    """Calibrate *target* with *calibrators* (the one place kpifs calibrates).

    Without calibrators the target is returned, with the frames' own
    covariance attached when ``options.covariance`` or
    ``options.joint_covariance`` asks for it.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.workflow import calibrate_observation
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> rng = np.random.default_rng(0)
    >>> t, c = (KernelPhaseData(rng.normal(0, 0.1, (200, 1, km.n_kp)), [1.6] * u.um,
    ...                         10 * u.mas, km) for _ in range(2))
    >>> calibrate_observation(t, [c]).meta["calibrated"]
    True
    """
    options = options or ExtractOptions()
    calibrators = list(calibrators)
    if calibrators:
        check_calibration(target, calibrators)
        target, calibrators = _checks.match_dead_channels(target, calibrators)
        result = calibrate(target, calibrators, shrinkage=options.shrinkage,
                           joint=options.joint_covariance, pixel_noise=options.pixel_noise)
        em = result.meta.get("error_model") or {}
        if em.get("model") == "modes" and em.get("dof", np.inf) < target.n_kp:
            rest = ("the others carry the pixel noise (ERR)" if em.get("pixel_modes") else
                    "its scale is measured on the calibrated data when detecting")
            frames = [k.n_frame for k in [target] + calibrators]
            warnings.warn(f"{target.name}: too few frames ({frames}, {em['dof']} degrees of "
                          f"freedom) for the covariance of "
                          f"{target.n_kp} kernel phases per channel: it is modelled on its "
                          f"{em['n_modes']} best-measured modes only, and {rest} (use several "
                          f"times more frames than kernel phases, or a coarser pupil model, "
                          f"--step)", KpifsWarning, stacklevel=2)
        digest = combined_digest([k.header.get("KPINHASH", k.name)
                                  for k in [target] + calibrators])
        result.header["KPINHASH"] = (digest, "digest of the input files")
        return result
    if options.covariance or options.joint_covariance:
        if target.n_frame < 2:
            raise KpifsError(f"{target.name}: one frame: no covariance can be estimated")
        target.covariance = empirical_covariance(target.kp, shrinkage=options.shrinkage,
                                                 source=target.name)
        if options.joint_covariance:
            target.joint_covariance = empirical_covariance(
                target.kp, joint=True, shrinkage=options.shrinkage, source=target.name)
    return target


def extract_filters(targets, calibrators, options=None, *, progress=False):
    """Target and calibrator files in several JWST filters as one calibrated product.

    Each filter is extracted with its own kernel (`kpifs.extraction.filters`) and a
    window of one angular radius, calibrated by the same filter's calibrator
    frames, and the filters are stacked as the channels of one product.

    Parameters
    ----------
    targets : list of str
        The target's files, in two or more filters.
    calibrators : list of list of str
        Each calibrator star's files (in the same filters).
    options : `ExtractOptions`

    Returns
    -------
    `~kpifs.data.KernelPhaseData`
        One frame, one channel per filter (by wavelength), calibrated.

    Examples
    --------
    >>> import tempfile, warnings, astropy.units as u
    >>> from kpifs.io import write_observation
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> from kpifs.workflow import ExtractOptions, extract_filters
    >>> d, files = tempfile.mkdtemp(), {"t": [], "c": []}
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
    """
    options = options or ExtractOptions()
    order, groups, cal_groups, scales = _filters.filter_groups(
        list(targets), list(calibrators), pixscale=options.pixscale)
    per_filter = _filters.filter_options(options, groups, order, scales)
    km = kernel_model_for(options, _filters.INSTRUMENT.name,
                          _filters.file_headers(groups[order[0]][0])[0])
    model, own = _filters.filter_models(km, order, groups, scales,
                                        filter_kernels=options.filter_kernels)
    radius = _filters.filter_window_radius(order, scales, options.window_radius)
    products = []
    for f in order:
        opts = dataclasses.replace(per_filter[f], window_radius=radius[f])
        t = extract_observation(groups[f], opts, model=own[f], progress=progress)
        cals = [extract_observation(cg[f], opts, model=own[f], progress=progress)
                for cg in cal_groups]
        products.append(calibrate_observation(t, cals, opts))
    kpd = _filters.stack_filters(products, order, kernel_model=model)
    # the options as given (each filter's window radius follows from them) and every file
    kpd.header["KPXOPTS"] = (json.dumps(options_record(options), sort_keys=True),
                             "kpifs extraction options")
    kpd.header["KPINHASH"] = (combined_digest([inputs_digest(list(targets))] + [
        inputs_digest(c) for c in calibrators]), "digest of the input files")
    return kpd


def reduce_observation(target, calibrators=(), options=None, *, progress=False):
    """The product ``kpifs extract TARGET [--calibrator CAL ...]`` writes, every option
    included: the one place where extraction meets calibration.

    - JWST files of the target in two filters or more: `extract_filters`;
    - else the target's kernel phases, calibrated by *calibrators* when given
      (`calibrate_observation`), or alone (with the frames' covariance when
      ``options.covariance`` asks for it);
    - ``options.angular_differential``: the product of a rotating sequence
      searched by what turns with the sky (`kpifs.calibration.adi.angular_differential`),
      with or without calibrators;
    - ``options.spectral_differential``: the product searched by the channel
      combinations free of the static residual's profiles
      (`kpifs.calibration.spectral_diff.spectral_differential`), with or without
      calibrators.

    Parameters
    ----------
    target : str or list of str
        The target's cube files.
    calibrators : list of list of str
        Cube files of each calibrator star (may be empty).
    options : `ExtractOptions`

    Returns
    -------
    product : `~kpifs.data.KernelPhaseData`
    stars : list of `~kpifs.data.KernelPhaseData`
        The target's and each calibrator's own kernel phases (empty for JWST
        filters, whose stars are per filter).

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.io import write_observation
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> from kpifs.workflow import ExtractOptions, reduce_observation
    >>> files = write_observation(simulate_scene("paper", n_frames=40, npup=32),
    ...                           tempfile.mkdtemp())
    >>> kpd, stars = reduce_observation(files["target"], [files["calibrator"]],
    ...                                 ExtractOptions(step="1.2m"))
    >>> kpd.meta["calibrated"], len(stars)
    (True, 2)
    """
    options = options or ExtractOptions()
    target = [str(target)] if isinstance(target, (str, Path)) else [str(f) for f in target]
    calibrators = [[str(f) for f in files] for files in calibrators]
    if len(_filters.jwst_filters(target)) > 1:     # JWST filters as the channels of one product
        if options.spectral_differential:
            raise KpifsError(f"{target[0]}: --spectral-differential needs the channels of "
                             f"one IFS cube; JWST filters are searched with a calibrator")
        if options.angular_differential:
            raise KpifsError(f"{target[0]}: --angular-differential needs one rotating "
                             f"sequence; JWST files in several filters make one calibrated "
                             f"frame per filter (reduce each filter on its own)")
        return extract_filters(target, calibrators, options, progress=progress), []
    tkp = extract_observation(target, options, progress=progress)
    cals = [extract_observation(files, calibrator_options(options), model=tkp.kernel_model,
                                progress=progress) for files in calibrators]
    kpd = calibrate_observation(tkp, cals, options)
    if options.spectral_differential and options.angular_differential and not cals:
        # ASDI (issue 39): the frames' spectral-differential product and their time blocks
        target_blocks(tkp)                         # refused before the work if they do not turn
        return angular_differential(tkp, _spectral_step(tkp, None, options, target)), [tkp]
    if options.angular_differential:               # issue 29
        kpd = angular_differential(tkp, kpd if cals else None)
    if options.spectral_differential:              # issue 39
        kpd = _spectral_step(tkp, kpd if (cals or options.angular_differential) else None,
                             options, target)
    return kpd, [tkp] + cals


def _spectral_step(target, product, options, files=None):
    """`~kpifs.calibration.spectral_diff.spectral_differential` with the options' basis
    (the static residual imaged through the target's pupil when the basis needs it);
    with no calibrator, the search's static term, and the target's cube *files* give
    it one more group, the pixels the extraction filled in every frame
    (`_filled_group`)."""
    basis = options.spectral_differential
    basis = "static" if basis is True else basis
    if basis not in SDK_BASES:
        raise KpifsError(f"spectral_differential must be one of {SDK_BASES}, got {basis!r}")
    if target.n_wave < 2:
        raise KpifsError(f"{target.name}: --spectral-differential needs several channels "
                         f"(an IFS cube); these data have one channel")
    rows = None
    if basis in ("static", "both"):
        rows = static_residual_rows(target.kernel_model, target.wavelengths, target.pixscale,
                                    window=target.window)
    out = spectral_differential(target, product, basis=basis, static_rows=rows,
                                shrinkage=options.shrinkage)
    if product is None:
        # the search's static term (no calibrator), imaged once with the product, not at
        # every search of it (`kpifs.detect.sdk.static_term_rows`)
        rows, sizes = _sdk.static_term_rows(target)
        filled, pixels = _filled_group(files, target, options)
        if filled is not None and filled.shape[1:] == rows.shape[1:]:
            rows, sizes = np.concatenate([rows, filled]), sizes + [len(filled)]
            out.spectral["static_filled"] = len(pixels)
        out.spectral["static_rows"], out.spectral["static_groups"] = rows, sizes
    return out


def _filled_group(files, target, options):
    """The static term's group of the pixels bad in every frame of the target's cube
    *files* (non-finite or masked, what the extraction filled) within the window's
    radius of the star (beyond it the window weighs less than 1/e and the halo is
    smooth enough for the fill): their kernel-phase responses, one row per pixel and
    channel (`~kpifs.extraction.filled.filled_pixel_rows`, issue 39); (None, []) with
    none, no files, or ``bad_pixels='exclude'`` (nothing filled)."""
    if not files or options.bad_pixels != "fill":
        return None, []
    with read_cube(files, instrument=options.instrument, dq_bits=options.dq_bits,
                   wavelengths=parse_wavelengths(options.wavelengths, source="--wavelengths"),
                   pixscale=_pixscale(options),
                   pa_given=parse_angles(options.pa, source="--pa") is not None) as cube:
        mask = cube.mask if options.mask is None else options.mask
        frames = np.setdiff1d(np.arange(cube.shape[0]), target.meta.get("dropped_frames", []))
        channels = np.setdiff1d(np.arange(cube.shape[1]),
                                target.meta.get("dropped_channels", []))
        rows, pixels = filled_pixel_rows(
            cube.data, target.kernel_model, wavelengths=target.wavelengths,
            pixscale=target.pixscale, window=target.window, mask=mask, frames=frames,
            channels=channels, centroid=options.centroid, on_nyquist=options.on_nyquist)
    log.info("%s: %d pixel(s) bad in every frame within the window's radius: %d row(s) "
             "of the static term's filled-pixel group", target.name, len(pixels),
             0 if rows is None else len(rows))
    return rows, pixels


def _mas(value, name):
    return None if value is None else to_quantity(value, u.mas, name=name)


def detect_observation(kpd, options=None, *, calibrators=(), progress=False):
    """Search kernel-phase data for companions with *options* (calibrating first if given
    *calibrators*).

    Returns a `~kpifs.data.DetectionResult`.

    Examples
    --------
    >>> from kpifs.detect.pipeline import _example_result
    >>> _example_result().test                           # made by detect()
    'B'
    """
    detect, default_grid = _pipeline.detect, _pipeline.default_grid
    options = (options or DetectOptions()).validate()
    if calibrators:
        kpd = calibrate_observation(kpd, calibrators, ExtractOptions(shrinkage=options.shrinkage))
    _checks.check_kernel_phase_data(kpd)
    _checks.check_covariance(kpd)
    if options.frame == "sky":
        _sky.search_frame(kpd, "sky")        # refused now, not after the search's set-up
    grid = None
    if options.max_sep is not None or options.grid_step is not None or \
            options.min_sep is not None:
        _checks.check_grid_memory(kpd, step=_mas(options.grid_step, "grid step"),
                                  max_sep=_mas(options.max_sep, "maximum separation"))
        grid = default_grid(kpd, step=_mas(options.grid_step, "grid step"),
                            max_sep=_mas(options.max_sep, "maximum separation"),
                            min_sep=_mas(options.min_sep, "minimum separation"),
                            frame=_sky.search_frame(kpd, options.frame))
    try:
        result = detect(kpd, test=options.test, pfa=options.pfa, pd=options.pd, grid=grid,
                        spectrum=_spectral.parse_spectrum(options.spectrum, kpd.n_wave),
                        basis=options.basis, n_draws=options.draws, seed=options.seed,
                        shrinkage=options.shrinkage, fit=options.fit,
                        max_candidates=options.max_candidates, static=options.static,
                        allow_uncalibrated=options.allow_uncalibrated, frame=options.frame,
                        null=options.null, blocks=options.blocks, aliased=options.aliased,
                        progress=progress)
    except KpifsError as exc:             # every message names the file searched
        if kpd.name in str(exc):
            raise
        raise KpifsError(f"{kpd.name}: {exc}") from None
    record = options_record(options)
    result.header["KPDOPTS"] = (json.dumps(record, sort_keys=True), "kpifs detection options")
    result.header["KPHASH"] = (products_digest(json.loads(kpd.header.get("KPXOPTS", "null")),
                                               kpd.header.get("KPINHASH", kpd.name), record),
                               "digest of the options and inputs")
    return result


def process_observation(target, calibrators, outdir, *, extract_options=None,
                        detect_options=None, overwrite=False, keep_stars=False,
                        progress=False):
    """Extract, calibrate and search one observation; write its products in *outdir*.

    Writes ``calibrated_kp.fits`` (as ``kpifs extract TARGET --calibrator CAL``
    would, through `reduce_observation`: JWST filters and the
    angular-differential mode included) and ``detection.fits`` (as ``kpifs
    detect calibrated_kp.fits`` would: from the file just written); with
    *keep_stars* also ``target_kp.fits`` and ``calibrator_kp.fits``
    (``calibrator<i>_kp.fits`` for several calibrators; none for JWST filters).

    Parameters
    ----------
    target : list of str
        The target's cube files.
    calibrators : list of list of str
        Cube files of each calibrator star (none only with
        ``extract_options.angular_differential``).
    outdir : str or Path
    extract_options, detect_options : `ExtractOptions`, `DetectOptions`
    overwrite : bool
        Replace existing products.

    Returns
    -------
    dict
        ``calibrated`` (`~kpifs.data.KernelPhaseData` as read back),
        ``result`` (`~kpifs.data.DetectionResult`) and ``paths``.

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.io import write_observation
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> from kpifs.workflow import DetectOptions, ExtractOptions, process_observation
    >>> tmp = tempfile.TemporaryDirectory()
    >>> d = tmp.name
    >>> files = write_observation(simulate_scene("paper", n_frames=100, npup=32), d)
    >>> out = process_observation(files["target"], [files["calibrator"]], d,
    ...                           extract_options=ExtractOptions(step="1.2m"),
    ...                           detect_options=DetectOptions(draws=1000, pfa=0.01))
    >>> sorted(p.name for p in out["paths"].values())
    ['calibrated_kp.fits', 'detection.fits']
    >>> tmp.cleanup()
    """
    xo = extract_options or ExtractOptions()
    do = (detect_options or DetectOptions()).validate()
    outdir = check_output_dir(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    target = [str(f) for f in target]
    calibrators = [[str(f) for f in files] for files in calibrators]
    _checks.check_inputs(target, calibrators)
    if not calibrators and not xo.angular_differential and not xo.spectral_differential:
        raise KpifsError(f"{target[0] if target else outdir}: no calibrator (only an "
                         f"angular- or spectral-differential reduction searches a target "
                         f"alone)")
    paths = {"calibrated": outdir / "calibrated_kp.fits", "detection": outdir / "detection.fits"}
    names = ["target_kp.fits"] + (["calibrator_kp.fits"] if len(calibrators) == 1 else
                                  [f"calibrator{i}_kp.fits" for i in
                                   range(1, len(calibrators) + 1)])
    star_paths = [outdir / n for n in names] if keep_stars else []
    for p in list(paths.values()) + star_paths:   # refuse before any work
        check_output_path(p, overwrite=overwrite)
    cal, stars = reduce_observation(target, calibrators, xo, progress=progress)
    star_paths = star_paths[:len(stars)]           # JWST filters: no single-star products
    for kpd, files, p in zip(stars, [target] + calibrators, star_paths):
        kpd.write(p, overwrite=overwrite, inputs=files)
    cal.write(paths["calibrated"], overwrite=overwrite,
              inputs=target + [f for files in calibrators for f in files])
    # detection from the file, as `kpifs detect` does, so both give the same products
    cal = KernelPhaseData.read(paths["calibrated"])
    result = detect_observation(cal, do, progress=progress)
    result.write(paths["detection"], inputs=[str(paths["calibrated"])], overwrite=overwrite)
    paths.update(zip(("target",) + tuple(f"calibrator{i}" for i in range(len(calibrators))),
                     star_paths))
    return {"calibrated": cal, "result": result, "paths": paths}
