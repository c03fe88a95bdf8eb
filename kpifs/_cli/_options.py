"""Parsed command-line options -> the workflow's option objects (no science here)."""
from ..workflow import DetectOptions, ExtractOptions

__all__ = ["extract_options", "detect_options"]


def extract_options(args):
    """`~kpifs.workflow.ExtractOptions` from the options the command has (the rest default)."""
    get = {k: getattr(args, a) for k, a in (
        ("instrument", "instrument"), ("wavelengths", "wavelengths"), ("pixscale", "pixscale"),
        ("pa", "pa"), ("dq_bits", "dq_bits"),
        ("pupil", "pupil"), ("pupil_scale", "pupil_scale"), ("step", "step"),
        ("offset", "offset"), ("min_transmission", "min_transmission"), ("grey", "grey"),
        ("rotation", "rotation"), ("min_redundancy", "min_redundancy"),
        ("hexagonal", "hexagonal"), ("window_size", "window_size"),
        ("window_radius", "window_radius"), ("centroid", "centroid"),
        ("bad_pixels", "bad_pixels"), ("bad_frames", "bad_frames"),
        ("on_nyquist", "nyquist"), ("precision", "precision"), ("shrinkage", "shrinkage"),
        ("joint_covariance", "joint_covariance"), ("covariance", "covariance"),
        ("pixel_noise", "pixel_noise"), ("filter_kernels", "filter_kernels"))
        if hasattr(args, a)}
    return ExtractOptions(**get)


def detect_options(args):
    """`~kpifs.workflow.DetectOptions` from the search options of the command."""
    get = {k: getattr(args, k) for k in ("test", "pfa", "pd", "max_sep", "min_sep",
                                         "grid_step", "spectrum", "basis", "draws", "seed",
                                         "shrinkage", "allow_uncalibrated", "frame", "null",
                                         "blocks", "aliased", "static")
           if hasattr(args, k)}
    return DetectOptions(**get)
