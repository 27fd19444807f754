"""Human reports: ``report.md`` with figures (the ``report`` exporter, matplotlib extra).

Registered through the entry point ``builtin_report = "imupipe.report"``.
"""

from ..hookspecs import hookimpl


@hookimpl
def imupipe_register_exporters(register):
    from .exporter import REPORT

    register(REPORT)
