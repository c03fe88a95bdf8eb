import hashlib
import shutil
import subprocess
import sys

import numpy as np
import pytest
from astropy.io import fits

from kpifs import __version__
from kpifs.cli import main
from kpifs.io.layouts import write_observation
from kpifs.simulation.simulate import simulate_scene


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    obs = simulate_scene("paper", n_frames=4, seed=5, npup=64)
    write_observation(obs, d)
    return d


def _run_error(capsys, argv, match):
    code = main(argv)
    captured = capsys.readouterr()
    assert code == 2, captured
    lines = [ln for ln in captured.err.splitlines() if "error" in ln]
    assert len(lines) == 1 and "Traceback" not in captured.err, captured.err
    assert match in lines[0], lines[0]
    return lines[0]


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert __version__ in capsys.readouterr().out


def test_kernel_command(tmp_path, capsys):
    out = tmp_path / "model.fits"
    assert main(["kernel", "--pupil", "subaru", "--step", "0.38m", "-o", str(out)]) == 0
    # the default (grey) Subaru model
    assert "337 sub-apertures, 676 uv points, rank 336, 340 kernel phases" in \
        capsys.readouterr().out
    with fits.open(out) as h:
        assert h["KER-MAT"].data.shape[0] == h[0].header["NKP"]
    _run_error(capsys, ["kernel", "--pupil", "subaru", "-o", str(out)], "--overwrite")
    assert main(["kernel", "--pupil", "subaru", "--offset", "0,0", "-o", str(out),
                 "--overwrite"]) == 0
    with fits.open(out) as h:
        # centro-symmetric: even pupil phases give no Fourier phase, rank ~ n_sub / 2
        assert h["KER-MAT"].header["RANK"] == len(h["APERTURE"].data) // 2 == 166


def test_extract_command(sim_dir, tmp_path, capsys):
    target = sim_dir / "target.fits"
    before = _sha(target)
    model = tmp_path / "model.fits"
    assert main(["kernel", "-o", str(model)]) == 0
    out = tmp_path / "kp.fits"
    assert main(["extract", str(target), "--wavelengths", "1.52um,1.60um,1.68um",
                 "--pixscale", "10.42mas", "--pupil", str(model), "-o", str(out)]) == 0
    assert _sha(target) == before
    with fits.open(out) as h:
        assert h[0].header["CONTENT"] == "KPFITS1"
        assert h[0].header["PSCALE"] == pytest.approx(10.42)
        assert h[0].header["KPSIMX"] == pytest.approx(80)     # input header kept
        assert h["KP-DATA"].data.shape == (4, 3, h[0].header["NKP"])
        np.testing.assert_allclose(h["CWAVEL"].data["CWAVEL"], [1.52e-6, 1.60e-6, 1.68e-6])
        assert any("kpifs" in str(x) for x in h[0].header["HISTORY"])
    # header cards give wavelengths and pixel scale; two cubes are concatenated
    out2 = tmp_path / "kp2.fits"
    assert main(["extract", str(target), str(sim_dir / "calibrator.fits"), "-o", str(out2)]) == 0
    with fits.open(out2) as h:
        assert h["KP-DATA"].data.shape[0] == 8


def test_extract_nyquist_option(sim_dir, tmp_path, capsys):
    target = sim_dir / "target.fits"
    out = tmp_path / "kp.fits"
    args = ["extract", str(target), "--pixscale", "25mas", "-o", str(out)]
    assert main(args) == 0
    assert "Nyquist" in capsys.readouterr().err
    out.unlink()
    _run_error(capsys, args + ["--nyquist", "raise"], "Nyquist")
    assert not out.exists()


def test_extract_single_precision_option(sim_dir, tmp_path):
    """--precision single: the same kernel phases to ~1e-6 rad, recorded in KPXOPTS."""
    out = {}
    for prec in ("double", "single"):
        out[prec] = tmp_path / f"{prec}.fits"
        assert main(["extract", str(sim_dir / "target.fits"), "--precision", prec, "-q",
                     "-o", str(out[prec])]) == 0
    a, b = (fits.getdata(out[p], "KP-DATA") for p in ("double", "single"))
    diff = np.max(np.abs(a - b))
    assert 0 < diff < 1e-5
    assert '"precision": "single"' in fits.getheader(out["single"])["KPXOPTS"]


