"""The refine task's commands (the task contract, :class:`nsplat.tasks.Task`): ``build``, ``step``, ``run``,
``evaluate``, ``render`` and ``view``, with the outlier filter's pass over the frames."""
from __future__ import annotations

import logging
import math
import resource
import time
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np
import torch

from nsplat.data.views import PosedViews
from nsplat.render.view_model import ViewModel
from nsplat.run.checkpoint import load_checkpoint
from nsplat.run.context import RunContext
from nsplat.run.engine import Engine, Trainables, checkpoint_rows, generator, latest_payload, op_seed, write_json
from nsplat.run.report import results
from nsplat.scene import SurfelScene
from nsplat.tasks.refine.config import Config
from nsplat.tasks.refine.data import RefineData, load_data
from nsplat.tasks.refine.filtering import improbable, point_errors
from nsplat.tasks.refine.metrics import evaluate_state
from nsplat.tasks.refine.model import Refiner, refiner_view
from nsplat.tasks.refine.optimisers import active_groups, depth_l1, masked_l1, optimizers, set_lr, step_active
from nsplat.tasks.refine.poses import motion_prior, odometry_prior, pose_errors
from nsplat.tasks.refine.sequence import (
    fit_heldout,
    frame_metrics,
    heldout_refiner,
    render_all,
    table,
    trajectory,
    trajectory_metrics,
    write_before_after,
    write_tum,
)
from nsplat.tasks.refine.trajectory import ate

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
    model, done, _ = restore_data(cfg, ctx)
    return model, done


def restore_data(cfg: Config, ctx: RunContext) -> tuple[Refiner, int, RefineData]:
    """The model of the run's latest checkpoint, its step and the task's data."""
    payload = load_checkpoint(ctx.run_dir, map_location=ctx.device)
    data = load_data(cfg, ctx.device)
    t = build(cfg, data.scene, data.frames, checkpoint_rows(payload, "model", "scene._means"))
    return t.modules["model"], t.load(payload), data


def _loss(cfg: Config, model: Refiner, idx: torch.Tensor, seed: int) -> tuple[torch.Tensor, dict[str, float]]:
    """The loss of a step on cameras ``idx``: the masked L1 image loss, with the depth term and the pose priors the
    config asks for; and its scalars for the log."""
    fr = model.frames
    img, alpha, depth = model(idx, seed=seed, with_depth=True)
    mask = fr.masks[idx] if cfg.mask_loss else torch.ones_like(fr.masks[idx])
    if cfg.coverage_mask > 0:
        mask = mask & (alpha.detach()[..., 0] >= cfg.coverage_mask)
    l1 = masked_l1(img, fr.images[idx], mask)
    total, scalars = l1, {"loss/l1": float(l1.detach())}
    if cfg.depth_loss > 0 and fr.depths is not None:
        d = depth_l1(depth, alpha, fr.depths[idx], mask)
        total, scalars["loss/depth"] = total + cfg.depth_loss * d, float(d.detach())
    p, cams = cfg.poses, model.cameras
    if p.odometry_weight > 0 and cams is not None and cams.twist is not None:
        total = total + p.odometry_weight * odometry_prior(cams.delta(), p.odometry_sigma)
    if p.motion_weight > 0 and fr.times is not None and cams is not None:
        V, _ = model.camera(torch.arange(len(fr), device=idx.device))
        total = total + p.motion_weight * motion_prior(V, fr.times, p.motion_sigma)
    return total, scalars


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
    loss, scalars = _loss(cfg, model, idx, op_seed(seed, "train", k))
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
    out = {**scalars, "scene/points": float(model.scene.num_points)}
    if fr.viewmats_gt is not None:
        with torch.no_grad():
            V, _ = model.camera(torch.arange(len(fr), device=device))
            if fr.depths is not None:  # an RGB-D sequence: its ground truth has a world frame of its own
                out["pose/ate_train"] = ate(torch.linalg.inv(V.double()), torch.linalg.inv(fr.viewmats_gt.double()))[
                    "rmse"]
            else:
                rot, trans = pose_errors(V, fr.viewmats_gt)
                out.update({"pose/rot_deg": float(rot.mean()), "pose/trans": float(trans.mean())})
    return out


