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

from nsplat.config import ConfigError, load_config, read_yaml, to_dict, yaml_load
from nsplat.data.nerf_scenes import NERF_SCENES
from nsplat.tasks import get_task
from nsplat.tasks.neural.config import Config

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
    """The dotted keys a config file names itself (without its base); naming ``data.scene`` names ``data.root``
    too, which is the scene's folder unless given."""
    data = yaml_load(path.read_text())
    data.pop("base", None)
    own = set(_flat(data))
    return own | {"data.root"} if "data.scene" in own else own


def _chain(name: str) -> list[str]:
    """The config and its bases, nearest first."""
    out = [name]
    while (base := yaml_load((CONFIGS / out[-1]).read_text()).get("base")) is not None:
        out.append(base)
    return out


def test_there_are_derived_neural_configs():
    assert {"colmap.yaml", "lego.yaml", "lego_splat_only.yaml", "nerf_synthetic.yaml", "splat_only.yaml"} <= set(NEURAL)


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


def _nerf(*overrides: str) -> Config:
    return load_config(Config, read_yaml(CONFIGS / "nerf_synthetic.yaml"), list(overrides))


@pytest.mark.parametrize("scene", NERF_SCENES)
def test_nerf_synthetic_trains_any_scene_from_its_400_copy(scene):
    """``data.scene`` picks the folder: the scene's 400² copy whatever ``data.resolution``; ``data.root`` wins."""
    cfg = _nerf(f"data.scene={scene}")
    assert (cfg.data.scene, cfg.data.root) == (scene, f"$NSPLAT_DATA/nerf_synthetic/{scene}_400")
    assert _nerf(f"data.scene={scene}", "data.resolution=400").data.root == cfg.data.root
    assert _nerf(f"data.scene={scene}", "data.root=/my/copy").data.root == "/my/copy"
    lego = _flat(to_dict(_nerf()))
    differ = {k for k, v in _flat(to_dict(cfg)).items() if v != lego[k]}
    assert differ == (set() if scene == "lego" else {"data.scene", "data.root"})


def _resolved_with(path: Path, *overrides: str) -> dict[str, Any]:
    raw = read_yaml(path)
    return _flat(to_dict(load_config(get_task(raw["task"]).Config, raw, list(overrides))))


def test_lego_is_the_nerf_synthetic_recipe_on_lego_with_its_box():
    lego, base = _resolved(CONFIGS / "lego.yaml"), _flat(to_dict(_nerf("data.scene=lego")))
    assert lego["data.scene"] == "lego" and lego["data.root"] == "$NSPLAT_DATA/nerf_synthetic/lego_400"
    assert {k for k in lego if lego[k] != base[k]} == {"geometry.bbox"}
    assert lego["geometry.bbox"] == [-0.8, -1.3, -0.75, 0.8, 1.3, 1.15]
    chair = _resolved_with(CONFIGS / "lego.yaml", "data.scene=chair")
    assert chair["data.root"] == "$NSPLAT_DATA/nerf_synthetic/chair_400"


@pytest.mark.parametrize("override, needles", [
    ("data.scene=chairs", ["data.scene", "one of chair, drums", "'chairs'"]),
    ("data.scene=7", ["data.scene", "expected", "7"]),
    ("data.source=colmap", ["data.scene", "source colmap", "'lego'"]),
])
def test_a_bad_scene_is_a_config_error_naming_the_field(override, needles):
    with pytest.raises(ConfigError) as info:
        _nerf(override)
    message = str(info.value)
    assert message.startswith("data.scene: ") and "\n" not in message
    assert all(n in message for n in needles), message
