"""Bad inputs through the command line: a clear one-line message naming the file and
the problem, exit status 2 for errors, inputs byte-identical, no partial output."""
import hashlib

import numpy as np
import pytest
from astropy.io import fits

from kpifs.cli import main
from kpifs.io.layouts import write_observation
from kpifs.simulate import simulate_scene


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    d = tmp_path_factory.mktemp("corpus")
    paper = simulate_scene("paper", n_frames=4, seed=3, npup=48)
    plain = write_observation(paper, d / "plain")
    charis = write_observation(simulate_scene("charis", n_frames=2, seed=3, npup=48,
                                              shape=(64, 64)), d / "charis", layout="charis")
    sphere = write_observation(simulate_scene("sphere", n_frames=2, seed=3, npup=48),
                               d / "sphere", layout="sphere")
    f = {"target": plain["target"][0], "cal": plain["calibrator"][0],
         "charis": charis["target"][0], "charis_tgt": charis["target"],
         "charis_cal": charis["calibrator"],
         "sphere_cube": sphere["target"][0]}
    with fits.open(f["target"]) as h:
        data, hdr = h[0].data.copy(), h[0].header.copy()
    f["truncated"] = d / "truncated.fits"
    f["truncated"].write_bytes(f["target"].read_bytes()[:10000])
    f["notfits"] = d / "notfits.fits"
    f["notfits"].write_text("SIMPLE = this is not FITS\n" * 20)
    f["naxis1"] = d / "spectrum.fits"
    fits.writeto(f["naxis1"], np.arange(100.0))
    f["naxis5"] = d / "fivedim.fits"
    fits.writeto(f["naxis5"], np.ones((2, 2, 3, 8, 8)))
    bad = data.copy()
    bad[2, 1] = np.nan
    f["nanslice"] = d / "nanslice.fits"
    fits.writeto(f["nanslice"], bad, hdr)
    bad = data.copy()
    bad[3] = 0
    f["zeroframe"] = d / "zeroframe.fits"
    fits.writeto(f["zeroframe"], bad, hdr)
    edge = np.roll(data, (-17, -17), axis=(2, 3))          # star 3 pixels from a corner
    f["edge"] = d / "edge.fits"
    fits.writeto(f["edge"], edge, hdr)
    for name, cards in {"nlam": dict(NLAM=20), "lammax": dict(LAM_MAX=3000.0)}.items():
        with fits.open(f["charis"]) as h:
            h[0].header.update(cards)
            f[name] = d / f"{name}_cube.fits"
            h.writeto(f[name])
    hdr2 = hdr.copy()
    del hdr2["KPWL3"]
    f["twochan"] = d / "twochannels.fits"
    fits.writeto(f["twochan"], data[:, :2], hdr2)
    hdr3 = hdr.copy()
    hdr3["PIXSCALE"] = 12.0
    f["otherscale"] = d / "otherscale.fits"
    fits.writeto(f["otherscale"], data, hdr3)
    f["single"] = d / "single.fits"
    fits.writeto(f["single"], data[:1], hdr)
    f["wl_unknown"] = d / "wl_unknown.txt"
    np.savetxt(f["wl_unknown"], [50.0, 60.0, 70.0])
    f["pupil_noscale"] = d / "pupil_noscale.fits"
    fits.writeto(f["pupil_noscale"], np.ones((64, 64)))
    f["adir"] = d / "adir.fits"
    f["adir"].mkdir()
    f["lone_sphere"] = d / "lone" / "science_cube.fits"
    f["lone_sphere"].parent.mkdir()
    f["lone_sphere"].write_bytes(f["sphere_cube"].read_bytes())
    return f


def _hashes(files):
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in files if p.is_file()}