@pytest.fixture
def bad_files(tmp_path, sim_dir):
    with fits.open(sim_dir / "target.fits") as h:
        data = h[0].data.copy()
        hdr = h[0].header.copy()
    files = {}
    d = data.copy()
    d[1, 0] = np.nan
    files["nan"] = tmp_path / "nanframe.fits"
    fits.writeto(files["nan"], d, hdr)
    d = data.copy()
    d[0, 2] = 0
    files["zero"] = tmp_path / "zeroframe.fits"
    fits.writeto(files["zero"], d, hdr)
    files["trunc"] = tmp_path / "truncated.fits"
    files["trunc"].write_bytes((sim_dir / "target.fits").read_bytes()[:20000])
    files["nowl"] = tmp_path / "nowave.fits"
    fits.writeto(files["nowl"], data)
    files["dir"] = tmp_path / "adir.fits"
    files["dir"].mkdir()
    return files


@pytest.mark.parametrize("key, extra, match", [
    ("nan", ["--bad-frames", "fail"], "nanframe.fits: 1 bad frame(s) of 4: frame(s) 1: empty "
                                      "(first at 1.520 um)"),
    ("zero", ["--bad-frames", "fail"], "zeroframe.fits: 1 bad frame(s) of 4: frame(s) 0: empty"),
    ("trunc", [], "truncated.fits"),
    ("nowl", ["--pixscale", "10mas"], "no wavelengths"),
    ("nowl", ["--wavelengths", "1.6um", "--pixscale", "10mas"], "1 wavelength(s) given"),
    ("nowl", ["--wavelengths=-1.5,1.6,1.7", "--pixscale", "10mas"], "> 0"),
    ("nowl", ["--wavelengths", "1.5,1.6,1.7", "--pixscale", "10mas", "--window", "64"],
     "larger than"),
    ("nowl", ["--wavelengths", "1.5,1.6,1.7"], "no pixel scale"),
    ("nowl", ["--wavelengths", "1.5,1.6,1.7", "--pixscale", "10mas", "--pupil", "hubble"],
     "unknown pupil 'hubble'"),
    ("nowl", ["--wavelengths", "1.5kg,1.6,1.7", "--pixscale", "10mas"], "wrong unit"),
    ("dir", [], "is a directory"),
])
def test_extract_bad_input(bad_files, tmp_path, capsys, key, extra, match):
    src = bad_files[key]
    before = _sha(src) if src.is_file() else None
    out = tmp_path / "out.fits"
    _run_error(capsys, ["extract", str(src), *extra, "-o", str(out)], match)
    assert not out.exists()
    assert not list(tmp_path.glob(".out.fits*"))   # no temporary left behind
    if before:
        assert _sha(src) == before


def test_existing_output_refused_before_work(sim_dir, tmp_path, capsys):
    out = tmp_path / "kp.fits"
    out.write_bytes(b"precious")
    _run_error(capsys, ["extract", str(sim_dir / "target.fits"), "-o", str(out)], "exists")
    assert out.read_bytes() == b"precious"


def test_simulate_command(tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", "--preset", "paper", "--frames", "2", "--separation", "150mas",
                 "--pa", "0deg", "--contrasts", "1e-3,1e-3,1e-3", "-q", "-o", str(out)]) == 0
    with fits.open(out / "target.fits") as h:
        assert h[0].header["KPSIMX"] == pytest.approx(150)
        assert h[0].header["KPSIMY"] == pytest.approx(0, abs=1e-9)
        assert h[0].header["KPSIMC2"] == pytest.approx(1e-3)
    _run_error(capsys, ["simulate", "--frames", "2", "-q", "-o", str(out)], "exists")


