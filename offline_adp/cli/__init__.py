"""``offline-adp``: a thin command line over the library's functions.

Every subcommand's ``--help`` ends with an example. Errors of our own types print one
clear message (no traceback) and exit with status 2; ``--traceback`` shows the stack.

The parser is :mod:`offline_adp.cli.parser`; the commands are in
:mod:`~offline_adp.cli.data_commands` (simulate, ingest, mcap-info, validate, inspect),
:mod:`~offline_adp.cli.fit_commands` (fit, evaluate, run, schema, report) and
:mod:`~offline_adp.cli.export_commands` (export, annotate, convert).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from offline_adp.cli._common import ALGORITHM_NAMES, FORMATS, log
from offline_adp.cli.parser import build_parser  # the commands: offline_adp.cli.*_commands
from offline_adp.errors import OfflineADPError

__all__ = ["ALGORITHM_NAMES", "FORMATS", "build_parser", "log", "main"]


class Terminated(KeyboardInterrupt):
    """SIGTERM (a scheduler's or ``kill``'s stop), handled as Ctrl-C is: a fit records
    "interrupted" and writes its checkpoint, a pipeline its stage's state, no temporary
    is left; the exit status is 143 (128 + SIGTERM)."""


def _on_sigterm(signum: int, frame: object) -> None:
    raise Terminated("SIGTERM")


def main(argv: Sequence[str] | None = None) -> int:
    import signal
    import threading

    previous = None
    if threading.current_thread() is threading.main_thread():  # handlers can only be set there
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        return _main(argv)
    except KeyboardInterrupt as exc:  # one arriving between the handlers below
        return _interrupted(exc)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _interrupted(exc: KeyboardInterrupt) -> int:
    print("terminated" if isinstance(exc, Terminated) else "interrupted", file=sys.stderr)
    return 143 if isinstance(exc, Terminated) else 130


def _main(argv: Sequence[str] | None) -> int:
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        if not getattr(args, "func", None):
            parser.print_help()
            return 2
        from offline_adp.progress import capturing_warnings

        with capturing_warnings() as caught:
            try:
                return _run(args)
            finally:
                caught.report(log)  # the package's warnings once each; the libraries' in one line
    except KeyboardInterrupt as exc:  # Ctrl-C while the parser or a command's imports load, or while warnings print
        return _interrupted(exc)


def _run(args: argparse.Namespace) -> int:
    """Run the parsed command; our errors as one line and exit status 2."""
    try:
        from offline_adp.progress import apply_logging_options

        apply_logging_options(args)
        return int(args.func(args))
    except OfflineADPError as exc:
        if args.traceback:
            raise
        print(f"offline-adp {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        return _interrupted(exc)
    except BrokenPipeError:  # output piped into `head` and the like
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except MemoryError:
        if args.traceback:
            raise
        print(f"offline-adp {args.command}: error: out of memory; use smaller settings (episodes, bootstrap "
              "replicates, horizon) or a machine with more memory", file=sys.stderr)
        return 2
    except OSError as exc:  # read-only location, full disk, a file or folder in the way: one line, exit 2
        if args.traceback:
            raise
        from offline_adp.errors import os_error_message

        print(f"offline-adp {args.command}: error: {os_error_message(exc, _output_of(args))}", file=sys.stderr)
        return 2
    except ValueError as exc:  # scikit-learn's check of a parameter raised inside a fit: a setting, not a bug
        if args.traceback or type(exc).__name__ != "InvalidParameterError":
            raise
        print(f"offline-adp {args.command}: error: {exc}", file=sys.stderr)
        return 2


def _output_of(args: argparse.Namespace) -> str | None:
    """The path a command writes (for an OSError that names none)."""
    for name in ("out", "json", "run", "write"):
        value = getattr(args, name, None)
        if isinstance(value, str):
            return value
    return None
