"""Logging and progress reporting, like a library should.

Every module logs to a child of the package logger ``offline_adp`` (``get_logger(__name__)``),
which has only a ``NullHandler``: an application decides what is shown
(``logging.basicConfig(level=logging.INFO)`` or ``logging.getLogger("offline_adp")``).
The CLI calls :func:`configure_logging` from ``-v/-q/--log-level``.

Long loops report through :class:`Progress`: a tqdm bar on stderr when ``show_progress``
and one INFO log record per update when ``verbose`` (shown on stderr even if the
application configured no logging).
"""

from __future__ import annotations

import logging
import sys
import warnings
from collections.abc import Mapping
from types import TracebackType
from typing import Any

PACKAGE = "offline_adp"
logging.getLogger(PACKAGE).addHandler(logging.NullHandler())

LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")


def get_logger(name: str = PACKAGE) -> logging.Logger:
    """The package logger or one of its children (pass ``__name__``)."""
    if name != PACKAGE and not name.startswith(PACKAGE + "."):
        name = f"{PACKAGE}.{name}"
    return logging.getLogger(name)


def resolve_level(verbose: int = 0, quiet: bool = False, log_level: str | None = None) -> int:
    """The logging level from CLI flags: ``--log-level`` wins, then ``-q`` (ERROR), then
    WARNING lowered one step per ``-v`` (``-v`` INFO, ``-vv`` DEBUG)."""
    if log_level:
        name = str(log_level).upper()
        if name not in LEVELS:
            from offline_adp.errors import SpecError

            raise SpecError(f"--log-level {log_level!r}: expected one of {list(LEVELS)}")
        return getattr(logging, name)
    if quiet:
        return logging.ERROR
    return max(logging.DEBUG, logging.WARNING - 10 * int(verbose))


class _StderrHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """A StreamHandler writing to whatever ``sys.stderr`` is at emit time (it may be
    replaced, e.g. by test capture or a notebook, after the handler was installed)."""

    @property  # type: ignore[override]
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, value: Any) -> None:
        pass


def configure_logging(level: int = logging.WARNING, stream: Any = None) -> logging.Handler:
    """Send the package's log records at ``level`` and above to ``stream`` (stderr) as
    ``LEVEL name: message`` lines; replaces a handler installed by an earlier call."""
    log = logging.getLogger(PACKAGE)
    for h in list(log.handlers):
        if getattr(h, "_oadp_cli", False):
            log.removeHandler(h)
    handler = logging.StreamHandler(stream) if stream is not None else _StderrHandler()
    handler.setFormatter(CliFormatter())
    handler._oadp_cli = True  # type: ignore[attr-defined]
    log.addHandler(handler)
    log.setLevel(level)
    return handler


def _fmt(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


class Progress:
    """Progress of a loop of ``total`` updates.

    Parameters
    ----------
    total : int or None
        Expected number of updates (None: unknown).
    desc : str
        What is running (the bar's label and the log records' prefix).
    show_progress : bool
        Draw a tqdm bar on stderr.
    verbose : bool
        Log one INFO record per update (to stderr if the application configured no
        handler for the package logger).
    fields : tuple of str
        Keys of an update's ``row`` to show (bar postfix and log record).
    logger : Logger, optional
        Where the records go (default: the package logger).
    """

    def __init__(self, total: int | None, desc: str, *, show_progress: bool = False, verbose: bool = False,
                 fields: tuple[str, ...] = (), logger: logging.Logger | None = None) -> None:
        self.total, self.desc, self.fields = total, desc, fields
        self.verbose, self.n = verbose, 0
        self.logger = logger or get_logger()
        self._bar: Any = None
        self._handler: logging.Handler | None = None
        if show_progress:
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=desc, unit="it", file=sys.stderr, leave=False)
        if verbose and not _has_handler(self.logger):
            self._handler = _StderrHandler()
            self._handler.setFormatter(logging.Formatter("%(name)s: %(message)s"))
            logging.getLogger(PACKAGE).addHandler(self._handler)
        if verbose:
            self._old_level = logging.getLogger(PACKAGE).level
            if not self.logger.isEnabledFor(logging.INFO):
                logging.getLogger(PACKAGE).setLevel(logging.INFO)

    def update(self, row: Mapping[str, Any] | None = None, n: int = 1) -> None:
        """Advance by ``n``; ``row`` (e.g. an iteration's diagnostics) is shown."""
        self.n += n
        shown = {k: row[k] for k in self.fields if row is not None and k in row and row[k] is not None}
        if self._bar is not None:
            if shown:
                self._bar.set_postfix({k: _fmt(v) for k, v in shown.items()}, refresh=False)
            self._bar.update(n)
        if self.verbose:
            of = f"/{self.total}" if self.total else ""
            self.logger.info("%s %d%s %s", self.desc, self.n, of, " ".join(f"{k}={_fmt(v)}" for k, v in shown.items()))

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        if self.verbose:
            logging.getLogger(PACKAGE).setLevel(self._old_level)
        if self._handler is not None:
            logging.getLogger(PACKAGE).removeHandler(self._handler)
            self._handler = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def _has_handler(logger: logging.Logger) -> bool:
    """Whether a record from ``logger`` reaches a real (non-Null) handler."""
    lg: logging.Logger | None = logger
    while lg is not None:
        if any(not isinstance(h, logging.NullHandler) for h in lg.handlers):
            return True
        if not lg.propagate:
            return False
        lg = lg.parent
    return False


