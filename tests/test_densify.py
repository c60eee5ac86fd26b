"""Adaptive density control: the point set changes, the optimiser state follows it row by row, the
screen-space gradient statistic is in pixels, and a resumed fit across densification events equals an
uninterrupted one."""
from __future__ import annotations

import math

import pytest
import torch

from nsplat.fitting import FitConfig, fit
from nsplat.fitting.densify import DensifyConfig, DensityStats, densify
from nsplat.render.renderer import RenderConfig, render_views
from nsplat.run.engine import LogConfig
from nsplat.scene import SceneConfig, SurfelScene
from nsplat.tasks.reconstruct import fibonacci_sphere
from tests.test_reconstruct import OFF, _lr, _tiny_problem, _views


def _scene(n: int = 6) -> SurfelScene:
    g = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=g)
    normals = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    scales = torch.tensor([0.01, 0.05, 0.01, 0.05, 0.01, 0.05])[:n, None].expand(n, 2).contiguous()
    cfg = SceneConfig(learn=["means", "normals", "scales", "opacities", "features"], opacity=None)
    return SurfelScene.from_points(cfg, means, normals, scales=scales, opacities=torch.linspace(0.01, 0.9, n),
                                   features=torch.rand(n, 3, generator=g))


def _stepped_adam(scene: SurfelScene) -> torch.optim.Adam:
    opt = torch.optim.Adam(scene.param_groups({"default": 0.01}))
    loss = sum((p * torch.arange(1, p.numel() + 1).reshape(p.shape)).sum() for p in scene.parameters())
    loss.backward()
    opt.step()
    return opt


def test_densify_splits_clones_prunes_and_gathers_optimizer_state():
    scene = _scene()
    opt = _stepped_adam(scene)
    old = {n: scene.tensor(n).detach().clone() for n in scene.cfg.learn}
    old_state = {n: {k: v.clone() for k, v in opt.state[scene.tensor(n)].items()} for n in scene.cfg.learn}
    stats = DensityStats(6)
    stats.grad.copy_(torch.tensor([0.0, 5.0, 3.0, 0.0, 4.0, 2.0]))
    stats.views.fill_(1.0)
    cfg = DensifyConfig(enabled=True, grad_threshold=1.0, split_size=0.03, children=2, max_growth=1.0,
                        prune_opacity=0.05)
    counts = densify(scene, stats, cfg, torch.Generator().manual_seed(0), [opt])
    # Point 0: opacity 0.01 < 0.05, pruned. Grow 1 (big: split), 2 (small: clone), 4 (small), 5 (big).
    assert counts == {"split": 2.0, "cloned": 2.0, "pruned": 1.0, "points": 5 - 2 + 2 + 4}
    stay, clones, children = [2, 3, 4], [2, 4], [1, 1, 5, 5]
    index = torch.tensor(stay + clones + children)
    assert scene.num_points == 9 and stats.grad.shape == (9,) and float(stats.grad.abs().sum()) == 0
    for name in scene.cfg.learn:
        p = scene.tensor(name)
        assert any(p is q for g in opt.param_groups for q in g["params"]), name
        st = opt.state[p]
        for key in ("exp_avg", "exp_avg_sq"):
            assert st[key].shape == p.shape
            assert torch.equal(st[key][:3], old_state[name][key][index[:3]]), (name, key)
            assert float(st[key][3:].abs().sum()) == 0, (name, key)
        assert torch.equal(st["step"], old_state[name]["step"])
    assert torch.equal(scene.tensor("means")[:3], old["means"][index[:3]])
    # Split children are smaller by `shrink`; clones keep their size and stay within a few std-devs.
    log_s = scene.tensor("scales").detach()
    assert torch.allclose(log_s[5:], old["scales"][index[5:]] - math.log(1.6))
    assert torch.equal(log_s[3:5], old["scales"][index[3:5]])
    offset = (scene.means[3:] - old["means"][index[3:]]).detach().norm(dim=-1)
    assert float(offset.min()) > 0 and float(offset.max()) < 6 * 0.05, offset.detach()
    # The optimiser steps over the new parameters.
    loss = sum(p.square().sum() for p in scene.parameters())
    loss.backward()
    opt.step()


