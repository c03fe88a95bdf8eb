"""Injection limits are stated as far as the steps allow: a bracket, interpolated only
between adjacent conclusive steps (issue 36: 0 / 2 / 4 of 4 found at 0.5 / 1 / 2 times the
analytic limit were printed as that limit to three digits)."""
import numpy as np
import pytest
import astropy.units as u
from astropy.table import QTable

from kpifs._cli.inject import bracket_text
from kpifs.inject import injection_brackets, limit_bracket
from kpifs.plotting import plot_injection_limits


def _table(contrasts, found, n):
    tab = QTable({"separation": [60.0] * len(contrasts) * u.mas, "contrast": contrasts,
                  "n_injected": [n] * len(contrasts), "n_detected": found,
                  "pd": np.asarray(found) / n})
    tab.meta.update(pd=0.5, pfa=1e-3, limits=[contrasts[1]], flags=["="],
                    separations_mas=[60.0])
    return tab


def test_four_angles_bracket_without_a_value():
    a = 1.92e-4
    low, high, value = limit_bracket([0.5 * a, a, 2 * a], [0, 2, 4], [4, 4, 4])
    assert (low, high) == (pytest.approx(0.5 * a), pytest.approx(2 * a))
    assert np.isnan(value)
    text = bracket_text(injection_brackets(_table([0.5 * a, a, 2 * a], [0, 2, 4], 4))[0])
    assert text == "between 9.6e-05 and 3.8e-04"


def test_inconclusive_steps_are_not_bounds():
    """1 of 4 found is what a step at the limit gives 31 % of the time: not below it."""
    low, high, value = limit_bracket([1e-4, 2e-4, 4e-4], [1, 3, 4], [4, 4, 4])
    assert np.isnan(low) and high == pytest.approx(4e-4) and np.isnan(value)


def test_adjacent_conclusive_steps_are_interpolated():
    low, high, value = limit_bracket([1e-4, 2e-4, 4e-4], [1, 16, 20], [20, 20, 20])
    assert (low, high) == (pytest.approx(1e-4), pytest.approx(2e-4))
    f = (0.5 - 0.05) / (0.8 - 0.05)
    assert value == pytest.approx(np.exp(np.log(1e-4) + f * np.log(2)))
    assert bracket_text({"limit_low": low, "limit_high": high,
                         "limit_interpolated": value}).startswith("1.5e-04 (interpolated")


def test_figure_draws_the_bracket_not_a_point():
    a = 1.92e-4
    fig = plot_injection_limits(_table([0.5 * a, a, 2 * a], [0, 2, 4], 4))
    ax = fig.axes[0]
    bars = [c for c in ax.collections if c.__class__.__name__ == "LineCollection"]
    assert len(bars) == 1
    (seg,) = bars[0].get_segments()
    assert seg[:, 1].tolist() == pytest.approx([0.5 * a, 2 * a])
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert not any("interpolated" in t for t in labels)


def test_saturated_ends_are_not_interpolated():
    """0 of 4 and 4 of 4 at adjacent steps a factor 8 apart: the limit is anywhere
    between them."""
    low, high, value = limit_bracket([1.5e-3, 1.2e-2], [0, 4], [4, 4])
    assert (low, high) == (pytest.approx(1.5e-3), pytest.approx(1.2e-2)) and np.isnan(value)


def test_info_reads_the_bracket_the_curve_file_holds(tmp_path, capsys):
    """`kpifs info curve.fits` on a file the writer made (its LIMITS table names the
    interpolated value limit_injection): the bracket, as `inject --curve` printed it
    (it raised KeyError 'limit_interpolated', exit 3)."""
    from types import SimpleNamespace
    from kpifs._cli.inject import _curve_hdulist
    from kpifs.cli import main
    a = 1.92e-4
    tab = _table([0.5 * a, a, 2 * a], [0, 2, 4], 4)
    tab.meta.update(ladder="adaptive", n_draws=1000, method="test", n_angles=4, seed=0)
    args = SimpleNamespace(pfa=1e-3, angles=4, seed=0)
    _curve_hdulist(tab, [60.0] * u.mas, [a], args, "t.fits").writeto(tmp_path / "curve.fits")
    assert main(["info", str(tmp_path / "curve.fits")]) == 0
    assert "60 mas: injections between 9.6e-05 and 3.8e-04, analytic 1.92e-04" in (
        capsys.readouterr().out)
