"""Task ``neural`` end to end on a tiny procedural scene with the sampled op: training lowers the
loss, an interrupted run resumed from its checkpoint equals the uninterrupted one bit for bit,
evaluation writes valid JSON and PNGs, ``render`` writes a video, bad configs fail clearly."""
from __future__ import annotations

import json
import logging
import math
import shutil
from pathlib import Path

import imageio
import imageio.v3 as iio
import pytest
import torch
import yaml
from plyfile import PlyData

from nsplat.cli import main
from nsplat.config import ConfigError, load_config
from nsplat.evaluation.image_metrics import lpips_status, psnr
from nsplat.evaluation.protocol import read_per_view_csv
from nsplat.gaussians.ply import read_gaussian_ply
from nsplat.run.checkpoint import load_checkpoint
from nsplat.run.context import RunContext
from nsplat.tasks import get_task
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.data import load_views
from nsplat.tasks.neural.evaluation import render_split
from nsplat.tasks.neural.geometry import fit_geometry
from nsplat.tasks.neural.model import load_model, neural_scene_from
from nsplat.tasks.neural.training import build, train_step

REPO = Path(__file__).resolve().parents[1]


def _tiny(cache: Path, **neural) -> dict:
    """A config small enough for CI: 24 px, 6/2/2 views, a few hundred points, 2-level networks."""
    return {
        "task": "neural", "seed": 0,
        "data": {"procedural": {"seed": 1, "resolution": 24, "views": [6, 2, 2], "objects": 2,
                                "cache_dir": str(cache)}},
        "geometry": {"grid": 24, "optim": {"epochs": 1, "batch": 3, "reposition": {"enabled": False}}},
        "render": {"samples": 16},
        "neural": {"steps": 4, "batch": 2, "features": 4, "unet": {"depth": 2, "width": 8},
                   "gan": {"width": 8, "layers": 2}, **neural},
        "log": {"every": 1, "images": 2, "checkpoint": 2, "validate": 2, "progress": False},
        "eval": {"orbit_frames": 4, "fps": 4, "val_views": 2},
    }


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("scenes")


def test_default_config_is_the_procedural_neural_task():
    raw = yaml.safe_load((REPO / "configs" / "default.yaml").read_text())
    cfg = load_config(get_task(raw["task"]).Config, raw)
    assert cfg.task == "neural" and cfg.data.source == "procedural"
    assert cfg.neural.gan.enabled and cfg.neural.gan.lambda_l1 == 100.0 and cfg.neural.features == 16
    assert sorted(cfg.neural.learn) == ["features", "means", "opacities"]


def test_config_errors_name_the_key(cache):
    with pytest.raises(ConfigError, match="neural.unet.dropuot"):
        load_config(Config, _tiny(cache, unet={"dropuot": 0.5}))
    with pytest.raises(ConfigError, match="neural.learn"):
        load_config(Config, _tiny(cache, learn={"colour": 0.1}))
    with pytest.raises(ConfigError, match="data.root"):
        load_config(Config, {"task": "neural", "data": {"source": "nerf_synthetic"}})
    bad = _tiny(cache)
    bad["geometry"]["opacity"] = 1.0
    bad["geometry"]["learn"] = ["means"]
    with pytest.raises(ConfigError, match="neural.learn: 'opacities'"):
        load_config(Config, bad)


def test_training_lowers_the_loss(cache, tmp_path):
    cfg = load_config(Config, _tiny(cache, steps=30, lr=3e-3, gan={"enabled": False}, learn={"features": 0.05}))
    ctx = RunContext(run_dir=tmp_path, device=torch.device("cpu"), seed=0)
    torch.manual_seed(0)
    train = load_views(cfg, "train", ctx.device)
    scene = neural_scene_from(cfg, fit_geometry(cfg, ctx, train), seed=0)
    t = build(cfg, scene)
    model = t.modules["model"]
    assert "disc" not in t.modules and "d" not in t.optimizers  # GAN off: nothing allocated
    assert [g["name"] for g in t.optimizers["g"].param_groups] == ["features", "unet"]

    def l1() -> float:
        rgb, _ = render_split(model, train, seed=123)
        return float((rgb - train.images).abs().mean())

    # Residual shader with a zero head: stage 2 starts exactly from the splatted stage-1 colours.
    rgb0, cond0 = render_split(model, train, seed=123)
    assert torch.allclose(rgb0, cond0[:, :3].permute(0, 2, 3, 1).clamp(1e-3, 1 - 1e-3), atol=1e-5)

    before = l1()
    losses = []
    for k in range(cfg.neural.steps):
        losses.append(train_step(cfg.neural, t, train, k)["loss/l1"])
    after = l1()
    assert all(math.isfinite(v) for v in losses)
    assert after < 0.8 * before, (before, after)  # measured: 0.086 -> 0.058