def test_densify_respects_growth_caps_highest_gradients_first():
    scene = _scene()
    stats = DensityStats(6)
    stats.grad.copy_(torch.tensor([1.0, 6.0, 5.0, 4.0, 3.0, 2.0]) * 10)
    stats.views.fill_(10.0)  # averages 1 … 6
    cfg = DensifyConfig(enabled=True, grad_threshold=0.5, split_size=1.0, max_growth=0.5, prune_opacity=0.0)
    counts = densify(scene, stats, cfg, torch.Generator().manual_seed(0))
    assert counts["cloned"] == 3 and counts["points"] == 9  # 3 = 50 % of 6: points 1, 2, 3
    cfg.max_points = 7
    scene, stats = _scene(), DensityStats(6)
    stats.grad.copy_(torch.tensor([1.0, 6.0, 5.0, 4.0, 3.0, 2.0]))
    stats.views.fill_(1.0)
    assert densify(scene, stats, cfg, torch.Generator().manual_seed(0))["points"] == 7


def test_screen_space_gradient_is_in_pixels():
    """Each view's own screen-space gradient ``[b,N,2]`` (loss per pixel of motion) counts by its length times the
    loss's pixel count; a point counts as seen by the views that moved it."""
    stats = DensityStats(2)
    grad = torch.tensor([[[3.0, 4.0], [0.0, 0.0]], [[0.0, 1.0], [0.0, 0.0]]])  # two views, two points
    stats.observe(grad, pixels=2)
    assert torch.equal(stats.grad, torch.tensor([12.0, 0.0])) and torch.equal(stats.views, torch.tensor([2.0, 0]))
    assert torch.equal(stats.average(), torch.tensor([6.0, 0.0]))


def test_one_call_keeps_each_views_screen_gradient_apart():
    """Views rendered in one op call (one seed per view) give each view the screen-space gradient of rendering it
    alone: what lets a growing fit render a step's views in one call."""
    scene, views, _ = _stage1_like(n=60, views=3, res=12)
    rcfg = RenderConfig(renderer="splat", samples=8)
    seeds = torch.tensor([5, 9, 2])

    def grads(v: list[int], seed) -> torch.Tensor:
        image, (m2d,) = render_views(scene, views.viewmats[v], views.Ks[v], 12, 12, rcfg, seed=seed, shading="sh",
                                     with_means2d=True)
        m2d.retain_grad()
        (image - views.images[v]).abs().mean(dim=(1, 2, 3)).sum().backward()
        return m2d.grad

    together = grads([0, 1, 2], seeds)
    assert bool((together != 0).any(-1).any(-1).all()), "every view is meant to move some points"
    for b in range(3):
        assert torch.allclose(together[b:b + 1], grads([b], int(seeds[b])), rtol=1e-5, atol=1e-9)


def test_densify_config_errors_name_the_field():
    with pytest.raises(ValueError, match="shrink"):
        DensifyConfig(shrink=0.0)
    with pytest.raises(ValueError, match="children"):
        DensifyConfig(children=0)
    cfg = DensifyConfig(enabled=True, start=2, every=2, stop=6)
    assert [e for e in range(1, 10) if cfg.due(e)] == [2, 4, 6]


class _Interrupt(Exception):
    pass


def test_fit_with_densification_resumes_exactly(tmp_path):
    dens = DensifyConfig(enabled=True, start=1, every=1, grad_threshold=0.0, split_size=0.05, max_growth=0.25,
                         prune_weight=0.01)
    cfg = FitConfig(epochs=3, batch=4, learn=_lr(0.03), reposition=OFF, densify=dens)
    rcfg = RenderConfig(renderer="splat")
    lg = LogConfig(checkpoint=2, validate=1, progress=False)  # 2 steps per epoch: a checkpoint per epoch
    _, images, vm, Ks, straight = _tiny_problem(n=120, views=6, res=16)
    views = _views(images, vm, Ks)
    fit(straight, views, cfg, rcfg, tmp_path / "a", log=lg, seed=3)
    assert straight.num_points > 120 * 1.5  # three events of up to +25 % each

    def stop_at(step: int, writer) -> dict[str, float]:
        if step == 6:  # killed after the last epoch's event, before its checkpoint
            raise _Interrupt
        return {}

    _, _, _, _, killed = _tiny_problem(n=120, views=6, res=16)
    with pytest.raises(_Interrupt):
        fit(killed, views, cfg, rcfg, tmp_path / "b", log=lg, seed=3, validate=stop_at)
    torch.manual_seed(999)  # a new process: global RNG state differs
    _, _, _, _, resumed = _tiny_problem(n=120, views=6, res=16)
    fit(resumed, views, cfg, rcfg, tmp_path / "b", log=lg, seed=3, resume=True)
    assert resumed.num_points == straight.num_points
    for name, t in straight.state_dict().items():
        assert torch.equal(t, resumed.state_dict()[name]), name


