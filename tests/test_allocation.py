""""Model only what a scene requires": configs without neural features, SH lighting, pose corrections,
a discriminator or per-point opacity/scale allocate none of them (every parameter and buffer is
inspected), and the configs that ask for them do allocate them (so the check can fail)."""
from __future__ import annotations

from pathlib import Path

import pytest

from tools import allocation as AT

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"


def _entries(config: str, overrides: list[str] | None = None):
    _task, cfg, models, _notes = AT.build_config(CONFIGS / config, overrides)
    return cfg, AT.inventory(models)


def _names(entries) -> set[str]:
    return {f"{e.module}.{e.name}" for e in entries}


def _reconstruct_config() -> str:
    return sorted(p.name for p in CONFIGS.glob("reconstruct_*.yaml"))[0]


def _neural_config() -> str:
    for p in sorted(CONFIGS.glob("*.yaml")):
        if "task: neural" in p.read_text():
            return p.name
    raise AssertionError("no shipped config of the neural task")


def test_rgb_reconstruction_allocates_only_the_scene_attributes_it_uses():
    cfg, entries = _entries(_reconstruct_config())
    per_point = {e.name: e for e in entries if e.per_point}
    # exactly the attributes the scene config asks for, nothing else, nothing global
    assert set(per_point) == {AT_STORAGE[a] for a in cfg.scene.allocated()}
    assert all(e.per_point for e in entries), [str(e) for e in entries if not e.per_point]
    assert per_point["_features"].shape == (AT.N_PLACEHOLDER, 3)  # RGB albedo, no neural features
    assert not any("sh" in e.module.split(".") or "unet" in e.module or "coeffs" in e.name for e in entries)
    learned = {e.name for e in entries if e.learned}
    assert learned == {AT_STORAGE[a] for a in cfg.scene.learn}


def test_constant_opacity_and_scale_allocate_nothing():
    _, entries = _entries(_reconstruct_config(), ["scene.opacity=0.8", "scene.scale=0.01",
                                                  "scene.learn=[means,normals,features]"])
    names = {e.name for e in entries}
    assert "_opacity_logits" not in names and "_log_scales" not in names
    assert names == {"_means", "_normals", "_features"}
    _, per_point = _entries(_reconstruct_config(), ["scene.opacity=null",
                                                    "scene.learn=[means,normals,features,opacities,scales]"])
    assert {"_opacity_logits", "_log_scales"} <= {e.name for e in per_point}


def test_refine_without_sh_or_pose_learning_allocates_neither():
    _, entries = _entries("refine_room.yaml", ["shading.model=albedo", "poses.learn=false",
                                               "poses.learn_focal=false"])
    for e in entries:
        assert e.module.startswith("model.scene"), f"unexpected allocation {e.module}.{e.name} {e.shape}"
    # the shipped config (SH lighting, learned poses) does allocate them: the check can fail
    _, shipped = _entries("refine_room.yaml", ["shading.model=sh", "poses.learn=true"])
    assert "model.sh.coeffs" in _names(shipped)
    assert "model.cameras.twist" in _names(shipped)


def test_frozen_sh_is_a_buffer_and_focal_only_when_asked():
    _, entries = _entries("refine_room.yaml", ["shading.model=sh", "shading.learn_sh=false",
                                               "poses.learn_focal=false"])
    coeffs = [e for e in entries if e.name == "coeffs"]
    assert len(coeffs) == 1 and not coeffs[0].learned and coeffs[0].shape == (9, 3)
    assert not any(e.name == "log_focal" for e in entries)
    _, focal = _entries("refine_room.yaml", ["poses.learn_focal=true"])
    assert any(e.name == "log_focal" and e.learned for e in focal)


def test_neural_features_and_networks_only_in_the_neural_task():
    _, entries = _entries(_neural_config(), ["neural.features=7", "neural.gan.enabled=false"])
    feats = [e for e in entries if e.module == "stage2.scene" and e.name == "_features"]
    assert len(feats) == 1 and feats[0].shape == (AT.N_PLACEHOLDER, 7)
    assert not any(e.module.startswith("discriminator") for e in entries)  # GAN off: not built
    assert any(".unet" in e.module for e in entries)
    _, with_gan = _entries(_neural_config(), ["neural.gan.enabled=true"])
    assert any(e.module.startswith("discriminator") for e in with_gan)


@pytest.mark.parametrize("config", sorted(p.name for p in CONFIGS.glob("*.yaml")))
def test_every_shipped_config_builds_and_has_an_inventory(config):
    _, cfg, models, notes = AT.build_config(CONFIGS / config)
    entries = AT.inventory(models)
    assert notes
    names = [f"{e.module}.{e.name}" for e in entries]
    assert len(names) == len(set(names))


AT_STORAGE = {"means": "_means", "normals": "_normals", "scales": "_log_scales", "opacities": "_opacity_logits",
              "features": "_features"}


def test_point_only_builds_stage1_alone_and_view_colour_adds_only_the_sh_rest():
    """``neural.steps: 0`` (the point-only model) allocates stage 1's scene and nothing else, as the task builds;
    ``neural.view_colour`` adds exactly stage 1's higher SH coefficients (3·((L+1)² − 1) channels) to the
    stage-2 features and nothing else (the U-Net's input stays C + 1 channels)."""
    _, entries = _entries("lego_splat_only.yaml")
    assert {e.module.split(".")[0] for e in entries} == {"stage1_scene"}
    _, on = _entries("lego.yaml", ["neural.view_colour=true", "geometry.sh_degree=3"])
    _, off = _entries("lego.yaml", ["neural.view_colour=false", "geometry.sh_degree=3"])
    feats = {name: [e for e in ents if e.module == "stage2.scene" and e.name == "_features"][0].shape
             for name, ents in (("on", on), ("off", off))}
    assert feats == {"on": (AT.N_PLACEHOLDER, 16 + 45), "off": (AT.N_PLACEHOLDER, 16)}
    rest = {f"{e.module}.{e.name}": e.shape for e in on if e.module != "stage2.scene"}
    assert rest == {f"{e.module}.{e.name}": e.shape for e in off if e.module != "stage2.scene"}
