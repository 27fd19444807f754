"""Built-in solvers: every submodule lists its components in ``COMPONENTS``."""

from ..hookspecs import hookimpl
from ..registration import register_package


@hookimpl
def imupipe_register_solvers(register):
    register_package(__name__, register)