def _args(cfg_path: Path, run: Path, *extra: str) -> list[str]:
    return ["--config", str(cfg_path), "--run", str(run), *extra]


def test_resume_equals_uninterrupted_and_eval_writes_json(cache, tmp_path, caplog):
    cfg_path = tmp_path / "tiny.yaml"
    cfg_path.write_text(yaml.safe_dump(_tiny(cache)))
    full, cut = tmp_path / "full", tmp_path / "cut"
    assert main(_args(cfg_path, full)) == 0  # 4 steps, checkpoints after steps 2 and 4
    # Simulate a run killed after its step-2 checkpoint: drop the later checkpoint and outputs.
    shutil.copytree(full, cut)
    (cut / "checkpoints" / "ckpt-00000004.pt").unlink()
    (cut / "checkpoints" / "latest").write_text("ckpt-00000002.pt")
    shutil.rmtree(cut / "eval_test")
    (cut / "finished.json").unlink()  # a killed run never finished
    assert main(["--run", str(cut), "--resume"]) == 0
    a = load_checkpoint(full)
    b = load_checkpoint(cut)
    assert a["step"] == b["step"] == 4
    for key in ("model", "disc"):
        ma, mb = a["modules"][key], b["modules"][key]
        assert ma.keys() == mb.keys()
        for name in ma:
            assert torch.equal(ma[name], mb[name]), (key, name)
    for key in ("g", "d"):
        for pid, st in a["optimizers"][key]["state"].items():
            for name, t in st.items():
                assert torch.equal(t, b["optimizers"][key]["state"][pid][name]), (key, pid, name)
    hist_a, hist_b = a["extra"]["history"], b["extra"]["history"]
    assert [r["val_psnr"] for r in hist_a] == [r["val_psnr"] for r in hist_b]

    # The training run evaluated the test split; metrics agree with a fresh `eval`.
    m = json.loads((full / "eval_test" / "metrics.json").read_text())
    per_view = json.loads((full / "eval_test" / "per_view.json").read_text())["views"]
    assert m["split"] == "test" and m["views"] == 2 == len(per_view)
    assert 0 < m["psnr"]["mean"] < 60 and m["psnr"]["std"] >= 0 and 0 < m["ssim"]["mean"] <= 1
    assert m["protocol"] == "standard"
    for net in ("vgg", "alex"):
        ok, msg = lpips_status(net)
        assert set(m["lpips"][net]) == {"mean", "std"} if ok else m["lpips"][net] == msg
    assert m["psnr"]["mean"] == pytest.approx(sum(v["psnr"] for v in per_view) / 2)
    table = read_per_view_csv(full / "eval_test" / "per_view.csv")
    assert [r["name"] for r in table] == [v["name"] for v in per_view]
    assert [r["psnr"] for r in table] == [v["psnr"] for v in per_view]
    assert iio.imread(full / "eval_test" / "sheet.png").shape[2] in (3, 4)
    for v in per_view:
        stem = Path(v["name"]).name
        render_png = iio.imread(full / "eval_test" / f"{stem}.png")
        gt_png = iio.imread(full / "eval_test" / f"{stem}_gt.png")
        assert render_png.shape == gt_png.shape == (24, 24, 3)
        # the standard protocol scores the 8-bit images the run wrote: their PSNR is the view's
        mse = float((((render_png.astype(float) - gt_png.astype(float)) / 255.0) ** 2).mean())
        assert 10 * math.log10(1 / mse) == pytest.approx(v["psnr"], abs=1e-6)
    m_cut = json.loads((cut / "eval_test" / "metrics.json").read_text())
    assert m_cut["psnr"] == m["psnr"] and m_cut["ssim"] == m["ssim"]
    assert main(["eval", "--run", str(full), "--split", "val"]) == 0
    m_val = json.loads((full / "eval_val" / "metrics.json").read_text())
    assert m_val["split"] == "val" and math.isfinite(m_val["psnr"]["mean"])
    hist = json.loads((full / "history.json").read_text())["history"]
    assert [r["step"] for r in hist] == [2, 4] and all("train_psnr" in r and "val_psnr" in r for r in hist)
    assert any((full / "tb").iterdir()) and (full / "geometry.ply").is_file()

    # the 3DGS export of a neural run holds stage 1's surfels and colour (the U-Net is not in the file)
    with caplog.at_level(logging.INFO, logger="nsplat"):
        assert main(["export", "--run", str(full), "--format", "3dgs"]) == 0
    assert "U-Net is not in the file" in caplog.text
    gs = read_gaussian_ply(full / "export" / "point_cloud.ply")
    assert gs["means"].shape[0] == PlyData.read(str(full / "geometry.ply"))["vertex"].count

    assert main(["render", "--run", str(full)]) == 0
    frames = list(imageio.get_reader(full / "orbit.mp4").iter_data())
    assert len(frames) == 4 and frames[0].shape == (24, 24, 3)