@pytest.mark.parametrize("shading", ["none", "lambert"])
def test_fit_renders_a_batch_in_one_call_with_the_per_view_gradients(tmp_path, monkeypatch, shading):
    """Without a per-view strategy a step's views go through one op call (one seed per view; shaded views with
    per-camera features): the gradients Adam steps with are those of one call per view, as a per-view strategy
    (here a stand-in for density control) makes the fitter render them, to summation order."""
    import nsplat.fitting.fitter as fitter
    from nsplat.fitting import Strategy

    cfg = FitConfig(epochs=1, batch=3, learn=_lr(0.03), reposition=OFF, shading=shading)
    rcfg = RenderConfig(renderer="splat")
    _, images, vm, Ks, _ = _tiny_problem(n=120, views=6, res=16)
    views = _views(images, vm, Ks)
    real_render, real_adam = fitter.render_views, fitter.adam_step

    def run(per_view: bool) -> tuple[list[int], list[torch.Tensor]]:
        cameras, grads = [], []
        monkeypatch.setattr(fitter, "render_views", lambda scene, viewmats, *a, **k: cameras.append(
            viewmats.shape[0]) or real_render(scene, viewmats, *a, **k))
        monkeypatch.setattr(fitter, "adam_step", lambda scene, opt, c: grads.append(
            [p.grad.clone() for p in scene.parameters()]) or real_adam(scene, opt, c))
        if per_view:
            monkeypatch.setattr(FitConfig, "strategies", lambda self: [type("PerView", (Strategy,),
                                                                            {"per_view": True})()])
        _, _, _, _, scene = _tiny_problem(n=120, views=6, res=16)
        fit(scene, views, cfg, rcfg, tmp_path / f"run-{per_view}", log=LogConfig(progress=False), seed=3)
        monkeypatch.undo()
        return cameras, grads

    cams_together, together = run(False)
    cams_apart, apart = run(True)
    assert cams_together == [3, 3] and cams_apart == [1] * 6
    for a, b in zip(together[0], apart[0]):  # the first step: the same parameters (later ones differ by rounding)
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6 * float(b.abs().max()))


def test_densify_prunes_points_below_the_contribution_threshold_with_their_optimizer_rows():
    """``prune_weight = w``: the points whose summed compositing weight is below ``w`` go (with their Adam rows,
    SH coefficients included); an event without the contributions it needs is an error naming the option."""
    n = 6
    g = torch.Generator().manual_seed(0)
    cfg_scene = SceneConfig(channels=12, learn=["means", "normals", "scales", "opacities", "features"], opacity=None,
                            feature_activation="identity")
    scene = SurfelScene.from_points(cfg_scene, torch.randn(n, 3, generator=g),
                                    torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1),
                                    scales=torch.full((n, 2), 0.01), opacities=torch.full((n,), 0.5),
                                    features=torch.rand(n, 12, generator=g))
    opt = _stepped_adam(scene)
    feats = scene.tensor("features").detach().clone()
    moments = opt.state[scene.tensor("features")]["exp_avg"].clone()
    stats = DensityStats(n)
    cfg = DensifyConfig(enabled=True, grad_threshold=1.0, prune_opacity=0.0, prune_weight=0.5)
    contrib = torch.tensor([3.0, 0.0, 0.49, 0.5, 7.0, 0.1])
    with pytest.raises(ValueError, match="prune_weight"):
        densify(scene, stats, cfg, torch.Generator().manual_seed(0), [opt])
    counts = densify(scene, stats, cfg, torch.Generator().manual_seed(0), [opt], contrib)
    keep = torch.tensor([0, 3, 4])
    assert counts == {"split": 0.0, "cloned": 0.0, "pruned": 3.0, "points": 3.0}
    assert torch.equal(scene.tensor("features").detach(), feats[keep])
    st = opt.state[scene.tensor("features")]
    assert st["exp_avg"].shape == (3, 12) and torch.equal(st["exp_avg"], moments[keep])
    with pytest.raises(ValueError, match="prune_weight"):
        DensifyConfig(prune_weight=-1.0)


