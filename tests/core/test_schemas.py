"""Table contracts: every schema file loads; stamp and check catch what they should."""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow as pa
import pytest

from imupipe import schemas
from imupipe.errors import SchemaError

REPO = Path(__file__).resolve().parents[2]

SCHEMA_FILES = sorted((REPO / "schemas").glob("*.json"))


@pytest.mark.parametrize("path", SCHEMA_FILES, ids=lambda p: p.stem)
def test_every_schema_file_loads(path):
    spec = json.loads(path.read_text())
    assert spec["id"] == path.stem, "a schema file is named after its id"
    schema = schemas.arrow_schema(spec["id"])
    assert schema.metadata[schemas.SCHEMA_KEY].decode() == spec["id"]
    for field in spec["fields"]:
        assert "unit" in field and "description" in field, f"{path.name}: {field['name']} lacks unit/description"


def test_stamp_then_check_and_units():
    t = pa.table({"t_ns": [1, 2], "x": [0.0, 1.0], "y": [0, 1], "z": [0.0, 1.0], "extra": ["a", "b"]})
    stamped = schemas.stamp(t, "accel")
    schemas.check(stamped, "accel")
    assert stamped.schema.field("y").type == pa.float64()
    assert stamped.column_names[-1] == "extra"
    assert schemas.unit("gyro", "x") == "rad/s" and schemas.unit("mag", "z") == "T"


def test_check_names_what_is_wrong():
    t = schemas.stamp(pa.table({"t_ns": [1], "x": [0.0], "y": [0.0], "z": [0.0]}), "accel")
    with pytest.raises(SchemaError, match="expected a table of schema 'gyro'"):
        schemas.check(t, "gyro")
    with pytest.raises(SchemaError, match="lacks column"):
        schemas.stamp(pa.table({"t_ns": [1], "x": [0.0]}), "accel")
    with pytest.raises(SchemaError, match="no schema 'nope'; known:"):
        schemas.spec("nope")
