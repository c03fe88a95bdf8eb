"""One driver (issue 38, item 3): every option of `kpifs extract` and `kpifs detect` reaches
`kpifs batch` and the Python driver with the same meaning and default, and `kpifs batch`
reduces JWST filter pairs and angular-differential sequences as `extract` + `detect` do."""
import argparse
import warnings

import numpy as np
import pytest
import astropy.units as u

from kpifs._cli._options import DETECT_FIELDS, EXTRACT_FIELDS, detect_options, extract_options
from kpifs._cli._parser import build_parser
from kpifs._defaults import DETECT, EXTRACT
from kpifs.cli import main
from kpifs.io.layouts import write_observation
from kpifs.simulation.simulate import simulate_scene
from kpifs.workflow import DetectOptions, ExtractOptions

#: Options that name a command's inputs and outputs, not how they are reduced: a batch
#: takes those from its manifest and its output folder.
NOT_REDUCTION = {"extract": {"output", "overwrite", "calibrator"},
                 "detect": {"output", "overwrite", "calibrator", "plots", "deprecated_step"}}
COMMON = {"help", "verbose", "quiet", "debug"}


def _options(command):
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {a.dest: a for a in sub.choices[command]._actions
            if a.option_strings and a.dest not in COMMON}


def _sample(action):
    """A value of the option other than its default, as typed on the command line."""
    if action.nargs == 0:
        return []
    if action.choices:
        return [next(c for c in action.choices if c != action.default)]
    if action.dest == "instrument":            # the registry's names (kpifs.io.instruments)
        return ["nirc2"]
    return ["7" if action.type is int else "0.3" if action.type is float else "0.55"]


def _fields(command):
    return {v: ("extract", k) for k, v in EXTRACT_FIELDS.items()} if command == "extract" \
        else {v: ("detect", k) for k, v in DETECT_FIELDS.items()}


@pytest.mark.parametrize("command", ["extract", "detect"])
def test_batch_and_the_driver_take_every_option(command):
    """Each reduction option of the command: the same option in `kpifs batch` (flags,
    default, choices, type), a field of the driver's options with the same default
    (`kpifs._defaults`), and a value given to either command lands in that field."""
    mine, batch = _options(command), _options("batch")
    fields = _fields(command)
    defaults = {"extract": EXTRACT, "detect": DETECT}
    objects = {"extract": (extract_options, ExtractOptions()),
               "detect": (detect_options, DetectOptions())}
    checked = set()
    for dest, action in mine.items():
        if dest in NOT_REDUCTION[command]:
            continue
        assert dest in fields, f"kpifs {command} {action.option_strings}: no driver field"
        kind, field = fields[dest]
        assert dest in batch, f"kpifs batch lacks {action.option_strings}"
        other = batch[dest]
        for attr in ("option_strings", "default", "choices", "type", "const", "nargs"):
            assert getattr(other, attr) == getattr(action, attr), (dest, attr)
        build, default_object = objects[kind]
        assert action.default == defaults[kind][field] == getattr(default_object, field), dest
        flag = action.option_strings[-1]
        value = _sample(action)
        given = {}
        for cmd, head in ((command, ["in.fits"]), ("batch", ["m.csv"])):
            args = build_parser().parse_args([cmd, *head, flag, *value, "-o", "out"])
            given[cmd] = getattr(build(args), field)
        assert given[command] == given["batch"] != action.default, (dest, given)
        checked.add(dest)
    assert checked == set(fields)         # and every field the command line maps is an option


def test_extract_and_detect_defaults_are_written_once():
    """Every driver field has its default from `kpifs._defaults`, and nothing else."""
    import dataclasses
    for cls, table in ((ExtractOptions, EXTRACT), (DetectOptions, DETECT)):
        fields = {f.name: f.default for f in dataclasses.fields(cls)}
        assert fields == table


@pytest.fixture(scope="module")
def jwst_pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("jwst")
    files = {"target": [], "calibrator": []}
    for wl, ps in ((1.5106, 31.0), (4.8213, 63.0)):
        obs = simulate_scene("nircam", wavelengths=[wl] * u.um, pixscale=ps * u.mas,
                             n_frames=6, npup=32, shape=(32, 32), seed=int(ps))
        f = write_observation(obs, d / f"f{int(ps)}", layout="jwst")
        for k in files:
            files[k] += [str(p) for p in f[k]]
    return d, files


