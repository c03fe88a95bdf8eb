"""What a candidate's fit says about it: flags where the model does not fit, and its
spectrum within the spectral model.

A candidate is still reported when its fit is doubtful, with its global
false-alarm probability judged against the inflated noise (the noise scale of
`~kpifs.detect.channels.combined_scale`); the ``flags`` column says why it
should not be taken at face value:

- ``contrast-bound``: a fitted contrast sits on the fit's bound (+-0.5): the
  binary model cannot account for the signal;
- ``inner-edge`` / ``outer-edge``: the fitted separation lies within one grid
  step of the searched range's edge, where the grid cannot bracket it;
- ``moved``: the fit left the grid peak (or its mirror, where a fit whose
  contrast came out negative is taken) by more than a resolution element
  ``lambda_min / B_max`` (or reached its position box);
- ``chi2``: the reduced chi-square of the residual once the candidate is
  subtracted exceeds `CHI2_FACTOR` times the noise scale applied to the
  search: the candidate leaves more unexplained than the rest of the data;
- ``spectrum-underdetermined``: searched in channel combinations (a
  spectral-differential search, ASDI), some channel keeps less than half of its
  information once the other channels' contrasts are fitted too
  (``fit_contrast_kept`` below `~kpifs.calibration.spectral_diff.SDK_LEVEL`): the
  combinations measure the spectrum there only in part (inside the inner
  separation), and its contrasts carry the errors that follow.
"""
import numpy as np
from astropy import units as u

from ..calibration.spectral_diff import SDK_LEVEL
from ..model.kernel import MAS
from .spectral import subspace_spectrum

__all__ = ["flag_candidates", "add_spectrum_model", "CHI2_FACTOR", "CONTRAST_BOUND"]

#: Reduced chi-square, relative to the search's noise scale, above which a fit is flagged.
CHI2_FACTOR = 3.0
#: The binary fit's contrast bound (`~kpifs.detect.fit.fit_binary`).
CONTRAST_BOUND = 0.5


def flag_candidates(cands, grid, *, resolution, noise_scale=1.0, box=20.0):
    """Add a ``flags`` column (comma-separated reasons, '' for none) to a candidate table.

    *resolution* (mas) is ``lambda_min / B_max``; *box* the half-width (mas) of
    the fit's position box.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from astropy.table import QTable
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect.quality import flag_candidates
    >>> grid = DetectionGrid.from_separation(200 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    >>> t = QTable({"x": [100, 20] * u.mas, "y": [0, 0] * u.mas,
    ...             "fit_x": [101, 15] * u.mas, "fit_y": [1, 0] * u.mas,
    ...             "fit_contrast": [[0.01], [0.5]], "chi2_red": [1.1, 9.0]})
    >>> flag_candidates(t, grid, resolution=40.0)
    >>> [str(f) for f in t["flags"]]
    ['', 'contrast-bound,inner-edge,chi2']
    """
    n = len(cands)
    flags = [[] for _ in range(n)]
    fitted = "fit_x" in cands.colnames
    step = float(max(abs(grid.step[0]), abs(grid.step[1])))
    for k in range(n):
        row = cands[k]
        if fitted:
            c = np.atleast_1d(np.asarray(row["fit_contrast"], float))
            if np.any(np.abs(c) >= CONTRAST_BOUND * (1 - 1e-6)):
                flags[k].append("contrast-bound")
            fx, fy = row["fit_x"].to_value(u.mas), row["fit_y"].to_value(u.mas)
        else:
            fx, fy = row["x"].to_value(u.mas), row["y"].to_value(u.mas)
        sep = float(np.hypot(fx, fy))
        if sep < float(grid.min_sep) + step:
            flags[k].append("inner-edge")
        if np.isfinite(grid.max_sep) and sep > float(grid.max_sep) - step:
            flags[k].append("outer-edge")
        if fitted:
            # from the peak or from its mirror, where the fit goes when the peak's
            # contrast came out negative (`kpifs.detect.fit.refine_candidates`)
            px, py = row["x"].to_value(u.mas), row["y"].to_value(u.mas)
            dx, dy = min(((fx - px, fy - py), (fx + px, fy + py)),
                         key=lambda d: np.hypot(*d))
            if np.hypot(dx, dy) > resolution or max(abs(dx), abs(dy)) >= box * (1 - 1e-6):
                flags[k].append("moved")
        if "chi2_red" in cands.colnames and \
                float(row["chi2_red"]) > CHI2_FACTOR * max(1.0, float(noise_scale)):
            flags[k].append("chi2")
        if "fit_contrast_kept" in cands.colnames and \
                np.any(np.asarray(row["fit_contrast_kept"], float) < SDK_LEVEL):
            flags[k].append("spectrum-underdetermined")
    cands["flags"] = [",".join(f) for f in flags]


def add_spectrum_model(cands, basis):
    """Add the candidates' contrast spectra within the spectral model *basis* (q, r).

    ``contrast_model`` (from the grid peak's free contrasts) and, for fitted
    candidates, ``fit_contrast_model`` and ``fit_contrast_model_err``: the
    weighted projection of the free per-channel contrasts on the model
    (`~kpifs.detect.spectral.subspace_spectrum`), beside the free ones.

    Examples
    --------
    >>> import numpy as np
    >>> from astropy.table import QTable
    >>> from kpifs.detect.quality import add_spectrum_model
    >>> t = QTable({"contrast": [[1.0, 1.2, 0.8]], "contrast_err": [[0.1, 0.1, 0.1]]})
    >>> add_spectrum_model(t, np.ones((3, 1)) / 3 ** 0.5)
    >>> np.round(t["contrast_model"][0], 3).tolist()
    [1.0, 1.0, 1.0]
    """
    q = np.asarray(basis).shape[0]
    for pre in ("", "fit_"):
        # a fit that gave its spectrum within the model itself keeps it (a stack of
        # channel combinations, `kpifs.detect._blockfit.refine_stack`)
        if pre + "contrast" not in cands.colnames or pre + "contrast_model" in cands.colnames:
            continue
        out, err = np.zeros((len(cands), q)), np.zeros((len(cands), q))
        for k in range(len(cands)):
            out[k], err[k] = subspace_spectrum(np.ravel(cands[pre + "contrast"][k]),
                                               np.ravel(cands[pre + "contrast_err"][k]), basis)
        cands[pre + "contrast_model"] = out
        if pre:
            cands[pre + "contrast_model_err"] = err


def resolution_mas(kernel_model, wavelengths):
    """``lambda_min / B_max`` in mas."""
    lam = u.Quantity(wavelengths, u.um).to_value(u.m).min()
    return float(lam / kernel_model.baseline_length.to_value(u.m).max() / MAS)
