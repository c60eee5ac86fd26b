"""Shape reconstruction: shading, the truncated baseline, repositioning, resume, and a tiny
reconstruction with the sampled op that must reduce the Chamfer distance by a clear factor."""
from __future__ import annotations

import math

import pytest
import torch

from nsplat.cameras import intrinsics_from_fov, look_at
from nsplat.config import ConfigError, load_config
from nsplat.data.views import PosedViews
from nsplat.evaluation.shape_metrics import point_cloud_distances
from nsplat.fitting import FitConfig, MaskLossConfig, RepositionConfig, build, fit
from nsplat.fitting.reposition import point_contributions, reposition
from nsplat.ops import splat_dense
from nsplat.render.renderer import RenderConfig, render_views
from nsplat.render.shading import lambert
from nsplat.render.truncated import splat_truncated
from nsplat.run.engine import LogConfig
from nsplat.scene import SceneConfig, SurfelScene, knn_spacing
from nsplat.tasks import get_task
from nsplat.tasks.reconstruct import Config, fibonacci_sphere


def _cameras(count: int, res: int, dist: float = 3.0, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(count, 3, generator=g), dim=-1)
    vm = look_at(dist * d, torch.zeros(count, 3), torch.tensor([0.0, 0.0, 1.0]))
    return vm, intrinsics_from_fov(math.radians(45), res, res, count)


def _ellipsoid(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    axes = torch.tensor([0.9, 0.55, 0.35])
    p, nrm = fibonacci_sphere(n, torch.zeros(3), 1.0)
    return p * axes, torch.nn.functional.normalize(nrm / axes, dim=-1)


# ------------------------------------------------------------------------------------------ shading
def test_lambert_paper_lights_hand_values():
    albedo = torch.tensor([[1.0, 1.0, 1.0], [0.5, 1.0, 0.2], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]])
    s = 1.0 / math.sqrt(2.0)
    # Camera-space normals (identity camera): towards the camera, up (-y), up-and-towards, away.
    normals = torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [0.0, -s, -s], [0.0, 0.0, 1.0]])
    out = lambert(albedo, normals, torch.eye(4)[None])
    expected = torch.tensor([[0.9, 0.0, 0.0], [0.0, 0.0, 0.2 * 0.9], [0.9 * s, 0.9 * s, 0.0], [0.0, 0.0, 0.0]])
    assert torch.allclose(out[0], expected, atol=1e-6)


def test_lambert_lights_follow_the_camera():
    # Rotating the camera and the normal together leaves the shading unchanged.
    vm = look_at(torch.tensor([[2.0, 1.0, 0.5]]), torch.zeros(1, 3), torch.tensor([0.0, 0.0, 1.0]))
    n_cam = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, -0.8]]), dim=-1)
    n_world = n_cam @ vm[0, :3, :3]  # R^T n_cam
    a = lambert(torch.ones(1, 3), n_world, vm)
    b = lambert(torch.ones(1, 3), n_cam, torch.eye(4)[None])
    assert torch.allclose(a, b, atol=1e-6)


# ------------------------------------------------------------------------------------ truncated
def _small_scene(n: int = 60, seed: int = 0) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.4
    normals = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    normals = torch.where(normals[:, 2:] > 0, -normals, normals)
    scales = torch.rand(n, 2, generator=g, dtype=torch.float64) * 0.08 + 0.03
    opac = torch.rand(n, generator=g, dtype=torch.float64) * 0.8 + 0.1
    feats = torch.rand(n, 3, generator=g, dtype=torch.float64)
    vm = torch.eye(4, dtype=torch.float64)[None].repeat(2, 1, 1)
    vm[:, 2, 3] = 3.0
    vm[1, 0, 3] = 0.3
    Ks = intrinsics_from_fov(math.radians(40), 20, 16, 2, dtype=torch.float64)
    return means, normals, scales, opac, feats, vm, Ks


