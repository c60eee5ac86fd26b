"""The refine task's optimisation: the masked L1 loss, Adam over the camera and the scene groups, the learning-rate
decay and the warm-up / joint / alternating schedule of which groups a step updates."""
from __future__ import annotations

import torch

from nsplat.scene import ATTRIBUTES
from nsplat.tasks.refine.config import CAMERA_GROUPS, GROUPS, Config
from nsplat.tasks.refine.model import Refiner


def optimizers(model: Refiner, cfg: Config) -> dict[str, torch.optim.Optimizer]:
    """Adam over the camera groups (``camera``) and the scene + shading groups (``scene``)."""
    lr = cfg.optim.learn
    out: dict[str, torch.optim.Optimizer] = {}
    cam_groups = []
    if model.pose_parameters():
        cam_groups.append({"params": model.pose_parameters(), "lr": lr["pose"], "name": "pose"})
    if model.focal_parameters():
        cam_groups.append({"params": model.focal_parameters(), "lr": lr["focal"], "name": "focal"})
    if model.exposure_parameters():
        cam_groups.append({"params": model.exposure_parameters(), "lr": lr["exposure"], "name": "exposure"})
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


def set_lr(opts: dict[str, torch.optim.Optimizer], cfg: Config, step: int) -> None:
    """Every group's rate at ``step``: its initial rate times ``optim.decay`` per ``decay_every`` steps after the
    warm-up."""
    o = cfg.optim
    f = o.decay ** (max(0, step - o.warmup) // o.decay_every) if o.decay_every > 0 else 1.0
    for opt in opts.values():
        for g in opt.param_groups:
            g["lr"] = g["initial_lr"] * f


def active_groups(cfg: Config, step: int) -> set[str]:
    """Parameter-group names updated at ``step`` (warm-up, then the joint or alternating schedule)."""
    o = cfg.optim
    if step < o.warmup:
        return set(o.warmup_groups)
    if o.schedule == "joint":
        return set(GROUPS)
    k = step - o.warmup
    camera_phase = (k // o.alternate_every) % 2 == 0
    return set(CAMERA_GROUPS) if camera_phase else set(GROUPS) - set(CAMERA_GROUPS)


def step_active(opts: dict[str, torch.optim.Optimizer], active: set[str]) -> None:
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


def masked_l1(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The mean absolute error of ``img [B,H,W,C]`` against ``ref [B,H,W,C]`` over the pixels of ``mask [B,H,W]``
    (a 0-dim tensor)."""
    m = mask[..., None].to(img.dtype)
    return ((img - ref).abs() * m).sum() / (m.sum() * img.shape[-1]).clamp_min(1.0)


def depth_l1(depth: torch.Tensor, alpha: torch.Tensor, sensor: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The mean relative depth error ``|d̂/α − d| / d`` of rendered ``depth``/``alpha`` ``[B,H,W,1]`` against
    ``sensor`` depth ``[B,H,W]`` over the pixels of ``mask [B,H,W]`` that have a reading (a 0-dim tensor)."""
    m = (mask & (sensor > 0)).to(depth.dtype)
    d = sensor.clamp_min(1e-6)
    err = (depth[..., 0] / alpha[..., 0].clamp_min(1e-3) - d).abs() / d
    return (err * m).sum() / m.sum().clamp_min(1.0)