def sequence_state(model: Refiner, data: RefineData, cfg: Config, seed: int, *, fit: bool,
                   progress: bool = True) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """An RGB-D refinement's figures in its current state: ``train`` and ``heldout`` image metrics (the held-out
    cameras fitted to the frozen scene when ``fit``, else at the trajectory's poses), ATE / RPE of every frame's
    camera, the point count; and the renders (``train``, ``heldout``) and poses (``c2w``)."""
    seq = data.sequence
    img = render_all(model, seed, cfg.optim.batch)
    out: dict[str, Any] = {"train": frame_metrics(img, data.frames)}
    renders = {"train": img}
    held = None
    if data.heldout is not None:
        held = (fit_heldout(model, data.heldout, cfg, seed, seq, progress) if fit
                else heldout_refiner(model, data.heldout))
        renders["heldout"] = render_all(held, seed, cfg.optim.batch)
        out["heldout"] = frame_metrics(renders["heldout"], data.heldout)
    renders["c2w"] = trajectory(model, held, seq)
    out.update(trajectory_metrics(renders["c2w"], seq, cfg.data.rgbd.trajectory_alignment))
    out["points"] = model.scene.num_points
    return out, renders


def _initial(model: Refiner, data: RefineData, cfg: Config, ctx: RunContext, seed: int) -> dict[str, Any]:
    """The "before" figures (written to ``metrics_initial.json``): with ``heldout.fit_before`` the held-out frames
    scored after the same camera + exposure fit as "after" gets (``heldout``, and the renders the before/after
    sheets show; at the trajectory's poses: ``heldout_unfitted``); ATE / RPE of the trajectory as given."""
    if data.sequence is None:
        init, img0 = evaluate_state(model, seed, cfg.optim.batch)
        torch.save(img0.cpu(), ctx.run_dir / "renders_initial.pt")
        return init
    init, renders = sequence_state(model, data, cfg, seed, fit=False)
    if cfg.heldout.fit_before and data.heldout is not None:
        held = fit_heldout(model, data.heldout, cfg, seed, data.sequence)
        renders["heldout"] = render_all(held, seed, cfg.optim.batch)
        init["heldout_unfitted"] = init["heldout"]
        init["heldout"] = frame_metrics(renders["heldout"], data.heldout)
    torch.save({k: v.cpu() for k, v in renders.items()}, ctx.run_dir / "renders_initial.pt")
    write_tum(ctx.run_dir / "trajectory_initial.txt", data.sequence.c2w, data.sequence,
              f"initial trajectory ({data.sequence.source.get('trajectory', '')})")
    if data.sequence.source.get("trajectory") == "estimate":
        write_tum(ctx.run_dir / "trajectory_estimate.txt", data.sequence.c2w, data.sequence,
                  "trajectory estimated from the frames (nsplat.data.tracking)")
    init["source"] = data.sequence.source
    return init


def _sequence_final(model: Refiner, data: RefineData, cfg: Config, ctx: RunContext, seed: int,
                    t: Trainables, clock: tuple[float, float]) -> dict[str, Any]:
    """The "after" figures of an RGB-D refinement, the outputs (trajectory, PLY, sheets, video, ``metrics.json``)
    and the before/after table on stdout."""
    final, renders = sequence_state(model, data, cfg, seed, fit=True)
    before = t.extra["initial"]
    write_tum(ctx.run_dir / "trajectory.txt", renders["c2w"], data.sequence, "refined trajectory")
    initial = torch.load(ctx.run_dir / "renders_initial.pt")
    shown = write_before_after(ctx.run_dir / "before_after", data.frames, initial["train"], renders["train"], "train")
    if data.heldout is not None:
        shown += write_before_after(ctx.run_dir / "before_after", data.heldout, initial["heldout"],
                                    renders["heldout"], "heldout")
    out = {"before": before, "after": final, "resolution": [data.frames.width, data.frames.height],
           "frames": {"train": len(data.frames), "heldout": 0 if data.heldout is None else len(data.heldout)},
           "wall_s": time.perf_counter() - clock[0], "cpu_s": time.process_time() - clock[1],
           "steps_wall_s": float(t.extra.get("seconds", 0.0)), "steps_cpu_s": float(t.extra.get("cpu_seconds", 0.0)),
           "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
           "removed": int(t.extra.get("removed", 0)), "steps": cfg.optim.steps}
    write_json(ctx.run_dir / "metrics.json", out)
    results.info("before/after (%d training frames, %d held out, %d×%d):\n%s", out["frames"]["train"],
                 out["frames"]["heldout"], *out["resolution"], table(before, final))
    results.info("outputs: %s, %s, %s", ctx.run_dir / "trajectory.txt", ctx.run_dir / "scene.ply",
                 ", ".join(str(Path(p)) for p in shown))
    return out