def test_truncated_equals_dense_without_truncation():
    args = _small_scene()
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    d = splat_dense(*args, 20, 16, background=bg)
    t = splat_truncated(*args, 20, 16, cutoff=50.0, background=bg)
    assert torch.allclose(t.image, d.image, atol=1e-10)
    assert torch.allclose(t.alpha, d.alpha, atol=1e-10)
    assert torch.allclose(t.depth, d.depth, atol=1e-10)


def test_truncated_gradients_equal_dense_without_truncation():
    means, normals, scales, opac, feats, vm, Ks = _small_scene()
    w = torch.rand(2, 16, 20, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    grads = []
    for render in (lambda *a: splat_dense(*a), lambda *a: splat_truncated(*a, cutoff=50.0)):
        leaves = [t.clone().requires_grad_(True) for t in (means, normals, scales, opac, feats)]
        out = render(*leaves, vm, Ks, 20, 16)
        ((out.image * w).sum() + out.depth.sum()).backward()
        grads.append([t.grad for t in leaves])
    for name, gd, gt in zip(("means", "normals", "scales", "opacities", "features"), *grads):
        assert torch.allclose(gt, gd, rtol=1e-9, atol=1e-12), name


def test_truncated_cuts_kernels_and_gradients_are_local():
    means, normals, scales, opac, feats, vm, Ks = _small_scene()
    # Point 0: a small splat far outside the image; point 1: large, in view.
    means = means.clone()
    means[0] = torch.tensor([3.0, 0.0, 0.0], dtype=torch.float64)
    means.requires_grad_(True)
    args = (means, normals, scales, opac, feats, vm[:1], Ks[:1], 20, 16)
    t3 = splat_truncated(*args, cutoff=3.0)
    t3.image.sum().backward()
    g_trunc = means.grad.clone()
    means.grad = None
    splat_dense(*args).image.sum().backward()
    assert g_trunc[0].abs().sum() == 0            # no pixel within 3σ: no gradient
    assert means.grad[0].abs().sum() > 0          # the dense renderer still has a (tiny) one
    assert g_trunc[1:].abs().sum() > 0
    # And the cut changes the image: truncated ≠ dense at 3σ but close.
    d = splat_dense(*(a.detach() if isinstance(a, torch.Tensor) else a for a in args))
    diff = (t3.image.detach() - d.image).abs().max()
    assert 0 < diff < 0.1


# ------------------------------------------------------------------------------ repositioning
def test_non_contributing_points_are_moved_next_to_visible_ones():
    means, normals = _ellipsoid(600)
    # Two extra points: one hidden inside the closed surface, one far outside every view.
    means = torch.cat([means, torch.tensor([[0.0, 0.0, 0.0], [50.0, 50.0, 50.0]])])
    normals = torch.cat([normals, torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])])
    spacing = torch.as_tensor(knn_spacing(means[:600]), dtype=torch.float32)
    scales = torch.cat([1.5 * spacing, torch.tensor([0.05, 0.05])])[:, None].expand(602, 2)
    scene = SurfelScene.from_points(SceneConfig(), means, normals, scales=scales)
    opt = torch.optim.Adam(scene.param_groups({"default": 0.01}))
    scene.means.sum().backward()
    opt.step()
    vm, Ks = _cameras(6, 24)
    contrib = point_contributions(scene, vm, Ks, 24, 24, RenderConfig(renderer="dense"))
    assert contrib[600] < 0.02 and contrib[601] < 0.02
    assert (contrib[:600] > 0.02).float().mean() > 0.4
    g = torch.Generator().manual_seed(0)
    moved = reposition(scene, contrib, 0.02, 1.0, g, opt)
    assert moved >= 2
    dist_to_surface = torch.cdist(scene.means[600:].detach(), means[:600]).min(dim=1).values
    assert bool((dist_to_surface < 0.3).all())
    assert bool((opt.state[scene.tensor("means")]["exp_avg"][600:] == 0).all())