def test_late_gan_starts_at_its_fraction_with_its_own_schedule(cache, tmp_path):
    cfg = load_config(Config, _tiny(cache, steps=4, ssim_weight=0.2, gan={"width": 8, "layers": 2, "start": 0.5,
                                                                         "weight": 0.1}))
    ctx = RunContext(run_dir=tmp_path, device=torch.device("cpu"), seed=0)
    train = load_views(cfg, "train", ctx.device)
    t = build(cfg, neural_scene_from(cfg, fit_geometry(cfg, ctx, train), seed=0))
    disc = t.modules["disc"]
    d0 = [p.detach().clone() for p in disc.parameters()]
    lr_d = t.optimizers["d"].param_groups[0]["lr"]
    seen = []
    for k in range(cfg.neural.steps):
        out = train_step(cfg.neural, t, train, k)
        seen.append(("loss/disc" in out, "loss/adv" in out, "loss/dssim" in out))
        if k == 1:  # before the start (step round(0.5 · 4) = 2): the discriminator has not moved
            assert all(torch.equal(a, b) for a, b in zip(d0, disc.parameters()))
            assert t.optimizers["d"].param_groups[0]["lr"] == lr_d
    assert seen == [(False, False, True)] * 2 + [(True, True, True)] * 2
    assert not all(torch.equal(a, b) for a, b in zip(d0, disc.parameters()))
    # Over its 2 active steps the discriminator's rate decays to lr_final of its start value.
    assert math.isclose(t.optimizers["d"].param_groups[0]["lr"], lr_d * cfg.neural.lr_final, rel_tol=1e-9)
    with pytest.raises(ConfigError, match="neural.gan.start"):
        load_config(Config, _tiny(cache, gan={"start": 1.0}))


def test_eval_draws_average_independent_feature_images(cache, tmp_path):
    """``eval.draws``: an evaluation render's feature image is the mean of that many op draws (draw j with the
    seeds shifted by j·DRAW_STRIDE; draw 0 is the plain render), and the U-Net shades the mean."""
    from nsplat.tasks.neural.model import DRAW_STRIDE

    raw = _tiny(cache)
    raw["eval"]["draws"] = 3
    cfg = load_config(Config, raw)
    ctx = RunContext(run_dir=tmp_path, device=torch.device("cpu"), seed=0)
    train = load_views(cfg, "train", ctx.device)
    model = build(cfg, neural_scene_from(cfg, fit_geometry(cfg, ctx, train), 0)).modules["model"].eval()
    views = train.subset([0, 1])
    one, cond1 = render_split(model, views, seed=5)
    avg, cond3 = render_split(model, views, seed=5, draws=cfg.eval.draws)
    with torch.no_grad():
        draws = [model.feature_image(views.viewmats, views.Ks, views.width, views.height, 5 + j * DRAW_STRIDE)
                 for j in range(3)]
        expected = torch.stack(draws).mean(0)
        rgb = model.shade(expected).permute(0, 2, 3, 1).clamp(0, 1)
    assert torch.equal(cond1, draws[0])
    assert torch.allclose(cond3, expected, atol=1e-6) and not torch.allclose(cond3, cond1, atol=1e-3)
    assert torch.allclose(avg, rgb, atol=1e-6) and not torch.allclose(avg, one, atol=1e-3)
    raw["eval"]["draws"] = 0
    with pytest.raises(ConfigError, match="eval.draws"):
        load_config(Config, raw)