def run(cfg: Config, ctx: RunContext) -> dict[str, Any]:
    """Refine; returns the final metrics (also written to ``metrics_final.json``; for an RGB-D sequence
    ``metrics.json`` holds the before/after figures)."""
    clock = (time.perf_counter(), time.process_time())
    torch.manual_seed(ctx.seed)
    data = load_data(cfg, ctx.device)
    payload = latest_payload(ctx.run_dir, ctx.resume, ctx.device)
    t = build(cfg, data.scene, data.frames, checkpoint_rows(payload, "model", "scene._means"))
    engine = Engine(ctx.run_dir, cfg.log, cfg.optim.steps, desc="refine")
    start = engine.resume(t, payload)
    model = t.modules["model"]
    eval_seed = op_seed(ctx.seed, "eval")
    if start == 0:
        if data.initial is not None:  # the trajectory as given, before the re-tracking
            given = build(cfg, data.initial.scene, data.initial.frames).modules["model"]
            init = _initial(given, data.initial, cfg, ctx, eval_seed)
            init["start"] = trajectory_metrics(data.sequence.c2w, data.sequence, cfg.data.rgbd.trajectory_alignment)
            init["source"] = data.sequence.source
            write_tum(ctx.run_dir / "trajectory_retracked.txt", data.sequence.c2w, data.sequence,
                      "the given trajectory re-tracked (nsplat.data.tracking)")
            del given
        else:
            init = _initial(model, data, cfg, ctx, eval_seed)
        write_json(ctx.run_dir / "metrics_initial.json", init)
        log.info("initial: %s", {k: v for k, v in init.items() if not isinstance(v, dict)})
        t.extra = {"initial": init, "seconds": 0.0, "removed": 0}

    def images(done: int, writer: Any) -> None:
        idx = torch.arange(1, device=ctx.device)
        with torch.no_grad():
            img = model(idx, seed=eval_seed)[0]
        writer.add_images("render", img.clamp(0, 1), done, dataformats="NHWC")

    engine.train(t, lambda k: step(cfg, t, ctx.seed, k), start=start, images=images,
                 view=lambda: refiner_view(model, eval_seed))
    _save_outputs(model, ctx)
    if data.sequence is not None:
        return _sequence_final(model, data, cfg, ctx, eval_seed, t, clock)
    final, img = evaluate_state(model, eval_seed, cfg.optim.batch)
    final.update(seconds=float(t.extra.get("seconds", 0.0)), removed=int(t.extra.get("removed", 0)),
                 steps=cfg.optim.steps, peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
    write_json(ctx.run_dir / "metrics_final.json", final)
    torch.save(img.cpu(), ctx.run_dir / "renders_final.pt")
    results.info("final: %s", final)
    return final


def evaluate(cfg: Config, ctx: RunContext, split: str = "train") -> dict[str, Any]:
    """Metrics of the run's latest checkpoint (the refined frames; for an RGB-D sequence also the held-out frames
    after fitting their cameras, and ATE / RPE; ``split`` is not used). Written to ``eval.json``."""
    model, done, data = restore_data(cfg, ctx)
    seed = op_seed(ctx.seed, "eval")
    if data.sequence is not None:
        out, _ = sequence_state(model, data, cfg, seed, fit=True)
    else:
        out, _ = evaluate_state(model, seed, cfg.optim.batch)
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