@pytest.fixture(scope="module")
def rotating(tmp_path_factory):
    """A pupil-tracking sequence over 60 deg (plain cubes, angles in a file next to them)."""
    d = tmp_path_factory.mktemp("adi")
    detpa = np.linspace(0.0, 60.0, 24)
    obs = simulate_scene("paper", n_frames=24, npup=32, seed=5, exptime=1 * u.s,
                         detpa=detpa, sky_offset=[90.0, 60.0] * u.mas, contrasts=2e-2)
    files = write_observation(obs, d)
    (d / "angles.txt").write_text("\n".join(f"{a:.3f}" for a in detpa) + "\n")
    return d, files


def _run(argv):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return main(argv)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::ResourceWarning",
                            "ignore::pytest.PytestUnraisableExceptionWarning")
def test_batch_reduces_filter_pairs_and_rotating_sequences(jwst_pair, rotating, tmp_path,
                                                           monkeypatch):
    """A manifest of a JWST filter pair and of an angular-differential sequence (no
    calibrator, angles from a file named relative to the manifest): the same products as
    `kpifs extract` + `kpifs detect`."""
    pytest.importorskip("dask.distributed")
    from test_workflow import _same_products
    jd, jf = jwst_pair
    ad, af = rotating
    dopt = ["--draws", "1000", "--pfa", "0.05", "-q"]
    cli = tmp_path / "cli"
    cli.mkdir()
    monkeypatch.chdir(tmp_path)
    assert _run(["extract", *jf["target"], "--calibrator", *jf["calibrator"], "--pupil",
                 "niriss_nrm", "-q", "-o", str(cli / "jw_kp.fits")]) == 0
    assert _run(["detect", str(cli / "jw_kp.fits"), *dopt, "-o", str(cli / "jw.fits")]) == 0
    assert _run(["extract", str(af["target"][0]), "--angular-differential", "--pa",
                 str(ad / "angles.txt"), "--step", "1.2m", "-q",
                 "-o", str(cli / "adi_kp.fits")]) == 0
    assert _run(["detect", str(cli / "adi_kp.fits"), *dopt, "-o", str(cli / "adi.fits")]) == 0
    # one manifest per kind (the options differ), paths relative to each manifest
    (jd / "m.csv").write_text("name,target,calibrator\njw,"
                              + ";".join(p[len(str(jd)) + 1:] for p in jf["target"]) + ","
                              + ";".join(p[len(str(jd)) + 1:] for p in jf["calibrator"]) + "\n")
    (ad / "m.csv").write_text("name,target,calibrator,pa\nadi,target.fits,,angles.txt\n")
    assert _run(["batch", str(jd / "m.csv"), "--pupil", "niriss_nrm", *dopt, "--workers", "1",
                 "-o", "out_jw"]) == 0
    assert _run(["batch", str(ad / "m.csv"), "--angular-differential", "--step", "1.2m", *dopt,
                 "--workers", "1", "-o", "out_adi"]) == 0
    for cli_kp, cli_det, entry in (("jw_kp.fits", "jw.fits", "out_jw/jw"),
                                   ("adi_kp.fits", "adi.fits", "out_adi/adi")):
        _same_products(cli / cli_kp, tmp_path / entry / "calibrated_kp.fits")
        _same_products(cli / cli_det, tmp_path / entry / "detection.fits")
    # a rerun skips both: the digest of the products is the one the batch expects
    assert _run(["batch", str(ad / "m.csv"), "--angular-differential", "--step", "1.2m", *dopt,
                 "--workers", "1", "-o", "out_adi"]) == 0
    from astropy.table import Table
    assert list(Table.read(tmp_path / "out_adi" / "summary.ecsv")["status"]) == ["skipped"]
    assert _run(["batch", str(jd / "m.csv"), "--pupil", "niriss_nrm", *dopt, "--workers", "1",
                 "-o", "out_jw"]) == 0
    assert list(Table.read(tmp_path / "out_jw" / "summary.ecsv")["status"]) == ["skipped"]
