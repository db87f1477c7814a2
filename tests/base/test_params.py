"""Typed parameter parsing and atomic outputs."""

from __future__ import annotations

import dataclasses
from typing import Literal

import pytest

from trace3d.errors import ConfigError
from trace3d.io import atomic_dir, atomic_file
from trace3d.params import from_mapping, load_params_arg


@dataclasses.dataclass
class Inner:
    depth: int = 2


@dataclasses.dataclass
class Example:
    threshold: float = 0.5
    iterations: int = 1000
    mode: Literal["a", "b"] = "a"
    enabled: bool = True
    inner: Inner = dataclasses.field(default_factory=Inner)
    sizes: list[int] = dataclasses.field(default_factory=lambda: [1, 2])
    path: str | None = None


def test_defaults_and_overrides():
    p = from_mapping(Example, {"threshold": 1, "mode": "b", "inner": {"depth": 5}, "path": "x"})
    assert p.threshold == 1.0 and isinstance(p.threshold, float)
    assert p.mode == "b" and p.inner.depth == 5 and p.path == "x" and p.iterations == 1000


@pytest.mark.parametrize(
    "values, message",
    [
        ({"treshold": 0.3}, r"unknown parameter\(s\) \['treshold'\]"),
        ({"iterations": 1.5}, r"params.iterations: expected an integer"),
        ({"iterations": True}, r"params.iterations: expected an integer"),
        ({"enabled": "yes"}, r"params.enabled: expected true or false"),
        ({"mode": "c"}, r"params.mode: 'c' is not one of \['a', 'b'\]"),
        ({"inner": {"dpth": 1}}, r"params.inner: unknown parameter"),
        ({"sizes": [1, "x"]}, r"params.sizes\[1\]: expected an integer"),
    ],
)
def test_refusals(values, message):
    with pytest.raises(ConfigError, match=message):
        from_mapping(Example, values)


def test_load_params_arg(tmp_path):
    assert load_params_arg('{"a": 1}') == {"a": 1}
    assert load_params_arg("") == {}
    f = tmp_path / "p.yaml"
    f.write_text("a: 2\n")
    assert load_params_arg(f"@{f}") == {"a": 2}
    with pytest.raises(ConfigError, match="does not exist"):
        load_params_arg(f"@{tmp_path / 'missing.yaml'}")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_params_arg("[1, 2]")


def test_atomic_dir_keeps_old_result_on_failure(tmp_path):
    out = tmp_path / "step"
    with atomic_dir(out) as tmp:
        (tmp / "result.txt").write_text("first")
    with pytest.raises(RuntimeError):
        with atomic_dir(out) as tmp:
            (tmp / "result.txt").write_text("half")
            raise RuntimeError("killed")
    assert (out / "result.txt").read_text() == "first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step"]
    with atomic_dir(out) as tmp:
        (tmp / "result.txt").write_text("second")
    assert (out / "result.txt").read_text() == "second"


def test_atomic_file(tmp_path):
    out = tmp_path / "a.json"
    out.write_text("old")
    with pytest.raises(ValueError):
        with atomic_file(out) as tmp:
            tmp.write_text("new")
            raise ValueError
    assert out.read_text() == "old"
    assert len(list(tmp_path.iterdir())) == 1
