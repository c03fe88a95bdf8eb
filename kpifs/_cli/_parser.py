"""The ``kpifs`` argument parser: options only, no science, nothing heavy imported.

Each subcommand names the module of `kpifs._cli` that runs it; the shared
option groups (cubes, pupil model, extraction, search) are defined once here
and turned into `~kpifs.workflow.ExtractOptions` / `~kpifs.workflow.DetectOptions`
by `kpifs._cli._options`. One vocabulary throughout: ``--step`` is the pupil
model's grid step (m), ``--grid-step`` the search grid's (mas); a number
without a unit is in the unit the option's help names. Every option's help
says its default.
"""
import argparse
import re

from .._defaults import DETECT, EXTRACT
from .._meta import VERSION
from ._epilogs import (EPILOG_BATCH, EPILOG_DETECT, EPILOG_EXTRACT, EPILOG_INFO,
                       EPILOG_INJECT, EPILOG_KERNEL, EPILOG_MODELCHECK, EPILOG_SIMULATE)

__all__ = ["build_parser", "EXIT_STATUS"]

EXIT_STATUS = ("exit status: 0 success; 1 batch: some entries failed (see summary.ecsv); "
               "2 bad input or usage (a one-line message naming the file and the problem); "
               "3 internal error (--debug shows the traceback); 130 interrupted (Ctrl-C)")

# instruments, their simulator layouts and presets are not listed here: the registry
# (`kpifs.io.instruments`) checks them when the command runs, and `kpifs info
# --instruments` lists them (the parser imports nothing heavy)
ROC_PRESETS = ("paper", "charis", "sphere", "sphere-sam")


def _cube_options(p):
    g = p.add_argument_group("input cubes")
    g.add_argument("--instrument", default=EXTRACT["instrument"], metavar="NAME",
                   help="file format: auto (the default: recognised from the header) or an "
                        "instrument's name (kpifs info --instruments lists them; generic: "
                        "any FITS cube)")
    g.add_argument("--wavelengths", help="list (1.52um,1.60um) or file (text/FITS, um or nm); "
                                         "default: from the file's header")
    g.add_argument("--pixscale", help="pixel scale, mas if no unit, e.g. 10.42mas; default: "
                                      "from the header or the instrument's (kpifs info "
                                      "--instruments)")
    g.add_argument("--dq-bits", metavar="FLAGS",
                   help="JWST: DQ flags read as bad pixels besides DO_NOT_USE, by name or "
                        "value, e.g. SATURATED,JUMP_DET or 6 (default: DO_NOT_USE only)")


def _pupil_options(p, *, model_files=True):
    g = p.add_argument_group("pupil model")
    files = " or a kernel-model FITS" if model_files else ""
    g.add_argument("--pupil", default=EXTRACT["pupil"],
                   help="telescope: subaru (aliases scexao, charis), vlt (alias sphere), "
                        "pharo, keck, jwst (alias nircam_clear), niriss_clearp, gpi (alias "
                        "gemini_south); a mask: niriss_nrm, sphere_sam7, gpi_nrm ('-' for "
                        "'_' accepted); or a pupil image FITS (pixel size in PUPSCALE or "
                        f"--pupil-scale){files}. Circular and annular apertures (a diameter "
                        "and a central obstruction) are built from Python "
                        "(kpifs.make_pupil('annular', diameter=..., obstruction=...)); "
                        "default: the instrument's telescope, subaru for plain cubes")
    g.add_argument("--pupil-scale", help="pixel size of a pupil image, m if no unit, e.g. "
                                         "0.02m (default: its PUPSCALE keyword)")
    g.add_argument("--step", default=EXTRACT["step"],
                   help="pupil model's grid step, m if no unit (default: the pupil's, 0.38m "
                        "for subaru and vlt, 0.16m for pharo)")
    g.add_argument("--offset", default=EXTRACT["offset"],
                   help="grid offset x,y, m if no unit (default 0.17m,0.11m; 0,0 gives a "
                        "centro-symmetric model)")
    g.add_argument("--min-transmission", type=float, default=EXTRACT["min_transmission"],
                   help="keep cells at least this much inside the pupil (default 0.2 for a "
                        "grey model, 0.9 for a binary one)")
    g.add_argument("--min-redundancy", type=float, default=EXTRACT["min_redundancy"],
                   help="grey model: leave out uv points of smaller redundancy (default 0.5)")
    kind = g.add_mutually_exclusive_group()
    kind.add_argument("--grey", dest="grey", action="store_const", const=True,
                      default=EXTRACT["grey"],
                      help="keep fractional transmissions (the default)")
    kind.add_argument("--binary", dest="grey", action="store_const", const=False,
                      help="binary model: every kept cell counts 1")
    g.add_argument("--rotation", default=EXTRACT["rotation"],
                   help="turn of the whole model to the pupil on the detector, deg if no "
                        "unit, e.g. -2deg (kpifs model-check measures it; default 0)")
    g.add_argument("--hexagonal", action="store_true", help="hexagonal grid (default square)")