def test_black_points_have_no_visual_contribution():
    # Two surfels facing an identity camera; the second is black (albedo 0).
    means = torch.tensor([[-0.5, 0.0, 3.0], [0.5, 0.0, 3.0]])
    normals = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    scene = SurfelScene.from_points(SceneConfig(), means, normals, scales=0.05,
                                    features=torch.tensor([[0.5, 0.5, 0.5], [0.0, 0.0, 0.0]]))
    vm, Ks = torch.eye(4)[None], intrinsics_from_fov(math.radians(40), 16, 16, 1)
    cfg = RenderConfig(renderer="dense")
    weight = point_contributions(scene, vm, Ks, 16, 16, cfg, measure="weight")
    radiance = point_contributions(scene, vm, Ks, 16, 16, cfg, measure="radiance")
    assert weight[0] > 0.5 and torch.allclose(weight[0], weight[1], rtol=1e-4)
    # Headlight only (normal faces the camera): colour norm of point 0 is 0.9 * 0.5.
    assert torch.allclose(radiance[0], 0.45 * weight[0], rtol=1e-4)
    assert radiance[1] == 0


def test_exact_contributions_are_the_dense_ones_and_hidden_points_count_as_hidden():
    """``exact=True`` gives the dense renderer's contributions (radiance, per-camera Lambert), and the point hidden
    inside the closed surface contributes nothing, where the sampled op's estimate lets it show through its sample."""
    means, normals = _ellipsoid(600)
    means = torch.cat([means, torch.zeros(1, 3)])
    normals = torch.cat([normals, torch.tensor([[0.0, 0.0, 1.0]])])
    spacing = torch.as_tensor(knn_spacing(means[:600]), dtype=torch.float32)
    scales = torch.cat([1.5 * spacing, torch.tensor([0.05])])[:, None].expand(601, 2)
    scene = SurfelScene.from_points(SceneConfig(), means, normals, scales=scales)
    vm, Ks = _cameras(4, 24)
    exact = point_contributions(scene, vm, Ks, 24, 24, RenderConfig(), exact=True)
    dense = point_contributions(scene, vm, Ks, 24, 24, RenderConfig(renderer="dense"))
    assert torch.allclose(exact, dense, rtol=1e-3, atol=1e-5)
    sampled = point_contributions(scene, vm, Ks, 24, 24, RenderConfig(samples=4))
    assert exact[600] < 0.02 < 1.0 < sampled[600]       # measured 0.0018 against 1.8


# ------------------------------------------------------------------------------------- fitting
def _tiny_problem(n: int = 300, views: int = 8, res: int = 24):
    gt_pts, gt_n = _ellipsoid(n)
    gt = SurfelScene.from_points(SceneConfig(), gt_pts, gt_n, features=1.0)
    vm, Ks = _cameras(views, res)
    with torch.no_grad():
        images = render_views(gt, vm, Ks, res, res, RenderConfig(renderer="dense"))
    s0, n0 = fibonacci_sphere(n, torch.zeros(3), 1.05)
    return gt_pts, images, vm, Ks, SurfelScene.from_points(SceneConfig(), s0, n0, features=0.5)


#: Repositioning off (the default is the paper's check after every epoch).
OFF = RepositionConfig(enabled=False)


def _lr(value: float) -> dict[str, float]:
    return {a: value for a in ("means", "normals", "scales", "features")}


def _views(images: torch.Tensor, vm: torch.Tensor, Ks: torch.Tensor) -> PosedViews:
    return PosedViews(images, vm, Ks, [str(i) for i in range(images.shape[0])])


def test_tiny_reconstruction_with_sampled_op_reduces_chamfer(tmp_path):
    gt_pts, images, vm, Ks, scene = _tiny_problem()
    before = point_cloud_distances(scene.means, gt_pts)
    cfg = FitConfig(epochs=30, batch=4, learn=_lr(0.03))
    fit(scene, _views(images, vm, Ks), cfg, RenderConfig(renderer="splat", samples=40, eps=0.01), tmp_path,
        log=LogConfig(checkpoint=100, progress=False))
    after = point_cloud_distances(scene.means, gt_pts)
    assert after["chamfer"] < before["chamfer"] / 2.0, (before, after)
    assert after["chamfer_sq"] < before["chamfer_sq"] / 4.0, (before, after)
    assert (tmp_path / "tb").is_dir() and (tmp_path / "checkpoints" / "latest").is_file()


