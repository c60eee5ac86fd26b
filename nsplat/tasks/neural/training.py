"""Stage 2 of the neural task: learned point features and the U-Net shader (+ PatchGAN), trained on the engine.

:func:`build` makes the trainables (the task contract's ``build``), :func:`train_step` is one step
(discriminator, then generator; data-parallel under torchrun), :func:`train_neural` runs the steps with
validation (``history.json``) and image summaries.
"""
from __future__ import annotations

import logging
import math
from typing import Any

import torch

from nsplat.config import ConfigError
from nsplat.data.views import PosedViews
from nsplat.evaluation.image_metrics import psnr
from nsplat.models.losses import discriminator_loss, generator_loss
from nsplat.render.view_model import cameras_of
from nsplat.run import distributed
from nsplat.run.context import RunContext
from nsplat.run.engine import Engine, Trainables, op_seed, write_json
from nsplat.scene import SurfelScene
from nsplat.tasks.neural import precision
from nsplat.tasks.neural.config import Config, NeuralConfig
from nsplat.tasks.neural.evaluation import render_split
from nsplat.tasks.neural.model import NeuralRenderer, build_discriminator, neural_view

log = logging.getLogger(__name__)


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


def train_step(n: NeuralConfig, t: Trainables, train: PosedViews, k: int) -> dict[str, float | torch.Tensor]:
    """The task contract's ``step``: one stage-2 step (discriminator, then generator) on a random batch.

    The batch's ``B`` view slots are split across ranks (:func:`nsplat.run.distributed.shard`) and each rank's
    share into chunks of ``n.chunk`` views; slot ``j`` is rendered with op seed ``op_seed(seed, "train",
    k·batch + j)`` whichever rank and chunk render it. Each chunk's losses are weighted by its share of
    ``B``, so the gradients summed over chunks and ranks (all-reduced) and the returned scalars are the
    whole batch's. The U-Net (:meth:`NeuralRenderer.shade`) and the discriminator run in the model's
    ``compute_dtype`` (``neural.precision``); the losses are computed in float32.
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

    def judge(cond: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """The discriminator's patch logits (float32) in the model's compute precision."""
        with precision.autocast(model.compute_dtype, cond.device.type):
            logits = disc(cond, image)
        return logits.float()

    sums: dict[str, float | torch.Tensor] = {}  # Σ over chunks of (chunk's share of B) × (chunk's mean), lazily

    def add(name: str, value: torch.Tensor, w: float) -> None:
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
            d_loss = discriminator_loss(judge(cd, gt), judge(cd, rgb.detach()), n.gan.mode)
            (w * d_loss).backward()
            add("loss/disc", d_loss.detach(), w)
        distributed.all_reduce_grads(t.optimizers["d"])
        t.optimizers["d"].step()
    t.optimizers["g"].zero_grad(set_to_none=True)
    for c in chunks:
        w = len(c) / B
        rgb, cond, gt = kept if kept is not None else forward(c)
        fake = judge(cond, rgb) if use_gan else None
        losses = generator_loss(rgb, gt, fake, lambda_l1=n.gan.lambda_l1, adv_weight=n.gan.weight,
                                ssim_weight=n.ssim_weight, mode=n.gan.mode)
        (w * losses["total"]).backward()
        for name, v in losses.items():
            add(f"loss/{name}", v.detach(), w)
        add("psnr/train_batch", psnr(rgb.detach(), gt).mean(), w)
    distributed.all_reduce_grads(t.optimizers["g"])
    t.optimizers["g"].step()
    t.schedulers["g"].step()
    if use_gan:
        t.schedulers["d"].step()
    out = distributed.all_reduce_scalars(sums)
    out.update({f"lr/{g['name']}": g["lr"] for g in t.optimizers["g"].param_groups})
    return out


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
                rgb, _ = render_split(model, sub, seed=cfg.eval_seed(), render_cfg=cfg.eval_render(),
                                      draws=cfg.eval.draws)
                rec[f"{name}_psnr"] = out[f"psnr/{name}"] = float(psnr(rgb, sub.images).mean())
        if cfg.neural.select == "best_val" and rec["val_psnr"] > t.extra.get("best_val", {}).get("psnr", -math.inf):
            t.extra["best_val"] = {"step": done, "psnr": rec["val_psnr"],
                                   "state": {k: v.detach().clone() for k, v in model.state_dict().items()}}
        t.extra["history"].append(rec)
        write_json(ctx.run_dir / "history.json", {"history": t.extra["history"],
                                                  "train_seconds": rec["elapsed_s"]})
        return out

    def images(done: int, writer: Any) -> None:
        sub = (val_sub if val_sub is not None else tr_sub).spread(2)
        rgb, cond = render_split(model, sub, seed=cfg.eval_seed(), render_cfg=cfg.eval_render(), draws=cfg.eval.draws)
        writer.add_images("images/features", _preview(cond), done)
        writer.add_images("images/render", _nchw(rgb), done)
        writer.add_images("images/gt", _nchw(sub.images), done)
        writer.add_images("images/error", _nchw((rgb - sub.images).abs().mean(-1, keepdim=True)), done)

    if cfg.neural.select == "best_val" and val_sub is None:
        raise ConfigError("neural.select: best_val needs validation views (a val split; eval.val_views >= 1)")
    engine = Engine(ctx.run_dir, cfg.log, cfg.neural.steps, desc="neural")
    engine.train(t, lambda k: train_step(cfg.neural, t, train, k), start=start,
                 validate=validate, images=images,
                 view=lambda: neural_view(model, cams, cfg.eval_seed()))
    best = t.extra.get("best_val")
    if cfg.neural.select == "best_val" and best is not None:
        model.load_state_dict(best["state"])
        log.info("stage 2: the model is step %d's (val %.2f dB, the best of %d validations; neural.select: best_val)",
                 best["step"], best["psnr"], len(t.extra["history"]))
    return t


def check_parallel(cfg: Config, views: int) -> None:
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
