"""The op's settings live in one place: :class:`nsplat.ops.SplatSettings`, held by ``Splatter`` and built
by the render gateway's ``RenderConfig``."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from nsplat.config import ConfigError, FieldError, from_dict
from nsplat.ops import SplatSettings, Splatter
from nsplat.render.renderer import RenderConfig, render
from tests.conftest import make_cameras, make_scene

PARAMS = ("means", "normals", "scales", "opacities", "features")


def test_render_config_op_fields_are_the_settings_with_their_defaults():
    fields = {f.name: f.default for f in dataclasses.fields(RenderConfig)}
    for f in dataclasses.fields(SplatSettings):
        assert f.name in fields, f.name
        assert fields[f.name] == f.default, f.name
    assert RenderConfig(samples=7, estimator="paper").op_settings() == SplatSettings(samples=7, estimator="paper")
    assert RenderConfig().op_settings("sampled").estimator == "sampled"


def test_render_config_validates_with_the_op_checks():
    with pytest.raises(FieldError, match=r"^hermite_order: expected an int in \[0, 16\], got 17$"):
        RenderConfig(hermite_order=17)
    with pytest.raises(ConfigError, match=r"render\.hermite_order: expected"):  # the section prefix is added
        from_dict(RenderConfig, {"hermite_order": 17}, prefix="render.")
    RenderConfig(renderer="dense", hermite_order=17)  # only the sampled renderer uses the op settings


def test_splatter_settings_and_keywords_are_one_thing():
    s = SplatSettings(samples=5, eps=0.02, estimator="ht-pips", lowpass=0.5, deterministic=False)
    a = Splatter(settings=s, base_seed=3)
    b = Splatter(5, 0.02, "ht-pips", "alpha", 0.01, 1e10, 0.5, 3, deterministic=False)  # positional still works
    assert a.settings == b.settings == s and a.samples == 5 and b.deterministic is False
    with pytest.raises(AttributeError):
        a.samples = 6  # read-only view of the settings
    with pytest.raises(TypeError, match="settings"):
        Splatter(settings={"samples": 5})
    with pytest.raises(ValueError, match="samples"):
        SplatSettings(samples=0)
    sc = make_scene(12, 0, C=3, dtype=torch.float32, spread=0.3)
    V, K = make_cameras(1, 8, 6, focal=8.0, dtype=torch.float32)
    args = (*(sc[n] for n in PARAMS), V, K, 8, 6)
    oa, ob = a(*args), b(*args)
    assert torch.equal(oa.image, ob.image) and torch.equal(oa.indices, ob.indices)
    cfg = RenderConfig(samples=5, eps=0.02, estimator="ht-pips", lowpass=0.5, deterministic=False)
    oc = render(*args, cfg, seed=3)  # the gateway renders with the same settings
    assert torch.equal(oc.image, oa.image)


def test_neural_eval_render_overrides_the_training_render_section():
    """``eval.render`` (task neural) overrides the top-level render settings for evaluation only."""
    from nsplat.tasks.neural.config import Config

    cfg = from_dict(Config, {"render": {"samples": 8, "estimator": "paper"}, "eval": {"render": {"samples": 32}}})
    assert cfg.render.samples == 8
    assert cfg.eval_render().samples == 32 and cfg.eval_render().estimator == "paper"
    assert from_dict(Config, {"render": {"samples": 8}}).eval_render() == RenderConfig(samples=8)
    with pytest.raises(ConfigError, match=r"eval\.render\.sample"):
        from_dict(Config, {"eval": {"render": {"sample": 3}}})
    with pytest.raises(ConfigError, match=r"eval\.render\.samples: expected a value >= 1"):
        from_dict(Config, {"eval": {"render": {"samples": 0}}})


def test_render_split_renders_with_the_eval_settings_and_restores_training_ones():
    from nsplat.data.views import PosedViews
    from nsplat.tasks.neural.evaluation import render_split

    class Probe(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.render_cfg, self.seen = RenderConfig(samples=8), []

        def forward(self, viewmats, Ks, width, height, seed, draws=1):
            self.seen.append(self.render_cfg.samples)
            B = viewmats.shape[0]
            return torch.zeros(B, 3, height, width), torch.zeros(B, 1, height, width)

    V, K = make_cameras(2, 4, 3, focal=4.0, dtype=torch.float32)
    views = PosedViews(torch.zeros(2, 3, 4, 3), V, K, ["a", "b"])
    model = Probe()
    render_split(model, views, seed=0, render_cfg=RenderConfig(samples=32))
    render_split(model, views, seed=0)
    assert model.seen == [32, 8] and model.render_cfg.samples == 8
