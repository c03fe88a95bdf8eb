"""Batch paths, workers' view of them, resume digests and progress (issues 37 #11, #15, 40):
fast checks, without a cluster."""
import os
import socket

from kpifs.batch import (BatchEntry, RunContext, absolute_entry, absolute_options,
                         process_entry, read_manifest)
from kpifs.provenance import inputs_digest
from kpifs.workflow import DetectOptions, ExtractOptions


def test_manifest_files_are_the_manifests_not_the_current_folders(tmp_path, monkeypatch):
    """A wavelength or angle file named in a manifest is the one next to the manifest, even
    when the current folder holds one of the same name (issue 37 #11)."""
    arch, here = tmp_path / "arch", tmp_path / "here"
    arch.mkdir()
    here.mkdir()
    for d in (arch, here):
        (d / "wl.txt").write_text("1.6\n")
        (d / "pa.txt").write_text("10\n")
    (arch / "m.csv").write_text("name,target,calibrator,wavelengths,pa,pixscale\n"
                                "a,t.fits,c1.fits;c2.fits|c3.fits,wl.txt,pa.txt,16.2mas\n"
                                "b,sub/t.fits,c.fits,1.52um,10,\n")
    monkeypatch.chdir(here)
    a, b = read_manifest("../arch/m.csv")
    assert a.wavelengths == str(arch / "wl.txt") and a.pa == str(arch / "pa.txt")
    assert a.target == [str(arch / "t.fits")]
    assert a.calibrators == [[str(arch / "c1.fits"), str(arch / "c2.fits")],
                             [str(arch / "c3.fits")]]
    assert a.pixscale == "16.2mas"
    assert (b.wavelengths, b.pa, b.pixscale, b.target) == ("1.52um", "10", None,
                                                           [str(arch / "sub" / "t.fits")])


def test_options_and_entries_made_absolute_on_the_client(tmp_path, monkeypatch):
    """What a worker elsewhere receives names no path relative to the client's folder."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pupil.fits").write_bytes(b"")
    xo = absolute_options(ExtractOptions(wavelengths="wl.txt", pa="12.5", pupil="pupil.fits",
                                         step="0.8m"), os.getcwd())
    assert (xo.wavelengths, xo.pa, xo.pupil, xo.step) == (
        str(tmp_path / "wl.txt"), "12.5", str(tmp_path / "pupil.fits"), "0.8m")
    assert absolute_options(ExtractOptions(pupil="niriss_nrm"), ".").pupil == "niriss_nrm"
    do = absolute_options(DetectOptions(spectrum="spec/flat.txt", basis="smooth:3"), ".")
    assert (do.spectrum, do.basis) == (str(tmp_path / "spec" / "flat.txt"), "smooth:3")
    e = absolute_entry(BatchEntry("x", ["../t.fits"], [["c.fits"]], wavelengths="w.fits"), ".")
    assert e.target == [str(tmp_path.parent / "t.fits")]
    assert e.calibrators == [[str(tmp_path / "c.fits")]] and e.wavelengths == str(
        tmp_path / "w.fits")


def test_a_worker_that_does_not_see_the_clients_folder_fails_the_entry(tmp_path):
    """An output folder without this run's lock (the same path on another filesystem) or an
    input the worker cannot see: the entry fails, naming the worker and the path, and
    nothing is written."""
    out = tmp_path / "out"
    out.mkdir()
    (tmp_path / "t.fits").write_bytes(b"x")
    (tmp_path / "c.fits").write_bytes(b"x")
    entry = BatchEntry("e", [str(tmp_path / "t.fits")], [[str(tmp_path / "c.fits")]])
    row = process_entry(entry, ExtractOptions(), DetectOptions(), str(out),
                        run=RunContext(token="abc"))
    assert row["status"] == "failed"
    assert f"{out}: process {os.getpid()} on {socket.gethostname()} does not see the " \
           f"client's output folder" in row["message"]
    assert list(out.iterdir()) == []
    gone = BatchEntry("e", [str(tmp_path / "t.fits")], [[str(tmp_path / "nowhere.fits")]])
    row = process_entry(gone, ExtractOptions(), DetectOptions(), str(out))
    assert f"{tmp_path / 'nowhere.fits'}: not found by process {os.getpid()}" in row["message"]
    wl = ExtractOptions(wavelengths=str(tmp_path / "wl.txt"))
    row = process_entry(entry, wl, DetectOptions(), str(out))
    assert f"{tmp_path / 'wl.txt'}: not found by process" in row["message"]
    assert list(out.iterdir()) == []


def test_digest_reads_the_content_not_the_size_and_time(tmp_path):
    """A file replaced by another of the same size and modification time changes the
    digest that resume keys on; a touch that changes nothing else does not (issue 37 #15)."""
    p = tmp_path / "cube.fits"
    p.write_bytes(b"A" * 5000)
    before = inputs_digest([p])
    st = os.stat(p)
    p.write_bytes(b"A" * 4999 + b"B")
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert (os.stat(p).st_size, os.stat(p).st_mtime_ns) == (st.st_size, st.st_mtime_ns)
    changed = inputs_digest([p])
    assert changed != before
    os.utime(p, ns=(st.st_atime_ns + 10**9, st.st_mtime_ns + 10**9))
    assert inputs_digest([p]) == changed
    p.write_bytes(b"A" * 5000)
    assert inputs_digest([p]) == before


def test_progress_counts_and_time_left(caplog):
    """Done, running, failed and left, and the time left, in the log for every entry."""
    import logging
    from kpifs._cluster import Progress
    shown = Progress(10, capacity=lambda: 2, enabled=False)
    shown.start -= 30                                   # 30 s elapsed
    with caplog.at_level(logging.INFO, logger="kpifs.batch"):
        shown.update("ok")
        shown.update("failed")
        shown.update("skipped")
    # 3 entries in 30 s, 7 to go: 70 s
    assert caplog.records[-1].getMessage() == ("batch: 2 done, 2 running, 1 failed, 5 left "
                                               "of 10, about 1 min 10 s left")
