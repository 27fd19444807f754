"""Table contracts: load ``schemas/*.json`` into pyarrow schemas, stamp and check tables.

A schema file is language-neutral JSON::

    {"id": "accel", "version": 1, "description": "...", "frame": "sensor",
     "fields": [{"name": "t_ns", "type": "int64", "unit": "ns", "description": "..."}, ...]}

``type`` is a pyarrow type name (``int64``, ``float64``, ``string``, ``bool``) or
``list<float64>[N]`` for a fixed-size list. Units go in field metadata, the schema
id, version and frame in schema metadata. Tables may carry extra columns.
"""

from __future__ import annotations

import json
import os
import re
from functools import cache
from pathlib import Path

import pyarrow as pa

from .errors import SchemaError
from .resources import shipped_dir

SCHEMA_KEY = b"imupipe.schema"
VERSION_KEY = b"imupipe.schema_version"
FRAME_KEY = b"imupipe.frame"
UNIT_KEY = b"unit"

_FIXED_LIST = re.compile(r"^list<(\w+)>\[(\d+)\]$")


def schema_dirs() -> list[Path]:
    """Where schema files live: ``$IMUPIPE_SCHEMAS`` (colon-separated), then the shipped ``schemas/``."""
    dirs = [Path(p) for p in os.environ.get("IMUPIPE_SCHEMAS", "").split(os.pathsep) if p]
    dirs.append(shipped_dir("schemas"))
    return dirs


def _arrow_type(name: str) -> pa.DataType:
    m = _FIXED_LIST.match(name)
    if m:
        return pa.list_(_arrow_type(m.group(1)), int(m.group(2)))
    try:
        return pa.type_for_alias(name)
    except ValueError:
        raise SchemaError(f"unknown field type {name!r} in a schema file") from None


@cache
def spec(schema_id: str) -> dict:
    """The parsed JSON of a schema, or an error naming the known ids."""
    for d in schema_dirs():
        path = d / f"{schema_id}.json"
        if path.is_file():
            return json.loads(path.read_text())
    known = sorted({p.stem for d in schema_dirs() if d.is_dir() for p in d.glob("*.json")})
    raise SchemaError(f"no schema {schema_id!r}; known: {', '.join(known)}")


@cache
def arrow_schema(schema_id: str) -> pa.Schema:
    """The pyarrow schema, with units in field metadata and id/version/frame in schema metadata."""
    s = spec(schema_id)
    fields = [
        pa.field(f["name"], _arrow_type(f["type"]), nullable=f.get("nullable", False),
                 metadata={UNIT_KEY: f.get("unit", "")})
        for f in s["fields"]
    ]
    meta = {SCHEMA_KEY: s["id"].encode(), VERSION_KEY: str(s["version"]).encode(),
            FRAME_KEY: s.get("frame", "none").encode()}
    return pa.schema(fields, metadata=meta)


def stamp(table: pa.Table, schema_id: str, extra: dict[str, str] | None = None) -> pa.Table:
    """Cast ``table``'s declared columns to the schema's types and attach its metadata.

    Extra columns are kept. Existing table metadata is kept, then overwritten by
    the schema's keys and ``extra``.
    """
    target = arrow_schema(schema_id)
    missing = [f.name for f in target if f.name not in table.column_names]
    if missing:
        raise SchemaError(f"table for schema {schema_id!r} lacks column(s) {', '.join(missing)}")
    fields, columns = [], []
    for name in table.column_names:
        col = table.column(name)
        if name in target.names:
            f = target.field(name)
            if col.type != f.type:  # a cast imports pyarrow.compute (~25 ms: a tenth of `imupipe ingest`)
                col = col.cast(f.type)
            fields.append(f)
        else:
            fields.append(table.schema.field(name))
        columns.append(col)
    meta = dict(table.schema.metadata or {})
    meta.update(target.metadata)
    for k, v in (extra or {}).items():
        meta[k.encode()] = v.encode()
    return pa.Table.from_arrays(columns, schema=pa.schema(fields, metadata=meta))


def schema_of(table: pa.Table) -> str | None:
    """The schema id a table claims, if any."""
    meta = table.schema.metadata or {}
    raw = meta.get(SCHEMA_KEY)
    return raw.decode() if raw else None


def check(table: pa.Table, schema_id: str, where: str = "") -> None:
    """Raise ``SchemaError`` unless ``table`` claims ``schema_id`` and has its columns and types."""
    prefix = f"{where}: " if where else ""
    if not isinstance(table, pa.Table):
        raise SchemaError(f"{prefix}expected an Arrow table of schema {schema_id!r}, got {type(table).__name__}")
    claimed = schema_of(table)
    if claimed != schema_id:
        raise SchemaError(f"{prefix}expected a table of schema {schema_id!r}, got one of schema {claimed!r}")
    target = arrow_schema(schema_id)
    for f in target:
        if f.name not in table.column_names:
            raise SchemaError(f"{prefix}table of schema {schema_id!r} lacks column {f.name!r}")
        actual = table.schema.field(f.name).type
        if actual != f.type:
            raise SchemaError(f"{prefix}column {f.name!r} of schema {schema_id!r} is {actual}, expected {f.type}")
        if not f.nullable and table.column(f.name).null_count:
            raise SchemaError(f"{prefix}column {f.name!r} of schema {schema_id!r} has nulls")


def unit(schema_id: str, column: str) -> str:
    """The unit of a column, as declared in its schema file."""
    return arrow_schema(schema_id).field(column).metadata[UNIT_KEY].decode()
