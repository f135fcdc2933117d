"""The one configuration layer: typed, validated models for every file a user writes.

Ingestion specs (Parquet/CSV and MCAP), pipeline files and fit configs are pydantic v2
models built on :class:`ConfigModel`. This module gives them one way to

- read a TOML file (:func:`load_toml`: missing file, non-UTF-8 bytes and TOML syntax
  errors become a :class:`~offline_adp.errors.SpecError` naming the file and line);
- validate a mapping against a model (:func:`validate_config`: every pydantic error
  becomes one :class:`~offline_adp.errors.SpecError` naming the file, the dotted key,
  what was expected (the allowed values for a ``Literal``) and what was found);
- publish a JSON Schema (:func:`json_schema`) so editors complete and check the TOML.

Models forbid unknown keys (a typo is an error listing the valid keys) and are frozen.
Nothing here runs code from a file.
"""

from __future__ import annotations

import difflib
import json
import os
import tomllib
import types
import typing
from collections.abc import Mapping, Sequence
from os import PathLike
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationInfo, field_validator
from pydantic import ValidationError as _PydanticValidationError

from offline_adp.errors import MAX_JSON_DEPTH, InvalidArgumentError, SpecError, json_depth

M = TypeVar("M", bound="ConfigModel")


class ConfigModel(BaseModel):
    """Base of every configuration model: unknown keys forbidden (listing the valid ones),
    frozen, values checked on load (``n_iterations = "ten"`` is an error naming the key,
    not a crash later). Lax pydantic mode, so TOML arrays fill tuples and integers fill
    floats; but ``true``/``false`` only where a field takes a bool (lax pydantic reads
    ``true`` as 1 or 1.0, so ``n_structures = true`` would run as 1)."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=False, validate_default=True)

    @field_validator("*", mode="before")
    @classmethod
    def _no_bool_for_numbers(cls, value: Any, info: ValidationInfo) -> Any:
        field = cls.model_fields.get(info.field_name) if info.field_name else None
        if field is not None:
            bad = _misplaced_bool(value, [field.annotation])
            if bad is not None:
                raise ValueError(f"a bool ({str(bad).lower()}) is not a valid value here")
        return value


def _misplaced_bool(value: Any, annotations: list[Any]) -> bool | None:
    """A bool in ``value`` (itself, or an element of a list/tuple, recursively) where none of
    ``annotations`` takes one; None if there is none. Mappings (e.g. a regressor's
    parameters, passed through as given) are not looked into."""
    if isinstance(value, bool):
        return None if any(_takes_bool(a) for a in annotations) else value
    if isinstance(value, list | tuple):
        elements: list[Any] = []
        for a in annotations:
            e = _elements(a)
            if e is None:  # any element type
                return None
            elements += e
        if not elements:  # not a sequence field: pydantic refuses the list itself
            return None
        for v in value:
            bad = _misplaced_bool(v, elements)
            if bad is not None:
                return bad
    return None


def _elements(annotation: Any) -> list[Any] | None:
    """Element types of the sequence types in ``annotation`` ([] if none; None if any)."""
    if annotation is Any or annotation is object:
        return None
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        out: list[Any] = []
        for a in typing.get_args(annotation):
            e = _elements(a)
            if e is None:
                return None
            out += e
        return out
    if origin is typing.Annotated:
        return _elements(typing.get_args(annotation)[0])
    if annotation in (list, tuple) or origin in (list, tuple, Sequence):
        args = [a for a in typing.get_args(annotation) if a is not Ellipsis]
        return args or None
    return []


def _takes_bool(annotation: Any) -> bool:
    """Whether a field annotated ``annotation`` accepts a bool as a bool (or anything)."""
    if annotation is bool or annotation is Any or annotation is object:
        return True
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        return any(_takes_bool(a) for a in typing.get_args(annotation))
    if origin is typing.Annotated:
        return _takes_bool(typing.get_args(annotation)[0])
    if origin is typing.Literal:
        return any(isinstance(a, bool) for a in typing.get_args(annotation))
    return False


#: The largest configuration file (TOML/JSON spec, pipeline, fit config) read: far above
#: any real one, so ``/dev/zero`` or a log named by mistake fails at once instead of filling memory.
MAX_CONFIG_BYTES = 4 << 20


def read_config_bytes(path: str | PathLike[str], what: str = "configuration",
                      max_bytes: int | None = None) -> bytes:
    """The bytes of a configuration file: the one reader of every TOML/JSON/YAML file a
    user writes (pipeline files, fit configs, ingestion specs).

    Only a regular file is read (a directory, FIFO, device such as ``/dev/zero`` or socket
    is refused without blocking), and at most ``max_bytes`` (default
    :data:`MAX_CONFIG_BYTES`); anything else is a :class:`~offline_adp.errors.SpecError`
    naming the file.
    """
    import stat

    p = Path(path)
    cap = MAX_CONFIG_BYTES if max_bytes is None else max_bytes
    try:
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise SpecError(f"{p}: no such {what} file") from None
    except IsADirectoryError:
        raise SpecError(f"{p}: is a directory, expected a {what} file") from None
    except OSError as e:
        raise SpecError(f"{p}: cannot read the {what} file ({e.strerror or e})") from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise SpecError(f"{p}: is a directory, expected a {what} file")
        if not stat.S_ISREG(st.st_mode):
            raise SpecError(f"{p}: not a regular file (a device, pipe or socket); expected a {what} file")
        if st.st_size > cap:
            raise SpecError(f"{p}: {st.st_size} bytes, more than a {what} file can be ({cap} bytes); "
                            "is this the right file?")
    except BaseException:
        os.close(fd)
        raise
    with os.fdopen(fd, "rb") as f:
        try:
            raw = f.read(cap + 1)
        except OSError as e:
            raise SpecError(f"{p}: cannot read the {what} file ({e.strerror or e})") from None
    if len(raw) > cap:  # grew while being read
        raise SpecError(f"{p}: more than {cap} bytes, more than a {what} file can be; is this the right file?")
    return raw


def load_toml(path: str | PathLike[str], what: str = "configuration") -> dict[str, Any]:
    """Read a TOML file into a dict, or raise a SpecError naming the file and the fault.

    Parameters
    ----------
    path : path-like
        The TOML file.
    what : str
        What the file is, for the message (``"pipeline"``, ``"ingestion spec"``...).
    """
    p = Path(path)
    raw = read_config_bytes(p, what)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        line = raw[: e.start].count(b"\n") + 1
        raise SpecError(f"{p}: line {line}: not UTF-8 text (byte 0x{raw[e.start]:02x} at offset {e.start}); "
                        f"save the {what} as UTF-8") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SpecError(f"{p}: not valid TOML: {e}") from None


def _loc(loc: tuple[Any, ...], section: str | None) -> str:
    parts = [section] if section else []
    for x in loc:
        if isinstance(x, int):
            parts.append(f"[{x}]")
        else:
            parts.append(("." if parts else "") + str(x))
    return "".join(parts).replace(".[", "[") or "(top level)"


def _valid_keys(model: type[BaseModel], loc: tuple[Any, ...]) -> list[str] | None:
    """The field names of the (nested) model at ``loc``'s parent, if it can be followed."""
    cur: Any = model
    for x in loc[:-1]:
        if isinstance(x, int):
            continue
        fields = getattr(cur, "model_fields", None)
        if not fields or x not in fields:
            return None
        ann = fields[x].annotation
        cur = _model_in(ann)
        if cur is None:
            return None
    fields = getattr(cur, "model_fields", None)
    if not fields:
        return None
    return sorted(f.alias or n for n, f in fields.items())


