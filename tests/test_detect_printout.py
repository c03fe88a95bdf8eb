"""What ``kpifs detect`` and ``kpifs info`` print: one line per fact, true to the run."""
import re

import numpy as np
import pytest
import astropy.units as u

from kpifs import KernelModel, KernelPhaseData, make_pupil
from kpifs.cli import main
from kpifs.data import DetectionResult

WL3 = [1.52, 1.60, 1.68] * u.um


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A target with a companion at (70, 40) mas and a calibrator, 300 frames each, white
    noise drawn on the uv points (the same realisation whatever kernel basis), no frame
    angles (the search stays on the detector)."""
    rng = np.random.default_rng(8)
    km = KernelModel.from_pupil(make_pupil("subaru", step=1.0 * u.m))

    def frames(n):
        return (km.kernel @ rng.normal(0, 1e-3, (km.n_uv, 3 * n))).T.reshape(n, 3, km.n_kp)
    truth = km.binary_kernel_phases([70, 40] * u.mas, [6e-3, 5e-3, 4e-3], WL3)
    d = tmp_path_factory.mktemp("kp")
    KernelPhaseData(frames(300) + truth, WL3, 10.42 * u.mas, km).write(d / "t.fits")
    KernelPhaseData(frames(300), WL3, 10.42 * u.mas, km).write(d / "c.fits")
    return d


@pytest.fixture(scope="module")
def printed(files):
    import contextlib
    import io
    out = files / "det.fits"
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        code = main(["detect", str(files / "t.fits"), "--calibrator", str(files / "c.fits"),
                     "--draws", "2000", "--max-sep", "150mas", "--grid-step", "15mas",
                     "-o", str(out), "-q"])
    assert code == 0
    return text.getvalue(), DetectionResult.read(out)


def test_one_line_per_fact(printed):
    text, res = printed
    lines = text.splitlines()
    assert lines[0].startswith("test: B (--test auto), the binary GLR test")
    assert lines[1].startswith(f"threshold: {res.threshold:.2f} for a global false-alarm "
                               f"probability of 0.001")
    assert lines[2] == "found: 1 candidate(s) above the threshold"
    assert text.count("per dof") == 1 and "for S" not in text     # the energy once, no S
    assert f"data consistency: residual chi2 {res.meta['chi2_red']:.2f} per dof" in text
    assert lines[-1].startswith("products: ") and "kpifs info" in lines[-1]


def test_candidate_line_gives_the_fitted_separation_contrast_and_frame(printed):
    """The separation is the fitted position's (the grid peak, on a 15 mas grid, is
    several mas away), the contrast is given with its error, and without the frames'
    angles no sky offset is made up from an assumed one."""
    text, res = printed
    row = res.candidates[0]
    fit = float(np.hypot(row["fit_x"].to_value(u.mas), row["fit_y"].to_value(u.mas)))
    grid = float(row["separation"].to_value(u.mas))
    assert abs(fit - grid) > 2
    assert f"separation {fit:.0f} mas; detector x {row['fit_x'].to_value(u.mas):.1f} +- " \
        in text
    mean = re.search(r"contrast (\S+) \(mean of 3 channels, 1-sigma", text)
    assert float(mean.group(1)) == pytest.approx(5e-3, rel=0.05)
    assert "dRA" not in text and "the frames' angles are unknown: no sky offsets" in text
    assert "dra" not in res.candidates.colnames


def test_info_gives_the_details(printed, files, capsys):
    _, res = printed
    assert main(["info", str(files / "det.fits")]) == 0
    out = capsys.readouterr().out
    assert "SEARCH: the residual map the search stopped on" in out
    assert "noise: residual chi2_red" in out and "noise scale of the test" in out
    assert "energy test T_E" in out
    fit = float(np.hypot(*(res.candidates[0][c].to_value(u.mas) for c in ("fit_x", "fit_y"))))
    assert f"1: separation {fit:.0f} mas" in out
