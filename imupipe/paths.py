"""Output paths: every name derived from input made safe and unique, every path kept under ``--out``.

Anything written or deleted under an output folder goes through ``under`` (or
``safe_name``/``unique_names`` for a component made from input: a session's
stem, a device or topic name). A name that is not already a plain file-system
name (``..``, ``a/b``, control characters, a leading dot) is rewritten and, if
that rewrite is ambiguous, given a short hash of the original, so ``a/b`` and
``a_b`` never share a folder.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterable
from pathlib import Path

from .errors import ImupipeError

_UNSAFE = re.compile(r"[^A-Za-z0-9_.+-]+")
MAX_NAME = 100  # characters kept of a name made from input


def _short_hash(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest()[:8]


def safe_name(name: str, default: str = "imu") -> str:
    """``name`` as one plain path component (``/imu0/data`` -> ``imu0_data``; ``..`` -> ``_..-<hash>``).

    Never empty, never ``.`` or ``..``, never hidden (no leading dot), never a
    separator; a rewritten name that could be mistaken for another gets a hash of
    the original.
    """
    name = str(name)
    clean = _UNSAFE.sub("_", name).strip("_")
    if not clean.strip("."):  # "", ".", "..", "...": nothing left but dots
        return f"{default}-{_short_hash(name)}" if name else default
    if clean.startswith("."):
        clean = f"_{clean}"
    if len(clean) > MAX_NAME:
        clean = f"{clean[:MAX_NAME]}-{_short_hash(name)}"
    return clean


def unique_names(names: Iterable[str], default: str = "imu") -> dict[str, str]:
    """Original -> safe name, different originals never mapping to one name.

    A name that is already safe keeps its spelling; one whose safe form collides
    with another's gets ``-<hash of the original>``.
    """
    names = list(dict.fromkeys(str(n) for n in names))
    safe = {n: safe_name(n, default) for n in names}
    out: dict[str, str] = {}
    used: set[str] = set()
    # names that are already safe first, so they keep their spelling
    for n in sorted(names, key=lambda n: (safe[n] != n, names.index(n))):
        s = safe[n]
        if s.lower() in used:  # case-insensitive file systems too
            s = f"{s}-{_short_hash(n)}"
        used.add(s.lower())
        out[n] = s
    return {n: out[n] for n in names}


def under(root: Path, *parts: str | Path) -> Path:
    """``root / parts...``, refused (``ImupipeError``) unless it lies inside ``root``.

    Checked on the resolved paths, so neither ``..`` nor a symbolic link can lead
    a write or a removal out of the output folder.
    """
    root = Path(root)
    path = root.joinpath(*parts)
    try:
        base = root.resolve()
        target = path.resolve()
    except (OSError, RuntimeError) as exc:  # a symlink loop
        raise ImupipeError(f"{path}: cannot resolve the output path ({exc}); "
                           "remove the looping link") from None
    if target == base and not parts:
        return path
    if target == base or not target.is_relative_to(base):
        raise ImupipeError(
            f"{path}: refused, it lies outside the output folder {root} "
            "(a name from the input leads out of it); rename the session or device"
        )
    return path


def check_out_dir(out: Path) -> Path:
    """Make the output folder ``out`` (parents too), or one line saying why it cannot be."""
    import os

    out = Path(out)
    try:
        if out.exists() and not out.is_dir():
            raise ImupipeError(f"--out {out}: is a file, not a folder; give a folder")
        out.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise ImupipeError(f"--out {out}: a file stands in its path; give a folder") from None
    except NotADirectoryError:
        raise ImupipeError(f"--out {out}: lies below a file, not a folder; give a folder") from None
    except PermissionError:
        raise ImupipeError(f"--out {out}: permission denied; give a folder you can write") from None
    except OSError as exc:
        raise ImupipeError(f"--out {out}: cannot be made ({exc.strerror or exc})") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise ImupipeError(f"--out {out}: not writable; give a folder you can write")
    return out
