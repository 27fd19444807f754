"""The error hierarchy: every message says what was expected, what was found, and the fix.

Errors that are the user's to fix (bad input, bad config) are ``ImupipeError``
subclasses; the command line turns them into one line and exit status 2.
Anything else is an internal failure (exit status 1).
"""

from __future__ import annotations


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