def test_repositioning_checks_every_epoch_but_the_last(tmp_path, monkeypatch):
    # A point moved after the last epoch would keep its copied attributes without a step to refit them.
    import nsplat.fitting.reposition as rp
    calls: list[int] = []
    monkeypatch.setattr(rp, "point_contributions",
                        lambda scene, *a, **k: calls.append(scene.num_points) or torch.ones(scene.num_points))
    _, images, vm, Ks, scene = _tiny_problem(n=60, views=4, res=12)
    cfg = FitConfig(epochs=5, batch=2, learn=_lr(0.01), reposition=RepositionConfig(every=2))
    fit(scene, _views(images, vm, Ks), cfg, RenderConfig(renderer="dense"), tmp_path,
        log=LogConfig(checkpoint=100, progress=False))
    assert len(calls) == 2  # after epochs 2 and 4
    calls.clear()
    cfg = FitConfig(epochs=4, batch=2, learn=_lr(0.01), reposition=RepositionConfig(every=2))
    fit(scene, _views(images, vm, Ks), cfg, RenderConfig(renderer="dense"), tmp_path / "b",
        log=LogConfig(checkpoint=100, progress=False))
    assert len(calls) == 1  # after epoch 2; not after the last (4)


def test_relative_threshold_moves_points_far_below_the_median(tmp_path, monkeypatch):
    """``reposition.relative``: a point contributes when it reaches ``relative`` × the median contribution (and
    ``min_weight``); points hidden just behind the surface, above ``min_weight`` but far below the median, move."""
    import nsplat.fitting.reposition as rp
    _, images, vm, Ks, scene = _tiny_problem(n=60, views=4, res=12)
    contrib = torch.full((60,), 10.0)
    contrib[:7] = 1.0            # hidden-ish: above min_weight, a tenth of the median
    contrib[7:9] = 0.01          # below min_weight
    monkeypatch.setattr(rp, "point_contributions", lambda scene, *a, **k: contrib.clone())
    moved: list[int] = []
    real = rp.reposition
    monkeypatch.setattr(rp, "reposition", lambda *a, **k: moved.append(real(*a, **k)) or moved[-1])
    for relative, expect in ((0.0, 2), (0.2, 9)):
        moved.clear()
        cfg = FitConfig(epochs=2, batch=2, learn=_lr(0.01), reposition=RepositionConfig(every=1, relative=relative))
        fit(scene, _views(images, vm, Ks), cfg, RenderConfig(renderer="dense"), tmp_path / str(relative),
            log=LogConfig(checkpoint=100, progress=False))
        assert moved == [expect], (relative, moved)
    with pytest.raises(ConfigError, match="relative"):
        RepositionConfig(relative=1.0)


class _Interrupt(Exception):
    pass


