"""Stage files: schema checks, provenance hashes (vs hashlib), atomic writes."""

from __future__ import annotations

import hashlib
import json

import h5py
import numpy as np
import pytest

from pixmuscle.errors import InputError, SchemaError
from pixmuscle.store import config_hash, open_stage, read_meta, write_dataset, write_stage


def test_roundtrip_and_provenance(tmp_path):
    src = tmp_path / "input.bin"
    src.write_bytes(b"pixel data" * 100)
    out = tmp_path / "sub" / "stage.h5"

    def write(f):
        write_dataset(f, "x", np.arange(5.0), units="cm")

    write_stage(out, schema="pixmuscle.test", version=3, write=write, config={"b": 1, "a": [1, 2]}, inputs=[src])
    with open_stage(out, schema="pixmuscle.test", version=3) as f:
        assert f["x"].attrs["units"] == "cm"
        np.testing.assert_array_equal(f["x"][()], np.arange(5.0))
    meta = read_meta(out)
    assert meta["units"]["length"] == "cm" and meta["units"]["force"] == "N"
    assert meta["provenance"]["inputs"][str(src)] == hashlib.sha256(src.read_bytes()).hexdigest()
    assert meta["provenance"]["config_sha256"] == config_hash({"a": [1, 2], "b": 1})  # key order irrelevant
    assert "a:" in meta["config"]
    assert list(tmp_path.joinpath("sub").iterdir()) == [out]  # no temporary left behind


def test_wrong_schema_and_version(tmp_path):
    out = tmp_path / "m.h5"
    write_stage(out, schema="pixmuscle.model", version=1, write=lambda f: None)
    with pytest.raises(SchemaError, match="schema 'pixmuscle.model' v1, expected 'pixmuscle.results' v1"):
        with open_stage(out, schema="pixmuscle.results", version=1):
            pass
    with pytest.raises(SchemaError, match="v1, expected 'pixmuscle.model' v2"):
        with open_stage(out, schema="pixmuscle.model", version=2):
            pass
    plain = tmp_path / "plain.h5"
    with h5py.File(plain, "w") as f:
        f["x"] = 1
    with pytest.raises(SchemaError, match="not a pixmuscle stage file"):
        with open_stage(plain, schema="pixmuscle.model", version=1):
            pass
    with pytest.raises(InputError, match="file not found"):
        with open_stage(tmp_path / "missing.h5", schema="pixmuscle.model", version=1):
            pass
    (tmp_path / "text.h5").write_text("not hdf5")
    with pytest.raises(InputError, match="not a readable HDF5 file"):
        with open_stage(tmp_path / "text.h5", schema="pixmuscle.model", version=1):
            pass


def test_killed_write_leaves_no_file(tmp_path):
    out = tmp_path / "stage.h5"
    write_stage(out, schema="pixmuscle.test", version=1, write=lambda f: f.create_dataset("old", data=1))

    def crash(f):
        f.create_dataset("half", data=np.zeros(10))
        raise KeyboardInterrupt  # simulates a killed run in the middle of writing

    with pytest.raises(KeyboardInterrupt):
        write_stage(out, schema="pixmuscle.test", version=1, write=crash)
    # the previous complete file is intact and no partial file is left
    with open_stage(out, schema="pixmuscle.test", version=1) as f:
        assert "old" in f and "half" not in f
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stage.h5"]
    json.loads(read_meta(out)["provenance"] and json.dumps(read_meta(out)["provenance"]))