@pytest.mark.slow
def test_demo_command(tmp_path, capsys):
    """The README's main job: simulated CHARIS files -> ... -> the companion is found."""
    out = tmp_path / "demo"
    assert main(["demo", "-o", str(out), "--frames", "100", "--draws", "4000"]) == 0
    printed = capsys.readouterr()
    assert "warning" not in printed.err                 # no Nyquist warning to puzzle over
    assert "on the sky (East positive)" in printed.out  # every position names its frame
    # the simulated inputs were made in a temporary folder: the products alone are left
    assert not (out / "charis").exists()
    assert sum(p.stat().st_size for p in out.rglob("*") if p.is_file()) < 50 * 2 ** 20
    for name in ("detection.fits", "calibrated_kp.fits", "target_kp.fits",
                 "figures/detection_map.png", "figures/contrast_curves.png",
                 "figures/candidate_spectrum.png"):
        assert (out / name).exists(), name
    with fits.open(out / "detection.fits") as h:
        cand = h["CANDIDATES"].data
        assert len(cand) >= 1
        assert abs(cand["fit_x"][0] - (-100)) < 5 and abs(cand["fit_y"][0] - 83) < 5
    _run_error(capsys, ["demo", "-o", str(out), "-q"], "--overwrite")


def test_entry_point_subprocess():
    exe = shutil.which("kpifs")
    cmd = [exe] if exe else [sys.executable, "-m", "kpifs.cli"]
    res = subprocess.run(cmd + ["--version"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and "kpifs" in res.stdout
    res = subprocess.run(cmd + ["extract", "nonexistent.fits", "-o", "x.fits"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    assert "nonexistent.fits: file not found" in res.stderr
    assert "Traceback" not in res.stderr


def test_outputs_have_normal_permissions(tmp_path):
    import os
    out = tmp_path / "model.fits"
    assert main(["kernel", "-o", str(out)]) == 0
    umask = os.umask(0)
    os.umask(umask)
    assert (out.stat().st_mode & 0o777) == (0o666 & ~umask)


def test_example_data_extracts(tmp_path):
    from pathlib import Path
    example = Path(__file__).resolve().parents[1] / "data_examples" / "paper" / "target.fits"
    if not example.exists():
        pytest.skip("data_examples/ not present (installed without the sdist)")
    out = tmp_path / "kp.fits"
    assert main(["extract", str(example), "-o", str(out)]) == 0
    with fits.open(out) as h:
        assert h["KP-DATA"].data.shape == (10, 3, 340)


@pytest.mark.parametrize("layout, pattern, shape", [
    ("charis", "target/CRSA*_cube.fits", (2, 22, 48, 48)),
    ("sphere", "target/science_cube.fits", (2, 39, 48, 48))])
def test_example_layouts_read(layout, pattern, shape):
    from pathlib import Path
    from kpifs.io import read_cube
    base = Path(__file__).resolve().parents[1] / "data_examples" / layout
    files = sorted(base.glob(pattern))
    if not files:
        pytest.skip("data_examples/ not present")
    with read_cube(files) as cube:
        assert cube.instrument == layout and cube.shape == shape


def test_every_public_object_has_a_runnable_example():
    """Docstring examples are run by pytest-doctestplus; this checks none is missing."""
    import importlib
    import inspect
    mods = ["kpifs", "kpifs.model.pupil", "kpifs.model.kernel", "kpifs.model.window",
            "kpifs.data", "kpifs.extraction.prepare", "kpifs.extraction.extract",
            "kpifs.model.fourier", "kpifs.simulation.simulate", "kpifs.io",
            "kpifs.io.wavelengths", "kpifs.io.angles", "kpifs.io.charis", "kpifs.io.sphere",
            "kpifs.io.layouts", "kpifs.io.products", "kpifs.io.kpfits",
            "kpifs.calibration.calibrate", "kpifs.covariance",
            "kpifs.calibration.errormodel", "kpifs.inject", "kpifs.detect",
            "kpifs.detect.stats", "kpifs.detect.limits", "kpifs.detect.fit", "kpifs.detect.null",
            "kpifs.detect.maps", "kpifs.detect.roc", "kpifs.plotting", "kpifs.workflow",
            "kpifs.provenance", "kpifs.batch", "kpifs.demo", "kpifs.cli"]
    missing = []
    for m in mods:
        mod = importlib.import_module(m)
        for name in mod.__all__:
            obj = getattr(mod, name)
            if (inspect.isfunction(obj) or inspect.isclass(obj)) and \
                    ">>>" not in (inspect.getdoc(obj) or ""):
                missing.append(f"{m}.{name}")
    assert not missing, missing
