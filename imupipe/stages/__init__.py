"""Built-in stages: every submodule lists its components in ``COMPONENTS``."""

from ..hookspecs import hookimpl
from ..registration import register_package


@hookimpl
def imupipe_register_stages(register):
    register_package(__name__, register)