def _extraction_options(p):
    g = p.add_argument_group("extraction")
    g.add_argument("--window", "--window-size", dest="window_size", type=int,
                   help="cut-out size in pixels (default: the image size, at most 64)")
    g.add_argument("--window-radius", type=float,
                   help="super-Gaussian radius in pixels (default 0.8 x half the cut-out)")
    g.add_argument("--centroid", default=EXTRACT["centroid"],
                   choices=("com", "peak", "quadratic", "2dg"),
                   help="star-centre method (default %(default)s)")
    g.add_argument("--bad-pixels", default=EXTRACT["bad_pixels"], choices=("fill", "exclude"),
                   help="interpolate bad pixels or leave them out (default %(default)s)")
    g.add_argument("--bad-frames", default=EXTRACT["bad_frames"], choices=("drop", "fail"),
                   help="frames empty, mostly NaN or without flux: drop them with a warning "
                        "or refuse the cube (default %(default)s)")
    g.add_argument("--nyquist", default=EXTRACT["on_nyquist"], choices=("drop", "raise", "own"),
                   help="uv points beyond some channel's Nyquist limit: drop them for every "
                        "channel (warn), refuse, or drop each for the channels that do not "
                        "sample it only (own; default %(default)s)")
    g.add_argument("--precision", default=EXTRACT["precision"], choices=("double", "single"),
                   help="Fourier products in double or single precision (~2x faster, ~1e-6 "
                        "rad added to the kernel phases; default %(default)s)")
    g = p.add_argument_group("covariance")
    g.add_argument("--shrinkage", default=EXTRACT["shrinkage"],
                   choices=("auto", "ledoit-wolf", "none"),
                   help="covariance estimator (default auto: Ledoit-Wolf when frames are too "
                        "few)")
    g.add_argument("--joint-covariance", action="store_true",
                   help="also estimate the joint covariance across channels")
    g.add_argument("--covariance", action="store_true",
                   help="store the frames' covariance even without a calibrator")
    g.add_argument("--pixel-noise", default=EXTRACT["pixel_noise"], choices=("auto", "none"),
                   help="auto: with per-pixel noise (JWST ERR), the kernel phases beyond the "
                        "error model's modes carry it, scaled to the calibrated data; none: "
                        "the modes only (default %(default)s)")
    g.add_argument("--filter-kernels", default=EXTRACT["filter_kernels"], choices=("own", "common"),
                   help="JWST filters as channels: each filter the kernel of the uv points "
                        "it samples, or all the kernel of those every filter samples "
                        "(default %(default)s)")


