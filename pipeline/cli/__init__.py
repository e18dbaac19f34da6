"""The ``twray`` command line.

Every bad input ends with one line on stderr naming the field, the value and
the rule, exit code 2, and nothing written.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading

from .. import __version__
from ..cache import log_to_stderr
from .. import runlog
from ..params import ParameterError
from ..runlog import RunFailed
from .args import EXIT_ENVIRONMENT, EXIT_INTERRUPTED, EXIT_PIPE, EXIT_USAGE, Parser, YES_HELP, subparser
from .graphs import add_camera, add_study
from .outputs import add_cache, add_design, add_figures, add_resummarize
from .trace import add_trace
from .volumes import add_generate, cmd_export_tiff, cmd_info, cmd_slices
from .wave import add_wave


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="twray", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"twray {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    add_generate(sub)
    add_trace(sub)
    add_study(sub)
    add_camera(sub)
    add_cache(sub)
    add_figures(sub)
    add_design(sub)
    add_resummarize(sub)
    add_wave(sub)
    p = subparser(sub, "slices", help="PNG cross-sections in the R-T, L-T and L-R planes")
    p.add_argument("volume", help="a twray volume (.zarr)")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=cmd_slices)
    p = subparser(sub, "export-tiff", help="one TIFF per L slice, for ImageJ/Avizo")
    p.add_argument("volume", help="a twray volume (.zarr)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--yes", action="store_true", help=YES_HELP)
    p.set_defaults(func=cmd_export_tiff)
    p = subparser(sub, "info", help="print a volume's shape, parameters and generated chunks")
    p.add_argument("volume", help="a twray volume (.zarr)")
    p.set_defaults(func=cmd_info)
    return parser


def _terminated(signum, frame):
    raise KeyboardInterrupt  # a kill (SIGTERM) cleans up like Ctrl-C: staged outputs are removed


def _interrupt_handled() -> None:
    """Tell CPython that the interrupt was handled. A KeyboardInterrupt that passed through code
    evaluated from a string (``exec`` of source: dataclasses and named tuples build their methods
    so, as modules are imported) sets a flag that catching it does not clear; under ``python -m``
    the interpreter then ends by SIGINT (status -2) instead of with the 130 returned. Evaluating a
    string clears the flag."""
    exec("None")


def main(argv: list[str] | None = None) -> int:
    log_to_stderr()
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _terminated)
    runlog.start()  # until a command names its cache
    try:
        args = build_parser().parse_args(argv)
        return args.func(args)
    except ParameterError as exc:
        print(f"twray: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        _interrupt_handled()
        print("twray: interrupted; nothing half-written is left (studies and the camera resume from their "
              "cache)", file=sys.stderr)
        return EXIT_INTERRUPTED
    except RunFailed as exc:  # a Dask task failed: its line names the scene, the fix and the log
        print(f"twray: error: {exc}", file=sys.stderr)
        return EXIT_ENVIRONMENT
    except BrokenPipeError:  # whoever read the output stopped reading (`twray trace --json | head`)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
        print("twray: stopped: the output's reader closed the pipe", file=sys.stderr)
        return EXIT_PIPE
    except OSError as exc:  # the filesystem refused (disk full, permissions): one line, not a traceback
        print(f"twray: error: {runlog.os_error_line(exc)}; {runlog.traceback_note(exc)}", file=sys.stderr)
        return EXIT_ENVIRONMENT
    except Exception as exc:  # a defect of twray: one line, the traceback in the log
        print(f"twray: error: internal error, {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''} "
              f"(a defect of twray: please report it with its traceback; {runlog.traceback_note(exc)})",
              file=sys.stderr)
        return EXIT_ENVIRONMENT
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