CASES = [
    # (name, argv builder, expected exit, text in the message)
    ("truncated FITS", lambda f: ["extract", f["truncated"]], 2, "truncated.fits"),
    ("not FITS", lambda f: ["extract", f["notfits"]], 2, "notfits.fits: not a readable FITS"),
    ("NAXIS 1", lambda f: ["extract", f["naxis1"], "--wavelengths", "1.6um", "--pixscale",
                           "10mas"], 2, "spectrum.fits: no image data"),
    ("NAXIS 5", lambda f: ["extract", f["naxis5"], "--wavelengths", "1.5,1.6,1.7",
                           "--pixscale", "10mas"], 2, "5 dimensions"),
    ("NLAM vs cube", lambda f: ["extract", f["nlam"]], 2, "NLAM = 20 but the cube has 22"),
    ("LAM_MAX contradicts", lambda f: ["extract", f["lammax"]], 2, "LAM_MAX = 3000.0"),
    ("wavelength unit", lambda f: ["extract", f["target"], "--wavelengths", "1.5kg,1.6,1.7"],
     2, "wrong unit"),
    ("wavelength file unit", lambda f: ["extract", f["target"], "--wavelengths",
                                        f["wl_unknown"]], 2, "cannot tell the unit"),
    ("all-NaN slice", lambda f: ["extract", f["nanslice"]], 2,
     "nanslice.fits: frame 2, channel 1"),
    ("all-zero frame", lambda f: ["extract", f["zeroframe"]], 2, "zeroframe.fits: frame 3"),
    ("calibrator channels", lambda f: ["extract", f["target"], "--calibrator",
                                       f["twochan"]], 2, "twochannels.fits has channels"),
    ("calibrator pixel scale", lambda f: ["extract", f["target"], "--calibrator",
                                          f["otherscale"]], 2, "otherscale.fits has pixel"),
    ("single target frame", lambda f: ["extract", f["single"], "--calibrator", f["cal"]], 2,
     "single frame without a covariance"),
    ("input is a directory", lambda f: ["extract", f["adir"]], 2, "adir.fits: is a directory"),
    ("missing input", lambda f: ["extract", f["adir"].parent / "nope.fits"], 2,
     "nope.fits: file not found"),
    ("missing calibrator", lambda f: ["extract", f["target"], "--calibrator",
                                      f["adir"].parent / "nocal.fits"], 2, "nocal.fits"),
    ("pupil without scale", lambda f: ["extract", f["target"], "--pupil",
                                       f["pupil_noscale"]], 2, "PUPSCALE"),
    ("unknown pupil", lambda f: ["extract", f["target"], "--pupil", "keck"], 2,
     "unknown pupil 'keck'"),
    ("plain cube read as CHARIS", lambda f: ["extract", f["target"], "--instrument",
                                             "charis"], 2, "not a CHARIS pipeline cube"),
    ("SPHERE without wavelengths", lambda f: ["extract", f["lone_sphere"]], 2,
     "science_cube.fits: no wavelengths"),
    ("window larger than image", lambda f: ["extract", f["target"], "--window", "80"], 2,
     "larger than"),
    ("info on a truncated file", lambda f: ["info", f["truncated"]], 2, "truncated.fits"),
    # warnings: the job runs, the message says what happened
    ("star at the edge", lambda f: ["extract", f["edge"]], 0, "closer to the image edge"),
    ("fewer frames than kernels", lambda f: ["extract", f["target"], "--calibrator",
                                             f["cal"]], 0, "Ledoit-Wolf shrinkage"),
    ("Nyquist-limited channel", lambda f: ["extract", *f["charis_tgt"], "--calibrator",
                                           *f["charis_cal"]], 0, "beyond the Nyquist limit"),
]


@pytest.mark.parametrize("name, argv, code, text", CASES, ids=[c[0] for c in CASES])
def test_bad_input(corpus, tmp_path, capsys, name, argv, code, text):
    out = tmp_path / "out.fits"
    before = _hashes([p for v in corpus.values() for p in (v if isinstance(v, list) else [v])])
    args = [str(a) for a in argv(corpus)]
    if args[0] == "extract":
        args += ["-o", str(out)]
    assert main(args) == code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert text in err, err
    if code:
        lines = [ln for ln in err.splitlines() if ": error: " in ln]
        assert len(lines) == 1, err
        assert not out.exists()
    assert not list(tmp_path.glob(".out.fits*"))          # no temporary left behind
    assert _hashes(before) == before                      # inputs untouched


def test_existing_output_and_directory_output(corpus, tmp_path, capsys):
    out = tmp_path / "kp.fits"
    out.write_bytes(b"keep me")
    assert main(["extract", str(corpus["target"]), "-o", str(out)]) == 2
    assert "exists; pass overwrite=True (--overwrite)" in capsys.readouterr().err
    assert out.read_bytes() == b"keep me"
    assert main(["extract", str(corpus["target"]), "-o", str(tmp_path)]) == 2
    assert "is a directory" in capsys.readouterr().err
    assert main(["extract", str(corpus["target"]), "-o", str(tmp_path / "no" / "x.fits")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_never_overwrite_an_input(corpus, tmp_path, capsys):
    src = tmp_path / "cube.fits"
    src.write_bytes(corpus["target"].read_bytes())
    before = src.read_bytes()
    assert main(["extract", str(src), "-o", str(src), "--overwrite"]) == 2
    assert "refusing to overwrite an input" in capsys.readouterr().err
    assert src.read_bytes() == before
