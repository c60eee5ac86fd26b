"""Task ``refine``: camera-pose and scene refinement against posed RGB frames (paper §4, room scale).

Given reference frames, initial (perturbed) cameras and an initial surfel cloud, minimise the masked
L1 image loss over per-camera SE(3) corrections (:mod:`nsplat.tasks.refine.poses`, optional focal), the scene's
learnable attributes (:class:`nsplat.scene.SurfelScene`: positions, normals, scales, opacity, albedo;
each switchable by ``scene.learn``) and the shading (2nd-order SH, :mod:`nsplat.sh`; or plain albedo;
or Lambert with the paper's fixed lights, :mod:`nsplat.shading`). Poses and scene are optimised
jointly or alternately (``optim.schedule``); the outlier filter (:mod:`nsplat.tasks.refine.filtering`) removes
points whose accumulated photometric error is improbable.

Data sources: ``room`` (the synthetic benchmark of :mod:`nsplat.data.room`, with ground-truth poses)
and ``nerf`` (NeRF-synthetic frames with ground-truth poses perturbed here, plus an initial cloud read
from a PLY written by :meth:`SurfelScene.save_ply`).

Every render goes through the gateway :func:`nsplat.render.render` (``render.renderer``: the sampled op,
the dense oracle or the truncated baseline).

Configuration: :mod:`nsplat.tasks.refine.config`. Steps run on the engine (:mod:`nsplat.engine`).

Outputs in the run folder: ``tb/`` (TensorBoard), ``checkpoints/`` (atomic, exact resume),
``metrics_initial.json`` / ``metrics_final.json`` (pose errors, masked PSNR/SSIM, point count),
``scene.ply``, ``cameras.pt``, and ``renders/`` from the ``render`` command.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import resource
from typing import Any

import imageio.v3 as iio
import numpy as np
import torch
from skimage.metrics import structural_similarity

from nsplat import render as gateway
from nsplat.cameras import perturb_viewmats
from nsplat.checkpoint import load_checkpoint
from nsplat.config import ConfigError
from nsplat.data.nerf_synthetic import load_split
from nsplat.data.paths import resolve, resolve_data
from nsplat.data.room import load_room
from nsplat.data.views import PosedViews
from nsplat.engine import Engine, Trainables, checkpoint_rows, generator, latest_payload, op_seed, write_json
from nsplat.render import RenderConfig, background_of
from nsplat.report import results
from nsplat.runctx import RunContext
from nsplat.scene import ATTRIBUTES, SurfelScene
from nsplat.sh import SHLighting
from nsplat.shading import lambert
from nsplat.tasks.refine.config import CAMERA_GROUPS, GROUPS, Config
from nsplat.tasks.refine.filtering import improbable, point_errors
from nsplat.tasks.refine.poses import CameraCorrection, pose_errors, pose_report
from nsplat.view_model import TrainingCameras, ViewModel

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------- rendering
def render_cameras(rcfg: RenderConfig, scene: SurfelScene, features: torch.Tensor, viewmats: torch.Tensor,
                   Ks: torch.Tensor, width: int, height: int, seed: int,
                   background: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Render cameras ``[B]`` through the gateway (:func:`nsplat.render.render`).

    Args:
        scene: the surfels (geometry). features: ``[N,C]`` (same for every camera) or ``[B,N,C]`` (per
            camera, rendered one by one). viewmats ``[B,4,4]``, Ks ``[B,3,3]``: cameras.
        seed: the op's sampling seed. background: ``[C]`` overriding ``render.background``.

    Returns:
        ``(image [B,H,W,C], alpha [B,H,W,1])``.
    """
    if features.dim() == 3:
        outs = [render_cameras(rcfg, scene, features[b], viewmats[b:b + 1], Ks[b:b + 1], width, height, seed,
                               background) for b in range(features.shape[0])]
        return torch.cat([o[0] for o in outs]), torch.cat([o[1] for o in outs])
    out = gateway.render(scene.means, scene.normals, scene.scales, scene.opacities, features, viewmats, Ks, width,
                         height, rcfg, seed=seed, background=background)
    return out.image, out.alpha