def test_fit_resumes_exactly(tmp_path):
    cfg = FitConfig(epochs=3, batch=4, learn=_lr(0.03), reposition=RepositionConfig(every=1, min_weight=0.5))
    rcfg = RenderConfig(renderer="splat")
    lg = LogConfig(checkpoint=2, validate=1, progress=False)  # 2 steps per epoch: a checkpoint per epoch
    _, images, vm, Ks, straight = _tiny_problem(n=120, views=6, res=16)
    views = _views(images, vm, Ks)
    fit(straight, views, cfg, rcfg, tmp_path / "a", log=lg, seed=3)

    def stop_at_last(step: int, writer) -> dict[str, float]:
        if step == 6:  # killed at the end of the last epoch, before its checkpoint
            raise _Interrupt
        return {}

    _, _, _, _, killed = _tiny_problem(n=120, views=6, res=16)
    with pytest.raises(_Interrupt):
        fit(killed, views, cfg, rcfg, tmp_path / "b", log=lg, seed=3, validate=stop_at_last)
    torch.manual_seed(999)  # a new process: global RNG state differs
    _, _, _, _, resumed = _tiny_problem(n=120, views=6, res=16)
    fit(resumed, views, cfg, rcfg, tmp_path / "b", log=lg, seed=3, resume=True)
    for name, t in straight.state_dict().items():
        assert torch.equal(t, resumed.state_dict()[name]), name
    assert not torch.equal(straight.means, _tiny_problem(n=120, views=6, res=16)[4].means)
    # A checkpoint of an earlier version (its epoch scheduler a MultiStepLR, which gives the same rates)
    # resumes to the same result.
    with pytest.raises(_Interrupt):
        fit(_tiny_problem(n=120, views=6, res=16)[4], views, cfg, rcfg, tmp_path / "c", log=lg, seed=3,
            validate=stop_at_last)
    folder = tmp_path / "c" / "checkpoints"
    path = folder / (folder / "latest").read_text().strip()
    payload = torch.load(path, weights_only=False)
    state = payload["schedulers"]["fit"]
    old = torch.optim.lr_scheduler.MultiStepLR(torch.optim.Adam([torch.zeros(1, requires_grad=True)], lr=0.03),
                                               cfg.milestones(), gamma=cfg.lr_gamma)
    payload["schedulers"]["fit"] = old.state_dict() | {"last_epoch": state["last_epoch"], "base_lrs": state["base_lrs"],
                                                      "_last_lr": state["_last_lr"]}
    torch.save(payload, path)
    _, _, _, _, legacy = _tiny_problem(n=120, views=6, res=16)
    fit(legacy, views, cfg, rcfg, tmp_path / "c", log=lg, seed=3, resume=True)
    for name, t in straight.state_dict().items():
        assert torch.equal(t, legacy.state_dict()[name]), name


# ---------------------------------------------------------------------------------------- task
def test_task_registered_and_config_errors_name_the_key():
    task = get_task("reconstruct")
    assert task.Config is Config
    base = {"task": "reconstruct"}
    cfg = load_config(Config, base, ["data.views=16", "render.renderer=truncated"])
    assert cfg.data.views == 16 and cfg.render.renderer == "truncated"
    for override, key in [("data.shape=dragon", "data.shape"), ("render.renderer=fast", "render.renderer"),
                          ("optim.colour=1", "optim.colour"), ("optim.learn={colour: 1}", "optim.learn"),
                          ("scene.channels=4", "scene.channels"),
                          ("render.estimator=biased", "render.estimator"), ("data.views=0", "data.views")]:
        with pytest.raises(ConfigError, match=key):
            load_config(Config, base, [override])


def test_fit_mask_weight_fits_coverage_and_needs_masks(tmp_path):
    """``mask_loss.weight``: the coverage term alone moves the silhouette towards the masks. The scene's colour
    equals the background, so the image loss is 0 everywhere and only the coverage term has a gradient;
    views without masks are a config error naming the option."""
    gt_pts, _, vm, Ks, _ = _tiny_problem(n=200, views=6, res=16)
    gt = SurfelScene.from_points(SceneConfig(), gt_pts * 0.6, gt_pts / gt_pts.norm(dim=1, keepdim=True),
                                 features=1.0)
    s0, n0 = fibonacci_sphere(200, torch.zeros(3), 1.05)
    scene = SurfelScene.from_points(SceneConfig(learn=["means", "scales"]), s0, n0, features=1.0)
    rcfg = RenderConfig(renderer="dense")
    with torch.no_grad():
        _, gt_alpha = render_views(gt, vm, Ks, 16, 16, rcfg, shading="none", with_alpha=True)
    white = torch.ones(6, 16, 16, 3)
    views = PosedViews(white, vm, Ks, [str(i) for i in range(6)], masks=gt_alpha[..., 0])

    def coverage_error() -> float:
        with torch.no_grad():
            _, a = render_views(scene, vm, Ks, 16, 16, rcfg, shading="none", with_alpha=True)
        return float((a - gt_alpha).abs().mean())

    before = coverage_error()
    control = FitConfig(epochs=30, batch=3, learn={"means": 0.03, "scales": 0.03}, shading="none", reposition=OFF)
    fit(scene, views, control, RenderConfig(renderer="splat"), tmp_path / "c", background=torch.ones(3),
        log=LogConfig(checkpoint=100, progress=False))
    assert coverage_error() > 0.95 * before  # without the term the silhouette stays (the image loss is ~0)
    cfg = FitConfig(epochs=30, batch=3, learn={"means": 0.03, "scales": 0.03}, shading="none", reposition=OFF,
                    mask_loss=MaskLossConfig(weight=1.0))
    fit(scene, views, cfg, RenderConfig(renderer="splat"), tmp_path / "a", background=torch.ones(3),
        log=LogConfig(checkpoint=100, progress=False))
    assert coverage_error() < 0.5 * before, (before, coverage_error())
    with pytest.raises(ConfigError, match="mask_loss.weight"):
        fit(scene, PosedViews(white, vm, Ks, [str(i) for i in range(6)]), cfg, RenderConfig(renderer="splat"),
            tmp_path / "b", log=LogConfig(checkpoint=100, progress=False))


