"""The refine task's commands (the task contract, :class:`nsplat.tasks.Task`): ``build``, ``step``, ``run``,
``evaluate``, ``render`` and ``view``, with the outlier filter's pass over the frames."""
from __future__ import annotations

import logging
import math
import resource
from typing import Any

import imageio.v3 as iio
import numpy as np
import torch

from nsplat.checkpoint import load_checkpoint
from nsplat.data.views import PosedViews
from nsplat.engine import Engine, Trainables, checkpoint_rows, generator, latest_payload, op_seed, write_json
from nsplat.report import results
from nsplat.runctx import RunContext
from nsplat.scene import SurfelScene
from nsplat.tasks.refine.config import Config
from nsplat.tasks.refine.data import load_data
from nsplat.tasks.refine.filtering import improbable, point_errors
from nsplat.tasks.refine.metrics import evaluate_state
from nsplat.tasks.refine.model import Refiner, refiner_view
from nsplat.tasks.refine.optimisers import active_groups, masked_l1, optimizers, set_lr, step_active
from nsplat.tasks.refine.poses import pose_errors
from nsplat.view_model import ViewModel

log = logging.getLogger("nsplat.tasks.refine")


@torch.no_grad()
def run_filter(model: Refiner, cfg: Config, seed: int) -> torch.Tensor:
    """Accumulate per-point photometric error over all frames; returns the outlier mask ``[N]``."""
    fr = model.frames
    N = model.scene.num_points
    E = torch.zeros(N, dtype=torch.float64, device=fr.images.device)
    W = torch.zeros_like(E)
    # per-camera colours (Lambert) need one camera per probe render
    step = 1 if cfg.shading.model == "lambert" else cfg.optim.batch
    for s in range(0, len(fr), step):
        idx = torch.arange(s, min(s + step, len(fr)), device=fr.images.device)
        V, _ = model.camera(idx)
        colours = model.colours(V)
        colours = colours[0] if colours.dim() == 3 else colours
        mask = fr.masks[idx] if cfg.mask_loss else None
        e, w = point_errors(lambda f: model(idx, seed, features=f)[0], colours, fr.images[idx], mask)
        E += e.double()
        W += w.double()
    return improbable(E, W, cfg.filter)


def _batch(cfg: Config, count: int, step: int, seed: int) -> torch.Tensor:
    """Views of ``step``: epochs of a seeded permutation (a function of the step: exact resume)."""
    per_epoch = max(1, math.ceil(count / cfg.optim.batch))
    epoch, k = divmod(step, per_epoch)
    perm = torch.randperm(count, generator=generator(seed, "batches", epoch))
    sel = perm[k * cfg.optim.batch:(k + 1) * cfg.optim.batch]
    return sel if sel.numel() else perm[:cfg.optim.batch]


def _save_outputs(model: Refiner, ctx: RunContext) -> None:
    model.scene.save_ply(ctx.run_dir / "scene.ply")
    V, K = model.camera(torch.arange(len(model.frames), device=model.frames.images.device))
    torch.save({"viewmats": V.detach().cpu(), "Ks": K.detach().cpu(),
                "sh": None if model.sh is None else model.sh.coeffs.detach().cpu()}, ctx.run_dir / "cameras.pt")


def build(cfg: Config, scene: SurfelScene, frames: PosedViews, points: int | None = None) -> Trainables:
    """The task contract's ``build``: module ``model`` (:class:`Refiner`) and optimisers ``camera``/``scene``.

    ``points`` (a checkpoint's point count) replaces ``scene`` by an empty scene of that size to load
    into; the camera pivots are computed from ``scene`` first.
    """
    model = Refiner(cfg, scene, frames).to(scene.means.device)
    if points is not None:
        model.scene = SurfelScene(cfg.scene, points, device=scene.means.device)
    return Trainables(modules={"model": model}, optimizers=optimizers(model, cfg))


def restore(cfg: Config, ctx: RunContext) -> tuple[Refiner, int]:
    """The model of the run's latest checkpoint and its step."""
    payload = load_checkpoint(ctx.run_dir, map_location=ctx.device)
    frames, scene = load_data(cfg, ctx.device)
    t = build(cfg, scene, frames, checkpoint_rows(payload, "model", "scene._means"))
    return t.modules["model"], t.load(payload)


