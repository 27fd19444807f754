"""imupipe: calibrate MEMS IMUs from recorded sessions and explain what the model gets wrong."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("imupipe")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"
