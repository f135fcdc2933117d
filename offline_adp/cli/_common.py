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


#: The flags made from the evaluation settings' model (:func:`add_settings_options`).
SETTING_FLAGS: set[str] = set()


def add_settings_options(parser: argparse.ArgumentParser, defaults: dict[str, object] | None = None) -> None:
    """One flag per field of :class:`~offline_adp.evaluation.settings.EvaluationSettings`
    (``fqe_bootstrap`` -> ``--fqe-bootstrap``), with the model's default (or ``defaults``'),
    help and check: a refused value is a usage error (exit 2) of one line naming the flag."""
    from offline_adp.evaluation.settings import EvaluationSettings, flag

    for name, field in EvaluationSettings.model_fields.items():
        default = (defaults or {}).get(name, field.default)
        shown = "" if default is None else f" (default {default})"
        metavar = {"simulator": "NAME", "fqe_params": "JSON", "estimand": "{finite,infinite}"}.get(name, "N")
        parser.add_argument(flag(name), dest=name, default=default, type=_setting_type(name), metavar=metavar,
                            help=(field.description or "") + shown)
        SETTING_FLAGS.add(flag(name))


def _setting_type(name: str):
    """argparse type of the setting ``name``: parsed and checked by the settings' model."""
    from offline_adp.errors import InvalidArgumentError
    from offline_adp.evaluation.settings import flag, parse_flag

    def parse(text: str) -> object:
        try:
            return parse_flag(name, text)
        except InvalidArgumentError as exc:  # argparse says "argument --flag: " itself
            raise argparse.ArgumentTypeError(str(exc).removeprefix(f"{flag(name)}: ")) from None

    parse.__name__ = name  # argparse names the type in "invalid <name> value" messages
    return parse


class OneLineParser(argparse.ArgumentParser):
    """A parser whose refused setting value (a flag of :func:`add_settings_options`) is one
    line, ``offline-adp evaluate: error: argument --bootstrap: ...``, exit 2: no usage
    block to find it in."""

    def error(self, message: str):  # type: ignore[override]
        head = message.split(":", 1)[0].removeprefix("argument ")
        if head in SETTING_FLAGS:
            self.exit(2, f"{self.prog}: error: {message}\n")
        super().error(message)


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