def _search_options(p):
    g = p.add_argument_group("search")
    # the tests are the registry's (kpifs.detect.statistics), checked with the options:
    # the parser imports nothing heavy, and spells no test
    g.add_argument("--test", default=DETECT["test"], metavar="TEST",
                   help="auto, or the name of a registered detection test (an unknown name "
                        "is answered with the list; docs/user/choosing_test.rst describes "
                        "each). auto: the spectral-model test when --basis has fewer "
                        "dimensions than the channels, else the binary GLR test "
                        "(default %(default)s)")
    g.add_argument("--pfa", type=float, default=DETECT["pfa"],
                   help="global false-alarm probability of the search (default %(default)s)")
    g.add_argument("--pd", type=float, default=DETECT["pd"],
                   help="detection probability of the limits (default %(default)s)")
    g.add_argument("--frame", default=DETECT["frame"], choices=("auto", "sky", "detector"),
                   help="search and map on the sky (dRA East-positive, dDec; the model turned "
                        "by each frame's detector angle; celestial WCS) or the detector "
                        "(default auto: the sky when every frame's angle is known)")
    g.add_argument("--null", default=DETECT["null"],
                   choices=("auto", "gaussian", "empirical", "both"),
                   help="null of the grid maximum: Gaussian Monte Carlo of the error model, "
                        "sign flips of the stars' time blocks (empirical), or the more "
                        "conservative of the two (both; default auto: both when the data carry "
                        "time blocks)")
    g.add_argument("--max-sep", help="largest separation searched, mas if no unit, e.g. "
                                     "200mas (default: the extraction window's radius, within "
                                     "the pupil grid's aliasing limit)")
    g.add_argument("--min-sep", help="smallest separation searched, mas if no unit, e.g. "
                                     "20mas (default: half a resolution element)")
    g.add_argument("--grid-step", dest="grid_step",
                   help="search grid step, mas if no unit, e.g. 5mas (default lambda/4D)")
    g.add_argument("--spectrum", help="companion spectrum shape: flat, comma list or file "
                                      "(default flat)")
    g.add_argument("--basis", help="spectral model of --test S: smooth:R (polynomial of rank "
                                   "R in wavelength), blackbody, or a file of template "
                                   "spectra (ECSV with a wavelength column, FITS) (default "
                                   "smooth:3)")
    g.add_argument("--draws", type=int, default=DETECT["draws"],
                   help="Monte-Carlo draws calibrating the grid search (default %(default)s)")
    g.add_argument("--seed", type=int, default=DETECT["seed"],
                   help="seed of those draws (default %(default)s)")


def _product_options(p):
    """How a product's search treats what its reduction left (detect and batch)."""
    g = p.add_argument_group("search of the product")
    g.add_argument("--allow-uncalibrated", action="store_true",
                   help="search data that no calibrator was subtracted from (refused "
                        "otherwise: aberrations look like companions)")
    g.add_argument("--blocks", default=DETECT["blocks"],
                   choices=("auto", "rotation", "angular-differential", "mean"),
                   help="a rotating sequence's time blocks: the calibrated mean and what "
                        "turns (rotation), what turns (angular-differential; with a "
                        "calibrator, and the mean at its own scale), or the "
                        "mean with the model averaged over the angles (mean); default: the "
                        "data's own (%(default)s)")
    g.add_argument("--aliased", default=DETECT["aliased"], choices=("keep", "exclude"),
                   help="channels whose pixels alias some of their uv points (their "
                        "contrasts are flagged): searched like the others (keep, the default) "
                        "or left out of the search, limits and fits (exclude)")
    g.add_argument("--static", default=DETECT["static"], choices=("auto", "none"),
                   help="single-channel data with no calibrator: add the kernel-phase "
                        "residual of static aberrations, imaged through the pupil and fitted "
                        "to the data, to their covariance (auto, the default) or not (none)")


