"""Detection tests as plug-ins (issue 38 item 1) and detect as stages (item 2)."""
import ast
from pathlib import Path

import numpy as np
import pytest
import astropy.units as u
from astropy.io import fits

from kpifs import KernelModel, KernelPhaseData, KpifsError, make_pupil
from kpifs.cli import main
from kpifs.data import DetectionGrid
from kpifs.detect import DetectionModel, NullCalibration, detect
from kpifs.detect._laws import norm_sf
from kpifs.detect.null import _CACHE
from kpifs.detect.options import SearchOptions
from kpifs.detect.statistics import (DetectionTest, get_test, register_test, registered_names,
                                     unregister_test)

PACKAGE = Path(__file__).resolve().parents[1] / "kpifs"


# --- the toy of docs/user/adding_a_test.rst ------------------------------------------
class _Batch:
    def __init__(self, n, npos, mirrored):
        self.best = np.zeros((n, npos), np.float32)
        self.worst = np.zeros((n, npos), np.float32) if mirrored else None

    def add(self, i, z):
        np.maximum(self.best, np.maximum(z, 0) ** 2, out=self.best)
        if self.worst is not None:      # the mirror position sees -z
            np.maximum(self.worst, np.minimum(z, 0) ** 2, out=self.worst)

    def finish(self, channel_sum):
        best = self.best.max(axis=1)
        if self.worst is not None:
            best = np.maximum(best, self.worst.max(axis=1))
        return {"M": best}


class _Reducer:
    def __init__(self, setup):
        self.npos, self.mirrored = len(setup.positions), setup.mirrored

    def batch(self, n):
        return _Batch(n, self.npos, self.mirrored)


class BrightestChannelTest(DetectionTest):
    name = "M"
    label = r"M: brightest channel, $\max_i \max(z_i, 0)^2$"
    description = "the brightest-channel test"
    power = 1.0

    def map_statistic(self, model, z, spectrum):
        return np.max(np.clip(np.nan_to_num(z), 0, None) ** 2, axis=-3)

    def local_pfa(self, model, t):
        q = len(model.wavelengths)
        one = norm_sf(np.sqrt(np.clip(np.nan_to_num(t), 0, None)))
        return 1 - (1 - one) ** q

    def null_reducer(self, setup):
        return _Reducer(setup)


@pytest.fixture
def toy_test():
    test = register_test(BrightestChannelTest)
    yield test
    unregister_test("M")


def _data(contrasts=(4e-3, 3e-3), seed=1):
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
    wl = [1.6, 1.7] * u.um
    rng = np.random.default_rng(seed)
    kp = km.binary_kernel_phases([60, -40] * u.mas, list(contrasts), wl)
    kp = kp + rng.normal(0, 1e-3, kp.shape)
    cov = np.stack([np.eye(km.n_kp) * 1e-6] * 2)
    return KernelPhaseData(kp[None], wl, 10.42 * u.mas, km, covariance=cov,
                           meta={"calibrated": True})


GRID = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)


# --- the registry --------------------------------------------------------------------
def test_registry_holds_every_test_in_order():
    assert registered_names() == ("NP", "E", "B", "B-paper", "S")
    assert [get_test(n).power for n in registered_names()] == [0.5, 1.0, 1.0, 0.5, 1.0]
    assert get_test("E").map_name == "B"
    with pytest.raises(KpifsError, match="unknown test 'Q'"):
        get_test("Q")
    with pytest.raises(KpifsError, match="not a named DetectionTest"):
        register_test(object())


def _string_constants(path):
    return {node.value for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.Constant) and isinstance(node.value, str)}


@pytest.mark.parametrize("rel", ["_cli/_parser.py", "_cli/detect.py", "_cli/info.py",
                                 "_cli/_summary.py", "_cli/roc.py", "plotting.py",
                                 "io/products.py", "detect/roc.py", "detect/pipeline.py",
                                 "detect/null.py", "detect/search.py", "detect/maps.py"])
def test_readers_of_the_registry_never_spell_a_test(rel):
    """The command line, figures, products, roc and the search read the registry: no
    test's name is a string of theirs (before: 84 literals in 11 files)."""
    path = PACKAGE / rel
    if not path.exists():
        pytest.skip(f"{rel} does not exist")
    assert not _string_constants(path) & set(registered_names())


