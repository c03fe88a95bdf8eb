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
from kpifs.simulation.simulate import simulate_scene  # noqa: E402
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


@pytest.fixture(scope="module")
def small_archive(tmp_path_factory):
    d = tmp_path_factory.mktemp("small")
    lines = ["name,target,calibrator"]
    for i in range(4):
        obs = simulate_scene("paper", n_frames=60, seed=40 + i, npup=32, exptime=1 * u.s,
                             contrasts=0.0)
        write_observation(obs, d / f"s{i}")
        lines.append(f"s{i},s{i}/target.fits,s{i}/calibrator.fits")
    (d / "small.csv").write_text("\n".join(lines) + "\n")
    return d


SMALL = ["--step", "1.2m", "--draws", "1000", "--pfa", "0.01", "--workers", "1", "-q"]


def _long_manifest(small_archive, tmp_path, n=8):
    """The small archive's four observations named *n* times over (absolute paths): a
    batch that is still running when its first entry is done, however busy the machine
    (with four entries, a loaded machine could finish them all between two looks)."""
    lines = ["name,target,calibrator"]
    for k in range(n):
        s = small_archive / f"s{k % 4}"
        lines.append(f"e{k},{s / 'target.fits'},{s / 'calibrator.fits'}")
    path = tmp_path / "long.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_batch_rerun_is_keyed_on_options(small_archive, tmp_path, capsys):
    """A rerun skips entries made with the same options and inputs, and redoes the others."""
    manifest = str(small_archive / "small.csv")
    out = str(tmp_path / "out")
    assert main(["batch", manifest, *SMALL, "-o", out]) == 0
    first = Table.read(tmp_path / "out" / "summary.ecsv")
    assert set(first["status"]) == {"ok"}
    assert all("step=1.2" in o and "pfa=0.01" in o for o in first["options"])
    assert main(["batch", manifest, *SMALL, "-o", out]) == 0
    again = Table.read(tmp_path / "out" / "summary.ecsv")
    assert set(again["status"]) == {"skipped"}
    assert list(again["options_hash"]) == list(first["options_hash"])
    # other options: every entry is redone, and the summary says with what
    assert main(["batch", manifest, *[a if a != "0.01" else "0.02" for a in SMALL],
                 "-o", out]) == 0
    third = Table.read(tmp_path / "out" / "summary.ecsv")
    assert set(third["status"]) == {"ok"}
    assert all("redone" in m for m in third["message"])
    assert all("pfa=0.02" in o for o in third["options"])
    assert not set(third["options_hash"]) & set(first["options_hash"])
    from astropy.io import fits
    with fits.open(tmp_path / "out" / "s0" / "detection.fits") as h:
        assert h[0].header["KPHASH"] == third["options_hash"][0]
        assert h[0].header["PFA"] == 0.02
    # an input touched, its content the same: the same products, skipped (issue 37 #15)
    import os
    path = small_archive / "s1" / "target.fits"
    path.touch()
    assert main(["batch", manifest, *[a if a != "0.01" else "0.02" for a in SMALL],
                 "-o", out]) == 0
    assert set(Table.read(tmp_path / "out" / "summary.ecsv")["status"]) == {"skipped"}
    # an input replaced by another of the same size and modification time: redone
    st, data = os.stat(path), bytearray(path.read_bytes())
    with fits.open(path) as h:
        start = h[0]._data_offset if h[0].data is not None else h[1]._data_offset
    data[start + 1000] ^= 1                 # one bit of one pixel
    path.write_bytes(bytes(data))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert os.stat(path).st_size == st.st_size and os.stat(path).st_mtime_ns == st.st_mtime_ns
    assert main(["batch", manifest, *[a if a != "0.01" else "0.02" for a in SMALL],
                 "-o", out]) == 0
    fourth = Table.read(tmp_path / "out" / "summary.ecsv")
    assert dict(zip(fourth["name"], fourth["status"])) == {
        "s0": "skipped", "s1": "ok", "s2": "skipped", "s3": "skipped"}


