"""The shipped configs derive from each other: a recipe change reaches every config built on it.

Every config of the neural task derives (``base:``, possibly through another) from ``configs/default.yaml``,
the main job; every setting a derived config does not name is its base's; and changing the main recipe
changes ``configs/colmap.yaml`` (which says it trains the main job's recipe on your photos).
"""
from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import pytest
import yaml

from nsplat.config import load_config, read_yaml, to_dict, yaml_load
from nsplat.tasks import get_task

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
NEURAL = sorted(p.name for p in CONFIGS.glob("*.yaml") if read_yaml(p)["task"] == "neural")


def _resolved(path: Path) -> dict[str, Any]:
    """The flat ``{dotted key: value}`` of a config file's resolved dataclass."""
    raw = read_yaml(path)
    over = ["data.root=my_scene"] if raw.get("data", {}).get("source") in ("colmap", "transforms") else []
    return _flat(to_dict(load_config(get_task(raw["task"]).Config, raw, over)))


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict) and v:
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


def _own_keys(path: Path) -> set[str]:
    """The dotted keys a config file names itself (without its base)."""
    data = yaml_load(path.read_text())
    data.pop("base", None)
    return set(_flat(data))


def _chain(name: str) -> list[str]:
    """The config and its bases, nearest first."""
    out = [name]
    while (base := yaml_load((CONFIGS / out[-1]).read_text()).get("base")) is not None:
        out.append(base)
    return out


def test_there_are_derived_neural_configs():
    assert {"colmap.yaml", "lego.yaml", "lego_splat_only.yaml", "splat_only.yaml"} <= set(NEURAL)


@pytest.mark.parametrize("name", [n for n in NEURAL if n != "default.yaml"])
def test_every_neural_config_derives_from_the_main_job(name):
    assert _chain(name)[-1] == "default.yaml", _chain(name)


@pytest.mark.parametrize("name", [n for n in NEURAL if n != "default.yaml"])
def test_what_a_derived_config_does_not_name_is_its_bases(name):
    path = CONFIGS / name
    base = CONFIGS / yaml_load(path.read_text())["base"]
    own, mine, theirs = _own_keys(path), _resolved(path), _resolved(base)
    inherited = [k for k in theirs if not any(k == o or k.startswith(o + ".") for o in own)]
    assert len(inherited) > 50
    differ = {k: (theirs[k], mine[k]) for k in inherited if mine[k] != theirs[k]}
    assert not differ, f"{name} differs from its base {base.name} where it names nothing: {differ}"


def test_a_change_of_the_main_recipe_reaches_colmap(tmp_path):
    """colmap.yaml trains the main job's recipe: change default.yaml's stage 2 and colmap.yaml follows (all but
    the stage-2 length, which colmap.yaml names: 1000 steps, selected on the lego capture's val curves)."""
    folder = tmp_path / "configs"
    shutil.copytree(CONFIGS, folder)
    before = _resolved(folder / "colmap.yaml")
    default = yaml_load((folder / "default.yaml").read_text())
    default["neural"]["batch"] = 3
    default["neural"]["unet"]["width"] = 24
    default["render"]["lowpass"] = 0.7
    (folder / "default.yaml").write_text(yaml.safe_dump(default, sort_keys=False))
    after = _resolved(folder / "colmap.yaml")
    assert (before["neural.batch"], before["neural.unet.width"], before["neural.steps"]) == (2, 16, 1000)
    assert (after["neural.batch"], after["neural.unet.width"], after["render.lowpass"]) == (3, 24, 0.7)
    assert {k for k in after if after[k] != before[k]} == {"neural.batch", "neural.unet.width", "render.lowpass"}