# --- a toy test, plugged in ---------------------------------------------------------
def test_a_registered_toy_test_runs_detect(toy_test):
    res = detect(_data(), grid=GRID, test="M", n_draws=2000, seed=0)
    assert res.test == "M" and res.report.test == "M"
    # the grid maximum's threshold is above one position's (local P_FA 1e-3)
    local = res.grid.valid & (res.pfa_local <= 1e-3)
    assert res.threshold > float(np.min(res.statistic[local]))
    assert len(res.candidates) == 1
    row = res.candidates[0]
    assert np.hypot(row["fit_x"].to_value(u.mas) - 60, row["fit_y"].to_value(u.mas) + 40) < 5
    # its local law: 1 - (1 - Q(sqrt t))^q, e.g. t = 9, q = 2
    assert float(toy_test.local_pfa(res_model(), np.array(9.0))) == pytest.approx(
        1 - (1 - norm_sf(3.0)) ** 2, rel=1e-12)
    assert "M" not in res.limits and set(res.limits) == {"NP", "E", "B", "B-paper", "S"}
    # a built-in search runs with the toy registered (its null is not one the limits read)
    assert res.meta["null"]["threshold"] == res.threshold
    res_b = detect(_data(), grid=GRID, test="B", n_draws=2000, seed=0)
    assert len(res_b.candidates) == 1 and "M" not in res_b.limits


def res_model():
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
    return DetectionModel(km, [1.6, 1.7] * u.um, np.eye(km.n_kp)[None].repeat(2, 0), GRID)


def test_a_registered_toy_test_on_the_command_line(toy_test, tmp_path, capsys):
    path = _data().write(tmp_path / "kp.fits")
    out = tmp_path / "det.fits"
    assert main(["detect", str(path), "--test", "M", "--draws", "2000", "--max-sep", "100",
                 "--min-sep", "20", "--grid-step", "10", "-o", str(out), "-q"]) == 0
    assert "the brightest-channel test" in capsys.readouterr().out
    assert fits.getheader(out)["TEST"] == "M"
    assert main(["detect", str(path), "--test", "Q", "-o", str(tmp_path / "q.fits")]) == 2
    assert "unknown test 'Q'" in capsys.readouterr().err


# --- the null reduces only what is asked for ------------------------------------------
def test_null_draws_a_test_alone_as_with_the_others():
    dm = res_model()
    _CACHE.clear()
    alone = NullCalibration(dm, form="B", n_draws=1500, seed=3)
    b = alone.draws.copy()
    assert len(_CACHE) == 2         # B's maxima and the map's mean square, nothing else
    _CACHE.clear()
    together = NullCalibration(dm, form="S", n_draws=1500, seed=3, also=("B", "B-paper"))
    together.draws
    assert len(_CACHE) == 5         # S, B, B-paper, Z2, G2
    np.testing.assert_array_equal(NullCalibration(dm, form="B", n_draws=1500, seed=3).draws, b)
    with pytest.raises(KpifsError, match="has no map"):
        NullCalibration(dm, form="E")


# --- detect as stages ------------------------------------------------------------------
def test_detect_with_options_is_detect_with_keywords():
    kpd = _data()
    a = detect(kpd, grid=GRID, n_draws=2000, seed=0, test="S")
    b = detect(kpd, SearchOptions(grid=GRID, n_draws=2000, seed=0, test="S"))
    np.testing.assert_array_equal(a.statistic, b.statistic)
    for k in a.limits:
        np.testing.assert_array_equal(a.limits[k], b.limits[k])
    assert a.meta == b.meta
    assert b.report.null.threshold == b.threshold == b.meta["null"]["threshold"]
    assert b.report.limits.noise_scale_subspace == b.meta["noise_scale_S"]
    with pytest.raises(KpifsError, match="not both"):
        detect(kpd, SearchOptions(), seed=1)
    with pytest.raises(KpifsError, match="unknown option"):
        detect(kpd, n_draw=2000)


def test_every_public_object_of_the_new_modules_has_an_example():
    import importlib
    import inspect
    missing = []
    for m in ("kpifs.detect.statistics", "kpifs.detect.statistics.neyman_pearson",
              "kpifs.detect.statistics.energy", "kpifs.detect.statistics.binary",
              "kpifs.detect.statistics.binary_paper", "kpifs.detect.statistics.subspace",
              "kpifs.detect.options", "kpifs.report", "kpifs.detect.known_position"):
        mod = importlib.import_module(m)
        for name in mod.__all__:
            obj = getattr(mod, name)
            if (inspect.isfunction(obj) or inspect.isclass(obj)) and \
                    ">>>" not in (inspect.getdoc(obj) or ""):
                missing.append(f"{m}.{name}")
    assert not missing, missing