def test_stage1_evaluation_averages_eval_draws(cache, tmp_path):
    """The point-only model is evaluated like the U-Net's feature images: ``eval_geometry.json`` holds the PSNR
    of the mean of ``eval.draws`` surfel renders (``render_views(draws=…)``: draw j with the seeds shifted by
    j·DRAW_STRIDE), which has less sampling noise than one draw; ``draws`` < 1 is an error naming it."""
    from nsplat.evaluation.image_metrics import psnr, quantise
    from nsplat.render.renderer import DRAW_STRIDE, render_views
    from nsplat.tasks.neural.evaluation import evaluate_geometry

    raw = _tiny(cache)
    raw["eval"]["draws"] = 3
    cfg = load_config(Config, raw)
    ctx = RunContext(run_dir=tmp_path, device=torch.device("cpu"), seed=0)
    train = load_views(cfg, "train", ctx.device)
    scene = fit_geometry(cfg, ctx, train)
    views = train.subset([0, 1, 2])
    with torch.no_grad():
        one = [render_views(scene, views.viewmats, views.Ks, views.width, views.height, cfg.eval_render(),
                            seed=7 + j * DRAW_STRIDE, background=views.background, shading="none")
               for j in range(3)]
        avg = render_views(scene, views.viewmats, views.Ks, views.width, views.height, cfg.eval_render(), seed=7,
                           background=views.background, shading="none", draws=3)
    assert torch.allclose(avg, torch.stack(one).mean(0), atol=1e-6) and not torch.allclose(avg, one[0], atol=1e-3)
    out = evaluate_geometry(cfg, ctx, {"train": views}, seed=7)
    expected = psnr(quantise(avg), quantise(views.images)).mean()  # the standard protocol: 8-bit images
    assert out["train"]["protocol"] == "standard"
    assert out["train"]["psnr"]["mean"] == pytest.approx(float(expected), abs=1e-4)
    with pytest.raises(ValueError, match="draws"):
        render_views(scene, views.viewmats, views.Ks, views.width, views.height, cfg.eval_render(), draws=0)


def test_view_colour_carries_stage1_sh_colour_into_stage2(cache, tmp_path):
    """``neural.view_colour``: the stage-2 points carry stage 1's higher SH coefficients (R = 3·((L+1)² − 1)
    extra stored channels, nothing more splatted), the first three splatted channels are the SH colour seen
    from each camera — so the untrained residual U-Net reproduces the stage-1 render (the same op draws:
    camera b with seed + b) — and the SH coefficients learn. Off (the default), nothing is allocated; on
    without SH stage-1 colour, a config error names the option."""
    from nsplat.render.renderer import render_views

    raw = _tiny(cache, view_colour=True)
    raw["geometry"].update({"sh_degree": 1, "prune_opacity": 0.0})
    raw["geometry"]["optim"]["shading"] = "sh"
    cfg = load_config(Config, raw)
    ctx = RunContext(run_dir=tmp_path, device=torch.device("cpu"), seed=0)
    train = load_views(cfg, "train", ctx.device)
    geo = fit_geometry(cfg, ctx, train)
    with torch.no_grad():
        geo.tensor("features")[:, 3:] += 0.3 * torch.randn(geo.num_points, 9,
                                                           generator=torch.Generator().manual_seed(1))
    model = build(cfg, neural_scene_from(cfg, geo, 0)).modules["model"]
    C = cfg.neural.features
    assert model.scene.cfg.channels == C + 9 and model.cond_channels == C + 1
    views = train.subset([0, 1, 2])
    rgb, cond = model(views.viewmats, views.Ks, views.width, views.height, seed=5)
    with torch.no_grad():
        stage1 = render_views(geo, views.viewmats, views.Ks, views.width, views.height, cfg.render, seed=5,
                              shading="sh", background=views.background)
    assert torch.allclose(cond[:, :3].permute(0, 2, 3, 1), stage1, atol=1e-5)
    # The residual head starts at zero: RGB = the base colour (clamped to [1e-3, 1 − 1e-3] by its logit).
    assert torch.allclose(rgb.permute(0, 2, 3, 1), stage1.clamp(1e-3, 1 - 1e-3), atol=1e-4)
    rgb.square().mean().backward()
    assert model.scene.tensor("features").grad[:, C:].abs().sum() > 0
    raw_off = _tiny(cache)
    raw_off["geometry"].update({"sh_degree": 1})
    raw_off["geometry"]["optim"]["shading"] = "sh"
    off = load_config(Config, raw_off)
    assert off.view_rest() == 0
    assert build(off, neural_scene_from(off, geo, 0)).modules["model"].scene.cfg.channels == C
    with pytest.raises(ConfigError, match="neural.view_colour"):
        load_config(Config, _tiny(cache, view_colour=True))


