"""Archive reprocessing on a local Dask cluster."""
import subprocess
import sys

import numpy as np
import pytest
import astropy.units as u
from astropy.table import Table

pytest.importorskip("dask.distributed")

from kpifs.batch import read_manifest, run_batch  # noqa: E402
from kpifs.cli import main  # noqa: E402
from kpifs.io.layouts import write_observation  # noqa: E402
from kpifs.simulate import simulate_scene  # noqa: E402
from kpifs.workflow import DetectOptions, ExtractOptions  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning",
                                        "ignore::ResourceWarning",
                                        "ignore::pytest.PytestUnraisableExceptionWarning")


def test_package_import_does_not_import_dask():
    code = "import sys, kpifs, kpifs.cli; print(any(m.startswith('dask') for m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    d = tmp_path_factory.mktemp("archive")
    for i, c in enumerate([3e-3, 0.0]):
        obs = simulate_scene("paper", n_frames=120, seed=10 + i, npup=64, exptime=1 * u.s,
                             contrasts=c)
        write_observation(obs, d / f"obs{i}")
    (d / "broken.fits").write_bytes(b"not a FITS file at all" * 10)
    (d / "archive.csv").write_text(
        "name,target,calibrator\n"
        "star_a,obs0/target.fits,obs0/calibrator.fits\n"
        "star_b,obs1/target.fits,obs1/calibrator.fits\n"
        "broken,broken.fits,obs1/calibrator.fits\n")
    return d


def test_batch_local_cluster_and_resume(archive, tmp_path):
    entries = read_manifest(archive / "archive.csv")
    opts = dict(extract_options=ExtractOptions(step=0.8 * u.m),
                detect_options=DetectOptions(draws=3000, pfa=1e-2))
    table = run_batch(entries, tmp_path, **opts, n_workers=2, processes=False,
                      progress=False)
    status = dict(zip(table["name"], table["status"]))
    assert status == {"star_a": "ok", "star_b": "ok", "broken": "failed"}
    rows = {r["name"]: r for r in table}
    assert "broken.fits" in rows["broken"]["message"]
    assert rows["star_a"]["n_candidates"] >= 1
    assert abs(rows["star_a"]["best_x"] - 80) < 15 and abs(rows["star_a"]["best_y"] - 60) < 15
    assert rows["star_b"]["n_candidates"] == 0
    assert (tmp_path / "star_a" / "detection.fits").exists()
    summary = Table.read(tmp_path / "summary.ecsv")
    assert len(summary) == 3
    # a rerun skips what is done, keeps its results, and retries the failure
    again = run_batch(entries, tmp_path, **opts, n_workers=1, processes=False,
                      progress=False)
    st = dict(zip(again["name"], again["status"]))
    assert st == {"star_a": "skipped", "star_b": "skipped", "broken": "failed"}
    assert again[again["name"] == "star_a"]["n_candidates"][0] == rows["star_a"]["n_candidates"]
    assert np.isclose(again[again["name"] == "star_a"]["best_x"][0], rows["star_a"]["best_x"])


def test_batch_cli_with_glob(archive, tmp_path, capsys):
    code = main(["batch", "--glob", str(archive / "obs0" / "target.fits"), "--calibrator",
                 str(archive / "obs0" / "calibrator.fits"), "--draws", "2000", "--step", "0.8m",
                 "--pfa", "0.01", "--workers", "1", "-q", "-o", str(tmp_path)])
    assert code == 0
    assert "1 entries: 1 processed" in capsys.readouterr().out
    assert main(["batch", "-o", str(tmp_path), "-q"]) == 2
    assert "nothing to do" in capsys.readouterr().err


def test_manifest_errors(tmp_path):
    from kpifs import KpifsError
    (tmp_path / "bad.csv").write_text("name,target\nx,y.fits\n")
    with pytest.raises(KpifsError, match="lacks column"):
        read_manifest(tmp_path / "bad.csv")
    (tmp_path / "dup.csv").write_text("name,target,calibrator\nx,a,b\nx,c,d\n")
    with pytest.raises(KpifsError, match="unique"):
        read_manifest(tmp_path / "dup.csv")
    with pytest.raises(KpifsError, match="not found"):
        read_manifest(tmp_path / "none.csv")
