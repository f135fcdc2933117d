"""Exception and warning types raised by offline_adp.

Every error raised on bad input is one of these, and its message names the file, row
(episode_id, step) or key at fault, says what was expected and what was found, and where
possible the command that fixes it.
"""

from __future__ import annotations


class OfflineADPError(Exception):
    """Base class of every error raised by offline_adp on bad input or bad use."""


class SchemaError(OfflineADPError):
    """A table or dataset does not have the columns, types or metadata the format requires."""


class SpecError(OfflineADPError):
    """An ingestion spec or pipeline file is malformed (unknown key, wrong type, bad value)."""


class IngestError(OfflineADPError):
    """An input file could not be turned into a dataset (unreadable, inconsistent rows)."""


class ValidationError(OfflineADPError):
    """The dataset doctor found defects and the caller asked to fail on them.

    Attributes
    ----------
    report : offline_adp.data.validate.ValidationReport
        The full report; ``str(error)`` shows its first findings.
    """

    def __init__(self, message: str, report: object | None = None) -> None:
        super().__init__(message)
        self.report = report


class ArtifactError(OfflineADPError):
    """A saved artifact (Q-function, policy, checkpoint) cannot be written or read safely:
    a member is missing, malformed, out of range or out of proportion; the message names
    the file and the member."""


class InvalidArgumentError(OfflineADPError, ValueError):
    """A function or command-line argument has a bad value (negative count, options that
    are not a JSON object...); the message names the argument and what is allowed."""


class WriteError(OfflineADPError):
    """An output location cannot be written: read-only, full, a directory where a file is
    expected or a file where a directory is expected; the message names the path."""


class LockedError(OfflineADPError):
    """Another process holds the lock of a dataset or run directory we are asked to write."""


class DatasetNotFoundError(OfflineADPError, FileNotFoundError):
    """A path that should be a dataset directory is missing or is not one."""


class NotFittedError(OfflineADPError, AttributeError):
    """An estimator was used before ``fit``."""


class InvalidTypeError(OfflineADPError, TypeError):
    """A function was given an object of the wrong kind (a dataset where a policy is
    needed...); the message names the argument and what it takes."""


class AccessModelError(OfflineADPError, TypeError):
    """An algorithm was given a weaker access model than it needs."""


class UnknownNameError(OfflineADPError, KeyError):
    """A registry lookup (problem, regressor, format) failed; the message lists valid names."""

    def __str__(self) -> str:  # KeyError would repr() the message
        return str(self.args[0]) if self.args else ""


class ExportError(OfflineADPError):
    """A policy (or a part of it) cannot be expressed in the export format (ONNX, LeRobot...)."""


class MissingExtraError(OfflineADPError, ImportError):
    """An optional dependency is not installed; the message names the extra to install."""


class ClusterError(OfflineADPError):
    """The Dask cluster cannot be reached, has no workers, or was lost during a fit."""


class RunDirectoryError(OfflineADPError):
    """A path is not the run directory a command needs (no model, already holds a run,
    or a resume that does not match the run it would continue)."""


class IncompatibleError(OfflineADPError):
    """Two things that must agree do not: a policy and a dataset (actions, features), a
    simulator and a dataset, or candidates evaluated against different estimands."""


class OutputExistsError(WriteError):
    """The output path already exists (or is the input); pass ``--overwrite`` or write elsewhere."""


class FormatVersionWarning(UserWarning):
    """A dataset or artifact was written by a different format or package version."""


class LogWarning(UserWarning):
    """Logs that are valid but probably not what was meant (a time limit flagged as a
    terminal state, values on a scale the learners cannot resolve)."""


class ScaleWarning(LogWarning):
    """Costs or features on a scale the tree builders cannot resolve (as scikit-learn's:
    a node whose target variance is below float64 eps is pure; a feature spanning less
    than 1e-7 on a node is constant there)."""


class DivergenceWarning(RuntimeWarning):
    """An iterative algorithm's values grew beyond what the problem allows."""


class ClusterWarning(RuntimeWarning):
    """A Dask fit went on in a degraded way (e.g. on fewer workers than it started with),
    so its result may differ from an undisturbed fit's."""


#: What an ``OSError`` of a write means, by errno name (the rest: the system's text).
_OS_ERROR_REASONS = {
    "EROFS": "read-only file system",
    "ENOSPC": "no space left on the device",
    "EDQUOT": "disk quota exceeded",
    "EACCES": "permission denied",
    "EPERM": "operation not permitted",
    "ENOTDIR": "a file is in the way where a directory is expected",
    "EISDIR": "is a directory, expected a file",
    "EEXIST": "already exists",
    "ENOTEMPTY": "is a non-empty directory",
    "ELOOP": "is a symbolic link (refused)",
    "ENAMETOOLONG": "file name too long",
    "EFBIG": "file too large",
}


def short_list(items: object, k: int = 8) -> str:
    """At most ``k`` items of a list for a message (never thousands)."""
    items = list(items)  # type: ignore[call-overload]
    return repr(items) if len(items) <= k else f"[{', '.join(repr(x) for x in items[:k])}, ... ({len(items)} in all)]"


def os_error_message(exc: OSError, path: object = None) -> str:
    """One line for an ``OSError``: the path at fault (the error's own file name, else
    ``path``), what it means and what to do; never a traceback."""
    import errno as _errno

    name = _errno.errorcode.get(exc.errno or -1, "")
    where = exc.filename if exc.filename is not None else path
    reason = _OS_ERROR_REASONS.get(name) or exc.strerror or str(exc) or type(exc).__name__
    detail = f" [{name}]" if name else ""
    other = f" -> {exc.filename2}" if getattr(exc, "filename2", None) else ""
    head = f"{where}{other}: " if where is not None else ""
    return f"{head}{reason}{detail}; check the location (free space, permissions, files or folders in the way) " \
           "or write somewhere else"


#: The deepest nesting of a JSON value read from a user or a file (a ``--fqe-params``
#: option, ``metrics.json``, ``run.json``...): far above any this package writes, so a
#: hostile file nested 200,000 deep is an error naming it, not a RecursionError.
MAX_JSON_DEPTH = 64


def json_depth(value: object, limit: int = MAX_JSON_DEPTH) -> int:
    """The nesting depth of a parsed JSON value (a scalar: 0), walked without recursion;
    counting stops past ``limit`` (then ``limit + 1`` is returned)."""
    deepest, stack = 0, [(value, 0)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, dict):
            v = list(v.values())
        if isinstance(v, list | tuple):
            d += 1
            if d > limit:
                return d
            deepest = max(deepest, d)
            stack.extend((x, d) for x in v if isinstance(x, dict | list | tuple))
    return deepest