def test_batch_interrupt_keeps_a_record(small_archive, tmp_path):
    """Ctrl-C: a short message, status 130, a summary of what finished; a rerun resumes."""
    import os
    import signal
    import time
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "kpifs", "batch", str(_long_manifest(small_archive, tmp_path)),
           *SMALL,
           "-o", str(out)]
    # Ctrl-C reaches the command even when this test runs in the background, where the
    # shell ignores SIGINT and the child would inherit that
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    t0 = time.time()
    while not (out / "e0" / "detection.fits").exists() and time.time() - t0 < 120:
        time.sleep(0.05)
    assert proc.poll() is None, "the batch finished before it could be interrupted"
    os.kill(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert "interrupted" in err and "summary.ecsv" in err
    summary = Table.read(out / "summary.ecsv")
    status = dict(zip(summary["name"], summary["status"]))
    assert status["e0"] == "ok"
    assert "interrupted" in status.values()
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    again = dict(zip(*Table.read(out / "summary.ecsv")[["name", "status"]].columns.values()))
    assert again["e0"] == "skipped"
    assert all(again[n] in ("ok", "skipped") for n in again)
    assert sum(s == "ok" for s in again.values()) == sum(s != "ok" for s in status.values())


def _entries(tmp_path, n=1):
    from kpifs.batch import BatchEntry
    return [BatchEntry(f"e{i}", [str(tmp_path / "missing.fits")], [[str(tmp_path / "c.fits")]])
            for i in range(n)]


def test_lock_refuses_a_second_run_and_takes_over_a_stale_one(tmp_path):
    """The folder's lock names its holder; a killed run's lock is detected and taken over."""
    import json
    import os
    import socket
    from kpifs._lock import FolderLock
    from kpifs.exceptions import KpifsError, KpifsWarning
    out = tmp_path / "out"
    out.mkdir()
    with FolderLock(out):
        info = json.loads((out / ".kpifs-batch.lock").read_text())
        assert info["pid"] == os.getpid() and info["host"] == socket.gethostname()
        with pytest.raises(KpifsError, match=rf"another kpifs batch writes in this folder "
                                             rf"\(pid {os.getpid()} on {socket.gethostname()}, "
                                             rf"since 20\d\d-"):
            run_batch(_entries(tmp_path), out, processes=False, progress=False)
    assert not (out / ".kpifs-batch.lock").exists()           # released
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()                                               # a pid that no longer runs
    (out / ".kpifs-batch.lock").write_text(json.dumps(
        {"pid": dead.pid, "host": socket.gethostname(), "time": 1.7e9}))
    with pytest.warns(KpifsWarning, match=f"stale batch lock \\(pid {dead.pid} on "):
        table = run_batch(_entries(tmp_path, 2), out, processes=False, progress=False)
    assert list(table["status"]) == ["failed", "failed"]
    assert not (out / ".kpifs-batch.lock").exists()
    # another host's lock cannot be checked: refused, with the file to remove if it is dead
    (out / ".kpifs-batch.lock").write_text(json.dumps(
        {"pid": 1, "host": "elsewhere.example", "time": 1.7e9}))
    with pytest.raises(KpifsError, match="pid 1 on elsewhere.example, since 2023-11-14"):
        run_batch(_entries(tmp_path), out, processes=False, progress=False)


def test_entry_names_stay_in_the_output_folder(tmp_path):
    """Names are plain folder names, and a name that is a link out of the folder is refused."""
    import os
    from kpifs.batch import BatchEntry, check_entry_name
    from kpifs.exceptions import KpifsError
    out = tmp_path / "out"
    out.mkdir()
    elsewhere = tmp_path / "earlier_run"
    elsewhere.mkdir()
    (elsewhere / "detection.fits").write_bytes(b"keep me")
    os.symlink(elsewhere, out / "link")
    for bad in ("../earlier_run", str(elsewhere), "a/b", "..", ""):
        with pytest.raises(KpifsError, match="not a plain folder name"):
            check_entry_name(bad)
    with pytest.raises(KpifsError, match="leads outside the output folder"):
        run_batch([BatchEntry("link", ["t.fits"], [["c.fits"]])], out, processes=False,
                  progress=False)
    assert (elsewhere / "detection.fits").read_bytes() == b"keep me"
    assert not (out / "summary.ecsv").exists()


def test_resume_digest_has_the_content_of_option_files(tmp_path):
    """An option file changed in place (same path) changes the digest that resume keys on."""
    from kpifs.workflow import observation_digest, options_record
    files = {k: tmp_path / f"{k}.txt" for k in ("wavelengths", "pa", "spectrum", "pupil")}
    for path in files.values():
        path.write_text("1.0\n")
    xo = ExtractOptions(wavelengths=str(files["wavelengths"]), pa=str(files["pa"]),
                        pupil=str(files["pupil"]))
    do = DetectOptions(spectrum=str(files["spectrum"]))
    rec = {**options_record(xo), **options_record(do)}
    import hashlib
    digest = hashlib.sha256(b"1.0\n").hexdigest()[:16]
    for k, path in files.items():
        assert rec[k] == f"{path} (sha256:{digest})"
    before = observation_digest(["t.fits"], [["c.fits"]], xo, do)
    for path in files.values():
        old = path.read_bytes()
        path.write_text("1.1\n")
        assert observation_digest(["t.fits"], [["c.fits"]], xo, do) != before, path
        path.write_bytes(old)
        assert observation_digest(["t.fits"], [["c.fits"]], xo, do) == before


def test_batch_redoes_an_entry_whose_wavelength_file_changed(small_archive, tmp_path):
    """The issue's case: the file given to --wavelengths edited in place, then a rerun."""
    from astropy.io import fits
    from kpifs.batch import BatchEntry
    wl = tmp_path / "wl.txt"
    wl.write_text("1.52\n1.60\n1.68\n")
    entry = [BatchEntry("s0", [str(small_archive / "s0" / "target.fits")],
                        [[str(small_archive / "s0" / "calibrator.fits")]])]
    opts = dict(extract_options=ExtractOptions(step=1.2 * u.m, wavelengths=str(wl)),
                detect_options=DetectOptions(draws=1000, pfa=1e-2), processes=False,
                progress=False)
    assert list(run_batch(entry, tmp_path / "out", **opts)["status"]) == ["ok"]
    assert list(run_batch(entry, tmp_path / "out", **opts)["status"]) == ["skipped"]
    wl.write_text("1.62\n1.70\n1.78\n")
    again = run_batch(entry, tmp_path / "out", **opts)
    assert list(again["status"]) == ["ok"] and "redone" in again["message"][0]
    with fits.open(tmp_path / "out" / "s0" / "calibrated_kp.fits") as h:
        np.testing.assert_allclose(h["CWAVEL"].data["CWAVEL"] * 1e6, [1.62, 1.70, 1.78])


def test_batch_ctrl_c_to_the_process_group(small_archive, tmp_path):
    """Ctrl-C as a terminal sends it (to every process of the group): one line, no worker
    tracebacks, a summary."""
    import os
    import signal
    import time
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "kpifs", "batch", str(_long_manifest(small_archive, tmp_path)),
           *SMALL,
           "-o", str(out)]
    # SIGINT as a terminal delivers it, even when this test runs in the background
    # (where the shell ignores SIGINT and the child would inherit that)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    t0 = time.time()
    while not (out / "e0" / "detection.fits").exists() and time.time() - t0 < 120:
        time.sleep(0.05)
    assert proc.poll() is None, "the batch finished before it could be interrupted"
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert (out / "summary.ecsv").exists() and not (out / ".kpifs-batch.lock").exists()