def _model_in(ann: Any) -> type[BaseModel] | None:
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        return ann
    for a in getattr(ann, "__args__", ()) or ():
        m = _model_in(a)
        if m is not None:
            return m
    return None


def did_you_mean(names: Sequence[str], valid: Sequence[str]) -> str:
    """`` (did you mean 'x'?)`` for one name, `` (did you mean 'x' for 'y'?)`` per name for
    several: the closest valid name (difflib) of each that has one, else ``""``.

    Parameters
    ----------
    names : sequence of str
        The names not found.
    valid : sequence of str
        The names there are.

    Returns
    -------
    str
    """
    near = {str(n): m[0] for n in names if (m := difflib.get_close_matches(str(n), [str(v) for v in valid], n=1))}
    if len(names) == 1:
        return f" (did you mean {next(iter(near.values()))!r}?)" if near else ""
    return "".join(f" (did you mean {m!r} for {n!r}?)" for n, m in near.items())


def format_validation_error(err: _PydanticValidationError, model: type[BaseModel], source: str,
                            section: str | None = None) -> str:
    """One readable message for all of a pydantic error's entries."""
    lines = []
    for e in err.errors():
        loc = tuple(e.get("loc", ()))
        where = _loc(loc, section)
        typ = e.get("type", "")
        if typ == "extra_forbidden":
            valid = _valid_keys(model, loc) or []
            hint = did_you_mean([str(loc[-1])], valid)
            lines.append(f"{where}: unknown key{hint}; valid keys are {valid}")
        elif typ == "missing":
            lines.append(f"{where}: missing required key")
        else:
            msg = e.get("msg", "invalid value")
            ctx = e.get("ctx") or {}
            if typ == "literal_error" and "expected" in ctx:
                msg = f"expected one of {ctx['expected']}"
            elif typ == "value_error" and "error" in ctx:  # a validator's own words, without "Value error, "
                msg = str(ctx["error"])
            got = e.get("input")
            got_s = repr(got)
            if len(got_s) > 80:
                got_s = got_s[:77] + "..."
            lines.append(f"{where}: {msg}, got {got_s}")
    head = f"{source}: " if source else ""
    if len(lines) == 1:
        return head + lines[0]
    return head + f"{len(lines)} problems:\n  " + "\n  ".join(lines)