def test_fit_sh_rest_lr_scales_the_higher_bands_step_only(tmp_path):
    """``sh_rest_lr = r`` with ``shading: sh``: after one Adam step the mean-colour channels ``:3`` move exactly
    as with ``r = 1`` and the higher SH coefficients ``3:`` move ``r`` times as far (the same gradients: the
    dense renderer is deterministic); a value outside (0, 1] is a config error naming the option."""
    _, images, vm, Ks, _ = _tiny_problem(n=120, views=4, res=24)
    s0, n0 = fibonacci_sphere(120, torch.zeros(3), 1.05)
    start = torch.rand(120, 12, generator=torch.Generator().manual_seed(0)) * 0.5
    moved = {}
    for r in (1.0, 0.05):
        scene = SurfelScene.from_points(SceneConfig(channels=12), s0.clone(), n0.clone(), features=start.clone())
        cfg = FitConfig(epochs=1, batch=4, learn=_lr(1e-2), reposition=OFF, shading="sh", sh_rest_lr=r)
        fit(scene, _views(images, vm, Ks), cfg, RenderConfig(renderer="dense"), tmp_path / f"r{r}",
            log=LogConfig(checkpoint=100, progress=False))
        moved[r] = scene.features.detach() - start
    assert moved[1.0][:, 3:].abs().max() > 1e-3  # the higher bands do move at the full rate
    torch.testing.assert_close(moved[0.05][:, :3], moved[1.0][:, :3], rtol=0, atol=1e-7)
    torch.testing.assert_close(moved[0.05][:, 3:], 0.05 * moved[1.0][:, 3:], rtol=1e-4, atol=1e-7)
    with pytest.raises(ConfigError, match="sh_rest_lr"):
        FitConfig(sh_rest_lr=0.0)


