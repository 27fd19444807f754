"""The error hierarchy: every message says what was expected, what was found, and the fix.

Errors that are the user's to fix (bad input, bad config) are ``ImupipeError``
subclasses; the command line turns them into one line and exit status 2.
Anything else is an internal failure (exit status 1).
"""

from __future__ import annotations

from typing import Any


class ImupipeError(Exception):
    """Base class for errors the user can act on."""


class ConfigError(ImupipeError):
    """A pipeline or session config is invalid (names the file and the key path)."""


class PluginError(ImupipeError):
    """A plugin is broken, or two plugins claim the same name."""


class SchemaError(ImupipeError):
    """A table does not match the schema it claims."""


class ReaderError(ImupipeError):
    """A recording cannot be read (names the file and what is wrong)."""


class SolverError(ImupipeError):
    """The data cannot support the requested calibration (says what is missing)."""


class MissingExtraError(ImupipeError):
    """An optional dependency is not installed."""

    def __init__(self, module: str, extra: str):
        super().__init__(
            f"this needs the optional dependency {module!r}: "
            f"install it with `pip install 'imupipe[{extra}]'`"
        )
        self.module = module
        self.extra = extra


def require(module: str, extra: str):
    """Import an optional dependency or raise an error naming the extra to install."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtraError(module, extra) from exc


def describe_validation(exc: Any, model: Any, prefix: tuple = ()) -> str:
    """One line for a pydantic ``ValidationError``: key path of the first error, what is wrong.

    ``prefix`` is the key path of ``model`` inside a larger document (e.g.
    ``("stages", "gyro", "params")``). An unknown key comes first (a typo also
    shows as the missing key it meant) and gets a "did you mean" hint.
    """
    import difflib

    errors = sorted(exc.errors(), key=lambda e: e["type"] != "extra_forbidden")
    first = errors[0]
    loc = tuple(first["loc"])
    key = _key_path((*prefix, *loc)) or "(top level)"
    if first["type"] == "extra_forbidden":
        what = "unknown key"
        known = _fields_at(model, tuple(str(p) for p in loc[:-1]))
        close = difflib.get_close_matches(str(loc[-1]), known, n=1) if known else []
        if close:
            what += f"; did you mean {close[0]!r}?"
        elif known:
            what += f"; known keys: {', '.join(known)}"
    elif first["type"] == "missing":
        what = "missing required key"
    else:
        what = f"{first['msg'].removeprefix('Value error, ')} (found {first.get('input')!r})"
    more = f" (and {len(errors) - 1} more error(s))" if len(errors) > 1 else ""
    return f"{key}: {what}{more}"


def _key_path(parts: tuple) -> str:
    return "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in parts).lstrip(".")


def _fields_at(model: Any, loc: tuple) -> list[str]:
    """Field names of the (nested) pydantic model at ``loc``, when it is a model; else []."""
    from pydantic import BaseModel

    current: Any = model
    for part in loc:
        origin = getattr(current, "__origin__", None)
        if origin is dict:  # a table of sections: ``stages.<key>``
            current = current.__args__[1]
            continue
        if origin is list:
            current = current.__args__[0]
            continue
        if part.isdigit():
            continue
        if not (isinstance(current, type) and issubclass(current, BaseModel)):
            return []
        info = current.model_fields.get(part)
        if info is None:
            return []
        current = info.annotation
    if isinstance(current, type) and issubclass(current, BaseModel):
        return list(current.model_fields)
    return []