def _reduction_options(p, *, pa_help):
    """What is made of a target's frames besides extraction (extract and batch)."""
    p.add_argument("--angular-differential", action="store_true",
                   help="keep the time blocks of a rotating sequence and search what "
                        "turns with the sky (what stays on the detector removed; with "
                        "--calibrator also the calibrated mean, scaled by its own reduced "
                        "chi-square; refused when the angles do not turn)")
    p.add_argument("--spectral-differential", nargs="?", const="static",
                   default=EXTRACT["spectral_differential"], metavar="BASIS",
                   choices=("poly", "static", "both"),
                   help="search only the channel combinations free of what varies like a "
                        "static aberration across the channels, kernel phase by kernel "
                        "phase: the leading channel profiles of the static residual imaged "
                        "through the pupil (static, the default), polynomials in 1/lambda "
                        "(poly) or both; no calibrator needed (with one: extra protection), "
                        "combined with --angular-differential when given; refused for "
                        "single-channel data")
    p.add_argument("--pa", metavar="DEG|LIST|FILE",
                   help="detector position angle of the target's frames (deg, East of North "
                        "of the detector +y axis): one value, a comma list with one per "
                        "frame, or a text/FITS file" + pa_help + " (default: the "
                        "instrument's, e.g. CHARIS PARANG+113; kpifs info --instruments lists "
                        "them; generic cubes: DETPA or 0)")


def _output(p, help_text="output FITS file", *, required=True, default=None):
    p.add_argument("-o", "--output", required=required, default=default, help=help_text)
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")


def _kernel(command):
    p = command("kernel", "build a kernel model and save it", EPILOG_KERNEL)
    _pupil_options(p)
    _output(p, "output kernel-model FITS file (required)")


def _extract(command):
    p = command("extract", "kernel phases of IFS cubes", EPILOG_EXTRACT)
    p.add_argument("cubes", nargs="+", metavar="CUBE",
                   help="FITS cube(s) of the target; several files are more frames")
    p.add_argument("--calibrator", action="append", nargs="+", metavar="CUBE",
                   help="cube(s) of a calibrator star; repeat the option for several "
                        "calibrators, whose mean is subtracted (default: none, kernel phases "
                        "of the target alone)")
    _cube_options(p)
    _reduction_options(p, pa_help="")
    _pupil_options(p)
    _extraction_options(p)
    _output(p, "output KPFITS file (required)")


def _modelcheck(command):
    p = command("model-check", "fit the pupil model to a star's frames; compare models",
                EPILOG_MODELCHECK, module="modelcheck")
    p.add_argument("cubes", nargs="+", metavar="CUBE",
                   help="FITS cube(s) of a star without a known companion")
    p.add_argument("--calibrator", nargs="+", metavar="CUBE",
                   help="cube(s) of a second such star (default: compare the two halves "
                        "of CUBE's frames)")
    _cube_options(p)
    p.add_argument("--pupil", default=None,
                   help="telescope (subaru, vlt, pharo; aliases scexao, charis, sphere) or "
                        "pupil image FITS (default: the instrument's telescope, subaru for "
                        "plain cubes)")
    p.add_argument("--pupil-scale", help="pixel size of a pupil image, m if no unit, e.g. "
                                         "0.02m (default: its PUPSCALE keyword)")
    p.add_argument("--rotations", default="-6,-4.5,-3,-1.5,0,1.5,3,4.5,6",
                   help="coarse grid of model turns, deg (default -6 to 6 by 1.5)")
    p.add_argument("--scales", default="0.97,0.98,0.99,1,1.01,1.02,1.03",
                   help="coarse grid of pixel-scale factors (default 0.97 to 1.03 by 0.01)")
    p.add_argument("--cuts", default="0.05,0.1,0.2,0.3,0.5",
                   help="transmission cuts of the grey models compared, besides the binary "
                        "model (default %(default)s)")
    p.add_argument("--steps", help="grid steps compared, m (default: the pupil's only)")
    p.add_argument("--window", "--window-size", dest="window_size", type=int,
                   help="cut-out size in pixels (default: the image size, at most 64)")
    p.add_argument("--window-radius", type=float,
                   help="super-Gaussian radius in pixels (default 0.8 x half the cut-out)")
    _output(p, "write the table of models tried (ECSV; default: printed only)",
            required=False)


