"""The figures show what the run did: the test used, and the map the search decided on."""
import warnings

import numpy as np
import pytest
import astropy.units as u

from kpifs import KernelModel, KernelPhaseData, make_pupil
from kpifs.data import DetectionGrid, DetectionResult
from kpifs.detect import detect
from kpifs.plotting import plot_contrast_curves, plot_detection_map

WL = np.linspace(1.16, 2.37, 8) * u.um


@pytest.fixture(scope="module")
def s_run():
    """An S search of a bright companion at (60, -40) mas in 8 channels of white noise.

    The noise is drawn on the uv points and projected: the same realisation whatever
    kernel basis the SVD returns, so only the null's Monte-Carlo threshold (a few per
    cent) varies between machines. Measured over seeds 0-11: the companion at 157-252
    times the threshold, the residual's maximum at 0.21-0.46 of it (0.23 for seed 3)."""
    km = KernelModel.from_pupil(make_pupil("subaru", step=1.0 * u.m))
    rng = np.random.default_rng(3)
    sigma = 1e-3
    kp = km.binary_kernel_phases([60, -40] * u.mas, np.linspace(8e-3, 5e-3, 8), WL)
    kp = kp + (km.kernel @ rng.normal(0, sigma, (km.n_uv, 8))).T
    kpd = KernelPhaseData(kp[None], WL, 10 * u.mas, km,
                          covariance=np.stack([np.eye(km.n_kp) * sigma ** 2] * 8),
                          meta={"calibrated": True})
    grid = DetectionGrid.from_separation(90 * u.mas, 15 * u.mas, min_sep=20 * u.mas)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return detect(kpd, test="S", grid=grid, n_draws=1000)


def test_s_run_limits_figure_has_an_s_curve(s_run):
    fig = plot_contrast_curves(s_run)
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels[0].startswith("S: ") and labels[0].endswith("(this search's test)")
    own = [line for line in ax.get_lines() if line.get_label() == labels[0]]
    assert len(own) == 1 and own[0].get_linewidth() > 2
    assert np.allclose(own[0].get_ydata(), s_run.curves["S_median"], equal_nan=True)
    assert "S search" in ax.get_title()


def test_detection_map_draws_what_the_search_decided_on(s_run, tmp_path):
    """The map drawn is the residual the search stopped on, in units of the threshold:
    the companion is subtracted (the data's own map has it far above), nothing in it is
    above the threshold, and the candidate is marked with its own statistic."""
    assert len(s_run.candidates) == 1
    assert np.nanmax(s_run.statistic) > 5 * s_run.threshold
    assert np.nanmax(s_run.search_map) < s_run.threshold
    fig = plot_detection_map(s_run)
    drawn = fig.axes[0].get_images()[0].get_array()
    assert np.allclose(np.ma.filled(drawn, np.nan), s_run.search_map / s_run.threshold,
                       equal_nan=True)
    ratio = float(s_run.candidates["statistic"][0]) / s_run.threshold
    assert [t.get_text() for t in fig.axes[0].texts] == [f"1: {ratio:.3g}x"]
    assert "S: spectral model" in fig.axes[0].get_title()
    # the products keep it (SEARCH), and a figure from them draws the same
    back = DetectionResult.read(s_run.write(tmp_path / "det.fits"))
    assert np.allclose(back.search_map, s_run.search_map, equal_nan=True)
