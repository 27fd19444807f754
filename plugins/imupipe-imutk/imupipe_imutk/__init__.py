"""imupipe plugin: imu_tk's ASCII sample files. Registers the ``imutk_text`` reader."""

from __future__ import annotations

from imupipe.hookspecs import hookimpl

from .reader import ImutkTextReader

__version__ = "0.1.0"


@hookimpl
def imupipe_register_readers(register):
    register(ImutkTextReader())