# ---------------------------------------------------------------------------------------- data
def load_data(cfg: Config, device: torch.device) -> tuple[PosedViews, SurfelScene]:
    """Frames (initial ``viewmats``, ``viewmats_gt``, bool ``masks [B,H,W]``) and the initial scene of
    ``cfg.data`` (on ``device``)."""
    d = cfg.data
    if d.source == "room":
        room = load_room(d.room, resolve(d.cache_dir))
        frames = room.views()
        n = room.means.shape[0]
        scene = SurfelScene.from_points(cfg.scene, room.means, room.normals,
                                        scales=room.scales[:, None].expand(n, 2).contiguous(),
                                        opacities=torch.full((n,), d.init_opacity), features=room.colours)
    else:
        nf = d.nerf
        views = load_split(resolve_data(nf.root, "nerf_synthetic/lego_400"), nf.split, resolution=nf.resolution,
                           background=cfg.render.background if cfg.scene.channels == 3 else (1.0, 1.0, 1.0),
                           limit=nf.limit or None)
        if not nf.cloud:
            raise ConfigError("data.nerf.cloud: a PLY initial cloud is required for source 'nerf'")
        scene = SurfelScene.load_ply(resolve(nf.cloud), cfg.scene)
        extent = float((scene.means.max(0).values - scene.means.min(0).values).max())
        g = torch.Generator().manual_seed(nf.perturb_seed)
        init = perturb_viewmats(views.viewmats, nf.rot_deg, nf.trans_frac * extent, generator=g)
        masks = torch.ones(views.images.shape[:3], dtype=torch.bool)
        frames = dataclasses.replace(views, masks=masks, viewmats=init.float(), viewmats_gt=views.viewmats)
    return frames.to(device), scene.to(device)


# ---------------------------------------------------------------------------------------- model
def scene_pivots(means: torch.Tensor, viewmats: torch.Tensor, near: float = 1e-3) -> torch.Tensor:
    """``[B, 3]`` pivots ``(0, 0, d_b)`` in camera coordinates: ``d_b`` the median depth of the points
    of ``means [N,3]`` in front of camera ``b`` and inside its 90° cone (1 when none are)."""
    cam = torch.einsum("bij,nj->bni", viewmats[:, :3, :3].to(means), means) + viewmats[:, None, :3, 3].to(means)
    z = cam[..., 2]
    ok = (z > near) & (cam[..., :2].norm(dim=-1) < z)
    out = torch.zeros(viewmats.shape[0], 3, dtype=means.dtype, device=means.device)
    for b in range(viewmats.shape[0]):
        out[b, 2] = z[b][ok[b]].median() if bool(ok[b].any()) else 1.0
    return out


