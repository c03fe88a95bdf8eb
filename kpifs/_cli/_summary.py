"""What ``kpifs detect`` prints: one line per fact, in words a user knows.

The test, its threshold, what was found (position in the frame the angles
allow, contrast and error, global false-alarm probability: a bound where the
Monte-Carlo null has no draw as high), how well the error model describes the
data, and where the products are. The details (both nulls' thresholds, the
energy test, the map's noise) are in ``kpifs info`` of the products.
"""
import numpy as np
from astropy import units as u

from ..detect.null import PFA_FLOOR
from ..detect.statistics import REGISTRY
from ..io.angles import data_angles

__all__ = []


def _words(name):
    """What the test *name* is (`DetectionTest.description
    <kpifs.detect.statistics.DetectionTest>`), for the first line."""
    test = REGISTRY.get(name)
    return test.description if test is not None else name


def pfa_text(pfa, tail, floors):
    """A candidate's global P_FA: a value, an extrapolation, or a bound at a Monte-Carlo
    floor (``< 1/(draws + 1)``: no null draw as high).

    Examples
    --------
    >>> from kpifs._cli._summary import pfa_text
    >>> pfa_text(1 / 30001, False, [30000]), pfa_text(2e-4, False, [30000])
    ('< 3.3e-05 (no null draw as high)', '2.0e-04')
    >>> pfa_text(1.9e-12, True, [5000])
    '1.9e-12 (extrapolated from the null tail)'
    """
    pfa = float(pfa)
    if pfa <= PFA_FLOOR * (1 + 1e-9):
        return f"< {PFA_FLOOR:.0e} (beyond double precision)"
    if not tail and any(abs(pfa * (n + 1) - 1) < 1e-6 for n in floors if n):
        return f"< {pfa:.1e} (no null draw as high)"
    return f"{pfa:.1e}" + (" (extrapolated from the null tail)" if tail else "")


def contrast_text(row):
    pre = "fit_" if "fit_contrast" in row.colnames else ""
    c = np.atleast_1d(np.asarray(row[pre + "contrast"], float))
    e = np.atleast_1d(np.asarray(row[pre + "contrast_err"], float))
    if c.size == 1:
        return f"contrast {c[0]:.2e} +- {e[0]:.1e}"
    return (f"contrast {np.mean(c):.2e} (mean of {c.size} channels, 1-sigma "
            f"{np.nanmin(e):.1e} to {np.nanmax(e):.1e} per channel)")


def position_text(row, *, sky_known):
    """Detector offsets with errors and the fitted separation; sky offsets and PA only
    when the frames' angles are known."""
    pre = "fit_" if "fit_x" in row.colnames else ""

    def mas(col):
        return float(row[col].to_value(u.mas))

    def pm(col):
        return f" +- {mas(col + '_err'):.1f}" if col + "_err" in row.colnames else ""
    x, y = mas(pre + "x"), mas(pre + "y")
    text = (f"separation {np.hypot(x, y):.0f} mas; detector x {x:.1f}{pm(pre + 'x')}, "
            f"y {y:.1f}{pm(pre + 'y')} mas")
    if sky_known and pre + "dra" in row.colnames:
        text += (f"; sky dRA {mas(pre + 'dra'):.1f}{pm(pre + 'dra')}, dDec "
                 f"{mas(pre + 'ddec'):.1f}{pm(pre + 'ddec')} mas, PA "
                 f"{row[pre + 'pa_sky'].to_value(u.deg):.1f} deg East of North")
    elif not sky_known:
        text += " (the frames' angles are unknown: no sky offsets)"
    return text


def _threshold_line(res):
    nul = res.meta.get("null") or {}
    text = (f"threshold: {res.threshold:.2f} for a global false-alarm probability of "
            f"{res.pfa:g} over the search grid")
    if "threshold_empirical" in nul and "threshold_gaussian" in nul:
        text += (f" (the larger of the Gaussian null's {nul['threshold_gaussian']:.2f} and "
                 f"the empirical one's {nul['threshold_empirical']:.2f}, "
                 f"{nul['n_blocks']} time blocks)")
    return text


def _consistency_line(res):
    """The residual's reduced chi-square once the candidates are subtracted (how well
    noise plus candidates describe the data) and the noise scale the test was judged
    with (the raw energy, companion included, is the energy test's: `kpifs info`)."""
    dof = res.energy.get("dof")
    kappa = res.meta.get("chi2_red")
    if not dof or kappa is None:
        return None
    scale = float(res.meta.get("noise_scale", 1.0))
    after = " once the candidates are subtracted" if len(res.candidates) else ""
    return (f"data consistency: residual chi2 {float(kappa):.2f} per dof ({dof} dof){after}; "
            f"noise scale {scale:.2f} applied to the {res.test} statistic, errors and limits")


def print_summary(res, kpd, *, chosen):
    """Print the summary of a search *res* of data *kpd* (*chosen*: the ``--test``
    given); `products_line` ends it."""
    how = " (--test auto)" if chosen == "auto" else ""
    print(f"test: {res.test}{how}, {_words(res.test)}")
    print(_threshold_line(res))
    sky_known = res.meta.get("frame") == "sky" or data_angles(kpd) is not None
    floors = [res.meta.get("n_draws"), (res.meta.get("null") or {}).get("empirical_draws")]
    print(f"found: {len(res.candidates)} candidate(s) above the threshold")
    for i, row in enumerate(res.candidates, 1):
        flags = f" [flagged: {row['flags']}]" if "flags" in row.colnames and row["flags"] \
            else ""
        print(f"  {i}: {position_text(row, sky_known=sky_known)}")
        print(f"     {contrast_text(row)}; global P_FA "
              f"{pfa_text(row['pfa_global'], row['pfa_global_tail'], floors)}{flags}")
    line = _consistency_line(res)
    if line:
        print(line)


def products_line(output, plots=None):
    """Where the products (and figures) are, and the command that says more."""
    where = f"products: {output}" + (f", figures in {plots}/" if plots else "")
    print(f"{where}; details: kpifs info {output}")
