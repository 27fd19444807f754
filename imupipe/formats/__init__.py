"""Exporters of a calibration to the files other software loads (``imupipe run --export``).

One module per target: ``kalibr``, ``imu_tk``, ``px4``, ``ardupilot``, ``imu_calib``.
Each writes under ``<out>/<session>/export/`` and says, in a comment inside the
file and in the log, whatever part of imupipe's calibration the target cannot
hold. Registered through the entry point ``builtin_formats = "imupipe.formats"``.
"""

from ..hookspecs import hookimpl
from ..registration import register_package


@hookimpl
def imupipe_register_exporters(register):
    register_package(__name__, register)