def _inject(command):
    p = command("inject", "inject companions into cubes; injection contrast curve",
                EPILOG_INJECT)
    p.add_argument("cubes", nargs="+", metavar="CUBE", help="FITS cube(s) of the target")
    p.add_argument("--position", help="companion offset x,y (detector) or dRA,dDec (--sky), "
                                      "mas if no unit, e.g. 150,-80mas (required without "
                                      "--curve)")
    p.add_argument("--sky", action="store_true",
                   help="--position is on the sky (East positive), turned by each frame's "
                        "detector position angle (default: on the detector)")
    p.add_argument("--contrast", help="contrast, or one per channel (comma list; required "
                                      "without --curve)")
    p.add_argument("--pa", metavar="DEG|LIST|FILE", help="detector position angles (see "
                                                         "extract; default: the instrument's)")
    p.add_argument("--curve", action="store_true",
                   help="measure the injection contrast curve instead (needs --calibrator)")
    p.add_argument("--calibrator", action="append", nargs="+", metavar="CUBE",
                   help="with --curve: cube(s) of a calibrator, repeat for several "
                        "(required with --curve)")
    p.add_argument("--separations", default="100,200,400mas",
                   help="with --curve: separations, mas if no unit (default %(default)s)")
    p.add_argument("--contrasts", default=None,
                   help="with --curve: a fixed contrast ladder, e.g. 1e-3,2e-3,5e-3 (default: "
                        "one that brackets the limit by itself, from 0.5 to 2 times the "
                        "analytic limit, extended while every step or none is found)")
    p.add_argument("--angles", type=int, default=4,
                   help="with --curve: position angles per contrast step (default %(default)s)")
    p.add_argument("--pfa", type=float, default=DETECT["pfa"],
                   help="global false-alarm probability of the detections (default %(default)s)")
    p.add_argument("--draws", type=int, default=DETECT["draws"],
                   help="Monte-Carlo draws calibrating the analytic limits' search (default "
                        "%(default)s)")
    p.add_argument("--injection-draws", type=int, default=1000,
                   help="with --curve: Monte-Carlo draws calibrating each injection's search "
                        "(default %(default)s)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the angles and of the draws (default %(default)s)")
    p.add_argument("--plots", metavar="DIR",
                   help="with --curve: write the figure there (default: no figure)")
    _cube_options(p)
    _pupil_options(p)
    _extraction_options(p)
    _output(p, "output FITS file: the injected cube, or the curve with --curve (required)")


def _info(command):
    p = command("info", "describe a cube, KPFITS, model, detection or injection file",
                EPILOG_INFO)
    p.add_argument("files", nargs="*", metavar="FILE", help="FITS file(s) to describe")
    p.add_argument("--instruments", action="store_true",
                   help="list the instruments kpifs reads: how each is recognised, its "
                        "pupil, pixel scale, angles and simulator layout")
    _cube_options(p)
    _pupil_options(p)


