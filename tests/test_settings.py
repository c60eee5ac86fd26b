"""One name and one default per setting.

Every setting is a field of a config dataclass: declared once with its default, its range check (a bad value
fails at load with the dotted key in the message) and its one-line doc (the class docstring). These tests
enumerate every setting of every task's config and of the viewer and check that:

* each is documented, and each section's default is its class's default (no second default for a section
  where it is used: a YAML that names part of a section gets the class defaults for the rest, always);
* each numeric setting rejects a value outside its range (NaN for floats, a large negative for integers),
  naming its dotted key;
* the render settings keep one name everywhere: no other section declares a field of the op's settings, and
  the spellings of evaluation (``eval.render.<name>``), the viewer (``viewer.render.<name>``) and the command
  line (``--seed``) resolve to the same fields.
"""
from __future__ import annotations

import dataclasses
import re
import types
import typing
from pathlib import Path
from typing import Any, Iterator

import pytest

from nsplat.cli import _configs, _parse
from nsplat.config import ConfigError, load_config, read_yaml, to_dict
from nsplat.ops import SplatSettings
from nsplat.render.renderer import RenderConfig
from nsplat.tasks import TASKS, get_task
from nsplat.viewer.config import ViewerConfig, split_viewer_overrides

ROOT = Path(__file__).resolve().parents[1]

#: Minimal valid raw config per task (what a key needs besides its own value to load).
BASES: dict[str, dict[str, Any]] = {name: {"task": name} for name in TASKS}

def _sections(cls: type, prefix: str = "") -> Iterator[tuple[str, type, dataclasses.Field]]:
    """``(dotted key, owning class, field)`` of every field of ``cls`` and its nested sections."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        yield prefix + f.name, cls, f
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            yield from _sections(tp, f"{prefix}{f.name}.")


def _settings() -> list[tuple[str, str, type, dataclasses.Field]]:
    """``(task, dotted key, owning class, field)`` of every setting of every task and of the viewer."""
    out = [(task, key, owner, f) for task in sorted(TASKS) for key, owner, f in _sections(get_task(task).Config)]
    out += [("viewer", "viewer." + key, owner, f) for key, owner, f in _sections(ViewerConfig)]
    return out


SETTINGS = _settings()


def _numeric(tp: Any) -> str | None:
    """``"int"`` / ``"float"`` when the annotation holds numbers (also optional ones and tuples of them)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is int:
        return "int"
    if tp is float:
        return "float"
    if origin in (typing.Union, types.UnionType, tuple, list):
        kinds = {_numeric(a) for a in args if a is not type(None) and a is not Ellipsis}
        return "float" if "float" in kinds else ("int" if kinds == {"int"} else None)
    return None


def test_the_enumeration_sees_every_task_and_the_viewer():
    tasks = {task for task, *_ in SETTINGS}
    assert tasks == set(TASKS) | {"viewer"}
    assert len(SETTINGS) > 250  # every leaf and section of the four tasks and the viewer


@pytest.mark.parametrize("task,key,owner,field", SETTINGS, ids=[f"{t}:{k}" for t, k, *_ in SETTINGS])
def test_every_setting_is_documented_in_its_class(task, key, owner, field):
    declared = next(c for c in owner.__mro__ if field.name in vars(c).get("__annotations__", {}))
    doc = declared.__doc__ or ""
    assert re.search(rf"(?<![\w.]){re.escape(field.name)}(?![\w(])", doc), \
        f"{key}: not documented in {declared.__module__}.{declared.__qualname__}'s docstring"


@pytest.mark.parametrize("task,key,owner,field", SETTINGS, ids=[f"{t}:{k}" for t, k, *_ in SETTINGS])
def test_a_section_has_one_default_its_class_default(task, key, owner, field):
    tp = typing.get_type_hints(owner)[field.name]
    if not dataclasses.is_dataclass(tp):
        return
    try:
        default = getattr(owner(), field.name)
    except (TypeError, ValueError):  # a section that cannot stand alone (its owner needs other keys)
        default = field.default_factory() if field.default_factory is not dataclasses.MISSING else field.default
    assert default == tp(), (f"{key}: the section's default differs from {tp.__name__}()'s; set the values in "
                             "the YAML recipe instead (a YAML naming part of the section would get the class's)")


