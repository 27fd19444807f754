"""Where the shipped schemas and pipelines are, in a source tree and in an installed wheel.

They live at the top of the repository (``schemas/``, ``pipelines/``); a wheel
installs them as data files under ``<prefix>/share/imupipe/`` (pyproject's
``[tool.setuptools.data-files]``).
"""

from __future__ import annotations

import sys
import sysconfig
from pathlib import Path

from .errors import ImupipeError


def shipped_dir(name: str) -> Path:
    """The directory of shipped ``name`` files (``"schemas"`` or ``"pipelines"``)."""
    candidates = [
        Path(__file__).resolve().parent.parent / name,  # source tree / editable install
        Path(sysconfig.get_path("data")) / "share" / "imupipe" / name,  # wheel data files
        Path(sys.prefix) / "share" / "imupipe" / name,
    ]
    for path in candidates:
        if path.is_dir():
            return path
    raise ImupipeError(f"the shipped {name}/ folder is missing (looked in {', '.join(map(str, candidates))}); "
                       "reinstall imupipe")
