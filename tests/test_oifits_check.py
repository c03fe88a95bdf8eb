"""Every OIFITS file kpifs writes passes OIFITSlib's strict checker (``oifits-check``:
"All checks passed") and is read by the ``oifits`` package.

The checker is taken from ``KPIFS_OIFITS_CHECK`` (its path; CI builds it, `.ci/run`),
else built from ``../shared/tools`` when cmake, cfitsio and glib are there; the tests
skip cleanly where neither is possible."""
import os
import shutil
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pytest
from astropy import units as u
from astropy.io import fits

from kpifs import KernelModel, KernelPhaseData, PupilModel, make_pupil
from kpifs.cli import main

from test_oifits import _mask_kpd, standin

TOOLS = Path(__file__).resolve().parents[1].parent / "shared" / "tools"


def _buildable():
    if not (TOOLS / "build_oifits_check.sh").is_file() or shutil.which("cmake") is None:
        return False
    pc = shutil.which("pkg-config")
    return pc is not None and \
        subprocess.run([pc, "--exists", "cfitsio", "glib-2.0"]).returncode == 0


@pytest.fixture(scope="session")
def oifits_check(tmp_path_factory):
    """``check(path) -> output`` of oifits-check on *path*."""
    exe = os.environ.get("KPIFS_OIFITS_CHECK", "").strip()
    if not exe:
        if not _buildable():
            pytest.skip("oifits-check unavailable: KPIFS_OIFITS_CHECK unset and "
                        "../shared/tools or its build dependencies absent")
        out = tmp_path_factory.mktemp("oifits_check")
        r = subprocess.run(["bash", str(TOOLS / "build_oifits_check.sh"), str(out)],
                           capture_output=True, text=True, timeout=600)
        if r.returncode != 0:
            pytest.skip(f"oifits-check could not be built: {r.stderr[-300:]}")
        exe = str(out / "oifits-check")
    if not os.access(exe, os.X_OK):
        pytest.skip(f"KPIFS_OIFITS_CHECK={exe} is not an executable")
    env = dict(os.environ, LD_LIBRARY_PATH=str(Path(exe).parent))

    def check(path):
        r = subprocess.run([exe, str(path)], capture_output=True, text=True, env=env,
                           timeout=120)
        return r.stdout + r.stderr
    return check


def _three_holes():
    xy = np.array([[0.0, 0.0], [2.0, 0.3], [0.7, 1.9]])
    return KernelModel.from_pupil(PupilModel(xy * u.m, step=0.4 * u.m, name="three holes",
                                             meta={"hole_diameter_m": 0.4}))


def _written(tmp_path):
    """Every kind of OIFITS kpifs writes: channels with correlations, one channel, one
    triangle (no OI_CORR), uncalibrated frames with amplitudes (OI_VIS2), a file read
    from another tool's OIFITS and written again, and `kpifs extract -o x.oifits`."""
    out = {}
    out["3 channels, OI_CORR"] = _mask_kpd().write(tmp_path / "a.oifits")
    out["1 channel"] = _mask_kpd(wl=(4.8,)).write(tmp_path / "b.oifits")
    km = _three_holes()
    one = KernelPhaseData(np.full((1, 1, km.n_kp), 0.01), [2.2] * u.um, 20 * u.mas, km,
                          covariance=np.eye(km.n_kp)[None] * 1e-4, detpa=[0.0],
                          meta={"calibrated": True})
    out["one triangle"] = one.write(tmp_path / "c.oifits")
    km7 = KernelModel.from_pupil(make_pupil("niriss_nrm"))
    rng = np.random.default_rng(0)
    frames = KernelPhaseData(rng.normal(0, 0.01, (6, 2, km7.n_kp)), [4.3, 4.8] * u.um,
                             65.6 * u.mas, km7, detpa=[10.0] * 6,
                             amplitudes=1 - np.abs(rng.normal(0, 0.05, (6, 2, km7.n_uv))),
                             meta={"calibrated": False})
    out["frames, OI_VIS2, uncalibrated"] = frames.write(tmp_path / "d.oifits")
    src = tmp_path / "amical.oifits"
    standin(src, wl=(3.8e-6, 4.8e-6), primary=True)
    out["read and written again"] = KernelPhaseData.read(src).write(tmp_path / "e.oifits")
    return out


@pytest.mark.filterwarnings("ignore::kpifs.KpifsWarning")
def test_every_written_oifits_passes_the_checker(tmp_path, oifits_check):
    files = _written(tmp_path)
    for what, path in files.items():
        report = oifits_check(path)
        assert "All checks passed" in report, f"{what}:\n{report}"
        assert "WARNING" not in report, f"{what}:\n{report}"


@pytest.mark.filterwarnings("ignore::kpifs.KpifsWarning")
def test_every_written_oifits_read_by_the_oifits_package(tmp_path):
    oifits = pytest.importorskip("oifits")
    for what, path in _written(tmp_path).items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            data = oifits.open(str(path))
        with fits.open(path) as h:
            assert len(data.t3) == len(h["OI_T3"].data), what
            phi = np.array([t.t3phi for t in data.t3]).reshape(h["OI_T3"].data["T3PHI"].shape)
            assert np.allclose(phi, h["OI_T3"].data["T3PHI"]), what


@pytest.mark.slow
def test_extract_writes_a_passing_oifits(tmp_path, oifits_check):
    """`kpifs extract --pupil sphere_sam7 -o x.oifits` (the command line's writer)."""
    from kpifs.io import write_observation
    from kpifs.simulation.simulate import simulate_scene
    files = write_observation(simulate_scene("sphere-sam", n_frames=4, npup=48, seed=2),
                              tmp_path / "sim")
    out = tmp_path / "cal.oifits"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["extract", str(files["target"][0]), "--pupil", "sphere_sam7",
                     "--calibrator", str(files["calibrator"][0]), "-o", str(out),
                     "--quiet"]) == 0
    report = oifits_check(out)
    assert "All checks passed" in report, report