def step(cfg: Config, t: Trainables, seed: int, k: int) -> dict[str, float]:
    """The task contract's ``step``: one masked-L1 step of the active groups (then the outlier filter)."""
    model, opts = t.modules["model"], t.optimizers
    fr = model.frames
    device = fr.images.device
    set_lr(opts, cfg, k)
    idx = _batch(cfg, len(fr), k, seed).to(device)
    active = active_groups(cfg, k)
    for opt in opts.values():
        opt.zero_grad(set_to_none=True)
    img, alpha = model(idx, seed=op_seed(seed, "train", k))
    mask = fr.masks[idx] if cfg.mask_loss else torch.ones_like(fr.masks[idx])
    if cfg.coverage_mask > 0:
        mask = mask & (alpha.detach()[..., 0] >= cfg.coverage_mask)
    loss = masked_l1(img, fr.images[idx], mask)
    loss.backward()
    step_active(opts, active)
    done = k + 1
    if cfg.filter.due(done):
        bad = run_filter(model, cfg, seed=op_seed(seed, "filter", done))
        if bool(bad.any()):
            model.scene = model.scene.select(~bad, opts.values())
            t.extra["removed"] = int(t.extra.get("removed", 0)) + int(bad.sum())
            log.info("step %d: outlier filter removed %d points (%d left)", done, int(bad.sum()),
                     model.scene.num_points)
    out = {"loss/l1": float(loss.detach()), "scene/points": float(model.scene.num_points)}
    if fr.viewmats_gt is not None:
        with torch.no_grad():
            V, _ = model.camera(torch.arange(len(fr), device=device))
            rot, trans = pose_errors(V, fr.viewmats_gt)
        out.update({"pose/rot_deg": float(rot.mean()), "pose/trans": float(trans.mean())})
    return out


def run(cfg: Config, ctx: RunContext) -> dict[str, Any]:
    """Refine; returns the final metrics (also written to ``metrics_final.json``)."""
    torch.manual_seed(ctx.seed)
    frames, scene = load_data(cfg, ctx.device)
    payload = latest_payload(ctx.run_dir, ctx.resume, ctx.device)
    t = build(cfg, scene, frames, checkpoint_rows(payload, "model", "scene._means"))
    engine = Engine(ctx.run_dir, cfg.log, cfg.optim.steps, desc="refine")
    start = engine.resume(t, payload)
    model = t.modules["model"]
    eval_seed = op_seed(ctx.seed, "eval")
    if start == 0:
        init, img0 = evaluate_state(model, eval_seed, cfg.optim.batch)
        write_json(ctx.run_dir / "metrics_initial.json", init)
        torch.save(img0.cpu(), ctx.run_dir / "renders_initial.pt")
        log.info("initial: %s", init)
        t.extra = {"initial": init, "seconds": 0.0, "removed": 0}

    def images(done: int, writer: Any) -> None:
        idx = torch.arange(1, device=ctx.device)
        with torch.no_grad():
            img = model(idx, seed=eval_seed)[0]
        writer.add_images("render", img.clamp(0, 1), done, dataformats="NHWC")

    engine.train(t, lambda k: step(cfg, t, ctx.seed, k), start=start, images=images,
                 view=lambda: refiner_view(model, eval_seed))
    final, img = evaluate_state(model, eval_seed, cfg.optim.batch)
    final.update(seconds=float(t.extra.get("seconds", 0.0)), removed=int(t.extra.get("removed", 0)),
                 steps=cfg.optim.steps, peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
    write_json(ctx.run_dir / "metrics_final.json", final)
    torch.save(img.cpu(), ctx.run_dir / "renders_final.pt")
    _save_outputs(model, ctx)
    results.info("final: %s", final)
    return final


def evaluate(cfg: Config, ctx: RunContext, split: str = "train") -> dict[str, Any]:
    """Metrics of the run's latest checkpoint (the refined frames; ``split`` is not used: refinement
    is scored on the frames it refines). Written to ``eval.json``."""
    model, done = restore(cfg, ctx)
    out, _ = evaluate_state(model, op_seed(ctx.seed, "eval"), cfg.optim.batch)
    out["step"] = done
    write_json(ctx.run_dir / "eval.json", out)
    results.info("eval: %s", out)
    return out


def render(cfg: Config, ctx: RunContext) -> None:
    """Write reference | render | |difference| PNGs of every frame to ``renders/``."""
    model, _ = restore(cfg, ctx)
    _, img = evaluate_state(model, op_seed(ctx.seed, "eval"), cfg.optim.batch)
    out = ctx.run_dir / "renders"
    out.mkdir(exist_ok=True)
    for b in range(img.shape[0]):
        ref = model.frames.images[b]
        row = torch.cat([ref, img[b].clamp(0, 1), (img[b] - ref).abs().clamp(0, 1)], 1)
        iio.imwrite(out / f"{b:03d}.png", (row.cpu().numpy() * 255).round().astype(np.uint8))


def view(cfg: Config, ctx: RunContext) -> ViewModel:
    """The task contract's ``view``: :func:`refiner_view` of the latest checkpoint (eval mode)."""
    model, _ = restore(cfg, ctx)
    return refiner_view(model.eval(), seed=op_seed(ctx.seed, "eval"))
