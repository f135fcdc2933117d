"""What the command modules share: the CLI logger, choices, argparse types, output helpers."""

from __future__ import annotations

import argparse
import sys

from offline_adp.progress import CLI_LOGGER, get_logger, is_terminal

#: The command line's own lines (progress, summaries): INFO records shown by default,
#: hidden by -q or --log-level WARNING (see offline_adp.progress.apply_logging_options).
log = get_logger(CLI_LOGGER)

FORMATS = ("dataset", "parquet", "csv", "mcap-json", "mcap-ros2")
#: The algorithm registry's names (offline_adp.algorithms.registry; a test keeps them equal).
ALGORITHM_NAMES = ("fqi", "fqe", "api", "cpi", "psdp")


def _progress(quiet: bool):
    """A step-progress callback: a tqdm bar on stderr when it is a terminal, unless quiet
    (in a log file the command's summary line says what was done)."""
    if quiet or not is_terminal():
        return None, lambda: None
    from tqdm import tqdm

    bar = tqdm(unit="step", desc="simulating", leave=False, file=sys.stderr)
    last = {"t": -1}

    def on_step(t: int) -> None:
        if t != last["t"]:
            last["t"] = t
            bar.update(1)

    return on_step, bar.close


def _particle_count(text: str) -> int:
    """argparse type: 0 (none) or an integer >= 2 (a Monte-Carlo interval needs two)."""
    from offline_adp.evaluation import particle_count_error

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 0 or an integer >= 2, got {text!r}") from None
    why = particle_count_error(value)
    if why:
        raise argparse.ArgumentTypeError(why)
    return value


def _rates(text: str) -> list[float]:
    """argparse type: positive finite numbers separated by commas (a rate limit per component)."""
    import math

    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected positive numbers separated by commas, got {text!r}") from None
    if not values or not all(math.isfinite(v) and v > 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected positive finite numbers, got {text!r}")
    return values


def _positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (a usage error, exit 2, otherwise)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _say(args: argparse.Namespace, msg: str) -> None:
    """A progress or summary line on stderr (an INFO record of the CLI logger: -q hides it)."""
    if not getattr(args, "quiet", False):
        log.info("%s", msg)


def _file_output(path: str, flag: str, what: str) -> None:
    """A command's output that must be a file: an existing directory there is an error."""
    from pathlib import Path

    from offline_adp.errors import WriteError

    p = Path(path)
    if p.is_dir() and not p.is_symlink():
        raise WriteError(f"{flag} {p} is a directory; name {what} to write (e.g. {p / 'out'})")