def _simulate(command):
    p = command("simulate", "simulate a target and a calibrator", EPILOG_SIMULATE)
    p.add_argument("--preset", default="paper", metavar="NAME",
                   help="instrument and scene to start from, e.g. paper, charis, sphere, "
                        "niriss, gpi (see below; an unknown name lists them; default "
                        "%(default)s)")
    p.add_argument("--layout", default="plain", metavar="NAME",
                   help="file layout: plain (one 4-D cube per star) or an instrument's "
                        "pipeline files, e.g. charis (kpifs info --instruments lists them; "
                        "default %(default)s)")
    p.add_argument("--frames", type=int,
                   help="number of frames per star (default: the preset's)")
    p.add_argument("--contrasts", help="per-channel contrasts, comma separated (default: the "
                                       "preset's)")
    p.add_argument("--separation", help="companion separation, mas if no unit, e.g. 100mas "
                                        "(default: the preset's)")
    p.add_argument("--pa", help="companion angle from +x towards +y, deg if no unit, e.g. "
                                "36.87deg; niriss, nircam, gpi: East of North on the sky "
                                "(default: the preset's)")
    p.add_argument("--wavefront", help="rms wavefront error, nm if no unit, e.g. 100nm "
                                       "(default: the preset's)")
    p.add_argument("--shape", type=int, help="image side in pixels (default: the preset's)")
    p.add_argument("--exptime", help="exposure time per frame, s if no unit, e.g. 1s "
                                     "(default 0.1s)")
    g = p.add_argument_group("quasi-static aberrations (as on sky; default none)")
    g.add_argument("--drift", help="rms of aberrations drifting from frame to frame, nm if "
                                   "no unit, e.g. 30nm (default 0)")
    g.add_argument("--drift-time", type=float,
                   help="their correlation time in frames (default 10)")
    g.add_argument("--static", help="rms of static aberrations common to both stars, nm if no "
                                    "unit (default 0)")
    g.add_argument("--static-diff", help="rms of static aberrations of the calibrator only "
                                         "(a calibration residual), nm if no unit, e.g. 10nm "
                                         "(default 0)")
    g.add_argument("--typical-static", action="store_true",
                   help="a static aberration typical of the instruments, for sequences with "
                        "no calibrator: 50 nm common to both stars at low order, 15 nm of "
                        "the target's own, 10 nm drifting (the options above override each)")
    g = p.add_argument_group("field rotation (pupil tracking: the sky turns, the aberrations "
                             "stay on the detector; default: the preset's angles)")
    g.add_argument("--rotation", help="the detector angle turns by this much over the "
                                      "sequence, deg if no unit, e.g. 40deg (default: none)")
    g.add_argument("--hour-angle", help="or: the star's hour angles at the start and the end, "
                                        "hours, e.g. --hour-angle=-1,1 (default: none)")
    g.add_argument("--declination", help="the star's declination, deg if no unit (with "
                                         "--hour-angle; default: none)")
    g.add_argument("--site", help="the observatory: maunakea, paranal, pachon, palomar, or a "
                                  "latitude in deg (with --hour-angle; default: the "
                                  "instrument's)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default %(default)s)")
    _output(p, "output directory (required)")


def _detect(command):
    p = command("detect", "search kernel phases for companions", EPILOG_DETECT)
    p.add_argument("kp", metavar="KP.fits", nargs="+",
                   help="kernel-phase data (KPFITS, from kpifs extract) or closure phases "
                        "(OIFITS; several OIFITS files of one target are searched together)")
    p.add_argument("--calibrator", nargs="+", metavar="CALIBRATOR_KP.fits",
                   help="kernel phases of calibrator star(s), if KP.fits is not calibrated "
                        "(default: none)")
    _search_options(p)
    # --step was the search grid here; everywhere else it is the pupil grid
    p.add_argument("--step", dest="deprecated_step", help=argparse.SUPPRESS)
    p.add_argument("--shrinkage", default=DETECT["shrinkage"],
                   choices=("auto", "ledoit-wolf", "none"),
                   help="covariance estimator when calibrating here (default %(default)s)")
    _product_options(p)
    p.add_argument("--plots", metavar="DIR", help="write PNG figures there (default: none)")
    _output(p, "output detection FITS file (required)")


def _roc(command):
    p = command("roc", "the seed paper's ROC experiment",
                "example:\n  kpifs roc --preset paper --frames 300 -o roc")
    p.add_argument("--preset", default="paper", choices=ROC_PRESETS,
                   help="scene simulated (default %(default)s)")
    p.add_argument("--frames", type=int, default=1000,
                   help="calibrator frames (default %(default)s)")
    p.add_argument("--draws", type=int, default=30000,
                   help="Monte-Carlo draws (default %(default)s)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the simulation and the draws (default %(default)s)")
    _output(p, "output directory (required)")


