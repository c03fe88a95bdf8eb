"""The command line's help and vocabulary (issue 24): every option of every command has
help text that says its default, the examples keep their line breaks, ``--step`` is the
pupil grid's step everywhere."""
import argparse
import warnings

import pytest

from kpifs.cli import main
from kpifs._cli._parser import build_parser

_FLAGS = (argparse._StoreTrueAction, argparse._StoreConstAction, argparse._CountAction,
          argparse._HelpAction, argparse._VersionAction)


def _commands():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return parser, sub.choices


def test_every_option_has_help_that_shows_its_default():
    _, commands = _commands()
    assert set(commands) == {"kernel", "extract", "model-check", "inject", "info",
                             "simulate", "detect", "roc", "batch", "demo"}
    missing, no_default = [], []
    for name, p in commands.items():
        for action in p._actions:
            if action.help == argparse.SUPPRESS:
                continue
            flag = "/".join(action.option_strings) or action.dest
            if not (action.help or "").strip():
                missing.append(f"{name} {flag}")
                continue
            if not action.option_strings or isinstance(action, _FLAGS):
                continue            # positional inputs and on/off flags have no default
            text = action.help % {"default": action.default}
            if "default" not in text and "required" not in text:
                no_default.append(f"{name} {flag}")
            if "%(default)s" in action.help:
                assert action.default is not None, f"{name} {flag}"
    assert not missing, f"options without help: {missing}"
    assert not no_default, f"options whose help does not say the default: {no_default}"


def test_step_means_the_pupil_grid_everywhere():
    _, commands = _commands()
    for name, p in commands.items():
        for action in p._actions:
            if "--step" in action.option_strings and action.help != argparse.SUPPRESS:
                assert "pupil" in action.help, name
            if "--grid-step" in action.option_strings:
                assert "search grid" in action.help, name
    # detect's old --step (its search grid) still works, with a warning, for one release
    from kpifs._cli.detect import _grid_step
    args = commands["detect"].parse_args(["kp.fits", "--step", "5mas", "-o", "x.fits"])
    with pytest.warns(Warning, match="--grid-step"):
        _grid_step(args)
    assert args.grid_step == "5mas"


def test_help_lists_exit_codes_pupils_and_keeps_example_lines():
    parser, commands = _commands()
    text = parser.format_help()
    for code in ("0 success", "1 batch", "2 bad input", "3 internal error", "130 interrupted"):
        assert code in text
    pupil = next(a for a in commands["extract"]._actions if "--pupil" in a.option_strings)
    for name in ("subaru", "scexao", "charis", "vlt", "sphere", "pharo", "ircular",
                 "annular"):
        assert name in pupil.help
    for name in ("simulate", "inject", "extract", "detect"):
        lines = commands[name].format_help().splitlines()
        continued = [i for i, line in enumerate(lines) if line.rstrip().endswith("\\")]
        assert continued, name                              # a two-line example
        assert all(lines[i + 1].startswith("      ") for i in continued), name
    assert any("--pupil-scale" in a.option_strings for a in commands["model-check"]._actions)


def test_detect_on_a_cube_suggests_extract(tmp_path, capsys):
    assert main(["simulate", "--frames", "2", "--shape", "16", "-q", "-o",
                 str(tmp_path / "sim")]) == 0
    cube = str(tmp_path / "sim" / "target.fits")
    assert main(["detect", cube, "-o", str(tmp_path / "d.fits")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and f"kpifs extract {cube}" in err
    # an existing output is refused in the command line's words
    (tmp_path / "kp.fits").write_bytes(b"keep")
    assert main(["extract", cube, "-o", str(tmp_path / "kp.fits"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "pass --overwrite" in err and "overwrite=True" not in err
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        from kpifs._utils import check_output_path
        from kpifs import KpifsError
        with pytest.raises(KpifsError, match="pass overwrite=True"):     # the API's words
            check_output_path(tmp_path / "kp.fits")


def test_progress_lines_with_the_time_left_when_stderr_is_not_a_terminal(monkeypatch, capsys):
    import kpifs._utils as utils
    monkeypatch.setattr(utils, "PROGRESS_EVERY", 0.0)          # a line at every step
    assert list(utils.progress(range(4), desc="work", unit="entry")) == [0, 1, 2, 3]
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 4 and lines[0].startswith("kpifs: work: 1/4 entry, ")
    assert lines[1].startswith("kpifs: work: 2/4 entries") and lines[1].endswith("left")
    bar = utils.progress(desc="grow", unit="injection", total=2)    # updated by hand
    bar.update(2)
    bar.total += 2                                                  # the work grew
    bar.update(1)
    bar.close()
    assert "3/4 injections" in capsys.readouterr().err
    assert list(utils.progress(range(3), enabled=False)) == [0, 1, 2]
    assert capsys.readouterr().err == ""


def test_every_command_has_its_runner_and_every_public_name_its_module():
    """The entry points load on first use through imports written out by hand
    (`kpifs._cli._runner`, `kpifs._module_of`): a command or a re-exported name added
    without its line there would fail only when used."""
    import kpifs
    from kpifs._cli import _runner
    _, commands = _commands()
    for name, sub in commands.items():
        run = _runner(sub.get_default("module"))
        assert callable(run) and run.__module__ == f"kpifs._cli.{sub.get_default('module')}"
    for name in kpifs.__all__:
        assert getattr(kpifs, name) is not None, name
    with pytest.raises(RuntimeError, match="no module"):
        _runner("no-such-command")