def _unseen_point(vm: torch.Tensor, Ks: torch.Tensor, res: int) -> torch.Tensor:
    """``[3]``: a point 4 units from the origin that no camera ``vm [V,4,4]``, ``Ks [V,3,3]`` has in front of it
    and inside its ``res``² image (with a margin of a quarter image)."""
    dirs, _ = fibonacci_sphere(200, torch.zeros(3), 1.0)
    for p in 4.0 * dirs:
        cam = vm[:, :3, :3] @ p + vm[:, :3, 3]
        px = (Ks @ cam[..., None])[..., 0]
        uv = px[:, :2] / px[:, 2:].clamp_min(1e-6)
        seen = (cam[:, 2] > 0) & (uv > -res / 4).all(-1) & (uv < 1.25 * res).all(-1)
        if not bool(seen.any()):
            return p
    raise AssertionError("every candidate point is seen")


def _stage1_like(n: int = 120, views: int = 6, res: int = 16):
    """The tiny problem as stage 1 sees it: view-dependent colour (SH degree 1, 12 channels), learned opacities
    and std-devs, plus two surfels that no training view sees (the last two rows)."""
    _, images, vm, Ks, _ = _tiny_problem(n=n, views=views, res=res)
    s0, n0 = fibonacci_sphere(n, torch.zeros(3), 1.05)
    far = _unseen_point(vm, Ks, res)
    means = torch.cat([s0, far[None], 1.1 * far[None]])
    normals = torch.cat([n0, torch.nn.functional.normalize(far, dim=0).expand(2, 3)])
    feats = torch.cat([torch.full((n + 2, 3), 0.5), torch.zeros(n + 2, 9)], 1)
    cfg = SceneConfig(channels=12, learn=["means", "normals", "scales", "opacities", "features"], opacity=None,
                      feature_activation="identity")
    scene = SurfelScene.from_points(cfg, means, normals, scales=torch.full((n + 2, 2), 0.04),
                                    opacities=torch.full((n + 2,), 0.9), features=feats)
    return scene, _views(images, vm, Ks), far


def test_fit_grows_during_an_annealed_sh_schedule_within_the_budget_and_drops_unseen_points(tmp_path):
    """Density control during a stage-1-like fit (SH colour at a smaller rate for the higher bands, a scale cap,
    an annealing tail, one view per step): the two surfels no training view sees are pruned at the first event,
    the count grows but never past ``max_points``, every new row stays finite, and two runs are identical."""
    dens = DensifyConfig(enabled=True, start=1, every=1, stop=2, grad_threshold=0.0, split_size=0.05,
                         max_growth=0.5, max_points=150, prune_opacity=0.0, prune_weight=0.01)
    cfg = FitConfig(epochs=3, batch=1, learn={**_lr(0.01), "opacities": 0.05}, reposition=OFF, densify=dens,
                    shading="sh", sh_rest_lr=0.05, max_scale=0.2, anneal_epochs=1, anneal_factor=0.25)
    rcfg = RenderConfig(renderer="splat")
    runs = []
    for name in ("a", "b"):
        scene, views, far = _stage1_like()
        out = fit(scene, views, cfg, rcfg, tmp_path / name, log=LogConfig(every=1, checkpoint=0, progress=False),
                  seed=5, background=torch.ones(3))
        runs.append(scene)
    scene = runs[0]
    assert 122 < scene.num_points <= 150, scene.num_points
    # both unseen surfels are gone (no copies either)
    assert float((scene.means.detach() - far).norm(dim=-1).min()) > 1.0
    assert scene.features.shape == (scene.num_points, 12)
    assert all(bool(torch.isfinite(t).all()) for t in scene.state_dict().values())
    assert float(scene.scales.detach().max()) <= 0.2 * (1 + 1e-6)
    assert math.isfinite(out["train/loss"])
    for name, t in runs[0].state_dict().items():
        assert torch.equal(t, runs[1].state_dict()[name]), name
