"""One workflow behind every interface; containers round-trip; the wavelength rule; the
package's import structure."""
import ast
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import astropy.units as u
from astropy.io import fits

from kpifs import ExtractionWindow, KernelModel, KernelPhaseData, KpifsError, make_pupil
from kpifs.cli import main
from kpifs.data import DetectionResult
from kpifs.io import parse_wavelengths, read_cube, write_observation
from kpifs.simulation.simulate import simulate_scene
from kpifs.workflow import (DetectOptions, ExtractOptions, calibrate_observation,
                            detect_observation, extract_observation, process_observation)

PACKAGE = Path(__file__).resolve().parents[1] / "kpifs"
IGNORED_CARDS = {"CHECKSUM", "DATASUM", "DATE"}


@pytest.fixture(scope="module")
def observation(tmp_path_factory):
    d = tmp_path_factory.mktemp("obs")
    obs = simulate_scene("paper", n_frames=120, seed=31, npup=48, exptime=1 * u.s,
                         contrasts=4e-3)
    return write_observation(obs, d)


# Floats agree to 1e-9: a Dask worker's single-threaded BLAS sums in another order than
# the command line's, and the error model's SVDs and whitening carry that rounding (1e-12)
# into the maps at ~1e-11. The Monte-Carlo null is drawn in single precision for speed, so
# false-alarm probabilities from its extrapolated tail agree to 1e-4 only.
# Thresholds read through the null's fitted tail (the mean of a tenth of its single-precision
# draws) carry their rounding, 1e-7, and so do the limits they set.
_RTOL = {"PFA": 1e-4, "CANDIDATES.pfa_global": 1e-4}
_CARD_RTOL = {"THRESH": 1e-6, "THRGAUS": 1e-6, "THREMP": 1e-6}


def _same(x, y, what):
    """Equal values (floats within the tolerances above)."""
    x, y = np.asarray(x), np.asarray(y)
    if x.dtype.kind in "fc":
        # a non-linear fit with finite-difference steps amplifies that rounding to ~1e-9
        rtol = _RTOL.get(what, 1e-6 if what.startswith(("CANDIDATES.fit_", "CURVES.", "LIMIT"))
                         else 1e-9)
        np.testing.assert_allclose(x, y, rtol=rtol,
                                   atol=1e-12 * float(np.nanmax(np.abs(y), initial=0)) or 1e-300,
                                   err_msg=what)
    else:
        np.testing.assert_array_equal(x, y, err_msg=what)


def _same_products(a, b, *, history=True):
    """Every HDU's data and header card equal, but checksums and input paths (and HISTORY
    lines, which a product written again adds to, with ``history=False``)."""
    with fits.open(a) as ha, fits.open(b) as hb:
        assert [h.name for h in ha] == [h.name for h in hb]
        for x, y in zip(ha, hb):
            cards = [[(c.keyword, c.value) for c in h.header.cards
                      if c.keyword not in IGNORED_CARDS and not c.keyword.startswith("KPIN")
                      and (history or c.keyword != "HISTORY")]
                     for h in (x, y)]
            assert [k for k, _ in cards[0]] == [k for k, _ in cards[1]], x.name
            for (k, v), (_, w) in zip(*cards):
                if isinstance(v, float):
                    assert v == pytest.approx(w, rel=_CARD_RTOL.get(k, 1e-12), nan_ok=True), \
                        (x.name, k)
                else:
                    assert v == w, (x.name, k)
            if x.data is None:
                continue
            if isinstance(x, fits.BinTableHDU):
                for col in x.columns.names:
                    _same(x.data[col], y.data[col], f"{x.name}.{col}")
            else:
                _same(x.data, y.data, x.name)


@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::ResourceWarning",
                            "ignore::pytest.PytestUnraisableExceptionWarning")
def test_batch_entry_equals_the_cli_calls(observation, tmp_path):
    """`kpifs batch` reduces an entry exactly as `kpifs extract --calibrator` + `kpifs detect`
    with the same (non-default) options."""
    pytest.importorskip("dask.distributed")
    t, c = str(observation["target"][0]), str(observation["calibrator"][0])
    xopt = ["--step", "0.8m", "--window-radius", "12", "--centroid", "quadratic",
            "--bad-pixels", "exclude", "--min-transmission", "0.8"]
    dopt = ["--draws", "2000", "--pfa", "0.01", "--seed", "3", "--max-sep", "120mas"]
    cli = tmp_path / "cli"
    cli.mkdir()
    assert main(["extract", t, "--calibrator", c, *xopt, "-q",
                 "-o", str(cli / "calibrated_kp.fits")]) == 0
    assert main(["detect", str(cli / "calibrated_kp.fits"), *dopt, "-q",
                 "-o", str(cli / "detection.fits")]) == 0
    assert main(["batch", "--glob", t, "--calibrator", c, *xopt, *dopt, "--workers", "1",
                 "-q", "-o", str(tmp_path / "batch")]) == 0
    entry = tmp_path / "batch" / "target"
    for name in ("calibrated_kp.fits", "detection.fits"):
        _same_products(cli / name, entry / name)
    with fits.open(entry / "calibrated_kp.fits") as h:
        assert h[0].header["WINRAD"] == 12.0        # the option reached the extraction