def _batch(command):
    p = command("batch", "reprocess many observations on Dask", EPILOG_BATCH)
    p.add_argument("manifest", nargs="*", metavar="MANIFEST",
                   help="CSV/ECSV with columns name, target, calibrator (';' separates files, "
                        "'|' calibrator stars; globs allowed)")
    p.add_argument("--glob", help="one entry per matching target file (default: the entries "
                                  "of the manifest)")
    p.add_argument("--calibrator", help="with --glob: calibrator file pattern for every entry "
                                        "(default: none)")
    p.add_argument("--scheduler", help="address of a running Dask scheduler (default: a local "
                                       "cluster)")
    p.add_argument("--workers", type=int, default=2,
                   help="local-cluster workers (default %(default)s)")
    _cube_options(p)
    _reduction_options(p, pa_help=", for every entry (a manifest's pa column sets one "
                       "entry's)")
    _pupil_options(p)
    _extraction_options(p)
    _search_options(p)
    _product_options(p)
    p.add_argument("-o", "--output", required=True, help="output directory (required)")
    p.add_argument("--overwrite", action="store_true",
                   help="redo entries already done (default: skip them, resuming a run)")


def _demo(command):
    p = command("demo", "run the whole chain on simulated data",
                "example:\n  kpifs demo -o demo_output")
    p.add_argument("--frames", type=int, default=200,
                   help="exposures per star (default %(default)s)")
    p.add_argument("--draws", type=int, default=DETECT["draws"],
                   help="Monte-Carlo draws calibrating the search (default %(default)s)")
    p.add_argument("--seed", type=int, default=1,
                   help="seed of the simulation and of the draws (default %(default)s)")
    p.add_argument("--keep-inputs", action="store_true",
                   help="keep the simulated CHARIS cubes in OUTPUT/charis (about 300 MB; "
                        "default: made in a temporary folder and removed)")
    _output(p, "output directory (default %(default)s)", required=False, default="kpifs_demo")


#: The commands, in the order ``kpifs --help`` lists them.
COMMANDS = (_kernel, _extract, _modelcheck, _inject, _info, _simulate, _detect, _roc, _batch,
            _demo)


#: A value that starts with a minus sign and a digit but is no plain number (a list such
#: as -60,40 or -3,-2,-1; a number with a unit, -2deg): no kpifs option looks like that.
_NEGATIVE_VALUE = re.compile(r"^-(\d|\.\d)")


def join_negative_values(argv):
    """``['--position', '-60,40']`` as ``['--position=-60,40']``: argparse takes a value that
    starts with a minus sign for an option unless it is a plain number (issue 37: the
    model-check example ``--rotations -3,-2,-1,0,1,2,3`` failed).

    Examples
    --------
    >>> from kpifs._cli._parser import join_negative_values
    >>> join_negative_values(["inject", "c.fits", "--position", "-60,40", "--pa", "-5"])
    ['inject', 'c.fits', '--position=-60,40', '--pa=-5']
    """
    out = []
    for arg in argv:
        if (out and _NEGATIVE_VALUE.match(arg) and out[-1].startswith("--")
                and "=" not in out[-1]):
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out


def build_parser():
    """The ``kpifs`` parser; ``args.module`` names the `kpifs._cli` module that runs it."""
    parser = argparse.ArgumentParser(
        prog="kpifs", description="Multi-wavelength kernel-phase analysis of IFS cubes.",
        epilog="Run 'kpifs COMMAND --help' for the options and examples of each command.\n"
               + EXIT_STATUS.replace("; ", ";\n  ").replace(": 0", ":\n  0"),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"kpifs {VERSION}")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("-v", "--verbose", action="count", default=0,
                        help="more messages (-vv for debugging ones)")
    common.add_argument("-q", "--quiet", action="store_true",
                        help="errors only: no progress, warnings or results printed")
    common.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    def command(name, help_text, epilog, module=None):
        p = sub.add_parser(name, parents=[common], help=help_text, epilog=epilog,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        p.set_defaults(module=module or name)
        return p

    for add in COMMANDS:
        add(command)
    return parser
