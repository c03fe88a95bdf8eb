"""Every reduction option's default, written once.

`kpifs.workflow.ExtractOptions` and `kpifs.workflow.DetectOptions` take their
field defaults from here, and so does the command line's parser
(`kpifs._cli._parser`), for ``extract``, ``detect``, ``batch``, ``inject`` and
``demo`` alike. This module imports nothing, so that ``kpifs --help`` stays
fast. ``None`` means "the instrument's or the data's own" (the option's help
says which).
"""

__all__ = ["EXTRACT", "DETECT"]

#: `kpifs.workflow.ExtractOptions`: reading, pupil model, extraction, covariance, and the
#: step between extraction and detection (calibrator, JWST filters, angular-differential,
#: spectral-differential: None for none, else the nuisance basis' name).
EXTRACT = {
    "instrument": "auto", "wavelengths": None, "pixscale": None, "pa": None, "dq_bits": None,
    "pupil": None, "pupil_scale": None, "step": None, "offset": None,
    "min_transmission": None, "grey": None, "min_redundancy": None, "rotation": None,
    "hexagonal": False,
    "window_size": None, "window_radius": None, "window_order": 4.0, "centroid": "com",
    "bad_pixels": "fill", "bad_frames": "drop", "on_nyquist": "drop", "mask": None,
    "precision": "double",
    "shrinkage": "auto", "joint_covariance": False, "covariance": False,
    "pixel_noise": "auto", "filter_kernels": "own", "angular_differential": False,
    "spectral_differential": None,
}

#: `kpifs.workflow.DetectOptions`: the search.
DETECT = {
    "test": "auto", "pfa": 1e-3, "pd": 0.5, "max_sep": None, "min_sep": None,
    "grid_step": None, "spectrum": None, "basis": None, "draws": 5000, "seed": 0,
    "shrinkage": "auto", "fit": True, "max_candidates": 20, "allow_uncalibrated": False,
    "frame": "auto", "null": "auto", "blocks": "auto", "aliased": "keep", "static": "auto",
}
