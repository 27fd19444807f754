"""The content-addressed cache of stage outputs, and the run manifest of a session.

A stage run's key is the sha256 of the canonical JSON of its ``KeyParts``: the
registered stage name and version, the plugin distribution that provides it
(name and version; none for imupipe's own stages, which are versioned by their
``version``), its validated params, its solver (name, version, distribution,
params) and the content digests of its inputs. A raw input's digest is made
from the session file(s), the stream name and the reader that turns them into
tables (its name, distribution and version, and those of any reader a session
manifest delegates to); an upstream input's digest is the upstream *output*
digest, so an upstream rerun that produces the same table invalidates nothing
downstream (early cutoff).

Layout under ``<out>/.cache/``::

    <key[:2]>/<key>/<port>.arrow     outputs, provenance in schema metadata
    <key[:2]>/<key>/outputs.json     port -> output digest, the stage's warnings; written
                                     last (the entry is complete)
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa
from pyarrow import ipc

from .. import __version__
from ..errors import ImupipeError
from ..io import file_digest, table_digest, write_arrow_hashed, write_text
from ..plugins import Registry
from .dag import Node

PROVENANCE_KEY = b"imupipe.provenance"
MANIFEST_FORMAT = 1
log = logging.getLogger("imupipe.pipeline")
OWN_DISTRIBUTION = "imupipe"  # its components are versioned by their own ``version``


def canonical(obj: Any) -> str:
    """Canonical JSON: sorted keys, no spaces (the text that is hashed)."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


