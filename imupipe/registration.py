"""Register every submodule's components from a package's hook implementation.

A built-in package (``imupipe.readers``, ``imupipe.stages``, ...) registers
whatever its submodules list in ``COMPONENTS``, so adding a module never means
editing a shared list.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable
from pathlib import Path
from typing import Any


def register_package(package: str, register: Callable[[Any], None]) -> None:
    pkg = importlib.import_module(package)
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda i: i.name):
        if info.name.startswith("_") or not _may_list_components(info):
            continue
        module = importlib.import_module(f"{package}.{info.name}")
        for component in getattr(module, "COMPONENTS", ()):
            register(component)


def _may_list_components(info: pkgutil.ModuleInfo) -> bool:
    """False for a source module that never names ``COMPONENTS``: a helper (the joint solver's
    block-tridiagonal algebra) with nothing to register is not imported for it (nor its scipy
    imports: ~0.15 s of a pipeline that never uses it)."""
    spec = info.module_finder.find_spec(info.name, None)
    origin = getattr(spec, "origin", None) or ""
    if not origin.endswith(".py"):
        return True
    return b"COMPONENTS" in Path(origin).read_bytes()
