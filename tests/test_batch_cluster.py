"""`kpifs batch --scheduler` on a real Dask cluster: a `dask scheduler` and two `dask worker`
processes started in a folder of their own, as on any cluster (issue 40)."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import astropy.units as u
from astropy.io import fits
from astropy.table import Table

pytest.importorskip("dask.distributed")

from kpifs.io.layouts import write_observation  # noqa: E402
from kpifs.simulation.simulate import simulate_scene  # noqa: E402

pytestmark = [pytest.mark.slow,
              pytest.mark.filterwarnings("ignore::DeprecationWarning",
                                         "ignore::ResourceWarning",
                                         "ignore::pytest.PytestUnraisableExceptionWarning")]

OPTIONS = ["--step", "1.2m", "--draws", "1000", "--pfa", "0.01", "-q"]


def _start(cmd, cwd, log, env=None):
    return subprocess.Popen(cmd, cwd=cwd, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True, env=env)


def _stop(procs):
    for p in procs:
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
    deadline = time.time() + 20
    for p in procs:
        try:
            p.wait(timeout=max(0.1, deadline - time.time()))
        except subprocess.TimeoutExpired:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            p.wait(timeout=10)


@pytest.fixture
def cluster(tmp_path):
    """A scheduler and two single-thread workers, each its own process, in ``home`` (their
    current folder) with Dask's scratch space in ``scratch``; the scheduler gives up on an
    entry whose worker dies (so that a killed worker's entry is marked failed)."""
    home, scratch = tmp_path / "home", tmp_path / "scratch"
    home.mkdir()
    scratch.mkdir()
    env = dict(os.environ, DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES="0")
    log = open(tmp_path / "cluster.log", "w")
    procs = []
    try:
        sfile = scratch / "scheduler.json"
        procs.append(_start([sys.executable, "-m", "distributed.cli.dask_scheduler",
                             "--port", "0", "--no-dashboard", "--scheduler-file", str(sfile)],
                            home, log, env))
        t0 = time.time()
        while not sfile.exists() and time.time() - t0 < 60:
            time.sleep(0.1)
        address = json.loads(sfile.read_text())["address"]
        for _ in range(2):
            procs.append(_start([sys.executable, "-m", "distributed.cli.dask_worker", address,
                                 "--nthreads", "1", "--no-dashboard",
                                 "--local-directory", str(scratch)], home, log, env))
        from dask.distributed import Client
        with Client(address, timeout=60) as client:
            client.wait_for_workers(2, timeout=120)
        yield {"address": address, "home": home, "procs": procs}
    finally:
        _stop(procs)
        log.close()


@pytest.fixture
def archive(tmp_path):
    """Six entries in ``arch`` with a manifest whose paths are relative to its folder, one
    with a wavelength file next to the manifest; a decoy of that file where the client runs."""
    d = tmp_path / "arch"
    lines = ["name,target,calibrator,wavelengths"]
    for i in range(6):
        obs = simulate_scene("paper", n_frames=60, seed=70 + i, npup=32, exptime=1 * u.s,
                             contrasts=3e-2 if i in (0, 3) else 0.0)
        write_observation(obs, d / f"s{i}")
        lines.append(f"s{i},s{i}/target.fits,s{i}/calibrator.fits," + ("wl.txt" if i == 1 else ""))
    wl = obs.wavelengths.to_value(u.um)
    (d / "wl.txt").write_text("\n".join(f"{w:.4f}" for w in wl * 1.01) + "\n")
    (d / "m.csv").write_text("\n".join(lines) + "\n")
    client = tmp_path / "client"
    client.mkdir()
    (client / "wl.txt").write_text("\n".join(f"{w:.4f}" for w in wl * 0.9) + "\n")
    return d, client, wl * 1.01


def _tree(folder):
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in Path(folder).rglob("*")}


