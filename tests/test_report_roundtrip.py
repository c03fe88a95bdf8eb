"""Issue 38: a detection product's cards are written from the search's typed report and
read back into it (`kpifs.report.DetectionReport`), not only into a free dict."""
import dataclasses

import numpy as np

from kpifs.data import DetectionResult
from kpifs.detect.pipeline import _example_result
from kpifs.report import DetectionReport, LimitsReport, NullReport

#: Fields a product's cards hold (the others are None when read back).
ON_CARDS = ("test", "map_test", "pfa", "pd", "n_draws", "seed", "frame", "chi2_red",
            "noise_scale", "aliased", "channels", "excluded_channels", "blocks", "static")


def _close(a, b):
    if isinstance(a, float) or isinstance(b, float):
        return np.isclose(a, b, rtol=1e-6)
    return a == b


def test_product_read_back_into_the_report(tmp_path):
    res = _example_result()
    path = tmp_path / "det.fits"
    res.write(path)
    back = DetectionResult.read(path)
    assert isinstance(back.report, DetectionReport)
    for name in ON_CARDS:
        assert _close(getattr(back.report, name), getattr(res.report, name)), name
    null, null0 = back.report.null, res.report.null
    assert isinstance(null, NullReport)
    assert null.method == null0.method and _close(null.threshold, null0.threshold)
    assert null.thresholds.keys() == null0.thresholds.keys()
    for k in null.thresholds:
        assert _close(null.thresholds[k], null0.thresholds[k])
    lim, lim0 = back.report.limits, res.report.limits
    assert isinstance(lim, LimitsReport)
    assert lim.null_channels == lim0.null_channels
    assert lim.calibrators == lim0.calibrators
    assert np.allclose(lim.spectrum, lim0.spectrum)
    # what the printouts read is the same from the search and from its product
    assert back.report.as_meta()["null"]["threshold"] == back.meta["null"]["threshold"]


def test_report_from_its_own_meta_is_itself():
    rep = _example_result().report
    again = DetectionReport.from_meta(rep.as_meta())
    assert again == rep
    assert [f.name for f in dataclasses.fields(again)] == \
        [f.name for f in dataclasses.fields(rep)]
