"""The refine task's model: :class:`Refiner` (scene, shading and camera corrections) renders the frames' cameras
through the gateway (:func:`nsplat.render.renderer.render`); :func:`refiner_view` is its live view."""
from __future__ import annotations

import torch

from nsplat.data.views import PosedViews
from nsplat.render import renderer as gateway
from nsplat.render.renderer import RenderConfig, background_of
from nsplat.render.sh import SHLighting
from nsplat.render.shading import lambert
from nsplat.render.view_model import TrainingCameras, ViewModel
from nsplat.scene import SurfelScene
from nsplat.tasks.refine.config import Config
from nsplat.tasks.refine.exposure import Exposure
from nsplat.tasks.refine.poses import CameraCorrection


def render_cameras(rcfg: RenderConfig, scene: SurfelScene, features: torch.Tensor, viewmats: torch.Tensor,
                   Ks: torch.Tensor, width: int, height: int, seed: int,
                   background: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Render cameras ``[B]`` through the gateway (:func:`nsplat.render.renderer.render`).

    Args:
        scene: the surfels (geometry). features: ``[N,C]`` (same for every camera) or ``[B,N,C]`` (per
            camera, rendered one by one). viewmats ``[B,4,4]``, Ks ``[B,3,3]``: cameras.
        seed: the op's sampling seed. background: ``[C]`` overriding ``render.background``.

    Returns:
        ``(image [B,H,W,C], alpha [B,H,W,1], depth [B,H,W,1])`` (depth: the alpha-weighted camera z).
    """
    if features.dim() == 3:
        outs = [render_cameras(rcfg, scene, features[b], viewmats[b:b + 1], Ks[b:b + 1], width, height, seed,
                               background) for b in range(features.shape[0])]
        return tuple(torch.cat([o[i] for o in outs]) for i in range(3))  # type: ignore[return-value]
    out = gateway.render(scene.means, scene.normals, scene.scales, scene.opacities, features, viewmats, Ks, width,
                         height, rcfg, seed=seed, background=background)
    return out.image, out.alpha, out.depth


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
    """Scene + shading + camera corrections (+ per-frame exposure); produces rendered views of camera indices.

    ``anchor``: keep ``poses.frozen`` fixed and frame 0's exposure at the identity (the gauge of a refinement);
    ``False`` for cameras fitted to a frozen scene (held-out frames), where the scene fixes the gauge.
    """

    def __init__(self, cfg: Config, scene: SurfelScene, frames: PosedViews, anchor: bool = True) -> None:
        super().__init__()
        self.cfg = cfg
        self.scene = scene
        self.frames = frames
        self.sh = (SHLighting(cfg.scene.channels, cfg.shading.ambient, learnable=cfg.shading.learn_sh)
                   if cfg.shading.model == "sh" else None)
        p = cfg.poses
        pivots = scene_pivots(scene.means.detach(), frames.viewmats) if p.pivot == "scene" else None
        self.cameras = (CameraCorrection(len(frames), learn_pose=p.learn, learn_focal=p.learn_focal,
                                         shared_focal=p.shared_focal, frozen=p.frozen if anchor else [],
                                         pivots=pivots)
                        if (p.learn or p.learn_focal) else None)
        self.exposure = (Exposure(len(frames), cfg.scene.channels, frozen=[0] if anchor else [])
                         if cfg.exposure.learn else None)

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

    def forward(self, index: torch.Tensor, seed: int, features: torch.Tensor | None = None,
                with_depth: bool = False) -> tuple[torch.Tensor, ...]:
        """Render cameras ``index [b]``: ``(image [b,H,W,C], alpha [b,H,W,1])``, and with ``with_depth`` the
        alpha-weighted camera z ``[b,H,W,1]`` too. ``features`` overrides the shaded colours (used by the outlier
        filter's probe; no exposure is applied then)."""
        V, K = self.camera(index)
        s = self.scene
        f = self.colours(V) if features is None else features
        bg = None
        if f.shape[-1] != s.cfg.channels:  # the outlier filter's probe: other channels on a zero background
            bg = f.new_zeros(f.shape[-1])
        img, alpha, depth = render_cameras(self.cfg.render, s, f, V, K, self.frames.width, self.frames.height, seed,
                                           bg)
        if self.exposure is not None and features is None:
            img = self.exposure(img, index)
        return (img, alpha, depth) if with_depth else (img, alpha)

    def pose_parameters(self) -> list[torch.nn.Parameter]:
        return [] if self.cameras is None else [p for p in (self.cameras.twist,) if p is not None]

    def focal_parameters(self) -> list[torch.nn.Parameter]:
        return [] if self.cameras is None or self.cameras.log_focal is None else [self.cameras.log_focal]

    def exposure_parameters(self) -> list[torch.nn.Parameter]:
        return [] if self.exposure is None else [self.exposure.log_gain, self.exposure.bias]


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