def _batch(client_dir, *args, timeout=600):
    return subprocess.Popen([sys.executable, "-m", "kpifs", "batch", "../arch/m.csv", *OPTIONS,
                             *args], cwd=client_dir, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


def _candidates(path):
    with fits.open(path) as h:
        return Table(h["CANDIDATES"].data)


def _same_candidates(a, b):
    """Equal candidate tables: a worker's single-threaded BLAS rounds in another order
    (1e-12, carried to ~1e-9 by the fits and to 1e-4 by P_FAs read from the null's tail:
    tests/test_workflow.py)."""
    ta, tb = _candidates(a), _candidates(b)
    assert ta.colnames == tb.colnames and len(ta) == len(tb)
    for col in ta.colnames:
        x, y = np.asarray(ta[col]), np.asarray(tb[col])
        if x.dtype.kind not in "fc":
            np.testing.assert_array_equal(x, y, err_msg=col)
            continue
        rtol = 1e-4 if "pfa" in col else 1e-6 if col.startswith("fit_") else 1e-9
        np.testing.assert_allclose(x, y, rtol=rtol, atol=1e-300, err_msg=col)


def _kill_a_busy_worker(address, out, proc, timeout=300):
    """SIGKILL the worker process running an entry that has started writing; its name."""
    from dask.distributed import Client
    with Client(address, timeout=60) as c:
        pids = c.run(os.getpid)
        t0 = time.time()
        while time.time() - t0 < timeout and proc.poll() is None:
            busy = {w: keys for w, keys in c.processing().items() if keys}
            started = {p.name.split(".")[0] for p in (out / ".kpifs-partial").glob("*")} \
                if (out / ".kpifs-partial").exists() else set()
            for w, keys in busy.items():
                names = {str(k).replace("kpifs-", "") for k in keys} & started
                if names and w in pids:
                    os.kill(pids[w], signal.SIGKILL)
                    return names.pop()
            time.sleep(0.05)
    raise AssertionError("no entry was seen running")


def test_batch_on_a_real_cluster(cluster, archive, tmp_path):
    """Paths relative to the manifest's folder, workers elsewhere: every product in -o, the
    same candidates as a local run, nothing written anywhere else; a worker killed
    mid-entry leaves no partial product, and a rerun completes all six."""
    arch, client, wl = archive
    local = subprocess.run([sys.executable, "-m", "kpifs", "batch", "../arch/m.csv", *OPTIONS,
                            "--workers", "1", "-o", "local"], cwd=client, capture_output=True,
                           text=True, timeout=900)
    assert local.returncode == 0, local.stderr
    before = {k: _tree(f) for k, f in (("home", cluster["home"]), ("arch", arch),
                                       ("client", client))}
    proc = _batch(client, "--scheduler", cluster["address"], "-o", "out")
    try:
        killed = _kill_a_busy_worker(cluster["address"], client / "out", proc)
        _, err = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    out = client / "out"
    summary = Table.read(out / "summary.ecsv")
    status = dict(zip(summary["name"], summary["status"]))
    # the entry it ran failed (and any queued on it: Dask gives each worker a little
    # ahead), with a message that says why; the others are done
    failed = {n for n, s in status.items() if s == "failed"}
    assert killed in failed and proc.returncode == 1, (status, err)
    assert set(status.values()) == {"ok", "failed"}, status
    for row in summary[summary["status"] == "failed"]:
        assert "died" in row["message"] and "KilledWorker" in row["message"]
        assert not (out / row["name"] / "detection.fits").exists()
    assert not (out / ".kpifs-partial").exists() and not list(out.rglob("*.tmp"))
    for name in [n for n, s in status.items() if s == "ok"]:
        assert sorted(p.name for p in (out / name).iterdir()) == ["calibrated_kp.fits",
                                                                  "detection.fits"]
    # a rerun finishes what is missing and keeps the rest
    again = _batch(client, "--scheduler", cluster["address"], "-o", "out")
    _, err = again.communicate(timeout=600)
    assert again.returncode == 0, err
    summary = Table.read(out / "summary.ecsv")
    status = dict(zip(summary["name"], summary["status"]))
    assert status == {f"s{i}": "ok" if f"s{i}" in failed else "skipped" for i in range(6)}
    # the same answers as the local run, and the manifest's own wavelength file used
    for i in range(6):
        _same_candidates(client / "local" / f"s{i}" / "detection.fits",
                         out / f"s{i}" / "detection.fits")
        with fits.open(out / f"s{i}" / "detection.fits") as h, \
                fits.open(client / "local" / f"s{i}" / "detection.fits") as g:
            assert h[0].header["KPHASH"] == g[0].header["KPHASH"]
    assert len(_candidates(out / "s0" / "detection.fits")) >= 1
    with fits.open(out / "s1" / "calibrated_kp.fits") as h:
        np.testing.assert_allclose(h["CWAVEL"].data["CWAVEL"] * 1e6, wl, rtol=1e-6)
    # nothing written elsewhere: not where the workers run, not in the archive, and in the
    # client's folder only the two output folders
    after = {k: _tree(f) for k, f in (("home", cluster["home"]), ("arch", arch),
                                      ("client", client))}
    assert after["home"] == before["home"]
    assert after["arch"] == before["arch"]
    assert {k.split("/")[0] for k in set(after["client"]) - set(before["client"])} == {"out"}


def test_scheduler_lost_stops_with_a_summary(cluster, archive):
    """The scheduler killed mid-run: a one-line message naming it, exit 2, and a summary
    written as entries finished: what finished is 'ok', the rest 'interrupted'; a rerun on
    a new cluster would resume (the products are whole)."""
    _, client, _ = archive
    proc = _batch(client, "--scheduler", cluster["address"], "-o", "out")
    out = client / "out"
    try:
        t0 = time.time()
        while time.time() - t0 < 300 and proc.poll() is None:
            if (out / "summary.ecsv").exists():       # written as the first entry finished
                early = Table.read(out / "summary.ecsv")
                if "ok" in set(early["status"]):
                    break
            time.sleep(0.05)
        assert "pending" in set(early["status"]), list(early["status"])
        cluster["procs"][0].kill()                     # the scheduler
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 2, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert f"lost the Dask scheduler at {cluster['address']}" in err
    assert "summary.ecsv" in err and "rerun to resume" in err
    summary = Table.read(out / "summary.ecsv")
    assert set(summary["status"]) <= {"ok", "interrupted"} and "ok" in set(summary["status"])
    for row in summary:
        assert (out / row["name"] / "detection.fits").exists() == (row["status"] == "ok")
    assert not (out / ".kpifs-batch.lock").exists()