def test_process_observation_equals_the_steps(observation, tmp_path):
    """The Python driver: the same products as calling its steps one by one."""
    xo = ExtractOptions(step="0.8m", window_radius=14.0)
    do = DetectOptions(draws=1500, pfa=0.01, seed=2)
    out = process_observation(observation["target"], [observation["calibrator"]],
                              tmp_path / "a", extract_options=xo, detect_options=do)
    t = extract_observation(observation["target"], xo)
    c = extract_observation(observation["calibrator"], xo, model=t.kernel_model)
    step = tmp_path / "b"
    step.mkdir()
    calibrate_observation(t, [c], xo).write(step / "calibrated_kp.fits")
    cal = KernelPhaseData.read(step / "calibrated_kp.fits")
    detect_observation(cal, do).write(step / "detection.fits")
    for name in ("calibrated_kp.fits", "detection.fits"):
        _same_products(out["paths"][name.split("_")[0].split(".")[0]], step / name)
    assert out["result"].candidates["x"].size >= 1     # the companion at (80, 60) mas


def test_kernel_phase_data_round_trip(observation, tmp_path):
    kpd = extract_observation(observation["target"], ExtractOptions(step="0.8m",
                                                                    window_radius=15.5))
    kpd.detpa = np.linspace(0, 10, kpd.n_frame)
    path = kpd.write(tmp_path / "kp.fits")
    back = KernelPhaseData.read(path)
    np.testing.assert_array_equal(back.kp, kpd.kp)
    np.testing.assert_array_equal(back.kernel_model.kernel, kpd.kernel_model.kernel)
    np.testing.assert_array_equal(back.detpa, kpd.detpa)
    assert back.window == kpd.window == ExtractionWindow(40, 15.5)
    assert back.wavelengths.unit == u.um and np.allclose(back.wavelengths, kpd.wavelengths)
    with pytest.raises(KpifsError, match="exists"):
        kpd.write(path)
    with pytest.raises(KpifsError, match="not kernel-phase data"):
        KernelPhaseData.read(observation["target"][0])
    with pytest.raises(KpifsError, match="file not found"):
        KernelPhaseData.read(tmp_path / "missing.fits")


def test_detection_result_round_trip(tmp_path):
    from kpifs.detect.pipeline import _example_result
    res = _example_result()
    path = res.write(tmp_path / "det.fits")
    back = DetectionResult.read(path)
    assert (back.test, back.pfa, back.pd, back.threshold) == (res.test, res.pfa, res.pd,
                                                              res.threshold)
    np.testing.assert_allclose(back.grid.x, res.grid.x)
    np.testing.assert_allclose(back.grid.y, res.grid.y)
    np.testing.assert_array_equal(back.grid.valid, res.grid.valid)
    for name in ("statistic", "pfa_local", "pfa_global", "contrast", "contrast_err"):
        np.testing.assert_array_equal(getattr(back, name), getattr(res, name))
    assert sorted(back.limits) == sorted(res.limits)
    for k in res.limits:
        np.testing.assert_array_equal(back.limits[k], res.limits[k])
    np.testing.assert_allclose(back.wavelengths, res.wavelengths)
    assert len(back.candidates) == len(res.candidates) == 1
    np.testing.assert_allclose(back.candidates["fit_contrast"], res.candidates["fit_contrast"])
    assert back.energy == pytest.approx(res.energy)
    assert back.limit is back.limits["B"]
    # written again, the products are the same
    back.write(tmp_path / "again.fits")
    _same_products(path, tmp_path / "again.fits", history=False)


# --- the one wavelength rule ----------------------------------------------------------
@pytest.mark.parametrize("value, expected", [
    ("1.52um,1.6um", [1.52, 1.6]),
    ("1.52, 1.6", [1.52, 1.6]),
    ("1520,1600", [1.52, 1.6]),                 # nm, told from the values
    ([1.52e-6, 1.6e-6], [1.52, 1.6]),           # m
    ([1520, 1600] * u.nm, [1.52, 1.6]),
    ((1.52 * u.um, 1600 * u.nm), [1.52, 1.6]),
])
def test_wavelength_forms(value, expected):
    assert parse_wavelengths(value).to_value(u.um) == pytest.approx(expected)


@pytest.mark.parametrize("value, match", [
    ("1.52m,1.6um", "outside 0.3-30 um"),
    ([0, 1.6], "> 0"),
    ("1.5kg", "wrong unit"),
    ("wave.fits", "wavelength file not found"),
    ("", "empty"),
    ([] * u.um, "no wavelengths"),
    ([5e3, 6e5], "cannot tell the unit"),
    ([5000, 40000] * u.nm, "40 um is outside"),
])
def test_wavelength_refusals(value, match):
    with pytest.raises(KpifsError, match=match):
        parse_wavelengths(value)