class Refiner(torch.nn.Module):
    """Scene + shading + camera corrections; produces rendered views of camera indices."""

    def __init__(self, cfg: Config, scene: SurfelScene, frames: PosedViews) -> None:
        super().__init__()
        self.cfg = cfg
        self.scene = scene
        self.frames = frames
        self.sh = (SHLighting(cfg.scene.channels, cfg.shading.ambient, learnable=cfg.shading.learn_sh)
                   if cfg.shading.model == "sh" else None)
        p = cfg.poses
        pivots = scene_pivots(scene.means.detach(), frames.viewmats) if p.pivot == "scene" else None
        self.cameras = (CameraCorrection(len(frames), learn_pose=p.learn, learn_focal=p.learn_focal,
                                         shared_focal=p.shared_focal, frozen=p.frozen, pivots=pivots)
                        if (p.learn or p.learn_focal) else None)

    def camera(self, index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Corrected ``(viewmats [b,4,4], Ks [b,3,3])`` of cameras ``index [b]``."""
        V, K = self.frames.viewmats[index], self.frames.Ks[index]
        if self.cameras is None:
            return V, K
        return self.cameras(V, K, index)

    def colours(self, viewmats: torch.Tensor) -> torch.Tensor:
        """Shaded point colours: ``[N,C]`` (albedo, SH) or ``[b,N,C]`` (Lambert, per camera)."""
        s = self.scene
        if self.cfg.shading.model == "sh":
            return self.sh(s.features, s.normals)
        if self.cfg.shading.model == "lambert":
            return lambert(s.features, s.normals, viewmats)
        return s.features

    def forward(self, index: torch.Tensor, seed: int, features: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Render cameras ``index [b]``: ``(image [b,H,W,C], alpha [b,H,W,1])``. ``features`` overrides
        the shaded colours (used by the outlier filter's probe)."""
        V, K = self.camera(index)
        s = self.scene
        f = self.colours(V) if features is None else features
        bg = None
        if f.shape[-1] != s.cfg.channels:  # the outlier filter's probe: other channels on a zero background
            bg = f.new_zeros(f.shape[-1])
        return render_cameras(self.cfg.render, s, f, V, K, self.frames.width, self.frames.height, seed, bg)

    def pose_parameters(self) -> list[torch.nn.Parameter]:
        return [] if self.cameras is None else [p for p in (self.cameras.twist,) if p is not None]

    def focal_parameters(self) -> list[torch.nn.Parameter]:
        return [] if self.cameras is None or self.cameras.log_focal is None else [self.cameras.log_focal]


def _optimizers(model: Refiner, cfg: Config) -> dict[str, torch.optim.Optimizer]:
    """Adam over the camera groups (``camera``) and the scene + shading groups (``scene``)."""
    lr = cfg.optim.learn
    out: dict[str, torch.optim.Optimizer] = {}
    cam_groups = []
    if model.pose_parameters():
        cam_groups.append({"params": model.pose_parameters(), "lr": lr["pose"], "name": "pose"})
    if model.focal_parameters():
        cam_groups.append({"params": model.focal_parameters(), "lr": lr["focal"], "name": "focal"})
    if cam_groups:
        out["camera"] = torch.optim.Adam(cam_groups)
    scene_groups = model.scene.param_groups({k: v for k, v in lr.items() if k in ATTRIBUTES})
    if model.sh is not None and cfg.shading.learn_sh:
        scene_groups.append({"params": [model.sh.coeffs], "lr": lr["sh"], "name": "sh"})
    if scene_groups:
        out["scene"] = torch.optim.Adam(scene_groups)
    for opt in out.values():
        for g in opt.param_groups:
            g["initial_lr"] = g["lr"]
    return out


def _set_lr(opts: dict[str, torch.optim.Optimizer], cfg: Config, step: int) -> None:
    o = cfg.optim
    f = o.decay ** (max(0, step - o.warmup) // o.decay_every) if o.decay_every > 0 else 1.0
    for opt in opts.values():
        for g in opt.param_groups:
            g["lr"] = g["initial_lr"] * f


def _active(cfg: Config, step: int) -> set[str]:
    """Parameter-group names updated at ``step`` (warm-up, then the joint or alternating schedule)."""
    o = cfg.optim
    if step < o.warmup:
        return set(o.warmup_groups)
    if o.schedule == "joint":
        return set(GROUPS)
    k = step - o.warmup
    camera_phase = (k // o.alternate_every) % 2 == 0
    return set(CAMERA_GROUPS) if camera_phase else set(GROUPS) - set(CAMERA_GROUPS)


def _step_active(opts: dict[str, torch.optim.Optimizer], active: set[str]) -> None:
    """Adam steps of the active groups only (inactive groups' gradients are dropped, so Adam leaves
    their values and moments untouched)."""
    for opt in opts.values():
        any_active = False
        for g in opt.param_groups:
            if g["name"] in active:
                any_active = True
            else:
                for p in g["params"]:
                    p.grad = None
        if any_active:
            opt.step()


def _masked_l1(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    m = mask[..., None].to(img.dtype)
    return ((img - ref).abs() * m).sum() / (m.sum() * img.shape[-1]).clamp_min(1.0)


# ---------------------------------------------------------------------------------------- metrics
def image_metrics(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor) -> tuple[float, float]:
    """Masked PSNR and SSIM of one image ``[H,W,C]`` in [0,1] against ``ref`` (``mask [H,W]``).

    SSIM is scikit-image's (Gaussian window σ = 1.5, data range 1) map averaged over valid pixels.
    """
    a = img.detach().clamp(0, 1).cpu().double().numpy()
    b = ref.detach().cpu().double().numpy()
    m = mask.detach().cpu().numpy().astype(bool)
    mse = float(((a - b) ** 2)[m].mean())
    psnr = 10.0 * math.log10(1.0 / max(mse, 1e-12))
    _, smap = structural_similarity(a, b, data_range=1.0, channel_axis=-1, gaussian_weights=True,
                                    sigma=1.5, use_sample_covariance=False, full=True)
    return psnr, float(smap.mean(-1)[m].mean())


@torch.no_grad()
def evaluate_state(model: Refiner, seed: int, batch: int) -> tuple[dict[str, Any], torch.Tensor]:
    """Pose errors and masked PSNR/SSIM over all frames; returns ``(metrics, renders [B,H,W,C])``."""
    fr = model.frames
    renders = []
    for s in range(0, len(fr), batch):
        idx = torch.arange(s, min(s + batch, len(fr)), device=fr.images.device)
        renders.append(model(idx, seed)[0])
    img = torch.cat(renders)
    ps, ss = zip(*(image_metrics(img[b], fr.images[b], fr.masks[b]) for b in range(len(fr))))
    out: dict[str, Any] = {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)),
                           "points": model.scene.num_points}
    if fr.viewmats_gt is not None:
        V, K = model.camera(torch.arange(len(fr), device=fr.images.device))
        out.update(pose_report(V, fr.viewmats_gt))
        if model.cameras is not None and model.cameras.log_focal is not None:
            out["focal_scale"] = torch.exp(model.cameras.log_focal).tolist()
    return out, img


# ---------------------------------------------------------------------------------------- filter
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


# ---------------------------------------------------------------------------------------- run
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
    return Trainables(modules={"model": model}, optimizers=_optimizers(model, cfg))


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
    _set_lr(opts, cfg, k)
    idx = _batch(cfg, len(fr), k, seed).to(device)
    active = _active(cfg, k)
    for opt in opts.values():
        opt.zero_grad(set_to_none=True)
    img, alpha = model(idx, seed=op_seed(seed, "train", k))
    mask = fr.masks[idx] if cfg.mask_loss else torch.ones_like(fr.masks[idx])
    if cfg.coverage_mask > 0:
        mask = mask & (alpha.detach()[..., 0] >= cfg.coverage_mask)
    loss = _masked_l1(img, fr.images[idx], mask)
    loss.backward()
    _step_active(opts, active)
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


# ---------------------------------------------------------------------------------------- views
def refiner_view(model: Refiner, seed: int = 0) -> ViewModel:
    """``model``'s surfels with its shading and its refined cameras (as frusta): the live view."""
    fr, s, rc = model.frames, model.scene, model.cfg.render
    with torch.no_grad():
        V, K = model.camera(torch.arange(len(fr), device=fr.images.device))
    cams = TrainingCameras(V.detach(), K.detach(), fr.width, fr.height, fr.images)
    bg = background_of(rc, s.features.shape[1], s.means)
    return ViewModel(s.means, s.normals, s.scales, s.opacities, s.features,
                     s.means.new_zeros(s.features.shape[1]) if bg is None else bg,
                     colours=lambda f, n, v: model.colours(v), render_cfg=rc, cameras=cams, task="refine", seed=seed)


def view(cfg: Config, ctx: RunContext) -> ViewModel:
    """The task contract's ``view``: :func:`refiner_view` of the latest checkpoint (eval mode)."""
    model, _ = restore(cfg, ctx)
    return refiner_view(model.eval(), seed=op_seed(ctx.seed, "eval"))
