"""Task ``neural``: neural point rendering (paper §4 "Neural Rendering") on NeRF-synthetic scenes.

Stage 1 (geometry): RGB surfels either read from a PLY or initialised on the visual hull of the
training silhouettes (:mod:`nsplat.data.visual_hull`) and fitted to the training views with the op
(:func:`nsplat.fitting.fit`, L1, features = RGB, no shading); written to ``geometry.ply``.

Stage 2 (neural): every point gets ``C`` learned features (the first three start from its stage-1
colour); the op splats them (plus coverage; the background is the data background in the colour
channels and 0 elsewhere) into a feature image that a U-Net shader
(:class:`nsplat.models.UNet`) turns into RGB, trained with ``λ_L1·L1 + adversarial`` against a
conditional PatchGAN (:class:`nsplat.models.PatchDiscriminator`). Which point attributes stay
learnable, with their own learning rates, is ``neural.learn``.

Configuration: :mod:`nsplat.tasks.neural_config`; the stage-2 networks: :mod:`nsplat.tasks.neural_model`;
evaluation outputs: :mod:`nsplat.tasks.neural_eval`.
Both stages run on the engine (:mod:`nsplat.engine`); every render goes through :mod:`nsplat.render`.
Both run data-parallel under torchrun (:mod:`nsplat.distributed`, docs/distributed.md); rank 0 alone
writes the run folder and evaluates.

Run folder: ``config.yaml``, ``geometry/`` (stage-1 logs and checkpoints), ``geometry.ply``,
``tb/`` (TensorBoard), ``checkpoints/`` (stage 2, atomic, exact resume), ``history.json`` (train
and val PSNR over steps), ``eval_<split>/`` (``metrics.json``, ``per_view.json``, PNGs),
``eval_geometry.json`` (stage 1 alone on val and the held-out split) and ``orbit.mp4``.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from typing import Any

import torch

from nsplat import distributed
from nsplat import render as gateway
from nsplat.checkpoint import load_checkpoint
from nsplat.config import ConfigError
from nsplat.data.nerf_synthetic import load_split
from nsplat.data.paths import resolve
from nsplat.data.procedural import ProceduralSpec, ensure_scene
from nsplat.data.views import PosedViews
from nsplat.engine import Engine, Trainables, checkpoint_rows, latest_payload, op_seed, write_json
from nsplat.fitting import fit
from nsplat.losses import discriminator_loss, generator_loss
from nsplat.metrics_image import psnr
from nsplat.runctx import RunContext
from nsplat.scene import SceneConfig, SurfelScene
from nsplat.tasks.neural_capture import capture_views, with_capture_render
from nsplat.tasks.neural_config import Config, NeuralConfig
from nsplat.tasks.neural_init import initial_geometry
from nsplat.tasks.neural_model import NeuralRenderer, build_discriminator, neural_view
from nsplat.view_model import ViewModel, cameras_of

log = logging.getLogger(__name__)

#: Runs data-parallel under torchrun (the CLI refuses tasks without this flag).
DISTRIBUTED = True


# ---------------------------------------------------------------------------------------------- data
def scene_root(cfg: Config) -> Path:
    """Folder of the NeRF-synthetic-format scene (the procedural one is generated on first use)."""
    d = cfg.data
    if d.source == "nerf_synthetic":
        root = resolve(d.root or "")
        if not (root / "transforms_train.json").is_file():
            raise ConfigError(f"data.root: no transforms_train.json in {root}")
        return root
    p = d.procedural
    spec = ProceduralSpec(seed=p.seed, resolution=p.resolution, views=tuple(p.views), objects=p.objects)
    return ensure_scene(spec, resolve(p.cache_dir))


def load_views(cfg: Config, split: str, device: torch.device) -> PosedViews:
    """One split of the configured scene on ``device`` (a COLMAP capture: :mod:`nsplat.tasks.neural_capture`)."""
    if cfg.data.source == "colmap":
        return capture_views(cfg, split, device)
    limit = {"train": cfg.data.train_limit, "val": cfg.data.val_limit, "test": cfg.data.test_limit}[split]
    views = load_split(scene_root(cfg), split, resolution=cfg.data.resolution, background=cfg.data.background,
                       limit=limit)
    return views.to(device)


# ---------------------------------------------------------------------------------------------- scenes
def neural_scene_config(cfg: Config) -> SceneConfig:
    """Stage-2 scene: ``C`` raw features (+ stage 1's higher SH coefficients with ``neural.view_colour``);
    learnable attributes from ``neural.learn``."""
    return SceneConfig(channels=cfg.neural.features + cfg.view_rest(), learn=list(cfg.neural.learn),
                       opacity=cfg.geometry.opacity, scale=None, feature_activation="identity")


# ---------------------------------------------------------------------------------------------- stage 1
def fit_geometry(cfg: Config, ctx: RunContext, train: PosedViews, val: PosedViews | None = None) -> SurfelScene:
    """Stage 1: initial points, fitted to ``train`` with the op (resumable); writes ``geometry.ply``.

    With ``geometry.log.validate > 0`` and ``val``, the stage-1 surfels are rendered on ``val``
    (``eval.val_views`` of them, evaluation settings, the mean of ``eval.draws`` draws) at that cadence
    and ``geometry_history.json`` records ``{step, elapsed_s, val_psnr}``; ``elapsed_s`` is the stage's
    wall time so far, from before the initial points, without the validation renders (the time-to-quality
    curve of stage 1)."""
    t0, validating = time.perf_counter(), 0.0
    scene = initial_geometry(cfg, train, ctx.seed)
    g = cfg.geometry
    history: list[dict[str, float]] = []
    val_sub = val.spread(cfg.eval.val_views) if val is not None else None

    def validate(done: int, writer: Any) -> dict[str, float]:
        nonlocal validating
        t1 = time.perf_counter()
        with torch.no_grad():
            rgb = gateway.render_views(scene, val_sub.viewmats, val_sub.Ks, val_sub.width, val_sub.height,
                                       cfg.eval_render(), seed=eval_seed(cfg), shading=g.optim.shading,
                                       background=val_sub.background, draws=cfg.eval.draws).clamp(0, 1)
        value = float(psnr(rgb, val_sub.images).mean())
        history.append({"step": done, "elapsed_s": t1 - t0 - validating, "val_psnr": value})
        write_json(ctx.run_dir / "geometry_history.json", {"history": history})
        validating += time.perf_counter() - t1
        return {"psnr/val": value}

    if g.optim.epochs > 0:
        fit(scene, train, g.optim, cfg.render, ctx.run_dir / "geometry", seed=ctx.seed, resume=ctx.resume,
            log=dataclasses.replace(g.log, progress=cfg.log.progress), background=train.background,
            desc="geometry", validate=validate if val_sub is not None and g.log.validate > 0 else None)
    if distributed.is_main():
        scene.save_ply(ctx.run_dir / "geometry.ply")
    return scene


@torch.no_grad()
def neural_scene_from(cfg: Config, geo: SurfelScene, seed: int) -> SurfelScene:
    """Stage-2 scene from the stage-1 surfels: geometry copied, features = [colour, N(0, σ²)…] (with
    ``neural.view_colour``: followed by stage 1's higher SH coefficients).

    Points with opacity below ``geometry.prune_opacity`` are dropped.
    """
    keep = torch.ones(geo.num_points, dtype=torch.bool, device=geo.means.device)
    if cfg.geometry.opacity is None:
        keep = geo.opacities >= cfg.geometry.prune_opacity
        if not bool(keep.any()):
            raise RuntimeError("stage 1 left no point above geometry.prune_opacity")
    C = cfg.neural.features
    gen = torch.Generator().manual_seed(seed)
    feats = torch.randn(int(keep.sum()), C, generator=gen, dtype=geo.means.dtype) * cfg.neural.feature_init_std
    feats = feats.to(geo.means.device)
    k = min(3, C)
    feats[:, :k] = geo.features[keep][:, :k]
    if cfg.view_rest():
        feats = torch.cat([feats, geo.features[keep][:, 3:]], 1)
    scfg = neural_scene_config(cfg)
    kwargs = {"features": feats}
    if scfg.opacity is None:
        kwargs["opacities"] = geo.opacities[keep]
    return SurfelScene.from_points(scfg, geo.means[keep].clone(), geo.normals[keep].clone(),
                                   scales=geo.scales[keep].clone(), **kwargs)


# ---------------------------------------------------------------------------------------------- stage 2
def build(cfg: Config, scene: SurfelScene, seed: int = 0) -> Trainables:
    """The task contract's ``build`` for stage 2: modules ``model`` (:class:`NeuralRenderer` over ``scene``)
    and ``disc`` (only when ``neural.gan.enabled``), Adam ``g``/``d`` with exponential schedulers, and the
    batch generator seeded ``seed``."""
    n = cfg.neural
    device = scene.means.device
    model = NeuralRenderer(scene, cfg).to(device)
    groups = scene.param_groups(n.learn) + [{"params": list(model.unet.parameters()), "lr": n.lr, "name": "unet"}]
    gamma = n.lr_final ** (1.0 / max(1, n.steps))
    opt_g = torch.optim.Adam(groups, betas=tuple(n.betas))
    t = Trainables(modules={"model": model}, optimizers={"g": opt_g},
                   schedulers={"g": torch.optim.lr_scheduler.ExponentialLR(opt_g, gamma)},
                   generator=torch.Generator().manual_seed(seed), extra={"seed": seed, "history": []})
    disc = build_discriminator(cfg, model.cond_channels)
    if disc is not None:
        t.modules["disc"] = disc.to(device)
        opt_d = torch.optim.Adam(disc.parameters(), lr=n.gan.lr, betas=tuple(n.gan.betas))
        t.optimizers["d"] = opt_d
        # The discriminator trains from n.gan_start_step() on; its rate decays over those steps only.
        gamma_d = n.lr_final ** (1.0 / max(1, n.steps - n.gan_start_step()))
        t.schedulers["d"] = torch.optim.lr_scheduler.ExponentialLR(opt_d, gamma_d)
    return t


def _nchw(x: torch.Tensor) -> torch.Tensor:
    return x.permute(0, 3, 1, 2).contiguous()


def _chunks(share: range, chunk: int | None) -> list[range]:
    """``share`` cut into consecutive ranges of at most ``chunk`` slots (one range when ``chunk`` is None)."""
    size = chunk or max(len(share), 1)
    return [share[i:i + size] for i in range(0, len(share), size)]


def train_step(n: NeuralConfig, t: Trainables, train: PosedViews, k: int) -> dict[str, float]:
    """The task contract's ``step``: one stage-2 step (discriminator, then generator) on a random batch.

    The batch's ``B`` view slots are split across ranks (:func:`nsplat.distributed.shard`) and each rank's
    share into chunks of ``n.chunk`` views; slot ``j`` is rendered with op seed ``op_seed(seed, "train",
    k·batch + j)`` whichever rank and chunk render it. Each chunk's losses are weighted by its share of
    ``B``, so the gradients summed over chunks and ranks (all-reduced) and the returned scalars are the
    whole batch's.
    """
    model, disc = t.modules["model"], t.modules.get("disc")
    idx = torch.randperm(len(train), generator=t.generator)[:n.batch].to(train.images.device)
    B, seed = idx.numel(), int(t.extra["seed"])
    chunks = _chunks(distributed.shard(B), n.chunk)

    def forward(c: range) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(rgb, cond, gt)`` of the chunk's slots ``c``, ``[b,·,H,W]``."""
        v = idx[c.start:c.stop]
        rgb, cond = model(train.viewmats[v], train.Ks[v], train.width, train.height,
                          [op_seed(seed, "train", k * n.batch + j) for j in c])
        return rgb, cond, _nchw(train.images[v])

    sums: dict[str, float] = {}  # Σ over chunks of (chunk's share of B) × (chunk's mean)

    def add(name: str, value: float, w: float) -> None:
        sums[name] = sums.get(name, 0.0) + w * value

    use_gan = disc is not None and k >= n.gan_start_step()
    kept = None  # a single chunk's forward, reused by the generator's step (more chunks: recomputed)
    if use_gan:
        t.optimizers["d"].zero_grad(set_to_none=True)
        for c in chunks:
            w = len(c) / B
            with torch.set_grad_enabled(len(chunks) == 1):
                rgb, cond, gt = forward(c)
            kept = (rgb, cond, gt) if len(chunks) == 1 else None
            cd = cond.detach()
            d_loss = discriminator_loss(disc(cd, gt), disc(cd, rgb.detach()), n.gan.mode)
            (w * d_loss).backward()
            add("loss/disc", d_loss.item(), w)
        distributed.all_reduce_grads(t.optimizers["d"])
        t.optimizers["d"].step()
    t.optimizers["g"].zero_grad(set_to_none=True)
    for c in chunks:
        w = len(c) / B
        rgb, cond, gt = kept if kept is not None else forward(c)
        fake = disc(cond, rgb) if use_gan else None
        losses = generator_loss(rgb, gt, fake, lambda_l1=n.gan.lambda_l1, adv_weight=n.gan.weight,
                                ssim_weight=n.ssim_weight, mode=n.gan.mode)
        (w * losses["total"]).backward()
        for name, v in losses.items():
            add(f"loss/{name}", v.item(), w)
        add("psnr/train_batch", float(psnr(rgb.detach(), gt).mean()), w)
    distributed.all_reduce_grads(t.optimizers["g"])
    t.optimizers["g"].step()
    t.schedulers["g"].step()
    if use_gan:
        t.schedulers["d"].step()
    out = distributed.all_reduce_scalars(sums)
    out.update({f"lr/{g['name']}": g["lr"] for g in t.optimizers["g"].param_groups})
    return out


def eval_seed(cfg: Config) -> int:
    """Op seed of every evaluation render (validation, test, orbit): fixed by the config's seed."""
    return op_seed(cfg.seed, "eval")


@torch.no_grad()
def render_split(model: NeuralRenderer, views: PosedViews, seed: int, batch: int = 4,
                 render_cfg: gateway.RenderConfig | None = None, draws: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Rendered RGB ``[B,H,W,3]`` and feature images ``[B,C',H,W]`` of all ``views`` (eval mode), with the
    render settings ``render_cfg`` (default: the model's, i.e. training's; see ``Config.eval_render``) and
    ``draws`` averaged op draws per feature image (``eval.draws``)."""
    was, trained_cfg = model.training, model.render_cfg
    model.eval()
    if render_cfg is not None:
        model.render_cfg = render_cfg
    rgbs, conds = [], []
    try:
        for s in range(0, len(views), batch):
            rgb, cond = model(views.viewmats[s:s + batch], views.Ks[s:s + batch], views.width, views.height, seed + s,
                              draws=draws)
            rgbs.append(rgb.permute(0, 2, 3, 1))
            conds.append(cond)
    finally:
        model.train(was)
        model.render_cfg = trained_cfg
    return torch.cat(rgbs).clamp(0, 1), torch.cat(conds)


def _preview(cond: torch.Tensor) -> torch.Tensor:
    """First three feature channels, min-max normalised per image, ``[B,3,H,W]``."""
    x = cond[:, :3]
    lo = x.flatten(1).min(1).values[:, None, None, None]
    hi = x.flatten(1).max(1).values[:, None, None, None]
    return (x - lo) / (hi - lo).clamp_min(1e-8)


def train_neural(cfg: Config, ctx: RunContext, t: Trainables, train: PosedViews, val: PosedViews | None,
                 start: int = 0) -> Trainables:
    """Stage 2 on the engine from step ``start``; validation writes ``history.json``."""
    model = t.modules["model"]
    tr_sub = train.spread(cfg.eval.val_views)
    val_sub = val.spread(cfg.eval.val_views) if val is not None else None
    cams = cameras_of(train.images, train.viewmats, train.Ks)

    def validate(done: int, writer: Any) -> dict[str, float]:
        rec: dict[str, float] = {"step": done, "elapsed_s": float(t.extra.get("seconds", 0.0))}
        out = {}
        for name, sub in (("train", tr_sub), ("val", val_sub)):
            if sub is not None:
                rgb, _ = render_split(model, sub, seed=eval_seed(cfg), render_cfg=cfg.eval_render(),
                                      draws=cfg.eval.draws)
                rec[f"{name}_psnr"] = out[f"psnr/{name}"] = float(psnr(rgb, sub.images).mean())
        t.extra["history"].append(rec)
        write_json(ctx.run_dir / "history.json", {"history": t.extra["history"],
                                                  "train_seconds": rec["elapsed_s"]})
        return out

    def images(done: int, writer: Any) -> None:
        sub = (val_sub if val_sub is not None else tr_sub).spread(2)
        rgb, cond = render_split(model, sub, seed=eval_seed(cfg), render_cfg=cfg.eval_render(), draws=cfg.eval.draws)
        writer.add_images("images/features", _preview(cond), done)
        writer.add_images("images/render", _nchw(rgb), done)
        writer.add_images("images/gt", _nchw(sub.images), done)
        writer.add_images("images/error", _nchw((rgb - sub.images).abs().mean(-1, keepdim=True)), done)

    engine = Engine(ctx.run_dir, cfg.log, cfg.neural.steps, desc="neural")
    engine.train(t, lambda k: train_step(cfg.neural, t, train, k), start=start,
                 validate=validate, images=images,
                 view=lambda: neural_view(model, cams, eval_seed(cfg)))
    return t


# ---------------------------------------------------------------------------------------------- commands
def run(cfg: Config, ctx: RunContext) -> dict:
    """Train (stage 1, then stage 2; resumable) and evaluate the held-out split (under torchrun: rank 0
    evaluates and returns the metrics, the other ranks return ``{}`` after training)."""
    cfg = with_capture_render(cfg)
    torch.manual_seed(ctx.seed)
    t0 = time.perf_counter()
    train = load_views(cfg, "train", ctx.device)
    _check_parallel(cfg, len(train))
    val = load_views(cfg, "val", ctx.device) if cfg.log.validate else None
    payload = latest_payload(ctx.run_dir, ctx.resume, "cpu")
    timing = {}
    if payload is None:
        geo = fit_geometry(cfg, ctx, train, val)
        timing["geometry_s"] = time.perf_counter() - t0
        if cfg.neural.steps == 0:
            return _point_only_result(cfg, ctx, val, timing)
        scene = neural_scene_from(cfg, geo, seed=ctx.seed)
        log.info("stage 2: %d points, %d features", scene.num_points, cfg.neural.features)
    else:
        points = checkpoint_rows(payload, "model", "scene._means")
        scene = SurfelScene(neural_scene_config(cfg), points, device=ctx.device)
    t = build(cfg, scene, ctx.seed)
    start = Engine(ctx.run_dir, cfg.log, cfg.neural.steps).resume(t, payload)
    train_neural(cfg, ctx, t, train, val, start)
    if not distributed.is_main():
        return {}
    timing["train_total_s"] = time.perf_counter() - t0
    metrics = evaluate(cfg, ctx, cfg.eval.split, model=t.modules["model"])
    if cfg.eval.geometry:
        from nsplat.tasks.neural_eval import evaluate_geometry

        splits = {"val": val if val is not None else load_views(cfg, "val", ctx.device),
                  cfg.eval.split: load_views(cfg, cfg.eval.split, ctx.device)}
        evaluate_geometry(cfg, ctx, splits, eval_seed(cfg))
    write_json(ctx.run_dir / "timing.json", {**timing, "neural_steps_s": float(t.extra.get("seconds", 0.0))})
    return metrics


def _point_only_result(cfg: Config, ctx: RunContext, val: PosedViews | None, timing: dict) -> dict:
    """``neural.steps: 0``: the stage-1 surfels are the model; their held-out metrics are the run's."""
    if not distributed.is_main():
        return {}
    from nsplat.tasks.neural_eval import evaluate_geometry

    splits = {"val": val if val is not None else load_views(cfg, "val", ctx.device),
              cfg.eval.split: load_views(cfg, cfg.eval.split, ctx.device)}
    out = evaluate_geometry(cfg, ctx, splits, eval_seed(cfg))
    write_json(ctx.run_dir / "timing.json", {**timing, "train_total_s": timing["geometry_s"], "neural_steps_s": 0.0})
    return {"split": cfg.eval.split, "points": out["points"], **out[cfg.eval.split]}


def _check_parallel(cfg: Config, views: int) -> None:
    """Refuse data-parallel settings that cannot give every rank a view or the single-process gradients."""
    P = distributed.world_size()
    if P == 1:
        return
    if min(cfg.neural.batch, views) < P:
        raise ConfigError(f"neural.batch: expected at least one training view per process ({P} processes), "
                          f"got a batch of {min(cfg.neural.batch, views)}")
    if "batch" in (cfg.neural.unet.norm, cfg.neural.gan.norm):
        raise ConfigError("neural.unet.norm / neural.gan.norm: batch norm statistics would differ per process; "
                          "use group, instance or none under torchrun")


def load_model(cfg: Config, ctx: RunContext) -> NeuralRenderer:
    """The trained renderer from the run's latest checkpoint."""
    cfg = with_capture_render(cfg)
    payload = load_checkpoint(ctx.run_dir, map_location="cpu")
    points = checkpoint_rows(payload, "model", "scene._means")
    model = NeuralRenderer(SurfelScene(neural_scene_config(cfg), points, device=ctx.device), cfg).to(ctx.device)
    model.load_state_dict(payload["modules"]["model"])
    return model


def evaluate(cfg: Config, ctx: RunContext, split: str = "test", model: NeuralRenderer | None = None) -> dict:
    """Held-out metrics of ``split`` (:func:`nsplat.tasks.neural_eval.evaluate_split`)."""
    from nsplat.tasks.neural_eval import evaluate_split

    if split not in ("train", "val", "test"):
        raise ConfigError(f"--split: expected train, val or test, got {split!r}")
    cfg = with_capture_render(cfg)
    model = model if model is not None else load_model(cfg, ctx)
    return evaluate_split(cfg, ctx, model, load_views(cfg, split, ctx.device), split, eval_seed(cfg))


def render(cfg: Config, ctx: RunContext) -> Path:
    """Write ``orbit.mp4``: the trained model along a circle of cameras around the scene."""
    from nsplat.tasks.neural_eval import write_orbit

    cfg = with_capture_render(cfg)
    return write_orbit(cfg, ctx, load_model(cfg, ctx), load_views(cfg, "train", ctx.device), eval_seed(cfg))


def view(cfg: Config, ctx: RunContext) -> ViewModel:
    """The task contract's ``view``: the trained renderer (eval mode) with the training cameras."""
    model = load_model(cfg, ctx).eval()
    train = load_views(cfg, "train", ctx.device)
    return neural_view(model, cameras_of(train.images, train.viewmats, train.Ks), seed=eval_seed(cfg))
