"""Scoring an RGB-D sequence's refinement as the field does: held-out frames, trajectory error, and what the user
gets (the refined trajectory as a TUM file, a before/after sheet and video, the before/after table).

* **Held-out frames** (``data.rgbd.holdout_every``) never enter the refinement. After it, their cameras (and
  exposures, when learned) are fitted to the frozen scene (:func:`fit_heldout`), as pose-refining methods do
  before scoring a novel view (with ``depth_loss``, their sensor depth joins the fit's loss: an RGB-D frame's
  depth is an input, its colour what is scored); "before" gets the same fit to the initial scene
  (``heldout.fit_before``, the default: both sides on equal terms), its figures at the trajectory's poses kept
  as ``heldout_unfitted``.
* **Image metrics** on each frame's valid pixels (:func:`frame_metrics`): PSNR, SSIM (the masked mean of
  scikit-image's map, :func:`nsplat.tasks.refine.metrics.image_metrics`) and LPIPS (AlexNet; pixels outside the
  mask take the reference's values, so they add no difference) where it can run offline.
* **Trajectory error** (:mod:`nsplat.tasks.refine.trajectory`): the training and held-out cameras in time order
  against the ground truth, ATE RMSE after an SE(3) (or, ``data.rgbd.trajectory_alignment: sim3``, Sim(3))
  alignment and RPE over consecutive frames.
"""
from __future__ import annotations

import contextlib
import logging
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch
from kornia.geometry.liegroup import Se3
from tqdm import tqdm

from nsplat.data.tum_format import write_trajectory
from nsplat.data.views import PosedViews
from nsplat.evaluation.comparison_sheet import write_sheet
from nsplat.evaluation.image_metrics import lpips, lpips_status
from nsplat.render.video import to_uint8, write_video
from nsplat.tasks.refine.config import Config
from nsplat.tasks.refine.data import Sequence
from nsplat.tasks.refine.metrics import image_metrics
from nsplat.tasks.refine.model import Refiner
from nsplat.tasks.refine.optimisers import depth_l1, masked_l1
from nsplat.tasks.refine.poses import motion_prior
from nsplat.tasks.refine.trajectory import ate, rpe

log = logging.getLogger("nsplat.tasks.refine")


@contextlib.contextmanager
def frozen(module: torch.nn.Module) -> Iterator[None]:
    """Within the block no parameter of ``module`` takes a gradient (restored afterwards)."""
    params = [p for p in module.parameters() if p.requires_grad]
    for p in params:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in params:
            p.requires_grad_(True)


@torch.no_grad()
def render_all(model: Refiner, seed: int, batch: int) -> torch.Tensor:
    """Every frame of ``model`` rendered: ``[B,H,W,C]``."""
    fr = model.frames
    out = []
    for s in range(0, len(fr), batch):
        idx = torch.arange(s, min(s + batch, len(fr)), device=fr.images.device)
        out.append(model(idx, seed)[0])
    return torch.cat(out)


def frame_metrics(img: torch.Tensor, views: PosedViews) -> dict[str, Any]:
    """Mean PSNR / SSIM / LPIPS of renders ``img [B,H,W,C]`` against ``views`` on their masks, and the per-frame
    PSNR (``psnr_frames``); ``lpips`` is ``None`` (with ``lpips_note``) when LPIPS cannot run offline."""
    ps, ss = zip(*(image_metrics(img[b], views.images[b], views.masks[b]) for b in range(len(views))))
    out: dict[str, Any] = {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "psnr_frames": list(ps)}
    ok, note = lpips_status("alex")
    if ok:
        m = views.masks[..., None].to(img.dtype)
        pred = img.clamp(0, 1) * m + views.images * (1 - m)
        out["lpips"] = float(lpips(pred, views.images, net="alex").mean())
    else:
        out["lpips"], out["lpips_note"] = None, note
    return out


def heldout_refiner(model: Refiner, views: PosedViews, seq: Sequence | None = None) -> Refiner:
    """A refiner of the held-out ``views`` over ``model``'s scene and shading (shared, not copied), with its own
    camera corrections and exposures and no anchor.

    With ``seq`` each held-out frame starts from the refined trajectory: its correction (and exposure) is the
    mean (:func:`mean_rigid`) of its nearest training frames' before and after it in time (corrections are
    nearly equal for neighbouring frames, :func:`nsplat.tasks.refine.poses.odometry_prior`), as a twist about
    its optical centre; without, from the identity (the trajectory's own pose).
    """
    held = Refiner(model.cfg, model.scene, views, anchor=False).to(views.images.device)
    held.sh = model.sh
    if seq is None:
        return held
    train = torch.tensor(seq.train)
    rows = []
    for h in seq.heldout:
        before, after = train[train < h], train[train > h]
        rows.append([seq.train.index(int(i)) for i in before[-1:].tolist() + after[:1].tolist()])
    with torch.no_grad():
        if held.cameras is not None and held.cameras.twist is not None and model.cameras.twist is not None:
            held.cameras.pivots = None  # the correction's twist about the optical centre
            D = model.cameras.delta()
            target = torch.stack([mean_rigid(D[r]) for r in rows])
            held.cameras.twist.copy_(Se3.from_matrix(target.double()).log().float())
        if held.exposure is not None and model.exposure is not None:
            m = model.exposure.mask
            for name in ("log_gain", "bias"):
                src = getattr(model.exposure, name) * m
                getattr(held.exposure, name).copy_(torch.stack([src[r].mean(0) for r in rows]))
    return held