def test_a_batch_of_views_renders_in_one_call_as_one_call_per_view(cache, tmp_path, monkeypatch):
    """Stage 2 renders a chunk's views in one op call with one seed per view: the feature images are those of
    one call per view (bitwise) and the gradients of every learnable tensor equal theirs to summation order."""
    import nsplat.render.renderer as gateway

    cfg = load_config(Config, _tiny(cache))
    ctx = RunContext(run_dir=tmp_path, device=torch.device("cpu"), seed=0)
    train = load_views(cfg, "train", ctx.device)
    model = build(cfg, neural_scene_from(cfg, fit_geometry(cfg, ctx, train), 0)).modules["model"]
    views, seeds = train.subset([0, 3, 5]), [11, 12, 13]
    calls = []
    real_render = gateway.render
    monkeypatch.setattr(gateway, "render", lambda *a, **k: calls.append(a[5].shape[0]) or real_render(*a, **k))
    params = [p for p in model.parameters() if p.requires_grad]
    weights = torch.rand(3, model.feature_image(views.viewmats[:1], views.Ks[:1], views.width, views.height,
                                                  [1]).shape[1], views.height, views.width,
                         generator=torch.Generator().manual_seed(0))
    calls.clear()
    batched = model.feature_image(views.viewmats, views.Ks, views.width, views.height, seeds)
    assert calls == [3], calls  # one op call for the three views
    grads = torch.autograd.grad((batched * weights).sum(), params, allow_unused=True)
    want = [None if g is None else torch.zeros_like(g) for g in grads]
    for b, sd in enumerate(seeds):
        one = model.feature_image(views.viewmats[b:b + 1], views.Ks[b:b + 1], views.width, views.height, sd)
        assert torch.equal(one, batched[b:b + 1]), b
        for acc, g in zip(want, torch.autograd.grad((one * weights[b:b + 1]).sum(), params, allow_unused=True)):
            if g is not None:
                acc += g
    for got, ref in zip(grads, want):
        if ref is not None:
            torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-6)  # float32: summation order only


def test_best_val_selection_keeps_the_state_of_the_best_validation(cache, tmp_path):
    """``neural.select: best_val``: the model evaluated after training, and by ``eval`` from the checkpoint, is
    the state at the validation with the highest val PSNR (not the last step's), and scores that PSNR again."""
    cfg_path = tmp_path / "tiny.yaml"
    cfg_path.write_text(yaml.safe_dump(_tiny(cache, steps=8, select="best_val", lr=3e-2,
                                             gan={"enabled": False}, learn={"features": 0.3})
                                       | {"log": {"every": 1, "images": 8, "checkpoint": 4, "validate": 1,
                                                  "progress": False}}))
    run = tmp_path / "run"
    assert main(_args(cfg_path, run)) == 0
    payload = load_checkpoint(run)
    hist = payload["extra"]["history"]
    best = payload["extra"]["best_val"]
    vals = [r["val_psnr"] for r in hist]
    assert best["psnr"] == max(vals) and best["step"] == hist[vals.index(max(vals))]["step"]
    cfg = load_config(Config, yaml.safe_load(cfg_path.read_text()))
    ctx = RunContext(run_dir=run, device=torch.device("cpu"), seed=0)
    model = load_model(cfg, ctx)
    for name, value in model.state_dict().items():
        assert torch.equal(value, best["state"][name]), name
    if best["step"] != payload["step"]:  # the last state differs from the selected one
        assert any(not torch.equal(payload["modules"]["model"][n], best["state"][n]) for n in best["state"])
    val = load_views(cfg, "val", ctx.device).spread(cfg.eval.val_views)
    rgb, _ = render_split(model, val, seed=cfg.eval_seed(), render_cfg=cfg.eval_render(), draws=cfg.eval.draws)
    assert float(psnr(rgb, val.images).mean()) == pytest.approx(best["psnr"], abs=1e-9)
    with pytest.raises(ConfigError, match="select"):
        load_config(Config, {"task": "neural", "neural": {"select": "best"}})
