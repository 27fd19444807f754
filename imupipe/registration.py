"""Register every submodule's components from a package's hook implementation.

A built-in package (``imupipe.readers``, ``imupipe.stages``, ...) registers
whatever its submodules list in ``COMPONENTS``, so adding a module never means
editing a shared list.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable
from typing import Any


def register_package(package: str, register: Callable[[Any], None]) -> None:
    pkg = importlib.import_module(package)
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{package}.{info.name}")
        for component in getattr(module, "COMPONENTS", ()):
            register(component)
