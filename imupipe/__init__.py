"""imupipe: calibrate MEMS IMUs from recorded sessions and explain what the model gets wrong."""

__version__ = "0.1.0"  # the one place it is set (pyproject.toml reads it)