def test_every_reader_follows_the_rule(tmp_path):
    """A list for SPHERE (was read as a file name), an override for CHARIS (was ignored)."""
    sphere = write_observation(simulate_scene("sphere", n_frames=1, npup=32, shape=(32, 32)),
                               tmp_path / "s", layout="sphere")
    wl = ",".join(f"{w:.4f}um" for w in np.linspace(1.0, 1.3, 39))
    with read_cube(sphere["target"][0], instrument="sphere", wavelengths=wl) as cube:
        assert cube.wavelengths[0].to_value(u.um) == pytest.approx(1.0)
    text = tmp_path / "wl.txt"
    np.savetxt(text, np.linspace(1000, 1300, 39))
    with read_cube(sphere["target"][0], instrument="sphere", wavelengths=str(text)) as cube:
        assert cube.wavelengths[-1].to_value(u.um) == pytest.approx(1.3)
    charis = write_observation(simulate_scene("charis", n_frames=1, npup=32, shape=(32, 32)),
                               tmp_path / "c", layout="charis")
    given = np.linspace(1.2, 2.4, 22) * u.um
    with read_cube(charis["target"], wavelengths=given) as cube:
        assert cube.instrument == "charis"
        np.testing.assert_allclose(cube.wavelengths, given)
    with pytest.raises(KpifsError, match="3 wavelength"):
        read_cube(charis["target"], wavelengths="1.2um,1.3um,1.4um")


# --- the package's structure ------------------------------------------------------------
def _module_name(path):
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _resolve(module, node, is_package):
    base = module.split(".") if is_package else module.split(".")[:-1]
    if node.level:
        base = base[:len(base) - (node.level - 1)]
        return ".".join(base + ([node.module] if node.module else []))
    return node.module


def test_imports_point_down_the_stack():
    """No import circle between kpifs modules, and no kpifs import hidden in a function."""
    graph, hidden = {}, []
    for path in PACKAGE.rglob("*.py"):
        if path.name == "_version.py":
            continue
        mod = _module_name(path)
        tree = ast.parse(path.read_text())
        deps = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                target = _resolve(mod, node, path.name == "__init__.py")
                if not target or not target.startswith("kpifs"):
                    continue
                names = [f"{target}.{a.name}" for a in node.names]
                deps.update(n for n in names + [target])
            elif isinstance(node, ast.Import):
                deps.update(a.name for a in node.names if a.name.startswith("kpifs"))
        for fn in ast.walk(tree):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for node in ast.walk(fn):
                    if isinstance(node, ast.ImportFrom) and (node.level or (
                            node.module or "").startswith("kpifs")):
                        hidden.append(f"{mod}.{fn.name}")
        graph[mod] = deps
    # the entry points load on first use, each import written out in a function: the
    # package's re-exports (``import kpifs`` stays fast) and the command line's command
    # modules (``kpifs --version`` does not load numpy)
    entry_points = {"kpifs._module_of", "kpifs._cli.main", "kpifs._cli._runner"}
    hidden = [h for h in hidden if h not in entry_points]
    assert not hidden, hidden
    modules = set(graph)
    edges = {m: {d for d in deps if d in modules and d != m} for m, deps in graph.items()}
    # a package's __init__ re-exports its modules: that is not an upward arrow
    edges = {m: {d for d in ds if not d.startswith(m + ".")} for m, ds in edges.items()}
    state = {}

    def visit(m, stack):
        state[m] = 1
        for d in edges[m]:
            if state.get(d) == 1:
                raise AssertionError("import circle: " + " -> ".join(stack + [m, d]))
            if d not in state:
                visit(d, stack + [m])
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m, [])
    # stages as packages (kpifs.model, kpifs.io, kpifs.extraction, ...) stack too: no
    # circle between them, each module counted in its package
    stage = {m: ".".join(m.split(".")[:2]) for m in modules}
    packages = {}
    for m, ds in edges.items():
        packages.setdefault(stage[m], set()).update(
            stage[d] for d in ds if stage[d] != stage[m] and stage[m] != "kpifs")
    state.clear()
    edges = packages
    for m in sorted(edges):
        if m not in state:
            visit(m, [])


def test_no_kpifs_module_loaded_lazily():
    """`kpifs._lazy.lazy_module` is for third-party modules only: a kpifs module loaded
    on first use would be an import that neither this test nor a reader sees."""
    calls = [f"{path.relative_to(PACKAGE.parent)}: {line.strip()}"
             for path in PACKAGE.rglob("*.py") for line in path.read_text().splitlines()
             if "lazy_module(\"kpifs" in line or "lazy_module('kpifs" in line]
    assert not calls, calls


def test_cli_start_imports_nothing_heavy():
    """`kpifs --help` / `--version` build the parser without numpy, astropy or scipy."""
    code = ("import sys, kpifs.cli; from kpifs._cli._parser import build_parser; "
            "build_parser(); print(sorted(m for m in ('numpy', 'astropy', 'scipy', "
            "'matplotlib') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "[]"


def test_kernel_model_registry_round_trip(tmp_path):
    km = KernelModel.from_pupil(make_pupil("vlt", step=1 * u.m))
    path = km.write(tmp_path / "model.fits")
    back = KernelModel.read(path)
    np.testing.assert_array_equal(back.kernel, km.kernel)
    assert "kpfits-model" in KernelModel.read.__doc__     # the registry lists the format
