"""Parsed command-line options -> the workflow's option objects (no science here).

One table per option object names the command line's option (its ``dest``) for
each field; the fields' defaults are `kpifs._defaults`, which the parser uses
too. A command passes the options it has; the others keep their defaults.
"""
from ..workflow import DetectOptions, ExtractOptions

__all__ = ["EXTRACT_FIELDS", "DETECT_FIELDS", "extract_options", "detect_options"]

#: `~kpifs.workflow.ExtractOptions` field -> the parsed option (``args`` attribute).
EXTRACT_FIELDS = {
    "instrument": "instrument", "wavelengths": "wavelengths", "pixscale": "pixscale",
    "pa": "pa", "dq_bits": "dq_bits", "pupil": "pupil", "pupil_scale": "pupil_scale",
    "step": "step", "offset": "offset", "min_transmission": "min_transmission",
    "grey": "grey", "rotation": "rotation", "min_redundancy": "min_redundancy",
    "hexagonal": "hexagonal", "window_size": "window_size", "window_radius": "window_radius",
    "centroid": "centroid", "bad_pixels": "bad_pixels", "bad_frames": "bad_frames",
    "on_nyquist": "nyquist", "precision": "precision", "shrinkage": "shrinkage",
    "joint_covariance": "joint_covariance", "covariance": "covariance",
    "pixel_noise": "pixel_noise", "filter_kernels": "filter_kernels",
    "angular_differential": "angular_differential",
    "spectral_differential": "spectral_differential",
}

#: `~kpifs.workflow.DetectOptions` field -> the parsed option.
DETECT_FIELDS = {k: k for k in (
    "test", "pfa", "pd", "max_sep", "min_sep", "grid_step", "spectrum", "basis", "draws",
    "seed", "shrinkage", "allow_uncalibrated", "frame", "null", "blocks", "aliased", "static")}


def extract_options(args):
    """`~kpifs.workflow.ExtractOptions` from the options the command has (the rest default)."""
    return ExtractOptions(**{k: getattr(args, a) for k, a in EXTRACT_FIELDS.items()
                             if hasattr(args, a)})


def detect_options(args):
    """`~kpifs.workflow.DetectOptions` from the search options of the command."""
    return DetectOptions(**{k: getattr(args, a) for k, a in DETECT_FIELDS.items()
                            if hasattr(args, a)})