def _override(task: str, key: str, value: str) -> None:
    if task == "viewer":
        split_viewer_overrides([f"{key}={value}"])
    else:
        load_config(get_task(task).Config, BASES[task], [f"{key}={value}"])


NUMERIC = [(t, k, o, f) for t, k, o, f in SETTINGS if _numeric(typing.get_type_hints(o)[f.name])]


@pytest.mark.parametrize("task,key,owner,field", NUMERIC, ids=[f"{t}:{k}" for t, k, *_ in NUMERIC])
def test_every_numeric_setting_is_range_checked_naming_its_key(task, key, owner, field):
    tp = typing.get_type_hints(owner)[field.name]
    kind = _numeric(tp)
    origin = typing.get_origin(tp)
    default = getattr(owner(), field.name) if _constructs(owner) else None
    bad = ".nan" if kind == "float" else "-1000000007"
    if origin in (tuple, list) or isinstance(default, (tuple, list)):
        length = len(default) if isinstance(default, (tuple, list)) else len(typing.get_args(tp))
        bad = "[" + ", ".join([bad] * max(1, length)) + "]"
    with pytest.raises(ConfigError) as err:
        _override(task, key, bad)
    assert key in str(err.value), str(err.value)


def _constructs(cls: type) -> bool:
    try:
        cls()
        return True
    except (TypeError, ValueError):
        return False


OP_FIELDS = set(SplatSettings.names())


def test_render_settings_are_declared_in_the_render_section_only():
    render_sections = {RenderConfig}
    twins = [f"{task}: {key}" for task, key, owner, f in SETTINGS
             if owner not in render_sections and f.name in OP_FIELDS and owner is not SplatSettings]
    assert not twins, f"op settings declared outside a render section (one name, one default): {twins}"


@pytest.mark.parametrize("name", sorted(f.name for f in dataclasses.fields(RenderConfig)))
def test_eval_and_viewer_spellings_resolve_to_the_render_fields(name):
    """``eval.render.<name>`` and ``viewer.render.<name>`` set exactly ``render.<name>`` of their renders."""
    base = RenderConfig()
    value = _other_value(name, getattr(base, name))
    cfg = load_config(get_task("neural").Config, BASES["neural"], [f"eval.render.{name}={value}"])
    assert getattr(cfg.eval_render(), name) == _parsed(value) and getattr(cfg.render, name) == getattr(base, name)
    _, viewer = split_viewer_overrides([f"viewer.render.{name}={value}"])
    assert getattr(viewer.render_cfg(base), name) == _parsed(value)
    changed = [k for k, v in to_dict(viewer.render_cfg(base)).items() if v != to_dict(base)[k]]
    assert changed == [name]


def _other_value(name: str, default: Any) -> str:
    """A valid value of render setting ``name`` other than its default, as override text."""
    choices = {"renderer": "dense", "estimator": "sampled", "composite": "additive", "background": "[0.5, 0.5, 0.5]"}
    if name in choices:
        return choices[name]
    if isinstance(default, bool):
        return str(not default).lower()
    if isinstance(default, int):
        return str(default + 1)
    if isinstance(default, float):
        return repr(default * 0.5 if name != "far" else default * 2)
    raise AssertionError(f"no test value for render.{name}")


def _parsed(text: str) -> Any:
    from nsplat.config import yaml_load

    return yaml_load(text)


def test_the_command_line_seed_is_the_config_seed(tmp_path):
    """``--seed N`` is the setting ``seed`` under its own name: the same config as ``seed=N``."""
    default = ROOT / "configs" / "demo.yaml"
    by_flag = _configs(_parse(["--config", str(default), "--seed", "7"]))[1]
    by_key = _configs(_parse(["--config", str(default), "seed=7"]))[1]
    assert by_flag.seed == 7 and to_dict(by_flag) == to_dict(by_key)


def test_the_shipped_configs_load():
    for path in sorted((ROOT / "configs").glob("*.yaml")):
        raw = read_yaml(path)
        capture = raw.get("data", {}).get("source") in ("colmap", "transforms")
        over = ["data.root=my_scene"] if capture and not raw["data"].get("root") else []
        cfg = load_config(get_task(raw["task"]).Config, raw, over)
        assert cfg.task == raw["task"]