def log_milestone(k: int, total: Any) -> bool:
    """Whether iteration ``k`` of a fit gets a progress line in a log (not a terminal): the
    quarters of ``total`` when it is a known count, else (``n_iterations="auto"``: the fit
    decides when it is done) iterations 1, 10, 20, 40, 80, ... (a handful of lines however
    long the fit runs)."""
    if isinstance(total, int) and not isinstance(total, bool) and total > 0:
        return k in {max(1, (total * q) // 4) for q in (1, 2, 3, 4)}
    return k == 1 or (k >= 10 and k % 10 == 0 and ((k // 10) & (k // 10 - 1)) == 0)


def fit_progress(est: Any, verbose: bool = False, show_progress: bool = False) -> Progress:
    """A :class:`Progress` for an iterative estimator's ``fit`` (FQI, FQE): the total is
    ``horizon``, else ``n_iterations``, and the
    shown fields are the usual convergence diagnostics."""
    total = getattr(est, "horizon", None) or getattr(est, "n_iterations", 0) or None
    total = total if isinstance(total, int) else None  # "auto": the fit decides
    name = type(est).__name__
    return Progress(total, name, show_progress=show_progress, verbose=verbose,
                    fields=("iteration", "sup_dq", "bellman_residual", "start_value", "wall_time"),
                    logger=get_logger(type(est).__module__))


class PhaseLines:
    """Progress lines of a phase of ``total`` parts of about equal cost, for a ``say``
    callback (an evaluation's progress): call it once per finished part (in any order, e.g.
    from a task map's ``on_done``); at the ``lines`` evenly spaced counts (2: the half and
    the end, so that a log stays short) it says ``"{desc} k/total, ETA 12 s"``, the wall
    time so far scaled to the parts left, and at the last ``"{desc} total/total in 9.8 s"``.
    A phase of one part says nothing here.

    ``clock``: the wall clock (seconds; the ETA is what the user waits, not CPU time).
    """

    def __init__(self, say: Any, desc: str, total: int, lines: int = 2, clock: Any = None) -> None:
        import time

        self.say, self.desc, self.total = say, desc, int(total)
        self.clock = clock or time.perf_counter
        self.start, self.done = self.clock(), 0
        self.marks = {max(1, (self.total * q) // lines) for q in range(1, lines + 1)} if self.total > 1 else set()

    def __call__(self, *_: Any) -> None:
        self.done += 1
        if self.done not in self.marks:
            return
        spent = self.clock() - self.start
        if self.done >= self.total:
            self.say(f"{self.desc} {self.done}/{self.total} in {_seconds(spent)}")
        else:
            left = spent / self.done * (self.total - self.done)
            self.say(f"{self.desc} {self.done}/{self.total}, ETA {_seconds(left)}")


def _seconds(s: float) -> str:
    """``9.8 s``, ``42 s``, ``3 min 05 s``."""
    if s < 10:
        return f"{s:.1f} s"
    if s < 120:
        return f"{s:.0f} s"
    m, r = divmod(int(round(s)), 60)
    return f"{m} min {r:02d} s"


# ----------------------------------------------------------------------------- CLI options
def add_logging_options(parser: Any) -> None:
    """Add ``-v/--verbose``, ``-q/--quiet`` and ``--log-level`` to an argparse parser and
    to every (nested) subcommand, so they are accepted before or after the subcommand.

    Subcommand-level values are stored under their own names (default: unset), so a
    subcommand's default never overrides the top-level flag; :func:`apply_logging_options`
    combines them. A subcommand that already has ``--quiet`` keeps its own.
    """
    import argparse

    def add(p: Any, top: bool) -> None:
        sfx = "" if top else "_sub"
        d = {} if top else {"default": argparse.SUPPRESS}
        have = {s for a in p._actions for s in a.option_strings}
        g = p.add_argument_group("logging") if not top else p
        if "-v" not in have:
            g.add_argument("-v", "--verbose", action="count", dest=f"log_verbose{sfx}",
                           help="more log output (-vv: debug)",
                           **({"default": 0} if top else d))
        if "-q" not in have and "--quiet" not in have:
            g.add_argument("-q", "--quiet", action="store_true", dest=f"log_quiet{sfx}", help="only errors",
                           **({"default": False} if top else d))
        if "--log-level" not in have:
            g.add_argument("--log-level", dest=f"log_level{sfx}", type=str.upper, choices=LEVELS, metavar="LEVEL",
                           help=f"logging level, one of {', '.join(LEVELS)}", **({"default": None} if top else d))
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for sp in a.choices.values():
                    add(sp, False)

    add(parser, True)


def apply_logging_options(args: Any) -> int:
    """Combine top-level and subcommand logging flags from parsed ``args``, set
    ``args.quiet`` (for the commands' own progress output) and configure logging;
    returns the level."""
    verbose = int(getattr(args, "log_verbose", 0) or 0) + int(getattr(args, "log_verbose_sub", 0) or 0)
    quiet = bool(getattr(args, "log_quiet", False) or getattr(args, "log_quiet_sub",
                                                              False) or getattr(args, "quiet", False))
    level_name = getattr(args, "log_level_sub", None) or getattr(args, "log_level", None)
    args.quiet = quiet
    level = resolve_level(verbose, quiet, level_name)
    configure_logging(level)
    # the command's own progress and summary lines (INFO of the CLI logger) show by default;
    # -q or an explicit --log-level above INFO hides them, -v/-vv/--log-level DEBUG add the library's
    logging.getLogger(CLI_LOGGER).setLevel(logging.INFO if level > logging.INFO and not quiet and not level_name
                                           else logging.NOTSET)
    return level


# ----------------------------------------------------------------------------- CLI output
#: The logger of the command line's own lines (progress, summaries, the warnings summary).
CLI_LOGGER = PACKAGE + ".cli"


def is_terminal(stream: Any = None) -> bool:
    """Whether ``stream`` (default: ``sys.stderr`` now) is a terminal: progress bars are
    drawn only there; a log file or a CI capture gets a few summary lines instead."""
    stream = sys.stderr if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


class CliFormatter(logging.Formatter):
    """The command line's own records (:data:`CLI_LOGGER` and its children) as plain lines
    (INFO: the message; other levels: ``level: message``); every other record as
    ``LEVEL name: message``."""

    def __init__(self) -> None:
        super().__init__("%(levelname)s %(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        if record.name == CLI_LOGGER or record.name.startswith(CLI_LOGGER + "."):
            msg = record.getMessage()
            return msg if record.levelno == logging.INFO else f"{record.levelname.lower()}: {msg}"
        return super().format(record)


def _ours(w: warnings.WarningMessage) -> bool:
    """A warning of this package (its category is ours, or it was raised from our code)."""
    import os

    here = os.path.dirname(os.path.abspath(__file__))
    return getattr(w.category, "__module__",
                   "").startswith(PACKAGE) or os.path.abspath(str(w.filename)).startswith(here + os.sep)


class CapturedWarnings:
    """Python warnings captured during a command (:func:`capturing_warnings`): the
    package's own are reported once each, every other library's (scikit-learn,
    LightGBM, numpy, ...) counted and summarised in one line (memory stays bounded
    however many are raised)."""

    def __init__(self) -> None:
        self.own: list[str] = []
        self.n_library = 0
        self.first_library: warnings.WarningMessage | None = None
        self._kinds: set[tuple[str, str]] = set()

    def add(self, w: warnings.WarningMessage) -> None:
        if _ours(w):
            cat = w.category.__name__
            text = str(w.message) if cat == "UserWarning" else f"{cat}: {w.message}"
            if text not in self.own:
                self.own.append(text)
            return
        self.n_library += 1
        if self.first_library is None:
            self.first_library = w
        if len(self._kinds) < 10_000:
            self._kinds.add((w.category.__name__, str(w.message)[:500]))

    def summary_lines(self) -> list[str]:
        """One line per distinct warning of the package, then ``N library warnings (first: ...)``."""
        lines = list(self.own)
        first = self.first_library
        if first is not None:
            n = self.n_library
            where = str(first.filename).replace("\\", "/").rsplit("/", 1)[-1]
            msg = (str(first.message).splitlines() or [""])[0][:200]
            lines.append(f"{n} library warning{'s' if n != 1 else ''} ({len(self._kinds)} distinct; first: "
                         f"{first.category.__name__} from {where}:{first.lineno}: {msg})")
        return lines

    def report(self, logger: logging.Logger | None = None) -> None:
        """Log :meth:`summary_lines` as WARNING records of the command-line logger."""
        log = logger or logging.getLogger(CLI_LOGGER)
        for line in self.summary_lines():
            log.warning("%s", line)


class capturing_warnings:  # noqa: N801 - used as a context manager, like warnings.catch_warnings
    """Capture every Python warning raised in this process while the block runs (each
    occurrence counted, none printed) into a :class:`CapturedWarnings`; report them with
    :meth:`CapturedWarnings.report` at the end of the command."""

    def __enter__(self) -> CapturedWarnings:
        self._cm = warnings.catch_warnings()  # restores the filters and showwarning on exit
        self._cm.__enter__()
        warnings.simplefilter("always")
        self.captured = CapturedWarnings()

        def show(message: Any, category: Any, filename: str, lineno: int, file: Any = None, line: Any = None) -> None:
            self.captured.add(warnings.WarningMessage(message, category, filename, lineno, file, line))

        warnings.showwarning = show
        return self.captured

    def __exit__(self, *exc: Any) -> None:
        self._cm.__exit__(*exc)