def mean_rigid(T: torch.Tensor) -> torch.Tensor:
    """The mean of rigid transforms ``T [k,4,4]``: the chordal mean rotation (the projection of their sum onto
    SO(3)) and the mean translation, ``[4,4]``."""
    U, _, Vt = torch.linalg.svd(T[:, :3, :3].double().sum(0))
    d = torch.ones(3, dtype=U.dtype)
    d[-1] = torch.sign(torch.det(U @ Vt))
    out = torch.eye(4, dtype=T.dtype)
    out[:3, :3] = (U * d) @ Vt
    out[:3, 3] = T[:, :3, 3].mean(0)
    return out


def fit_heldout(model: Refiner, views: PosedViews, cfg: Config, seed: int, seq: Sequence,
                progress: bool = True) -> Refiner:
    """Fit the held-out frames' cameras (and exposures) to ``model``'s frozen scene and shading
    (``cfg.heldout``), starting from the refined trajectory (:func:`heldout_refiner`): Adam on the masked L1 loss
    (plus the depth term) over all held-out frames each step."""
    held = heldout_refiner(model, views, seq)
    h = cfg.heldout
    groups = [{"params": held.pose_parameters(), "lr": h.lr_pose},
              {"params": held.exposure_parameters(), "lr": h.lr_exposure}]
    groups = [g for g in groups if g["params"]]
    if h.steps == 0 or not groups:
        return held
    opt = torch.optim.Adam(groups)
    for g in opt.param_groups:
        g["initial_lr"] = g["lr"]
    fr = held.frames
    with frozen(model.scene), (frozen(model.sh) if model.sh is not None else contextlib.nullcontext()):
        for k in tqdm(range(h.steps), desc="held-out cameras", unit="step", disable=not progress, leave=False):
            f = 0.5 ** (k // h.decay_every) if h.decay_every else 1.0
            for g in opt.param_groups:
                g["lr"] = g["initial_lr"] * f
            opt.zero_grad(set_to_none=True)
            for s in range(0, len(fr), cfg.optim.batch):
                idx = torch.arange(s, min(s + cfg.optim.batch, len(fr)), device=fr.images.device)
                img, alpha, depth = held(idx, seed=seed + k, with_depth=True)
                mask = fr.masks[idx]
                if cfg.coverage_mask > 0:
                    mask = mask & (alpha.detach()[..., 0] >= cfg.coverage_mask)
                loss = masked_l1(img, fr.images[idx], mask)
                if cfg.depth_loss > 0 and fr.depths is not None:
                    loss = loss + cfg.depth_loss * depth_l1(depth, alpha, fr.depths[idx], mask)
                loss.backward()
            if cfg.poses.motion_weight > 0 and held.cameras is not None:
                (cfg.poses.motion_weight * motion_prior(timeline(model, held, seq), seq.timestamps,
                                                        cfg.poses.motion_sigma)).backward()
            opt.step()
    return held


def timeline(train: Refiner, held: Refiner, seq: Sequence) -> torch.Tensor:
    """World → camera ``[F,4,4]`` of every frame in time order: the training cameras (detached) and the held-out
    ones (differentiable)."""
    dev = train.frames.images.device
    with torch.no_grad():
        Vt, _ = train.camera(torch.arange(len(train.frames), device=dev))
    Vh, _ = held.camera(torch.arange(len(held.frames), device=dev))
    out = Vt.new_zeros(len(seq.train) + len(seq.heldout), 4, 4)
    out = out.index_put((torch.tensor(seq.train, device=dev),), Vt)
    return out.index_put((torch.tensor(seq.heldout, device=dev),), Vh)


@torch.no_grad()
def trajectory(train: Refiner, held: Refiner | None, seq: Sequence) -> torch.Tensor:
    """The camera → world poses ``[F,4,4]`` (float64) of every frame in time order: the training frames' cameras
    of ``train`` and the held-out frames' of ``held`` (their initial poses when ``None``)."""
    out = seq.c2w.clone()
    dev = train.frames.images.device
    V, _ = train.camera(torch.arange(len(train.frames), device=dev))
    out[seq.train] = torch.linalg.inv(V.double().cpu())
    if held is not None and seq.heldout:
        Vh, _ = held.camera(torch.arange(len(held.frames), device=dev))
        out[seq.heldout] = torch.linalg.inv(Vh.double().cpu())
    return out


def trajectory_metrics(c2w: torch.Tensor, seq: Sequence, alignment: str = "se3") -> dict[str, float]:
    """ATE (RMSE, mean, max; metres) after the ``alignment`` (``se3`` rigid, ``sim3`` with a scale:
    ``data.rgbd.trajectory_alignment``) and RPE (consecutive frames: translation RMSE in metres, rotation RMSE in
    degrees; with ``sim3`` the translations scaled by the alignment's scale first) of ``c2w [F,4,4]`` against the
    ground truth (empty without one); ``ate_scale`` is the alignment's scale (1 for ``se3``)."""
    if seq.c2w_gt is None:
        return {}
    a = ate(c2w, seq.c2w_gt, with_scale=alignment == "sim3")
    scaled = c2w.double().clone()
    scaled[:, :3, 3] *= a["scale"]
    r = rpe(scaled, seq.c2w_gt)
    return {"ate_rmse": a["rmse"], "ate_mean": a["mean"], "ate_max": a["max"], "ate_scale": a["scale"],
            "rpe_trans_rmse": r["trans_rmse"], "rpe_rot_rmse_deg": r["rot_rmse_deg"]}


def write_tum(path: Path, c2w: torch.Tensor, seq: Sequence, what: str) -> Path:
    """``c2w [F,4,4]`` as a TUM trajectory file at the sequence's timestamps."""
    return write_trajectory(path, seq.timestamps.numpy(), c2w, comment=what)


def write_before_after(folder: Path, views: PosedViews, before: torch.Tensor, after: torch.Tensor,
                       name: str, fps: float = 8.0) -> list[Path]:
    """A sheet (reference | before | after, with |error|) and a video of reference | before | after | |after error|
    for ``views`` and renders ``before``/``after`` ``[B,H,W,3]``; invalid pixels shown darkened."""
    folder.mkdir(parents=True, exist_ok=True)
    m = views.masks[..., None].to(before.dtype)
    shade = 0.35 + 0.65 * m
    ref = views.images * shade
    b, a = before.clamp(0, 1) * shade, after.clamp(0, 1) * shade
    err = ((after.clamp(0, 1) - views.images).abs().mean(-1, keepdim=True) * m * 4).clamp(0, 1).expand_as(a)
    frames = to_uint8(torch.cat([ref, b, a, err], 2).cpu())
    video = write_video(frames, folder / f"{name}.mp4", fps)
    psnr = torch.tensor([image_metrics(after[i], views.images[i], views.masks[i])[0] for i in range(len(views))])
    psnr0 = torch.tensor([image_metrics(before[i], views.images[i], views.masks[i])[0] for i in range(len(views))])
    sheet_after = write_sheet(folder / f"{name}_after.png", views.names, views.images * m, after.clamp(0, 1) * m,
                              psnr, 6)
    sheet_before = write_sheet(folder / f"{name}_before.png", views.names, views.images * m, before.clamp(0, 1) * m,
                               psnr0, 6)
    return [video, sheet_before, sheet_after]


def table(before: dict[str, Any], after: dict[str, Any]) -> str:
    """The before/after table (markdown) of the figures present in both."""
    rows = [("train PSNR (dB)", "train", "psnr"), ("train SSIM", "train", "ssim"), ("train LPIPS", "train", "lpips"),
            ("held-out PSNR (dB)", "heldout", "psnr"), ("held-out SSIM", "heldout", "ssim"),
            ("held-out LPIPS", "heldout", "lpips"), ("ATE RMSE (m)", None, "ate_rmse"),
            ("RPE trans. RMSE (m)", None, "rpe_trans_rmse"), ("RPE rot. RMSE (deg)", None, "rpe_rot_rmse_deg"),
            ("points", None, "points")]
    lines = ["| | before (SLAM start) | after | change |", "|---|---|---|---|"]
    for label, section, key in rows:
        b = (before.get(section) or {}).get(key) if section else before.get(key)
        a = (after.get(section) or {}).get(key) if section else after.get(key)
        if b is None or a is None:
            continue
        change = f"{100.0 * (a - b) / abs(b):+.1f} %" if b else ""
        fmt = "{:.0f}" if key == "points" else "{:.4f}"
        lines.append(f"| {label} | {fmt.format(b)} | {fmt.format(a)} | {change} |")
    if before.get("heldout_unfitted"):
        u = before["heldout_unfitted"]
        lines.append(f"\nheld-out frames: both sides scored after the same per-frame camera + exposure fit "
                     f"(before at the trajectory's poses, unfitted: {u['psnr']:.2f} dB, SSIM {u['ssim']:.4f})")
    return "\n".join(lines)
