"""SurfelScene: allocation per config, op-ready properties, optimiser groups, replace, PLY, state."""
from __future__ import annotations

import pytest
import torch

from nsplat.config import ConfigError, from_dict
from nsplat.scene import SceneConfig, SurfelScene, knn_spacing


def _points(n: int = 50, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, 3, generator=g), torch.randn(n, 3, generator=g)


def _names(scene: SurfelScene) -> tuple[set[str], set[str]]:
    return {n for n, _ in scene.named_parameters()}, {n for n, _ in scene.named_buffers()}


def test_default_allocates_only_requested():
    m, n = _points()
    scene = SurfelScene.from_points(SceneConfig(), m, n)
    params, buffers = _names(scene)
    assert params == {"_means", "_normals", "_log_scales", "_features"}
    assert buffers == set()  # constant opacity: nothing allocated
    assert scene.opacities.shape == (50,) and bool((scene.opacities == 1.0).all())


def test_frozen_are_buffers_and_constants_absent():
    m, n = _points()
    cfg = SceneConfig(channels=5, learn=["means"], opacity=None, scale=0.1)
    scene = SurfelScene.from_points(cfg, m, n, opacities=0.3, features=torch.arange(5.0))
    params, buffers = _names(scene)
    assert params == {"_means"}
    assert buffers == {"_normals", "_opacity_logits", "_features"}
    assert scene.scales.shape == (50, 2) and bool((scene.scales == 0.1).all())
    assert torch.allclose(scene.opacities, torch.full((50,), 0.3))
    assert torch.equal(scene.features[7], torch.arange(5.0))
    with pytest.raises(KeyError, match="scales"):
        scene.tensor("scales")


def test_properties_are_op_ready_and_differentiable():
    m, n = _points()
    cfg = SceneConfig(learn=["means", "normals", "scales", "opacities", "features"], opacity=None,
                      feature_activation="sigmoid")
    scene = SurfelScene.from_points(cfg, m, 5 * n, scales=torch.rand(50, 2) + 0.1,
                                    opacities=torch.rand(50) * 0.9 + 0.05,
                                    features=0.25)
    assert torch.allclose(scene.normals.norm(dim=-1), torch.ones(50))
    assert bool((scene.scales > 0).all())
    assert bool(((scene.opacities > 0) & (scene.opacities < 1)).all())
    assert torch.allclose(scene.features, torch.full((50, 3), 0.25), atol=1e-6)
    loss = scene.means.sum() + scene.normals.sum() + scene.scales.sum() + scene.opacities.sum() + scene.features.sum()
    loss.backward()
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in scene.parameters())


def test_default_scale_is_neighbour_spacing():
    m, n = _points()
    scene = SurfelScene.from_points(SceneConfig(), m, n, scale_factor=2.0)
    sp = torch.as_tensor(knn_spacing(m), dtype=torch.float32)
    assert torch.allclose(scene.scales, 2.0 * sp[:, None].expand(50, 2), rtol=1e-5)


def test_param_groups():
    m, n = _points()
    scene = SurfelScene.from_points(SceneConfig(learn=["means", "features"]), m, n)
    groups = scene.param_groups({"default": 0.01, "means": 0.005, "opacities": 1.0})
    assert [(g["name"], g["lr"]) for g in groups] == [("means", 0.005), ("features", 0.01)]
    assert groups[0]["params"][0] is scene.tensor("means")
    with pytest.raises(ValueError, match="'features'"):
        scene.param_groups({"means": 0.01})
    with pytest.raises(ValueError, match="unknown attribute"):
        scene.param_groups({"default": 0.01, "colour": 0.1})


def test_replace_sets_rows_and_resets_adam_rows():
    m, n = _points()
    scene = SurfelScene.from_points(SceneConfig(), m, n)
    opt = torch.optim.Adam(scene.param_groups({"default": 0.01}))
    for _ in range(2):
        opt.zero_grad()
        (scene.means.pow(2).sum() + scene.features.sum() + scene.scales.sum() + scene.normals[:, 0].sum()).backward()
        opt.step()
    before = {k: v.clone() for k, v in scene.state_dict().items()}
    idx = torch.tensor([3, 10])
    new_means = torch.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    scene.replace(idx, {"means": new_means, "scales": torch.full((2, 2), 0.5)}, opt)
    assert torch.equal(scene.means[idx], new_means)
    assert torch.allclose(scene.scales[idx], torch.full((2, 2), 0.5))
    keep = torch.ones(50, dtype=torch.bool)
    keep[idx] = False
    assert torch.equal(scene.means[keep], before["_means"][keep])
    assert torch.equal(scene.tensor("features"), before["_features"])  # not given → unchanged
    for name in ("means", "normals", "scales", "features"):
        st = opt.state[scene.tensor(name)]
        assert bool((st["exp_avg"][idx] == 0).all()) and bool((st["exp_avg_sq"][idx] == 0).all())
        assert bool((st["exp_avg_sq"][keep] != 0).any())


def test_ply_roundtrip(tmp_path):
    m, n = _points()
    cfg = SceneConfig(channels=4, opacity=None, learn=["means"])
    scene = SurfelScene.from_points(cfg, m, n, scales=torch.rand(50, 2) + 0.1, opacities=0.7,
                                    features=torch.randn(50, 4))
    scene.save_ply(tmp_path / "s.ply")
    back = SurfelScene.load_ply(tmp_path / "s.ply", cfg)
    for name in ("means", "normals", "scales", "opacities", "features"):
        assert torch.allclose(getattr(back, name), getattr(scene, name), atol=1e-6), name
    with pytest.raises(ValueError, match="f_4"):
        SurfelScene.load_ply(tmp_path / "s.ply", SceneConfig(channels=5))
    with pytest.raises(FileNotFoundError, match="path"):
        SurfelScene.load_ply(tmp_path / "nope.ply", cfg)


def test_state_dict_roundtrip():
    m, n = _points()
    a = SurfelScene.from_points(SceneConfig(opacity=None, learn=["means", "opacities"]), m, n)
    b = SurfelScene(a.cfg, 50)
    b.load_state_dict(a.state_dict())
    assert torch.equal(a.opacities, b.opacities) and torch.equal(a.scales, b.scales)


@pytest.mark.parametrize("data, key", [
    ({"learn": ["means", "colour"]}, "scene.learn"),
    ({"learn": ["opacities"]}, "scene.learn"),
    ({"scale": 0.1, "learn": ["scales"]}, "scene.learn"),
    ({"opacity": 1.5}, "scene.opacity"),
    ({"channels": 0}, "scene.channels"),
    ({"feature_activation": "relu"}, "feature_activation"),
])
def test_config_errors_name_the_key(data, key):
    with pytest.raises(ConfigError, match=key):
        from_dict(SceneConfig, data, prefix="scene.")
