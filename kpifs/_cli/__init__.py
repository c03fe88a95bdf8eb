"""The ``kpifs`` command line (private: `kpifs.cli.main` is the public entry point).

One small module per command (``kpifs._cli.extract`` runs ``kpifs extract``,
and so on); each turns the parsed options into the workflow's option objects,
calls `kpifs.workflow` and prints. The parser (`kpifs._cli._parser`) imports
nothing heavy, and a command's module is imported only when that command
runs, so ``kpifs --help`` and ``kpifs --version`` start fast.

Exit status: 0 success, 1 ``kpifs batch`` with failed entries, 2 bad input or
usage (one-line message naming the file and the problem), 3 an unexpected
internal error (rerun with ``--debug`` for the traceback), 130 interrupted.
"""
import logging
import os
import sys
import warnings

from ._parser import build_parser, join_negative_values

__all__ = ["main"]

log = logging.getLogger("kpifs")


def _setup_logging(args):
    """Send kpifs's log records to stderr at the level -v/-q ask for."""
    level = logging.WARNING - 10 * args.verbose
    if args.quiet:
        level = logging.ERROR
    for h in [h for h in log.handlers if getattr(h, "_kpifs_cli", False)]:
        log.removeHandler(h)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("kpifs: %(message)s"))
    handler._kpifs_cli = True
    log.addHandler(handler)
    log.setLevel(max(level, logging.DEBUG))


def _make_show(args):
    def show(message, category, filename, lineno, file=None, line=None):
        if not args.quiet:
            print(f"kpifs {args.command}: warning: {message}", file=sys.stderr)
    return show


def _blas_threads():
    """BLAS on one thread while a command runs (``KPIFS_BLAS_THREADS`` sets another number).

    kpifs spreads its heavy work over the cores itself (`kpifs._utils.thread_map`,
    one BLAS thread per chunk); what is left to BLAS are products of a few hundred
    rows, where its threads gain little on two cores and, on a busy machine, wait
    for each other: ``kpifs detect`` on the README's 400 frames took 27 s of CPU
    with two BLAS threads at a load of 15, 4.4 s with one.
    """
    from threadpoolctl import threadpool_limits
    env = os.environ.get("KPIFS_BLAS_THREADS", "").strip()
    return threadpool_limits(limits=int(env) if env.isdigit() and int(env) > 0 else 1,
                             user_api="blas")


def _runner(module):
    """The ``run`` function of the `kpifs._cli` module *module*, imported now (each import
    written out: the tools that draw the package's structure see them)."""
    if module == "batch":
        from . import batch as command
    elif module == "demo":
        from . import demo as command
    elif module == "detect":
        from . import detect as command
    elif module == "extract":
        from . import extract as command
    elif module == "info":
        from . import info as command
    elif module == "inject":
        from . import inject as command
    elif module == "kernel":
        from . import kernel as command
    elif module == "modelcheck":
        from . import modelcheck as command
    elif module == "roc":
        from . import roc as command
    elif module == "simulate":
        from . import simulate as command
    else:                                            # a parser entry without its module
        raise RuntimeError(f"no module kpifs._cli.{module}")
    return command.run


def main(argv=None):
    """Run the ``kpifs`` command line; return the exit status."""
    parser = build_parser()
    args = parser.parse_args(join_negative_values(sys.argv[1:] if argv is None else
                                                  [str(a) for a in argv]))
    if args.command is None:
        parser.print_help()
        return 2
    _setup_logging(args)
    # the command's module, and with it numpy/astropy, is imported only now: --help and
    # --version have exited in parse_args without them
    from .._utils import OVERWRITE_HINT as hint
    from ..exceptions import KpifsError
    run = _runner(args.module)
    bad_input = (KpifsError, OSError)
    old_show = warnings.showwarning
    hint[0] = "--overwrite"      # messages name the command line's options, not the API's
    try:
        with warnings.catch_warnings(), _blas_threads():
            warnings.simplefilter("default")
            warnings.showwarning = _make_show(args)
            return run(args)
    except BrokenPipeError:  # output piped into `head` and closed: not an error
        sys.stderr.close()
        return 0
    except KeyboardInterrupt as exc:
        why = f": {exc}" if str(exc) else ""
        print(f"kpifs {args.command}: interrupted{why}", file=sys.stderr)
        return 130
    except bad_input as exc:
        if args.debug:
            raise
        print(f"kpifs {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # pragma: no cover - a bug, not bad input
        if args.debug:
            raise
        print(f"kpifs {args.command}: internal error: {type(exc).__name__}: {exc} "
              f"(rerun with --debug for the traceback)", file=sys.stderr)
        return 3
    finally:
        warnings.showwarning = old_show
        hint[0] = "overwrite=True"
