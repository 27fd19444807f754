"""Host-side hook implementations that every run has (not components)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pluggy

from .errors import ReaderError

hookimpl = pluggy.HookimplMarker("imupipe")


@hookimpl(trylast=True)
def imupipe_choose_reader(path: Path, head: bytes, readers: dict[str, Any]) -> str | None:
    claims = [name for name, reader in sorted(readers.items()) if reader.sniff(path, head)]
    if len(claims) > 1:
        raise ReaderError(
            f"{path}: readers {' and '.join(repr(c) for c in claims)} both claim this file; "
            "name one with `reader = \"NAME\"` in the session manifest or pipeline [input]"
        )
    return claims[0] if claims else None