def test_fit_max_scale_caps_every_std_dev_from_the_first_render(tmp_path):
    """``max_scale = c``: std-devs that start above ``c`` are clamped before the first render (the first step's
    loss is the dense L1 of the clamped scene) and none exceeds ``c`` after any step, while the same run without
    the cap leaves them above it; a scene with a constant std-dev is a config error naming the option."""
    _, images, vm, Ks, scene = _tiny_problem(n=120, views=4, res=24)
    cap = 0.12
    start = torch.full((120, 2), 0.08)
    start[::7] = 0.4  # a few surfels far above the cap
    rcfg = RenderConfig(renderer="dense")

    def run(max_scale: float, epochs: int) -> tuple[SurfelScene, dict[str, float]]:
        trial = SurfelScene.from_points(scene.cfg, scene.means.detach().clone(), scene.normals.detach().clone(),
                                        scales=start.clone(), features=0.5)
        cfg = FitConfig(epochs=epochs, batch=4, learn=_lr(0.05), lr_decays=0, reposition=OFF, max_scale=max_scale)
        out = fit(trial, _views(images, vm, Ks), cfg, rcfg, tmp_path / f"c{max_scale}-e{epochs}",
                  log=LogConfig(checkpoint=100, progress=False))
        return trial, out

    clamped = SurfelScene.from_points(scene.cfg, scene.means.detach().clone(), scene.normals.detach().clone(),
                                      scales=start.clamp(max=cap), features=0.5)
    with torch.no_grad():
        expected = float((render_views(clamped, vm, Ks, 24, 24, rcfg) - images).abs().mean())
    _, out = run(cap, 1)
    assert out["train/loss"] == pytest.approx(expected, rel=1e-5), (out["train/loss"], expected)
    capped, _ = run(cap, 6)
    assert float(capped.scales.detach().max()) <= cap * (1 + 1e-6)
    free, _ = run(0.0, 6)
    assert float(free.scales.detach().max()) > 1.5 * cap
    const = SurfelScene.from_points(SceneConfig(scale=0.1, learn=["means", "features"]), scene.means.detach(),
                                    scene.normals.detach(), features=0.5)
    with pytest.raises(ConfigError, match="max_scale"):
        fit(const, _views(images, vm, Ks), FitConfig(epochs=1, batch=4, learn={"features": 0.01}, reposition=OFF,
                                                     max_scale=0.05), rcfg, tmp_path / "const",
            log=LogConfig(checkpoint=100, progress=False))


@pytest.mark.filterwarnings("ignore:Detected call of `lr_scheduler.step\\(\\)` before")  # rates only, no steps
def test_fit_anneal_tail_decays_the_rate_geometrically_over_the_last_epochs(tmp_path):
    """``anneal_epochs = A``, ``anneal_factor = f``: epochs before the tail keep the step schedule's rates
    (``lr_gamma`` per milestone); the j-th epoch of the tail runs at ``f^(j/A)`` times that, the last at ``f``
    times; without a tail the rates are those of ``MultiStepLR`` at the same milestones (the schedule of
    earlier versions); a tail longer than the run or a factor outside (0, 1] is a config error naming it."""
    scene = _tiny_problem(n=60, views=4, res=16)[4]
    cfg = FitConfig(epochs=8, batch=4, learn=_lr(0.04), lr_decays=1, anneal_epochs=3, anneal_factor=0.125,
                    reposition=OFF)
    t = build(scene, cfg)
    opt, sched = t.optimizers["fit"], t.schedulers["fit"]
    rates = []
    for _ in range(cfg.epochs):
        rates.append(opt.param_groups[0]["lr"])
        sched.step()
    expected = [0.04] * 4 + [0.02, 0.02 * 0.5, 0.02 * 0.25, 0.02 * 0.125]
    assert rates == pytest.approx(expected, rel=1e-12), rates
    plain = FitConfig(epochs=12, batch=4, learn=_lr(0.04), lr_decays=3, lr_gamma=0.3, reposition=OFF)
    t = build(scene, plain)
    ref_opt = torch.optim.Adam([torch.zeros(1, requires_grad=True)], lr=0.04)
    ref = torch.optim.lr_scheduler.MultiStepLR(ref_opt, plain.milestones(), gamma=0.3)
    for _ in range(plain.epochs):
        assert t.optimizers["fit"].param_groups[0]["lr"] == pytest.approx(ref_opt.param_groups[0]["lr"], rel=1e-12)
        t.schedulers["fit"].step()
        ref.step()
    out = fit(scene, _views(*_tiny_problem(n=60, views=4, res=16)[1:4]), cfg, RenderConfig(renderer="dense"),
              tmp_path, log=LogConfig(checkpoint=100, progress=False))
    assert out["epoch/lr"] == pytest.approx(0.02 * 0.125)  # after the last epoch: the tail's end
    with pytest.raises(ConfigError, match="anneal_epochs"):
        FitConfig(epochs=4, anneal_epochs=5)
    with pytest.raises(ConfigError, match="anneal_factor"):
        FitConfig(epochs=4, anneal_epochs=2, anneal_factor=0.0)
    FitConfig(epochs=0, anneal_epochs=12)  # no fit (stage 2 from a fitted geometry.ply): nothing to anneal
