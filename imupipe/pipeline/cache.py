"""The content-addressed cache of stage outputs, and the run manifest of a session.

A stage run's key is the sha256 of the canonical JSON of its ``KeyParts``: the
registered stage name and version, its validated params, its solver (name,
version, params) and the content digests of its inputs. A raw input's digest
is made from the session file(s) and the stream name; an upstream input's digest
is the upstream *output* digest, so an upstream rerun that produces the same
table invalidates nothing downstream (early cutoff).

Layout under ``<out>/.cache/``::

    <key[:2]>/<key>/<port>.arrow     outputs, provenance in schema metadata
    <key[:2]>/<key>/outputs.json     port -> output digest; written last (the entry is complete)
"""

from __future__ import annotations

import hashlib
import json
import tomllib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa

from .. import __version__
from ..errors import ImupipeError
from ..io import file_digest, read_arrow, table_digest, write_arrow, write_text
from .dag import Node

PROVENANCE_KEY = b"imupipe.provenance"
MANIFEST_FORMAT = 1


def canonical(obj: Any) -> str:
    """Canonical JSON: sorted keys, no spaces (the text that is hashed)."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


def sha256(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


# --------------------------------------------------------------------------- raw inputs


def session_files(path: Path) -> list[Path]:
    """The files whose bytes make a session: the file, plus those a ``.toml`` manifest names.

    A manifest's string values that name an existing file (relative to the
    manifest) are taken as its data files, whatever the manifest layout.
    """
    path = Path(path)
    files = [path]
    if path.suffix.lower() == ".toml":
        try:
            raw = tomllib.loads(path.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError, OSError):
            return files  # the reader will say what is wrong
        for text in _strings(raw):
            candidate = path.parent / text
            if len(text) < 4096 and candidate.is_file() and candidate.resolve() != path.resolve():
                files.append(candidate)
    return files


def _strings(obj: Any):
    if isinstance(obj, str):
        yield obj
    elif isinstance(obj, dict):
        for v in obj.values():
            yield from _strings(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from _strings(v)


def session_digest(path: Path) -> str:
    """Digest of a session's bytes (all its files, see ``session_files``)."""
    path = Path(path)
    parts = [
        [str(f.relative_to(path.parent)) if f != path else "", file_digest(f)]
        for f in session_files(path)
    ]
    return sha256(canonical(sorted(parts)))


def stream_digest(session: str, device: str | None, stream: str) -> str:
    """The digest of raw input ``session.<stream>`` of one device of a session."""
    return sha256(canonical({"session": session, "device": device, "stream": stream}))


# --------------------------------------------------------------------------- keys


@dataclass(frozen=True)
class KeyParts:
    """Everything a stage run's output depends on; ``key`` hashes it."""

    stage: str
    version: str
    params: dict
    solver: dict | None
    inputs: dict  # port -> content digest

    @property
    def key(self) -> str:
        return sha256(canonical(asdict(self)))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> KeyParts:
        return cls(d["stage"], d["version"], d["params"], d.get("solver"), d["inputs"])


def key_parts(node: Node, inputs: dict[str, str]) -> KeyParts:
    """The key parts of ``node`` given its input digests (port -> digest)."""
    params = node.params.model_dump(mode="json")
    solver = None
    if node.solver is not None:
        params.pop("solver_params", None)  # keyed by the validated solver params below
        s = node.solver.solver
        solver = {
            "name": s.name,
            "version": str(s.version),
            "params": node.solver.params.model_dump(mode="json"),
        }
    # normalise through JSON so tuples/lists and the manifest's copy compare equal
    return KeyParts(
        node.stage.name,
        str(node.stage.version),
        json.loads(canonical(params)),
        solver,
        dict(sorted(inputs.items())),
    )


# --------------------------------------------------------------------------- the cache


class Cache:
    """Stage outputs by key, under ``root`` (``<out>/.cache``). Safe for concurrent writers."""

    def __init__(self, root: Path):
        self.root = Path(root)

    def _dir(self, key: str) -> Path:
        return self.root / key[:2] / key

    def digests(self, key: str) -> dict[str, str] | None:
        """Output digests of a complete entry, or None when the key was never stored."""
        index = self._dir(key) / "outputs.json"
        try:
            outputs = json.loads(index.read_text())["outputs"]
        except (FileNotFoundError, json.JSONDecodeError, KeyError):
            return None
        if not all((self._dir(key) / f"{port}.arrow").is_file() for port in outputs):
            return None
        return outputs

    def load(self, key: str, port: str) -> pa.Table:
        """An output as the stage returned it (provenance stripped)."""
        path = self._dir(key) / f"{port}.arrow"
        try:
            table = read_arrow(path)
        except (pa.ArrowInvalid, OSError) as exc:
            raise ImupipeError(
                f"{path}: cached output is unreadable ({exc}); delete {self._dir(key)} and rerun"
            ) from None
        meta = {k: v for k, v in (table.schema.metadata or {}).items() if k != PROVENANCE_KEY}
        return table.replace_schema_metadata(meta or None)

    def store(
        self, parts: KeyParts, outputs: dict[str, pa.Table], stage_key: str
    ) -> dict[str, str]:
        """Write the outputs of one stage run; return port -> output digest."""
        key = parts.key
        digests = {port: table_digest(table) for port, table in outputs.items()}
        for port, table in outputs.items():
            provenance = {
                "stage": stage_key,
                "uses": parts.stage,
                "version": parts.version,
                "key": key,
                "port": port,
                "inputs": parts.inputs,
                "digest": digests[port],
                "imupipe_version": __version__,
            }
            meta = dict(table.schema.metadata or {})
            meta[PROVENANCE_KEY] = canonical(provenance).encode()
            write_arrow(self._dir(key) / f"{port}.arrow", table.replace_schema_metadata(meta))
        write_text(
            self._dir(key) / "outputs.json",
            json.dumps({"key": key, "parts": parts.to_dict(), "outputs": digests}, indent=1),
        )
        return digests


def provenance(path: Path) -> dict:
    """The provenance a cached Arrow file carries in its schema metadata."""
    from pyarrow import ipc

    with pa.memory_map(str(path), "r") as source:
        meta = ipc.open_file(source).schema.metadata or {}
    return json.loads(meta[PROVENANCE_KEY])


# --------------------------------------------------------------------------- run manifest


def read_manifest(path: Path) -> dict | None:
    """The run manifest of a session (``<out>/<session-id>/run.json``), or None."""
    try:
        manifest = json.loads(Path(path).read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None
    return manifest if manifest.get("format") == MANIFEST_FORMAT else None


def write_manifest(path: Path, manifest: dict) -> None:
    write_text(path, json.dumps({"format": MANIFEST_FORMAT, **manifest}, indent=1) + "\n")
