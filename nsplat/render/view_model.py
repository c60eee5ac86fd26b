"""What a viewer or an export shows of a scene: :class:`ViewModel` (surfels, shading, shader, training
cameras) and the builders every task shares.

Tasks build their :class:`ViewModel` here (their ``view`` function of the task contract, and the
engine's live-view hook); :mod:`nsplat.viewer` renders and serves it. The dependency runs one way:
the viewer imports the tasks, never the reverse.

Every task reduces to surfels + optional per-camera shading + an optional image-space shader:

* ``neural``: learned features splatted by the op, turned into RGB by the U-Net;
* ``reconstruct`` / ``refine`` / ``demo``: RGB surfels (Lambert- or SH-shaded where the task shades).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import torch

from nsplat.render.renderer import RenderConfig
from nsplat.render.sh import view_colour
from nsplat.render.shading import lambert
from nsplat.scene import SurfelScene


@dataclasses.dataclass
class TrainingCameras:
    """The cameras a model was trained on (shown as frusta).

    Attributes:
        viewmats: ``[V,4,4]`` OpenCV world→camera. Ks: ``[V,3,3]`` intrinsics in pixels.
        width, height: their image size. images: ``[V,H,W,3]`` in [0, 1], or ``None``.
    """

    viewmats: torch.Tensor
    Ks: torch.Tensor
    width: int
    height: int
    images: torch.Tensor | None = None


@dataclasses.dataclass
class ViewModel:
    """A renderable trained scene.

    Attributes:
        means ``[N,3]``, normals ``[N,3]``, scales ``[N,2]`` (std-devs), opacities ``[N]``: surfels.
        features: ``[N,C]`` per-point features (RGB albedo for the surfel tasks, learned for ``neural``).
        background: ``[C]`` feature background.
        colours: optional per-camera shading ``f(features [N,C], normals [N,3], viewmat [1,4,4]) → [N,C]``
            (e.g. Lambert with camera-relative lights); ``None`` splats ``features`` as they are.
        shader: optional image-space shader ``f(feature image [1,C',H,W]) → RGB [1,3,H,W]`` (the U-Net);
            ``C' = C + 1`` when ``alpha_input`` (coverage appended). ``None``: RGB = first 3 channels.
        alpha_input: append the splatted alpha to the shader's input.
        render_cfg: the run's render settings (:class:`nsplat.render.renderer.RenderConfig`); the viewer starts from
            them, with the ``viewer.render`` overrides (:class:`nsplat.viewer.model.RenderSettings`).
        cameras: the training cameras, or ``None``.
        task: task name (for labels). seed: op seed of every viewer render (fixed: same camera, same image).
        sh_degree: ``features`` hold a view-dependent colour of this spherical-harmonics degree
            (``3·(L+1)²`` channels, :func:`nsplat.render.sh.view_colour`), or ``None`` (RGB albedo, or learned
            features when there is a ``shader``).
    """

    means: torch.Tensor
    normals: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    features: torch.Tensor
    background: torch.Tensor
    colours: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor] | None = None
    shader: Callable[[torch.Tensor], torch.Tensor] | None = None
    alpha_input: bool = False
    render_cfg: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    cameras: TrainingCameras | None = None
    task: str = ""
    seed: int = 0
    sh_degree: int | None = None

    @property
    def num_points(self) -> int:
        """Number of surfels N."""
        return int(self.means.shape[0])

    @torch.no_grad()
    def rgb_colours(self) -> torch.Tensor:
        """``[N,3]`` unshaded point colours in [0, 1] (first three feature channels, clamped; a grey
        copy of the first channel when C < 3) — what a point-cloud export writes as ``red green blue``."""
        f = self.features.detach()
        f = f[:, :3] if f.shape[1] >= 3 else f[:, :1].expand(-1, 3)
        return f.clamp(0, 1)


def cameras_of(images: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor) -> TrainingCameras:
    """Training cameras from ``images [V,H,W,C]``, ``viewmats [V,4,4]``, ``Ks [V,3,3]``."""
    V, H, W = images.shape[:3]
    return TrainingCameras(viewmats, Ks, int(W), int(H), images[..., :3] if images.shape[-1] >= 3 else None)


def surfel_view(scene: SurfelScene, cameras: TrainingCameras | None, *, shading: str = "none",
                background: torch.Tensor | None = None, render_cfg: RenderConfig | None = None, task: str = "",
                seed: int = 0) -> ViewModel:
    """View of RGB surfels; ``shading="lambert"`` shades them with the paper's camera-relative lights,
    ``shading="sh"`` evaluates their view-dependent colour (:func:`nsplat.render.sh.view_colour`) per camera."""
    colours = None
    if shading == "lambert":
        colours = lambert
    elif shading == "sh":
        means = scene.means.detach()

        def colours(features: torch.Tensor, normals: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
            return view_colour(features, means, viewmat[0])[None]

    bg = scene.means.new_zeros(3 if shading == "sh" else scene.features.shape[1]) if background is None \
        else background
    return ViewModel(scene.means, scene.normals, scene.scales, scene.opacities, scene.features, bg,
                     colours=colours, render_cfg=render_cfg or RenderConfig(), cameras=cameras, task=task, seed=seed,
                     sh_degree=math.isqrt(scene.features.shape[1] // 3) - 1 if shading == "sh" else None)