def sha256(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


# --------------------------------------------------------------------------- raw inputs


def session_digest(path: Path, reader: Any = None) -> str:
    """Digest of a session's bytes: the file, and the files its reader says it is made of
    (the reader's optional ``inputs(path)``, e.g. a manifest's data files)."""
    path = Path(path)
    inputs = getattr(reader, "inputs", None)
    files = [path, *(inputs(path) if callable(inputs) else [])]
    parts = [[_relative(f, path.parent) if f != path else "", file_digest(f) if f.is_file() else None]
             for f in files]
    return sha256(canonical(sorted(parts, key=str)))


def _relative(file: Path, folder: Path) -> str:
    """``file`` as the manifest names it relative to ``folder`` (absolute if on another drive)."""
    try:
        return os.path.relpath(file, folder)
    except ValueError:  # Windows: another drive
        return str(file.resolve())


def stream_digest(session: str, device: str | None, stream: str, reader: dict | None) -> str:
    """The digest of raw input ``session.<stream>`` of one device of a session.

    ``reader``: ``reader_identity`` of the reader that turns the session into tables.
    """
    return sha256(
        canonical({"session": session, "device": device, "stream": stream, "reader": reader})
    )


# --------------------------------------------------------------------------- plugin versions


def distribution(registry: Registry, kind: str, name: str) -> dict | None:
    """``{"name", "version"}`` of the plugin distribution providing a component.

    None for imupipe's own components (their ``version`` attribute keys them, so a
    release does not rerun everything) and for plugins registered without one
    (e.g. a test's fixture module).
    """
    component = registry.components[kind].get(name)
    if component is None or not component.distribution:
        return None
    if component.distribution == OWN_DISTRIBUTION:
        return None
    return {"name": component.distribution, "version": component.dist_version}


def claimant(registry: Registry, path: Path, forced: str | None):
    """The reader that would read ``path`` (chosen by sniffing, nothing is read)."""
    from ..ingest import choose_reader

    return choose_reader(Path(path), registry, forced)


def reader_identity(registry: Registry, reader: Any, path: Path) -> dict:
    """What makes a session's tables besides its bytes: the reader chosen for ``path``.

    ``{"name", "distribution", "version", "delegates": [...]}``: the reader's
    distribution and version, imupipe's own included (readers have no version of
    their own, so a fix in a built-in reader reaches the cache only this way),
    and the same for every reader a session manifest hands files to
    (the reader's optional ``delegates(path)``). Chosen by sniffing, nothing is read.
    """
    identity = _reader_entry(registry, reader.name)
    delegates = getattr(reader, "delegates", None)
    if callable(delegates):
        identity["delegates"] = [_reader_entry(registry, n) for n in sorted(set(delegates(path)))]
    return identity


def _reader_entry(registry: Registry, name: str) -> dict:
    component = registry.components["readers"].get(name)
    if component is None:  # a manifest may name a reader only the installed plugins provide
        from ..plugins import make_registry

        component = make_registry().components["readers"].get(name)
    if component is None:
        return {"name": name, "distribution": "", "version": ""}
    return {"name": name, "distribution": component.distribution,
            "version": component.dist_version}


# --------------------------------------------------------------------------- keys


@dataclass(frozen=True)
class KeyParts:
    """Everything a stage run's output depends on; ``key`` hashes it."""

    stage: str
    version: str
    params: dict
    solver: dict | None  # name, version, distribution, params
    inputs: dict  # port -> content digest
    distribution: dict | None = None  # a plugin stage's {"name", "version"}; None: built in

    @property
    def key(self) -> str:
        return sha256(canonical(asdict(self)))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> KeyParts:
        return cls(
            d["stage"], d["version"], d["params"], d.get("solver"), d["inputs"],
            d.get("distribution"),
        )


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
            "distribution": node.solver_distribution,
            "params": node.solver.params.model_dump(mode="json"),
        }
    # normalise through JSON so tuples/lists and the manifest's copy compare equal
    return KeyParts(
        node.stage.name,
        str(node.stage.version),
        json.loads(canonical(params)),
        solver,
        dict(sorted(inputs.items())),
        node.distribution,
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
        entry = self.entry(key)
        return None if entry is None else entry["outputs"]

    def entry(self, key: str) -> dict | None:
        """A complete, verified entry's index (``outputs``: port -> digest, ``warnings``), or None.

        Every output file's size and sha256 are checked against those recorded when
        it was stored; a damaged or incomplete entry is a miss, with a warning (the
        stage reruns and replaces it).
        """
        index = self._dir(key) / "outputs.json"
        try:
            entry = json.loads(index.read_text())
            outputs = entry["outputs"]
            files = entry.get("files")
        except FileNotFoundError:
            return None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError):
            log.warning("cache entry %s is damaged (unreadable outputs.json); recomputing it",
                        self._dir(key))
            return None
        if not isinstance(files, dict) or set(files) != set(outputs):
            log.info("cache entry %s records no file digests (older imupipe); recomputing it",
                     self._dir(key))
            return None
        for port in outputs:
            why = self._damage(key, port, files[port])
            if why:
                log.warning("cache entry %s is damaged (%s.arrow: %s); recomputing it",
                            self._dir(key), port, why)
                return None
        entry.setdefault("warnings", [])
        return entry

    def _damage(self, key: str, port: str, record: dict, data: bytes | None = None) -> str:
        """Why the stored file of ``port`` does not match its record, or "" when it does."""
        path = self._dir(key) / f"{port}.arrow"
        try:
            if data is None:
                size = path.stat().st_size
                if size != record.get("size"):
                    return f"{size} bytes, {record.get('size')} were stored"
                data = path.read_bytes()
        except FileNotFoundError:
            return "missing"
        except (OSError, AttributeError) as exc:
            return f"unreadable: {exc}"
        if len(data) != record.get("size"):
            return f"{len(data)} bytes, {record.get('size')} were stored"
        if hashlib.sha256(data).hexdigest() != record.get("sha256"):
            return "content does not match its digest"
        return ""

    def load(self, key: str, port: str) -> pa.Table:
        """An output as the stage returned it (provenance stripped); its bytes verified first."""
        path = self._dir(key) / f"{port}.arrow"
        try:
            data = path.read_bytes()
            record = (json.loads((self._dir(key) / "outputs.json").read_text()).get("files") or {})
            why = self._damage(key, port, record.get(port) or {}, data)
            if why:
                raise ImupipeError(f"{path}: cached output is damaged ({why}); rerun to recompute it")
            with pa.BufferReader(data) as source:
                table = ipc.open_file(source).read_all()
        except (pa.ArrowInvalid, OSError, json.JSONDecodeError, AttributeError) as exc:
            raise ImupipeError(
                f"{path}: cached output is unreadable ({exc}); delete {self._dir(key)} and rerun"
            ) from None
        meta = {k: v for k, v in (table.schema.metadata or {}).items() if k != PROVENANCE_KEY}
        return table.replace_schema_metadata(meta or None)

    def store(
        self,
        parts: KeyParts,
        outputs: dict[str, pa.Table],
        stage_key: str,
        warnings: Sequence[str] = (),
    ) -> dict[str, str]:
        """Write the outputs of one stage run and the warnings it gave; return port -> digest.

        ``outputs.json`` (written last, so an entry without it is incomplete) records
        each file's size and sha256, checked whenever the entry is reused.
        """
        key = parts.key
        digests = {port: table_digest(table) for port, table in outputs.items()}
        files = {}
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
            size, sha256 = write_arrow_hashed(self._dir(key) / f"{port}.arrow", table.replace_schema_metadata(meta))
            files[port] = {"size": size, "sha256": sha256}
        write_text(
            self._dir(key) / "outputs.json",
            json.dumps(
                {"key": key, "parts": parts.to_dict(), "outputs": digests, "files": files,
                 "warnings": list(warnings)},
                indent=1,
            ),
        )
        return digests


def provenance(path: Path) -> dict:
    """The provenance a cached Arrow file carries in its schema metadata."""
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
