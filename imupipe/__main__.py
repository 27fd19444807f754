"""``python -m imupipe ...``: the same as the ``imupipe`` command."""

import sys

from .cli import main

sys.exit(main())