def validate_config(model: type[M], data: Mapping[str, Any] | None, source: str | PathLike[str] = "",
                    section: str | None = None) -> M:
    """Validate ``data`` against ``model``; any problem is one SpecError naming the file
    (``source``), the dotted key (prefixed with ``section``) and the allowed values.
    """
    try:
        return model.model_validate(dict(data or {}))
    except _PydanticValidationError as e:
        raise SpecError(format_validation_error(e, model, str(source), section)) from None


def json_schema(model: type[BaseModel]) -> dict[str, Any]:
    """The JSON Schema of a configuration model (for editors checking TOML, e.g. Taplo)."""
    return model.model_json_schema()


def write_json_schema(model: type[BaseModel], path: str | PathLike[str]) -> Path:
    """Write :func:`json_schema` of ``model`` to ``path`` (pretty-printed, sorted keys)."""
    p = Path(path)
    p.write_text(json.dumps(json_schema(model), indent=2, sort_keys=True) + "\n", encoding="utf-8")
    return p


def parse_json_object(text: str | None, flag: str, example: str = '{"n_iterations": 30}') -> dict[str, Any]:
    """A command-line option holding a JSON object (``None``/empty: ``{}``); anything else
    raises :class:`InvalidArgumentError` naming the option."""
    if not text:
        return {}
    shown = text if len(text) <= 80 else text[:77] + "..."
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InvalidArgumentError(f"{flag}: not valid JSON ({exc.msg} at character {exc.pos}): {shown!r}") from None
    except RecursionError:
        raise InvalidArgumentError(f"{flag}: JSON nested deeper than {MAX_JSON_DEPTH} levels") from None
    if not isinstance(value, dict):
        raise InvalidArgumentError(f"{flag}: expected a JSON object such as '{example}', got {shown!r}")
    if json_depth(value) > MAX_JSON_DEPTH:
        raise InvalidArgumentError(f"{flag}: JSON nested deeper than {MAX_JSON_DEPTH} levels")
    return value
