"""Config validation: unknown keys, wrong types, ranges, paths — each error names the key path."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Literal

import pytest

from pixmuscle.config import parse_section, read_yaml
from pixmuscle.errors import InputError


@dataclasses.dataclass(frozen=True)
class Inner:
    to: float = dataclasses.field(default=0.95, metadata={"range": (0.0, 1.0)})
    start: float = 0.0


@dataclasses.dataclass(frozen=True)
class Section:
    steps: int = dataclasses.field(default=10, metadata={"range": (1, None)})
    kernel: Literal["cubic", "tent"] = "cubic"
    a_over_h: tuple[float, ...] = (1.65, 1.65, 1.65)
    activation: Inner = dataclasses.field(default_factory=Inner)
    mesh: Path | None = dataclasses.field(default=None, metadata={"must_exist": True})
    names: dict[str, float] = dataclasses.field(default_factory=dict)
    penalty: float = dataclasses.field(default=1.0, metadata={"gt": 0})


def test_defaults_and_values(tmp_path):
    (tmp_path / "m.txt").write_text("x")
    cfg = parse_section(Section, {"steps": 3, "activation": {"to": 0.5}, "mesh": "m.txt", "a_over_h": [1, 2, 3]},
                        "solve", tmp_path)
    assert cfg.steps == 3 and cfg.activation.to == 0.5 and cfg.activation.start == 0.0
    assert cfg.mesh == (tmp_path / "m.txt").resolve()
    assert cfg.a_over_h == (1.0, 2.0, 3.0)
    assert parse_section(Section, None, "solve") == Section()


@pytest.mark.parametrize(
    "data, message",
    [
        ({"stpes": 3}, "solve.stpes: unknown key; did you mean 'steps'?"),
        ({"steps": "ten"}, "solve.steps: expected an integer, got 'ten'"),
        ({"steps": 0}, "solve.steps: expected a value ≥ 1, got 0"),
        ({"kernel": "cubik"}, "did you mean 'cubic'?"),
        ({"activation": {"to": 1.5}}, "solve.activation.to: expected a value ≤ 1.0, got 1.5"),
        ({"activation": {"too": 1}}, "solve.activation.too: unknown key"),
        ({"mesh": "missing.vtu"}, "solve.mesh: file not found"),
        ({"a_over_h": "1.65"}, "solve.a_over_h: expected a list of a number"),
        ({"names": {"a": "x"}}, "solve.names.a: expected a number"),
        ({"penalty": 0}, "solve.penalty: expected a value > 0"),
        ({"steps": True}, "solve.steps: expected an integer, got True"),
    ],
)
def test_errors_name_the_key(tmp_path, data, message):
    with pytest.raises(InputError) as exc:
        parse_section(Section, data, "solve", tmp_path)
    assert message in str(exc.value)


def test_required_key():
    @dataclasses.dataclass(frozen=True)
    class Req:
        mri: Path = dataclasses.field(metadata={"doc": "anatomical MRI, NIfTI"})

    with pytest.raises(InputError, match=r"seg.mri: required key is missing \(anatomical MRI, NIfTI\)"):
        parse_section(Req, {}, "seg")


def test_read_yaml_errors(tmp_path):
    with pytest.raises(InputError, match="config file not found"):
        read_yaml(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\n")
    with pytest.raises(InputError, match="not valid YAML"):
        read_yaml(bad)
    lst = tmp_path / "list.yaml"
    lst.write_text("- 1\n- 2\n")
    with pytest.raises(InputError, match="mapping of sections"):
        read_yaml(lst)
